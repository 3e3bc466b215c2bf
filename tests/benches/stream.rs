//! Streaming benchmark: tiles per second through a 100 Mbit/s link, and the share of the
//! link they use.
//!
//! ```text
//! cargo bench -p terrain-tests --bench stream -- [DATABASE_DIR]
//! ```
//!
//! Without an argument it builds himalaya_4097 (1365 tiles over six levels, 1024 of them at
//! level 0; a second or two on the link) from `$TERRAIN_DATA_DIR`. A real server on
//! 127.0.0.1 serves the database through a shaping proxy (`terrain_tests::proxy`, a token
//! bucket shared by all connections, no burst) limited to 100 Mbit/s; the client's
//! [`Fetcher`] (4, 8 and 16 requests at once, a run each) fetches every tile of every level
//! as a flight would (the tile blob and the coarsest texture level), coarsest level first.
//! The baseline, measured in the same run through an identical link, is one bulk download
//! of a 24 MiB body: what the link delivers to a single transfer that never waits on a
//! round trip.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};
use terrain_client::http_client::TileClient;
use terrain_client::requests::{FetchEvent, Fetcher, FetcherConfig, Want};
use terrain_server::build::{BuildOptions, build};
use terrain_shared::TileBlob;
use terrain_tests::proxy::{FaultPlan, FaultyProxy};
use terrain_tests::server::TestServer;
use terrain_tests::synthetic::{LARGE_TEXTURE, SyntheticDb};

/// 100 Mbit/s in bytes per second.
const LINK_BYTES_PER_S: u64 = 12_500_000;
const BULK_BYTES: usize = 24 << 20;
/// Requests at once, one run each; the fetcher's default is 8.
const CONCURRENCY: [usize; 3] = [4, 8, 16];

fn main() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = match std::env::args().skip(1).find(|a| !a.starts_with("--")) {
        Some(dir) => std::path::PathBuf::from(dir),
        None => {
            let Some(kit) = std::env::var_os("TERRAIN_DATA_DIR") else {
                eprintln!(
                    "usage: cargo bench -p terrain-tests --bench stream -- DATABASE_DIR  (or set TERRAIN_DATA_DIR)"
                );
                std::process::exit(2);
            };
            let heights = std::path::Path::new(&kit).join("himalaya_4097/g10g_himalaya_4097.png");
            build(
                &BuildOptions::new(&heights, tmp.path().join("db")),
                &|_, _| {},
                &AtomicBool::new(false),
            )
            .unwrap_or_else(|e| panic!("{}: {e}", heights.display()))
            .out
        }
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    println!(
        "machine: {} ({} cores); link: 100 Mbit/s token bucket on loopback",
        cpu_model(),
        num_cores()
    );

    // Baseline: one bulk body through an identical link.
    let synthetic = SyntheticDb::write_with_large_texture(BULK_BYTES).expect("synthetic database");
    let bulk_server = TestServer::start(synthetic.dir());
    let bulk_proxy = FaultyProxy::start(
        bulk_server.addr(),
        FaultPlan::pass_through().with_bandwidth(LINK_BYTES_PER_S),
    );
    let bulk_rate = runtime.block_on(async {
        let client = TileClient::new(bulk_proxy.base_url()).expect("client");
        let manifest = client.manifest().await.expect("manifest");
        // Its hash, from its tile blob (as written): the body is verified as a tile's is.
        let (id, level) = LARGE_TEXTURE;
        let blob = TileBlob::decode(synthetic.heights(id)).expect("a tile blob");
        let started = Instant::now();
        let body = client
            .texture(&manifest, id, level, Some(&blob.texture[level as usize]))
            .await
            .expect("bulk body");
        body.len() as f64 / started.elapsed().as_secs_f64()
    });

    // Tiles, as a flight fetches them.
    let server = TestServer::start(&db);
    let nominal = LINK_BYTES_PER_S as f64;
    println!(
        "baseline  bulk body {:>8.2} MB/s = {:.1}% of the link",
        bulk_rate / 1e6,
        100.0 * bulk_rate / nominal
    );
    for concurrency in CONCURRENCY {
        let proxy = FaultyProxy::start(
            server.addr(),
            FaultPlan::pass_through().with_bandwidth(LINK_BYTES_PER_S),
        );
        let (tiles, elapsed, payload, wire) = runtime.block_on(async {
            let client = TileClient::new(proxy.base_url()).expect("client");
            let manifest = Arc::new(client.manifest().await.expect("manifest"));
            let wire_before = proxy.stats().bytes_sent;
            let config = FetcherConfig {
                concurrency,
                ..FetcherConfig::default()
            };
            let mut fetcher = Fetcher::new(
                client,
                Arc::clone(&manifest),
                config,
                tokio::runtime::Handle::current(),
            );
            let started = Instant::now();
            // Coarsest level first, as a flight's first frame asks (it covers the most
            // screen), then row-major within a level.
            let mut ids: Vec<_> = manifest.tiles().map(|(id, _)| id).collect();
            ids.sort_by_key(|id| std::cmp::Reverse(id.level));
            for (rank, id) in ids.into_iter().enumerate() {
                fetcher.request(id, Want::Tile, rank as u64);
            }
            let mut delivered = 0;
            while delivered < manifest.tile_count() {
                for event in fetcher.poll() {
                    match event {
                        FetchEvent::Tile { .. } => delivered += 1,
                        FetchEvent::Failed { id, error, .. } => panic!("tile {id}: {error}"),
                        FetchEvent::TextureLevel { .. } | FetchEvent::Data { .. } => {}
                    }
                }
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
            let elapsed = started.elapsed().as_secs_f64();
            (
                delivered,
                elapsed,
                fetcher.stats().bytes_downloaded,
                proxy.stats().bytes_sent - wire_before,
            )
        });
        println!(
            "{concurrency:>2} at once {tiles} tiles in {elapsed:.2} s = {:>6.1} tiles/s; link used {:.1}% on the wire ({:.1}% by tile bodies); bodies vs bulk baseline {:.2}x",
            tiles as f64 / elapsed,
            100.0 * wire as f64 / elapsed / nominal,
            100.0 * payload as f64 / elapsed / nominal,
            payload as f64 / elapsed / bulk_rate
        );
    }
}

fn num_cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into())
}
