//! Builder memory benchmark: peak memory and speed of `terrain-server build` on
//! himalaya_4097 (4097^2 samples) and on a mosaic of four mirrored copies of it (8193^2,
//! four times the samples; `common/mosaic.rs`), each built by the release binary as a
//! child process.
//!
//! ```text
//! cargo bench -p terrain-server --bench build_memory
//! ```
//!
//! The builder holds a band of tile rows per level, never a level, so four times the
//! samples (twice the width) must not mean four times the memory; and it fills voids region
//! by region, so the same raster with SRTM-like voids (3% of its samples) must not mean the
//! raster held whole: both peaks at most 1.25 times the source's. It prints, per input,
//! the samples, the wall time, samples per second and the peak resident memory; then the
//! ratio of the peaks (target: at most 1.25, with a PASS or FAIL line; the exit status is 0
//! either way) and, per input, the pyramid's bytes over level 0's (heights, textures, both;
//! about 4/3, since each level has a quarter of the samples of the one below).
//!
//! Then every product: himalaya_4097 with `--patches` and the web tiles (the source is
//! georeferenced), each product's seconds and samples a second from the build's own
//! `speed` line against its target (the tiles 8, the patches 2, the web tiles 5 M samples/s);
//! and the peak with `--patches` (no web tiles) of the source and of the mosaic, whose ratio
//! has the same 1.25 target.
//!
//! Peak memory is the kernel's high-water mark of the child's resident set (`VmHWM` in
//! `/proc/<pid>/status`), read every [`POLL`] while it runs: the mark only rises, so the
//! last reading is the peak unless the child grew in its last milliseconds (it then writes
//! its manifest, a few hundred kilobytes). Linux only.
//!
//! Data: `$TERRAIN_DATA_DIR`, else `../shared/data` beside the repository; without it the
//! benchmark says NOT RUN. The mosaic and the databases go to a temporary directory,
//! removed at the end. Takes about 5 minutes on 2 cores.

mod common;

use anyhow::{Context, bail};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use terrain_server::db::{TileDb, Verify};

/// How often the child's high-water mark is read.
const POLL: Duration = Duration::from_millis(2);
/// Most the mosaic's peak may exceed the source's, as a ratio.
const TARGET_RATIO: f64 = 1.25;
const SOURCE: &str = "himalaya_4097/g10g_himalaya_4097.png";
/// Share of the samples made voids in the copy of the source with voids.
const VOID_SHARE: f64 = 0.03;
/// The no-data value of the copy with voids (himalaya's heights stop at 8,752 m).
const VOID_NODATA: u16 = 65535;

fn main() {
    let Some(data) = common::data_dir() else {
        println!(
            "NOT RUN: build_memory needs the data kit: set {} to its data/ directory",
            common::DATA_DIR_VAR
        );
        return;
    };
    // `-- DIR`: also write DIR/build_memory.md (`scripts/bench.sh` puts it in BENCHMARKS.md).
    let out = std::env::args_os()
        .skip(1)
        .find(|a| !a.to_string_lossy().starts_with('-'))
        .map(std::path::PathBuf::from);
    if let Err(error) = run(&data, out.as_deref()) {
        eprintln!("build_memory: {error:#}");
        std::process::exit(1);
    }
}

/// One input's build.
struct Measured {
    name: String,
    samples: u64,
    elapsed: Duration,
    peak_kib: u64,
    /// The build's `speed` line: per product, its seconds and M samples/s.
    speed: Vec<(String, f64, f64)>,
    /// Bytes of heights and textures, level 0 and all levels.
    heights: [u64; 2],
    textures: [u64; 2],
}

fn run(data: &Path, out: Option<&Path>) -> anyhow::Result<()> {
    let source = data.join(SOURCE);
    if !source.exists() {
        println!("NOT RUN: build_memory needs {}", source.display());
        return Ok(());
    }
    let work = tempfile::Builder::new()
        .prefix("build-memory-")
        .tempdir()
        .context("cannot create a temporary directory")?;
    let mosaic_dir = work.path().join("himalaya_mosaic_8193");
    std::fs::create_dir_all(&mosaic_dir)?;
    let mosaic = mosaic_dir.join("himalaya_mosaic_8193.png");
    let started = Instant::now();
    let [w, h] = common::mosaic::write_mirrored(&source, &mosaic)?;
    write_dataset_json(&source, &mosaic_dir)?;
    println!("machine: {}", common::machine());
    println!(
        "mosaic: {w} x {h} samples written in {:.1} s ({:.0} MiB)",
        started.elapsed().as_secs_f64(),
        std::fs::metadata(&mosaic)?.len() as f64 / (1024.0 * 1024.0)
    );
    println!();
    // The same raster with SRTM-like voids (3% of the samples, regions up to 60 samples
    // across), which the builder fills region by region in bounded memory.
    let voids_dir = work.path().join("himalaya_voids_4097");
    std::fs::create_dir_all(&voids_dir)?;
    let with_voids = voids_dir.join("himalaya_voids_4097.png");
    let void_samples =
        common::mosaic::write_with_voids(&source, &with_voids, VOID_SHARE, VOID_NODATA)?;
    write_dataset_json(&source, &voids_dir)?;
    let json = voids_dir.join("dataset.json");
    let mut info: serde_json::Map<String, serde_json::Value> =
        serde_json::from_slice(&std::fs::read(&json)?)?;
    info.insert("nodata".into(), serde_json::json!(VOID_NODATA));
    std::fs::write(&json, serde_json::to_vec_pretty(&info)?)?;
    println!("with voids: {void_samples} void samples punched in a copy of the source");
    let no_web = ["--no-web"];
    let small = measure(&source, &work.path().join("db-4097"), &no_web)?;
    let voided = measure(&with_voids, &work.path().join("db-4097-voids"), &no_web)?;
    let large = measure(&mosaic, &work.path().join("db-8193"), &no_web)?;
    let every = measure(&source, &work.path().join("db-4097-all"), &["--patches"])?;
    let patches = ["--patches", "--no-web"];
    let small_patches = measure(&source, &work.path().join("db-4097-patches"), &patches)?;
    let large_patches = measure(&mosaic, &work.path().join("db-8193-patches"), &patches)?;
    let mut report = report(&small, &voided, &large, void_samples);
    report.push_str(&every_product(&every, &small_patches, &large_patches));
    print!("{report}");
    if let Some(out) = out {
        std::fs::create_dir_all(out)?;
        let path = out.join("build_memory.md");
        std::fs::write(&path, report)
            .with_context(|| format!("cannot write {}", path.display()))?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

/// The tables and the two ratios against their target, in Markdown, stamped with the run.
fn report(small: &Measured, voided: &Measured, large: &Measured, void_samples: u64) -> String {
    use std::fmt::Write as _;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "<!-- written by `cargo bench -p terrain-server --bench build_memory`; do not edit -->"
    );
    let _ = writeln!(s, "Run: {}.\n", common::stamp::line());
    let _ = writeln!(
        s,
        "| input | samples | seconds | M samples/s | peak RSS MiB |"
    );
    let _ = writeln!(s, "|---|---:|---:|---:|---:|");
    for m in [small, voided, large] {
        let _ = writeln!(
            s,
            "| {} | {} | {:.1} | {:.2} | {:.1} |",
            m.name,
            m.samples,
            m.elapsed.as_secs_f64(),
            m.samples as f64 / m.elapsed.as_secs_f64() / 1e6,
            m.peak_kib as f64 / 1024.0
        );
    }
    let verdict = |ratio: f64| {
        if ratio <= TARGET_RATIO {
            "PASS"
        } else {
            "FAIL"
        }
    };
    let ratio = large.peak_kib as f64 / small.peak_kib as f64;
    let voids_ratio = voided.peak_kib as f64 / small.peak_kib as f64;
    let _ = writeln!(
        s,
        "\nPeak RSS, 4x the samples over 1x: **{ratio:.3}** (target at most {TARGET_RATIO}: {}).",
        verdict(ratio)
    );
    let _ = writeln!(
        s,
        "Peak RSS, with voids ({void_samples} void samples, {:.0}% of the source's) over without: **{voids_ratio:.3}** (target at most {TARGET_RATIO}: {}).\n",
        100.0 * VOID_SHARE,
        verdict(voids_ratio)
    );
    let _ = writeln!(
        s,
        "| input | pyramid / level 0, heights | textures | both |"
    );
    let _ = writeln!(s, "|---|---:|---:|---:|");
    for m in [small, large] {
        let over = |[level0, all]: [u64; 2]| all as f64 / level0 as f64;
        let both = [m.heights[0] + m.textures[0], m.heights[1] + m.textures[1]];
        let _ = writeln!(
            s,
            "| {} | {:.3} | {:.3} | {:.3} |",
            m.name,
            over(m.heights),
            over(m.textures),
            over(both)
        );
    }
    s
}

/// Each product's rate against its target, and the peak with the patches, 4x against 1x.
fn every_product(every: &Measured, small: &Measured, large: &Measured) -> String {
    use std::fmt::Write as _;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "\nEvery product, {} with `--patches` and the web tiles, from the build's summary:\n",
        every.name
    );
    let _ = writeln!(s, "| product | seconds | M samples/s | target | |");
    let _ = writeln!(s, "|---|---:|---:|---:|---|");
    for (product, seconds, rate) in &every.speed {
        let target = match product.as_str() {
            "tiles, heights and textures" => 8.0,
            "patches" => 2.0,
            "web" => 5.0,
            _ => f64::NAN,
        };
        let verdict = if *rate >= target { "PASS" } else { "FAIL" };
        let _ = writeln!(
            s,
            "| {product} | {seconds:.1} | {rate:.2} | {target} | {verdict} |"
        );
    }
    let _ = writeln!(
        s,
        "\nWhole build with every product: {:.1} s, peak RSS {:.1} MiB.\n",
        every.elapsed.as_secs_f64(),
        every.peak_kib as f64 / 1024.0
    );
    let ratio = large.peak_kib as f64 / small.peak_kib as f64;
    let _ = writeln!(
        s,
        "Peak RSS with `--patches --no-web`: {} {:.1} MiB, {} {:.1} MiB; 4x the samples over 1x: **{ratio:.3}** (target at most {TARGET_RATIO}: {}).",
        small.name,
        small.peak_kib as f64 / 1024.0,
        large.name,
        large.peak_kib as f64 / 1024.0,
        if ratio <= TARGET_RATIO {
            "PASS"
        } else {
            "FAIL"
        }
    );
    s
}

/// The products of a build summary's `speed` line: `NAME S s (R M samples/s)`, `; `-separated.
fn parse_speed(stdout: &str) -> Vec<(String, f64, f64)> {
    let Some(line) = stdout.lines().find_map(|l| l.strip_prefix("  speed")) else {
        return Vec::new();
    };
    line.split(';')
        .filter_map(|part| {
            let part = part.trim();
            let (head, rate) = part.split_once(" s (")?;
            let (name, seconds) = head.rsplit_once(' ')?;
            let rate = rate.strip_suffix(" M samples/s)")?;
            Some((name.to_string(), seconds.parse().ok()?, rate.parse().ok()?))
        })
        .collect()
}

/// The source's dataset.json minus what names its own files and place, so the mosaic gets
/// the same spacing and height scale (and a computed texture, as the source has).
fn write_dataset_json(source: &Path, dir: &Path) -> anyhow::Result<()> {
    let beside = source.with_file_name("dataset.json");
    let text =
        std::fs::read(&beside).with_context(|| format!("cannot read {}", beside.display()))?;
    let mut info: serde_json::Map<String, serde_json::Value> = serde_json::from_slice(&text)?;
    for key in [
        "heights",
        "texture",
        "width",
        "height",
        "north_west_corner_deg",
        "spacing_deg",
    ] {
        info.remove(key);
    }
    std::fs::write(dir.join("dataset.json"), serde_json::to_vec_pretty(&info)?)?;
    Ok(())
}

/// Builds `input` into `out` with the release binary and `flags`, reading its high-water
/// mark and its summary.
fn measure(input: &Path, out: &Path, flags: &[&str]) -> anyhow::Result<Measured> {
    let name = input
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    eprintln!("building {name} {} ...", flags.join(" "));
    let started = Instant::now();
    let mut child = Command::new(env!("CARGO_BIN_EXE_terrain-server"))
        .arg("build")
        .arg(input)
        .arg("--out")
        .arg(out)
        // The first three without the web tiles, which only georeferenced inputs (the
        // source, not its copies) get: the same products for every input.
        .args(["--force", "--quiet"])
        .args(flags)
        .stdout(Stdio::piped())
        .spawn()
        .context("cannot start terrain-server")?;
    let status_path = PathBuf::from(format!("/proc/{}/status", child.id()));
    // The summary is a few lines: read at the end, it never fills the pipe.
    let mut stdout = child.stdout.take().context("the child's stdout")?;
    let mut peak_kib = 0;
    let status = loop {
        if let Some(kib) = high_water_mark_kib(&status_path) {
            peak_kib = peak_kib.max(kib);
        }
        if let Some(status) = child.try_wait()? {
            break status;
        }
        std::thread::sleep(POLL);
    };
    let elapsed = started.elapsed();
    let mut summary = String::new();
    std::io::Read::read_to_string(&mut stdout, &mut summary)?;
    if !status.success() {
        bail!("terrain-server build {} failed: {status}", input.display());
    }
    if peak_kib == 0 {
        bail!("no VmHWM in {} (not Linux?)", status_path.display());
    }
    let db = TileDb::open(out, Verify::SizesOnly)?;
    let manifest = db.manifest();
    let (mut heights, mut textures) = ([0u64; 2], [0u64; 2]);
    for (id, record) in manifest.tiles() {
        let texture: u64 = (0..manifest.texture.levels)
            .filter_map(|level| db.texture(id, level))
            .map(|blob| blob.bytes.len() as u64)
            .sum();
        if id.level == 0 {
            heights[0] += record.bytes;
            textures[0] += texture;
        }
        heights[1] += record.bytes;
        textures[1] += texture;
    }
    Ok(Measured {
        name,
        samples: u64::from(manifest.raster.width) * u64::from(manifest.raster.height),
        elapsed,
        peak_kib,
        speed: parse_speed(&summary),
        heights,
        textures,
    })
}

/// `VmHWM` of a `/proc/<pid>/status`, in KiB; `None` once the process has exited.
fn high_water_mark_kib(status: &Path) -> Option<u64> {
    let text = std::fs::read_to_string(status).ok()?;
    let line = text.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}
