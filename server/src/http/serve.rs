//! The accept loop: how connections are taken, protected and drained.
//!
//! `axum::serve` has no header-read timeout, so connections are served here with hyper's
//! HTTP/1 connection builder directly (as in axum's `serve-with-hyper` example):
//!
//! - every accepted socket gets `TCP_NODELAY`: responses are written whole, and Nagle's
//!   algorithm would only hold back the last segment of each;
//! - a client must send its request head within [`ServeOptions::header_read_timeout`].
//!   hyper arms that timer whenever it waits for a head, so it also closes idle keep-alive
//!   connections and connections that never send anything (slowloris);
//! - at most [`ServeOptions::max_connections`] connections are open at once; beyond that
//!   the loop stops accepting and new clients wait in the kernel's backlog;
//! - on shutdown the listener is closed at once (new connections are refused), each open
//!   connection finishes the response it is sending and closes, and whatever is still open
//!   after [`ServeOptions::shutdown_deadline`] is dropped.
//!
//! The per-request limits (timeout, concurrency limit with load shedding) are tower layers
//! in [`super::app_with`].

use super::AppState;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulShutdown;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::Semaphore;
use tokio::task::JoinSet;
use tower::Service;

/// Long enough for any real client on a slow mobile link, short enough that idle or
/// trickling connections do not pile up (nginx's `client_header_timeout` is 60 s; 10 s is
/// what Go's and Envoy's hardening guides suggest for public servers).
pub const DEFAULT_HEADER_READ_TIMEOUT: Duration = Duration::from_secs(10);
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
    /// Time a client has to send a complete request head (and the longest a keep-alive
    /// connection may sit idle).
    pub header_read_timeout: Duration,
    /// Time from routing a request to its response head; beyond it the answer is 503.
    pub request_timeout: Duration,
    /// Requests in their handler at once; more are shed with 503 rather than queued.
    pub max_concurrent_requests: usize,
    /// Open connections at once; beyond it new connections wait to be accepted.
    pub max_connections: usize,
    /// How long shutdown lets in-flight responses finish before dropping them.
    pub shutdown_deadline: Duration,
}

impl Default for ServeOptions {
    fn default() -> Self {
        ServeOptions {
            header_read_timeout: DEFAULT_HEADER_READ_TIMEOUT,
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
) -> std::io::Result<()> {
    let router = super::app_with(state, &options);
    let mut http = hyper::server::conn::http1::Builder::new();
    http.timer(TokioTimer::new())
        .header_read_timeout(options.header_read_timeout);
    let graceful = GracefulShutdown::new();
    let connection_slots = Arc::new(Semaphore::new(options.max_connections.max(1)));
    let mut connections = JoinSet::new();
    let mut shutdown = std::pin::pin!(shutdown);

    loop {
        // Finished connection tasks are reaped here so the set does not grow without bound.
        while connections.try_join_next().is_some() {}
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
        let router = router.clone();
        let service = hyper::service::service_fn(move |request: hyper::Request<Incoming>| {
            router.clone().call(request)
        });
        let connection = graceful.watch(http.serve_connection(TokioIo::new(stream), service));
        connections.spawn(async move {
            if let Err(error) = connection.await {
                // Header timeouts, resets and clients that vanish mid-response land here:
                // routine on a public server, so not a warning.
                tracing::debug!(%peer, %error, "connection ended with an error");
            }
            drop(slot);
        });
    }

    // Closing the listener first makes new connections fail at once rather than wait in
    // the backlog of a server that will never accept them.
    drop(listener);
    while connections.try_join_next().is_some() {}
    let open = connections.len();
    tracing::info!(open, deadline = ?options.shutdown_deadline, "shutting down: finishing responses in flight");
    tokio::select! {
        () = graceful.shutdown() => tracing::info!("all connections closed"),
        () = tokio::time::sleep(options.shutdown_deadline) => {
            tracing::warn!(open = connections.len(), "shutdown deadline passed: dropping the remaining connections");
        }
    }
    // Dropping the set aborts any connection task still running.
    connections.shutdown().await;
    Ok(())
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
