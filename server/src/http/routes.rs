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
use crate::db::StoredBlob;
use axum::body::Body;
use axum::extract::rejection::PathRejection;
use axum::extract::{FromRequestParts, Path, State};
use axum::http::request::Parts;
use axum::http::{HeaderMap, HeaderValue, StatusCode, Uri, header};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;
use headers::{ETag, HeaderMapExt, IfNoneMatch};
use serde::Deserialize;
use std::convert::Infallible;
use std::sync::Arc;
use terrain_shared::TileId;
use terrain_shared::routes::API_PREFIX;

/// Content type of a tile blob (`terrain_shared::tile_blob`: mask errors, texture hashes,
/// heights).
pub const HEIGHTS_CONTENT_TYPE: &str = "application/vnd.terrain.tile";
pub const JSON_CONTENT_TYPE: &str = "application/json";
/// Tiles never change under their URL: a year is the longest lifetime RFC 9111 caches are
/// expected to honour, and `immutable` spares browsers the revalidation on reload.
pub const TILE_CACHE_CONTROL: &str = "public, max-age=31536000, immutable";
/// The manifest may be stored, but must be revalidated (a 304 when unchanged) before each use.
pub const MANIFEST_CACHE_CONTROL: &str = "public, no-cache";

/// axum route template of [`terrain_shared::routes::heights`]. Built from the same prefix;
/// the test `templates_fill_in_to_the_shared_paths` keeps the rest in step.
pub fn heights_template() -> String {
    format!("{API_PREFIX}/{{content_version}}/levels/{{level}}/tiles/{{x}}/{{y}}/heights")
}

/// axum route template of [`terrain_shared::routes::texture`].
pub fn texture_template() -> String {
    format!("{API_PREFIX}/{{content_version}}/levels/{{level}}/tiles/{{x}}/{{y}}/texture/{{mip}}")
}

/// axum route template of [`terrain_shared::routes::patch`].
pub fn patch_template() -> String {
    format!("{API_PREFIX}/{{content_version}}/levels/{{level}}/tiles/{{x}}/{{y}}/patch")
}

/// axum route template of [`terrain_shared::routes::patch_index`].
pub fn patch_index_template() -> String {
    format!("{API_PREFIX}/{{content_version}}/patches/index")
}

/// Content type of a quadtree patch body and of the patch index
/// (`terrain_shared::quadtree`).
pub const PATCH_CONTENT_TYPE: &str = "application/vnd.terrain.patch";

#[derive(Debug, serde::Deserialize)]
pub(super) struct IndexPath {
    content_version: String,
}

/// The level-0 spelling of the single-level API, answered with a permanent redirect to
/// [`heights_template`] at level 0.
pub fn legacy_heights_template() -> String {
    format!("{API_PREFIX}/{{content_version}}/tiles/{{x}}/{{y}}/heights")
}

/// The level-0 spelling of a texture level, redirected like [`legacy_heights_template`].
pub fn legacy_texture_template() -> String {
    format!("{API_PREFIX}/{{content_version}}/tiles/{{x}}/{{y}}/texture/{{mip}}")
}

#[derive(Debug, Deserialize)]
pub(super) struct HeightsPath {
    content_version: String,
    level: String,
    x: String,
    y: String,
}

#[derive(Debug, Deserialize)]
pub(super) struct TexturePath {
    content_version: String,
    level: String,
    x: String,
    y: String,
    mip: String,
}

#[derive(Debug, Deserialize)]
pub(super) struct LegacyPath {
    content_version: String,
    x: String,
    y: String,
    mip: Option<String>,
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

/// The manifest, gzipped when the client accepts gzip: the bytes compressed once when
/// the database was opened, never per request. The gzip body is another representation of
/// the same resource, so its entity tag is weak (`W/"hash"`, RFC 9110 section 8.8.1, as
/// nginx does); `If-None-Match` compares weakly, so either tag revalidates either body.
pub(super) async fn manifest(
    State(state): State<Arc<AppState>>,
    conditional: Conditional,
    headers: HeaderMap,
) -> Response {
    let db = state.db();
    let gzipped = accepts_gzip(&headers);
    let body = if gzipped {
        db.manifest_gzip()
    } else {
        db.manifest_json()
    };
    let mut response = entity(
        &conditional,
        body,
        db.manifest_etag(),
        JSON_CONTENT_TYPE,
        MANIFEST_CACHE_CONTROL,
    );
    let ok = response.status() == StatusCode::OK;
    let headers = response.headers_mut();
    headers.insert(header::VARY, HeaderValue::from_static("accept-encoding"));
    if gzipped {
        if ok {
            headers.insert(header::CONTENT_ENCODING, HeaderValue::from_static("gzip"));
        }
        let weak = HeaderValue::from_str(&format!("W/\"{}\"", db.manifest_hash())).ok();
        if let Some(weak) = weak {
            headers.insert(header::ETAG, weak);
        }
    }
    response
}

/// Whether `Accept-Encoding` accepts gzip (RFC 9110 section 12.5.3): `gzip`, `x-gzip` or
/// `*`, with a q-value above zero. An explicit `gzip;q=0` refuses it even if `*` is listed.
fn accepts_gzip(headers: &HeaderMap) -> bool {
    let mut star = false;
    for value in headers.get_all(header::ACCEPT_ENCODING) {
        let Ok(value) = value.to_str() else { continue };
        for item in value.split(',') {
            let mut parts = item.split(';');
            let coding = parts.next().unwrap_or("").trim().to_ascii_lowercase();
            let refused = parts.any(|param| {
                let param = param.trim().to_ascii_lowercase();
                param
                    .strip_prefix("q=")
                    .and_then(|q| q.trim().parse::<f32>().ok())
                    .is_some_and(|q| q <= 0.0)
            });
            match coding.as_str() {
                "gzip" | "x-gzip" => return !refused,
                "*" => star = !refused,
                _ => {}
            }
        }
    }
    star
}

pub(super) async fn heights(
    State(state): State<Arc<AppState>>,
    uri: Uri,
    path: Result<Path<HeightsPath>, PathRejection>,
    conditional: Conditional,
) -> Result<Response, HttpError> {
    check_canonical(&uri, HEIGHTS_SPELLING)?;
    let Path(path) = path.map_err(malformed_path)?;
    let id = parse_tile(&path.level, &path.x, &path.y)?;
    let db = state.db_for(&path.content_version)?;
    super::check_in_grid(&db, id)?;
    let blob = db.heights(id).ok_or_else(|| super::outside_grid(&db, id))?;
    stored_entity(&conditional, blob, HEIGHTS_CONTENT_TYPE, TILE_CACHE_CONTROL).await
}

pub(super) async fn patch(
    State(state): State<Arc<AppState>>,
    uri: Uri,
    path: Result<Path<HeightsPath>, PathRejection>,
    conditional: Conditional,
) -> Result<Response, HttpError> {
    check_canonical(&uri, PATCH_SPELLING)?;
    let Path(path) = path.map_err(malformed_path)?;
    let id = parse_tile(&path.level, &path.x, &path.y)?;
    let db = state.db_for(&path.content_version)?;
    super::check_in_grid(&db, id)?;
    let blob = db.patch(id).ok_or(HttpError::NoPatches)?;
    stored_entity(&conditional, blob, PATCH_CONTENT_TYPE, TILE_CACHE_CONTROL).await
}

pub(super) async fn patch_index(
    State(state): State<Arc<AppState>>,
    uri: Uri,
    path: Result<Path<IndexPath>, PathRejection>,
    conditional: Conditional,
) -> Result<Response, HttpError> {
    check_canonical(&uri, PATCH_INDEX_SPELLING)?;
    let Path(path) = path.map_err(malformed_path)?;
    let db = state.db_for(&path.content_version)?;
    let blob = db.patch_index().ok_or(HttpError::NoPatches)?;
    stored_entity(&conditional, blob, PATCH_CONTENT_TYPE, TILE_CACHE_CONTROL).await
}

pub(super) async fn texture(
    State(state): State<Arc<AppState>>,
    uri: Uri,
    path: Result<Path<TexturePath>, PathRejection>,
    conditional: Conditional,
) -> Result<Response, HttpError> {
    check_canonical(&uri, TEXTURE_SPELLING)?;
    let Path(path) = path.map_err(malformed_path)?;
    let id = parse_tile(&path.level, &path.x, &path.y)?;
    let level = parse_number("texture level", &path.mip)?;
    let db = state.db_for(&path.content_version)?;
    super::check_in_grid(&db, id)?;
    let manifest = db.manifest();
    let blob = db.texture(id, level).ok_or(HttpError::NoSuchTextureLevel {
        id,
        level,
        last: manifest.texture.levels.saturating_sub(1),
    })?;
    let content_type = manifest.texture.format.content_type();
    stored_entity(&conditional, blob, content_type, TILE_CACHE_CONTROL).await
}

/// A level-0 tile URL of the single-level API: checked like any tile URL, then a permanent
/// redirect (308) to its one spelling with the level, cacheable like the tile itself.
pub(super) async fn legacy_tile(
    State(state): State<Arc<AppState>>,
    uri: Uri,
    path: Result<Path<LegacyPath>, PathRejection>,
) -> Result<Response, HttpError> {
    let spelling = if uri.path().ends_with("/heights") {
        HEIGHTS_SPELLING
    } else {
        TEXTURE_SPELLING
    };
    check_canonical(&uri, spelling)?;
    let Path(path) = path.map_err(malformed_path)?;
    let id = parse_tile("0", &path.x, &path.y)?;
    let db = state.db_for(&path.content_version)?;
    super::check_in_grid(&db, id)?;
    let cv = &path.content_version;
    let location = match &path.mip {
        None => terrain_shared::routes::heights(cv, id),
        Some(mip) => terrain_shared::routes::texture(cv, id, parse_number("texture level", mip)?),
    };
    let mut response = StatusCode::PERMANENT_REDIRECT.into_response();
    let headers = response.headers_mut();
    if let Ok(location) = HeaderValue::from_str(&location) {
        headers.insert(header::LOCATION, location);
    }
    headers.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static(TILE_CACHE_CONTROL),
    );
    Ok(response)
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
pub(super) fn entity(
    conditional: &Conditional,
    bytes: &Bytes,
    etag: Option<&HeaderValue>,
    content_type: &'static str,
    cache_control: &'static str,
) -> Response {
    let not_modified = conditional_matches(conditional, etag);
    respond(
        not_modified,
        bytes.clone(),
        etag,
        content_type,
        cache_control,
    )
}

/// [`entity`] for a blob of the database, read only when a body is sent
/// ([`StoredBlob::fetch`]): a local pack changed under the server, or a store's object
/// changed, gives a 500 naming it; a store that does not answer gives a 503 with
/// `Retry-After`; either way a line in the log, never a dead process or the wrong bytes.
pub(super) async fn stored_entity(
    conditional: &Conditional,
    blob: &StoredBlob,
    content_type: &'static str,
    cache_control: &'static str,
) -> Result<Response, HttpError> {
    let not_modified = conditional_matches(conditional, blob.etag.as_ref());
    let body = if not_modified {
        Bytes::new()
    } else {
        blob.fetch().await.map_err(|error| {
            tracing::error!("{error}");
            match error {
                crate::store::ReadError::Unavailable { .. } => {
                    HttpError::StoreUnavailable(error.to_string())
                }
                _ => HttpError::Internal(error.to_string()),
            }
        })?
    };
    Ok(respond(
        not_modified,
        body,
        blob.etag.as_ref(),
        content_type,
        cache_control,
    ))
}

/// Whether `If-None-Match` matches `etag`: the answer is a 304 without a body.
fn conditional_matches(conditional: &Conditional, etag: Option<&HeaderValue>) -> bool {
    // The tag was made when the database opened; it is parsed only to answer an
    // `If-None-Match`. A damaged manifest's blob without a valid tag is still served.
    match (etag, &conditional.0) {
        (Some(etag), Some(if_none_match)) => etag
            .to_str()
            .ok()
            .and_then(|tag| tag.parse::<ETag>().ok())
            .is_some_and(|tag| !if_none_match.precondition_passes(&tag)),
        _ => false,
    }
}

/// A 304 (`not_modified`) or a 200 with `body`, with the entity's validators and caching.
fn respond(
    not_modified: bool,
    body: Bytes,
    etag: Option<&HeaderValue>,
    content_type: &'static str,
    cache_control: &'static str,
) -> Response {
    let mut response = if not_modified {
        // RFC 9110 section 15.4.5: a 304 repeats the validators and caching headers of the 200,
        // but carries no body and no Content-Type.
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        let mut response = Response::new(Body::from(body));
        response
            .headers_mut()
            .insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
        response
    };
    let headers = response.headers_mut();
    if let Some(etag) = etag {
        headers.insert(header::ETAG, etag.clone());
    }
    headers.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static(cache_control),
    );
    response
}

const HEIGHTS_SPELLING: &str =
    "/v1/{content_version}/levels/{level}/tiles/{x}/{y}/heights, plain digits, no query";
const PATCH_SPELLING: &str =
    "/v1/{content_version}/levels/{level}/tiles/{x}/{y}/patch, plain digits, no query";
const PATCH_INDEX_SPELLING: &str = "/v1/{content_version}/patches/index, no query";
const TEXTURE_SPELLING: &str =
    "/v1/{content_version}/levels/{level}/tiles/{x}/{y}/texture/{mip}, plain digits, no query";

/// Refuses the spellings of a tile URL that routing alone would accept: a query string
/// (ignored by the handler, but part of every cache's key) and percent-encoding (`%31` for
/// `1`; no segment of a tile URL needs it). Coordinates are checked by [`parse_number`].
pub(super) fn check_canonical(uri: &Uri, canonical: &'static str) -> Result<(), HttpError> {
    if uri.query().is_some() {
        return Err(HttpError::NotCanonical {
            reason: "tile URLs take no query string",
            canonical,
        });
    }
    if uri.path().contains('%') {
        return Err(HttpError::NotCanonical {
            reason: "tile URLs are never percent-encoded",
            canonical,
        });
    }
    Ok(())
}

fn parse_tile(level: &str, x: &str, y: &str) -> Result<TileId, HttpError> {
    Ok(TileId::at(
        parse_number("level", level)?,
        parse_number("x coordinate", x)?,
        parse_number("y coordinate", y)?,
    ))
}

/// Parses a path segment as a `u32` in its one canonical spelling: ASCII digits, no sign,
/// no leading zeros. `str::parse` alone would also take `+7` and `007`; refusing those
/// keeps one URL per tile, so caches cannot be bypassed by respelling a coordinate.
pub(super) fn parse_number(segment: &'static str, value: &str) -> Result<u32, HttpError> {
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
        let id = TileId::at(1, 3, 4);
        let fill = |template: String| {
            template
                .replace("{content_version}", "abc")
                .replace("{level}", "1")
                .replace("{x}", "3")
                .replace("{y}", "4")
                .replace("{mip}", "2")
        };
        assert_eq!(fill(heights_template()), routes::heights("abc", id));
        assert_eq!(fill(texture_template()), routes::texture("abc", id, 2));
    }

    #[test]
    fn gzip_is_accepted_as_rfc_9110_reads() {
        for (accept, expected) in [
            ("gzip", true),
            ("GZIP", true),
            ("x-gzip", true),
            ("deflate, gzip;q=0.5", true),
            ("gzip;q=0", false),
            ("gzip; q=0.0", false),
            ("*", true),
            ("*;q=0", false),
            ("gzip;q=0, *", false),
            ("br, zstd", false),
            ("", false),
        ] {
            let mut headers = HeaderMap::new();
            headers.insert(header::ACCEPT_ENCODING, HeaderValue::from_static(accept));
            assert_eq!(accepts_gzip(&headers), expected, "{accept:?}");
        }
        assert!(!accepts_gzip(&HeaderMap::new()));
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
