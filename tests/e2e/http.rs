//! The HTTP server against a real client: routes (every level of the pyramid, and the
//! single-level spelling redirected), caching headers, errors, compression, CORS, metrics,
//! and the hardening (timeouts, load shedding, graceful shutdown).
//!
//! Every test serves a [`SyntheticDb`] on `127.0.0.1:0` through the library's `serve`,
//! and talks to it with reqwest, or with a raw TCP socket where a test needs to misbehave
//! the way no HTTP client library will (trickle headers, stop reading a body).

use reqwest::Method;
use reqwest::header::HeaderMap;
use std::io::Read;
use std::time::{Duration, Instant};
use terrain_server::http::ServeOptions;
use terrain_shared::manifest::content_hash;
use terrain_shared::routes;
use terrain_shared::{TileBlob, TileId};
use terrain_tests::server::TestServer;
use terrain_tests::synthetic::{LARGE_TEXTURE, SyntheticDb};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Content type of a tile blob (`terrain_shared::tile_blob`), what the heights route serves.
const HEIGHTS_CONTENT_TYPE: &str = "application/vnd.terrain.tile";
const TILE_CACHE_CONTROL: &str = "public, max-age=31536000, immutable";
const MANIFEST_CACHE_CONTROL: &str = "public, no-cache";
/// Route templates as they must appear in metric labels.
const HEIGHTS_ROUTE: &str = "/v1/{content_version}/levels/{level}/tiles/{x}/{y}/heights";
const TEXTURE_ROUTE: &str = "/v1/{content_version}/levels/{level}/tiles/{x}/{y}/texture/{mip}";
/// The single-level API's spelling of a level-0 tile, answered with a redirect.
const LEGACY_HEIGHTS_ROUTE: &str = "/v1/{content_version}/tiles/{x}/{y}/heights";

/// One answer, read whole.
#[derive(Debug)]
struct Answer {
    status: u16,
    headers: HeaderMap,
    body: Vec<u8>,
}

impl Answer {
    fn header(&self, name: &str) -> &str {
        self.headers
            .get(name)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
    }

    /// The `(error, status)` of a JSON error body; panics if the body is not one.
    fn json_error(&self) -> (String, u16) {
        assert_eq!(
            self.header("content-type"),
            "application/json",
            "error body type"
        );
        let value: serde_json::Value = serde_json::from_slice(&self.body).unwrap_or_else(|error| {
            panic!(
                "error body is not JSON ({error}): {:?}",
                String::from_utf8_lossy(&self.body)
            )
        });
        let message = value["error"]
            .as_str()
            .expect("error body has an \"error\" string")
            .to_string();
        let status = value["status"]
            .as_u64()
            .expect("error body has a numeric \"status\"") as u16;
        (message, status)
    }
}

async fn fetch(
    client: &reqwest::Client,
    method: Method,
    url: &str,
    headers: &[(&str, &str)],
) -> Answer {
    let mut request = client.request(method, url);
    for (name, value) in headers {
        request = request.header(*name, *value);
    }
    let response = request
        .send()
        .await
        .unwrap_or_else(|error| panic!("request to {url} failed: {error}"));
    let status = response.status().as_u16();
    let headers = response.headers().clone();
    let body = response
        .bytes()
        .await
        .unwrap_or_else(|error| panic!("body of {url} failed: {error}"))
        .to_vec();
    Answer {
        status,
        headers,
        body,
    }
}

async fn get(client: &reqwest::Client, url: &str) -> Answer {
    fetch(client, Method::GET, url, &[]).await
}

fn synthetic() -> SyntheticDb {
    SyntheticDb::write().expect("cannot write the synthetic database")
}

fn manifest_json(db: &SyntheticDb) -> Vec<u8> {
    std::fs::read(db.dir().join(terrain_server::db::MANIFEST_FILE))
        .expect("cannot read the synthetic manifest")
}

fn quoted(hash: &str) -> String {
    format!("\"{hash}\"")
}

/// What a successful GET of one entity must return.
struct Expected {
    path: String,
    bytes: Vec<u8>,
    content_type: &'static str,
    cache_control: &'static str,
}

#[tokio::test]
async fn manifest_and_every_tile_are_served_with_their_bytes_content_type_etag_and_cache_control() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let client = reqwest::Client::new();
    let version = &db.manifest().content_version;

    let mut expected = vec![Expected {
        path: routes::MANIFEST.to_string(),
        bytes: manifest_json(&db),
        content_type: "application/json",
        cache_control: MANIFEST_CACHE_CONTROL,
    }];
    for id in db.all_tile_ids() {
        expected.push(Expected {
            path: routes::heights(version, id),
            bytes: db.heights(id).to_vec(),
            content_type: HEIGHTS_CONTENT_TYPE,
            cache_control: TILE_CACHE_CONTROL,
        });
        for level in 0..db.manifest().texture.levels {
            expected.push(Expected {
                path: routes::texture(version, id, level),
                bytes: db.texture(id, level).to_vec(),
                content_type: "image/png",
                cache_control: TILE_CACHE_CONTROL,
            });
        }
    }
    // 1 manifest + (4 tiles of level 0 + 1 of level 1) x (heights + 2 levels): refuse to
    // pass on an empty grid.
    assert_eq!(expected.len(), 16);

    for entity in &expected {
        let answer = get(&client, &server.url(&entity.path)).await;
        assert_eq!(answer.status, 200, "{}", entity.path);
        assert!(
            answer.body == entity.bytes,
            "{}: body differs from the stored bytes",
            entity.path
        );
        assert_eq!(
            answer.header("content-type"),
            entity.content_type,
            "{}",
            entity.path
        );
        assert_eq!(
            answer.header("etag"),
            quoted(&content_hash(&entity.bytes)),
            "{}",
            entity.path
        );
        assert_eq!(
            answer.header("cache-control"),
            entity.cache_control,
            "{}",
            entity.path
        );
        assert_eq!(
            answer.header("content-length"),
            entity.bytes.len().to_string(),
            "{}",
            entity.path
        );
    }

    // The served tile blobs decode to the codes the database was written with, at every
    // level, and the texture hashes they carry verify the texture bodies served.
    for id in db.all_tile_ids() {
        let answer = get(&client, &server.url(&routes::heights(version, id))).await;
        let blob = TileBlob::decode(&answer.body).expect("a served tile blob decodes");
        assert_eq!(
            blob,
            TileBlob::decode(db.heights(id)).expect("as written"),
            "{id}"
        );
        let heights =
            terrain_shared::Heights::decode(&blob.heights).expect("served heights decode");
        assert_eq!(heights, SyntheticDb::codes(id), "{id}");
        assert_eq!(
            blob.mask_errors_m.len(),
            db.manifest().mask_levels as usize,
            "{id}"
        );
        assert_eq!(
            blob.texture.len(),
            db.manifest().texture.levels as usize,
            "{id}"
        );
        for (level, listed) in blob.texture.iter().enumerate() {
            let path = routes::texture(version, id, level as u32);
            let texture = get(&client, &server.url(&path)).await;
            assert_eq!(texture.status, 200, "{path}");
            assert_eq!(content_hash(&texture.body), listed.hash, "{path}");
            assert_eq!(texture.body.len() as u64, listed.bytes, "{path}");
        }
    }
}

#[tokio::test]
async fn head_requests_get_the_headers_of_get_without_a_body() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let client = reqwest::Client::new();
    let id = TileId::new(0, 1);
    let answer = fetch(
        &client,
        Method::HEAD,
        &server.url(&routes::heights(&db.manifest().content_version, id)),
        &[],
    )
    .await;
    assert_eq!(answer.status, 200);
    assert!(answer.body.is_empty());
    assert_eq!(answer.header("etag"), quoted(&content_hash(db.heights(id))));
    assert_eq!(
        answer.header("content-length"),
        db.heights(id).len().to_string()
    );
}

#[tokio::test]
async fn a_matching_if_none_match_gives_304_without_a_body_and_another_gives_200() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let client = reqwest::Client::new();
    let version = &db.manifest().content_version;
    let id = TileId::new(1, 1);
    let entities = [
        (
            routes::MANIFEST.to_string(),
            content_hash(&manifest_json(&db)),
            MANIFEST_CACHE_CONTROL,
        ),
        (
            routes::heights(version, id),
            content_hash(db.heights(id)),
            TILE_CACHE_CONTROL,
        ),
        (
            routes::texture(version, id, 1),
            content_hash(db.texture(id, 1)),
            TILE_CACHE_CONTROL,
        ),
        (
            routes::heights(version, TileId::at(1, 0, 0)),
            content_hash(db.heights(TileId::at(1, 0, 0))),
            TILE_CACHE_CONTROL,
        ),
        (
            routes::texture(version, TileId::at(1, 0, 0), 0),
            content_hash(db.texture(TileId::at(1, 0, 0), 0)),
            TILE_CACHE_CONTROL,
        ),
    ];
    for (path, hash, cache_control) in &entities {
        let tag = quoted(hash);
        let matching = [
            tag.clone(),
            format!("W/{tag}"),
            format!("\"0123\", {tag}"),
            format!("W/\"0123\",{tag} , \"4567\""),
            "*".to_string(),
        ];
        for if_none_match in &matching {
            let answer = fetch(
                &client,
                Method::GET,
                &server.url(path),
                &[("if-none-match", if_none_match)],
            )
            .await;
            assert_eq!(
                answer.status, 304,
                "{path} with If-None-Match: {if_none_match}"
            );
            assert!(answer.body.is_empty(), "{path}: a 304 has no body");
            assert_eq!(answer.header("etag"), tag, "{path}: a 304 repeats the ETag");
            assert_eq!(
                answer.header("cache-control"),
                *cache_control,
                "{path}: a 304 repeats Cache-Control"
            );
        }
        for if_none_match in ["\"0123\"", "\"0123\", W/\"4567\"", &hash.clone(), "garbage"] {
            let answer = fetch(
                &client,
                Method::GET,
                &server.url(path),
                &[("if-none-match", if_none_match)],
            )
            .await;
            assert_eq!(
                answer.status, 200,
                "{path} with If-None-Match: {if_none_match}"
            );
            assert!(!answer.body.is_empty());
        }
    }
}

/// Sends `method path` and checks the status and the JSON error body; returns the message.
async fn check_error(
    client: &reqwest::Client,
    server: &TestServer,
    method: Method,
    path: &str,
    status: u16,
) -> String {
    let answer = fetch(client, method.clone(), &server.url(path), &[]).await;
    assert_eq!(
        answer.status,
        status,
        "{method} {path}: {:?}",
        String::from_utf8_lossy(&answer.body)
    );
    let (message, body_status) = answer.json_error();
    assert_eq!(body_status, status, "{method} {path}: status in the body");
    assert!(
        !message.is_empty() && message.len() < 300,
        "{method} {path}: a short message, got {message:?}"
    );
    assert_eq!(
        answer.header("cache-control"),
        "no-store",
        "{method} {path}: errors are not cached"
    );
    message
}

#[tokio::test]
async fn malformed_coordinates_and_levels_give_400_with_a_json_body() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let client = reqwest::Client::new();
    let v = &db.manifest().content_version;
    let cases = [
        format!("/v1/{v}/levels/0/tiles/-1/0/heights"),
        format!("/v1/{v}/levels/0/tiles/0/-1/heights"),
        format!("/v1/{v}/levels/-1/tiles/0/0/heights"),
        format!("/v1/{v}/levels/x/tiles/0/0/heights"),
        format!("/v1/{v}/levels/01/tiles/0/0/heights"),
        format!("/v1/{v}/levels/+1/tiles/0/0/heights"),
        format!("/v1/{v}/levels/4294967296/tiles/0/0/heights"),
        format!("/v1/{v}/levels/%FF/tiles/0/0/heights"),
        format!("/v1/{v}/levels/0/tiles/0/0/texture/-1"),
        format!("/v1/{v}/levels/1.0/tiles/0/0/texture/0"),
        format!("/v1/{v}/levels/0/tiles/x/0/texture/0"),
        // The single-level spelling is checked like the levels' before it is redirected.
        format!("/v1/{v}/tiles/-1/0/heights"),
        format!("/v1/{v}/tiles/0/-1/heights"),
        format!("/v1/{v}/tiles/x/0/heights"),
        format!("/v1/{v}/tiles/0/1.0/heights"),
        format!("/v1/{v}/tiles/4294967296/0/heights"),
        format!("/v1/{v}/tiles/0/99999999999999999999999999/heights"),
        format!("/v1/{v}/tiles/01/0/heights"),
        format!("/v1/{v}/tiles/+1/0/heights"),
        format!("/v1/{v}/tiles/%20/0/heights"),
        format!("/v1/{v}/tiles/%FF/0/heights"),
        format!("/v1/{v}/tiles/0/0/texture/-1"),
        format!("/v1/{v}/tiles/0/0/texture/one"),
        format!("/v1/{v}/tiles/0/0/texture/4294967296"),
        format!("/v1/{v}/tiles/-5/0/texture/0"),
    ];
    for path in &cases {
        check_error(&client, &server, Method::GET, path, 400).await;
    }
    for (path, segment) in [
        (
            format!("/v1/{v}/levels/0/tiles/-1/0/heights"),
            "x coordinate",
        ),
        (format!("/v1/{v}/tiles/-1/0/heights"), "x coordinate"),
        (format!("/v1/{v}/levels/-1/tiles/0/0/heights"), "level"),
    ] {
        let message = check_error(&client, &server, Method::GET, &path, 400).await;
        assert!(
            message.contains(segment) && message.contains("\"-1\""),
            "{path}: {message}"
        );
    }
}

#[tokio::test]
async fn missing_tiles_levels_stale_versions_and_unknown_routes_give_404_with_a_json_body() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let client = reqwest::Client::new();
    let v = &db.manifest().content_version;
    let levels = db.manifest().texture.levels;
    // The pyramid: level 0 of 2x2 tiles, level 1 of one.
    let past_the_last = db.manifest().level_count();
    assert_eq!(past_the_last, 2);
    let cases = [
        routes::heights(v, TileId::new(2, 0)),
        routes::heights(v, TileId::new(0, 2)),
        routes::heights(v, TileId::new(u32::MAX, u32::MAX)),
        routes::heights(v, TileId::at(1, 1, 0)),
        routes::heights(v, TileId::at(past_the_last, 0, 0)),
        routes::heights(v, TileId::at(u32::MAX, 0, 0)),
        routes::texture(v, TileId::new(2, 1), 0),
        routes::texture(v, TileId::at(1, 0, 1), 0),
        routes::texture(v, TileId::at(past_the_last, 0, 0), 0),
        routes::texture(v, TileId::new(0, 0), levels),
        routes::texture(v, TileId::at(1, 0, 0), levels),
        routes::texture(v, TileId::new(0, 0), u32::MAX),
        "/v1".to_string(),
        "/v1/manifest.json/x".to_string(),
        "/v2/manifest.json".to_string(),
        format!("/v1/{v}/tiles/0/0"),
        format!("/v1/{v}/tiles/0/0/heights/extra"),
        format!("/v1/{v}/levels/0/tiles/0/0"),
        format!("/v1/{v}/levels/0/tiles/0/0/heights/extra"),
        format!("/v1/{v}/levels/0/heights"),
        // A single-level URL of a tile that does not exist is not redirected.
        format!("/v1/{v}/tiles/2/0/heights"),
        format!("/v1/{v}/tiles/0/2/texture/0"),
        "/v1/../../etc/passwd".to_string(),
    ];
    for path in &cases {
        check_error(&client, &server, Method::GET, path, 404).await;
    }

    let message = check_error(
        &client,
        &server,
        Method::GET,
        &routes::heights(v, TileId::new(5, 0)),
        404,
    )
    .await;
    assert!(
        message.contains("5/0") && message.contains("2x2"),
        "{message}"
    );
    let message = check_error(
        &client,
        &server,
        Method::GET,
        &routes::heights(v, TileId::at(1, 1, 0)),
        404,
    )
    .await;
    assert!(
        message.contains("L1:1/0") && message.contains("1x1"),
        "{message}"
    );
    // A level past the last names the levels there are, for heights and textures.
    for path in [
        routes::heights(v, TileId::at(past_the_last, 0, 0)),
        routes::texture(v, TileId::at(past_the_last, 0, 0), 0),
    ] {
        let message = check_error(&client, &server, Method::GET, &path, 404).await;
        assert!(
            message.contains(&format!("level {past_the_last} does not exist"))
                && message.contains(&format!("levels 0 to {}", past_the_last - 1)),
            "{path}: {message}"
        );
    }
    let message = check_error(
        &client,
        &server,
        Method::GET,
        &routes::texture(v, TileId::new(0, 0), levels),
        404,
    )
    .await;
    assert!(
        message.contains(&format!("0 to {}", levels - 1)),
        "{message}"
    );

    // A stale content version is a 404 that names the current one, for heights and textures
    // of every level, and for the single-level spelling (not redirected).
    for path in [
        routes::heights("0000000000000000", TileId::new(0, 0)),
        routes::texture("previous", TileId::new(0, 0), 0),
        routes::heights("0000000000000000", TileId::at(1, 0, 0)),
        "/v1/0000000000000000/tiles/0/0/heights".to_string(),
        "/v1/previous/tiles/0/0/texture/1".to_string(),
    ] {
        let message = check_error(&client, &server, Method::GET, &path, 404).await;
        assert!(
            message.contains(v.as_str()),
            "the 404 of a stale version names the current one: {message}"
        );
    }

    // Anything but GET and HEAD on a route: 405, also JSON.
    check_error(&client, &server, Method::POST, routes::MANIFEST, 405).await;
    check_error(
        &client,
        &server,
        Method::DELETE,
        &routes::heights(v, TileId::new(0, 0)),
        405,
    )
    .await;
}

#[tokio::test]
async fn the_manifest_is_gzipped_when_asked_and_heights_and_textures_never_are() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let client = reqwest::Client::new();
    let v = &db.manifest().content_version;
    let manifest = manifest_json(&db);
    // Compact JSON, a tile record one short array: under a kilobyte for five tiles, which
    // gzip still shrinks (checked below).
    assert!(
        manifest.len() > 512,
        "the synthetic manifest is large enough to be compressed"
    );

    let answer = fetch(
        &client,
        Method::GET,
        &server.url(routes::MANIFEST),
        &[("accept-encoding", "gzip")],
    )
    .await;
    assert_eq!(answer.status, 200);
    assert_eq!(answer.header("content-encoding"), "gzip");
    assert!(
        answer
            .header("vary")
            .to_ascii_lowercase()
            .contains("accept-encoding")
    );
    assert!(answer.body.len() < manifest.len());
    let mut unzipped = Vec::new();
    flate2::read::GzDecoder::new(answer.body.as_slice())
        .read_to_end(&mut unzipped)
        .expect("a valid gzip body");
    assert!(
        unzipped == manifest,
        "gunzipped manifest differs from the stored one"
    );
    // The gzip representation gets a weak tag, which still revalidates.
    let weak = format!("W/{}", quoted(&content_hash(&manifest)));
    assert_eq!(answer.header("etag"), weak);
    let answer = fetch(
        &client,
        Method::GET,
        &server.url(routes::MANIFEST),
        &[("accept-encoding", "gzip"), ("if-none-match", &weak)],
    )
    .await;
    assert_eq!(answer.status, 304);

    // Without Accept-Encoding: identity, strong tag.
    let answer = get(&client, &server.url(routes::MANIFEST)).await;
    assert_eq!(answer.header("content-encoding"), "");
    assert!(answer.body == manifest);

    let (id, above) = (TileId::new(0, 0), TileId::at(1, 0, 0));
    for (path, bytes) in [
        (routes::heights(v, id), db.heights(id)),
        (routes::texture(v, id, 0), db.texture(id, 0)),
        (routes::texture(v, id, 1), db.texture(id, 1)),
        (routes::heights(v, above), db.heights(above)),
        (routes::texture(v, above, 1), db.texture(above, 1)),
    ] {
        let answer = fetch(
            &client,
            Method::GET,
            &server.url(&path),
            &[("accept-encoding", "gzip, deflate, br, zstd")],
        )
        .await;
        assert_eq!(answer.status, 200, "{path}");
        assert_eq!(
            answer.header("content-encoding"),
            "",
            "{path} must not be recompressed"
        );
        assert!(answer.body == bytes, "{path}");
        assert_eq!(
            answer.header("etag"),
            quoted(&content_hash(bytes)),
            "{path}: strong tag kept"
        );
    }
}

#[tokio::test]
async fn cors_headers_let_any_origin_read_tiles_and_their_etag() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let client = reqwest::Client::new();
    let path = routes::heights(&db.manifest().content_version, TileId::new(0, 0));

    let answer = fetch(
        &client,
        Method::GET,
        &server.url(&path),
        &[("origin", "https://viewer.example")],
    )
    .await;
    assert_eq!(answer.status, 200);
    assert_eq!(answer.header("access-control-allow-origin"), "*");
    assert!(
        answer
            .header("access-control-expose-headers")
            .to_ascii_lowercase()
            .contains("etag")
    );

    // Errors carry CORS headers too, so a browser client can read why.
    let answer = fetch(
        &client,
        Method::GET,
        &server.url("/nope"),
        &[("origin", "https://viewer.example")],
    )
    .await;
    assert_eq!(answer.status, 404);
    assert_eq!(answer.header("access-control-allow-origin"), "*");

    let preflight = fetch(
        &client,
        Method::OPTIONS,
        &server.url(&path),
        &[
            ("origin", "https://viewer.example"),
            ("access-control-request-method", "GET"),
            ("access-control-request-headers", "if-none-match"),
        ],
    )
    .await;
    assert_eq!(preflight.status, 200);
    assert_eq!(preflight.header("access-control-allow-origin"), "*");
    assert!(
        preflight
            .header("access-control-allow-methods")
            .contains("GET")
    );
    assert!(
        preflight
            .header("access-control-allow-headers")
            .to_ascii_lowercase()
            .contains("if-none-match")
    );
}

#[tokio::test]
async fn healthz_answers_ok() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let answer = get(&reqwest::Client::new(), &server.url(routes::HEALTHZ)).await;
    assert_eq!(answer.status, 200);
    assert_eq!(answer.body, b"ok\n");
}

/// The value of the sample `name{labels}` in a metrics text, 0 if absent.
fn sample(text: &str, name: &str, labels: &str) -> f64 {
    let prefix = format!("{name}{{{labels}}} ");
    text.lines()
        .find_map(|line| line.strip_prefix(&prefix))
        .map(|value| {
            value
                .trim()
                .parse()
                .unwrap_or_else(|_| panic!("bad value in {name}{{{labels}}}: {value}"))
        })
        .unwrap_or(0.0)
}

#[tokio::test]
async fn metrics_count_requests_and_bytes_by_route_template_and_status_and_time_them() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let client = reqwest::Client::new();
    let v = &db.manifest().content_version;

    let mut heights_bytes = 0;
    for id in db.all_tile_ids() {
        assert_eq!(
            get(&client, &server.url(&routes::heights(v, id)))
                .await
                .status,
            200
        );
        heights_bytes += db.heights(id).len();
    }
    assert_eq!(
        get(
            &client,
            &server.url(&routes::texture(v, TileId::new(0, 0), 1))
        )
        .await
        .status,
        200
    );
    assert_eq!(
        get(&client, &server.url(&routes::heights(v, TileId::new(9, 9))))
            .await
            .status,
        404
    );
    assert_eq!(
        get(
            &client,
            &server.url(&format!("/v1/{v}/levels/0/tiles/a/0/heights"))
        )
        .await
        .status,
        400
    );
    // A single-level URL: its redirect is counted under its own template.
    let no_redirects = reqwest::Client::builder()
        .redirect(reqwest::redirect::Policy::none())
        .build()
        .expect("client");
    assert_eq!(
        get(
            &no_redirects,
            &server.url(&format!("/v1/{v}/tiles/0/0/heights"))
        )
        .await
        .status,
        308
    );
    assert_eq!(
        get(&client, &server.url("/no/such/route")).await.status,
        404
    );
    assert_eq!(
        get(&client, &server.url(routes::MANIFEST)).await.status,
        200
    );

    let answer = get(&client, &server.url(routes::METRICS)).await;
    assert_eq!(answer.status, 200);
    assert!(
        answer
            .header("content-type")
            .starts_with("application/openmetrics-text")
    );
    let text = String::from_utf8(answer.body).expect("metrics are text");

    let route = |route: &str, status: u16| format!("route=\"{route}\",status=\"{status}\"");
    let tiles = db.all_tile_ids().len() as f64;
    assert_eq!(tiles, 5.0);
    for (labels, count) in [
        (route(HEIGHTS_ROUTE, 200), tiles),
        (route(HEIGHTS_ROUTE, 404), 1.0),
        (route(HEIGHTS_ROUTE, 400), 1.0),
        (route(LEGACY_HEIGHTS_ROUTE, 308), 1.0),
        (route(TEXTURE_ROUTE, 200), 1.0),
        (route("unmatched", 404), 1.0),
        (route(routes::MANIFEST, 200), 1.0),
    ] {
        assert_eq!(
            sample(&text, "http_requests_total", &labels),
            count,
            "http_requests_total{{{labels}}}\n{text}"
        );
    }
    assert_eq!(
        sample(
            &text,
            "http_response_body_bytes_total",
            &route(HEIGHTS_ROUTE, 200)
        ),
        heights_bytes as f64,
        "{text}"
    );
    // Latency histogram: one observation per heights request whatever its status, and a
    // cumulative bucket count that reaches it.
    let heights_label = format!("route=\"{HEIGHTS_ROUTE}\"");
    assert_eq!(
        sample(&text, "http_request_duration_seconds_count", &heights_label),
        tiles + 2.0,
        "{text}"
    );
    assert!(sample(&text, "http_request_duration_seconds_sum", &heights_label) > 0.0);
    assert_eq!(
        sample(
            &text,
            "http_request_duration_seconds_bucket",
            &format!("le=\"+Inf\",{heights_label}")
        ),
        tiles + 2.0,
        "{text}"
    );
    assert!(text.contains("http_requests_in_flight"));
    // Labels are templates, never raw URLs: no content version, no coordinates.
    assert!(
        !text.contains(v.as_str()) && !text.contains("/tiles/0/"),
        "raw URLs leaked into labels:\n{text}"
    );
}

/// Writes a raw request for `path` and reads until the end of the response head; returns
/// the head and whatever body bytes came with it.
async fn send_raw_request(stream: &mut TcpStream, path: &str) -> (String, Vec<u8>) {
    let request = format!("GET {path} HTTP/1.1\r\nHost: test\r\n\r\n");
    stream
        .write_all(request.as_bytes())
        .await
        .expect("cannot send the request");
    let mut received = Vec::new();
    let mut chunk = [0u8; 1024];
    loop {
        let n = stream
            .read(&mut chunk)
            .await
            .expect("cannot read the response head");
        assert!(n > 0, "connection closed before the response head");
        received.extend_from_slice(&chunk[..n]);
        if let Some(end) = received.windows(4).position(|w| w == b"\r\n\r\n") {
            let head = String::from_utf8_lossy(&received[..end]).into_owned();
            return (head, received[end + 4..].to_vec());
        }
    }
}

#[tokio::test]
async fn graceful_shutdown_finishes_the_response_in_flight_then_refuses_connections() {
    // Far more than loopback socket buffers hold (a few MiB each way), so the server cannot
    // finish sending until the client reads: the response is truly in flight.
    const LARGE: usize = 48 << 20;
    let db =
        SyntheticDb::write_with_large_texture(LARGE).expect("cannot write the synthetic database");
    let deadline = Duration::from_secs(20);
    let mut server = TestServer::start_with(
        db.dir(),
        ServeOptions {
            shutdown_deadline: deadline,
            ..ServeOptions::default()
        },
    );
    let (id, level) = LARGE_TEXTURE;
    let path = routes::texture(&db.manifest().content_version, id, level);

    let mut stream = TcpStream::connect(server.addr())
        .await
        .expect("cannot connect");
    let (head, mut body) = send_raw_request(&mut stream, &path).await;
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    assert!(
        head.to_ascii_lowercase()
            .contains(&format!("content-length: {LARGE}")),
        "{head}"
    );

    let shutdown_started = Instant::now();
    server.begin_shutdown();

    // New connections are refused once the listener is closed...
    let refused_by = Instant::now() + Duration::from_secs(5);
    loop {
        match TcpStream::connect(server.addr()).await {
            Err(_) => break,
            Ok(_) => {
                assert!(
                    Instant::now() < refused_by,
                    "new connections still accepted 5 s after shutdown began"
                );
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }
    }
    // ...while the server still waits for the response in flight.
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert!(
        !server.is_stopped(),
        "serve returned with a response still in flight"
    );

    // The client reads the rest: every byte arrives, then the server closes the connection.
    let mut chunk = vec![0u8; 1 << 16];
    loop {
        let n = tokio::time::timeout(Duration::from_secs(10), stream.read(&mut chunk))
            .await
            .expect("the rest of the body arrives")
            .expect("reading the body");
        if n == 0 {
            break;
        }
        body.extend_from_slice(&chunk[..n]);
    }
    assert_eq!(
        body.len(),
        LARGE,
        "the whole body arrives before the connection closes"
    );
    assert!(body == db.texture(id, level), "the body is the stored blob");

    let wait_from = Instant::now();
    while !server.is_stopped() {
        assert!(
            wait_from.elapsed() < Duration::from_secs(5),
            "serve did not return after its last response"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert!(
        shutdown_started.elapsed() < deadline,
        "shutdown ended by itself, not by its deadline"
    );
    server.stop().expect("serve returns Ok");
}

#[tokio::test]
async fn a_client_trickling_its_headers_is_cut_off_by_the_header_read_timeout() {
    let db = synthetic();
    let timeout = Duration::from_millis(300);
    let server = TestServer::start_with(
        db.dir(),
        ServeOptions {
            header_read_timeout: timeout,
            ..ServeOptions::default()
        },
    );

    let stream = TcpStream::connect(server.addr())
        .await
        .expect("cannot connect");
    let (mut reader, mut writer) = stream.into_split();
    let started = Instant::now();
    // The reader notes when the server closes the connection (EOF or reset), and whether
    // it ever answered.
    let closed = tokio::spawn(async move {
        let mut received = Vec::new();
        let _ = reader.read_to_end(&mut received).await;
        (started.elapsed(), received)
    });
    // One byte every 100 ms: the full head would take about 5 s, far beyond the timeout.
    for byte in b"GET /healthz HTTP/1.1\r\nHost: test\r\nX-Slow: yes\r\n\r\n" {
        if writer.write_all(&[*byte]).await.is_err() || closed.is_finished() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let (closed_after, received) = tokio::time::timeout(Duration::from_secs(5), closed)
        .await
        .expect("the server closes a trickling connection")
        .expect("reader task");
    // The server's clock starts when it accepts, a little before `started` here (after
    // connect returned): allow that much.
    assert!(
        closed_after >= timeout - Duration::from_millis(50),
        "closed after {closed_after:?}, before the timeout"
    );
    // Well before the trickle would have finished: the timeout, not the end of the head,
    // closed it (with margin for a loaded CI machine).
    assert!(
        closed_after < Duration::from_secs(3),
        "closed after {closed_after:?}, long after the {timeout:?} timeout"
    );
    let answer = String::from_utf8_lossy(&received);
    assert!(
        !answer.contains("200 OK"),
        "the trickled request was answered: {answer}"
    );

    // A client that connects and sends nothing is closed too.
    let mut idle = TcpStream::connect(server.addr())
        .await
        .expect("cannot connect");
    let mut buffer = [0u8; 64];
    let result = tokio::time::timeout(Duration::from_secs(5), idle.read(&mut buffer)).await;
    assert!(
        matches!(result, Ok(Ok(0)) | Ok(Err(_))),
        "a silent connection is closed: {result:?}"
    );
}

#[tokio::test]
async fn requests_beyond_the_concurrency_limit_are_shed_with_503_not_queued() {
    let db = synthetic();
    let options = ServeOptions {
        max_concurrent_requests: 1,
        ..ServeOptions::default()
    };
    let server = TestServer::start_with(db.dir(), options);
    let client = reqwest::Client::new();
    let tile = server.url(&routes::heights(
        &db.manifest().content_version,
        TileId::new(0, 0),
    ));

    // The one permit is held by a request that sleeps inside the handler stack (the
    // `test-hooks` route: no tile request stays in its handler long enough to hold one). The
    // holder goes first, alone, so no probe races it for the permit; should it still be
    // shed itself (a probe of the previous attempt in flight on a loaded machine), it is
    // sent again, a bounded number of times.
    let mut shed = None;
    let mut holder = None;
    for _attempt in 0..5 {
        let task = {
            let (client, url) = (client.clone(), server.url("/__test/sleep/2000"));
            tokio::spawn(async move { get(&client, &url).await })
        };
        tokio::time::sleep(Duration::from_millis(200)).await;
        while !task.is_finished() {
            let answer = get(&client, &tile).await;
            if answer.status == 503 {
                shed = Some(answer);
                break;
            }
            assert_eq!(answer.status, 200);
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        holder = Some(task);
        if shed.is_some() {
            break;
        }
    }
    let holder = holder.expect("at least one attempt");
    let shed = shed.expect("no request was shed while the only permit was held");
    let (message, _) = shed.json_error();
    assert!(message.contains("limit"), "{message}");
    assert_eq!(shed.header("retry-after"), "1");

    // Health and metrics are outside the limit, so an overloaded server can be watched.
    if !holder.is_finished() {
        assert_eq!(get(&client, &server.url(routes::HEALTHZ)).await.status, 200);
    }
    let held = holder.await.expect("holder task");
    assert_eq!(
        (held.status, held.body.as_slice()),
        (200, b"slept\n".as_slice())
    );
    assert_eq!(
        get(&client, &tile).await.status,
        200,
        "the permit is released"
    );
    let metrics =
        String::from_utf8(get(&client, &server.url(routes::METRICS)).await.body).expect("text");
    assert!(
        sample(
            &metrics,
            "http_requests_total",
            &format!("route=\"{HEIGHTS_ROUTE}\",status=\"503\"")
        ) >= 1.0
    );
}

#[tokio::test]
async fn a_request_slower_than_the_request_timeout_gets_503() {
    let db = synthetic();
    let timeout = Duration::from_millis(200);
    let server = TestServer::start_with(
        db.dir(),
        ServeOptions {
            request_timeout: timeout,
            ..ServeOptions::default()
        },
    );
    let started = Instant::now();
    let answer = get(&reqwest::Client::new(), &server.url("/__test/sleep/10000")).await;
    assert_eq!(answer.status, 503);
    let (message, _) = answer.json_error();
    assert!(message.contains("longer than"), "{message}");
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "answered after {:?}",
        started.elapsed()
    );
}

/// A raw request line (any form of request target) on a fresh connection; returns the
/// response head. The answer is read while the request is written: a server refusing an
/// oversized head answers and closes before the whole request is sent.
async fn raw_head(server: &TestServer, request: &str) -> String {
    let stream = TcpStream::connect(server.addr())
        .await
        .expect("cannot connect");
    let (mut reader, mut writer) = stream.into_split();
    let read = tokio::spawn(async move {
        let mut received = Vec::new();
        let mut chunk = [0u8; 4096];
        loop {
            match tokio::time::timeout(Duration::from_secs(5), reader.read(&mut chunk)).await {
                Ok(Ok(n)) if n > 0 => received.extend_from_slice(&chunk[..n]),
                _ => break,
            }
            if received.windows(4).any(|w| w == b"\r\n\r\n") {
                break;
            }
        }
        received
    });
    // The server may close before all of an oversized request is written.
    let _ = writer.write_all(request.as_bytes()).await;
    let received = read.await.expect("reader task");
    let text = String::from_utf8_lossy(&received).into_owned();
    text.split("\r\n\r\n").next().unwrap_or("").to_string()
}

#[tokio::test]
async fn a_tile_url_has_one_spelling_no_query_string_and_no_percent_encoding() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let client = reqwest::Client::new();
    let v = &db.manifest().content_version;
    let heights = routes::heights(v, TileId::new(1, 0));
    let texture = routes::texture(v, TileId::new(1, 0), 0);
    assert_eq!(get(&client, &server.url(&heights)).await.status, 200);
    assert_eq!(get(&client, &server.url(&texture)).await.status, 200);
    let legacy = format!("/v1/{v}/tiles/1/0/heights");
    for respelled in [
        format!("{heights}?v=2"),
        format!("{heights}?"),
        format!("{texture}?cache-buster=1"),
        heights.replace("/tiles/1/", "/tiles/%31/"),
        heights.replace("/levels/0/", "/levels/%30/"),
        texture.replace("/texture/0", "/texture/%30"),
        // The single-level spelling is held to one spelling too before it is redirected.
        format!("{legacy}?v=2"),
        legacy.replace("/tiles/1/", "/tiles/%31/"),
    ] {
        let answer = get(&client, &server.url(&respelled)).await;
        assert_eq!(answer.status, 400, "{respelled} was served");
        let (message, _) = answer.json_error();
        assert!(message.contains("one spelling"), "{respelled}: {message}");
    }
    // Routing matches the path as sent, so a respelled fixed segment matches no route.
    let answer = get(
        &client,
        &server.url(&heights.replace("/heights", "/h%65ights")),
    )
    .await;
    assert_eq!(answer.status, 404);
    // The absolute form of the same request target is the same URL (RFC 9112 section
    // 3.2.2: a server must accept it, and the target URI, which caches key on, is the one
    // the origin form names), so it is answered, with the same entity tag.
    let origin = raw_head(
        &server,
        &format!("GET {heights} HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n"),
    )
    .await;
    let absolute = raw_head(
        &server,
        &format!(
            "GET http://{}{heights} HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n",
            server.addr()
        ),
    )
    .await;
    assert!(absolute.starts_with("HTTP/1.1 200"), "{absolute}");
    let etag = |head: &str| {
        head.lines()
            .find(|l| l.to_ascii_lowercase().starts_with("etag:"))
            .map(str::to_string)
    };
    assert_eq!(etag(&absolute), etag(&origin));
    assert!(etag(&origin).is_some(), "{origin}");
}

#[tokio::test]
async fn a_single_level_tile_url_is_redirected_permanently_to_its_level_0_spelling() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let v = &db.manifest().content_version;
    let no_redirects = reqwest::Client::builder()
        .redirect(reqwest::redirect::Policy::none())
        .build()
        .expect("client");
    let following = reqwest::Client::new();
    let levels = db.manifest().texture.levels;
    let mut redirects = 0;
    for id in db.tile_ids() {
        let mut pairs = vec![(
            format!("/v1/{v}/tiles/{}/{}/heights", id.x, id.y),
            routes::heights(v, id),
            db.heights(id),
        )];
        for level in 0..levels {
            pairs.push((
                format!("/v1/{v}/tiles/{}/{}/texture/{level}", id.x, id.y),
                routes::texture(v, id, level),
                db.texture(id, level),
            ));
        }
        for (legacy, target, bytes) in pairs {
            for method in [Method::GET, Method::HEAD] {
                let answer = fetch(
                    &no_redirects,
                    method.clone(),
                    &server.url(&legacy),
                    &[("origin", "https://viewer.example")],
                )
                .await;
                // 308, not 301: the method is kept (RFC 9110 section 15.4.9).
                assert_eq!(answer.status, 308, "{method} {legacy}");
                assert_eq!(answer.header("location"), target, "{method} {legacy}");
                // As cacheable as the tile: the content version in the URL pins both.
                assert_eq!(
                    answer.header("cache-control"),
                    TILE_CACHE_CONTROL,
                    "{method} {legacy}"
                );
                assert_eq!(
                    answer.header("access-control-allow-origin"),
                    "*",
                    "{method} {legacy}: a browser may follow it"
                );
                redirects += 1;
            }
            // A client that follows redirects gets the tile's bytes.
            let followed = get(&following, &server.url(&legacy)).await;
            assert_eq!(followed.status, 200, "{legacy}");
            assert!(followed.body == bytes, "{legacy}: body after the redirect");
            assert_eq!(
                followed.header("etag"),
                quoted(&content_hash(bytes)),
                "{legacy}"
            );
        }
    }
    // 4 tiles x (heights + 2 levels) x (GET, HEAD): refuse to pass on an empty grid.
    assert_eq!(redirects, 24);
}

#[tokio::test]
async fn the_gzipped_manifest_is_the_one_compressed_at_open() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let client = reqwest::Client::new();
    let stored = server.state().db().manifest_gzip().clone();
    for _ in 0..3 {
        let answer = fetch(
            &client,
            Method::GET,
            &server.url(routes::MANIFEST),
            &[("accept-encoding", "gzip")],
        )
        .await;
        assert_eq!(answer.header("content-encoding"), "gzip");
        // Compressed per request, a body would be streamed (chunked, no length); the stored
        // bytes go out whole, with their length.
        assert_eq!(answer.header("content-length"), stored.len().to_string());
        assert!(answer.body == stored, "the body is the stored gzip");
    }
    let refused = fetch(
        &client,
        Method::GET,
        &server.url(routes::MANIFEST),
        &[("accept-encoding", "gzip;q=0, *")],
    )
    .await;
    assert_eq!(refused.header("content-encoding"), "");
    assert_eq!(refused.header("vary"), "accept-encoding");
}

#[tokio::test]
async fn a_client_that_never_reads_is_cut_off_by_the_write_timeout() {
    const LARGE: usize = 48 << 20;
    let db =
        SyntheticDb::write_with_large_texture(LARGE).expect("cannot write the synthetic database");
    let timeout = Duration::from_millis(500);
    let server = TestServer::start_with(
        db.dir(),
        ServeOptions {
            write_timeout: timeout,
            ..ServeOptions::default()
        },
    );
    let (id, level) = LARGE_TEXTURE;
    let path = routes::texture(&db.manifest().content_version, id, level);
    let mut stream = TcpStream::connect(server.addr())
        .await
        .expect("cannot connect");
    let (head, mut body) = send_raw_request(&mut stream, &path).await;
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    // The client stops reading; well past the timeout, it reads what was sent: the socket
    // buffers' worth, then the end of a connection the server gave up on.
    tokio::time::sleep(timeout * 6).await;
    let mut chunk = vec![0u8; 1 << 16];
    let ended = tokio::time::timeout(Duration::from_secs(10), async {
        loop {
            match stream.read(&mut chunk).await {
                Ok(0) | Err(_) => break,
                Ok(n) => body.extend_from_slice(&chunk[..n]),
            }
        }
    })
    .await;
    assert!(ended.is_ok(), "the connection stayed open");
    assert!(
        body.len() < LARGE,
        "the whole body arrived ({} bytes): nothing was cut off",
        body.len()
    );
    let client = reqwest::Client::new();
    let metrics =
        String::from_utf8(get(&client, &server.url(routes::METRICS)).await.body).expect("text");
    assert_eq!(
        sample(
            &metrics,
            "http_connections_closed_by_server_total",
            "reason=\"write_timeout\""
        ),
        1.0,
        "{metrics}"
    );
}

#[tokio::test]
async fn when_every_slot_is_taken_the_oldest_idle_connection_makes_room() {
    let db = synthetic();
    let slots = 32;
    let server = TestServer::start_with(
        db.dir(),
        ServeOptions {
            max_connections: slots,
            ..ServeOptions::default()
        },
    );
    // Every slot held by a connection that sends nothing (the default idle timeout, 10 s,
    // would keep each for that long).
    let mut idle = Vec::new();
    for _ in 0..slots + 8 {
        idle.push(
            TcpStream::connect(server.addr())
                .await
                .expect("cannot connect"),
        );
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    let client = reqwest::Client::new();
    let started = Instant::now();
    let answer = tokio::time::timeout(
        Duration::from_secs(5),
        get(&client, &server.url(routes::HEALTHZ)),
    )
    .await
    .expect("a new client is served while idle connections hold every slot");
    assert_eq!(answer.status, 200);
    assert!(
        started.elapsed() < Duration::from_secs(2),
        "served after {:?}",
        started.elapsed()
    );
    let metrics =
        String::from_utf8(get(&client, &server.url(routes::METRICS)).await.body).expect("text");
    assert!(
        sample(
            &metrics,
            "http_connections_closed_by_server_total",
            "reason=\"evicted\""
        ) >= 8.0,
        "{metrics}"
    );
    drop(idle);
}

#[tokio::test]
async fn http2_with_prior_knowledge_is_served() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let client = reqwest::Client::builder()
        .http2_prior_knowledge()
        .build()
        .expect("client");
    let v = &db.manifest().content_version;
    let id = TileId::new(0, 0);
    let response = client
        .get(server.url(&routes::heights(v, id)))
        .send()
        .await
        .expect("an h2c request is answered");
    assert_eq!(response.version(), reqwest::Version::HTTP_2);
    assert_eq!(response.status(), 200);
    let body = response.bytes().await.expect("body");
    assert!(body.as_ref() == db.heights(id));
}

#[tokio::test]
async fn heads_too_large_for_the_server_are_answered_and_counted() {
    let db = synthetic();
    let server = TestServer::start(db.dir());
    let long_uri = format!("/{}", "a".repeat(70_000));
    let head = raw_head(
        &server,
        &format!("GET {long_uri} HTTP/1.1\r\nHost: test\r\n\r\n"),
    )
    .await;
    assert!(head.starts_with("HTTP/1.1 414"), "{head}");
    let head = raw_head(
        &server,
        &format!(
            "GET /healthz HTTP/1.1\r\nHost: test\r\nX-Big: {}\r\n\r\n",
            // Well past hyper's 400 kB buffer: a head just past it can still be parsed
            // whole when one read brings more than the limit.
            "b".repeat(4_000_000)
        ),
    )
    .await;
    assert!(head.starts_with("HTTP/1.1 431"), "{head}");
    let client = reqwest::Client::new();
    let metrics =
        String::from_utf8(get(&client, &server.url(routes::METRICS)).await.body).expect("text");
    for status in [414, 431] {
        assert_eq!(
            sample(
                &metrics,
                "http_requests_total",
                &format!("route=\"unmatched\",status=\"{status}\"")
            ),
            1.0,
            "{status}: {metrics}"
        );
    }
}
