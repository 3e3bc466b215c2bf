//! A misbehaving link for tests: a TCP proxy in front of a real server that, response by
//! response and on a fixed schedule, passes a response through, flips a byte of its body,
//! cuts its body short, resets the connection or answers 500 itself; and that can hold
//! every request for a while (a long round trip) and shape everything it sends to a given
//! bandwidth.
//!
//! Every request goes upstream with `Connection: close`, so each connection carries one
//! request and one response, and the proxy reads the whole response (until the server
//! closes) before it decides what to do with it. That keeps the proxy free of HTTP framing
//! (chunking, keep-alive) and makes each fault exactly one response. It runs on its own
//! tokio runtime on a thread, like [`crate::server::TestServer`], and stops on drop.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::oneshot;
use tokio::time::Instant;

/// Bytes written to the client per write, and the unit of bandwidth shaping: small enough
/// that shaping is smooth at 100 Mbit/s (16 KiB is 1.3 ms there), large enough to cost few
/// timer wake-ups.
pub const CHUNK_BYTES: usize = 16 * 1024;
/// Depth of the shaped link's token bucket, in chunks (64 KiB: about 5 ms at 100 Mbit/s).
pub const BURST_CHUNKS: usize = 4;
/// The length an [`Fault::Oversized`] response states: far past any tile or manifest.
pub const OVERSIZED_BYTES: u64 = 1 << 30;
/// Longest request head read; the tile API's heads are a few hundred bytes.
const MAX_HEAD_BYTES: usize = 64 * 1024;

/// What happens to one response.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Fault {
    /// Sent as received.
    Pass,
    /// One byte in the middle of the body is flipped (a response without a body passes).
    Corrupt,
    /// The head (with its full `Content-Length`) and half of the body are sent, then the
    /// connection is closed.
    Truncate,
    /// The connection is reset (`SO_LINGER` 0) without any response; the request never
    /// reaches the server.
    Reset,
    /// A `500 Internal Server Error` with a short JSON body, as an overloaded server or a
    /// gateway in front of it answers; the request never reaches the server.
    ServerError,
    /// A `200 OK` whose chunked body never ends: zeros, until the client goes away. The
    /// request never reaches the server.
    Endless,
    /// A `200 OK` that says `Content-Length:` [`OVERSIZED_BYTES`] and sends zeros towards
    /// it, until the client goes away. The request never reaches the server.
    Oversized,
}

/// Which responses get which [`Fault`].
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct FaultPlan {
    /// Faults in turn: the n-th eligible response gets `rotation[n % len]`. Empty passes all.
    pub rotation: Vec<Fault>,
    /// Only requests whose path contains this are eligible; `None`: all.
    pub path_contains: Option<String>,
    /// A path gets a fault other than [`Fault::Pass`] at most this often; later requests
    /// for it pass and are not eligible. `None`: no limit.
    pub max_faults_per_path: Option<u32>,
    /// Bandwidth towards the clients in bytes per second, shared by all connections;
    /// `None`: unlimited.
    pub bandwidth: Option<u64>,
    /// Every request waits this long before it goes on (a slow link's round trip, or a
    /// server far away); requests wait side by side, not one after the other.
    pub delay: Duration,
}

impl FaultPlan {
    /// Every response passes.
    pub fn pass_through() -> FaultPlan {
        FaultPlan::default()
    }

    /// Responses get `faults` in turn.
    pub fn rotation(faults: &[Fault]) -> FaultPlan {
        FaultPlan {
            rotation: faults.to_vec(),
            ..FaultPlan::default()
        }
    }

    pub fn only_paths_containing(mut self, part: &str) -> FaultPlan {
        self.path_contains = Some(part.to_string());
        self
    }

    pub fn at_most_per_path(mut self, faults: u32) -> FaultPlan {
        self.max_faults_per_path = Some(faults);
        self
    }

    /// Shapes the link to `bytes_per_second` (100 Mbit/s is 12_500_000).
    pub fn with_bandwidth(mut self, bytes_per_second: u64) -> FaultPlan {
        self.bandwidth = Some(bytes_per_second);
        self
    }

    /// Holds every request for `delay` before it goes on.
    pub fn with_delay(mut self, delay: Duration) -> FaultPlan {
        self.delay = delay;
        self
    }
}

/// What the proxy did so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ProxyStats {
    pub connections: u64,
    pub passed: u64,
    pub corrupted: u64,
    pub truncated: u64,
    pub reset: u64,
    pub server_errors: u64,
    /// Endless and oversized bodies begun.
    pub endless: u64,
    /// Bytes written to clients, heads included.
    pub bytes_sent: u64,
}

/// A running proxy. Dropping it stops it; connections still open are dropped.
#[derive(Debug)]
pub struct FaultyProxy {
    addr: SocketAddr,
    base_url: String,
    shared: Arc<Shared>,
    shutdown: Option<oneshot::Sender<()>>,
    thread: Option<JoinHandle<std::io::Result<()>>>,
}

impl FaultyProxy {
    /// A proxy on `127.0.0.1:0` forwarding to `upstream`. Panics if it cannot bind: a test
    /// cannot go on without it.
    pub fn start(upstream: SocketAddr, plan: FaultPlan) -> FaultyProxy {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("cannot bind 127.0.0.1:0");
        listener
            .set_nonblocking(true)
            .expect("cannot make the listener non-blocking");
        let addr = listener
            .local_addr()
            .expect("cannot read the bound address");
        let shared = Arc::new(Shared::new(plan));
        let (shutdown, stop) = oneshot::channel::<()>();
        let for_thread = Arc::clone(&shared);
        let thread = std::thread::Builder::new()
            .name(format!("faulty-proxy-{}", addr.port()))
            .spawn(move || {
                // Two workers, as the test server: concurrency without crowding 2 cores.
                let runtime = tokio::runtime::Builder::new_multi_thread()
                    .worker_threads(2)
                    .enable_all()
                    .build()?;
                runtime.block_on(accept_loop(listener, upstream, for_thread, stop))
            })
            .expect("cannot spawn the proxy thread");
        FaultyProxy {
            addr,
            base_url: format!("http://{addr}"),
            shared,
            shutdown: Some(shutdown),
            thread: Some(thread),
        }
    }

    /// `http://127.0.0.1:PORT`, without a trailing slash.
    pub fn base_url(&self) -> &str {
        &self.base_url
    }

    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    pub fn stats(&self) -> ProxyStats {
        let counters = &self.shared.counters;
        let load = |counter: &AtomicU64| counter.load(Ordering::Relaxed);
        ProxyStats {
            connections: load(&counters.connections),
            passed: load(&counters.passed),
            corrupted: load(&counters.corrupted),
            truncated: load(&counters.truncated),
            reset: load(&counters.reset),
            server_errors: load(&counters.server_errors),
            endless: load(&counters.endless),
            bytes_sent: load(&counters.bytes_sent),
        }
    }
}

impl Drop for FaultyProxy {
    fn drop(&mut self) {
        if let Some(shutdown) = self.shutdown.take() {
            let _ = shutdown.send(());
        }
        if let Some(thread) = self.thread.take() {
            let result = thread.join();
            if !std::thread::panicking() {
                match result {
                    Ok(Ok(())) => {}
                    Ok(Err(error)) => panic!("the faulty proxy failed: {error}"),
                    Err(_) => panic!("the faulty proxy thread panicked"),
                }
            }
        }
    }
}

// ---- private ----

#[derive(Debug)]
struct Shared {
    plan: FaultPlan,
    schedule: Mutex<Schedule>,
    link: Option<Link>,
    counters: Counters,
}

#[derive(Debug, Default)]
struct Schedule {
    eligible: u64,
    faults_per_path: HashMap<String, u32>,
}

#[derive(Debug, Default)]
struct Counters {
    connections: AtomicU64,
    passed: AtomicU64,
    corrupted: AtomicU64,
    truncated: AtomicU64,
    reset: AtomicU64,
    server_errors: AtomicU64,
    endless: AtomicU64,
    bytes_sent: AtomicU64,
}

impl Shared {
    fn new(plan: FaultPlan) -> Shared {
        let link = plan.bandwidth.map(Link::new);
        Shared {
            plan,
            schedule: Mutex::new(Schedule::default()),
            link,
            counters: Counters::default(),
        }
    }

    /// The fault for the next response to a request for `path`.
    fn decide(&self, path: &str) -> Fault {
        let plan = &self.plan;
        if plan.rotation.is_empty()
            || plan
                .path_contains
                .as_deref()
                .is_some_and(|part| !path.contains(part))
        {
            return Fault::Pass;
        }
        let mut schedule = self.schedule.lock().unwrap_or_else(PoisonError::into_inner);
        let faulted = schedule.faults_per_path.get(path).copied().unwrap_or(0);
        if plan
            .max_faults_per_path
            .is_some_and(|limit| faulted >= limit)
        {
            return Fault::Pass;
        }
        let fault = plan.rotation[(schedule.eligible % plan.rotation.len() as u64) as usize];
        schedule.eligible += 1;
        if fault != Fault::Pass {
            *schedule
                .faults_per_path
                .entry(path.to_string())
                .or_default() += 1;
        }
        fault
    }

    fn count(&self, fault: Fault) {
        let counter = match fault {
            Fault::Pass => &self.counters.passed,
            Fault::Corrupt => &self.counters.corrupted,
            Fault::Truncate => &self.counters.truncated,
            Fault::Reset => &self.counters.reset,
            Fault::ServerError => &self.counters.server_errors,
            Fault::Endless | Fault::Oversized => &self.counters.endless,
        };
        counter.fetch_add(1, Ordering::Relaxed);
    }
}

/// The shaped link: a token bucket kept as the time at which the link is next free (the
/// "virtual scheduling" form of the same algorithm, ITU-T I.371's GCRA). Writers reserve
/// their chunk's time on it and sleep until it has passed, so all connections together get
/// `bytes_per_second`, as on one real link. The bucket holds [`BURST_CHUNKS`] chunks: a
/// writer whose timer woke late (tokio's timer has millisecond resolution, a chunk at
/// 100 Mbit/s takes 1.3 ms) may catch up that much, as a real link's queue lets it;
/// without it a single stream lost up to half the link to timer lag (measured 6.4 MB/s of
/// 12.5).
#[derive(Debug)]
struct Link {
    bytes_per_second: f64,
    /// Time the bucket's depth takes to send: how far behind a writer may fall and catch up.
    burst: Duration,
    free_at: Mutex<Instant>,
}

impl Link {
    fn new(bytes_per_second: u64) -> Link {
        let bytes_per_second = bytes_per_second.max(1) as f64;
        Link {
            bytes_per_second,
            burst: Duration::from_secs_f64((BURST_CHUNKS * CHUNK_BYTES) as f64 / bytes_per_second),
            free_at: Mutex::new(Instant::now()),
        }
    }

    /// Waits until `bytes` may be sent.
    async fn take(&self, bytes: usize) {
        let until = {
            let mut free_at = self.free_at.lock().unwrap_or_else(PoisonError::into_inner);
            let now = Instant::now();
            let earliest = now.checked_sub(self.burst).unwrap_or(now);
            let start = (*free_at).max(earliest);
            *free_at = start + Duration::from_secs_f64(bytes as f64 / self.bytes_per_second);
            *free_at
        };
        tokio::time::sleep_until(until).await;
    }
}

async fn accept_loop(
    listener: std::net::TcpListener,
    upstream: SocketAddr,
    shared: Arc<Shared>,
    stop: oneshot::Receiver<()>,
) -> std::io::Result<()> {
    let listener = TcpListener::from_std(listener)?;
    let mut stop = std::pin::pin!(stop);
    loop {
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            // A dropped sender also means stop: the test is gone.
            _ = &mut stop => return Ok(()),
        };
        // An accept error concerns one connection (the client gave up); the next may work.
        let Ok((client, _)) = accepted else { continue };
        shared.counters.connections.fetch_add(1, Ordering::Relaxed);
        let shared = Arc::clone(&shared);
        tokio::spawn(async move {
            // A failed connection is what this proxy is for, or a client that went away
            // (a cancelled request): neither is the proxy's failure.
            let _ = proxy_one(client, upstream, &shared).await;
        });
    }
}

/// One connection: one request and its response.
async fn proxy_one(
    mut client: TcpStream,
    upstream: SocketAddr,
    shared: &Shared,
) -> std::io::Result<()> {
    client.set_nodelay(true)?;
    let head = read_request_head(&mut client).await?;
    if !shared.plan.delay.is_zero() {
        tokio::time::sleep(shared.plan.delay).await;
    }
    let path = request_path(&head);
    let fault = shared.decide(&path);
    if fault == Fault::Reset {
        client.set_zero_linger()?;
        shared.count(fault);
        return Ok(());
    }
    if matches!(fault, Fault::Endless | Fault::Oversized) {
        shared.count(fault);
        // The client going away ends the body: what it read is all it will.
        let _ = send_zeros(&mut client, fault == Fault::Endless, shared).await;
        return Ok(());
    }
    if fault == Fault::ServerError {
        shared.count(fault);
        let body = r#"{"error":"internal server error (from the faulty proxy)","status":500}"#;
        let response = format!(
            "HTTP/1.1 500 Internal Server Error\r\ncontent-type: application/json\r\n\
             content-length: {}\r\nconnection: close\r\n\r\n{body}",
            body.len()
        );
        client.write_all(response.as_bytes()).await?;
        return client.shutdown().await;
    }
    let mut server = TcpStream::connect(upstream).await?;
    server.write_all(&with_connection_close(&head)).await?;
    let mut response = Vec::new();
    server.read_to_end(&mut response).await?;
    let body_start = find(&response, b"\r\n\r\n").map_or(response.len(), |end| end + 4);
    let body_len = response.len() - body_start;
    let (done, send_len) = match fault {
        Fault::Corrupt if body_len > 0 => {
            response[body_start + body_len / 2] ^= 0x5a;
            (Fault::Corrupt, response.len())
        }
        Fault::Truncate => (Fault::Truncate, body_start + body_len / 2),
        Fault::Pass
        | Fault::Corrupt
        | Fault::Reset
        | Fault::ServerError
        | Fault::Endless
        | Fault::Oversized => (Fault::Pass, response.len()),
    };
    shared.count(done);
    for chunk in response[..send_len].chunks(CHUNK_BYTES) {
        if let Some(link) = &shared.link {
            link.take(chunk.len()).await;
        }
        client.write_all(chunk).await?;
        shared
            .counters
            .bytes_sent
            .fetch_add(chunk.len() as u64, Ordering::Relaxed);
    }
    client.shutdown().await
}

/// Reads until the blank line that ends a request head (GET requests have no body).
async fn read_request_head(client: &mut TcpStream) -> std::io::Result<Vec<u8>> {
    let mut head = Vec::with_capacity(1024);
    let mut buffer = [0u8; 4096];
    while find(&head, b"\r\n\r\n").is_none() {
        if head.len() > MAX_HEAD_BYTES {
            return Err(std::io::Error::other("request head too long"));
        }
        let read = client.read(&mut buffer).await?;
        if read == 0 {
            return Err(std::io::ErrorKind::UnexpectedEof.into());
        }
        head.extend_from_slice(&buffer[..read]);
    }
    Ok(head)
}

/// The target of the request line (`GET /v1/... HTTP/1.1`).
fn request_path(head: &[u8]) -> String {
    let line = head.split(|&b| b == b'\r').next().unwrap_or_default();
    let text = String::from_utf8_lossy(line);
    text.split(' ').nth(1).unwrap_or_default().to_string()
}

/// The head with any `Connection` header replaced by `Connection: close`.
fn with_connection_close(head: &[u8]) -> Vec<u8> {
    let text = String::from_utf8_lossy(head);
    let mut lines: Vec<&str> = text
        .trim_end_matches("\r\n")
        .split("\r\n")
        .filter(|line| !line.to_ascii_lowercase().starts_with("connection:"))
        .collect();
    lines.push("Connection: close");
    let mut out = lines.join("\r\n").into_bytes();
    out.extend_from_slice(b"\r\n\r\n");
    out
}

fn find(haystack: &[u8], needle: &[u8]) -> Option<usize> {
    haystack
        .windows(needle.len())
        .position(|window| window == needle)
}

/// A `200 OK` of zeros: chunked and endless when `endless`, else [`OVERSIZED_BYTES`] long;
/// returns once it is all sent or the client is gone.
async fn send_zeros(client: &mut TcpStream, endless: bool, shared: &Shared) -> std::io::Result<()> {
    let framing = if endless {
        "transfer-encoding: chunked".to_string()
    } else {
        format!("content-length: {OVERSIZED_BYTES}")
    };
    let head = format!(
        "HTTP/1.1 200 OK\r\ncontent-type: application/octet-stream\r\n{framing}\r\n\
         connection: close\r\n\r\n"
    );
    client.write_all(head.as_bytes()).await?;
    let zeros = vec![0u8; CHUNK_BYTES];
    let chunk_head = format!("{:x}\r\n", zeros.len());
    let mut sent = 0u64;
    while endless || sent < OVERSIZED_BYTES {
        if endless {
            client.write_all(chunk_head.as_bytes()).await?;
        }
        client.write_all(&zeros).await?;
        if endless {
            client.write_all(b"\r\n").await?;
        }
        sent += zeros.len() as u64;
        shared
            .counters
            .bytes_sent
            .fetch_add(zeros.len() as u64, Ordering::Relaxed);
    }
    Ok(())
}
