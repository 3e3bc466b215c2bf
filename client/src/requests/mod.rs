//! Carries out the pager's fetch decisions over HTTP: a priority queue of tile requests,
//! at most [`FetcherConfig::concurrency`] of them running at once, each retried with
//! backoff when the failure is worth another try, and cancellable whether queued or running.
//!
//! The frame loop never awaits: it calls [`Fetcher::request`] and [`Fetcher::cancel`] with
//! the pager's decisions and [`Fetcher::poll`] once a frame, which starts queued requests
//! and hands back whatever finished. Each request runs as one task on the tokio runtime the
//! fetcher was given; retries and their backoff sleeps happen inside that task.
//!
//! Owns: ordering, deduplication, concurrency, retries, cancellation, the counters in
//! [`FetchStats`]. Left to [`crate::http_client::TileClient`]: the single attempt (URL, status,
//! hash check, decoding off the async threads). Left to the pager: *what* to fetch and in
//! which order (the priority key).
//!
//! **Invariant:** nothing corrupt is delivered. Every body passes the manifest's hash
//! (checked by [`TileClient`]) and heights are decoded before a [`FetchEvent`] is made.
//!
//! **Invariant:** a cancelled request delivers nothing, even when its task had already
//! finished: each running request carries a ticket, and a result whose ticket is no longer
//! current is dropped in [`Fetcher::poll`].

mod job;

use self::job::{Job, Verdict, verdict};
use crate::http_client::{FetchError, TileClient};
pub use crate::tasks::Spawner;
use crate::tasks::{self, TaskHandle};
use bytes::Bytes;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::hash::BuildHasher;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;
use terrain_shared::{Heights, Manifest, TileId, routes};
use tokio::sync::{Notify, mpsc};

/// Requests running at once: the same as `terrain-client fetch`, for the same reason (keeps a
/// local server and a LAN busy without queueing behind the server's own limit).
pub const DEFAULT_CONCURRENCY: usize = 8;
/// Tries of one blob on transient failures. Five tries with the default backoff span about
/// 1.5 s at most (0.1 + 0.2 + 0.4 + 0.8 s of cap): longer than a server restart behind a
/// load balancer usually takes, short enough that a dead server is reported while the
/// viewer is still looking at the place that needed the tile.
pub const DEFAULT_MAX_ATTEMPTS: u32 = 5;
/// Cap of the first backoff: a round trip or two on a WAN.
pub const DEFAULT_BACKOFF_BASE: Duration = Duration::from_millis(100);
/// No single backoff exceeds this; beyond a few seconds a waiting tile is better reported.
pub const DEFAULT_BACKOFF_MAX: Duration = Duration::from_secs(5);
/// Bodies of one blob that may come back corrupt before it is reported: one refetch. A
/// flipped bit on the way is rare and does not repeat; a blob that is corrupt twice is
/// corrupt at the source (or on a cache in front of it), and asking again will not help.
pub const DEFAULT_CORRUPT_ATTEMPTS: u32 = 2;

/// How the fetcher schedules and retries.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FetcherConfig {
    /// Requests running at once; 0 counts as 1. A [`Want::Tile`] request fetches its two
    /// blobs side by side, any other one blob at a time, so a server sees at most twice
    /// this many HTTP requests from one client. A request waiting out a backoff keeps its
    /// slot, so a struggling server is not asked more while it struggles.
    pub concurrency: usize,
    /// Tries of one blob on transient failures (timeouts, refused or reset connections,
    /// bodies cut short, 5xx, 408, 429), the first included.
    pub max_attempts: u32,
    /// Cap of the first backoff; each further retry doubles the cap.
    pub backoff_base: Duration,
    /// Largest cap of any backoff.
    pub backoff_max: Duration,
    /// Bodies of one blob that may fail their hash or decoding before it is reported.
    pub corrupt_attempts: u32,
    /// The largest manifest taken ([`crate::http_client::MAX_MANIFEST_BYTES`] by default; a
    /// flight takes no more than its memory budget).
    pub max_manifest_bytes: u64,
}

impl Default for FetcherConfig {
    fn default() -> Self {
        FetcherConfig {
            concurrency: DEFAULT_CONCURRENCY,
            max_attempts: DEFAULT_MAX_ATTEMPTS,
            backoff_base: DEFAULT_BACKOFF_BASE,
            backoff_max: DEFAULT_BACKOFF_MAX,
            corrupt_attempts: DEFAULT_CORRUPT_ATTEMPTS,
            max_manifest_bytes: crate::http_client::MAX_MANIFEST_BYTES,
        }
    }
}

/// What a request asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Want {
    /// What a tile needs to be shown: its heights and its coarsest texture level.
    Tile,
    /// One finer texture level (or any level) of a tile, on request.
    TextureLevel(u32),
    /// Data of a level-of-detail method's own for the tile, its key the method's number
    /// for the piece; where it lives is given with [`Fetcher::request_data`].
    Data(u32),
}

/// A finished request, handed out by [`Fetcher::poll`].
#[derive(Debug)]
pub enum FetchEvent {
    /// Heights (verified and decoded) and the coarsest texture level (verified, encoded).
    Tile {
        id: TileId,
        heights: Heights,
        /// Size of the tile blob as received.
        heights_bytes: u64,
        /// Per strip-mask level, its error against the full-resolution surface, metres.
        mask_errors_m: Vec<f32>,
        /// Hash and size of each texture level, coarsest first, for
        /// [`Fetcher::request_texture`].
        texture: Vec<terrain_shared::Blob>,
        coarsest_texture: Bytes,
        /// Tries of the blob that needed most (1: nothing was retried).
        attempts: u32,
        /// From the request's start to its end: its two GETs side by side (with any
        /// backoff between tries) and the decoding.
        elapsed: Duration,
        /// Decoding the heights, on the blocking pool.
        decode: Duration,
    },
    /// One texture level, verified, in the manifest's `texture.format`.
    TextureLevel {
        id: TileId,
        level: u32,
        bytes: Bytes,
        /// From the request's start to its end (with any backoff between tries).
        elapsed: Duration,
    },
    /// A method's own data ([`Want::Data`]), verified when its hash was given.
    Data { id: TileId, key: u32, bytes: Bytes },
    /// The request gave up; `error` is the last failure.
    Failed {
        id: TileId,
        want: Want,
        error: FetchError,
        /// Tries of the blob that failed.
        attempts: u32,
    },
}

impl FetchEvent {
    pub fn id(&self) -> TileId {
        match self {
            FetchEvent::Tile { id, .. }
            | FetchEvent::TextureLevel { id, .. }
            | FetchEvent::Data { id, .. }
            | FetchEvent::Failed { id, .. } => *id,
        }
    }
}

/// Counters since the fetcher was made.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FetchStats {
    /// Bodies received, retried and discarded ones included. A body that failed its hash
    /// is counted at the size the manifest gives (the error does not carry its length);
    /// bodies cut short are not counted.
    pub bytes_downloaded: u64,
    /// HTTP requests started, retries included.
    pub requests_started: u64,
    /// Tries repeated after a transient failure.
    pub retries: u64,
    /// Tries repeated after a body failed its hash or decoding.
    pub corrupt_refetches: u64,
    /// Requests delivered as [`FetchEvent::Tile`] or [`FetchEvent::TextureLevel`].
    pub delivered: u64,
    /// Requests delivered as [`FetchEvent::Failed`].
    pub failures: u64,
    /// Requests dropped by [`Fetcher::cancel`], queued or running.
    pub cancelled: u64,
}

/// The fetch queue and its running requests. See the module documentation.
#[derive(Debug)]
pub struct Fetcher {
    client: TileClient,
    manifest: Arc<Manifest>,
    config: FetcherConfig,
    runtime: Spawner,
    queue: RequestQueue,
    running: HashMap<Request, Running>,
    /// Requests queued or running, per tile: what [`Fetcher::pending`] lists.
    pending_tiles: HashMap<TileId, u32>,
    /// Where each [`Want::Data`] request's body lives, until it ends.
    data: HashMap<(TileId, u32), DataSource>,
    /// The hash each [`Want::TextureLevel`] request's body must have, until it ends.
    textures: HashMap<(TileId, u32), terrain_shared::Blob>,
    finished_sender: mpsc::UnboundedSender<Finished>,
    finished: mpsc::UnboundedReceiver<Finished>,
    /// Told each time a request finishes ([`Fetcher::next_finished`]).
    progress: Arc<Notify>,
    counters: Arc<Counters>,
    next_ticket: u64,
    /// Random per fetcher, so that clients restarted together after an outage do not
    /// retry in lockstep.
    jitter_seed: u64,
    delivered: u64,
    failures: u64,
    cancelled: u64,
}

impl Fetcher {
    /// A fetcher for the tiles of `manifest`, served where `client` points, running its
    /// requests on `runtime` (which needs its time driver: backoff sleeps there).
    pub fn new(
        client: TileClient,
        manifest: Arc<Manifest>,
        config: FetcherConfig,
        runtime: impl Into<Spawner>,
    ) -> Fetcher {
        let (finished_sender, finished) = mpsc::unbounded_channel();
        Fetcher {
            client,
            manifest,
            config,
            runtime: runtime.into(),
            queue: RequestQueue::default(),
            running: HashMap::new(),
            pending_tiles: HashMap::new(),
            data: HashMap::new(),
            textures: HashMap::new(),
            finished_sender,
            finished,
            progress: Arc::new(Notify::new()),
            counters: Arc::new(Counters::default()),
            next_ticket: 0,
            jitter_seed: std::collections::hash_map::RandomState::new().hash_one(0u64),
            delivered: 0,
            failures: 0,
            cancelled: 0,
        }
    }

    /// Fetches the server's manifest again ([`fetch_manifest`], with its retries).
    pub async fn fetch_manifest(&self) -> Result<Manifest, FetchError> {
        fetch_manifest(&self.client, &self.config).await
    }

    /// The manifest whose tiles this fetcher fetches.
    pub fn manifest(&self) -> &Arc<Manifest> {
        &self.manifest
    }

    /// Fetches `manifest`'s tiles from now on (the server's database was rebuilt): every
    /// request queued or running is dropped, as by [`Fetcher::cancel`], since its URL names
    /// content the server no longer serves.
    pub fn replace_manifest(&mut self, manifest: Arc<Manifest>) {
        let pending: Vec<TileId> = self.pending().collect();
        self.cancel(&pending);
        self.manifest = manifest;
    }

    /// The server's base URL, as the client normalised it.
    pub fn base_url(&self) -> &str {
        self.client.base_url()
    }

    /// Queues a request; smaller `priority` starts sooner, equal keys in the order given.
    ///
    /// A request already running is left alone. A request already queued is not queued
    /// twice but takes the new `priority`: the latest frame's order is the one that counts.
    pub fn request(&mut self, id: TileId, want: Want, priority: u64) {
        let request = Request { id, want };
        if self.running.contains_key(&request) {
            return;
        }
        if self.queue.push(request, priority) {
            *self.pending_tiles.entry(id).or_default() += 1;
        }
    }

    /// Queues a request for a method's own data of tile `id` (see [`Want::Data`]): the body
    /// at `path` on the server, checked against `hash` (BLAKE3, first 128 bits, hex) when
    /// given. Otherwise as [`Fetcher::request`].
    pub fn request_data(
        &mut self,
        id: TileId,
        key: u32,
        path: String,
        hash: Option<String>,
        bytes: Option<u64>,
        priority: u64,
    ) {
        self.data
            .insert((id, key), DataSource { path, hash, bytes });
        self.request(id, Want::Data(key), priority);
    }

    /// Queues a request for texture `level` of tile `id`, whose body must match `blob` (the
    /// tile blob's entry for it, [`FetchEvent::Tile`]'s `texture`). Otherwise as
    /// [`Fetcher::request`].
    pub fn request_texture(
        &mut self,
        id: TileId,
        level: u32,
        blob: terrain_shared::Blob,
        priority: u64,
    ) {
        self.textures.insert((id, level), blob);
        self.request(id, Want::TextureLevel(level), priority);
    }

    /// Drops every queued request for these tiles and aborts their running ones: none of
    /// them will be delivered.
    pub fn cancel(&mut self, ids: &[TileId]) {
        let ids: HashSet<TileId> = ids.iter().copied().collect();
        let mut dropped = self.queue.remove_tiles(&ids);
        let running: Vec<Request> = self
            .running
            .keys()
            .filter(|request| ids.contains(&request.id))
            .copied()
            .collect();
        for request in running {
            if let Some(task) = self.running.remove(&request) {
                task.handle.abort();
                dropped.push(request);
            }
        }
        for request in dropped {
            self.cancelled += 1;
            self.forget_pending(request.id);
        }
    }

    /// Hands out everything that finished since the last call and starts queued requests
    /// up to the concurrency limit. Never blocks.
    pub fn poll(&mut self) -> Vec<FetchEvent> {
        // Looked at before draining the channel: a task sends its result before it ends,
        // so one that has ended and is still running here once the channel is drained
        // ended without sending (it panicked or its runtime shut down).
        let ended: Vec<(Request, u64)> = self
            .running
            .iter()
            .filter(|(_, task)| task.handle.is_finished())
            .map(|(request, task)| (*request, task.ticket))
            .collect();

        let mut events = Vec::new();
        while let Ok(finished) = self.finished.try_recv() {
            let current = self
                .running
                .get(&finished.request)
                .is_some_and(|task| task.ticket == finished.ticket);
            if !current {
                // Cancelled after it finished but before this poll: never delivered.
                continue;
            }
            self.running.remove(&finished.request);
            self.forget_pending(finished.request.id);
            events.push(finished.event);
        }
        for (request, ticket) in ended {
            if self
                .running
                .get(&request)
                .is_some_and(|task| task.ticket == ticket)
            {
                self.running.remove(&request);
                self.forget_pending(request.id);
                events.push(FetchEvent::Failed {
                    id: request.id,
                    want: request.want,
                    error: FetchError::Cancelled {
                        url: self.client.url(&request.path(&self.manifest, &self.data)),
                    },
                    attempts: 0,
                });
            }
        }
        for event in &events {
            match event {
                FetchEvent::Failed { .. } => self.failures += 1,
                _ => self.delivered += 1,
            }
        }

        while self.running.len() < self.config.concurrency.max(1) {
            let Some(request) = self.queue.pop() else {
                break;
            };
            self.start(request);
        }
        events
    }

    /// Tiles with a request queued or running (what the pager calls "in flight"), each
    /// once, in no particular order.
    pub fn pending(&self) -> impl Iterator<Item = TileId> + '_ {
        self.pending_tiles.keys().copied()
    }

    /// Number of tiles [`Fetcher::pending`] lists.
    pub fn pending_count(&self) -> usize {
        self.pending_tiles.len()
    }

    /// Sets `out[manifest.index(id)]` to whether tile `id` is pending, every other entry
    /// to false. Tiles outside the manifest's grids or beyond `out` are left out.
    pub fn mark_pending(&self, out: &mut [bool], manifest: &Manifest) {
        out.fill(false);
        for id in self.pending_tiles.keys() {
            if let Some(slot) = manifest.index(*id).and_then(|i| out.get_mut(i)) {
                *slot = true;
            }
        }
    }

    /// Waits until a running request finishes (one that finished since the last wait
    /// counts) or `at_most` passes; at once when none is running. What a flight that does
    /// not pace itself in wall-clock time waits on between frames (`fly --no-wait`).
    #[cfg(not(target_arch = "wasm32"))]
    pub async fn next_finished(&self, at_most: Duration) {
        if self.running.is_empty() {
            return;
        }
        let _ = tokio::time::timeout(at_most, self.progress.notified()).await;
    }

    /// Requests running now (at most the concurrency limit).
    pub fn running_count(&self) -> usize {
        self.running.len()
    }

    pub fn stats(&self) -> FetchStats {
        FetchStats {
            bytes_downloaded: self.counters.bytes_downloaded.load(Ordering::Relaxed),
            requests_started: self.counters.requests_started.load(Ordering::Relaxed),
            retries: self.counters.retries.load(Ordering::Relaxed),
            corrupt_refetches: self.counters.corrupt_refetches.load(Ordering::Relaxed),
            delivered: self.delivered,
            failures: self.failures,
            cancelled: self.cancelled,
        }
    }

    fn start(&mut self, request: Request) {
        let ticket = self.next_ticket;
        self.next_ticket += 1;
        let job = Job {
            client: self.client.clone(),
            manifest: Arc::clone(&self.manifest),
            config: self.config.clone(),
            counters: Arc::clone(&self.counters),
            data: match request.want {
                Want::Data(key) => self.data.get(&(request.id, key)).cloned(),
                _ => None,
            },
            texture_blob: match request.want {
                Want::TextureLevel(level) => self.textures.get(&(request.id, level)).cloned(),
                _ => None,
            },
            request,
            jitter_seed: mix(self.jitter_seed ^ mix(ticket)),
        };
        let sender = self.finished_sender.clone();
        let progress = Arc::clone(&self.progress);
        let handle = self.runtime.spawn(async move {
            let event = job.run().await;
            // The receiver is gone only when the fetcher is; then nobody wants the result.
            let _ = sender.send(Finished {
                request,
                ticket,
                event,
            });
            progress.notify_one();
        });
        self.running.insert(request, Running { ticket, handle });
    }

    fn forget_pending(&mut self, id: TileId) {
        if let Some(count) = self.pending_tiles.get_mut(&id) {
            *count -= 1;
            if *count == 0 {
                self.pending_tiles.remove(&id);
                self.data.retain(|(tile, _), _| *tile != id);
                self.textures.retain(|(tile, _), _| *tile != id);
            }
        }
    }
}

impl Drop for Fetcher {
    /// Running requests would otherwise go on downloading for nobody.
    fn drop(&mut self) {
        for task in self.running.values() {
            task.handle.abort();
        }
    }
}

/// The delay before retry number `retry` (0 for the first retry): "full jitter" (AWS
/// Architecture Blog, "Exponential Backoff And Jitter", 2015), uniform in
/// `[0, min(backoff_max, backoff_base * 2^retry)]`, drawn from `random`. Full jitter spreads
/// the retries of many clients that failed together, which is when a server needs it most.
pub fn backoff_delay(config: &FetcherConfig, retry: u32, random: u64) -> Duration {
    let doubled = config
        .backoff_base
        .checked_mul(1u32 << retry.min(31))
        .unwrap_or(config.backoff_max);
    let cap = doubled.min(config.backoff_max);
    let cap_nanos = u64::try_from(cap.as_nanos()).unwrap_or(u64::MAX);
    match cap_nanos.checked_add(1) {
        Some(span) => Duration::from_nanos(random % span),
        None => Duration::from_nanos(random),
    }
}

/// The server's manifest, tried like a tile's blob: transient failures (5xx, a body cut
/// short, a reset) are retried with backoff up to [`FetcherConfig::max_attempts`] tries,
/// a body that fails its hash or does not parse is fetched again up to
/// [`FetcherConfig::corrupt_attempts`] times, and anything else (404: no server there) is
/// reported at once. One bad response does not end a client that has only started.
pub async fn fetch_manifest(
    client: &TileClient,
    config: &FetcherConfig,
) -> Result<Manifest, FetchError> {
    let jitter_seed = std::collections::hash_map::RandomState::new().hash_one(1u64);
    let (mut tries, mut corrupt) = (0, 0);
    loop {
        tries += 1;
        let error = match client.manifest().await {
            Ok(manifest) => return Ok(manifest),
            Err(error) => error,
        };
        let kind = FailureKind::of(&error);
        if kind == FailureKind::Corrupt {
            corrupt += 1;
        }
        if verdict(config, kind, tries, corrupt) == Verdict::GiveUp {
            return Err(error);
        }
        let delay = backoff_delay(config, tries - 1, mix(jitter_seed ^ mix(u64::from(tries))));
        tracing::warn!(
            tries,
            delay_ms = delay.as_millis() as u64,
            "manifest: {}; trying again",
            error.chain()
        );
        tasks::sleep(delay).await;
    }
}

/// How a failed try is classified.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FailureKind {
    /// May succeed later: see [`FetchError::is_transient`].
    Transient,
    /// The body did not match its hash or did not decode: worth one more fetch.
    Corrupt,
    /// Repeats on every try (4xx, not in the grid, no such level, cancelled): reported at once.
    Permanent,
}

impl FailureKind {
    pub fn of(error: &FetchError) -> FailureKind {
        if error.is_transient() {
            return FailureKind::Transient;
        }
        match error {
            FetchError::HashMismatch { .. }
            | FetchError::TooLarge { .. }
            | FetchError::Decode { .. }
            | FetchError::TileBlob { .. }
            | FetchError::Manifest { .. } => FailureKind::Corrupt,
            _ => FailureKind::Permanent,
        }
    }
}

// ---- private ----

/// One thing to fetch: the unit of queueing, deduplication and cancellation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
struct Request {
    id: TileId,
    want: Want,
}

impl Request {
    /// The route of the request's first blob, to name it in an error.
    fn path(&self, manifest: &Manifest, data: &HashMap<(TileId, u32), DataSource>) -> String {
        match self.want {
            Want::Tile => routes::heights(&manifest.content_version, self.id),
            Want::TextureLevel(level) => routes::texture(&manifest.content_version, self.id, level),
            Want::Data(key) => data
                .get(&(self.id, key))
                .map_or_else(String::new, |d| d.path.clone()),
        }
    }
}

/// Where a [`Want::Data`] body lives and the hash it must have.
#[derive(Debug, Clone, PartialEq, Eq)]
struct DataSource {
    path: String,
    hash: Option<String>,
    bytes: Option<u64>,
}

/// Queued requests, smallest priority key first, first come first served among equal keys.
#[derive(Debug, Default)]
struct RequestQueue {
    /// (priority, arrival) -> request: the order requests start in.
    order: BTreeMap<(u64, u64), Request>,
    /// request -> its key in `order`, for deduplication and removal.
    keys: HashMap<Request, (u64, u64)>,
    arrivals: u64,
}

impl RequestQueue {
    /// Queues `request`, or moves it to `priority` if it is queued already. Returns whether
    /// it is new.
    fn push(&mut self, request: Request, priority: u64) -> bool {
        let key = (priority, self.arrivals);
        self.arrivals += 1;
        match self.keys.insert(request, key) {
            Some(old) if old.0 == priority => {
                // Same priority: keep its place among equals.
                self.keys.insert(request, old);
                false
            }
            Some(old) => {
                self.order.remove(&old);
                self.order.insert(key, request);
                false
            }
            None => {
                self.order.insert(key, request);
                true
            }
        }
    }

    fn pop(&mut self) -> Option<Request> {
        let (_, request) = self.order.pop_first()?;
        self.keys.remove(&request);
        Some(request)
    }

    /// Removes every request for these tiles and returns them.
    fn remove_tiles(&mut self, ids: &HashSet<TileId>) -> Vec<Request> {
        let removed: Vec<Request> = self
            .keys
            .keys()
            .filter(|request| ids.contains(&request.id))
            .copied()
            .collect();
        for request in &removed {
            if let Some(key) = self.keys.remove(request) {
                self.order.remove(&key);
            }
        }
        removed
    }

    #[cfg(test)]
    fn len(&self) -> usize {
        self.order.len()
    }
}

#[derive(Debug)]
struct Running {
    ticket: u64,
    handle: TaskHandle,
}

/// What a task sends back when it ends on its own.
#[derive(Debug)]
struct Finished {
    request: Request,
    ticket: u64,
    event: FetchEvent,
}

/// Shared with the tasks, which count as they go.
#[derive(Debug, Default)]
struct Counters {
    bytes_downloaded: AtomicU64,
    requests_started: AtomicU64,
    retries: AtomicU64,
    corrupt_refetches: AtomicU64,
}

/// SplitMix64's finaliser (Steele, Lea and Flood 2014): a cheap, well-mixed hash of a
/// counter, plenty for jitter and no dependency.
fn mix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tile(x: u32, y: u32) -> Request {
        Request {
            id: TileId::new(x, y),
            want: Want::Tile,
        }
    }

    fn drain(queue: &mut RequestQueue) -> Vec<Request> {
        std::iter::from_fn(|| queue.pop()).collect()
    }

    /// Pushes `(request, priority)` in order and checks the order they pop in.
    fn check_queue(pushes: &[(Request, u64)], expected: &[Request]) {
        let mut queue = RequestQueue::default();
        for &(request, priority) in pushes {
            queue.push(request, priority);
        }
        assert_eq!(queue.len(), expected.len(), "queued {pushes:?}");
        assert_eq!(drain(&mut queue), expected, "queued {pushes:?}");
        assert!(queue.keys.is_empty());
    }

    #[test]
    fn requests_start_smallest_priority_first_and_in_arrival_order_among_equals() {
        let (a, b, c, d) = (tile(0, 0), tile(1, 0), tile(2, 0), tile(3, 0));
        check_queue(&[(a, 3), (b, 1), (c, 2)], &[b, c, a]);
        check_queue(&[(a, 1), (b, 1), (c, 0), (d, 1)], &[c, a, b, d]);
        check_queue(&[], &[]);
    }

    #[test]
    fn a_request_queued_twice_is_queued_once_at_its_latest_priority() {
        let (a, b, c) = (tile(0, 0), tile(1, 0), tile(2, 0));
        check_queue(&[(a, 1), (b, 2), (a, 3)], &[b, a]);
        check_queue(&[(a, 5), (b, 2), (a, 0)], &[a, b]);
        // The same priority again keeps its place among equals.
        check_queue(&[(a, 1), (b, 1), (a, 1), (c, 1)], &[a, b, c]);
        let level = Request {
            id: TileId::new(0, 0),
            want: Want::TextureLevel(2),
        };
        check_queue(&[(a, 1), (level, 1), (a, 2)], &[level, a]);
        let mut queue = RequestQueue::default();
        assert!(queue.push(a, 1));
        assert!(!queue.push(a, 0));
        assert!(queue.push(level, 0));
    }

    #[test]
    fn removing_tiles_drops_every_request_for_them_and_keeps_the_rest_in_order() {
        let mut queue = RequestQueue::default();
        let level = Request {
            id: TileId::new(0, 0),
            want: Want::TextureLevel(1),
        };
        for (request, priority) in [
            (tile(0, 0), 0),
            (tile(1, 0), 1),
            (level, 2),
            (tile(2, 0), 3),
        ] {
            queue.push(request, priority);
        }
        let mut removed = queue.remove_tiles(&HashSet::from([TileId::new(0, 0)]));
        removed.sort_by_key(|request| request.want == Want::Tile);
        assert_eq!(removed, [level, tile(0, 0)]);
        assert_eq!(drain(&mut queue), [tile(1, 0), tile(2, 0)]);
    }

    fn backoff_config(base_ms: u64, max_ms: u64) -> FetcherConfig {
        FetcherConfig {
            backoff_base: Duration::from_millis(base_ms),
            backoff_max: Duration::from_millis(max_ms),
            ..FetcherConfig::default()
        }
    }

    #[test]
    fn backoff_stays_within_the_doubling_cap_and_the_maximum() {
        let config = backoff_config(100, 5000);
        let caps_ms = [100, 200, 400, 800, 1600, 3200, 5000, 5000];
        for (retry, cap_ms) in caps_ms.into_iter().enumerate() {
            let cap = Duration::from_millis(cap_ms);
            for random in [0, 1, u64::MAX, u64::MAX / 2, 123_456_789] {
                let delay = backoff_delay(&config, retry as u32, random);
                assert!(delay <= cap, "retry {retry}: {delay:?} > {cap:?}");
            }
            // The top of the range is reachable.
            let top = u64::try_from(cap.as_nanos()).expect("fits");
            assert_eq!(backoff_delay(&config, retry as u32, top), cap);
        }
        // No overflow however many retries.
        for retry in [31, 32, 64, u32::MAX] {
            assert!(backoff_delay(&config, retry, u64::MAX) <= Duration::from_secs(5));
        }
        assert_eq!(
            backoff_delay(&backoff_config(0, 0), 3, 12345),
            Duration::ZERO
        );
    }

    #[test]
    fn jittered_delays_spread_over_their_whole_range() {
        let config = backoff_config(100, 5000);
        let cap = Duration::from_millis(800);
        let delays: Vec<Duration> = (0..1000u64)
            .map(|i| backoff_delay(&config, 3, mix(42 ^ mix(i))))
            .collect();
        assert!(delays.iter().all(|delay| *delay <= cap));
        // Uniform on [0, 800 ms]: every tenth of the range is hit, the mean is near 400 ms.
        for tenth in 0..10u32 {
            let (low, high) = (cap * tenth / 10, cap * (tenth + 1) / 10);
            assert!(
                delays.iter().any(|d| *d >= low && *d < high),
                "no delay in [{low:?}, {high:?})"
            );
        }
        let mean = delays.iter().sum::<Duration>() / delays.len() as u32;
        assert!(
            mean > Duration::from_millis(350) && mean < Duration::from_millis(450),
            "{mean:?}"
        );
    }

    fn http(status: u16) -> FetchError {
        FetchError::Http {
            url: "u".into(),
            status: reqwest::StatusCode::from_u16(status).expect("valid status"),
            body: String::new(),
        }
    }

    #[test]
    fn transient_failures_are_retried_corrupt_bodies_refetched_and_the_rest_reported() {
        let corrupt = FetchError::HashMismatch {
            url: "u".into(),
            expected: "a".into(),
            found: "b".into(),
        };
        let cases = [
            (http(500), FailureKind::Transient),
            (http(503), FailureKind::Transient),
            (http(408), FailureKind::Transient),
            (http(429), FailureKind::Transient),
            (http(404), FailureKind::Permanent),
            (http(400), FailureKind::Permanent),
            (http(410), FailureKind::Permanent),
            (corrupt, FailureKind::Corrupt),
            (
                FetchError::NotInGrid {
                    id: TileId::new(9, 9),
                    columns: 2,
                    rows: 2,
                },
                FailureKind::Permanent,
            ),
            (
                FetchError::NoSuchTextureLevel {
                    id: TileId::new(0, 0),
                    level: 9,
                    levels: 3,
                },
                FailureKind::Permanent,
            ),
            (
                FetchError::Cancelled { url: "u".into() },
                FailureKind::Permanent,
            ),
        ];
        for (error, kind) in cases {
            assert_eq!(FailureKind::of(&error), kind, "{error}");
        }
    }

    #[test]
    fn retries_stop_at_max_attempts_and_corrupt_refetches_at_corrupt_attempts() {
        let config = FetcherConfig {
            max_attempts: 3,
            corrupt_attempts: 2,
            ..FetcherConfig::default()
        };
        use FailureKind::{Corrupt, Permanent, Transient};
        use Verdict::{GiveUp, RetryCorrupt, RetryTransient};
        // (kind, tries so far, corrupt so far) -> verdict
        let cases = [
            (Transient, 1, 0, RetryTransient),
            (Transient, 2, 0, RetryTransient),
            (Transient, 3, 0, GiveUp),
            (Corrupt, 1, 1, RetryCorrupt),
            (Corrupt, 2, 2, GiveUp),
            // A corrupt body after transient failures still has its refetch if tries remain.
            (Corrupt, 2, 1, RetryCorrupt),
            (Corrupt, 3, 1, GiveUp),
            (Transient, 2, 1, RetryTransient),
            (Permanent, 1, 0, GiveUp),
        ];
        for (kind, tries, corrupt, expected) in cases {
            assert_eq!(
                verdict(&config, kind, tries, corrupt),
                expected,
                "{kind:?} after {tries} tries, {corrupt} corrupt"
            );
        }
    }
}
