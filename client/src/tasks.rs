//! Where the fetcher's requests run, and how they wait: the one part of the fetch path that
//! differs between a program and a browser tab.
//!
//! Natively a request is a task on the tokio runtime the fetcher was given, its backoff a
//! `tokio::time::sleep`, a tile's decoding a job on the blocking pool. In the page there is
//! one thread and its event loop: a request is a task of the page's own
//! (`wasm_bindgen_futures::spawn_local`), its backoff a timer of the page's, and decoding
//! runs where the body arrived.

use std::future::Future;
use std::time::Duration;

/// Where requests run: a tokio runtime (natively) or the page's task queue (in a browser).
#[derive(Debug, Clone)]
pub struct Spawner {
    #[cfg(not(target_arch = "wasm32"))]
    runtime: tokio::runtime::Handle,
}

#[cfg(not(target_arch = "wasm32"))]
impl From<tokio::runtime::Handle> for Spawner {
    /// Requests on `runtime`, which needs its time driver (backoff sleeps there).
    fn from(runtime: tokio::runtime::Handle) -> Spawner {
        Spawner { runtime }
    }
}

/// A running task, cancellable.
#[derive(Debug)]
pub struct TaskHandle {
    #[cfg(not(target_arch = "wasm32"))]
    handle: tokio::task::JoinHandle<()>,
    #[cfg(target_arch = "wasm32")]
    abort: futures_util::future::AbortHandle,
    #[cfg(target_arch = "wasm32")]
    finished: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

#[cfg(not(target_arch = "wasm32"))]
impl Spawner {
    /// Runs `task` on the runtime.
    pub fn spawn(&self, task: impl Future<Output = ()> + Send + 'static) -> TaskHandle {
        TaskHandle {
            handle: self.runtime.spawn(task),
        }
    }
}

#[cfg(target_arch = "wasm32")]
impl Spawner {
    /// The page's own task queue.
    pub fn page() -> Spawner {
        Spawner {}
    }

    /// Runs `task` as one of the page's tasks.
    pub fn spawn(&self, task: impl Future<Output = ()> + 'static) -> TaskHandle {
        use std::sync::Arc;
        use std::sync::atomic::{AtomicBool, Ordering};
        let (task, abort) = futures_util::future::abortable(task);
        let finished = Arc::new(AtomicBool::new(false));
        let done = Arc::clone(&finished);
        wasm_bindgen_futures::spawn_local(async move {
            let _ = task.await;
            done.store(true, Ordering::Release);
        });
        TaskHandle { abort, finished }
    }
}

impl TaskHandle {
    /// Stops the task at its next wait; what it would have delivered is never sent.
    pub fn abort(&self) {
        #[cfg(not(target_arch = "wasm32"))]
        self.handle.abort();
        #[cfg(target_arch = "wasm32")]
        {
            self.abort.abort();
            self.finished
                .store(true, std::sync::atomic::Ordering::Release);
        }
    }

    /// Whether the task has ended (finished, failed or aborted).
    pub fn is_finished(&self) -> bool {
        #[cfg(not(target_arch = "wasm32"))]
        return self.handle.is_finished();
        #[cfg(target_arch = "wasm32")]
        return self.finished.load(std::sync::atomic::Ordering::Acquire);
    }
}

/// Waits `delay` (a backoff) without holding the thread.
pub async fn sleep(delay: Duration) {
    #[cfg(not(target_arch = "wasm32"))]
    tokio::time::sleep(delay).await;
    #[cfg(target_arch = "wasm32")]
    gloo_timers::future::sleep(delay).await;
}

/// Runs `work` (milliseconds of CPU, such as decoding a tile) off the async threads: on
/// tokio's blocking pool natively, so it stalls no other request sharing a thread; in the
/// page, where there is one thread, at once. `None` when the work was cancelled.
pub async fn off_thread<T: Send + 'static>(work: impl FnOnce() -> T + Send + 'static) -> Option<T> {
    #[cfg(not(target_arch = "wasm32"))]
    return match tokio::task::spawn_blocking(work).await {
        Ok(done) => Some(done),
        Err(join) => match join.try_into_panic() {
            Ok(panic) => std::panic::resume_unwind(panic),
            Err(_) => None,
        },
    };
    #[cfg(target_arch = "wasm32")]
    return Some(work());
}
