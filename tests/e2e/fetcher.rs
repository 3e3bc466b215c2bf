//! The [`Fetcher`] over real sockets: a real server with the jacksboro database, reached
//! directly or through a [`FaultyProxy`] that corrupts, truncates, resets and slows down
//! responses; a server stopped and started again on the same port. Every delivered tile (of
//! every level of the pyramid) is compared with the same tile fetched directly from the
//! server.

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};
use terrain_client::http_client::FetchedTile;
use terrain_client::http_client::{FetchError, TileClient};
use terrain_client::requests::{FetchEvent, Fetcher, FetcherConfig, Want};
use terrain_server::build::{BuildOptions, build};
use terrain_shared::manifest::Level;
use terrain_shared::{Manifest, TileId, routes};
use terrain_tests::data::jacksboro;
use terrain_tests::proxy::{Fault, FaultPlan, FaultyProxy};
use terrain_tests::server::{RestartableServer, TestServer};

/// Smaller than the default tiles, so the 403x344 fixture makes a 7x6 grid and three levels
/// above it (4x3, 2x2, 1x1): 59 tiles give the fault schedules many tiles to land on.
const TILE_SIZE: u32 = 65;
/// Tiles of every level of the fixture in [`TILE_SIZE`] tiles.
const TILES: u64 = 42 + 12 + 4 + 1;
/// Backoff of these tests: short, so a test with retries still takes well under a second.
const BACKOFF_BASE: Duration = Duration::from_millis(10);
const BACKOFF_MAX: Duration = Duration::from_millis(200);
/// No test should come near this; it turns a hang into a failure that shows the state.
const IDLE_TIMEOUT: Duration = Duration::from_secs(20);

#[test]
fn through_a_proxy_that_corrupts_truncates_and_resets_every_tile_still_arrives_intact() {
    let db = JacksboroDb::build();
    let server = TestServer::start(&db.dir);
    // One response in two is faulted, the three faults in turn; each URL is faulted once at
    // most, so every blob arrives on its second try at the latest.
    let plan = FaultPlan::rotation(&[
        Fault::Pass,
        Fault::Corrupt,
        Fault::Pass,
        Fault::Truncate,
        Fault::Pass,
        Fault::Reset,
    ])
    .at_most_per_path(1);
    let proxy = FaultyProxy::start(server.addr(), plan);
    let runtime = runtime();
    let reference = Reference::fetch(&runtime, server.base_url(), &db.manifest);
    let mut fetcher = fetcher(&runtime, proxy.base_url(), &db.manifest, quick_config());

    let finest = db.manifest.texture.levels - 1;
    for (priority, id) in db.ids().enumerate() {
        fetcher.request(id, Want::Tile, priority as u64);
        // Its hash, from the tile blob, is what the body is checked against.
        let blob = reference.texture_blob(id, finest);
        fetcher.request_texture(id, finest, blob, priority as u64);
    }
    let events = run_until_idle(&mut fetcher);

    let delivered = reference.check_delivered(&events);
    assert_eq!(delivered.tiles, db.ids().collect(), "every tile arrived");
    assert_eq!(delivered.levels, db.ids().map(|id| (id, finest)).collect());
    assert_eq!(delivered.failed, Vec::<TileId>::new());

    let (stats, faults) = (fetcher.stats(), proxy.stats());
    assert!(
        faults.corrupted > 0 && faults.truncated > 0 && faults.reset > 0,
        "{faults:?}"
    );
    // Each faulted response costs exactly one more try: corrupt bodies a refetch, cut or
    // reset connections a retry.
    assert_eq!(
        stats.corrupt_refetches, faults.corrupted,
        "{stats:?} {faults:?}"
    );
    assert_eq!(
        stats.retries,
        faults.truncated + faults.reset,
        "{stats:?} {faults:?}"
    );
    assert_eq!(
        stats.requests_started,
        3 * TILES + stats.retries + stats.corrupt_refetches
    );
    assert_eq!((stats.delivered, stats.failures), (2 * TILES, 0));
}

#[test]
fn a_tile_that_is_always_corrupt_is_reported_after_its_refetch_and_the_others_arrive() {
    let db = JacksboroDb::build();
    let server = TestServer::start(&db.dir);
    let bad = TileId::new(2, 1);
    let bad_path = routes::heights(&db.manifest.content_version, bad);
    let plan = FaultPlan::rotation(&[Fault::Corrupt]).only_paths_containing(&bad_path);
    let proxy = FaultyProxy::start(server.addr(), plan);
    let runtime = runtime();
    let reference = Reference::fetch(&runtime, server.base_url(), &db.manifest);
    let config = quick_config();
    let mut fetcher = fetcher(&runtime, proxy.base_url(), &db.manifest, config.clone());

    request_all_tiles(&mut fetcher, &db.manifest);
    let events = run_until_idle(&mut fetcher);

    let delivered = reference.check_delivered(&events);
    let mut others: HashSet<TileId> = db.ids().collect();
    others.remove(&bad);
    assert_eq!(delivered.tiles, others);
    assert_eq!(delivered.failed, [bad]);
    let (error, attempts) = events
        .iter()
        .find_map(|event| match event {
            FetchEvent::Failed {
                error, attempts, ..
            } => Some((error, *attempts)),
            _ => None,
        })
        .expect("a failure");
    assert_eq!(attempts, config.corrupt_attempts);
    assert!(matches!(error, FetchError::HashMismatch { .. }), "{error}");
    assert!(error.to_string().contains(&bad_path), "{error}");
    assert_eq!(proxy.stats().corrupted, u64::from(config.corrupt_attempts));
    let stats = fetcher.stats();
    assert_eq!(
        (stats.corrupt_refetches, stats.retries),
        (1, 0),
        "{stats:?}"
    );
    assert_eq!(
        (stats.delivered, stats.failures),
        (TILES - 1, 1),
        "{stats:?}"
    );
}

#[test]
fn a_server_stopped_mid_fetch_and_started_again_on_the_same_port_gets_every_tile_delivered() {
    let db = JacksboroDb::build();
    let mut server = RestartableServer::start(&db.dir);
    let runtime = runtime();
    let reference = Reference::fetch(&runtime, &server.base_url(), &db.manifest);
    // Enough tries that the backoff outlasts the outage: the caps 20, 40, ... 200 ms add
    // up to about 4 s over 30 tries, and full jitter halves that on average.
    let config = FetcherConfig {
        concurrency: 2,
        max_attempts: 30,
        backoff_base: Duration::from_millis(20),
        ..quick_config()
    };
    let mut fetcher = fetcher(&runtime, &server.base_url(), &db.manifest, config);
    request_all_tiles(&mut fetcher, &db.manifest);

    let mut events = Vec::new();
    let deadline = Instant::now() + IDLE_TIMEOUT;
    while events.len() < 5 {
        events.extend(fetcher.poll());
        assert!(Instant::now() < deadline, "no tiles before the stop");
        std::thread::sleep(Duration::from_millis(1));
    }
    // Requests start only in `poll`, so everything not yet running meets a stopped server.
    server.stop();
    let outage = Instant::now() + Duration::from_millis(300);
    while Instant::now() < outage {
        events.extend(fetcher.poll());
        std::thread::sleep(Duration::from_millis(1));
    }
    let during_outage = fetcher.stats();
    assert!(during_outage.retries > 0, "{during_outage:?}");
    server.restart();
    events.extend(run_until_idle(&mut fetcher));

    let delivered = reference.check_delivered(&events);
    assert_eq!(delivered.failed, Vec::<TileId>::new());
    assert_eq!(delivered.tiles, db.ids().collect());
}

#[test]
fn a_request_the_server_refuses_with_404_fails_at_once_with_its_reason() {
    let db = JacksboroDb::build();
    let server = TestServer::start(&db.dir);
    let runtime = runtime();
    let current = db.manifest.content_version.clone();
    let levels = db.manifest.texture.levels;

    let reference = Reference::fetch(&runtime, server.base_url(), &db.manifest);

    let mut stale = db.manifest.clone();
    stale.content_version = "0123456789abcdef".into();
    // A manifest promising one texture level more than the server has.
    let mut extra_texture_level = db.manifest.clone();
    extra_texture_level.texture.levels += 1;
    // A manifest promising one level of the pyramid more than the server has.
    let mut extra_level = db.manifest.clone();
    let last: Level = extra_level.levels.last().expect("levels").clone();
    extra_level.levels.push(last);
    let past_the_last = TileId::at(db.manifest.level_count(), 0, 0);

    struct Case<'a> {
        manifest: &'a Manifest,
        id: TileId,
        want: Want,
        /// The hash a texture level is asked with (the tile blob's entry).
        texture: Option<terrain_shared::Blob>,
        /// Parts the error's message must contain.
        message: &'a [&'a str],
        /// HTTP requests the failure costs: 0 when the manifest refused, else 1, or 2 for a
        /// tile (its heights and coarsest texture level are asked for together).
        requests: u64,
    }
    let cases = [
        Case {
            manifest: &stale,
            id: TileId::new(0, 0),
            want: Want::Tile,
            texture: None,
            message: &["404", "not served", &current],
            requests: 2,
        },
        Case {
            manifest: &stale,
            id: TileId::new(1, 0),
            want: Want::TextureLevel(1),
            texture: Some(reference.texture_blob(TileId::new(1, 0), 1)),
            message: &["404", "not served", &current],
            requests: 1,
        },
        Case {
            manifest: &stale,
            id: TileId::at(2, 1, 1),
            want: Want::Tile,
            texture: None,
            message: &["404", "not served", &current],
            requests: 2,
        },
        Case {
            manifest: &extra_texture_level,
            id: TileId::new(0, 0),
            want: Want::TextureLevel(levels),
            texture: Some(reference.texture_blob(TileId::new(0, 0), levels - 1)),
            message: &["404", &format!("not {levels}")],
            requests: 1,
        },
        Case {
            manifest: &extra_level,
            id: past_the_last,
            want: Want::Tile,
            texture: None,
            message: &[
                "404",
                &format!("level {} does not exist", past_the_last.level),
            ],
            requests: 2,
        },
        Case {
            manifest: &db.manifest,
            id: TileId::new(99, 0),
            want: Want::Tile,
            texture: None,
            message: &["not in the 7x6 grid"],
            requests: 0,
        },
        Case {
            manifest: &db.manifest,
            id: TileId::at(1, 4, 0),
            want: Want::Tile,
            texture: None,
            message: &["not in the 4x3 grid"],
            requests: 0,
        },
        Case {
            manifest: &db.manifest,
            id: past_the_last,
            want: Want::Tile,
            texture: None,
            message: &["not in the 0x0 grid"],
            requests: 0,
        },
        Case {
            manifest: &db.manifest,
            id: TileId::new(0, 0),
            want: Want::TextureLevel(levels),
            texture: Some(reference.texture_blob(TileId::new(0, 0), levels - 1)),
            message: &["texture levels 0 to"],
            requests: 0,
        },
    ];
    for case in cases {
        let mut fetcher = fetcher(&runtime, server.base_url(), case.manifest, quick_config());
        match (case.want, case.texture) {
            (Want::TextureLevel(level), Some(blob)) => {
                fetcher.request_texture(case.id, level, blob, 0)
            }
            (want, _) => fetcher.request(case.id, want, 0),
        }
        let events = run_until_idle(&mut fetcher);
        let [
            FetchEvent::Failed {
                id,
                want,
                error,
                attempts,
            },
        ] = events.as_slice()
        else {
            panic!(
                "{} {:?}: expected one failure, got {events:?}",
                case.id, case.want
            );
        };
        let message = error.to_string();
        assert_eq!(
            (*id, *want, *attempts),
            (case.id, case.want, 1),
            "{message}"
        );
        for part in case.message {
            assert!(message.contains(part), "{message:?} lacks {part:?}");
        }
        let stats = fetcher.stats();
        assert_eq!(
            (stats.requests_started, stats.retries, stats.failures),
            (case.requests, 0, 1),
            "{message}"
        );
    }
}

#[test]
fn a_texture_level_asked_for_without_its_hash_is_refused_as_corrupt() {
    let db = JacksboroDb::build();
    let server = TestServer::start(&db.dir);
    let runtime = runtime();
    let config = quick_config();
    let mut fetcher = fetcher(&runtime, server.base_url(), &db.manifest, config.clone());
    // A finer level's hash is in its tile blob: asked for without it, no body can match.
    let id = TileId::new(1, 0);
    fetcher.request(id, Want::TextureLevel(1), 0);
    let events = run_until_idle(&mut fetcher);
    let [
        FetchEvent::Failed {
            error, attempts, ..
        },
    ] = events.as_slice()
    else {
        panic!("expected one failure, got {events:?}");
    };
    // Refused as its body starts (longer than the 0 bytes a blob without a hash stands
    // for), or by its hash: corrupt either way.
    assert!(
        matches!(
            error,
            FetchError::TooLarge { .. } | FetchError::HashMismatch { .. }
        ),
        "{error}"
    );
    assert_eq!(*attempts, config.corrupt_attempts);
    // With its hash, the same level arrives.
    let reference = Reference::fetch(&runtime, server.base_url(), &db.manifest);
    fetcher.request_texture(id, 1, reference.texture_blob(id, 1), 0);
    let events = run_until_idle(&mut fetcher);
    let delivered = reference.check_delivered(&events);
    assert_eq!(delivered.levels, HashSet::from([(id, 1)]));
}

#[test]
fn cancelled_tiles_on_a_slow_link_are_never_delivered_and_the_pending_set_empties() {
    let db = JacksboroDb::build();
    let server = TestServer::start(&db.dir);
    // Level 0's 42 tiles, then one tile of level 1: the cancelling is the same at every
    // level, and the pending marks go where the manifest's dense order says.
    let ids: Vec<TileId> = db
        .ids()
        .filter(|id| id.level == 0)
        .chain([TileId::at(1, 3, 2)])
        .collect();
    assert_eq!(ids.len(), 43);
    // About 100 ms a tile on the link, so the whole grid would take about 4 s.
    let tile_bytes: u64 = ids
        .iter()
        .filter_map(|id| db.manifest.tile(*id))
        .map(|t| t.bytes + t.coarsest_texture_bytes)
        .sum();
    let per_tile = tile_bytes / ids.len() as u64;
    let proxy = FaultyProxy::start(
        server.addr(),
        FaultPlan::pass_through().with_bandwidth(per_tile * 10),
    );
    let runtime = runtime();
    let reference = Reference::fetch(&runtime, server.base_url(), &db.manifest);
    let config = FetcherConfig {
        concurrency: 1,
        ..quick_config()
    };
    let mut fetcher = fetcher(&runtime, proxy.base_url(), &db.manifest, config);
    for (priority, id) in ids.iter().enumerate() {
        fetcher.request(*id, Want::Tile, priority as u64);
    }

    let mut events = Vec::new();
    let deadline = Instant::now() + IDLE_TIMEOUT;
    while events.is_empty() {
        events.extend(fetcher.poll());
        assert!(Instant::now() < deadline, "nothing delivered");
        std::thread::sleep(Duration::from_millis(1));
    }
    assert_eq!(
        events.iter().map(FetchEvent::id).collect::<Vec<_>>(),
        [ids[0]]
    );
    // The second tile is on the link now: it is cancelled with all but two of the rest.
    assert_eq!(fetcher.running_count(), 1);
    let keep = [ids[5], ids[42]];
    let cancelled: Vec<TileId> = ids[1..]
        .iter()
        .copied()
        .filter(|id| !keep.contains(id))
        .collect();
    fetcher.cancel(&cancelled);
    let mut pending: Vec<TileId> = fetcher.pending().collect();
    pending.sort();
    assert_eq!(pending, keep);
    let mut marks = vec![true; TILES as usize];
    fetcher.mark_pending(&mut marks, &db.manifest);
    assert_eq!(marks.iter().filter(|pending| **pending).count(), 2);
    // Tile 5 of level 0, and tile (3, 2) of level 1 after level 0's 42: 42 + 2 * 4 + 3.
    assert!(marks[5] && marks[53]);
    events.extend(run_until_idle(&mut fetcher));

    let delivered = reference.check_delivered(&events);
    assert_eq!(delivered.tiles, HashSet::from([ids[0], keep[0], keep[1]]));
    assert_eq!((fetcher.pending_count(), fetcher.running_count()), (0, 0));
    let stats = fetcher.stats();
    assert_eq!(
        (stats.cancelled, stats.delivered, stats.failures),
        (40, 3, 0),
        "{stats:?}"
    );
    // The cancelled tile on the link was dropped, not downloaded to the end for nobody;
    // the other cancelled ones were never asked for.
    assert!(stats.requests_started <= 2 * 4, "{stats:?}");
    let sent = proxy.stats().bytes_sent;
    assert!(
        sent < tile_bytes / 4,
        "{sent} of {tile_bytes} bytes went over the link"
    );
}

#[test]
fn results_that_finished_before_their_cancel_are_never_delivered() {
    let db = JacksboroDb::build();
    let server = TestServer::start(&db.dir);
    let runtime = runtime();
    let mut fetcher = fetcher(&runtime, server.base_url(), &db.manifest, quick_config());
    let ids: Vec<TileId> = db.ids().filter(|id| id.level == 0).take(8).collect();
    for (priority, id) in ids.iter().enumerate() {
        fetcher.request(*id, Want::Tile, priority as u64);
    }
    assert!(
        fetcher.poll().is_empty(),
        "nothing can have finished before it started"
    );
    assert_eq!(fetcher.running_count(), 8);
    // Every body counted means every task is done with the network; the results are
    // waiting for the next poll.
    let expected: u64 = ids
        .iter()
        .filter_map(|id| db.manifest.tile(*id))
        .map(|t| t.bytes + t.coarsest_texture_bytes)
        .sum();
    let deadline = Instant::now() + IDLE_TIMEOUT;
    while fetcher.stats().bytes_downloaded < expected {
        assert!(Instant::now() < deadline, "{:?}", fetcher.stats());
        std::thread::sleep(Duration::from_millis(1));
    }
    std::thread::sleep(Duration::from_millis(100));
    fetcher.cancel(&ids);
    assert_eq!(fetcher.pending_count(), 0);
    let events = fetcher.poll();
    assert!(events.is_empty(), "{events:?}");
    let stats = fetcher.stats();
    assert_eq!((stats.cancelled, stats.delivered), (8, 0), "{stats:?}");
}

// ---- harness ----

/// The jacksboro fixture built with [`TILE_SIZE`]; deleted on drop.
struct JacksboroDb {
    _tmp: tempfile::TempDir,
    dir: PathBuf,
    manifest: Manifest,
}

impl JacksboroDb {
    fn build() -> JacksboroDb {
        let tmp = tempfile::tempdir().expect("tempdir");
        let mut options = BuildOptions::new(jacksboro(), tmp.path().join("db"));
        options.tile_size = TILE_SIZE;
        let report =
            build(&options, &|_, _| {}, &AtomicBool::new(false)).expect("jacksboro builds");
        let manifest = report.manifest;
        let grids: Vec<(u32, u32)> = (0..manifest.level_count())
            .map(|k| (manifest.grid(k).columns, manifest.grid(k).rows))
            .collect();
        assert_eq!(grids, [(7, 6), (4, 3), (2, 2), (1, 1)]);
        assert_eq!(manifest.tile_count() as u64, TILES);
        JacksboroDb {
            _tmp: tmp,
            dir: report.out,
            manifest,
        }
    }

    /// Every tile of every level, level 0 first, row-major within a level.
    fn ids(&self) -> impl Iterator<Item = TileId> + '_ {
        self.manifest.tiles().map(|(id, _)| id)
    }
}

/// The fetcher's runtime: two workers, as the servers', on a 2-core machine.
fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("tokio runtime")
}

fn quick_config() -> FetcherConfig {
    FetcherConfig {
        backoff_base: BACKOFF_BASE,
        backoff_max: BACKOFF_MAX,
        ..FetcherConfig::default()
    }
}

fn fetcher(
    runtime: &tokio::runtime::Runtime,
    base_url: &str,
    manifest: &Manifest,
    config: FetcherConfig,
) -> Fetcher {
    let client = TileClient::new(base_url).expect("client");
    Fetcher::new(
        client,
        Arc::new(manifest.clone()),
        config,
        runtime.handle().clone(),
    )
}

/// Every tile of every level, in the manifest's order (level 0 first, then row-major) as
/// the priority.
fn request_all_tiles(fetcher: &mut Fetcher, manifest: &Manifest) {
    for (priority, (id, _)) in manifest.tiles().enumerate() {
        fetcher.request(id, Want::Tile, priority as u64);
    }
}

/// Polls, as a frame loop would, until nothing is pending; everything delivered.
fn run_until_idle(fetcher: &mut Fetcher) -> Vec<FetchEvent> {
    let deadline = Instant::now() + IDLE_TIMEOUT;
    let mut events = fetcher.poll();
    while fetcher.pending_count() > 0 {
        assert!(
            Instant::now() < deadline,
            "still {} pending after {IDLE_TIMEOUT:?}: {:?}",
            fetcher.pending_count(),
            fetcher.stats()
        );
        std::thread::sleep(Duration::from_millis(1));
        events.extend(fetcher.poll());
    }
    events
}

/// Every tile's blob (decoded) and texture levels, fetched directly from the server.
struct Reference {
    tiles: HashMap<TileId, FetchedTile>,
    textures: HashMap<(TileId, u32), Vec<u8>>,
}

/// What a run delivered, checked against the [`Reference`].
#[derive(Debug)]
struct Delivered {
    tiles: HashSet<TileId>,
    levels: HashSet<(TileId, u32)>,
    failed: Vec<TileId>,
}

impl Reference {
    fn fetch(runtime: &tokio::runtime::Runtime, base_url: &str, manifest: &Manifest) -> Reference {
        let client = TileClient::new(base_url).expect("client");
        runtime.block_on(async {
            let mut tiles = HashMap::new();
            let mut textures = HashMap::new();
            for (id, _) in manifest.tiles() {
                let tile = client
                    .tile(manifest, id)
                    .await
                    .unwrap_or_else(|e| panic!("reference {id}: {e}"));
                for level in 0..manifest.texture.levels {
                    // Verified against the tile blob's table.
                    let bytes = client
                        .texture(manifest, id, level, Some(&tile.texture[level as usize]))
                        .await
                        .unwrap_or_else(|e| panic!("reference {id} level {level}: {e}"));
                    textures.insert((id, level), bytes.to_vec());
                }
                tiles.insert(id, tile);
            }
            Reference { tiles, textures }
        })
    }

    /// The hash and size of texture `level` of tile `id`, from its tile blob.
    fn texture_blob(&self, id: TileId, level: u32) -> terrain_shared::Blob {
        self.tiles[&id].texture[level as usize].clone()
    }

    /// Checks every delivered tile and level against the reference (and that none came
    /// twice); what was delivered and what failed.
    fn check_delivered(&self, events: &[FetchEvent]) -> Delivered {
        let mut delivered = Delivered {
            tiles: HashSet::new(),
            levels: HashSet::new(),
            failed: Vec::new(),
        };
        for event in events {
            match event {
                FetchEvent::Tile {
                    id,
                    heights,
                    heights_bytes,
                    mask_errors_m,
                    texture,
                    coarsest_texture,
                    attempts,
                    ..
                } => {
                    let reference = &self.tiles[id];
                    assert_eq!(*heights, reference.heights, "tile {id} heights");
                    assert_eq!(*mask_errors_m, reference.mask_errors_m, "tile {id} errors");
                    assert_eq!(*texture, reference.texture, "tile {id} texture hashes");
                    assert!(*heights_bytes > 0 && *attempts >= 1);
                    assert_eq!(
                        Some(&coarsest_texture.to_vec()),
                        self.textures.get(&(*id, 0)),
                        "tile {id} coarsest texture"
                    );
                    assert!(delivered.tiles.insert(*id), "tile {id} delivered twice");
                }
                FetchEvent::TextureLevel {
                    id, level, bytes, ..
                } => {
                    assert_eq!(
                        Some(&bytes.to_vec()),
                        self.textures.get(&(*id, *level)),
                        "tile {id} level {level}"
                    );
                    assert!(delivered.levels.insert((*id, *level)), "{id} {level} twice");
                }
                FetchEvent::Data { id, key, .. } => {
                    panic!("data {key} of tile {id} delivered though never asked for")
                }
                FetchEvent::Failed { id, .. } => delivered.failed.push(*id),
            }
        }
        delivered
    }
}
