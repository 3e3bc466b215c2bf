//! Heights codec benchmark: size, decode and encode speed of the codec's two coders against
//! the baselines a tile server would otherwise use, all measured in the same run on the
//! same tiles.
//!
//! ```text
//! cargo bench -p terrain-server --bench codec -- [DEM ...]
//! ```
//!
//! Without arguments it reads puget_sound_1k and himalaya_4097 from `$TERRAIN_DATA_DIR`.
//! For each DEM it cuts the same 129^2 tiles as the builder and reports bytes per sample
//! for: codec version 2 (rANS with contexts, the default); version 1 (byte planes and
//! zstd 19, what databases before it hold); each tile as a 16-bit greyscale PNG (best
//! compression, adaptive filters); plain zstd (level 19) of the raw 16-bit samples; and
//! the entropy of the planar residuals given a local-gradient context, with a global
//! table per class and no table cost (the floor a context-modelling coder is held to).
//! A third table gives other floors: order-0 entropies of the planar and of LOCO-I's
//! median predictor.
//! Speeds are single-threaded, in million samples per second. The two coders' decodes are
//! timed in alternating rounds and each reported as its median round, so load on the
//! machine falls on both alike.
use std::path::PathBuf;
use std::time::{Duration, Instant};
use terrain_server::build::{input, tiles};
use terrain_shared::Heights;
use terrain_shared::heights::{self, Coder};

const TILE_SIZE: u32 = 129;
/// Each decode measurement repeats whole passes over all tiles for at least this long.
const MEASURE_FOR: Duration = Duration::from_secs(1);
/// Alternating rounds of the two coders' decodes.
const ROUNDS: usize = 5;

fn main() {
    let mut paths: Vec<PathBuf> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .map(PathBuf::from)
        .collect();
    if paths.is_empty() {
        let Some(dir) = std::env::var_os("TERRAIN_DATA_DIR") else {
            eprintln!(
                "usage: cargo bench -p terrain-server --bench codec -- DEM...  (or set TERRAIN_DATA_DIR)"
            );
            std::process::exit(2);
        };
        let dir = PathBuf::from(dir);
        paths = vec![
            dir.join("puget_sound_1k/ps_height_1k.png"),
            dir.join("himalaya_4097/g10g_himalaya_4097.png"),
        ];
    }
    println!(
        "machine: {} ({} cores); decode on one thread",
        cpu_model(),
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    println!();
    let rows: Vec<Rows> = paths.iter().map(|p| bench(p)).collect();
    println!("Size, bytes per sample:");
    println!();
    println!(
        "| DEM | tiles | version 2 (rANS) | version 1 (zstd planes) | PNG-16 | zstd-19 raw | gradient-context floor | version 2 over the floor | version 2 vs version 1 | vs PNG-16 |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for row in &rows {
        println!("{}", row.size);
    }
    println!();
    println!(
        "Speed, million samples per second on one thread (decodes: median of {ROUNDS} alternating rounds):"
    );
    println!();
    println!(
        "| DEM | decode version 2 | decode version 1 | version 2 / version 1 | zstd raw decode | PNG decode | encode version 2 | encode version 1 (zstd 19) |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for row in &rows {
        println!("{}", row.speed);
    }
    println!();
    println!("Other floors (entropies of the same tiles' residuals, bytes/sample):");
    println!();
    println!(
        "| DEM | planar, order 0 | MED, order 0 | planar given local gradient (12 classes) | needed for 1.3x PNG-16 |"
    );
    println!("|---|---|---|---|---|");
    for row in &rows {
        println!("{}", row.entropy);
    }
}

/// One DEM's rows of the three tables.
struct Rows {
    size: String,
    speed: String,
    entropy: String,
}

/// Measures one DEM.
fn bench(path: &std::path::Path) -> Rows {
    let raster = match input::read_heights(
        path,
        &input::ReadOptions {
            nodata: None,
            float_quantum_m: 0.01,
            out_of_range: input::OutOfRange::Refuse,
        },
    ) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("{}: {e}", path.display());
            std::process::exit(1);
        }
    };
    let grid = tiles::Grid::covering(raster.width, raster.height, TILE_SIZE);
    let cut: Vec<_> = grid
        .tiles()
        .map(|id| {
            tiles::cut(
                &raster.codes,
                raster.width,
                raster.height,
                grid,
                id,
                1.0,
                0.0,
            )
        })
        .collect();
    let samples: usize = cut.iter().map(|t| t.heights.codes.len()).sum();

    let (ours, ours_encode) = timed(samples, || {
        cut.iter()
            .map(|t| t.heights.encode().expect("encodes"))
            .collect::<Vec<_>>()
    });
    let (v1, v1_encode) = timed(samples, || {
        cut.iter()
            .map(|t| {
                t.heights
                    .encode_with(Coder::Zstd(heights::DEFAULT_ZSTD_LEVEL))
                    .expect("encodes")
            })
            .collect::<Vec<_>>()
    });
    for (a, b) in ours.iter().zip(&v1) {
        assert_eq!(
            Heights::decode(a).expect("decodes"),
            Heights::decode(b).expect("decodes")
        );
    }
    let raw: Vec<Vec<u8>> = cut
        .iter()
        .map(|t| {
            t.heights
                .codes
                .iter()
                .flat_map(|&c| (c as u16).to_le_bytes())
                .collect()
        })
        .collect();
    let zstd_raw: Vec<Vec<u8>> = raw
        .iter()
        .map(|r| zstd::bulk::compress(r, 19).expect("zstd"))
        .collect();
    let png: Vec<Vec<u8>> = cut.iter().map(|t| png16(&t.heights)).collect();
    let entropy = entropy(&cut);

    let size =
        |blobs: &[Vec<u8>]| blobs.iter().map(Vec::len).sum::<usize>() as f64 / samples as f64;
    let (ours_b, v1_b, png_b, zstd_b) = (size(&ours), size(&v1), size(&png), size(&zstd_raw));

    let decode_all = |blobs: &[Vec<u8>]| {
        for blob in blobs {
            std::hint::black_box(Heights::decode(blob).expect("decodes"));
        }
    };
    let (mut ours_rounds, mut v1_rounds) = (Vec::new(), Vec::new());
    for _ in 0..ROUNDS {
        ours_rounds.push(rate(samples, || decode_all(&ours)));
        v1_rounds.push(rate(samples, || decode_all(&v1)));
    }
    let (ours_rate, v1_rate) = (median(ours_rounds), median(v1_rounds));
    let mut buffer = vec![0u8; (TILE_SIZE * TILE_SIZE * 2) as usize];
    let mut decompressor = zstd::bulk::Decompressor::new().expect("zstd context");
    let zstd_rate = rate(samples, || {
        for blob in &zstd_raw {
            std::hint::black_box(
                decompressor
                    .decompress_to_buffer(blob, &mut buffer)
                    .expect("zstd"),
            );
        }
    });
    let png_rate = rate(samples, || {
        for blob in &png {
            std::hint::black_box(image::load_from_memory(blob).expect("png"));
        }
    });
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    Rows {
        size: format!(
            "| {name} | {} | {ours_b:.3} | {v1_b:.3} | {png_b:.3} | {zstd_b:.3} | {:.3} | {:+.1}% | {:.1}% smaller | {:.2}x smaller |",
            cut.len(),
            entropy.planar_given_gradient,
            (ours_b / entropy.planar_given_gradient - 1.0) * 100.0,
            (1.0 - ours_b / v1_b) * 100.0,
            png_b / ours_b,
        ),
        speed: format!(
            "| {name} | {ours_rate:.0} | {v1_rate:.0} | {:.2}x | {zstd_rate:.0} | {png_rate:.0} | {ours_encode:.1} | {v1_encode:.1} |",
            ours_rate / v1_rate,
        ),
        entropy: format!(
            "| {name} | {:.3} | {:.3} | {:.3} | {:.3} |",
            entropy.planar,
            entropy.med,
            entropy.planar_given_gradient,
            png_b / 1.3
        ),
    }
}

/// Runs `make` once, returning what it made and its rate in million samples per second.
fn timed<T>(samples: usize, make: impl FnOnce() -> T) -> (T, f64) {
    let started = Instant::now();
    let made = make();
    (made, samples as f64 / started.elapsed().as_secs_f64() / 1e6)
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// Million samples per second of repeated passes of `pass` over `samples` samples.
fn rate(samples: usize, mut pass: impl FnMut()) -> f64 {
    pass(); // warm caches and lazily created contexts
    let started = Instant::now();
    let mut passes = 0usize;
    while started.elapsed() < MEASURE_FOR {
        pass();
        passes += 1;
    }
    (samples * passes) as f64 / started.elapsed().as_secs_f64() / 1e6
}

fn png16(heights: &Heights) -> Vec<u8> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    let pixels: Vec<u16> = heights.codes.iter().map(|&c| c as u16).collect();
    let image = image::ImageBuffer::<image::Luma<u16>, _>::from_raw(
        u32::from(heights.width),
        u32::from(heights.height),
        pixels,
    )
    .expect("sized");
    let mut out = std::io::Cursor::new(Vec::new());
    image
        .write_with_encoder(PngEncoder::new_with_quality(
            &mut out,
            CompressionType::Best,
            FilterType::Adaptive,
        ))
        .expect("png");
    out.into_inner()
}

/// Entropy bounds, in bytes per sample, of the tiles' prediction residuals.
struct Entropy {
    /// Order-0 entropy of the planar predictor `west + north - north_west` (what the codec uses).
    planar: f64,
    /// Order-0 entropy of LOCO-I's median edge detector, median(west, north, west + north - north_west).
    med: f64,
    /// Entropy of the planar residual given a context of the local gradient,
    /// `|west - north_west| + |north - north_west|` in 12 logarithmic classes: what a coder
    /// with ideal context modelling (and no table cost) could reach.
    planar_given_gradient: f64,
}

fn entropy(tiles: &[tiles::TileSamples]) -> Entropy {
    use std::collections::HashMap;
    const CLASSES: usize = 12;
    let mut planar = HashMap::<i32, u64>::new();
    let mut med = HashMap::<i32, u64>::new();
    let mut by_class: Vec<HashMap<i32, u64>> = vec![HashMap::new(); CLASSES];
    let mut total = 0u64;
    for tile in tiles {
        let n = usize::from(tile.heights.width);
        let at = |x: usize, y: usize| tile.heights.codes[y * n + x];
        for y in 0..n {
            for x in 0..n {
                let west = if x > 0 { at(x - 1, y) } else { 0 };
                let north = if y > 0 { at(x, y - 1) } else { 0 };
                let north_west = if x > 0 && y > 0 { at(x - 1, y - 1) } else { 0 };
                let gradient = west + north - north_west;
                let median = gradient.clamp(west.min(north), west.max(north));
                let residual = at(x, y) - gradient;
                *planar.entry(residual).or_default() += 1;
                *med.entry(at(x, y) - median).or_default() += 1;
                let activity =
                    (west - north_west).unsigned_abs() + (north - north_west).unsigned_abs();
                let class = ((32 - activity.leading_zeros()) as usize).min(CLASSES - 1);
                *by_class[class].entry(residual).or_default() += 1;
                total += 1;
            }
        }
    }
    // Bits of a histogram coded with its own frequencies.
    let bits = |counts: &HashMap<i32, u64>| -> f64 {
        let sum: u64 = counts.values().sum();
        counts
            .values()
            .map(|&c| -(c as f64) * (c as f64 / sum as f64).log2())
            .sum()
    };
    let per_sample = |b: f64| b / total as f64 / 8.0;
    Entropy {
        planar: per_sample(bits(&planar)),
        med: per_sample(bits(&med)),
        planar_given_gradient: per_sample(by_class.iter().map(bits).sum()),
    }
}

fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|text| {
            text.lines()
                .find(|l| l.starts_with("model name"))
                .map(|l| l.split(':').nth(1).unwrap_or("").trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into())
}
