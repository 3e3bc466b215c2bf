//! A normal client's latency while an attacker holds or churns thousands of connections.
//!
//! Its own test binary, so it runs alone: timing a p99 beside the other end-to-end tests
//! on a two-core machine would measure them, not the server. Needs about 11,000 file
//! descriptors (both ends of 5,000 connections in one process, plus the client's).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use terrain_shared::routes;
use terrain_tests::server::TestServer;
use terrain_tests::synthetic::SyntheticDb;
use tokio::io::AsyncReadExt;
use tokio::net::TcpStream;

const HELD: usize = 5_000;
const CHURNED: usize = 4_300;
const SAMPLES: usize = 300;
const P99_LIMIT: Duration = Duration::from_millis(100);
/// A normal request still unanswered after this long is given up (and counted as this).
const STALLED: Duration = Duration::from_secs(2);

/// The soft limit on open files, from `/proc/self/limits`.
fn open_files_limit() -> Option<u64> {
    let limits = std::fs::read_to_string("/proc/self/limits").ok()?;
    let line = limits.lines().find(|l| l.starts_with("Max open files"))?;
    line.split_whitespace().nth(3)?.parse().ok()
}

/// `SAMPLES` requests, each on a new connection (connecting is what an attacker holding
/// slots delays); returns the sorted latencies.
async fn sample_latencies(server: &TestServer, path: &str) -> Vec<Duration> {
    let client = reqwest::Client::builder()
        .pool_max_idle_per_host(0)
        .timeout(Duration::from_secs(30))
        .build()
        .expect("client");
    let url = server.url(path);
    let mut latencies = Vec::with_capacity(SAMPLES);
    for _ in 0..SAMPLES {
        let started = Instant::now();
        let answered = tokio::time::timeout(STALLED, async {
            let response = client.get(&url).send().await.expect("request answered");
            assert_eq!(response.status(), 200);
            response.bytes().await.expect("body");
        })
        .await;
        // A stalled request counts as the time given up after: the p99 fails either way.
        latencies.push(if answered.is_ok() {
            started.elapsed()
        } else {
            STALLED
        });
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    latencies.sort();
    latencies
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    let index = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[index]
}

fn report(what: &str, latencies: &[Duration]) -> Duration {
    let p99 = percentile(latencies, 0.99);
    println!(
        "{what}: p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms over {} requests",
        percentile(latencies, 0.5).as_secs_f64() * 1e3,
        p99.as_secs_f64() * 1e3,
        latencies[latencies.len() - 1].as_secs_f64() * 1e3,
        latencies.len()
    );
    p99
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_normal_client_stays_fast_while_thousands_of_connections_are_held_or_churned() {
    let limit = open_files_limit().unwrap_or(0);
    assert!(
        limit >= 2 * HELD as u64 + 1_000,
        "this test needs {} open files, the limit is {limit}: raise it with `ulimit -n`",
        2 * HELD + 1_000
    );
    let db = SyntheticDb::write().expect("synthetic database");
    let server = TestServer::start(db.dir());
    let path = routes::heights(
        &db.manifest().content_version,
        terrain_shared::TileId::new(0, 0),
    );

    let quiet = sample_latencies(&server, &path).await;
    report("no attack", &quiet);

    // 1. Idle connections that never send a byte, opened all at once and held. Sampling
    // starts as soon as most are open (within a few seconds, well inside the idle timeout,
    // so the timeout cannot be what frees slots for the normal client).
    let connected = Arc::new(AtomicU64::new(0));
    let release = Arc::new(tokio::sync::Notify::new());
    let mut held = Vec::with_capacity(HELD);
    let opened_at = Instant::now();
    for _ in 0..HELD {
        let (connected, release, addr) =
            (Arc::clone(&connected), Arc::clone(&release), server.addr());
        held.push(tokio::spawn(async move {
            if let Ok(stream) = TcpStream::connect(addr).await {
                connected.fetch_add(1, Ordering::Relaxed);
                release.notified().await;
                drop(stream);
            }
        }));
    }
    while connected.load(Ordering::Relaxed) < (HELD as u64) * 9 / 10
        && opened_at.elapsed() < Duration::from_secs(3)
    {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let under_held = sample_latencies(&server, &path).await;
    let held_p99 = report(
        &format!(
            "{HELD} idle connections held ({} open after {:.1} s)",
            connected.load(Ordering::Relaxed),
            opened_at.elapsed().as_secs_f64()
        ),
        &under_held,
    );
    release.notify_waiters();
    for task in held {
        task.abort();
    }

    // 2. Connections reopened as soon as the server closes them.
    let stop = Arc::new(AtomicBool::new(false));
    let reopened = Arc::new(AtomicU64::new(0));
    let mut churn = Vec::with_capacity(CHURNED);
    for _ in 0..CHURNED {
        let (stop, reopened, addr) = (Arc::clone(&stop), Arc::clone(&reopened), server.addr());
        churn.push(tokio::spawn(async move {
            while !stop.load(Ordering::Relaxed) {
                let Ok(mut stream) = TcpStream::connect(addr).await else {
                    tokio::time::sleep(Duration::from_millis(10)).await;
                    continue;
                };
                reopened.fetch_add(1, Ordering::Relaxed);
                let mut byte = [0u8; 1];
                let _ = tokio::time::timeout(Duration::from_secs(60), stream.read(&mut byte)).await;
            }
        }));
    }
    tokio::time::sleep(Duration::from_secs(1)).await;
    let under_churn = sample_latencies(&server, &path).await;
    let churn_p99 = report(
        &format!(
            "{CHURNED} connections reopened as they close ({} opened)",
            reopened.load(Ordering::Relaxed)
        ),
        &under_churn,
    );
    stop.store(true, Ordering::Relaxed);
    for task in churn {
        task.abort();
    }

    assert!(
        held_p99 < P99_LIMIT,
        "p99 {held_p99:?} with {HELD} idle connections held"
    );
    assert!(
        churn_p99 < P99_LIMIT,
        "p99 {churn_p99:?} with {CHURNED} connections churned"
    );
}
