//! One HTTP request per call against a tile server: the manifest, a tile's heights, a
//! tile's texture level. Owns URL building, status handling and content verification:
//! every tile body is checked against the hash the manifest records for it, so a caller
//! never sees bytes the manifest does not vouch for.
//!
//! Left to callers: retries, backoff, cancellation and the order in which tiles are
//! fetched (the belt order of the later pager). Each call here is one attempt, and
//! [`FetchError::is_transient`] tells such a caller which failures are worth another.

use bytes::Bytes;
use std::time::Duration;
use terrain_shared::manifest::{ManifestError, content_hash};
use terrain_shared::tile_blob::TileBlobError;
use terrain_shared::{Blob, DecodeError, Heights, Manifest, TileBlob, TileId, routes};
use thiserror::Error;
use web_time::Instant;

/// Longest wait for a TCP connection. A tile server is usually near (same host, LAN or a
/// CDN edge), where a connection takes milliseconds; 5 s separates "slow" from "not there".
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
/// Longest time for one whole request, body included. The largest blob (a finest texture
/// level of a 4097-sample tile, a few MB) takes well under a second on a LAN; 30 s leaves
/// room for a slow link without letting a stuck server hold a request forever.
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(30);
/// How much of an error response's body goes into [`FetchError::Http`]. The server's
/// bodies are one short JSON object; anything longer is not meant for a person, and no
/// more of it is read.
pub const MAX_ERROR_BODY: usize = 512;
/// The largest manifest a client takes, unless told otherwise
/// ([`TileClient::with_max_manifest_bytes`]): about a hundred bytes a tile, so a pyramid of
/// two million tiles. A longer body (or one that says it will be) is refused as it arrives,
/// not read to its end.
pub const MAX_MANIFEST_BYTES: u64 = 256 << 20;
/// The largest body whose size nothing states (a method's data without an index entry, a
/// finer texture level fetched unverified), far above any tile's.
pub const MAX_UNSIZED_BODY: u64 = 64 << 20;

#[cfg(not(target_arch = "wasm32"))]
const USER_AGENT: &str = concat!("terrain-client/", env!("CARGO_PKG_VERSION"));

/// A client for one tile server. Cheap to clone (the connection pool is shared), so hand
/// a clone to each task.
///
/// ```no_run
/// # async fn demo() -> Result<(), terrain_client::http_client::FetchError> {
/// use terrain_client::http_client::TileClient;
/// use terrain_shared::TileId;
///
/// let client = TileClient::new("http://127.0.0.1:8080")?;
/// let manifest = client.manifest().await?;
/// let tile = client.tile(&manifest, TileId::new(0, 0)).await?;
/// let coarsest = client.texture(&manifest, TileId::new(0, 0), 0, Some(&tile.texture[0])).await?;
/// # Ok(()) }
/// ```
#[derive(Debug, Clone)]
pub struct TileClient {
    /// Scheme, host, port and any path prefix, without a trailing slash: route paths
    /// (which start with `/`) are appended as they are, so a server mounted under a prefix
    /// (`http://host/terrain`) works too.
    base: String,
    http: reqwest::Client,
    /// The most bytes a manifest may have ([`MAX_MANIFEST_BYTES`] by default).
    max_manifest_bytes: u64,
}

/// Why a request did not produce verified content.
#[derive(Debug, Error)]
pub enum FetchError {
    #[error("invalid server URL {url:?}: {reason}")]
    BadUrl { url: String, reason: String },
    #[error("could not set up the HTTP client")]
    ClientSetup {
        #[source]
        source: reqwest::Error,
    },
    /// No usable response: connection refused or reset, timeout, body cut short.
    #[error("GET {url} failed")]
    Transport {
        url: String,
        #[source]
        source: reqwest::Error,
    },
    /// The server answered 4xx or 5xx; `body` is the start of its JSON error body.
    #[error("GET {url}: {status}: {body}")]
    Http {
        url: String,
        status: reqwest::StatusCode,
        body: String,
    },
    /// The body is longer than it can be: its size is known (a tile's, from the manifest)
    /// or capped (the manifest's), and the server said it would send more, or began to.
    /// Refused without reading the rest, so an endless or oversized body costs no memory.
    #[error("GET {url}: the body is longer than the {limit} bytes it can be{}", declared.map(|d| format!(" (Content-Length: {d})")).unwrap_or_else(|| " (cut off there)".into()))]
    TooLarge {
        url: String,
        limit: u64,
        declared: Option<u64>,
    },
    #[error("GET {url}: body has content hash {found}, the manifest says {expected}")]
    HashMismatch {
        url: String,
        expected: String,
        found: String,
    },
    #[error("GET {url}: body is not a valid heights tile")]
    Decode {
        url: String,
        #[source]
        source: DecodeError,
    },
    #[error("GET {url}: body is not a valid tile blob")]
    TileBlob {
        url: String,
        #[source]
        source: TileBlobError,
    },
    #[error("GET {url}: unusable manifest")]
    Manifest {
        url: String,
        #[source]
        source: ManifestError,
    },
    #[error("tile {id} is not in the {columns}x{rows} grid of its level")]
    NotInGrid { id: TileId, columns: u32, rows: u32 },
    #[error("tile {id} has texture levels 0 to {}, not {level}", levels.saturating_sub(1))]
    NoSuchTextureLevel { id: TileId, level: u32, levels: u32 },
    /// The runtime shut down before the work finished (it never panics: decoding returns
    /// errors for any input).
    #[error("{url}: cancelled before it finished")]
    Cancelled { url: String },
}

impl FetchError {
    /// The error and every cause under it, joined by `: `, each once: what a log line or a
    /// report needs (the variants' own messages leave their `#[source]` out, so that
    /// `anyhow`'s `{:#}` does not print a cause twice).
    pub fn chain(&self) -> String {
        cause_chain(self)
    }

    /// Whether the same request may succeed if tried again later: transport failures,
    /// timeouts, and the statuses that say "not now" (408, 429, 5xx). Everything else is
    /// a property of the request or the content and repeats on every attempt.
    pub fn is_transient(&self) -> bool {
        match self {
            FetchError::Transport { .. } => true,
            FetchError::Http { status, .. } => {
                status.is_server_error()
                    || *status == reqwest::StatusCode::REQUEST_TIMEOUT
                    || *status == reqwest::StatusCode::TOO_MANY_REQUESTS
            }
            _ => false,
        }
    }
}

impl TileClient {
    /// A client for the server at `base_url`, e.g. `http://127.0.0.1:8080`. Only plain
    /// `http` is supported: this build has no TLS (put a TLS-terminating proxy in front).
    pub fn new(base_url: &str) -> Result<TileClient, FetchError> {
        let bad = |reason: &str| FetchError::BadUrl {
            url: base_url.to_string(),
            reason: reason.to_string(),
        };
        let url = reqwest::Url::parse(base_url).map_err(|e| bad(&e.to_string()))?;
        match url.scheme() {
            "http" => {}
            "https" => {
                return Err(bad(
                    "https is not supported by this build (no TLS); use http",
                ));
            }
            other => return Err(bad(&format!("scheme {other:?} is not http"))),
        }
        if url.host_str().is_none_or(str::is_empty) {
            return Err(bad("no host"));
        }
        if url.query().is_some() || url.fragment().is_some() {
            return Err(bad("a server URL takes no query or fragment"));
        }
        // In a page the browser sets the user agent and its own connection timeouts.
        #[cfg(not(target_arch = "wasm32"))]
        let http = reqwest::Client::builder()
            .connect_timeout(CONNECT_TIMEOUT)
            .timeout(REQUEST_TIMEOUT)
            .user_agent(USER_AGENT);
        #[cfg(target_arch = "wasm32")]
        let http = reqwest::Client::builder();
        let http = http
            .build()
            .map_err(|source| FetchError::ClientSetup { source })?;
        Ok(TileClient {
            base: url.as_str().trim_end_matches('/').to_string(),
            http,
            max_manifest_bytes: MAX_MANIFEST_BYTES,
        })
    }

    /// This client with manifests of at most `bytes` (a flight caps it at its memory
    /// budget: a manifest it could not hold is refused as it arrives).
    pub fn with_max_manifest_bytes(mut self, bytes: u64) -> TileClient {
        self.max_manifest_bytes = bytes;
        self
    }

    /// The server's base URL, without a trailing slash.
    pub fn base_url(&self) -> &str {
        &self.base
    }

    /// The absolute URL of a route path from [`terrain_shared::routes`].
    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    /// Fetches and validates the manifest. The server tags it with its content hash (a
    /// strong `ETag`); a body that does not match its tag was damaged on the way and is a
    /// [`FetchError::HashMismatch`], worth fetching again, like a damaged tile.
    pub async fn manifest(&self) -> Result<Manifest, FetchError> {
        let url = self.url(routes::MANIFEST);
        let (body, etag) = self.get_tagged(&url, self.max_manifest_bytes).await?;
        // A weak tag (`W/"..."`) names another representation (compressed); only a strong
        // one is the hash of these bytes.
        if let Some(expected) = etag.as_deref().and_then(|tag| tag.strip_prefix('"')) {
            verify_hash(&url, &body, expected.trim_end_matches('"'))?;
        }
        Manifest::from_json(&body).map_err(|source| FetchError::Manifest { url, source })
    }

    /// Fetches one tile's blob, verifies it and decodes it (mask errors, texture hashes,
    /// heights) off the async threads.
    pub async fn tile(&self, manifest: &Manifest, id: TileId) -> Result<FetchedTile, FetchError> {
        let body = self.tile_bytes(manifest, id).await?;
        decode_tile(
            self.url(&routes::heights(&manifest.content_version, id)),
            body,
        )
        .await
    }

    /// Fetches one tile's blob and verifies its hash, without decoding: for callers that
    /// decode elsewhere or time the two steps apart.
    pub async fn tile_bytes(&self, manifest: &Manifest, id: TileId) -> Result<Bytes, FetchError> {
        let blob = record(manifest, id)?.blob();
        let url = self.url(&routes::heights(&manifest.content_version, id));
        self.get_verified(url, &blob).await
    }

    /// Fetches one texture level (0 = coarsest) of one tile and verifies it against
    /// `expected`, the tile blob's entry for it ([`FetchedTile::texture`]); `None` fetches
    /// it unverified, for a caller that verifies it once the tile blob is in
    /// ([`verify_hash`]). Returns the encoded image, in the manifest's `texture.format`.
    pub async fn texture(
        &self,
        manifest: &Manifest,
        id: TileId,
        level: u32,
        expected: Option<&Blob>,
    ) -> Result<Bytes, FetchError> {
        record(manifest, id)?;
        if level >= manifest.texture.levels {
            return Err(FetchError::NoSuchTextureLevel {
                id,
                level,
                levels: manifest.texture.levels,
            });
        }
        let url = self.url(&routes::texture(&manifest.content_version, id, level));
        match expected {
            Some(blob) => self.get_verified(url, blob).await,
            // Unverified: the coarsest level, whose size the manifest gives.
            None => {
                let limit = match level {
                    0 => record(manifest, id)?.coarsest_texture_bytes,
                    _ => MAX_UNSIZED_BODY,
                };
                self.get(&url, limit).await
            }
        }
    }

    /// Fetches the body at `path` (a route of [`terrain_shared::routes`]), verified against
    /// `hash` (BLAKE3, first 128 bits, hex) when given, of at most `bytes` bytes when its
    /// size is known ([`MAX_UNSIZED_BODY`] when not).
    pub async fn blob(
        &self,
        path: &str,
        hash: Option<&str>,
        bytes: Option<u64>,
    ) -> Result<Bytes, FetchError> {
        let url = self.url(path);
        let body = self.get(&url, bytes.unwrap_or(MAX_UNSIZED_BODY)).await?;
        if let Some(expected) = hash {
            verify_hash(&url, &body, expected)?;
        }
        Ok(body)
    }

    async fn get_verified(&self, url: String, blob: &Blob) -> Result<Bytes, FetchError> {
        let body = self.get(&url, blob.bytes).await?;
        verify_hash(&url, &body, &blob.hash)?;
        Ok(body)
    }

    /// One GET of a body of at most `limit` bytes; a 4xx/5xx becomes [`FetchError::Http`]
    /// carrying the start of the server's error body.
    async fn get(&self, url: &str, limit: u64) -> Result<Bytes, FetchError> {
        self.get_tagged(url, limit).await.map(|(body, _)| body)
    }

    /// [`TileClient::get`], with the response's `ETag` when it has one.
    #[tracing::instrument(level = "debug", skip(self), fields(status, bytes, ms))]
    async fn get_tagged(
        &self,
        url: &str,
        limit: u64,
    ) -> Result<(Bytes, Option<String>), FetchError> {
        let start = Instant::now();
        let transport = |source| FetchError::Transport {
            url: url.to_string(),
            source,
        };
        let response = self.http.get(url).send().await.map_err(transport)?;
        let status = response.status();
        let span = tracing::Span::current();
        span.record("status", status.as_u16());
        if status.is_client_error() || status.is_server_error() {
            // The error body is best effort (the status alone says what happened), and only
            // its start is read.
            let body = read_body(response, MAX_ERROR_BODY as u64, true)
                .await
                .unwrap_or_default();
            let body = error_body_text(&body);
            tracing::debug!(%status, body, "error response");
            return Err(FetchError::Http {
                url: url.to_string(),
                status,
                body,
            });
        }
        let etag = response
            .headers()
            .get(reqwest::header::ETAG)
            .and_then(|tag| tag.to_str().ok())
            .map(str::to_string);
        let too_large = |declared| FetchError::TooLarge {
            url: url.to_string(),
            limit,
            declared,
        };
        if let Some(declared) = response.content_length().filter(|&d| d > limit) {
            return Err(too_large(Some(declared)));
        }
        let body = read_body(response, limit, false)
            .await
            .map_err(|e| match e {
                BodyError::Transport(source) => transport(source),
                BodyError::TooLarge => too_large(None),
            })?;
        span.record("bytes", body.len());
        span.record("ms", start.elapsed().as_millis() as u64);
        tracing::debug!("fetched");
        Ok((body, etag))
    }
}

/// Why [`read_body`] stopped.
enum BodyError {
    Transport(reqwest::Error),
    TooLarge,
}

/// Reads `response`'s body a chunk at a time, never holding more than `limit` bytes: past
/// them it stops, with the bytes so far when `truncate`, else [`BodyError::TooLarge`].
#[cfg(not(target_arch = "wasm32"))]
async fn read_body(
    mut response: reqwest::Response,
    limit: u64,
    truncate: bool,
) -> Result<Bytes, BodyError> {
    let limit = usize::try_from(limit).unwrap_or(usize::MAX);
    // The stated length when it fits, so a sized body is one allocation; else doubling,
    // never past the limit, so a body cut off there never held more than `limit` bytes.
    let stated = response
        .content_length()
        .and_then(|n| usize::try_from(n).ok());
    let mut body = Vec::with_capacity(stated.unwrap_or(0).min(limit));
    while let Some(chunk) = response.chunk().await.map_err(BodyError::Transport)? {
        if body.len() + chunk.len() > limit {
            if truncate {
                body.extend_from_slice(&chunk[..limit - body.len()]);
                break;
            }
            return Err(BodyError::TooLarge);
        }
        let needed = body.len() + chunk.len();
        if needed > body.capacity() {
            let grown = needed.max(body.len().saturating_mul(2)).min(limit);
            body.reserve_exact(grown - body.len());
        }
        body.extend_from_slice(&chunk);
    }
    Ok(Bytes::from(body))
}

/// [`read_body`] in a page: the browser's `fetch` hands the body over whole, so a body
/// whose length was stated is refused before it is read when too long (the caller checks),
/// and one whose length was not is held by the browser whole before the limit applies.
#[cfg(target_arch = "wasm32")]
async fn read_body(
    response: reqwest::Response,
    limit: u64,
    truncate: bool,
) -> Result<Bytes, BodyError> {
    let limit = usize::try_from(limit).unwrap_or(usize::MAX);
    let body = response.bytes().await.map_err(BodyError::Transport)?;
    match body.len() > limit {
        false => Ok(body),
        true if truncate => Ok(body.slice(..limit)),
        true => Err(BodyError::TooLarge),
    }
}

/// `error` and every cause under it, joined by `: `. Causes whose text the one above
/// already ends with (a wrapper repeating its source) are left out, so each shows once.
pub fn cause_chain(error: &(dyn std::error::Error + 'static)) -> String {
    let mut text = error.to_string();
    let mut cause = error.source();
    while let Some(error) = cause {
        let line = error.to_string();
        if !line.is_empty() && !text.ends_with(&line) {
            text.push_str(": ");
            text.push_str(&line);
        }
        cause = error.source();
    }
    text
}

/// A tile blob, decoded: what a tile brings besides its bounds in the manifest.
#[derive(Debug, Clone)]
pub struct FetchedTile {
    /// Per strip-mask level, its error against the full-resolution surface, metres.
    pub mask_errors_m: Vec<f32>,
    /// Hash and size of each texture level, coarsest first: what the texture bodies are
    /// checked against.
    pub texture: Vec<Blob>,
    pub heights: Heights,
}

/// Decodes a tile blob fetched from `url` off the async threads ([`crate::tasks::off_thread`]): a large tile takes
/// milliseconds of CPU, which would stall every other request sharing the async thread.
pub async fn decode_tile(url: String, body: Bytes) -> Result<FetchedTile, FetchError> {
    let decode = move || -> Result<FetchedTile, FetchError> {
        let blob = TileBlob::head(&body).map_err(|source| FetchError::TileBlob {
            url: url.clone(),
            source,
        })?;
        let heights = Heights::decode(&body[blob.heights_at..])
            .map_err(|source| FetchError::Decode { url, source })?;
        Ok(FetchedTile {
            mask_errors_m: blob.mask_errors_m,
            texture: blob.texture,
            heights,
        })
    };
    crate::tasks::off_thread(decode).await.unwrap_or_else(|| {
        Err(FetchError::Cancelled {
            url: "a tile blob being decoded".into(),
        })
    })
}

fn record(manifest: &Manifest, id: TileId) -> Result<&terrain_shared::TileRecord, FetchError> {
    manifest.tile(id).ok_or_else(|| {
        let grid = manifest.grid(id.level);
        FetchError::NotInGrid {
            id,
            columns: grid.columns,
            rows: grid.rows,
        }
    })
}

/// The start of an error body as one line of text, cut at a character boundary.
fn error_body_text(body: &[u8]) -> String {
    let text = String::from_utf8_lossy(body);
    let text = text.trim();
    if text.is_empty() {
        return "(empty body)".to_string();
    }
    if text.len() <= MAX_ERROR_BODY {
        return text.replace(['\r', '\n'], " ");
    }
    let mut end = MAX_ERROR_BODY;
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    format!("{}…", text[..end].replace(['\r', '\n'], " "))
}

/// A body fetched from `url` must hash to `expected`; else it was damaged on the way.
pub fn verify_hash(url: &str, body: &[u8], expected: &str) -> Result<(), FetchError> {
    let found = content_hash(body);
    if found != expected {
        return Err(FetchError::HashMismatch {
            url: url.to_string(),
            expected: expected.to_string(),
            found,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check_bad_url(url: &str, reason_contains: &str) {
        match TileClient::new(url) {
            Err(FetchError::BadUrl { reason, .. }) => {
                assert!(reason.contains(reason_contains), "{url}: reason {reason:?}");
            }
            other => panic!("{url}: expected BadUrl, got {other:?}"),
        }
    }

    #[test]
    fn server_urls_without_http_or_host_are_refused() {
        check_bad_url("127.0.0.1:8080", "");
        check_bad_url("not a url", "");
        check_bad_url("https://example.org", "https");
        check_bad_url("ftp://example.org", "scheme");
        check_bad_url("http://example.org/?a=1", "query");
    }

    #[test]
    fn route_paths_are_appended_to_the_base_url_and_its_prefix() {
        let client = TileClient::new("http://127.0.0.1:8080/").expect("valid url");
        assert_eq!(
            client.url(routes::MANIFEST),
            "http://127.0.0.1:8080/v1/manifest.json"
        );
        let client = TileClient::new("http://host/terrain/").expect("valid url");
        assert_eq!(client.base_url(), "http://host/terrain");
        assert_eq!(
            client.url(&routes::heights("abc", TileId::new(1, 2))),
            "http://host/terrain/v1/abc/levels/0/tiles/1/2/heights"
        );
    }

    #[test]
    fn error_messages_name_the_request_status_and_server_reason() {
        let error = FetchError::Http {
            url: "http://h/v1/x/tiles/9/9/heights".into(),
            status: reqwest::StatusCode::NOT_FOUND,
            body: error_body_text(br#"{"error":"tile 9/9 is outside the 2x2 grid","status":404}"#),
        };
        assert_eq!(
            error.to_string(),
            r#"GET http://h/v1/x/tiles/9/9/heights: 404 Not Found: {"error":"tile 9/9 is outside the 2x2 grid","status":404}"#
        );
        assert!(!error.is_transient());
        let overloaded = FetchError::Http {
            url: "u".into(),
            status: reqwest::StatusCode::SERVICE_UNAVAILABLE,
            body: String::new(),
        };
        assert!(overloaded.is_transient());
    }

    #[test]
    fn long_or_empty_error_bodies_are_shortened_or_named() {
        assert_eq!(error_body_text(b"  "), "(empty body)");
        let long = "é".repeat(MAX_ERROR_BODY);
        let text = error_body_text(long.as_bytes());
        assert!(
            text.len() <= MAX_ERROR_BODY + '…'.len_utf8(),
            "{} bytes",
            text.len()
        );
        assert!(text.ends_with('…'));
    }
}
