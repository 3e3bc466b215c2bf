//! Headless flights against a real server: the square converges, and the flight's own CSV
//! shows the pager's invariants held on every frame.

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::time::Duration;
use terrain_client::flight::{CSV_HEADER, FlightArgs, FlightError, StreamArgs, fly};
use terrain_client::memory::MemorySize;
use terrain_client::requests::FetcherConfig;
use terrain_client::scene::Scene;
use terrain_server::build::{BuildOptions, build};
use terrain_shared::{Manifest, TileId};
use terrain_tests::data::{budget_for_level_0_tiles, build_jacksboro, jacksboro, tile_bytes};
use terrain_tests::proxy::{Fault, FaultPlan, FaultyProxy};
use terrain_tests::server::{RestartableServer, TestServer};

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime")
}

/// A paging-only flight (no GPU) over the default path, each frame as soon as a request
/// finishes (`fly --no-wait`): the same frames as a flight paced in wall-clock time, in the
/// time the server takes.
fn paging_flight(server: &str, out: &Path, memory: Option<u64>) -> FlightArgs {
    let mut stream = StreamArgs::new(server, memory.map(MemorySize));
    stream.concurrency = 4;
    FlightArgs {
        no_render: true,
        no_wait: true,
        ..FlightArgs::new(stream, out)
    }
}

/// [`paging_flight`] paced at its frame rate in wall-clock time, for a test that does
/// something to the server at a moment of the flight (an outage, a rebuild) or that needs
/// the pager's wall-clock wait before a failed tile is asked for again.
fn paced_paging_flight(server: &str, out: &Path, memory: Option<u64>) -> FlightArgs {
    FlightArgs {
        no_wait: false,
        ..paging_flight(server, out, memory)
    }
}

fn args(server: &TestServer, out: &Path, memory: Option<u64>) -> FlightArgs {
    paging_flight(server.base_url(), out, memory)
}

/// `flight.csv` as rows of named columns.
fn read_csv(path: &Path) -> Vec<std::collections::HashMap<String, String>> {
    let text = std::fs::read_to_string(path).expect("flight.csv");
    let mut lines = text.lines();
    let header: Vec<String> = lines
        .next()
        .expect("header")
        .split(',')
        .map(str::to_string)
        .collect();
    assert_eq!(header.join(","), CSV_HEADER);
    lines
        .map(|l| {
            header
                .iter()
                .cloned()
                .zip(l.split(',').map(str::to_string))
                .collect()
        })
        .collect()
}

fn number(row: &std::collections::HashMap<String, String>, column: &str) -> u64 {
    row[column]
        .parse()
        .unwrap_or_else(|e| panic!("{column} = {:?}: {e}", row[column]))
}

fn jacksboro_server(dir: &Path) -> (TestServer, Manifest) {
    let report = build_jacksboro(dir);
    (TestServer::start(&report.out), report.manifest)
}

#[test]
fn a_flight_over_jacksboro_with_ample_memory_converges_to_the_whole_pyramid() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (server, manifest) = jacksboro_server(tmp.path());
    let out = tmp.path().join("flight");
    let summary = runtime()
        .block_on(fly(&args(&server, &out, Some(64 << 20))))
        .expect("flight");
    let rows = read_csv(&summary.csv);
    assert_eq!(rows.len() as u64, summary.frames);
    let last = rows.last().expect("frames");
    // The default path ends still over the centre, tile (1, 1) of level 0's 4 x 3 grid:
    // three belts reach every tile. Every tile of the levels above is resident too.
    assert_eq!(
        (number(last, "current_x"), number(last, "current_y")),
        (1, 1)
    );
    assert_eq!(number(last, "complete_belts"), 3);
    assert!(manifest.level_count() > 1);
    assert_eq!(number(last, "resident_tiles"), manifest.tile_count() as u64);
    assert_eq!(number(last, "in_flight"), 0);
    let all: u64 = manifest
        .tiles()
        .map(|(id, _)| tile_bytes(&manifest, id))
        .sum();
    assert_eq!(
        number(last, "resident_bytes"),
        all,
        "resident bytes are exactly what the tiles hold"
    );
    assert_eq!(
        number(last, "evicted_unused_bytes"),
        0,
        "nothing is evicted under an ample budget"
    );
    // The ground under the viewpoint comes from the resident tile's decoded heights: the
    // source raster's nearest sample.
    let (width, _, codes) = terrain_tests::data::png_codes(&jacksboro());
    let metres = |column: &str| last[column].parse::<f64>().expect("a number");
    let (sx, sy) = (
        (metres("x_m") / manifest.spacing_m[0]).round() as u32,
        (metres("y_m") / manifest.spacing_m[1]).round() as u32,
    );
    assert_eq!(
        metres("ground_m"),
        f64::from(codes[(sy * width + sx) as usize])
    );
    assert_eq!(summary.charts.len(), 1, "no render chart without rendering");
    let chart = image::open(&summary.charts[0]).expect("flight.png is an image");
    assert!(chart.width() >= 800 && chart.height() >= 600);
}

/// `fly --no-wait` flies the frames a flight paced in wall-clock time flies: the same
/// count, each at the same place of the path, and it converges as that one does.
#[test]
fn a_flight_without_waiting_flies_the_frames_of_a_paced_one() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (server, manifest) = jacksboro_server(tmp.path());
    let fly_to = |name: &str, args: FlightArgs| {
        let summary = runtime().block_on(fly(&args)).expect("flight");
        let rows = read_csv(&summary.csv);
        let last = rows.last().expect("frames");
        println!("{name}: {} frames in {} s", rows.len(), last["wall_s"]);
        assert_eq!(
            number(last, "resident_tiles"),
            manifest.tile_count() as u64,
            "{name}"
        );
        assert_eq!(number(last, "in_flight"), 0, "{name}");
        rows
    };
    let limit = Some(64 << 20);
    let paced = fly_to(
        "paced",
        paced_paging_flight(server.base_url(), &tmp.path().join("paced"), limit),
    );
    let quick = fly_to(
        "no wait",
        paging_flight(server.base_url(), &tmp.path().join("quick"), limit),
    );
    assert_eq!(quick.len(), paced.len());
    for (q, p) in quick.iter().zip(&paced) {
        for column in ["frame", "x_m", "y_m", "current_x", "current_y"] {
            assert_eq!(q[column], p[column], "{column} at frame {}", p["frame"]);
        }
    }
}

#[test]
fn a_tight_budget_keeps_resident_bytes_under_the_limit_on_every_frame() {
    tight_budget_flight(false);
}

#[test]
fn a_single_level_flight_on_a_tight_budget_keeps_resident_bytes_under_the_limit_on_every_frame() {
    tight_budget_flight(true);
}

/// A lap with room for about three tiles of level 0 (less than the nine of a full second
/// belt): paging every level (the coarser levels with room for all their tiles, so that
/// level 0 alone is tight), or level 0 alone (`--single-level`, the paper's client).
fn tight_budget_flight(single_level: bool) {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (server, manifest) = jacksboro_server(tmp.path());
    let budget = if single_level {
        tile_bytes(&manifest, TileId::new(0, 0)) * 3 * 10 / 9
    } else {
        budget_for_level_0_tiles(&manifest, 3)
    };
    let mut flight = args(&server, &tmp.path().join("flight"), Some(budget));
    flight.stream.single_level = single_level;
    let summary = runtime().block_on(fly(&flight)).expect("flight");
    let rows = read_csv(&summary.csv);
    // The pager knows each tile's bytes from the manifest and starts a belt, the current
    // tile's included, only if it fits: not a byte over.
    assert_eq!(summary.frames_over_limit, 0, "{summary}");
    let mut evicted_at_some_point = false;
    let mut previous_resident = 0;
    for row in &rows {
        let (resident, limit) = (
            number(row, "resident_bytes"),
            number(row, "memory_limit_bytes"),
        );
        assert!(
            resident <= limit,
            "frame {}: {resident} bytes against a limit of {limit}",
            row["frame"]
        );
        evicted_at_some_point |= resident < previous_resident;
        previous_resident = resident;
    }
    assert!(
        evicted_at_some_point,
        "a lap over the terrain with room for three tiles must evict"
    );
    let last = rows.last().expect("frames");
    assert_eq!(number(last, "in_flight"), 0, "the still end converges");
    assert!(
        number(last, "complete_belts") >= 1,
        "the current tile is always kept"
    );
    let paged = if single_level {
        manifest.levels[0].tiles.len()
    } else {
        manifest.tile_count()
    };
    assert!(number(last, "resident_tiles") < paged as u64);
}

#[test]
fn a_flight_against_a_wrong_url_says_why() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (server, _) = jacksboro_server(tmp.path());
    let mut wrong = args(&server, &tmp.path().join("flight"), Some(64 << 20));
    wrong.stream.server = format!("{}/no/such/prefix", server.base_url());
    let error = runtime()
        .block_on(fly(&wrong))
        .expect_err("no manifest there");
    let message = error.to_string();
    assert!(
        message.contains("404") && message.contains("manifest.json"),
        "{message}"
    );
}

#[test]
fn a_server_stopped_mid_flight_and_started_again_is_recovered_from() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_jacksboro(tmp.path());
    let mut server = RestartableServer::start(&report.out);
    // Room for ten of level 0's twelve tiles: the square can reach two belts (nine tiles)
    // but not the whole grid, so the lap keeps fetching and evicting all along.
    let args = paced_paging_flight(
        &server.base_url(),
        &tmp.path().join("flight"),
        Some(budget_for_level_0_tiles(&report.manifest, 10)),
    );
    let flight = std::thread::spawn(move || runtime().block_on(fly(&args)));
    // Down from 0.5 s to 3.5 s of the 12 s lap: the pager fetches several times in between
    // (each time the viewpoint enters a new tile), so requests meet the outage.
    std::thread::sleep(std::time::Duration::from_millis(500));
    server.stop();
    std::thread::sleep(std::time::Duration::from_millis(3000));
    server.restart();
    let summary = flight
        .join()
        .expect("flight thread")
        .expect("the flight survives the outage");
    let rows = read_csv(&summary.csv);
    let last = rows.last().expect("frames");
    assert!(
        summary.retries > 0,
        "requests during the outage were retried"
    );
    assert_eq!(
        number(last, "in_flight"),
        0,
        "everything asked for after the restart arrived"
    );
    assert!(
        number(last, "complete_belts") >= 2,
        "the square was rebuilt after the outage"
    );
    let downloaded_at = |wall_s: f64| {
        rows.iter()
            .find(|r| r["wall_s"].parse::<f64>().unwrap_or(0.0) >= wall_s)
            .map_or(0, |r| number(r, "bytes_downloaded"))
    };
    assert!(
        number(last, "bytes_downloaded") > downloaded_at(4.0),
        "tiles arrived after the restart"
    );
    // Tiles whose retries ran out during the outage were asked for again by the pager; what
    // arrived is intact, since the fetcher delivers only bodies matching the manifest's
    // hashes (the fetcher tests compare them tile by tile across the same kind of outage).
}

#[test]
fn a_himalaya_flight_in_32_mib_keeps_resident_tiles_under_the_limit_every_frame() {
    let Some(heights) =
        terrain_tests::data::kit_file("himalaya flight", "himalaya_4097/g10g_himalaya_4097.png")
    else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let db =
        terrain_tests::fixtures::database(&heights, terrain_tests::fixtures::Options::Defaults);
    let server = TestServer::start(&db);
    let mut flight = args(&server, &tmp.path().join("flight"), Some(32 << 20));
    flight.stream.concurrency = 8;
    let summary = runtime().block_on(fly(&flight)).expect("flight");
    let rows = read_csv(&summary.csv);
    let limit = (32u64 << 20) * 9 / 10;
    for row in &rows {
        assert_eq!(number(row, "memory_limit_bytes"), limit);
        assert!(
            number(row, "resident_bytes") <= limit,
            "frame {}: {} bytes resident",
            row["frame"],
            row["resident_bytes"]
        );
    }
    // The square is far larger than one belt, and the budget is what stops it: the whole
    // pyramid (1365 tiles of about 67 KiB) would need about 90 MiB.
    let last = rows.last().expect("frames");
    assert!(
        number(last, "complete_belts") >= 5,
        "{} complete belts",
        last["complete_belts"]
    );
    assert_eq!(server.state().db().manifest().tile_count(), 1365);
    assert!(number(last, "resident_tiles") < 1365);
    assert!(
        summary.peak_resident_bytes > limit / 2,
        "the flight used its budget"
    );
}

// ---- hostile servers and links ----

/// The jacksboro database built into `dir/name` with `tile_size` and heights offset by
/// `offset_m` (a different offset makes every heights blob, and the content version, new).
fn jacksboro_db(dir: &Path, name: &str, tile_size: u32, offset_m: f64) -> Manifest {
    let mut options = BuildOptions::new(jacksboro(), dir.join(name));
    options.tile_size = tile_size;
    options.height_offset = Some(offset_m);
    build(&options, &|_, _| {}, &AtomicBool::new(false))
        .expect("jacksboro builds")
        .manifest
}

#[test]
fn a_manifest_answered_500_cut_short_or_corrupt_once_is_fetched_again() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (server, manifest) = jacksboro_server(tmp.path());
    let runtime = runtime();
    for fault in [Fault::ServerError, Fault::Truncate, Fault::Corrupt] {
        let plan = FaultPlan::rotation(&[fault])
            .only_paths_containing("manifest.json")
            .at_most_per_path(1);
        let proxy = FaultyProxy::start(server.addr(), plan);
        let config = FetcherConfig {
            backoff_base: Duration::from_millis(10),
            ..FetcherConfig::default()
        };
        let connection = runtime
            .block_on(Scene::connect(
                proxy.base_url(),
                config,
                runtime.handle().clone(),
            ))
            .unwrap_or_else(|e| panic!("{fault:?} once: {}", e.chain()));
        assert_eq!(*connection.manifest, manifest, "{fault:?}");
        let stats = proxy.stats();
        let faulted = stats.server_errors + stats.truncated + stats.corrupted;
        assert_eq!(
            (faulted, stats.connections),
            (1, 2),
            "{fault:?}: one faulted answer, one good one: {stats:?}"
        );
    }
}

#[test]
fn a_flight_over_a_link_with_2_s_a_request_still_loads_tiles() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (server, manifest) = jacksboro_server(tmp.path());
    let proxy = FaultyProxy::start(
        server.addr(),
        FaultPlan::pass_through().with_delay(Duration::from_secs(2)),
    );
    let summary = runtime()
        .block_on(fly(&paging_flight(
            proxy.base_url(),
            &tmp.path().join("flight"),
            Some(64 << 20),
        )))
        .unwrap_or_else(|e| panic!("{e}"));
    let rows = read_csv(&summary.csv);
    let last = rows.last().expect("frames");
    // The lap crosses a tile every half second; a tile takes 2 s. Requests that the square
    // would hold anyway are kept in flight, so they land.
    assert!(
        summary.tiles_fetched >= 4,
        "{} tiles fetched",
        summary.tiles_fetched
    );
    assert!(
        number(last, "complete_belts") >= 1,
        "the current tile is held at the end"
    );
    assert!(number(last, "resident_tiles") <= manifest.tile_count() as u64);
}

#[test]
fn a_flight_that_loads_nothing_says_so_fails_and_still_writes_its_outputs() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (server, _) = jacksboro_server(tmp.path());
    // Every tile request is reset; the manifest passes.
    let proxy = FaultyProxy::start(
        server.addr(),
        FaultPlan::rotation(&[Fault::Reset]).only_paths_containing("/tiles/"),
    );
    let out = tmp.path().join("flight");
    let error = runtime()
        .block_on(fly(&paging_flight(proxy.base_url(), &out, Some(64 << 20))))
        .expect_err("nothing can arrive");
    let message = error.to_string();
    assert!(
        matches!(error, FlightError::NothingLoaded { .. }),
        "{message}"
    );
    assert!(message.contains("no tile arrived"), "{message}");
    assert!(out.join("flight.csv").exists() && out.join("flight.png").exists());
}

#[test]
fn a_tile_corrupt_at_its_source_is_given_up_after_a_bounded_number_of_requests() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_jacksboro(tmp.path());
    let manifest = report.manifest;
    // Flip a byte in the middle of tile (1, 1)'s blob, as a disk would; the server (opened
    // checking sizes only, as `serve --no-verify`) serves it as it is.
    let bad = TileId::new(1, 1);
    let pack = report.out.join(terrain_server::db::HEIGHTS_PACK);
    let mut bytes = std::fs::read(&pack).expect("heights.pack");
    let offset: u64 = manifest
        .tiles()
        .take_while(|(id, _)| *id != bad)
        .map(|(_, t)| t.bytes)
        .sum();
    let record = manifest.tile(bad).expect("in grid");
    let blob = offset as usize..(offset + record.bytes) as usize;
    assert_eq!(
        terrain_shared::manifest::content_hash(&bytes[blob.clone()]),
        record.hash
    );
    bytes[blob.start + blob.len() / 2] ^= 0x5a;
    std::fs::write(&pack, bytes).expect("heights.pack written");
    let server = RestartableServer::start(&report.out);

    let summary = runtime()
        .block_on(fly(&paced_paging_flight(
            &server.base_url(),
            &tmp.path().join("flight"),
            Some(64 << 20),
        )))
        .expect("the flight goes on without the bad tile");
    assert_eq!(
        summary.unavailable.iter().map(|t| t.id).collect::<Vec<_>>(),
        [bad],
        "{summary}"
    );
    assert!(
        summary.unavailable[0].error.contains("content hash"),
        "{summary}"
    );
    let limit = u64::from(terrain_client::scene::TILE_REQUESTS_BEFORE_GIVING_UP);
    assert_eq!(summary.failures, limit, "{summary}");
    // Each failed request fetched the bad heights twice (one refetch); the rest is counted
    // in `retries`, as flight.csv documents.
    assert_eq!(summary.retries, limit + (limit - 1), "{summary}");
    let rows = read_csv(&summary.csv);
    assert_eq!(
        number(rows.last().expect("frames"), "retries"),
        summary.retries
    );
    let everything: u64 = manifest
        .tiles()
        .map(|(_, t)| t.bytes + t.coarsest_texture_bytes)
        .sum();
    assert!(
        summary.bytes_downloaded
            <= everything + 2 * limit * (record.bytes + record.coarsest_texture_bytes),
        "{} bytes downloaded, the tiles are {everything}",
        summary.bytes_downloaded
    );
    assert!(
        summary.to_string().contains("tile 1/1 given up"),
        "{summary}"
    );
}

/// Flies a lap with room for ten of jacksboro's twelve level-0 tiles (so it keeps
/// fetching) while the served database is replaced, after 1 s, by `rebuilt` (a directory
/// beside it).
fn fly_through_a_rebuild(tmp: &Path, rebuilt: &str) -> terrain_client::flight::FlightSummary {
    let report = build_jacksboro(tmp);
    let mut server = RestartableServer::start(&report.out);
    let args = paced_paging_flight(
        &server.base_url(),
        &tmp.join("flight"),
        Some(budget_for_level_0_tiles(&report.manifest, 10)),
    );
    let flight = std::thread::spawn(move || runtime().block_on(fly(&args)));
    std::thread::sleep(Duration::from_millis(1000));
    server.stop();
    std::fs::rename(&report.out, tmp.join("old-db")).expect("old database moved away");
    std::fs::rename(tmp.join(rebuilt), &report.out).expect("new database moved in");
    server.restart();
    flight
        .join()
        .expect("flight thread")
        .unwrap_or_else(|e| panic!("the flight goes on through the rebuild: {e}"))
}

#[test]
fn a_database_rebuilt_mid_flight_with_the_same_grid_is_reloaded_and_the_flight_goes_on() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let rebuilt = jacksboro_db(
        tmp.path(),
        "rebuilt",
        terrain_server::build::DEFAULT_TILE_SIZE,
        1.0,
    );
    let summary = fly_through_a_rebuild(tmp.path(), "rebuilt");
    let [change] = summary.content_changes.as_slice() else {
        panic!("one content change: {summary}");
    };
    assert_eq!(change.to, rebuilt.content_version);
    assert!(change.kept_dropped.is_some(), "the same grid: {change}");
    let rows = read_csv(&summary.csv);
    let last = rows.last().expect("frames");
    assert_eq!(number(last, "in_flight"), 0);
    assert!(
        number(last, "complete_belts") >= 2,
        "the square was rebuilt"
    );
}

#[test]
fn a_database_rebuilt_mid_flight_with_another_grid_restarts_paging_and_the_flight_goes_on() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let rebuilt = jacksboro_db(tmp.path(), "rebuilt", 65, 0.0);
    assert_eq!((rebuilt.grid(0).columns, rebuilt.grid(0).rows), (7, 6));
    let summary = fly_through_a_rebuild(tmp.path(), "rebuilt");
    let [change] = summary.content_changes.as_slice() else {
        panic!("one content change: {summary}");
    };
    assert_eq!(change.to, rebuilt.content_version);
    assert_eq!(
        change.kept_dropped, None,
        "the grid changed shape: {change}"
    );
    let rows = read_csv(&summary.csv);
    let last = rows.last().expect("frames");
    assert_eq!(number(last, "in_flight"), 0);
    // The lap ends over the centre, which is tile (3, 2) or so of the new 7 x 6 grid,
    // beyond the old 4 x 3 one.
    assert!(
        number(last, "current_x") >= 3,
        "current tile {}/{}",
        last["current_x"],
        last["current_y"]
    );
    assert!(number(last, "resident_tiles") >= 1);
}
