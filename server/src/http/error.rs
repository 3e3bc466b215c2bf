//! Every way a request can fail, and the one place that turns a failure into a response.
//!
//! Handlers and middleware return [`HttpError`]; its [`IntoResponse`] picks the status and
//! writes the same short JSON body for all of them, `{"error":"...","status":404}`, so a
//! client (or a person with curl) always gets a machine-readable reason and never axum's
//! plain-text rejections.

use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use std::time::Duration;
use terrain_shared::TileId;
use terrain_shared::routes::MANIFEST;
use thiserror::Error;

/// Why a request was not answered with the resource it asked for.
#[derive(Debug, Error)]
pub enum HttpError {
    /// A path segment that must be a tile coordinate or a texture level is not one.
    #[error(
        "malformed {segment} {value:?}: expected a decimal integer from 0 to 4294967295 without sign or leading zeros"
    )]
    MalformedNumber {
        segment: &'static str,
        value: String,
    },
    /// The path could not be split into its parameters (e.g. invalid percent-encoding).
    #[error("malformed path: {reason}")]
    MalformedPath { reason: String },
    /// A tile URL spelled another way than the one the API gives it: each tile has one
    /// URL, so a cache in front of the server cannot be filled or bypassed by respelling.
    #[error("{reason}; a tile URL has one spelling: {canonical}")]
    NotCanonical {
        reason: &'static str,
        canonical: &'static str,
    },
    #[error("tile {id} is outside the {columns}x{rows} grid of its level")]
    TileOutsideGrid { id: TileId, columns: u32, rows: u32 },
    #[error("level {level} does not exist: the pyramid has levels 0 to {last}")]
    NoSuchLevel { level: u32, last: u32 },
    #[error("tile {id} has texture levels 0 to {last}, not {level}")]
    NoSuchTextureLevel { id: TileId, level: u32, last: u32 },
    /// The URL names a database this server does not serve (usually the previous build):
    /// the client should fetch the manifest again.
    #[error(
        "content version {requested:?} is not served; the current one is {current:?} (see {MANIFEST})"
    )]
    UnknownContentVersion { requested: String, current: String },
    #[error("no such route")]
    NoRoute,
    /// The database was built without quadtree patches.
    #[error(
        "this database has no quadtree patches: build it with `terrain-server build --patches`"
    )]
    NoPatches,
    /// The database has no web tiles (MapLibre's and Cesium's routes).
    #[error(
        "this database has no web tiles: its source is not georeferenced (GeoTIFF tags, an .hgt name or dataset.json bounds), or it was built with --no-web"
    )]
    NoWeb,
    #[error(
        "no {what} tile {z}/{x}/{y}: the terrain does not reach it, or it is past the finest zoom {max_zoom}"
    )]
    NoWebTile {
        what: &'static str,
        z: u32,
        x: u32,
        y: u32,
        max_zoom: u32,
    },
    /// A document naming absolute URLs was asked with a Host header that is not a host.
    #[error(
        "the Host header is not a host name or address with an optional port; give the server --public-url behind a proxy"
    )]
    BadHost,
    #[error("method not allowed: this API only answers GET and HEAD")]
    MethodNotAllowed,
    /// Load shedding: the concurrency limit is reached, and waiting in a queue would only
    /// add latency for every client, so the request is refused at once.
    #[error("the server is at its limit of concurrent requests; retry shortly")]
    Overloaded,
    #[error("the request took longer than {0:?}")]
    Timeout(Duration),
    /// The object store behind the server did not answer for a blob not in its cache.
    #[error("the tile store is unavailable; retry shortly: {0}")]
    StoreUnavailable(String),
    #[error("internal error: {0}")]
    Internal(String),
}

impl HttpError {
    pub fn status(&self) -> StatusCode {
        match self {
            HttpError::MalformedNumber { .. }
            | HttpError::MalformedPath { .. }
            | HttpError::NotCanonical { .. }
            | HttpError::BadHost => StatusCode::BAD_REQUEST,
            HttpError::TileOutsideGrid { .. }
            | HttpError::NoSuchLevel { .. }
            | HttpError::NoSuchTextureLevel { .. }
            | HttpError::UnknownContentVersion { .. }
            | HttpError::NoRoute
            | HttpError::NoPatches
            | HttpError::NoWeb
            | HttpError::NoWebTile { .. } => StatusCode::NOT_FOUND,
            HttpError::MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
            // 503 rather than 408 for a timeout: 408 says the *client* was too slow to send
            // its request, while here the server was too slow to answer it.
            HttpError::Overloaded | HttpError::Timeout(_) | HttpError::StoreUnavailable(_) => {
                StatusCode::SERVICE_UNAVAILABLE
            }
            HttpError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }
}

#[derive(serde::Serialize)]
struct ErrorBody<'a> {
    error: &'a str,
    status: u16,
}

impl IntoResponse for HttpError {
    fn into_response(self) -> Response {
        let status = self.status();
        let message = self.to_string();
        // Serialising two plain fields cannot fail; the fallback keeps the body JSON anyway.
        let body = serde_json::to_vec(&ErrorBody {
            error: &message,
            status: status.as_u16(),
        })
        .unwrap_or_else(|_| format!("{{\"status\":{}}}", status.as_u16()).into_bytes());
        let mut response = (status, body).into_response();
        let headers = response.headers_mut();
        headers.insert(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/json"),
        );
        // Errors describe this server's state at this moment (a stale version, overload),
        // not a resource: no cache should keep them.
        headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
        if matches!(
            self,
            HttpError::Overloaded | HttpError::Timeout(_) | HttpError::StoreUnavailable(_)
        ) {
            headers.insert(header::RETRY_AFTER, HeaderValue::from_static("1"));
        }
        if matches!(self, HttpError::MethodNotAllowed) {
            headers.insert(header::ALLOW, HeaderValue::from_static("GET, HEAD"));
        }
        response
    }
}
