//! The accept loop: how connections are taken, protected and drained.
//!
//! `axum::serve` has no header-read timeout, so connections are served here with
//! hyper-util's connection builder directly (as in axum's `serve-with-hyper` example). It
//! speaks HTTP/1.1 and, to clients that know it in advance, HTTP/2 over cleartext (h2c
//! prior knowledge); the first bytes tell which.
//!
//! - every accepted socket gets `TCP_NODELAY`: responses are written whole, and Nagle's
//!   algorithm would only hold back the last segment of each;
//! - a connection with no request in progress for [`ServeOptions::header_read_timeout`]
//!   is closed: one that never sends anything (slowloris), one trickling its head, and an
//!   idle keep-alive connection alike;
//! - a response whose bytes make no progress for [`ServeOptions::write_timeout`] (a
//!   client that asks and never reads) ends its connection, as nginx's `send_timeout`;
//! - at most [`ServeOptions::max_connections`] connections are open at once. When all are
//!   taken, the oldest connection with no request in progress is closed to make room, so
//!   a crowd of idle connections cannot lock new clients out; only when every connection
//!   is busy do new ones wait in the kernel's backlog;
//! - a request head too large for hyper (414, 431) never reaches the router; it is
//!   counted in `/metrics` from the connection's error;
//! - on shutdown the listener is closed at once (new connections are refused), each open
//!   connection finishes the response it is sending and closes, and whatever is still open
//!   after [`ServeOptions::shutdown_deadline`] is dropped.
//!
//! The per-request limits (timeout, concurrency limit with load shedding) are tower layers
//! in [`super::app_with`].

use super::AppState;
use axum::body::{Body, HttpBody};
use bytes::Bytes;
use hyper::body::Incoming;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use std::collections::BTreeMap;
use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Notify, Semaphore, watch};
use tokio::task::JoinSet;
use tower::Service;

/// Long enough for any real client on a slow mobile link, short enough that idle or
/// trickling connections do not pile up (nginx's `client_header_timeout` is 60 s; 10 s is
/// what Go's and Envoy's hardening guides suggest for public servers).
pub const DEFAULT_HEADER_READ_TIMEOUT: Duration = Duration::from_secs(10);
/// A response that makes no progress for this long is abandoned: the client stopped
/// reading. Progress, not total time, is bounded, so a slow link still gets a large body.
pub const DEFAULT_WRITE_TIMEOUT: Duration = Duration::from_secs(10);
/// Tile handlers answer in microseconds; a request still unanswered after this long is
/// stuck, and the client is better served by a 503 it can retry.
pub const DEFAULT_REQUEST_TIMEOUT: Duration = Duration::from_secs(10);
/// Requests handled at once before new ones are refused with 503. The tile handlers never
/// wait on anything, so this rarely binds; it caps the damage if one ever does.
pub const DEFAULT_MAX_CONCURRENT_REQUESTS: usize = 1024;
/// Open connections at once. Each costs a file descriptor and a few KiB; 4096 stays well
/// inside the usual 65536 descriptor limit of a container.
pub const DEFAULT_MAX_CONNECTIONS: usize = 4096;
/// How long shutdown waits for responses in flight. Below Docker's 10 s between SIGTERM
/// and SIGKILL, so the server exits on its own terms.
pub const DEFAULT_SHUTDOWN_DEADLINE: Duration = Duration::from_secs(8);

/// Limits of [`serve`] and of the layers in [`super::app_with`].
#[derive(Debug, Clone)]
pub struct ServeOptions {
    /// Time a connection may go without a request in progress: to send a complete
    /// request head after connecting, and between requests on a keep-alive connection.
    pub header_read_timeout: Duration,
    /// Time a response may make no progress (the client not reading) before its
    /// connection is closed.
    pub write_timeout: Duration,
    /// Time from routing a request to its response head; beyond it the answer is 503.
    pub request_timeout: Duration,
    /// Requests in their handler at once; more are shed with 503 rather than queued.
    pub max_concurrent_requests: usize,
    /// Open connections at once; beyond it the oldest idle one is closed, or, when none
    /// is idle, new connections wait to be accepted.
    pub max_connections: usize,
    /// How long shutdown lets in-flight responses finish before dropping them.
    pub shutdown_deadline: Duration,
}

impl Default for ServeOptions {
    fn default() -> Self {
        ServeOptions {
            header_read_timeout: DEFAULT_HEADER_READ_TIMEOUT,
            write_timeout: DEFAULT_WRITE_TIMEOUT,
            request_timeout: DEFAULT_REQUEST_TIMEOUT,
            max_concurrent_requests: DEFAULT_MAX_CONCURRENT_REQUESTS,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            shutdown_deadline: DEFAULT_SHUTDOWN_DEADLINE,
        }
    }
}

/// Serves [`super::app_with`] on `listener` until `shutdown` resolves, then drains
/// connections for at most `options.shutdown_deadline`.
///
/// Returns once every connection is closed or dropped. Errors of single connections are
/// logged, not returned: one bad client never stops the server.
pub async fn serve(
    listener: TcpListener,
    state: Arc<AppState>,
    options: ServeOptions,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> io::Result<()> {
    let router = super::app_with(Arc::clone(&state), &options);
    let mut http = hyper_util::server::conn::auto::Builder::new(TokioExecutor::new());
    // No hyper header-read timer: it arms one per request. The connection's own watchdog
    // below closes a connection with no request in progress (trickling or idle) for both
    // protocols, with one timer per connection.
    http.http1()
        .timer(TokioTimer::new())
        .header_read_timeout(None);
    http.http2().timer(TokioTimer::new());
    let http = Arc::new(http);
    let table = Arc::new(ConnectionTable::default());
    let connection_slots = Arc::new(Semaphore::new(options.max_connections.max(1)));
    let (stop_tx, stop_rx) = watch::channel(false);
    let mut connections = JoinSet::new();
    let mut shutdown = std::pin::pin!(shutdown);

    loop {
        // Finished connection tasks are reaped here so the set does not grow without bound.
        while connections.try_join_next().is_some() {}
        if connection_slots.available_permits() == 0 && table.close_oldest_idle() {
            state.metrics.connection_closed(CloseReason::Evicted);
        }
        let slot = tokio::select! {
            slot = Arc::clone(&connection_slots).acquire_owned() => slot,
            () = &mut shutdown => break,
        };
        let Ok(slot) = slot else { break };
        let (stream, peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(error) => {
                    accept_error(error).await;
                    continue;
                }
            },
            () = &mut shutdown => break,
        };
        if let Err(error) = stream.set_nodelay(true) {
            tracing::debug!(%peer, %error, "cannot set TCP_NODELAY");
        }
        let tracker = table.open();
        let service = {
            let router = router.clone();
            let tracker = Arc::clone(&tracker);
            hyper::service::service_fn(move |request: hyper::Request<Incoming>| {
                let busy = Busy::begin(&tracker);
                let response = router.clone().call(request);
                async move {
                    let response = response.await?;
                    Ok::<_, std::convert::Infallible>(response.map(|body| {
                        Body::new(BusyBody {
                            inner: body,
                            _busy: busy,
                        })
                    }))
                }
            })
        };
        let io = TokioIo::new(WriteTimeout::new(stream, options.write_timeout));
        let http = Arc::clone(&http);
        let state = Arc::clone(&state);
        let table = Arc::clone(&table);
        let mut stop = stop_rx.clone();
        let idle_timeout = options.header_read_timeout;
        connections.spawn(async move {
            let connection = http.serve_connection(io, service);
            let mut connection = std::pin::pin!(connection);
            let mut closing = false;
            // Set when the connection is closed for being idle: hyper closes an idle
            // connection at once on a graceful shutdown, but not one halfway through a
            // request head (a trickle), which is dropped when this grace runs out.
            let mut drop_at: Option<tokio::time::Instant> = None;
            let result = loop {
                let idle_for = tracker.idle_for();
                let idle_check =
                    tokio::time::sleep(idle_timeout.saturating_sub(idle_for.unwrap_or_default()));
                let dropped = async {
                    match drop_at {
                        Some(at) => tokio::time::sleep_until(at).await,
                        None => std::future::pending().await,
                    }
                };
                tokio::select! {
                    result = connection.as_mut() => break result,
                    () = dropped => break Ok(()),
                    () = tracker.close.notified(), if !closing => {
                        closing = true;
                        connection.as_mut().graceful_shutdown();
                    }
                    _ = stop.wait_for(|stop| *stop), if !closing => {
                        closing = true;
                        connection.as_mut().graceful_shutdown();
                    }
                    () = idle_check, if !closing => {
                        if tracker.idle_for().is_some_and(|idle| idle >= idle_timeout) {
                            closing = true;
                            state.metrics.connection_closed(CloseReason::Idle);
                            connection.as_mut().graceful_shutdown();
                            drop_at = Some(
                                tokio::time::Instant::now() + idle_timeout.min(IDLE_CLOSE_GRACE),
                            );
                        }
                    }
                }
            };
            if let Err(error) = result {
                connection_error(&state, peer, &*error);
            }
            table.close(&tracker);
            drop(slot);
        });
    }

    // Closing the listener first makes new connections fail at once rather than wait in
    // the backlog of a server that will never accept them.
    drop(listener);
    while connections.try_join_next().is_some() {}
    let open = connections.len();
    tracing::info!(open, deadline = ?options.shutdown_deadline, "shutting down: finishing responses in flight");
    let _ = stop_tx.send(true);
    let drained = async { while connections.join_next().await.is_some() {} };
    tokio::select! {
        () = drained => tracing::info!("all connections closed"),
        () = tokio::time::sleep(options.shutdown_deadline) => {
            tracing::warn!(open = connections.len(), "shutdown deadline passed: dropping the remaining connections");
        }
    }
    // Dropping the set aborts any connection task still running.
    connections.shutdown().await;
    Ok(())
}

/// Logs a connection's error and counts the request heads hyper refused itself.
fn connection_error(
    state: &AppState,
    peer: std::net::SocketAddr,
    error: &(dyn std::error::Error + 'static),
) {
    if let Some(error) = error.downcast_ref::<hyper::Error>() {
        if error.is_parse_too_large() {
            // hyper answered 414 or 431 before any route saw the request.
            let status = if error.to_string().contains("URI") {
                414
            } else {
                431
            };
            state.metrics.refused_head(status);
        } else if error.is_parse() && !error.is_parse_version_h2() {
            state.metrics.refused_head(400);
        }
    }
    let chain = ErrorChain(error).to_string();
    if chain.contains(WRITE_TIMED_OUT) {
        state.metrics.connection_closed(CloseReason::WriteTimeout);
    }
    // Header timeouts, resets and clients that vanish mid-response land here: routine on
    // a public server, so not a warning.
    tracing::debug!(%peer, error = %chain, "connection ended with an error");
}

const WRITE_TIMED_OUT: &str = "write timed out";

/// How long a connection closed for being idle may take to close on its own before it is
/// dropped. Nothing is in progress on it, so nothing is lost.
const IDLE_CLOSE_GRACE: Duration = Duration::from_secs(1);

/// Why the server closed a connection itself (counted in `/metrics`).
#[derive(Debug, Clone, Copy)]
pub enum CloseReason {
    /// No request in progress for the idle timeout.
    Idle,
    /// Closed to make room for a new connection while all slots were taken.
    Evicted,
    /// Its response made no progress for the write timeout.
    WriteTimeout,
}

impl CloseReason {
    pub fn label(self) -> &'static str {
        match self {
            CloseReason::Idle => "idle",
            CloseReason::Evicted => "evicted",
            CloseReason::WriteTimeout => "write_timeout",
        }
    }
}

/// An error and its causes on one line.
struct ErrorChain<'a>(&'a (dyn std::error::Error + 'static));

impl std::fmt::Display for ErrorChain<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.0)?;
        let mut source = self.0.source();
        while let Some(cause) = source {
            write!(f, ": {cause}")?;
            source = cause.source();
        }
        Ok(())
    }
}

/// The open connections, oldest first, with whether each has a request in progress.
#[derive(Debug, Default)]
struct ConnectionTable {
    next_id: AtomicU64,
    open: Mutex<BTreeMap<u64, Arc<Tracker>>>,
}

impl ConnectionTable {
    fn open(&self) -> Arc<Tracker> {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let tracker = Arc::new(Tracker {
            id,
            busy: AtomicUsize::new(0),
            idle_since: Mutex::new(Some(Instant::now())),
            closing: AtomicBool::new(false),
            close: Notify::new(),
        });
        self.lock().insert(id, Arc::clone(&tracker));
        tracker
    }

    fn close(&self, tracker: &Tracker) {
        self.lock().remove(&tracker.id);
    }

    /// Asks the oldest connection with no request in progress to close. False when every
    /// connection is busy (or already closing).
    fn close_oldest_idle(&self) -> bool {
        let open = self.lock();
        let oldest_idle = open.values().find(|tracker| {
            tracker.busy.load(Ordering::Acquire) == 0 && !tracker.closing.load(Ordering::Acquire)
        });
        match oldest_idle {
            Some(tracker) => {
                tracker.closing.store(true, Ordering::Release);
                // `notify_one` keeps a permit, so the task sees it even if not waiting yet.
                tracker.close.notify_one();
                true
            }
            None => false,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, Arc<Tracker>>> {
        // A panic while holding this lock cannot leave the map inconsistent (each
        // operation is a single insert, remove or read), so a poisoned lock is still usable.
        self.open
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// One connection's state as the accept loop sees it.
#[derive(Debug)]
struct Tracker {
    id: u64,
    /// Requests received whose response body has not been sent yet.
    busy: AtomicUsize,
    /// Since when no request has been in progress (`None` while one is).
    idle_since: Mutex<Option<Instant>>,
    closing: AtomicBool,
    close: Notify,
}

impl Tracker {
    fn idle_for(&self) -> Option<Duration> {
        let idle_since = self
            .idle_since
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        idle_since.map(|since| since.elapsed())
    }

    fn set_idle_since(&self, since: Option<Instant>) {
        *self
            .idle_since
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = since;
    }
}

/// A request in progress on its connection, from its head until its body is sent.
#[derive(Debug)]
struct Busy(Arc<Tracker>);

impl Busy {
    fn begin(tracker: &Arc<Tracker>) -> Busy {
        if tracker.busy.fetch_add(1, Ordering::AcqRel) == 0 {
            tracker.set_idle_since(None);
        }
        Busy(Arc::clone(tracker))
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        if self.0.busy.fetch_sub(1, Ordering::AcqRel) == 1 {
            self.0.set_idle_since(Some(Instant::now()));
        }
    }
}

/// A response body that keeps its connection marked busy until it is sent (or dropped).
#[derive(Debug)]
struct BusyBody {
    inner: Body,
    _busy: Busy,
}

impl HttpBody for BusyBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, axum::Error>>> {
        // `Body` is `Unpin` (it boxes its inner body), so no pin projection is needed.
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// A socket whose writes fail with `TimedOut` once they have made no progress for the
/// write timeout: the peer's receive window stayed closed (it stopped reading).
#[derive(Debug)]
struct WriteTimeout {
    stream: TcpStream,
    timeout: Duration,
    /// Armed when a write first returns `Pending`, disarmed by any progress.
    stalled: Option<Pin<Box<tokio::time::Sleep>>>,
}

impl WriteTimeout {
    fn new(stream: TcpStream, timeout: Duration) -> WriteTimeout {
        WriteTimeout {
            stream,
            timeout,
            stalled: None,
        }
    }

    /// After a write returned `Pending`: an error once the stall outlasts the timeout.
    fn check_stall(&mut self, cx: &mut Context<'_>) -> Poll<io::Error> {
        let timeout = self.timeout;
        let stalled = self
            .stalled
            .get_or_insert_with(|| Box::pin(tokio::time::sleep(timeout)));
        match stalled.as_mut().poll(cx) {
            Poll::Ready(()) => Poll::Ready(io::Error::new(
                io::ErrorKind::TimedOut,
                format!("{WRITE_TIMED_OUT}: no progress for {timeout:?}"),
            )),
            Poll::Pending => Poll::Pending,
        }
    }

    fn progressed<T>(
        &mut self,
        polled: Poll<io::Result<T>>,
        cx: &mut Context<'_>,
    ) -> Poll<io::Result<T>> {
        match polled {
            Poll::Ready(result) => {
                self.stalled = None;
                Poll::Ready(result)
            }
            Poll::Pending => self.check_stall(cx).map(Err),
        }
    }
}

impl AsyncRead for WriteTimeout {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_read(cx, buf)
    }
}

impl AsyncWrite for WriteTimeout {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let polled = Pin::new(&mut self.stream).poll_write(cx, buf);
        self.progressed(polled, cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let polled = Pin::new(&mut self.stream).poll_write_vectored(cx, bufs);
        self.progressed(polled, cx)
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let polled = Pin::new(&mut self.stream).poll_flush(cx);
        self.progressed(polled, cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }
}

/// Resolves on the first SIGINT (Ctrl-C) or SIGTERM (`docker stop`, Kubernetes).
///
/// If a handler cannot be installed that signal is logged and ignored; the other still works.
pub async fn shutdown_signal() {
    let interrupt = async {
        match tokio::signal::ctrl_c().await {
            Ok(()) => tracing::info!("SIGINT received"),
            Err(error) => {
                tracing::error!(%error, "cannot listen for SIGINT");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(unix)]
    let terminate = async {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut signal) => {
                signal.recv().await;
                tracing::info!("SIGTERM received");
            }
            Err(error) => {
                tracing::error!(%error, "cannot listen for SIGTERM");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        () = interrupt => {}
        () = terminate => {}
    }
}

/// Per-connection accept errors (the peer reset before we took it) are retried at once;
/// others (out of file descriptors) get a pause so the loop does not spin on them, as
/// `axum::serve` does.
async fn accept_error(error: std::io::Error) {
    use std::io::ErrorKind::{ConnectionAborted, ConnectionRefused, ConnectionReset};
    if matches!(
        error.kind(),
        ConnectionAborted | ConnectionRefused | ConnectionReset
    ) {
        return;
    }
    tracing::error!(%error, "accept failed; pausing for a second");
    tokio::time::sleep(Duration::from_secs(1)).await;
}
