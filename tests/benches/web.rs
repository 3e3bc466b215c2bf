//! The web tiles against our own formats: bytes, and requests per second.
//!
//! ```text
//! cargo bench -p terrain-tests --bench web -- [--seconds S]
//! ```
//!
//! Builds jacksboro (bundled) and, with `$TERRAIN_DATA_DIR`, mt_rainier_90m.tif and
//! himalaya_4097, and prints per dataset:
//!
//! - **bytes**, on the same area: the finest level of each pyramid over the source samples
//!   it covers. Our heights (tile blobs of level 0, heights in the default codec), the Terrarium and
//!   Terrain-RGB PNGs of the finest zoom, and the gzipped quantized-mesh tiles of the finest
//!   level; per tile, and per source sample (tile bytes times the share of the tile on
//!   the terrain, summed, over the samples).
//! - **requests per second** of a real server on 127.0.0.1 (16 requests at once from
//!   reqwest, for `--seconds` each, 3 by default) on the native tile-blob route, the
//!   Terrarium route and the quantized-mesh route, each over all its tiles in turn; the
//!   ratio is to the native route, measured in the same run.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use terrain_server::build::{BuildOptions, build};
use terrain_server::db::{TileDb, Verify};
use terrain_server::web::index::Kind;
use terrain_tests::server::TestServer;

const CONCURRENCY: usize = 16;

fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|text| {
            text.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into())
}

/// Requests per second over `urls`, in turn, `CONCURRENCY` at once, for `seconds`.
async fn rate(urls: Arc<Vec<String>>, seconds: f64) -> f64 {
    let client = reqwest::Client::new();
    let done = Arc::new(AtomicU64::new(0));
    let stop = Arc::new(AtomicBool::new(false));
    let started = Instant::now();
    let mut tasks = Vec::new();
    for worker in 0..CONCURRENCY {
        let (client, urls, done, stop) = (client.clone(), urls.clone(), done.clone(), stop.clone());
        tasks.push(tokio::spawn(async move {
            let mut i = worker;
            while !stop.load(Ordering::Relaxed) {
                let url = &urls[i % urls.len()];
                let response = client.get(url).send().await.expect("request");
                assert!(
                    response.status().is_success(),
                    "{url}: {}",
                    response.status()
                );
                response.bytes().await.expect("body");
                done.fetch_add(1, Ordering::Relaxed);
                i += CONCURRENCY;
            }
        }));
    }
    tokio::time::sleep(Duration::from_secs_f64(seconds)).await;
    stop.store(true, Ordering::Relaxed);
    for t in tasks {
        t.await.expect("worker");
    }
    done.load(Ordering::Relaxed) as f64 / started.elapsed().as_secs_f64()
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let seconds = args
        .iter()
        .position(|a| a == "--seconds")
        .and_then(|i| args.get(i + 1))
        .and_then(|s| s.parse().ok())
        .unwrap_or(3.0);
    let fixture = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures/jacksboro/jacksboro_fault_dem.png");
    let mut inputs = vec![("jacksboro", fixture)];
    match std::env::var_os("TERRAIN_DATA_DIR") {
        Some(kit) => {
            let kit = std::path::PathBuf::from(kit);
            inputs.push((
                "mt_rainier_90m",
                kit.join("srtm_geotiff/mt_rainier_90m.tif"),
            ));
            inputs.push((
                "himalaya_4097",
                kit.join("himalaya_4097/g10g_himalaya_4097.png"),
            ));
        }
        None => println!("note: TERRAIN_DATA_DIR not set: jacksboro only"),
    }
    println!(
        "machine: {} ({} cores); {CONCURRENCY} requests at once for {seconds} s per route, loopback",
        cpu_model(),
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    for (name, input) in inputs {
        let tmp = tempfile::tempdir().expect("tempdir");
        let options = BuildOptions {
            web: true,
            ..BuildOptions::new(&input, tmp.path().join("db"))
        };
        let report = build(&options, &|_, _| {}, &AtomicBool::new(false))
            .unwrap_or_else(|e| panic!("{}: {e}", input.display()));
        let db = TileDb::open(&report.out, Verify::SizesOnly).expect("opens");
        let m = db.manifest();
        let info = m.web.as_ref().expect("georeferenced: web tiles");
        let samples = f64::from(m.raster.width) * f64::from(m.raster.height);
        let level0: Vec<u64> = m.levels[0].tiles.iter().map(|t| t.bytes).collect();
        let ours = level0.iter().sum::<u64>() as f64;
        let placement =
            terrain_server::web::crs::Placement::new(m.georeference.as_ref()).expect("placement");
        // Share of a tile's rectangle on the terrain, from a 16x16 grid of points.
        let on_terrain = |rect: [f64; 4], mercator: bool| -> f64 {
            let mut inside = 0;
            for j in 0..16 {
                for i in 0..16 {
                    let fx = (f64::from(i) + 0.5) / 16.0;
                    let fy = (f64::from(j) + 0.5) / 16.0;
                    let lon = rect[0] + (rect[2] - rect[0]) * fx;
                    let lat = if mercator {
                        let (ys, yn) = (merc_y(rect[1]), merc_y(rect[3]));
                        inv_merc_y(yn + (ys - yn) * fy)
                    } else {
                        rect[3] + (rect[1] - rect[3]) * fy
                    };
                    let (c, r) = placement.to_sample(lon, lat).expect("projects");
                    if c >= 0.0
                        && r >= 0.0
                        && c <= f64::from(m.raster.width - 1)
                        && r <= f64::from(m.raster.height - 1)
                    {
                        inside += 1;
                    }
                }
            }
            f64::from(inside) / 256.0
        };
        let mut rows = Vec::new();
        let mut urls_of = |kind: Kind| -> Vec<String> {
            let finest = match kind {
                Kind::QuantizedMesh => info.cesium_max_level,
                _ => info.xyz_max_zoom,
            };
            let (mut bytes, mut covered, mut tiles) = (0u64, 0.0f64, 0usize);
            let mut urls = Vec::new();
            for (e, blob) in db.web_tiles().filter(|(e, _)| e.kind == kind) {
                urls.push(*e);
                if e.z != finest {
                    continue;
                }
                let rect = match kind {
                    Kind::QuantizedMesh => {
                        let d = 180.0 / f64::from(1u32 << e.z);
                        [
                            -180.0 + f64::from(e.x) * d,
                            -90.0 + f64::from(e.y) * d,
                            -180.0 + f64::from(e.x + 1) * d,
                            -90.0 + f64::from(e.y + 1) * d,
                        ]
                    }
                    _ => {
                        let n = f64::from(1u32 << e.z);
                        let lon = |x: u32| f64::from(x) / n * 360.0 - 180.0;
                        let lat = |y: u32| {
                            (std::f64::consts::PI * (1.0 - 2.0 * f64::from(y) / n))
                                .sinh()
                                .atan()
                                .to_degrees()
                        };
                        [lon(e.x), lat(e.y + 1), lon(e.x + 1), lat(e.y)]
                    }
                };
                let share = on_terrain(rect, kind != Kind::QuantizedMesh);
                bytes += blob.bytes.len() as u64;
                covered += blob.bytes.len() as f64 * share;
                tiles += 1;
            }
            rows.push(format!(
                "  {:<26} {:>6} tiles {:>9.0} B/tile {:>7.3} B/sample ({:.2}x ours)",
                format!("{kind:?} (zoom/level {finest})"),
                tiles,
                bytes as f64 / tiles.max(1) as f64,
                covered / samples,
                covered / ours
            ));
            urls.sort();
            urls.into_iter()
                .map(|e| terrain_server::http::web::tile_path(&m.content_version, e))
                .collect()
        };
        let terrarium = urls_of(Kind::Terrarium);
        urls_of(Kind::TerrainRgb);
        let meshes = urls_of(Kind::QuantizedMesh);
        println!(
            "\n{name}: {} x {} samples, {} level-0 tiles\n  {:<26} {:>6} tiles {:>9.0} B/tile {:>7.3} B/sample",
            m.raster.width,
            m.raster.height,
            level0.len(),
            "ours: tile blobs (level 0)",
            level0.len(),
            ours / level0.len() as f64,
            ours / samples
        );
        for row in &rows {
            println!("{row}");
        }
        let native: Vec<String> = m
            .tiles()
            .map(|(id, _)| terrain_shared::routes::heights(&m.content_version, id))
            .collect();
        drop(db);
        let server = TestServer::start(&report.out);
        let base = server.base_url().to_string();
        let full = |paths: Vec<String>| {
            Arc::new(
                paths
                    .into_iter()
                    .map(|p| format!("{base}{p}"))
                    .collect::<Vec<_>>(),
            )
        };
        let (native, terrarium, meshes) = (full(native), full(terrarium), full(meshes));
        let (r_native, r_terrarium, r_mesh) = runtime.block_on(async {
            rate(native.clone(), 0.5).await; // warm-up
            (
                rate(native, seconds).await,
                rate(terrarium, seconds).await,
                rate(meshes, seconds).await,
            )
        });
        println!(
            "  requests/s: native tile blobs {r_native:.0}; Terrarium PNGs {r_terrarium:.0} ({:.2}x); quantized-mesh {r_mesh:.0} ({:.2}x)",
            r_terrarium / r_native,
            r_mesh / r_native
        );
    }
}

fn merc_y(lat: f64) -> f64 {
    let lat = lat.to_radians();
    (lat.tan() + 1.0 / lat.cos()).ln()
}

fn inv_merc_y(y: f64) -> f64 {
    y.sinh().atan().to_degrees()
}
