//! The routes the web's own clients read (`crate::web`): TileJSON documents and XYZ tiles
//! for MapLibre GL JS (Terrarium, Mapbox Terrain-RGB, the texture), and `layer.json` with
//! quantized-mesh tiles for CesiumJS.
//!
//! The documents are small and name absolute tile URLs (MapLibre resolves a TileJSON's tile
//! URLs against the page, not the document), built per request from the request's `Host`
//! or `--public-url`; like the manifest they are revalidated (`no-cache`). Tile URLs carry
//! the content version and are immutable like every other tile; their bodies are slices of
//! `web.pack`, stored gzipped for quantized-mesh (served with `Content-Encoding: gzip`, as
//! Cesium's own terrain servers do, whatever the request accepts: there is no other copy).

use super::AppState;
use super::error::HttpError;
use super::routes::{Conditional, JSON_CONTENT_TYPE, TILE_CACHE_CONTROL, stored_entity};
use crate::db::TileDb;
use crate::web::index::{Entry, Kind};
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, Uri, header};
use axum::response::{IntoResponse, Response};
use serde_json::json;
use std::sync::Arc;
use terrain_shared::routes::API_PREFIX;

/// Content type of a quantized-mesh tile.
pub const QUANTIZED_MESH_CONTENT_TYPE: &str = "application/vnd.quantized-mesh";
/// Documents that name tile URLs: stored, but revalidated before each use.
const DOCUMENT_CACHE_CONTROL: &str = "public, no-cache";

/// The MapLibre TileJSON documents.
pub const TERRARIUM_JSON: &str = "/v1/terrarium.json";
pub const TERRAIN_RGB_JSON: &str = "/v1/terrain-rgb.json";
pub const TEXTURE_JSON: &str = "/v1/texture.json";
/// Cesium's terrain: pass `/v1/cesium/` to `CesiumTerrainProvider.fromUrl`.
pub const CESIUM_LAYER: &str = "/v1/cesium/layer.json";

/// The route segment of each XYZ kind, and its file suffix.
fn xyz_segment(kind: Kind) -> (&'static str, &'static str) {
    match kind {
        Kind::Terrarium => ("terrarium", "png"),
        Kind::TerrainRgb => ("terrain-rgb", "png"),
        Kind::Texture => ("texture", "png"),
        Kind::QuantizedMesh => ("cesium", "terrain"),
    }
}

/// Path of one web tile (`y` in the scheme's own numbering: XYZ from the north, TMS from
/// the south for quantized-mesh).
pub fn tile_path(content_version: &str, e: Entry) -> String {
    let (segment, suffix) = xyz_segment(e.kind);
    format!(
        "{API_PREFIX}/{content_version}/{segment}/{}/{}/{}.{suffix}",
        e.z, e.x, e.y
    )
}

/// axum route templates of the tiles.
pub fn tile_templates() -> Vec<(String, Kind)> {
    [
        Kind::Terrarium,
        Kind::TerrainRgb,
        Kind::Texture,
        Kind::QuantizedMesh,
    ]
    .into_iter()
    .map(|kind| {
        let (segment, _) = xyz_segment(kind);
        (
            format!("{API_PREFIX}/{{content_version}}/{segment}/{{z}}/{{x}}/{{file}}"),
            kind,
        )
    })
    .collect()
}

#[derive(Debug, serde::Deserialize)]
pub(super) struct TilePath {
    content_version: String,
    z: String,
    x: String,
    file: String,
}

/// `http://host` of the request (or `--public-url`), refusing a Host header that is not a
/// plain host name or address with an optional port.
fn base_url(state: &AppState, headers: &HeaderMap) -> Result<String, HttpError> {
    if let Some(url) = &state.public_url {
        return Ok(url.trim_end_matches('/').to_string());
    }
    let host = headers
        .get(header::HOST)
        .and_then(|h| h.to_str().ok())
        .unwrap_or("");
    let plain = !host.is_empty()
        && host.len() <= 255
        && host
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"-.:[]".contains(&b));
    if !plain {
        return Err(HttpError::BadHost);
    }
    Ok(format!("http://{host}"))
}

fn web_info(db: &TileDb) -> Result<&terrain_shared::manifest::WebInfo, HttpError> {
    db.manifest().web.as_ref().ok_or(HttpError::NoWeb)
}

fn document(body: serde_json::Value) -> Response {
    let bytes = serde_json::to_vec(&body).unwrap_or_default();
    let mut response = bytes.into_response();
    let headers = response.headers_mut();
    headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(JSON_CONTENT_TYPE),
    );
    headers.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static(DOCUMENT_CACHE_CONTROL),
    );
    response
}

fn tilejson(state: &AppState, headers: &HeaderMap, kind: Kind) -> Result<Response, HttpError> {
    let db = state.db();
    let info = web_info(&db)?;
    let manifest = db.manifest();
    let base = base_url(state, headers)?;
    let (segment, suffix) = xyz_segment(kind);
    let [w, s, e, n] = info.bounds_deg;
    let mut doc = json!({
        "tilejson": "3.0.0",
        "name": format!("{} ({segment})", manifest.dataset),
        "version": manifest.content_version,
        "scheme": "xyz",
        "tiles": [format!("{base}{API_PREFIX}/{}/{segment}/{{z}}/{{x}}/{{y}}.{suffix}", manifest.content_version)],
        "tileSize": info.xyz_tile_size,
        "minzoom": 0,
        "maxzoom": info.xyz_max_zoom,
        "bounds": [w, s, e, n],
        "center": [(w + e) / 2.0, (s + n) / 2.0, info.xyz_max_zoom.saturating_sub(2)],
    });
    match kind {
        Kind::Terrarium => doc["encoding"] = json!("terrarium"),
        Kind::TerrainRgb => doc["encoding"] = json!("mapbox"),
        _ => {}
    }
    Ok(document(doc))
}

pub(super) async fn terrarium_json(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
) -> Result<Response, HttpError> {
    tilejson(&state, &headers, Kind::Terrarium)
}

pub(super) async fn terrain_rgb_json(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
) -> Result<Response, HttpError> {
    tilejson(&state, &headers, Kind::TerrainRgb)
}

pub(super) async fn texture_json(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
) -> Result<Response, HttpError> {
    tilejson(&state, &headers, Kind::Texture)
}

/// Cesium's `layer.json`: the tiles every level has (`available`), with the error each
/// level's meshes keep within (`max_error_m`, not part of the format).
pub(super) async fn cesium_layer(
    State(state): State<Arc<AppState>>,
) -> Result<Response, HttpError> {
    let db = state.db();
    let info = web_info(&db)?;
    let manifest = db.manifest();
    let mut available: Vec<Vec<serde_json::Value>> = Vec::new();
    for z in 0..=info.cesium_max_level {
        let (x0, x1, y0, y1) = crate::web::tiling::geographic_range(info.bounds_deg, z);
        available.push(vec![
            json!({"startX": x0, "startY": y0, "endX": x1, "endY": y1}),
        ]);
    }
    Ok(document(json!({
        "tilejson": "2.1.0",
        "name": manifest.dataset,
        "format": "quantized-mesh-1.0",
        "version": "1.0.0",
        "scheme": "tms",
        "projection": "EPSG:4326",
        "tiles": [format!("{API_PREFIX}/{}/cesium/{{z}}/{{x}}/{{y}}.terrain", manifest.content_version)],
        "extensions": ["octvertexnormals"],
        "minzoom": 0,
        "maxzoom": info.cesium_max_level,
        "bounds": info.bounds_deg,
        "available": available,
        "max_error_m": info.cesium_max_error_m,
    })))
}

pub(super) async fn tile(
    State(state): State<Arc<AppState>>,
    kind: Kind,
    uri: Uri,
    path: Result<Path<TilePath>, axum::extract::rejection::PathRejection>,
    conditional: Conditional,
) -> Result<Response, HttpError> {
    let Path(path) = path.map_err(|r| HttpError::MalformedPath {
        reason: r.body_text(),
    })?;
    let (segment, suffix) = xyz_segment(kind);
    let spelling = match kind {
        Kind::Terrarium => {
            "/v1/{content_version}/terrarium/{z}/{x}/{y}.png, plain digits, no query"
        }
        Kind::TerrainRgb => {
            "/v1/{content_version}/terrain-rgb/{z}/{x}/{y}.png, plain digits, no query"
        }
        Kind::Texture => "/v1/{content_version}/texture/{z}/{x}/{y}.png, plain digits, no query",
        Kind::QuantizedMesh => {
            "/v1/{content_version}/cesium/{z}/{x}/{y}.terrain, plain digits, no query"
        }
    };
    super::routes::check_canonical(&uri, spelling)?;
    let z = super::routes::parse_number("zoom", &path.z)?;
    let x = super::routes::parse_number("x coordinate", &path.x)?;
    let y = path
        .file
        .strip_suffix(suffix)
        .and_then(|f| f.strip_suffix('.'))
        .ok_or(HttpError::NotCanonical {
            reason: "the last segment is the row and the file suffix",
            canonical: spelling,
        })?;
    let y = super::routes::parse_number("y coordinate", y)?;
    let db = state.db_for(&path.content_version)?;
    let info = web_info(&db)?;
    let entry = Entry { kind, z, x, y };
    let blob = db.web_tile(entry).ok_or(HttpError::NoWebTile {
        what: segment,
        z,
        x,
        y,
        max_zoom: match kind {
            Kind::QuantizedMesh => info.cesium_max_level,
            _ => info.xyz_max_zoom,
        },
    })?;
    let content_type = match kind {
        Kind::QuantizedMesh => QUANTIZED_MESH_CONTENT_TYPE,
        _ => "image/png",
    };
    let mut response = stored_entity(&conditional, blob, content_type, TILE_CACHE_CONTROL).await?;
    if kind == Kind::QuantizedMesh && response.status() == axum::http::StatusCode::OK {
        response
            .headers_mut()
            .insert(header::CONTENT_ENCODING, HeaderValue::from_static("gzip"));
    }
    Ok(response)
}

/// `/`: the viewer when the server has one, else where the routes are.
pub(super) async fn root(State(state): State<Arc<AppState>>) -> Response {
    if state.viewer.is_some() {
        let mut response = axum::http::StatusCode::FOUND.into_response();
        response.headers_mut().insert(
            header::LOCATION,
            HeaderValue::from_static("/view/index.html"),
        );
        return response;
    }
    let db = state.db();
    let web = if db.manifest().web.is_some() {
        format!(
            "MapLibre: {TERRARIUM_JSON} (raster-dem, terrarium), {TERRAIN_RGB_JSON} (mapbox), {TEXTURE_JSON} (raster)\nCesium: CesiumTerrainProvider.fromUrl(\"/v1/cesium/\")\n"
        )
    } else {
        "no web tiles in this database (its source is not georeferenced, or it was built with --no-web)\n".into()
    };
    let text = format!(
        "terrain-server: {}\nmanifest: {}\n{web}viewer: start with --viewer viewer/dist (after bash viewer/setup.sh)\n",
        db.manifest().dataset,
        terrain_shared::routes::MANIFEST
    );
    ([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], text).into_response()
}
