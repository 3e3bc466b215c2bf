//! The builder on real data: every input format, heights identical to the source, voids
//! filled and reported, textures registered, and no half-written database ever.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use terrain_server::build::{BuildError, BuildOptions, BuildReport, BuildWarning, build};
use terrain_server::db::{DbError, TileDb, Verify, WriteError};
use terrain_shared::manifest::TextureSource;
use terrain_shared::{Blob, Heights, Manifest, TileBlob, TileId};
use terrain_tests::data::{geotiff_i16, jacksboro, kit_file, png_codes, workspace_binary};

fn build_into(heights: &Path, dir: &Path, adjust: impl FnOnce(&mut BuildOptions)) -> BuildReport {
    let mut options = BuildOptions::new(heights, dir.join("db"));
    adjust(&mut options);
    build(&options, &|_, _| {}, &AtomicBool::new(false))
        .unwrap_or_else(|e| panic!("{}: {e}", heights.display()))
}

/// One tile of an opened database, decoded: its tile blob and the heights in it.
struct Decoded {
    id: TileId,
    blob: TileBlob,
    heights: Heights,
}

/// Decodes every tile of every level of an opened database, in manifest order (level 0
/// first, row-major within a level).
fn decoded_tiles(db: &TileDb) -> Vec<Decoded> {
    db.manifest()
        .tiles()
        .map(|(id, _)| {
            let stored = db.heights(id).expect("tile in grid");
            let blob = TileBlob::decode(&stored.bytes).unwrap_or_else(|e| panic!("tile {id}: {e}"));
            let heights =
                Heights::decode(&blob.heights).unwrap_or_else(|e| panic!("tile {id}: {e}"));
            Decoded { id, blob, heights }
        })
        .collect()
}

/// The level-0 raster position of sample `(x, y)` of tile `id`: a tile of level `k` keeps
/// every `2^k`-th sample of level 0, and samples past its level's raster (padding) repeat
/// the last real one, as do samples past level 0's.
fn source_position(m: &Manifest, id: TileId, x: u32, y: u32) -> (u32, u32) {
    let n = m.tile_size;
    let raster = m.levels[id.level as usize].raster;
    let lx = (id.x * (n - 1) + x).min(raster.width - 1);
    let ly = (id.y * (n - 1) + y).min(raster.height - 1);
    (
        (lx << id.level).min(m.raster.width - 1),
        (ly << id.level).min(m.raster.height - 1),
    )
}

/// Every sample of every tile of every level equals `source` at its raster position;
/// padding repeats the nearest edge sample. Returns the number of real level-0 samples
/// compared.
fn check_tiles_equal_source(db: &TileDb, source: impl Fn(u32, u32) -> i32) -> usize {
    let m: &Manifest = db.manifest();
    let n = m.tile_size;
    let mut compared = 0;
    let tiles = decoded_tiles(db);
    assert_eq!(tiles.len(), m.tile_count());
    for Decoded { id, heights, .. } in tiles {
        assert_eq!((heights.width, heights.height), (n as u16, n as u16));
        let valid = m.valid(id);
        for y in 0..n {
            for x in 0..n {
                let (sx, sy) = source_position(m, id, x, y);
                let got = heights.codes[(y * n + x) as usize];
                assert_eq!(
                    got,
                    source(sx, sy),
                    "tile {id} sample ({x}, {y}) = raster ({sx}, {sy})"
                );
                if id.level == 0 && x < valid[0] && y < valid[1] {
                    compared += 1;
                }
            }
        }
    }
    compared
}

/// The largest distance, metres, between tile `id`'s surface and the level-0 samples that
/// lie on the sides of its cells (where its surface is the straight line between two of its
/// samples, whichever way the cells are split): a floor under its distance from the
/// full-resolution surface. `source` gives level-0 heights in metres.
fn deviation_along_cell_sides(m: &Manifest, id: TileId, source: impl Fn(u32, u32) -> f64) -> f64 {
    let n = m.tile_size;
    let step = 1u32 << id.level;
    let raster = m.levels[id.level as usize].raster;
    let level0 = |lx: u32, ly: u32| (lx * step, ly * step);
    let inside = |(x, y): (u32, u32)| x < m.raster.width && y < m.raster.height;
    let mut worst = 0.0f64;
    for j in 0..n {
        for i in 0..n {
            let (lx, ly) = (id.x * (n - 1) + i, id.y * (n - 1) + j);
            if lx >= raster.width || ly >= raster.height || !inside(level0(lx, ly)) {
                continue;
            }
            let (x0, y0) = level0(lx, ly);
            let a = source(x0, y0);
            // East along the row, south along the column: both ends real samples.
            for (ends, along) in [
                (
                    (i + 1 < n && lx + 1 < raster.width).then(|| level0(lx + 1, ly)),
                    0,
                ),
                (
                    (j + 1 < n && ly + 1 < raster.height).then(|| level0(lx, ly + 1)),
                    1,
                ),
            ] {
                let Some(end) = ends.filter(|&e| inside(e)) else {
                    continue;
                };
                let b = source(end.0, end.1);
                for t in 1..step {
                    let (x, y) = if along == 0 {
                        (x0 + t, y0)
                    } else {
                        (x0, y0 + t)
                    };
                    let line = a + (b - a) * f64::from(t) / f64::from(step);
                    worst = worst.max((source(x, y) - line).abs());
                }
            }
        }
    }
    worst
}

fn open(report: &BuildReport) -> TileDb {
    TileDb::open(&report.out, Verify::Hashes).expect("built database opens")
}

#[test]
fn jacksboro_heights_are_stored_exactly_with_shared_borders() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_into(&jacksboro(), tmp.path(), |_| {});
    let (w, h, codes) = png_codes(&jacksboro());
    let m = &report.manifest;
    assert_eq!((m.raster.width, m.raster.height), (403, 344));
    // 403 x 344 samples, then every other one: 202 x 173, then 102 x 87, one tile.
    let grids: Vec<(u32, u32)> = (0..m.level_count())
        .map(|k| (m.grid(k).columns, m.grid(k).rows))
        .collect();
    assert_eq!(grids, [(4, 3), (2, 2), (1, 1)]);
    assert_eq!(m.tile_count(), 17);
    assert_eq!(
        m.spacing_m,
        [74.3, 92.6],
        "spacing from the fixture's dataset.json"
    );
    assert_eq!(m.texture.source, TextureSource::Generated);
    assert!(report.warnings.is_empty(), "{:?}", report.warnings);
    let db = open(&report);
    // Shared borders are real duplicates: counting each raster sample once per tile that holds it.
    let compared = check_tiles_equal_source(&db, |x, y| codes[(y * w + x) as usize]);
    assert!(compared >= (w * h) as usize);
    // Per-tile metadata is consistent with the samples: bounds hold (above level 0, those
    // of the full-resolution surface under the tile, its children's), errors grow from the
    // tile's distance to full resolution (0 at level 0), which is at least what its cells'
    // sides show; the tile blob lists the texture levels the database holds.
    let metres = |x: u32, y: u32| f64::from(codes[(y * w + x) as usize]);
    let mut level_bytes = vec![0u64; m.texture.levels as usize];
    for Decoded { id, blob, heights } in decoded_tiles(&db) {
        let record = m.tile(id).expect("record");
        let (lo, hi) = heights.code_range();
        if id.level == 0 {
            assert_eq!(
                (record.min_m, record.max_m),
                (lo as f32, hi as f32),
                "tile {id}"
            );
            assert_eq!(blob.mask_errors_m[0], 0.0, "tile {id}");
        } else {
            let children: Vec<_> = m
                .children(id)
                .into_iter()
                .map(|c| m.tile(c).expect("child"))
                .collect();
            assert!(!children.is_empty(), "tile {id}");
            let min = children.iter().map(|c| c.min_m).fold(f32::MAX, f32::min);
            let max = children.iter().map(|c| c.max_m).fold(f32::MIN, f32::max);
            assert_eq!((record.min_m, record.max_m), (min, max), "tile {id}");
            assert!(
                record.min_m <= lo as f32 && hi as f32 <= record.max_m,
                "tile {id}"
            );
            let floor = deviation_along_cell_sides(m, id, metres);
            assert!(
                f64::from(blob.mask_errors_m[0]) >= floor - 1e-3,
                "tile {id}: mask 0 is {} m from full resolution, its cell sides show {floor} m",
                blob.mask_errors_m[0]
            );
        }
        assert_eq!(blob.mask_errors_m.len(), m.mask_levels as usize);
        // Each mask's error is its distance from the tile plus the tile's from full
        // resolution (the triangle inequality), which adds up one level's decimation error
        // after another: each within the heights it spans.
        let spans =
            f64::from(hi - lo) + f64::from(id.level) * f64::from(record.max_m - record.min_m);
        assert!(
            blob.mask_errors_m
                .iter()
                .all(|&e| e >= blob.mask_errors_m[0] && f64::from(e) <= spans + 0.02),
            "tile {id}: {:?}",
            blob.mask_errors_m
        );
        assert!(record.roughness_m > 0.0, "tile {id}");
        assert_eq!(blob.texture.len(), m.texture.levels as usize, "tile {id}");
        assert_eq!(
            blob.texture[0].bytes, record.coarsest_texture_bytes,
            "tile {id}"
        );
        for (level, listed) in blob.texture.iter().enumerate() {
            let stored = db.texture(id, level as u32).expect("texture level");
            assert_eq!(Blob::of(&stored.bytes), *listed, "tile {id} level {level}");
            level_bytes[level] += listed.bytes;
        }
    }
    // The manifest's totals per texture level are the tile blobs' sizes added up.
    assert_eq!(m.texture.level_bytes, level_bytes);
}

#[test]
fn puget_sound_keeps_its_decimetre_heights_and_its_cell_centred_texture() {
    let Some(heights) = kit_file("puget_sound", "puget_sound_1k/ps_height_1k.png") else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_into(&heights, tmp.path(), |_| {});
    let m = &report.manifest;
    assert_eq!((m.heights.quantum_m, m.spacing_m), (0.1, [160.0, 160.0]));
    assert!(
        (m.heights.max_m - 4379.8).abs() < 1e-6,
        "Mt Rainier: {}",
        m.heights.max_m
    );
    assert_eq!(m.texture.source, TextureSource::Image);
    assert_eq!(m.texture.size, 128, "one texel per cell, as in the source");
    let db = open(&report);
    let (w, _, codes) = png_codes(&heights);
    check_tiles_equal_source(&db, |x, y| codes[(y * w + x) as usize]);

    // Registration: with one texel per cell, texel (i, j) of tile (x, y) is source texel
    // (128 x + i, 128 y + j). Compare a whole tile, and the same tile shifted by one texel,
    // which must match worse: JPEG blurs, a half-texel error would not show, a whole one does.
    let source = image::open(heights.with_file_name("ps_texture_1k.png"))
        .expect("texture")
        .into_rgb8();
    let id = TileId::new(3, 2);
    let finest = db.texture(id, m.texture.levels - 1).expect("finest level");
    let tile = image::load_from_memory(&finest.bytes)
        .expect("jpeg")
        .into_rgb8();
    let mean_difference = |shift: i64| {
        let mut total = 0.0;
        for j in 8..120u32 {
            for i in 8..120u32 {
                let sx = (i64::from(3 * 128 + i) + shift) as u32;
                let a = tile.get_pixel(i, j).0;
                let b = source.get_pixel(sx, 2 * 128 + j).0;
                total += (0..3).map(|k| f64::from(a[k].abs_diff(b[k]))).sum::<f64>() / 3.0;
            }
        }
        total / (112.0 * 112.0)
    };
    let (aligned, shifted) = (mean_difference(0), mean_difference(1));
    assert!(
        aligned < 8.0 && aligned * 1.5 < shifted,
        "aligned {aligned:.2}, shifted by one texel {shifted:.2}"
    );
}

#[test]
fn himalaya_4097_builds_a_32_by_32_grid_with_everest() {
    let Some(heights) = kit_file("himalaya_4097", "himalaya_4097/g10g_himalaya_4097.png") else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_into(&heights, tmp.path(), |_| {});
    let m = &report.manifest;
    assert_eq!((m.grid(0).columns, m.grid(0).rows), (32, 32));
    // 4097, 2049, ... 129 samples: six levels, the last one tile.
    assert_eq!(m.level_count(), 6);
    assert_eq!(m.tile_count(), 1365);
    assert_eq!((m.heights.min_m, m.heights.max_m), (0.0, 8752.0));
    assert!(
        m.tiles().all(|(id, _)| m.valid(id) == [129, 129]),
        "4097 = 32 * 128 + 1, and every level 2^k * 128 + 1: no padding"
    );
    let db = open(&report);
    // Flat sea: tiles over nothing but zeros (at full resolution, whatever their level)
    // have no roughness and no mask error at any mask level.
    let sea: Vec<_> = m.tiles().filter(|(_, t)| t.max_m == 0.0).collect();
    assert!(sea.iter().any(|(id, _)| id.level == 0));
    assert!(
        sea.iter().any(|(id, _)| id.level > 0),
        "the sea is larger than a tile"
    );
    for (id, record) in sea {
        let blob = TileBlob::decode(&db.heights(id).expect("in grid").bytes).expect("blob");
        assert!(
            record.roughness_m == 0.0 && blob.mask_errors_m.iter().all(|&e| e == 0.0),
            "tile {id}: {} m rough, {:?}",
            record.roughness_m,
            blob.mask_errors_m
        );
    }
    let (w, _, codes) = png_codes(&heights);
    check_tiles_equal_source(&db, |x, y| codes[(y * w + x) as usize]);
}

#[test]
fn grand_canyon_8_bit_heights_keep_their_ten_metre_steps() {
    let Some(heights) = kit_file(
        "grand_canyon",
        "grand_canyon_hoppe/gcanyon_elev_crop.bw.png",
    ) else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_into(&heights, tmp.path(), |_| {});
    let m = &report.manifest;
    assert_eq!((m.heights.quantum_m, m.spacing_m), (10.0, [60.0, 60.0]));
    assert_eq!(m.texture.source, TextureSource::Image);
    let db = open(&report);
    let (w, _, codes) = png_codes(&heights);
    check_tiles_equal_source(&db, |x, y| codes[(y * w + x) as usize]);
}

/// SRTM GeoTIFFs: voids are counted exactly, filled without spikes, and every valid
/// sample is stored unchanged.
fn check_srtm_geotiff(name: &str) {
    let Some(tif) = kit_file(name, &format!("srtm_geotiff/{name}")) else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_into(&tif, tmp.path(), |_| {});
    let (w, _, source) = geotiff_i16(&tif);
    let voids = source.iter().filter(|&&v| v == -32768).count();
    assert!(voids > 0);
    let filled = report.warnings.iter().find_map(|w| match w {
        BuildWarning::FilledVoids(r) => Some(r.samples),
        _ => None,
    });
    assert_eq!(filled, Some(voids), "{name}: {:?}", report.warnings);
    let m = &report.manifest;
    assert_eq!(m.heights.filled_voids, voids as u64);
    let georeference = m.georeference.as_ref().expect("GeoTIFF geotransform");
    assert_eq!(georeference.crs.as_deref(), Some("EPSG:4326"));
    assert!(
        m.spacing_m[0] < m.spacing_m[1],
        "3 arc-seconds are narrower east-west away from the equator"
    );

    let valid_min = source
        .iter()
        .filter(|&&v| v != -32768)
        .min()
        .copied()
        .map(i32::from)
        .expect("valid");
    let valid_max = source
        .iter()
        .filter(|&&v| v != -32768)
        .max()
        .copied()
        .map(i32::from)
        .expect("valid");
    let db = open(&report);
    let n = m.tile_size;
    for Decoded { id, heights, .. } in decoded_tiles(&db) {
        for y in 0..n {
            for x in 0..n {
                let (sx, sy) = source_position(m, id, x, y);
                let got = heights.codes[(y * n + x) as usize];
                let original = i32::from(source[(sy * w + sx) as usize]);
                if original == -32768 {
                    assert!(
                        (valid_min..=valid_max).contains(&got),
                        "{name}: void at ({sx}, {sy}) filled with {got}"
                    );
                } else {
                    assert_eq!(got, original, "{name}: ({sx}, {sy})");
                }
            }
        }
    }
}

#[test]
fn mt_rainier_geotiff_voids_are_reported_and_filled() {
    check_srtm_geotiff("mt_rainier_90m.tif");
}

#[test]
fn mt_fuji_geotiff_voids_are_reported_and_filled() {
    check_srtm_geotiff("mt_fuji_90m.tif");
}

#[test]
fn an_srtm_hgt_file_gives_the_same_heights_as_its_geotiff() {
    let Some(tif) = kit_file("hgt", "srtm_geotiff/mt_rainier_90m.tif") else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    // The same 1201^2 int16 samples as SRTM distributes them: big-endian, named by corner.
    let (_, _, samples) = geotiff_i16(&tif);
    let hgt = tmp.path().join("N46W122.hgt");
    let bytes: Vec<u8> = samples.iter().flat_map(|s| s.to_be_bytes()).collect();
    std::fs::write(&hgt, bytes).expect("write hgt");

    let from_hgt = build_into(&hgt, &tmp.path().join("a"), |_| {});
    let from_tif = build_into(&tif, &tmp.path().join("b"), |_| {});
    let georeference = from_hgt
        .manifest
        .georeference
        .clone()
        .expect("from the file name");
    assert_eq!(georeference.origin, [-122.0, 47.0]);
    assert_eq!(
        from_hgt.manifest.heights.filled_voids,
        from_tif.manifest.heights.filled_voids
    );
    let (a, b) = (open(&from_hgt), open(&from_tif));
    let (ta, tb) = (decoded_tiles(&a), decoded_tiles(&b));
    assert_eq!(ta.len(), tb.len());
    assert_eq!(ta.len(), a.manifest().tile_count());
    for (x, y) in ta.iter().zip(&tb) {
        assert_eq!(x.heights.codes, y.heights.codes, "tile {}", x.id);
        assert_eq!(x.blob.mask_errors_m, y.blob.mask_errors_m, "tile {}", x.id);
    }
    for (s, t) in from_hgt
        .manifest
        .spacing_m
        .iter()
        .zip(from_tif.manifest.spacing_m)
    {
        assert!((s - t).abs() < 0.5, "{s} vs {t}");
    }
}

#[test]
fn a_truncated_or_wrong_sized_input_is_a_clear_error() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let bytes = std::fs::read(jacksboro()).expect("fixture");
    let truncated = tmp.path().join("truncated.png");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).expect("write");
    let error = build(
        &BuildOptions::new(&truncated, tmp.path().join("db")),
        &|_, _| {},
        &AtomicBool::new(false),
    )
    .expect_err("a truncated PNG must not build");
    assert!(error.to_string().contains("truncated.png"), "{error}");
    let hgt = tmp.path().join("N10E010.hgt");
    std::fs::write(&hgt, vec![0u8; 1000]).expect("write");
    let error = build(
        &BuildOptions::new(&hgt, tmp.path().join("db")),
        &|_, _| {},
        &AtomicBool::new(false),
    )
    .expect_err("a 1000-byte .hgt must not build");
    assert!(error.to_string().contains("1201^2"), "{error}");
    assert!(!tmp.path().join("db").exists());
}

#[test]
fn a_damaged_database_is_refused_when_it_opens() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_into(&jacksboro(), tmp.path(), |_| {});
    let pack = report.out.join(terrain_server::db::HEIGHTS_PACK);
    let mut bytes = std::fs::read(&pack).expect("pack");
    let last = bytes.len() - 1;
    bytes[last] ^= 0x40;
    std::fs::write(&pack, &bytes).expect("write");
    match TileDb::open(&report.out, Verify::Hashes) {
        Err(DbError::HashMismatch { id, .. }) => {
            // The pack ends with the coarsest level's one tile.
            assert_eq!(id, TileId::at(2, 0, 0), "the last tile holds the last byte")
        }
        other => panic!("expected a hash mismatch, got {other:?}"),
    }
    bytes.truncate(last);
    std::fs::write(&pack, &bytes).expect("write");
    assert!(matches!(
        TileDb::open(&report.out, Verify::SizesOnly),
        Err(DbError::PackSize { .. })
    ));
}

#[test]
fn an_existing_database_is_replaced_only_with_force() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let first = build_into(&jacksboro(), tmp.path(), |o| o.tile_size = 65);
    let again = build(
        &BuildOptions::new(jacksboro(), &first.out),
        &|_, _| {},
        &AtomicBool::new(false),
    );
    assert!(
        matches!(again, Err(BuildError::Write(WriteError::Exists(_)))),
        "{again:?}"
    );
    assert_eq!(
        open(&first).manifest().tile_size,
        65,
        "the refused build left the old database alone"
    );
    let mut options = BuildOptions::new(jacksboro(), &first.out);
    options.force = true;
    build(&options, &|_, _| {}, &AtomicBool::new(false)).expect("forced build");
    assert_eq!(
        TileDb::open(&first.out, Verify::Hashes)
            .expect("opens")
            .manifest()
            .tile_size,
        129
    );
    assert_eq!(leftovers(tmp.path()), Vec::<PathBuf>::new());
}

/// Hidden temporary entries a build left in `dir`.
fn leftovers(dir: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(dir)
        .expect("readable")
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with('.'))
        })
        .collect()
}

#[test]
fn a_cancelled_build_leaves_nothing_behind() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let cancel = AtomicBool::new(false);
    let options = BuildOptions {
        tile_size: 33,
        ..BuildOptions::new(jacksboro(), tmp.path().join("db"))
    };
    let result = build(
        &options,
        &|done, _| {
            if done >= 3 {
                cancel.store(true, Ordering::Relaxed)
            }
        },
        &cancel,
    );
    assert!(matches!(result, Err(BuildError::Cancelled)), "{result:?}");
    assert!(!tmp.path().join("db").exists());
    assert_eq!(leftovers(tmp.path()), Vec::<PathBuf>::new());
}

/// A 2049^2 synthetic DEM: large enough that building it takes seconds.
fn large_synthetic_dem(dir: &Path) -> PathBuf {
    let path = dir.join("large.png");
    let image = image::ImageBuffer::from_fn(2049, 2049, |x, y| {
        let (x, y) = (f64::from(x) / 60.0, f64::from(y) / 45.0);
        image::Luma([
            (20_000.0 + 8_000.0 * x.sin() * y.cos() + 3_000.0 * (x * 3.1 + y).sin()) as u16,
        ])
    });
    image.save(&path).expect("write png");
    path
}

/// Waits until the builder's hidden temporary directory appears in `dir`.
fn wait_for_temporary_dir(dir: &Path, child: &mut std::process::Child) {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while leftovers(dir).is_empty() {
        assert!(
            child.try_wait().expect("wait").is_none(),
            "build ended before it could be interrupted"
        );
        assert!(
            std::time::Instant::now() < deadline,
            "the build never started"
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
}

/// Starts the real builder on a large synthetic DEM in `dir` and returns once its hidden
/// temporary directory exists (the build is under way), with the output path.
fn start_large_build(dir: &Path) -> (std::process::Child, PathBuf) {
    let input = large_synthetic_dem(dir);
    let out = dir.join("db");
    let mut child = std::process::Command::new(workspace_binary("terrain-server"))
        .args(["build", "--quiet", "--tile-size", "65"])
        .arg(&input)
        .arg("--out")
        .arg(&out)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("builder starts");
    wait_for_temporary_dir(dir, &mut child);
    (child, out)
}

/// The temporary directory of the build running in `dir` once its lock is taken.
fn locked_temporary_dir(dir: &Path) -> PathBuf {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    loop {
        if let Some(found) = leftovers(dir)
            .into_iter()
            .find(|d| d.join(terrain_server::db::BUILDING_LOCK).exists())
        {
            return found;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "no locked temporary directory"
        );
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
}

#[test]
fn a_killed_build_never_leaves_a_database_at_the_output_and_the_next_build_removes_what_it_left() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (mut child, out) = start_large_build(tmp.path());
    let left = locked_temporary_dir(tmp.path());
    child.kill().expect("SIGKILL");
    child.wait().expect("reaped");
    assert!(!out.exists(), "a killed build left {}", out.display());
    // What remains is hidden and marked as being built: the server refuses it even when it
    // holds a manifest (a build killed during the web tiles).
    assert!(left.exists());
    std::fs::write(
        left.join(terrain_server::db::MANIFEST_FILE),
        report_manifest_json(),
    )
    .expect("a manifest as a build killed late leaves one");
    let error = TileDb::open(&left, Verify::SizesOnly).expect_err("refused");
    assert!(
        error
            .to_string()
            .contains("is a database being built, or one a killed build left"),
        "{error}"
    );
    let served = std::process::Command::new(workspace_binary("terrain-server"))
        .arg("serve")
        .arg(&left)
        .args(["--addr", "127.0.0.1:0"])
        .output()
        .expect("runs");
    assert_eq!(served.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&served.stderr).contains("is a database being built"),
        "{}",
        String::from_utf8_lossy(&served.stderr)
    );
    // The next build to the same output removes it, and says so.
    let (ok, stdout, stderr) = build_cli(&jacksboro(), &out, &[]);
    assert!(ok, "{stderr}");
    assert!(
        stdout.contains("removed what 1 killed build(s) to this output left"),
        "{stdout}"
    );
    assert!(!left.exists(), "{} is still there", left.display());
    assert_eq!(leftovers(tmp.path()), Vec::<PathBuf>::new());
    assert!(!out.join(terrain_server::db::BUILDING_LOCK).exists());
    TileDb::open(&out, Verify::Hashes).expect("the new database opens");
}

/// Any small manifest: what a build killed after writing its manifest leaves.
fn report_manifest_json() -> Vec<u8> {
    let tmp = tempfile::tempdir().expect("tempdir");
    terrain_tests::data::build_jacksboro(tmp.path())
        .manifest
        .to_json()
}

#[test]
fn ctrl_c_sigterm_and_sighup_cancel_a_build_and_clean_up() {
    for signal in ["-INT", "-TERM", "-HUP"] {
        let tmp = tempfile::tempdir().expect("tempdir");
        let (child, out) = start_large_build(tmp.path());
        locked_temporary_dir(tmp.path());
        let sent = std::process::Command::new("kill")
            .args([signal, &child.id().to_string()])
            .status()
            .expect("kill runs");
        assert!(sent.success());
        let output = child.wait_with_output().expect("exits");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{signal}");
        assert!(stderr.contains("cancelled"), "{signal}: {stderr}");
        assert!(!out.exists(), "{signal}");
        assert_eq!(leftovers(tmp.path()), Vec::<PathBuf>::new(), "{signal}");
    }
}

#[test]
fn a_manifest_whose_extent_disagrees_with_its_raster_and_spacing_is_refused() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = terrain_tests::data::build_jacksboro(tmp.path());
    assert!(Manifest::from_json(&report.manifest.to_json()).is_ok());
    let mut tampered = report.manifest.clone();
    tampered.extent_m[0] += 100.0;
    let error = Manifest::from_json(&tampered.to_json()).expect_err("extent off by 100 m");
    assert!(error.to_string().contains("extent"), "{error}");
}

/// A 40x30 float32 GeoTIFF (no GDAL no-data tag) with heights from 16 to 180 m in
/// centimetres, and `special` samples `(x, y, value)` written over them.
fn float_geotiff(dir: &Path, special: &[(u32, u32, f32)]) -> PathBuf {
    let (w, h) = (40u32, 30u32);
    let mut samples: Vec<f32> = (0..w * h)
        .map(|i| {
            let (x, y) = (f64::from(i % w), f64::from(i / w));
            (16.0 + 164.0 * (x / 39.0) * (0.5 + 0.5 * (y / 7.0).sin().abs())) as f32
        })
        .map(|m| (m * 100.0).round() / 100.0)
        .collect();
    samples[0] = 16.0;
    samples[(w * h - 1) as usize] = 180.0;
    samples[1] = 16.25; // not a whole number: the quantum applies
    for &(x, y, value) in special {
        samples[(y * w + x) as usize] = value;
    }
    let path = dir.join("float.tif");
    let file = std::fs::File::create(&path).expect("create tif");
    tiff::encoder::TiffEncoder::new(file)
        .expect("tiff encoder")
        .write_image::<tiff::encoder::colortype::Gray32Float>(w, h, &samples)
        .expect("write float tif");
    path
}

/// Runs the release builder on `input` with extra flags: (success, stdout, stderr).
fn build_cli(input: &Path, out: &Path, flags: &[&str]) -> (bool, String, String) {
    let mut args: Vec<&std::ffi::OsStr> = vec!["build".as_ref(), "--quiet".as_ref()];
    args.push(input.as_os_str());
    args.push("--out".as_ref());
    args.push(out.as_os_str());
    args.extend(flags.iter().map(std::ffi::OsStr::new));
    terrain_tests::data::run_binary("terrain-server", &args)
}

#[test]
fn float_heights_no_code_can_hold_are_refused_with_their_count_and_place() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("db");
    // A stray 1e30: one sample, named with its position and value.
    let tif = float_geotiff(tmp.path(), &[(5, 3, 1e30)]);
    let (ok, _, stderr) = build_cli(&tif, &out, &[]);
    assert!(!ok, "a 1e30 m sample must not build: {stderr}");
    assert!(stderr.contains("1 of 1200 float samples"), "{stderr}");
    assert!(stderr.contains("1e30 at (5, 3)"), "{stderr}");
    assert!(!out.exists());

    // -3.4e38, the float32 no-data of many tools, with no tag saying so.
    let tif = float_geotiff(
        tmp.path(),
        &[(0, 0, f32::MIN), (39, 0, f32::MIN), (7, 29, f32::MIN)],
    );
    let (ok, _, stderr) = build_cli(&tif, &out, &[]);
    assert!(!ok, "unmarked -3.4e38 no-data must not build: {stderr}");
    assert!(stderr.contains("3 of 1200 float samples"), "{stderr}");
    assert!(
        stderr.contains("at (0, 0)")
            && stderr.contains("at (39, 0)")
            && stderr.contains("at (7, 29)"),
        "{stderr}"
    );
    assert!(stderr.contains("--out-of-range nodata"), "{stderr}");
    assert!(!out.exists());

    // Infinities are not heights either.
    let tif = float_geotiff(tmp.path(), &[(2, 2, f32::INFINITY)]);
    let (ok, _, stderr) = build_cli(&tif, &out, &[]);
    assert!(!ok && stderr.contains("inf at (2, 2)"), "{stderr}");
}

#[test]
fn a_float_quantum_too_fine_for_the_heights_is_refused() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("db");
    let tif = float_geotiff(tmp.path(), &[]);
    for policy in ["refuse", "nodata"] {
        let (ok, _, stderr) = build_cli(
            &tif,
            &out,
            &["--float-quantum", "1e-12", "--out-of-range", policy],
        );
        assert!(
            !ok,
            "{policy}: a 1e-12 m quantum cannot hold 16 .. 180 m: {stderr}"
        );
        assert!(stderr.contains("16 .. 180 m"), "{policy}: {stderr}");
        assert!(stderr.contains("--float-quantum"), "{policy}: {stderr}");
        assert!(!out.exists());
    }
    for bad in ["0", "-1", "nan"] {
        let (ok, _, stderr) = build_cli(&tif, &out, &["--float-quantum", bad]);
        assert!(!ok && stderr.contains("quantum"), "{bad}: {stderr}");
    }
    // The same file at a sane quantum builds exactly.
    let (ok, stdout, stderr) = build_cli(&tif, &out, &[]);
    assert!(ok, "{stderr}");
    assert!(
        stdout.contains("16.0 .. 180.0 m in steps of 0.01 m"),
        "{stdout}"
    );
}

#[test]
fn out_of_range_floats_become_voids_when_asked() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("db");
    let tif = float_geotiff(
        tmp.path(),
        &[
            (5, 3, 1e30),
            (0, 0, f32::MIN),
            (7, 29, f32::NEG_INFINITY),
            (9, 9, f32::NAN),
        ],
    );
    let (ok, stdout, stderr) = build_cli(&tif, &out, &["--out-of-range", "nodata"]);
    assert!(ok, "{stderr}");
    assert!(
        stdout.contains("3 float samples no height code holds were taken as no-data"),
        "{stdout}"
    );
    assert!(
        stdout.contains("filled 4 no-data samples"),
        "NaN is no-data: {stdout}"
    );
    let db = TileDb::open(&out, Verify::Hashes).expect("opens");
    let m = db.manifest();
    assert_eq!(m.heights.filled_voids, 4);
    // Each void is filled from the surface around it: near what the surface the raster
    // samples gives there (a corner void continues its edges' slopes, so it may lie a
    // little past the raster's range).
    let surface = |x: u32, y: u32| {
        let (x, y) = (f64::from(x), f64::from(y));
        16.0 + 164.0 * (x / 39.0) * (0.5 + 0.5 * (y / 7.0).sin().abs())
    };
    let mut filled = Vec::new();
    for Decoded { id, heights, .. } in decoded_tiles(&db) {
        if id.level != 0 {
            continue;
        }
        for y in 0..m.tile_size {
            for x in 0..m.tile_size {
                let at = source_position(m, id, x, y);
                if [(5, 3), (0, 0), (7, 29), (9, 9)].contains(&at) {
                    let got = heights.metres(x as usize, y as usize);
                    filled.push((at, got, surface(at.0, at.1)));
                }
            }
        }
    }
    assert!(filled.len() >= 4, "{filled:?}");
    for &(at, got, want) in &filled {
        assert!(
            (got - want).abs() < 3.0,
            "void at {at:?}: {got} m, the surface {want} m"
        );
    }
    assert!(m.heights.max_m <= 180.0 + 1e-9, "{} m", m.heights.max_m);
}

/// The default heights coder is rANS (codec 2) and `--heights-codec zstd` still writes codec
/// 1: the same heights and mask errors in every tile, fewer bytes with rANS. The summary
/// gives each product's seconds and samples a second.
#[test]
fn both_heights_coders_hold_the_same_tiles_and_the_summary_gives_each_products_rate() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (rans, zstd) = (dir.path().join("rans"), dir.path().join("zstd"));
    let (ok, stdout, stderr) = build_cli(&jacksboro(), &rans, &[]);
    assert!(ok, "{stderr}");
    let speed = stdout
        .lines()
        .find(|l| l.starts_with("  speed "))
        .unwrap_or_else(|| panic!("no speed line in {stdout}"));
    assert!(
        speed.contains("tiles, heights and textures")
            && speed.contains("; web ")
            && speed.matches(" M samples/s)").count() == 2,
        "{speed}"
    );
    let (ok, _, stderr) = build_cli(&jacksboro(), &zstd, &["--heights-codec", "zstd"]);
    assert!(ok, "{stderr}");
    let (rans, zstd) = (
        TileDb::open(&rans, Verify::Hashes).expect("opens"),
        TileDb::open(&zstd, Verify::Hashes).expect("opens"),
    );
    assert_eq!(rans.manifest().heights.codec, "planar-rans/2");
    assert_eq!(zstd.manifest().heights.codec, "planar-zstd/1");
    let (a, b) = (decoded_tiles(&rans), decoded_tiles(&zstd));
    assert_eq!(a.len(), b.len());
    let (mut rans_bytes, mut zstd_bytes) = (0, 0);
    for (a, b) in a.iter().zip(&b) {
        assert_eq!((a.id, &a.heights), (b.id, &b.heights));
        assert_eq!(a.blob.mask_errors_m, b.blob.mask_errors_m, "tile {}", a.id);
        assert_eq!(
            (a.blob.heights[4], b.blob.heights[4]),
            (2, 1),
            "codec versions"
        );
        rans_bytes += a.blob.heights.len();
        zstd_bytes += b.blob.heights.len();
    }
    assert!(
        rans_bytes < zstd_bytes,
        "rANS {rans_bytes} bytes, zstd {zstd_bytes}"
    );
}
