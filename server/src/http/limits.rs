//! The tile API's per-request limits in one layer: a server-wide cap on requests in their
//! handler, with load shedding (503 at once, never a queue), and a request timeout (503).
//!
//! One layer rather than tower's `LoadShed` + `GlobalConcurrencyLimit` + `Timeout` +
//! `HandleError`: tile handlers answer in their first poll, so the timer is armed only
//! when a handler does not (tower's timeout arms one per request), and the permit is taken
//! with `try_acquire`, without a future.

use super::error::HttpError;
use axum::extract::Request;
use axum::response::{IntoResponse, Response};
use std::convert::Infallible;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// Wraps each route of the tile API; every clone shares one semaphore, so the limit is
/// per server, not per route.
#[derive(Debug, Clone)]
pub(super) struct TileLimitsLayer {
    permits: Arc<Semaphore>,
    timeout: Duration,
}

impl TileLimitsLayer {
    pub(super) fn new(max_concurrent_requests: usize, timeout: Duration) -> TileLimitsLayer {
        TileLimitsLayer {
            permits: Arc::new(Semaphore::new(max_concurrent_requests.max(1))),
            timeout,
        }
    }
}

impl<S> tower::Layer<S> for TileLimitsLayer {
    type Service = TileLimits<S>;

    fn layer(&self, inner: S) -> TileLimits<S> {
        TileLimits {
            inner,
            permits: Arc::clone(&self.permits),
            timeout: self.timeout,
        }
    }
}

#[derive(Debug, Clone)]
pub(super) struct TileLimits<S> {
    inner: S,
    permits: Arc<Semaphore>,
    timeout: Duration,
}

impl<S> tower::Service<Request> for TileLimits<S>
where
    S: tower::Service<Request, Response = Response, Error = Infallible>,
{
    type Response = Response;
    type Error = Infallible;
    type Future = LimitedFuture<S::Future>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: Request) -> Self::Future {
        match Arc::clone(&self.permits).try_acquire_owned() {
            Ok(permit) => LimitedFuture::Running {
                inner: self.inner.call(request),
                permit,
                timeout: self.timeout,
                timer: None,
            },
            Err(_) => LimitedFuture::Shed,
        }
    }
}

pin_project_lite::pin_project! {
    /// A routed request under its permit, or shed.
    #[project = LimitedProj]
    pub(super) enum LimitedFuture<F> {
        Running {
            #[pin]
            inner: F,
            permit: OwnedSemaphorePermit,
            timeout: Duration,
            timer: Option<Pin<Box<tokio::time::Sleep>>>,
        },
        Shed,
    }
}

impl<F> Future for LimitedFuture<F>
where
    F: Future<Output = Result<Response, Infallible>>,
{
    type Output = Result<Response, Infallible>;

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        match self.project() {
            LimitedProj::Shed => Poll::Ready(Ok(HttpError::Overloaded.into_response())),
            LimitedProj::Running {
                inner,
                permit: _,
                timeout,
                timer,
            } => {
                if let Poll::Ready(answer) = inner.poll(cx) {
                    return Poll::Ready(answer);
                }
                let timeout = *timeout;
                let timer = timer.get_or_insert_with(|| Box::pin(tokio::time::sleep(timeout)));
                match timer.as_mut().poll(cx) {
                    Poll::Ready(()) => Poll::Ready(Ok(HttpError::Timeout(timeout).into_response())),
                    Poll::Pending => Poll::Pending,
                }
            }
        }
    }
}
