//! The pyramid of levels end to end: the manifest stays small whatever the number of tiles,
//! and a scene pages every level as the strip-mask paper's Algorithm 1 within the level's
//! share of one memory limit.

use std::sync::atomic::AtomicBool;
use std::time::Duration;
use terrain_client::page;
use terrain_server::build::{BuildOptions, build};
use terrain_tests::data::{jacksboro, kit_file};
use terrain_tests::server::TestServer;

/// What the manifest may cost a client per tile of every level, gzipped as sent.
const MAX_MANIFEST_BYTES_PER_TILE: f64 = 96.0;

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime")
}

/// Builds `heights` into `dir` with tiles of `tile_size` and serves it.
fn serve(heights: &std::path::Path, dir: &std::path::Path, tile_size: u32) -> TestServer {
    let mut options = BuildOptions::new(heights, dir.join("db"));
    options.tile_size = tile_size;
    let report = build(&options, &|_, _| {}, &AtomicBool::new(false)).expect("builds");
    TestServer::start(&report.out)
}

/// The manifest as the server sends it to a client that accepts gzip, per tile.
fn manifest_bytes_per_tile(server: &TestServer) -> (usize, usize, f64) {
    let db = server.state().db();
    let tiles = db.manifest().tile_count();
    let sent = db.manifest_gzip().len();
    (sent, tiles, sent as f64 / tiles as f64)
}

#[test]
fn the_manifest_sends_at_most_96_bytes_a_tile_gzipped() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut checked = vec![(
        "jacksboro, tiles of 33",
        serve(&jacksboro(), &tmp.path().join("j"), 33),
    )];
    if let Some(himalaya) = kit_file("manifest size", "himalaya_4097/g10g_himalaya_4097.png") {
        checked.push((
            "himalaya_4097",
            serve(&himalaya, &tmp.path().join("h"), 129),
        ));
    }
    for (name, server) in &checked {
        let (sent, tiles, per_tile) = manifest_bytes_per_tile(server);
        eprintln!(
            "{name}: manifest {sent} bytes gzipped for {tiles} tiles: {per_tile:.1} bytes a tile"
        );
        assert!(
            per_tile <= MAX_MANIFEST_BYTES_PER_TILE,
            "{name}: {per_tile:.1} bytes a tile ({sent} for {tiles})"
        );
        assert!(
            server.state().db().manifest().level_count() > 1,
            "{name}: a pyramid"
        );
    }
}

#[test]
fn every_level_pages_a_square_of_complete_belts_around_its_tile_and_the_sum_stays_under_the_limit()
{
    let tmp = tempfile::tempdir().expect("tempdir");
    // Tiles of 33 samples: 13 x 11 at level 0, then 7 x 6, 4 x 3, 2 x 2 and one tile.
    let server = serve(&jacksboro(), tmp.path(), 33);
    let runtime = runtime();
    let connection = terrain_tests::connect(&runtime, server.base_url());
    let manifest = std::sync::Arc::clone(&connection.manifest);
    assert_eq!(manifest.level_count(), 5);
    // Room for the coarsest tile and about ten tiles on each other level: every level is
    // paged, and the limit binds on the finer ones.
    let (_, largest) = connection
        .scene(u64::MAX, true, None)
        .largest_tile()
        .expect("tiles");
    let limit = 45 * largest;
    let mut scene = connection.scene(limit, true, None);
    let mut fetcher = connection.fetcher;
    let [w, h] = manifest.extent_m;
    let mut complete = vec![0u32; 5];
    for frame in 0..240u64 {
        // West to east across the middle, then still.
        let f = (frame as f64 / 160.0).min(1.0);
        let position = [(0.1 + 0.8 * f) * w, 0.5 * h, 2000.0];
        std::thread::sleep(Duration::from_millis(4));
        let update = scene.update(&mut fetcher, frame, position).expect("update");
        assert_eq!(update.levels.len(), 5, "frame {frame}: every level paged");
        let shares: u64 = update.levels.iter().map(|l| l.pager.memory_limit).sum();
        assert!(
            shares <= limit,
            "frame {frame}: shares {shares} over the limit {limit}"
        );
        for level in &update.levels {
            let (k, d) = (level.level, &level.decision);
            // Counted from the tile of this level under the viewpoint.
            let extent = (f64::from(manifest.tile_size - 1)) * f64::from(1u32 << k);
            let viewpoint = [
                position[0] / (extent * manifest.spacing_m[0]),
                position[1] / (extent * manifest.spacing_m[1]),
            ];
            assert_eq!(
                d.current,
                page::current_tile(&level.pager, viewpoint),
                "frame {frame} level {k}: belts counted from another tile"
            );
            // The square of complete belts is resident, every tile of it.
            for id in page::square_tiles(&level.pager, d.current, d.complete_belts) {
                assert!(
                    scene.is_resident(id.with_level(k)),
                    "frame {frame} level {k}: tile {id} of the square of {} belts is not resident",
                    d.complete_belts
                );
            }
            complete[k as usize] = d.complete_belts;
        }
        assert!(
            scene.resident_bytes() <= limit,
            "frame {frame}: {} bytes resident, limit {limit}",
            scene.resident_bytes()
        );
    }
    // At rest: every level holds at least its own tile's belt; the coarsest level is whole;
    // the limit kept level 0 from holding everything.
    assert!(
        complete.iter().all(|&c| c >= 1),
        "complete belts per level: {complete:?}"
    );
    let level0 = manifest.grid(0);
    let resident0 = (0..level0.rows)
        .flat_map(|y| (0..level0.columns).map(move |x| terrain_shared::TileId::new(x, y)))
        .filter(|&id| scene.is_resident(id))
        .count();
    assert!(
        resident0 < (level0.columns * level0.rows) as usize,
        "level 0 whole: the limit does not bind"
    );
    assert!(
        scene.is_resident(terrain_shared::TileId::at(4, 0, 0)),
        "the coarsest tile"
    );
}
