//! Request metrics in the Prometheus/OpenMetrics text format, and the per-request span.
//!
//! `observe` is the outermost middleware, so it sees every answer, load-shedding 503s
//! and 404s included. It labels by route *template* (axum's `MatchedPath`, e.g.
//! `/v1/{content_version}/tiles/{x}/{y}/heights`), never by the raw URL: one time series
//! per route and status, however many tiles or hostile paths there are.
//!
//! What is counted:
//! - `http_requests_total{route,status}`: answers, counted when the response head is ready;
//! - `http_request_duration_seconds{route}`: time from routing to response head;
//! - `http_response_body_bytes_total{route,status}`: body bytes handed to the connection
//!   (after gzip, so the manifest counts what went on the wire);
//! - `http_requests_in_flight`: requests between routing and the end of their body;
//! - `database_reloads_total`: rebuilt databases put in place of the one served;
//! - the cache of hot blobs ([`crate::store::BlobCache`]): `blob_cache_requests_total`
//!   (blob bodies asked of it), its loads on a miss (`store_gets_total`,
//!   `store_get_errors_total`, `store_read_bytes_total` for a database in an object store;
//!   `pack_reads_total`, `pack_read_errors_total`, `pack_read_bytes_total` for a
//!   directory), and the gauges `blob_cache_bytes` (held), `blob_cache_capacity_bytes` and
//!   `blob_cache_hit_ratio` (1 - loads / requests, since the start).

use super::AppState;
use axum::body::{Body, HttpBody};
use axum::extract::{MatchedPath, Request, State};
use axum::middleware::Next;
use axum::response::Response;
use bytes::Bytes;
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Instant;
use tracing::Instrument;

/// Content type of [`Metrics::encode`]'s output.
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";
/// Route label of requests that matched no route (the 404 fallback).
pub const UNMATCHED_ROUTE: &str = "unmatched";

#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RouteLabels {
    route: &'static str,
}

#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RouteStatusLabels {
    route: &'static str,
    status: u16,
}

/// The route template as a label that costs no allocation per request. Templates are a
/// fixed set (the router's routes); each is made `'static` the first time it is seen and
/// kept for the life of the process.
fn route_label(template: &str) -> &'static str {
    static SEEN: std::sync::RwLock<Vec<&'static str>> = std::sync::RwLock::new(Vec::new());
    let known = |seen: &[&'static str]| seen.iter().copied().find(|t| *t == template);
    if let Some(label) = known(
        &SEEN
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner),
    ) {
        return label;
    }
    let mut seen = SEEN
        .write()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    if let Some(label) = known(&seen) {
        return label;
    }
    // Bounded: `MatchedPath` only ever holds one of the router's templates.
    let label: &'static str = Box::leak(template.to_owned().into_boxed_str());
    seen.push(label);
    label
}

/// The server's counters, shared by every request through [`AppState`].
#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
struct ReasonLabels {
    reason: &'static str,
}

#[derive(Debug)]
pub struct Metrics {
    registry: Registry,
    closed: Family<ReasonLabels, Counter>,
    requests: Family<RouteStatusLabels, Counter>,
    body_bytes: Family<RouteStatusLabels, Counter>,
    latency: Family<RouteLabels, Histogram, fn() -> Histogram>,
    in_flight: Gauge,
    reloads: Counter,
    cache: Option<CacheGauges>,
}

/// The gauges of a store's cache, set from it each time the metrics are read.
#[derive(Debug)]
struct CacheGauges {
    cache: Arc<crate::store::BlobCache>,
    held: Gauge,
    capacity: Gauge,
    hit_ratio: Gauge<f64, std::sync::atomic::AtomicU64>,
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    pub fn new() -> Metrics {
        let requests = Family::<RouteStatusLabels, Counter>::default();
        let body_bytes = Family::<RouteStatusLabels, Counter>::default();
        let latency = Family::<RouteLabels, Histogram, fn() -> Histogram>::new_with_constructor(
            latency_histogram,
        );
        let in_flight = Gauge::default();
        let closed = Family::<ReasonLabels, Counter>::default();
        let mut registry = Registry::default();
        registry.register(
            "http_connections_closed_by_server",
            "Connections the server closed itself: idle, evicted to make room, write timeout",
            closed.clone(),
        );
        registry.register(
            "http_requests",
            "HTTP requests answered, by route template and status",
            requests.clone(),
        );
        registry.register(
            "http_response_body_bytes",
            "Response body bytes sent, by route template and status",
            body_bytes.clone(),
        );
        registry.register(
            "http_request_duration_seconds",
            "Time from routing to response head, by route template",
            latency.clone(),
        );
        registry.register(
            "http_requests_in_flight",
            "Requests being answered, bodies included",
            in_flight.clone(),
        );
        let reloads = Counter::default();
        registry.register(
            "database_reloads",
            "Rebuilt databases served in place of the one before (SIGHUP or the directory's poll)",
            reloads.clone(),
        );
        Metrics {
            registry,
            reloads,
            closed,
            requests,
            body_bytes,
            latency,
            in_flight,
            cache: None,
        }
    }

    /// Reports the counters and gauges of the cache of hot blobs: its loads named for what
    /// they are, GETs to an object store (`from_store`) or reads of a local pack.
    pub fn register_cache(&mut self, cache: Arc<crate::store::BlobCache>, from_store: bool) {
        let r = &mut self.registry;
        let (loads, errors, bytes) = if from_store {
            (
                (
                    "store_gets",
                    "Ranged GETs sent to the object store (cache misses)",
                ),
                (
                    "store_get_errors",
                    "GETs to the object store that failed after retries, or returned other bytes than their hash names",
                ),
                (
                    "store_read_bytes",
                    "Bytes read from the object store that matched their hash",
                ),
            )
        } else {
            (
                (
                    "pack_reads",
                    "Blobs read from the local packs (cache misses)",
                ),
                (
                    "pack_read_errors",
                    "Reads of the local packs that failed or did not match their hash (a pack changed)",
                ),
                (
                    "pack_read_bytes",
                    "Bytes read from the local packs that matched their hash",
                ),
            )
        };
        r.register(
            "blob_cache_requests",
            "Blob bodies asked of the cache of hot blobs",
            cache.requests.clone(),
        );
        r.register(loads.0, loads.1, cache.loads.clone());
        r.register(errors.0, errors.1, cache.load_errors.clone());
        r.register(bytes.0, bytes.1, cache.loaded_bytes.clone());
        let gauges = CacheGauges {
            cache,
            held: Gauge::default(),
            capacity: Gauge::default(),
            hit_ratio: Gauge::default(),
        };
        r.register(
            "blob_cache_bytes",
            "Bytes the cache of hot blobs holds",
            gauges.held.clone(),
        );
        r.register(
            "blob_cache_capacity_bytes",
            "The cache's limit in bytes (serve --cache-bytes)",
            gauges.capacity.clone(),
        );
        r.register(
            "blob_cache_hit_ratio",
            "Blob requests answered without a load, since the start",
            gauges.hit_ratio.clone(),
        );
        self.cache = Some(gauges);
    }

    /// The whole registry in the OpenMetrics text format.
    /// A request head that hyper answered itself (400, 414, 431) before any route saw it:
    /// counted under the [`UNMATCHED_ROUTE`] label.
    pub fn refused_head(&self, status: u16) {
        self.requests
            .get_or_create(&RouteStatusLabels {
                route: UNMATCHED_ROUTE,
                status,
            })
            .inc();
    }

    /// A rebuilt database served in place of the one before.
    pub fn reloaded(&self) {
        self.reloads.inc();
    }

    /// A connection the server closed itself.
    pub fn connection_closed(&self, reason: super::serve::CloseReason) {
        self.closed
            .get_or_create(&ReasonLabels {
                reason: reason.label(),
            })
            .inc();
    }

    pub fn encode(&self) -> Result<String, std::fmt::Error> {
        if let Some(gauges) = &self.cache {
            let requests = gauges.cache.requests.get();
            let loads = gauges.cache.loads.get();
            gauges.held.set(gauges.cache.held() as i64);
            gauges.capacity.set(gauges.cache.capacity() as i64);
            let ratio = if requests == 0 {
                0.0
            } else {
                1.0 - loads.min(requests) as f64 / requests as f64
            };
            gauges.hit_ratio.set(ratio);
        }
        let mut text = String::new();
        prometheus_client::encoding::text::encode(&mut text, &self.registry)?;
        Ok(text)
    }
}

/// Buckets from 50 us (a tile answered from the map) doubling to about 1.6 s (a request
/// stuck behind an overloaded runtime): 16 buckets, one decade every ~3.3 of them.
fn latency_histogram() -> Histogram {
    Histogram::new(exponential_buckets(50e-6, 2.0, 16))
}

/// Middleware: one span per request, the counters above, and one log line per answer.
pub(super) async fn observe(
    State(state): State<Arc<AppState>>,
    request: Request,
    next: Next,
) -> Response {
    let started = Instant::now();
    let route = match request.extensions().get::<MatchedPath>() {
        Some(path) => route_label(path.as_str()),
        None => UNMATCHED_ROUTE,
    };
    let method = request.method().clone();
    let span = tracing::debug_span!("request", %method, %route);
    let metrics = &state.metrics;
    metrics.in_flight.inc();
    let in_flight = InFlight(metrics.in_flight.clone());

    let response = next.run(request).instrument(span.clone()).await;

    let latency = started.elapsed();
    let status = response.status();
    let labels = RouteStatusLabels {
        route,
        status: status.as_u16(),
    };
    metrics.requests.get_or_create(&labels).inc();
    let bytes = metrics.body_bytes.get_or_create_owned(&labels);
    metrics
        .latency
        .get_or_create(&RouteLabels {
            route: labels.route,
        })
        .observe(latency.as_secs_f64());

    let _entered = span.enter();
    let latency_us = latency.as_micros() as u64;
    if status.is_server_error() {
        tracing::warn!(status = status.as_u16(), latency_us, "answered");
    } else {
        tracing::debug!(status = status.as_u16(), latency_us, "answered");
    }
    response.map(|body| {
        Body::new(CountedBody {
            inner: body,
            bytes,
            _in_flight: in_flight,
        })
    })
}

/// Decrements the in-flight gauge when the response body is finished or dropped.
#[derive(Debug)]
struct InFlight(Gauge);

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.dec();
    }
}

/// A response body that counts the bytes the connection takes from it.
#[derive(Debug)]
struct CountedBody {
    inner: Body,
    bytes: Counter,
    _in_flight: InFlight,
}

impl HttpBody for CountedBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, axum::Error>>> {
        // `Body` is `Unpin` (it boxes its inner body), so no pin projection is needed.
        let polled = Pin::new(&mut self.inner).poll_frame(cx);
        if let Poll::Ready(Some(Ok(frame))) = &polled
            && let Some(data) = frame.data_ref()
        {
            self.bytes.inc_by(data.len() as u64);
        }
        polled
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}
