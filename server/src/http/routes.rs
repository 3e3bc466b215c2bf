//! The handlers: manifest, heights, texture levels, health, metrics and the 404/405 answers.
//!
//! A tile handler parses its path segments itself (so a malformed one gets our JSON 400,
//! not axum's plain-text rejection), checks the content version, looks the blob up in the
//! [`TileDb`](crate::db::TileDb) and answers with a clone of its `Bytes`: a reference-count
//! increment on a slice of the memory map. Nothing is decoded, copied or re-encoded, and
//! nothing from the URL ever reaches the file system.
//!
//! Caching: every entity carries a strong `ETag` (its content hash) and answers a matching
//! `If-None-Match` with 304. Tile URLs carry the content version, so a tile URL always
//! names the same bytes and tiles are `immutable`; the manifest's URL is fixed, so caches
//! must revalidate it (`no-cache`), which the ETag makes a cheap 304.

use super::AppState;
use super::error::HttpError;
use axum::body::Body;
use axum::extract::rejection::PathRejection;
use axum::extract::{FromRequestParts, Path, State};
use axum::http::request::Parts;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;
use headers::{ETag, HeaderMapExt, IfNoneMatch};
use serde::Deserialize;
use std::convert::Infallible;
use std::sync::Arc;
use terrain_shared::TileId;
use terrain_shared::routes::API_PREFIX;

/// Content type of an encoded heights tile (`terrain_shared::heights`).
pub const HEIGHTS_CONTENT_TYPE: &str = "application/vnd.terrain.heights";
pub const JSON_CONTENT_TYPE: &str = "application/json";
/// Tiles never change under their URL: a year is the longest lifetime RFC 9111 caches are
/// expected to honour, and `immutable` spares browsers the revalidation on reload.
pub const TILE_CACHE_CONTROL: &str = "public, max-age=31536000, immutable";
/// The manifest may be stored, but must be revalidated (a 304 when unchanged) before each use.
pub const MANIFEST_CACHE_CONTROL: &str = "public, no-cache";

/// axum route template of [`terrain_shared::routes::heights`]. Built from the same prefix;
/// the test `templates_fill_in_to_the_shared_paths` keeps the rest in step.
pub fn heights_template() -> String {
    format!("{API_PREFIX}/{{content_version}}/tiles/{{x}}/{{y}}/heights")
}

/// axum route template of [`terrain_shared::routes::texture`].
pub fn texture_template() -> String {
    format!("{API_PREFIX}/{{content_version}}/tiles/{{x}}/{{y}}/texture/{{level}}")
}

#[derive(Debug, Deserialize)]
pub(super) struct HeightsPath {
    content_version: String,
    x: String,
    y: String,
}

#[derive(Debug, Deserialize)]
pub(super) struct TexturePath {
    content_version: String,
    x: String,
    y: String,
    level: String,
}

/// The request's `If-None-Match`, if any, parsed from the request head without copying
/// the other headers.
#[derive(Debug)]
pub(super) struct Conditional(Option<IfNoneMatch>);

impl<S: Send + Sync> FromRequestParts<S> for Conditional {
    type Rejection = Infallible;

    async fn from_request_parts(parts: &mut Parts, _state: &S) -> Result<Self, Self::Rejection> {
        // A malformed If-None-Match is ignored, as RFC 9110 section 13.1.2 allows: the
        // client gets the full answer instead of a 304.
        Ok(Conditional(parts.headers.typed_get()))
    }
}

pub(super) async fn manifest(
    State(state): State<Arc<AppState>>,
    conditional: Conditional,
) -> Response {
    let db = &state.db;
    entity(
        &conditional,
        db.manifest_json(),
        db.manifest_hash(),
        JSON_CONTENT_TYPE,
        MANIFEST_CACHE_CONTROL,
    )
}

pub(super) async fn heights(
    State(state): State<Arc<AppState>>,
    path: Result<Path<HeightsPath>, PathRejection>,
    conditional: Conditional,
) -> Result<Response, HttpError> {
    let Path(path) = path.map_err(malformed_path)?;
    let id = parse_tile(&path.x, &path.y)?;
    state.check_content_version(&path.content_version)?;
    let blob = state.db.heights(id).ok_or_else(|| state.outside_grid(id))?;
    Ok(entity(
        &conditional,
        &blob.bytes,
        &blob.hash,
        HEIGHTS_CONTENT_TYPE,
        TILE_CACHE_CONTROL,
    ))
}

pub(super) async fn texture(
    State(state): State<Arc<AppState>>,
    path: Result<Path<TexturePath>, PathRejection>,
    conditional: Conditional,
) -> Result<Response, HttpError> {
    let Path(path) = path.map_err(malformed_path)?;
    let id = parse_tile(&path.x, &path.y)?;
    let level = parse_number("texture level", &path.level)?;
    state.check_content_version(&path.content_version)?;
    state.check_in_grid(id)?;
    let manifest = state.db.manifest();
    let blob = state
        .db
        .texture(id, level)
        .ok_or(HttpError::NoSuchTextureLevel {
            id,
            level,
            last: manifest.texture.levels.saturating_sub(1),
        })?;
    let content_type = manifest.texture.format.content_type();
    Ok(entity(
        &conditional,
        &blob.bytes,
        &blob.hash,
        content_type,
        TILE_CACHE_CONTROL,
    ))
}

pub(super) async fn healthz() -> &'static str {
    "ok\n"
}

pub(super) async fn metrics(State(state): State<Arc<AppState>>) -> Result<Response, HttpError> {
    let text = state
        .metrics
        .encode()
        .map_err(|error| HttpError::Internal(format!("cannot encode metrics: {error}")))?;
    Ok(([(header::CONTENT_TYPE, super::metrics::CONTENT_TYPE)], text).into_response())
}

pub(super) async fn no_route() -> HttpError {
    HttpError::NoRoute
}

pub(super) async fn method_not_allowed() -> HttpError {
    HttpError::MethodNotAllowed
}

/// The 200 or 304 answer for one stored entity.
fn entity(
    conditional: &Conditional,
    bytes: &Bytes,
    hash: &str,
    content_type: &'static str,
    cache_control: &'static str,
) -> Response {
    // Hashes are lowercase hex, so the quoted tag is always a valid entity tag and header
    // value; a damaged manifest with any other hash still gets an answer, just no ETag.
    let etag = format!("\"{hash}\"");
    let parsed: Option<ETag> = etag.parse().ok();
    let not_modified = match (&parsed, &conditional.0) {
        (Some(etag), Some(if_none_match)) => !if_none_match.precondition_passes(etag),
        _ => false,
    };
    let mut response = if not_modified {
        // RFC 9110 section 15.4.5: a 304 repeats the validators and caching headers of the 200,
        // but carries no body and no Content-Type.
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        let mut response = Response::new(Body::from(bytes.clone()));
        response
            .headers_mut()
            .insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
        response
    };
    let headers = response.headers_mut();
    if let Some(etag) = parsed {
        headers.typed_insert(etag);
    }
    headers.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static(cache_control),
    );
    response
}

fn parse_tile(x: &str, y: &str) -> Result<TileId, HttpError> {
    Ok(TileId::new(
        parse_number("x coordinate", x)?,
        parse_number("y coordinate", y)?,
    ))
}

/// Parses a path segment as a `u32` in its one canonical spelling: ASCII digits, no sign,
/// no leading zeros. `str::parse` alone would also take `+7` and `007`; refusing those
/// keeps one URL per tile, so caches cannot be bypassed by respelling a coordinate.
fn parse_number(segment: &'static str, value: &str) -> Result<u32, HttpError> {
    let canonical = !value.is_empty()
        && value.bytes().all(|b| b.is_ascii_digit())
        && (value == "0" || !value.starts_with('0'));
    let malformed = || HttpError::MalformedNumber {
        segment,
        value: truncated(value),
    };
    if !canonical {
        return Err(malformed());
    }
    value.parse().map_err(|_| malformed())
}

fn malformed_path(rejection: PathRejection) -> HttpError {
    HttpError::MalformedPath {
        reason: rejection.body_text(),
    }
}

/// Echoes at most a few dozen characters of client input back in an error body
/// (content versions are 16 hex digits, coordinates at most 10 digits).
pub(super) fn truncated(value: &str) -> String {
    const MAX_ECHO: usize = 40;
    match value.char_indices().nth(MAX_ECHO) {
        Some((end, _)) => format!("{}...", &value[..end]),
        None => value.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use terrain_shared::routes;

    #[test]
    fn templates_fill_in_to_the_shared_paths() {
        let id = TileId::new(3, 4);
        let fill = |template: String| {
            template
                .replace("{content_version}", "abc")
                .replace("{x}", "3")
                .replace("{y}", "4")
                .replace("{level}", "2")
        };
        assert_eq!(fill(heights_template()), routes::heights("abc", id));
        assert_eq!(fill(texture_template()), routes::texture("abc", id, 2));
    }

    #[test]
    fn numbers_are_accepted_only_in_their_canonical_spelling() {
        for (input, expected) in [
            ("0", Some(0)),
            ("7", Some(7)),
            ("4294967295", Some(u32::MAX)),
            ("4294967296", None),
            ("99999999999999999999999", None),
            ("", None),
            ("-1", None),
            ("+1", None),
            ("01", None),
            ("1.0", None),
            ("x", None),
            (" 1", None),
            ("١", None),
        ] {
            assert_eq!(
                parse_number("x coordinate", input).ok(),
                expected,
                "input {input:?}"
            );
        }
    }
}
