//! Headless flights against a real server: the square converges, and the flight's own CSV
//! shows the pager's invariants held on every frame.

use std::path::Path;
use std::sync::atomic::AtomicBool;
use terrain_client::flight::{CSV_HEADER, FlightArgs, fly};
use terrain_client::memory::MemorySize;
use terrain_server::build::{BuildOptions, build};
use terrain_shared::{Manifest, TileId};
use terrain_tests::data::jacksboro;
use terrain_tests::server::TestServer;

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread().enable_all().build().expect("tokio runtime")
}

fn args(server: &TestServer, out: &Path, memory: Option<u64>) -> FlightArgs {
    FlightArgs {
        server: server.base_url().to_string(),
        flight: None,
        memory: memory.map(MemorySize),
        limit_percent: 90.0,
        out: out.to_path_buf(),
        fps: 30.0,
        concurrency: 4,
        no_nearest_when_outside: false,
        quiet: true,
    }
}

/// `flight.csv` as rows of named columns.
fn read_csv(path: &Path) -> Vec<std::collections::HashMap<String, String>> {
    let text = std::fs::read_to_string(path).expect("flight.csv");
    let mut lines = text.lines();
    let header: Vec<String> = lines.next().expect("header").split(',').map(str::to_string).collect();
    assert_eq!(header.join(","), CSV_HEADER);
    lines.map(|l| header.iter().cloned().zip(l.split(',').map(str::to_string)).collect()).collect()
}

fn number(row: &std::collections::HashMap<String, String>, column: &str) -> u64 {
    row[column].parse().unwrap_or_else(|e| panic!("{column} = {:?}: {e}", row[column]))
}

/// Bytes the client holds for a resident tile: compressed heights, decoded codes (4 bytes
/// each) and the coarsest texture level.
fn tile_bytes(manifest: &Manifest, id: TileId) -> u64 {
    let record = manifest.tile(id).expect("in grid");
    record.heights.bytes + 4 * u64::from(manifest.tile_size).pow(2) + record.texture[0].bytes
}

/// The largest bytes of any belt around any tile: the most the pager may overspend.
fn largest_belt_bytes(manifest: &Manifest) -> u64 {
    let mut largest = 0;
    for current in manifest.tiles.iter().map(|t| t.id()) {
        for belt in 0..manifest.grid.columns.max(manifest.grid.rows) {
            let bytes: u64 = manifest.tiles.iter().map(|t| t.id()).filter(|t| t.belt_distance(current) == belt).map(|t| tile_bytes(manifest, t)).sum();
            largest = largest.max(bytes);
        }
    }
    largest
}

fn jacksboro_server(dir: &Path) -> (TestServer, Manifest) {
    let report = build(&BuildOptions::new(jacksboro(), dir.join("db")), &|_, _| {}, &AtomicBool::new(false)).expect("builds");
    (TestServer::start(&report.out), report.manifest)
}

#[test]
fn a_flight_over_jacksboro_with_ample_memory_converges_to_the_whole_grid() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (server, manifest) = jacksboro_server(tmp.path());
    let out = tmp.path().join("flight");
    let summary = runtime().block_on(fly(&args(&server, &out, Some(64 << 20)))).expect("flight");
    let rows = read_csv(&summary.csv);
    assert_eq!(rows.len() as u64, summary.frames);
    let last = rows.last().expect("frames");
    // The default path ends still over the centre, tile (1, 1) of the 4 x 3 grid: three
    // belts reach every tile.
    assert_eq!((number(last, "current_x"), number(last, "current_y")), (1, 1));
    assert_eq!(number(last, "complete_belts"), 3);
    assert_eq!(number(last, "resident_tiles"), manifest.tiles.len() as u64);
    assert_eq!(number(last, "in_flight"), 0);
    let all: u64 = manifest.tiles.iter().map(|t| tile_bytes(&manifest, t.id())).sum();
    assert_eq!(number(last, "resident_bytes"), all, "resident bytes are exactly what the tiles hold");
    assert_eq!(number(last, "evicted_unused_bytes"), 0, "nothing is evicted under an ample budget");
    assert!(summary.chart.exists());
    let chart = image::open(&summary.chart).expect("flight.png is an image");
    assert!(chart.width() >= 800 && chart.height() >= 600);
}

#[test]
fn a_tight_budget_keeps_resident_bytes_within_one_belt_of_the_limit_on_every_frame() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (server, manifest) = jacksboro_server(tmp.path());
    let one_tile = tile_bytes(&manifest, TileId::new(0, 0));
    // Room for about three tiles: less than the nine of a full second belt.
    let budget = one_tile * 3 * 10 / 9;
    let summary = runtime().block_on(fly(&args(&server, &tmp.path().join("flight"), Some(budget)))).expect("flight");
    let rows = read_csv(&summary.csv);
    let slack = largest_belt_bytes(&manifest);
    let mut evicted_at_some_point = false;
    let mut previous_resident = 0;
    for row in &rows {
        let (resident, limit) = (number(row, "resident_bytes"), number(row, "memory_limit_bytes"));
        assert!(resident <= limit + slack, "frame {}: {resident} bytes against a limit of {limit} + {slack}", row["frame"]);
        evicted_at_some_point |= resident < previous_resident;
        previous_resident = resident;
    }
    assert!(evicted_at_some_point, "a lap over the terrain with room for three tiles must evict");
    let last = rows.last().expect("frames");
    assert_eq!(number(last, "in_flight"), 0, "the still end converges");
    assert!(number(last, "complete_belts") >= 1, "the current tile is always kept");
    assert!(number(last, "resident_tiles") < manifest.tiles.len() as u64);
}

#[test]
fn a_flight_against_a_wrong_url_says_why() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (server, _) = jacksboro_server(tmp.path());
    let mut wrong = args(&server, &tmp.path().join("flight"), Some(64 << 20));
    wrong.server = format!("{}/no/such/prefix", server.base_url());
    let error = runtime().block_on(fly(&wrong)).expect_err("no manifest there");
    let message = error.to_string();
    assert!(message.contains("404") && message.contains("manifest.json"), "{message}");
}
