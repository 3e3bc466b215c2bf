//! Serves an opened [`TileDb`] over HTTP: the versioned tile API, health and metrics.
//!
//! - [`routes`]: the handlers, entity tags and caching headers;
//! - [`error`]: every failure and its one JSON response;
//! - [`metrics`]: counters by route template and the per-request span;
//! - [`serve`](mod@serve): the hardened accept loop and graceful shutdown;
//! - [`cli`]: `terrain-server serve`, the runtime and the signal handling;
//! - [`reload`]: a rebuilt database served without a restart (SIGHUP, or a poll).
//!
//! The layers, outermost first, and why in that order:
//!
//! 1. metrics and tracing, so every answer is counted, 503s from shedding included;
//! 2. CORS, so error answers carry the CORS headers too and browsers can read them;
//! 3. only on the tile API: load shedding at the concurrency limit and the request timeout
//!    ([`limits`]).
//!    `/healthz` and `/metrics` stay outside, so an overloaded server can still be watched.
//!
//! **Invariant:** nothing from a URL is used as a file path; every lookup goes through
//! [`TileDb`], by parsed tile id and level. The one exception is the viewer page under
//! `/view/`, served only with `--viewer DIR` by tower-http's `ServeDir`, which refuses any
//! path leaving `DIR`.

pub mod cli;
pub mod error;
#[cfg(feature = "test-hooks")]
#[doc(hidden)]
pub mod hooks;
mod limits;
pub mod metrics;
pub mod reload;
pub mod routes;
pub mod serve;
pub mod web;

pub use cli::{ServeArgs, run_cli};
pub use error::HttpError;
pub use metrics::Metrics;
pub use serve::{ServeOptions, serve, shutdown_signal};

use crate::db::{TileDb, Verify};
use axum::Router;
use axum::http::{Method, header};
use axum::routing::get;
use std::sync::{Arc, RwLock};
use terrain_shared::TileId;
use terrain_shared::routes::{HEALTHZ, MANIFEST, METRICS};
use tower::ServiceBuilder;
use tower_http::cors::{Any, CorsLayer};

/// Everything a request may need, shared by all of them.
#[derive(Debug)]
pub struct AppState {
    /// The database served now; [`AppState::reload`] puts a rebuilt one in its place.
    db: RwLock<Arc<TileDb>>,
    /// For a database in an object store, the version served before the last reload: still
    /// answered to requests that name it (a client, or a cache, mid-flight on the old
    /// manifest), since the store keeps it. A local directory's old version is closed
    /// instead, so that its disk space is freed.
    previous: RwLock<Option<Arc<TileDb>>>,
    /// How a database is checked when it is opened again.
    verify: Verify,
    pub metrics: Metrics,
    /// `scheme://host[:port]` put in front of tile URLs in the web documents, instead of
    /// the request's `Host` (for a server behind a proxy).
    pub public_url: Option<String>,
    /// The viewer page's files (`viewer/dist`), served under `/view/`.
    pub viewer: Option<std::path::PathBuf>,
}

/// What [`AppState::reload`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Reloaded {
    /// The directory holds the database already served (the same content version).
    Unchanged,
    /// A new database is served from now on; requests that began earlier end with the old
    /// one, whose files are closed when the last of them ends.
    Replaced { from: String, to: String },
}

impl AppState {
    /// Serves `db`, opened with [`Verify::Hashes`] (reloads check hashes too).
    pub fn new(db: TileDb) -> AppState {
        AppState::with_verify(db, Verify::Hashes)
    }

    /// Serves `db`; a reload opens the directory again checking it as `verify` says.
    pub fn with_verify(db: TileDb, verify: Verify) -> AppState {
        AppState {
            db: RwLock::new(Arc::new(db)),
            previous: RwLock::new(None),
            verify,
            metrics: Metrics::new(),
            public_url: None,
            viewer: None,
        }
    }

    /// The database served now. A request takes it once and answers from it alone, so a
    /// reload in the middle never mixes two versions in one answer.
    pub fn db(&self) -> Arc<TileDb> {
        Arc::clone(
            &self
                .db
                .read()
                .unwrap_or_else(std::sync::PoisonError::into_inner),
        )
    }

    /// The database a request naming `content_version` is answered from: the one served,
    /// or (for a store) the one served before the last reload.
    pub fn db_for(&self, content_version: &str) -> Result<Arc<TileDb>, HttpError> {
        let current = self.db();
        if current.manifest().content_version == content_version {
            return Ok(current);
        }
        let previous = self
            .previous
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone();
        if let Some(previous) = previous
            && previous.manifest().content_version == content_version
        {
            return Ok(previous);
        }
        check_content_version(&current, content_version).map(|()| current)
    }

    /// Opens the database again (the directory, or the version the store's pointer names)
    /// and serves what it holds now, when its content version differs. On an error (the
    /// directory missing, a build's lock in it, a damaged pack, the store down) the database
    /// served stays.
    pub async fn reload(&self) -> Result<Reloaded, crate::db::DbError> {
        // What is needed of the database served, and no reference to it held past here:
        // once the swap below is done, the last request that took it closes its packs.
        let (origin, from) = {
            let current = self.db();
            (
                current.origin().clone(),
                current.manifest().content_version.clone(),
            )
        };
        let fresh = match origin {
            crate::db::Origin::Dir(dir) => {
                let verify = self.verify;
                let cache = Arc::clone(self.db().cache());
                tokio::task::spawn_blocking(move || TileDb::open_with_cache(&dir, verify, cache))
                    .await
                    .map_err(|e| crate::db::DbError::Io {
                        path: std::path::PathBuf::from("(reload)"),
                        source: std::io::Error::other(e.to_string()),
                    })??
            }
            crate::db::Origin::Store { source, .. } => {
                let version = crate::store::current_version(&*source.store, &source.url).await?;
                if version == from {
                    return Ok(Reloaded::Unchanged);
                }
                TileDb::open_store(source, &version, self.verify).await?
            }
        };
        let to = fresh.manifest().content_version.clone();
        if from == to {
            return Ok(Reloaded::Unchanged);
        }
        let keep_previous = matches!(fresh.origin(), crate::db::Origin::Store { .. });
        // Counted before the new version can be seen, so whoever sees it sees the count.
        self.metrics.reloaded();
        let replaced = std::mem::replace(
            &mut *self
                .db
                .write()
                .unwrap_or_else(std::sync::PoisonError::into_inner),
            Arc::new(fresh),
        );
        // Outside the lock: unmapping the old packs (when no request holds them) does not
        // hold up the requests taking the new database.
        let kept = if keep_previous {
            Some(replaced)
        } else {
            drop(replaced);
            None
        };
        let dropped = std::mem::replace(
            &mut *self
                .previous
                .write()
                .unwrap_or_else(std::sync::PoisonError::into_inner),
            kept,
        );
        drop(dropped);
        Ok(Reloaded::Replaced { from, to })
    }
}

/// The content version in a tile URL must be the one served: an old one names tiles this
/// server no longer has, whatever their coordinates.
fn check_content_version(db: &TileDb, requested: &str) -> Result<(), HttpError> {
    let current = &db.manifest().content_version;
    if requested == current {
        return Ok(());
    }
    Err(HttpError::UnknownContentVersion {
        requested: routes::truncated(requested),
        current: current.clone(),
    })
}

fn check_in_grid(db: &TileDb, id: TileId) -> Result<(), HttpError> {
    match db.manifest().tile(id) {
        Some(_) => Ok(()),
        None => Err(outside_grid(db, id)),
    }
}

fn outside_grid(db: &TileDb, id: TileId) -> HttpError {
    let manifest = db.manifest();
    if id.level >= manifest.level_count() {
        return HttpError::NoSuchLevel {
            level: id.level,
            last: manifest.coarsest_level(),
        };
    }
    let grid = manifest.grid(id.level);
    HttpError::TileOutsideGrid {
        id,
        columns: grid.columns,
        rows: grid.rows,
    }
}

/// The application with the default [`ServeOptions`] limits.
pub fn app(state: Arc<AppState>) -> Router {
    app_with(state, &ServeOptions::default())
}

/// The application: routes and every layer, with the per-request limits of `options`.
pub fn app_with(state: Arc<AppState>, options: &ServeOptions) -> Router {
    let tile_api = Router::new()
        .route(MANIFEST, get(routes::manifest))
        .route(&routes::heights_template(), get(routes::heights))
        .route(&routes::texture_template(), get(routes::texture))
        .route(&routes::patch_template(), get(routes::patch))
        .route(&routes::patch_index_template(), get(routes::patch_index))
        .route(&routes::legacy_heights_template(), get(routes::legacy_tile))
        .route(&routes::legacy_texture_template(), get(routes::legacy_tile))
        .route(web::TERRARIUM_JSON, get(web::terrarium_json))
        .route(web::TERRAIN_RGB_JSON, get(web::terrain_rgb_json))
        .route(web::TEXTURE_JSON, get(web::texture_json))
        .route(web::CESIUM_LAYER, get(web::cesium_layer));
    let tile_api = web::tile_templates()
        .into_iter()
        .fold(tile_api, |router, (template, kind)| {
            router.route(
                &template,
                get(move |state, uri, path, conditional| {
                    web::tile(state, kind, uri, path, conditional)
                }),
            )
        });
    #[cfg(feature = "test-hooks")]
    let tile_api = tile_api.route(hooks::SLEEP, get(hooks::sleep));

    let tile_api = tile_api.layer(limits::TileLimitsLayer::new(
        options.max_concurrent_requests,
        options.request_timeout,
    ));

    let mut operations = Router::new()
        .route(HEALTHZ, get(routes::healthz))
        .route(METRICS, get(routes::metrics))
        .route("/", get(web::root));
    if let Some(dir) = &state.viewer {
        // The one route that reads files: tower-http's ServeDir, which refuses any path
        // that would leave `dir` (`..`, absolute paths, symbolic links are followed only
        // inside what the OS resolves under it).
        // A directory asked for without its slash is redirected to it: ServeDir sees the
        // path without `/view`, so its `Location` gets the prefix back here.
        let files = tower::ServiceBuilder::new()
            .map_response(|mut response: axum::http::Response<_>| {
                let location = response.headers().get(axum::http::header::LOCATION);
                if let Some(fixed) = location
                    .and_then(|l| l.to_str().ok())
                    .filter(|l| l.starts_with('/'))
                    .and_then(|l| axum::http::HeaderValue::from_str(&format!("/view{l}")).ok())
                {
                    response
                        .headers_mut()
                        .insert(axum::http::header::LOCATION, fixed);
                }
                response
            })
            .service(tower_http::services::ServeDir::new(dir));
        operations = operations.nest_service("/view", files);
    }

    tile_api
        .merge(operations)
        .fallback(routes::no_route)
        .method_not_allowed_fallback(routes::method_not_allowed)
        .layer(
            ServiceBuilder::new()
                .layer(axum::middleware::from_fn_with_state(
                    Arc::clone(&state),
                    metrics::observe,
                ))
                .layer(cors()),
        )
        .with_state(state)
}

/// Any origin may read tiles (they are public), with GET and HEAD only. `ETag` is exposed
/// so a web client can revalidate the manifest itself, and `If-None-Match` allowed for it.
fn cors() -> CorsLayer {
    CorsLayer::new()
        .allow_origin(Any)
        .allow_methods([Method::GET, Method::HEAD])
        .allow_headers([header::IF_NONE_MATCH])
        .expose_headers([header::ETAG])
        .max_age(std::time::Duration::from_secs(24 * 60 * 60))
}
