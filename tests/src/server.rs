//! A real tile server for tests: the library's own [`serve`] on `127.0.0.1:0`, on a
//! background thread with its own tokio runtime, shut down (gracefully) on drop.
//!
//! The server runs on its own runtime so a test may block its own thread (or run a
//! single-threaded runtime) without starving the server it talks to.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;
use terrain_server::db::{TileDb, Verify};
use terrain_server::http::{AppState, ServeOptions, serve};
use tokio::sync::oneshot;

/// Worker threads of the server's runtime: more than one, so tests that hold a request in
/// flight exercise real concurrency, and no more, on a 2-core CI machine.
const SERVER_WORKER_THREADS: usize = 2;

/// A running server. Dropping it shuts it down and waits for it (at most its
/// `shutdown_deadline`).
#[derive(Debug)]
pub struct TestServer {
    addr: SocketAddr,
    base_url: String,
    state: Arc<AppState>,
    shutdown: Option<oneshot::Sender<()>>,
    thread: Option<JoinHandle<std::io::Result<()>>>,
}

impl TestServer {
    /// Serves the database in `db_dir` with the default options.
    pub fn start(db_dir: &Path) -> TestServer {
        Self::start_with(db_dir, ServeOptions::default())
    }

    /// Serves the database in `db_dir` with `options`. Panics if the database does not
    /// open or no port can be bound: a test cannot go on without its server.
    pub fn start_with(db_dir: &Path, options: ServeOptions) -> TestServer {
        Self::start_state(Self::open(db_dir), options)
    }

    /// Serves the database in `db_dir` with the viewer page's files from `viewer` under
    /// `/view/`.
    pub fn start_with_viewer(db_dir: &Path, viewer: &Path) -> TestServer {
        let mut state = Self::open(db_dir);
        state.viewer = Some(viewer.to_path_buf());
        Self::start_state(state, ServeOptions::default())
    }

    fn open(db_dir: &Path) -> AppState {
        let db = TileDb::open(db_dir, Verify::Hashes).unwrap_or_else(|error| {
            panic!(
                "cannot open the test database {}: {error}",
                db_dir.display()
            )
        });
        AppState::new(db)
    }

    fn start_state(state: AppState, options: ServeOptions) -> TestServer {
        let state = Arc::new(state);
        // Bound here, not on the server thread, so the address is known (and connectable:
        // the kernel queues connections) before `start` returns.
        let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("cannot bind 127.0.0.1:0");
        listener
            .set_nonblocking(true)
            .expect("cannot make the listener non-blocking");
        let addr = listener
            .local_addr()
            .expect("cannot read the bound address");
        let (shutdown, stop) = oneshot::channel::<()>();
        let served = Arc::clone(&state);
        let thread = std::thread::Builder::new()
            .name(format!("test-server-{}", addr.port()))
            .spawn(move || {
                let runtime = tokio::runtime::Builder::new_multi_thread()
                    .worker_threads(SERVER_WORKER_THREADS)
                    .enable_all()
                    .build()?;
                runtime.block_on(async move {
                    let listener = tokio::net::TcpListener::from_std(listener)?;
                    // A dropped sender also means stop: the test is gone.
                    serve(listener, served, options, async move {
                        let _ = stop.await;
                    })
                    .await
                })
            })
            .expect("cannot spawn the server thread");
        TestServer {
            addr,
            base_url: format!("http://{addr}"),
            state,
            shutdown: Some(shutdown),
            thread: Some(thread),
        }
    }

    /// `http://127.0.0.1:PORT`, without a trailing slash.
    pub fn base_url(&self) -> &str {
        &self.base_url
    }

    /// The absolute URL of `path` (which starts with `/`).
    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base_url)
    }

    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The state the server shares with its handlers (database, metrics).
    pub fn state(&self) -> &AppState {
        &self.state
    }

    /// Starts a graceful shutdown and returns at once.
    pub fn begin_shutdown(&mut self) {
        if let Some(shutdown) = self.shutdown.take() {
            let _ = shutdown.send(());
        }
    }

    /// Whether `serve` has returned.
    pub fn is_stopped(&self) -> bool {
        self.thread.as_ref().is_none_or(JoinHandle::is_finished)
    }

    /// Shuts down (if not yet begun) and waits for `serve` to return; its result.
    pub fn stop(mut self) -> std::io::Result<()> {
        self.stop_inner()
    }

    fn stop_inner(&mut self) -> std::io::Result<()> {
        self.begin_shutdown();
        match self.thread.take() {
            Some(thread) => match thread.join() {
                Ok(result) => result,
                Err(_) => Err(std::io::Error::other("the server thread panicked")),
            },
            None => Ok(()),
        }
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        let result = self.stop_inner();
        if let Err(error) = result
            && !std::thread::panicking()
        {
            panic!("the test server failed: {error}");
        }
    }
}

/// A server that can be stopped and started again on the same address, which
/// [`TestServer`] (a fresh port each time) cannot do.
#[derive(Debug)]
pub struct RestartableServer {
    db_dir: PathBuf,
    addr: SocketAddr,
    running: Option<(oneshot::Sender<()>, JoinHandle<std::io::Result<()>>)>,
}

impl RestartableServer {
    pub fn start(db_dir: &Path) -> RestartableServer {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind 127.0.0.1:0");
        let addr = listener.local_addr().expect("bound address");
        let mut server = RestartableServer {
            db_dir: db_dir.to_path_buf(),
            addr,
            running: None,
        };
        server.serve(listener);
        server
    }

    pub fn base_url(&self) -> String {
        format!("http://{}", self.addr)
    }

    pub fn stop(&mut self) {
        if let Some((shutdown, thread)) = self.running.take() {
            let _ = shutdown.send(());
            match thread.join() {
                Ok(result) => result.expect("the server failed"),
                Err(_) => panic!("the server thread panicked"),
            }
        }
    }

    /// Binds the same address again: the standard library sets `SO_REUSEADDR` on Unix, so
    /// the old connections in TIME_WAIT do not block it.
    pub fn restart(&mut self) {
        let listener = std::net::TcpListener::bind(self.addr)
            .unwrap_or_else(|error| panic!("cannot bind {} again: {error}", self.addr));
        self.serve(listener);
    }

    fn serve(&mut self, listener: std::net::TcpListener) {
        listener
            .set_nonblocking(true)
            .expect("non-blocking listener");
        let db = TileDb::open(&self.db_dir, Verify::SizesOnly).expect("the database opens");
        let state = Arc::new(AppState::with_verify(db, Verify::SizesOnly));
        // Shutdown drains for at most this long: the test stops the server mid-fetch and
        // should not wait the default 8 s for a connection that never ends.
        let options = ServeOptions {
            shutdown_deadline: Duration::from_millis(200),
            ..ServeOptions::default()
        };
        let (shutdown, stop) = oneshot::channel::<()>();
        let thread = std::thread::spawn(move || {
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()?;
            runtime.block_on(async move {
                let listener = tokio::net::TcpListener::from_std(listener)?;
                serve(listener, state, options, async move {
                    let _ = stop.await;
                })
                .await
            })
        });
        self.running = Some((shutdown, thread));
    }
}

impl Drop for RestartableServer {
    fn drop(&mut self) {
        if let Some((shutdown, thread)) = self.running.take() {
            let _ = shutdown.send(());
            let _ = thread.join();
        }
    }
}
