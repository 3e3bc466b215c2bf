//! The web tiles (`terrain_server::web`) through a real server and client: the heights
//! MapLibre and Cesium would read are checked against the source raster, read here
//! independently of the builder, and against the errors the server states; the routes'
//! spellings, caching and errors; the PMTiles export; an input without a georeference.

use std::io::Read;
use std::path::Path;
use terrain_server::web::quantized_mesh::{self, GeoRect};
use terrain_tests::data::{jacksboro, png_codes, run_binary};
use terrain_tests::server::TestServer;

/// Jacksboro's dataset.json: the north-west sample's centre and the step, degrees.
const JACKSBORO_ORIGIN: (f64, f64) = (-84.41375, 36.73292);
const JACKSBORO_STEP: f64 = 0.000_833_333_333_333_333_4;

struct Answer {
    status: u16,
    headers: reqwest::header::HeaderMap,
    body: Vec<u8>,
}

async fn get(url: &str) -> Answer {
    let response = reqwest::Client::new()
        .get(url)
        .send()
        .await
        .unwrap_or_else(|e| panic!("GET {url}: {e}"));
    let status = response.status().as_u16();
    let headers = response.headers().clone();
    let body = response.bytes().await.expect("body").to_vec();
    Answer {
        status,
        headers,
        body,
    }
}

async fn json(url: &str) -> serde_json::Value {
    let a = get(url).await;
    assert_eq!(a.status, 200, "{url}: {}", String::from_utf8_lossy(&a.body));
    serde_json::from_slice(&a.body).expect("JSON")
}

fn build(input: &Path, out: &Path, flags: &[&str]) -> String {
    let mut args: Vec<&std::ffi::OsStr> = vec!["build".as_ref(), "--quiet".as_ref()];
    args.push(input.as_os_str());
    args.push("--out".as_ref());
    args.push(out.as_os_str());
    args.extend(flags.iter().map(std::ffi::OsStr::new));
    let (ok, stdout, stderr) = run_binary("terrain-server", &args);
    assert!(ok, "build {}: {stderr}", input.display());
    stdout
}

/// Bilinear value of a row-major raster at fractional sample `(c, r)`.
fn bilinear(w: u32, h: u32, at: impl Fn(u32, u32) -> f64, c: f64, r: f64) -> f64 {
    let (c0, r0) = (c.floor() as u32, r.floor() as u32);
    let (c1, r1) = ((c0 + 1).min(w - 1), (r0 + 1).min(h - 1));
    let (fc, fr) = (c - f64::from(c0), r - f64::from(r0));
    let top = at(c0, r0) * (1.0 - fc) + at(c1, r0) * fc;
    let bottom = at(c0, r1) * (1.0 - fc) + at(c1, r1) * fc;
    top * (1.0 - fr) + bottom * fr
}

fn terrarium_value(p: &[u8]) -> f64 {
    f64::from(p[0]) * 256.0 + f64::from(p[1]) + f64::from(p[2]) / 256.0 - 32768.0
}

fn mapbox_value(p: &[u8]) -> f64 {
    -10000.0 + (f64::from(p[0]) * 65536.0 + f64::from(p[1]) * 256.0 + f64::from(p[2])) * 0.1
}

/// Web Mercator pixel centre to longitude and latitude (written here again, not taken from
/// the server).
fn pixel_lon_lat(z: u32, x: u32, y: u32, i: u32, j: u32) -> (f64, f64) {
    let world = 256.0 * f64::from(1u32 << z);
    let px = f64::from(x * 256 + i) + 0.5;
    let py = f64::from(y * 256 + j) + 0.5;
    let lon = px / world * 360.0 - 180.0;
    let lat = (std::f64::consts::PI * (1.0 - 2.0 * py / world))
        .sinh()
        .atan()
        .to_degrees();
    (lon, lat)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jacksboro_terrarium_and_terrain_rgb_tiles_hold_the_source_heights() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = tmp.path().join("db");
    let summary = build(&jacksboro(), &db, &[]);
    assert!(summary.contains("web "), "{summary}");
    let server = TestServer::start(&db);
    let base = server.base_url();
    let tilejson = json(&format!("{base}/v1/terrarium.json")).await;
    assert_eq!(tilejson["encoding"], "terrarium");
    let template = tilejson["tiles"][0].as_str().expect("tile URL").to_string();
    assert!(
        template.starts_with(&format!("{base}/v1/")),
        "absolute: {template}"
    );
    let max_zoom = tilejson["maxzoom"].as_u64().expect("maxzoom") as u32;
    // 74 m samples at 36.6 N: zoom 10's pixels are 122 m, zoom 11's 61 m.
    assert_eq!(max_zoom, 10);
    let bounds: Vec<f64> = tilejson["bounds"]
        .as_array()
        .expect("bounds")
        .iter()
        .map(|v| v.as_f64().expect("number"))
        .collect();
    let (w, h, codes) = png_codes(&jacksboro());
    let expected_bounds = [
        JACKSBORO_ORIGIN.0,
        JACKSBORO_ORIGIN.1 - f64::from(h - 1) * JACKSBORO_STEP,
        JACKSBORO_ORIGIN.0 + f64::from(w - 1) * JACKSBORO_STEP,
        JACKSBORO_ORIGIN.1,
    ];
    for (got, want) in bounds.iter().zip(expected_bounds) {
        assert!(
            (got - want).abs() < 1e-9,
            "bounds {bounds:?}, expected {expected_bounds:?}"
        );
    }
    let rgb_template = json(&format!("{base}/v1/terrain-rgb.json")).await["tiles"][0]
        .as_str()
        .expect("tile URL")
        .to_string();
    let source = |c: u32, r: u32| f64::from(codes[(r * w + c) as usize]);
    // At the finest zoom the tiles are resampled from level 0, so a pixel holds the
    // source's bilinear value at its centre within the encoding's quantum.
    let (mut checked, mut outside, mut worst, mut worst_rgb) = (0, 0, 0.0f64, 0.0f64);
    let mut worst_off = 0.0f64;
    let z = max_zoom;
    let tile = |lon: f64, lat: f64| {
        let n = f64::from(1u32 << z);
        let x = ((lon + 180.0) / 360.0 * n).floor() as u32;
        let lat = lat.to_radians();
        let y = ((1.0 - (lat.tan() + 1.0 / lat.cos()).ln() / std::f64::consts::PI) / 2.0 * n)
            .floor() as u32;
        (x, y)
    };
    let (x0, y0) = tile(bounds[0], bounds[3]);
    let (x1, y1) = tile(bounds[2], bounds[1]);
    for y in y0..=y1 {
        for x in x0..=x1 {
            let url = |t: &str| {
                t.replace("{z}", &z.to_string())
                    .replace("{x}", &x.to_string())
                    .replace("{y}", &y.to_string())
            };
            let answer = get(&url(&template)).await;
            assert_eq!(answer.status, 200, "{}", url(&template));
            assert_eq!(answer.headers["content-type"], "image/png");
            assert_eq!(
                answer.headers["cache-control"],
                "public, max-age=31536000, immutable"
            );
            let terr = image::load_from_memory(&answer.body)
                .expect("PNG")
                .to_rgb8();
            let rgb = image::load_from_memory(&get(&url(&rgb_template)).await.body)
                .expect("PNG")
                .to_rgb8();
            for j in 0..256 {
                for i in 0..256 {
                    let (lon, lat) = pixel_lon_lat(z, x, y, i, j);
                    let c = (lon - JACKSBORO_ORIGIN.0) / JACKSBORO_STEP;
                    let r = (JACKSBORO_ORIGIN.1 - lat) / JACKSBORO_STEP;
                    let got = terrarium_value(&terr.get_pixel(i, j).0);
                    let got_rgb = mapbox_value(&rgb.get_pixel(i, j).0);
                    let inside =
                        c >= 0.0 && r >= 0.0 && c <= f64::from(w - 1) && r <= f64::from(h - 1);
                    // Pixels within a hair of the border may fall either way.
                    let near = c >= -1e-3
                        && r >= -1e-3
                        && c <= f64::from(w - 1) + 1e-3
                        && r <= f64::from(h - 1) + 1e-3;
                    if inside {
                        let want = bilinear(w, h, source, c, r);
                        worst = worst.max((got - want).abs());
                        worst_rgb = worst_rgb.max((got_rgb - want).abs());
                        checked += 1;
                    } else if !near {
                        // Off the terrain: the height of the nearest point of its edge, so
                        // the surface ends level with the DEM rather than falling to 0 m.
                        let edge = bilinear(
                            w,
                            h,
                            source,
                            c.clamp(0.0, f64::from(w - 1)),
                            r.clamp(0.0, f64::from(h - 1)),
                        );
                        worst_off = worst_off.max((got - edge).abs());
                        outside += 1;
                    }
                }
            }
        }
    }
    println!(
        "zoom {z}: {checked} pixels on the terrain, {outside} off it; worst |Terrarium - source| {worst:.4} m, |Terrain-RGB - source| {worst_rgb:.4} m, off it |Terrarium - nearest edge| {worst_off:.4} m"
    );
    assert!(checked > 20_000 && outside > 1000, "{checked} {outside}");
    // Half a quantum, and the f32 the tiles' heights are decoded in.
    assert!(worst <= 0.5 / 256.0 + 1e-3, "Terrarium off by {worst} m");
    assert!(worst_rgb <= 0.05 + 1e-3, "Terrain-RGB off by {worst_rgb} m");
    assert!(
        worst_off <= 0.5 / 256.0 + 1e-3,
        "off the terrain, Terrarium is {worst_off} m from the nearest edge's height"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jacksboro_quantized_mesh_tiles_stay_within_the_error_layer_json_states() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = tmp.path().join("db");
    build(&jacksboro(), &db, &[]);
    let server = TestServer::start(&db);
    let base = server.base_url();
    let layer = json(&format!("{base}/v1/cesium/layer.json")).await;
    assert_eq!(layer["format"], "quantized-mesh-1.0");
    assert_eq!(layer["scheme"], "tms");
    assert_eq!(layer["extensions"][0], "octvertexnormals");
    let template = layer["tiles"][0].as_str().expect("template").to_string();
    let max_level = layer["maxzoom"].as_u64().expect("maxzoom") as u32;
    let errors: Vec<f64> = layer["max_error_m"]
        .as_array()
        .expect("max_error_m")
        .iter()
        .map(|v| v.as_f64().expect("number"))
        .collect();
    let available = layer["available"].as_array().expect("available");
    assert_eq!(available.len() as u32, max_level + 1);
    let (w, h, codes) = png_codes(&jacksboro());
    let mut report = Vec::new();
    for level in [max_level, max_level - 1, max_level - 3] {
        let range = &available[level as usize][0];
        let n = |k: &str| range[k].as_u64().expect("range") as u32;
        let (mut worst, mut samples) = (0.0f64, 0u64);
        for y in n("startY")..=n("endY") {
            for x in n("startX")..=n("endX") {
                let url = format!(
                    "{base}{}",
                    template
                        .replace("{z}", &level.to_string())
                        .replace("{x}", &x.to_string())
                        .replace("{y}", &y.to_string())
                );
                let answer = get(&url).await;
                assert_eq!(answer.status, 200, "{url}");
                assert_eq!(answer.headers["content-encoding"], "gzip");
                assert_eq!(
                    answer.headers["content-type"],
                    "application/vnd.quantized-mesh"
                );
                let mut bytes = Vec::new();
                flate2::read::GzDecoder::new(&answer.body[..])
                    .read_to_end(&mut bytes)
                    .expect("gzip");
                let tile = quantized_mesh::decode(&bytes).expect("a quantized-mesh tile");
                assert_eq!(tile.normals.as_ref().map(Vec::len), Some(tile.mesh.u.len()));
                let d = 180.0 / f64::from(1u32 << level);
                let rect = GeoRect {
                    west: -180.0 + f64::from(x) * d,
                    south: -90.0 + f64::from(y) * d,
                    east: -180.0 + f64::from(x + 1) * d,
                    north: -90.0 + f64::from(y + 1) * d,
                };
                // Every source sample inside the tile, against the mesh there.
                for r in 0..h {
                    for c in 0..w {
                        let lon = JACKSBORO_ORIGIN.0 + f64::from(c) * JACKSBORO_STEP;
                        let lat = JACKSBORO_ORIGIN.1 - f64::from(r) * JACKSBORO_STEP;
                        if lon <= rect.west
                            || lon >= rect.east
                            || lat <= rect.south
                            || lat >= rect.north
                        {
                            continue;
                        }
                        let got =
                            quantized_mesh::height_at(&tile, &rect, lon, lat).expect("inside");
                        worst = worst.max((got - f64::from(codes[(r * w + c) as usize])).abs());
                        samples += 1;
                    }
                }
            }
        }
        report.push(format!(
            "level {level}: {samples} samples, worst {worst:.2} m, stated {:.2} m",
            errors[level as usize]
        ));
        assert!(samples > 0, "level {level} covers no sample");
        // The stated error is measured at the samples; dequantized u, v and heights move
        // the surface by a hair more.
        assert!(
            worst <= errors[level as usize] * 1.01 + 0.05,
            "level {level}: {worst} m from the source, layer.json states {} m",
            errors[level as usize]
        );
    }
    println!("{}", report.join("\n"));
    // Cesium asks for both level-0 tiles whatever the terrain covers.
    for x in 0..2 {
        let url = format!(
            "{base}{}",
            template
                .replace("{z}", "0")
                .replace("{x}", &x.to_string())
                .replace("{y}", "0")
        );
        assert_eq!(get(&url).await.status, 200, "{url}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn web_tile_urls_have_one_spelling_and_clear_errors() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = tmp.path().join("db");
    build(&jacksboro(), &db, &[]);
    let server = TestServer::start(&db);
    let base = server.base_url();
    let tilejson = json(&format!("{base}/v1/terrarium.json")).await;
    let template = tilejson["tiles"][0].as_str().expect("URL").to_string();
    let good = template
        .replace("{z}", "9")
        .replace("{x}", "135")
        .replace("{y}", "199");
    let answer = get(&good).await;
    assert_eq!(answer.status, 200, "{good}");
    let etag = answer.headers["etag"].clone();
    assert_eq!(answer.headers["access-control-allow-origin"], "*");
    let not_modified = reqwest::Client::new()
        .get(&good)
        .header("if-none-match", etag)
        .send()
        .await
        .expect("GET");
    assert_eq!(not_modified.status().as_u16(), 304);
    for (bad, status, says) in [
        (format!("{good}?v=1"), 400, "no query"),
        (good.replace("199.png", "199.PNG"), 400, "suffix"),
        (good.replace("/135/", "/0135/"), 400, "leading zeros"),
        (good.replace("199.png", "199.jpg"), 400, "suffix"),
        (good.replace("/9/135/199", "/9/1/1"), 404, "does not reach"),
        (good.replace("/9/135/199", "/14/1/1"), 404, "finest zoom 10"),
    ] {
        let a = get(&bad).await;
        let body = String::from_utf8_lossy(&a.body);
        assert_eq!(a.status, status, "{bad}: {body}");
        assert!(body.contains(says), "{bad}: {body}");
    }
    // `/` says where the routes are.
    let root = get(&format!("{base}/")).await;
    assert_eq!(root.status, 200);
    assert!(String::from_utf8_lossy(&root.body).contains("/v1/terrarium.json"));
    let cv = tilejson["version"].as_str().expect("version");
    let stale = good.replace(cv, "0123456789abcdef");
    assert_eq!(get(&stale).await.status, 404);
    // A Host header that is not a host is refused rather than echoed into URLs.
    let a = reqwest::Client::new()
        .get(format!("{base}/v1/terrarium.json"))
        .header("host", "evil.example/<script>")
        .send()
        .await
        .expect("GET");
    assert_eq!(a.status().as_u16(), 400);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_input_without_a_georeference_builds_without_web_tiles_and_says_why() {
    let tmp = tempfile::tempdir().expect("tempdir");
    // The DEM alone, without its dataset.json: nothing says where it lies.
    let png = tmp.path().join("dem.png");
    std::fs::copy(jacksboro(), &png).expect("copy");
    let db = tmp.path().join("db");
    let summary = build(&png, &db, &["--spacing", "30"]);
    assert!(summary.contains("no web tiles"), "{summary}");
    assert!(!db.join("web.pack").exists());
    let server = TestServer::start(&db);
    let base = server.base_url();
    for route in [
        "/v1/terrarium.json",
        "/v1/texture.json",
        "/v1/cesium/layer.json",
    ] {
        let a = get(&format!("{base}{route}")).await;
        assert_eq!(a.status, 404, "{route}");
        assert!(
            String::from_utf8_lossy(&a.body).contains("not georeferenced"),
            "{route}: {}",
            String::from_utf8_lossy(&a.body)
        );
    }
    assert_eq!(get(&format!("{base}/v1/manifest.json")).await.status, 200);
    let (ok, _, stderr) = run_binary(
        "terrain-server",
        &[
            "export".as_ref(),
            db.as_os_str(),
            "--pmtiles".as_ref(),
            tmp.path().join("x.pmtiles").as_os_str(),
        ],
    );
    assert!(!ok && stderr.contains("no web tiles"), "{stderr}");
    assert!(!tmp.path().join("x.pmtiles").exists());
}

#[test]
fn the_pmtiles_export_holds_every_terrarium_tile_and_replaces_nothing_unasked() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = tmp.path().join("db");
    build(&jacksboro(), &db, &[]);
    let out = tmp.path().join("jacksboro.pmtiles");
    let export = |force: bool| {
        let mut args: Vec<&std::ffi::OsStr> = vec![
            "export".as_ref(),
            db.as_os_str(),
            "--pmtiles".as_ref(),
            out.as_os_str(),
        ];
        if force {
            args.push("--force".as_ref());
        }
        run_binary("terrain-server", &args)
    };
    let (ok, stdout, stderr) = export(false);
    assert!(ok, "{stderr}");
    assert!(stdout.contains("26 tiles"), "{stdout}");
    // Made as any new file is (0644 under a umask of 0022), not a temporary file's 0600:
    // a web server running as another user reads it.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let probe = tmp.path().join("probe");
        std::fs::write(&probe, b"").expect("probe");
        let mode = |p: &Path| std::fs::metadata(p).expect("meta").permissions().mode() & 0o777;
        assert_eq!(mode(&out), mode(&probe), "the archive's mode");
        assert_ne!(mode(&out) & 0o044, 0, "others can read it under this umask");
    }
    let bytes = std::fs::read(&out).expect("archive");
    // PMTiles v3 header: magic, version, then little-endian offsets and counts.
    assert_eq!(&bytes[..7], b"PMTiles");
    assert_eq!(bytes[7], 3);
    let u64_at = |at: usize| u64::from_le_bytes(bytes[at..at + 8].try_into().expect("8 bytes"));
    assert_eq!(u64_at(72), 26, "addressed tiles");
    assert_eq!(bytes[99], 2, "tile type png");
    assert_eq!((bytes[100], bytes[101]), (0, 10), "zooms");
    let data = (u64_at(56), u64_at(64));
    assert_eq!(
        data.0 + data.1,
        bytes.len() as u64,
        "tile data ends the file"
    );
    let (ok, _, stderr) = export(false);
    assert!(!ok && stderr.contains("--force"), "{stderr}");
    assert!(export(true).0);
    // Nothing half-written is left beside it.
    let left: Vec<_> = std::fs::read_dir(tmp.path())
        .expect("dir")
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains(".part"))
        .collect();
    assert!(left.is_empty(), "{left:?}");
}

/// A GeoTIFF in UTM zone 10N (EPSG:32610): 30 m samples near Mt Rainier whose heights are
/// a plane in easting and northing, so any misplacement shows as a height error.
fn utm_plane_geotiff(dir: &Path) -> (std::path::PathBuf, [f64; 2]) {
    use tiff::encoder::{TiffEncoder, colortype};
    use tiff::tags::Tag;
    let (w, h) = (240u32, 180u32);
    let origin = [590_000.0, 5_195_000.0];
    let plane = |e: f64, n: f64| 1000.0 + 0.02 * (e - origin[0]) - 0.01 * (n - origin[1]);
    let samples: Vec<i16> = (0..w * h)
        .map(|i| {
            let (c, r) = (f64::from(i % w), f64::from(i / w));
            plane(origin[0] + 30.0 * c, origin[1] - 30.0 * r).round() as i16
        })
        .collect();
    let path = dir.join("utm.tif");
    let file = std::fs::File::create(&path).expect("create");
    let mut tiff = TiffEncoder::new(file).expect("encoder");
    let mut image = tiff.new_image::<colortype::GrayI16>(w, h).expect("image");
    let enc = image.encoder();
    enc.write_tag(Tag::Unknown(33550), &[30.0f64, 30.0, 0.0][..])
        .expect("scale");
    // PixelIsPoint: the tie point is sample (0, 0)'s centre.
    enc.write_tag(
        Tag::Unknown(33922),
        &[0.0f64, 0.0, 0.0, origin[0], origin[1], 0.0][..],
    )
    .expect("tie point");
    let keys: [u16; 16] = [1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 2, 3072, 0, 1, 32610];
    enc.write_tag(Tag::Unknown(34735), &keys[..])
        .expect("geokeys");
    image.write_data(&samples).expect("data");
    (path, origin)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_utm_geotiff_is_placed_on_the_globe_by_its_projection() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (tif, origin) = utm_plane_geotiff(tmp.path());
    let db = tmp.path().join("db");
    let summary = build(&tif, &db, &[]);
    assert!(summary.contains("EPSG:32610"), "{summary}");
    let server = TestServer::start(&db);
    let base = server.base_url();
    let tilejson = json(&format!("{base}/v1/terrarium.json")).await;
    let bounds: Vec<f64> = tilejson["bounds"]
        .as_array()
        .expect("bounds")
        .iter()
        .map(|v| v.as_f64().expect("number"))
        .collect();
    // 7.2 km x 5.4 km just west of Rainier's summit (46.85 N, 121.76 W).
    assert!(
        bounds[0] > -121.9 && bounds[2] < -121.7 && bounds[1] > 46.8 && bounds[3] < 46.95,
        "{bounds:?}"
    );
    let placement =
        terrain_server::web::crs::Placement::new(Some(&terrain_shared::manifest::Georeference {
            crs: Some("EPSG:32610".into()),
            origin,
            sample_step: [30.0, -30.0],
        }))
        .expect("UTM");
    let z = tilejson["maxzoom"].as_u64().expect("maxzoom") as u32;
    let template = tilejson["tiles"][0].as_str().expect("URL").to_string();
    let n = f64::from(1u32 << z);
    let (cx, cy) = {
        let lon = (bounds[0] + bounds[2]) / 2.0;
        let lat = ((bounds[1] + bounds[3]) / 2.0).to_radians();
        (
            ((lon + 180.0) / 360.0 * n) as u32,
            ((1.0 - (lat.tan() + 1.0 / lat.cos()).ln() / std::f64::consts::PI) / 2.0 * n) as u32,
        )
    };
    let url = template
        .replace("{z}", &z.to_string())
        .replace("{x}", &cx.to_string())
        .replace("{y}", &cy.to_string());
    let tile = image::load_from_memory(&get(&url).await.body)
        .expect("PNG")
        .to_rgb8();
    let (mut worst, mut checked) = (0.0f64, 0);
    for j in (0..256).step_by(5) {
        for i in (0..256).step_by(5) {
            let (lon, lat) = pixel_lon_lat(z, cx, cy, i, j);
            let (c, r) = placement.to_sample(lon, lat).expect("projects");
            if !(1.0..238.0).contains(&c) || !(1.0..178.0).contains(&r) {
                continue;
            }
            let want = 1000.0 + 0.02 * (30.0 * c) - 0.01 * (-30.0 * r);
            worst = worst.max((terrarium_value(&tile.get_pixel(i, j).0) - want).abs());
            checked += 1;
        }
    }
    println!("UTM plane: {checked} pixels, worst {worst:.3} m");
    assert!(checked > 500, "{checked}");
    // Samples hold whole metres: half a metre of rounding, and a plane is kept by bilinear
    // interpolation.
    assert!(worst < 0.51, "{worst} m off the plane: misplaced");
}

/// One raw request (no URL normalisation on the way): the status line's code and the body.
async fn raw_get(addr: &str, target: &str) -> (u16, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut stream = tokio::net::TcpStream::connect(addr).await.expect("connect");
    let request = format!("GET {target} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
    stream.write_all(request.as_bytes()).await.expect("write");
    let mut answer = Vec::new();
    stream.read_to_end(&mut answer).await.expect("read");
    let text = String::from_utf8_lossy(&answer).into_owned();
    let status = text.get(9..12).and_then(|s| s.parse().ok()).unwrap_or(0);
    (status, text)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_viewer_directory_is_the_only_one_served_and_never_left() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = tmp.path().join("db");
    build(&jacksboro(), &db, &[]);
    let view = tmp.path().join("view");
    std::fs::create_dir_all(&view).expect("view");
    std::fs::write(view.join("index.html"), "<p>viewer</p>").expect("write");
    std::fs::write(tmp.path().join("secret.txt"), "SECRET").expect("write");
    let server = TestServer::start_with_viewer(&db, &view);
    let base = server.base_url();
    let addr = base.trim_start_matches("http://").to_string();
    let a = get(&format!("{base}/view/index.html")).await;
    assert_eq!(a.status, 200);
    assert_eq!(String::from_utf8_lossy(&a.body), "<p>viewer</p>");
    let root = reqwest::Client::builder()
        .redirect(reqwest::redirect::Policy::none())
        .build()
        .expect("client")
        .get(format!("{base}/"))
        .send()
        .await
        .expect("GET /");
    assert_eq!(root.status().as_u16(), 302);
    assert_eq!(root.headers()["location"], "/view/index.html");
    // A directory without its slash (the wasm client's page, /view/client) is redirected to
    // it under /view, not to the server's root.
    std::fs::create_dir_all(view.join("client")).expect("client dir");
    std::fs::write(view.join("client/index.html"), "<p>client</p>").expect("write");
    let no_redirects = reqwest::Client::builder()
        .redirect(reqwest::redirect::Policy::none())
        .build()
        .expect("client");
    let bare = no_redirects
        .get(format!("{base}/view/client"))
        .send()
        .await
        .expect("GET /view/client");
    assert!(bare.status().is_redirection(), "{}", bare.status());
    assert_eq!(bare.headers()["location"], "/view/client/");
    let page = get(&format!("{base}/view/client/")).await;
    assert_eq!(String::from_utf8_lossy(&page.body), "<p>client</p>");
    for target in [
        "/view/../secret.txt",
        "/view/%2e%2e/secret.txt",
        "/view/..%2fsecret.txt",
        "/view/%2e%2e%2fsecret.txt",
        "/view//etc/passwd",
        "/view/../../../../etc/passwd",
        "/view/missing.js",
    ] {
        let (status, text) = raw_get(&addr, target).await;
        assert!(
            !text.contains("SECRET") && !text.contains("root:"),
            "{target}: {status} leaked a file outside the viewer: {text}"
        );
        assert!(status == 404 || status == 400, "{target}: {status}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn srtm_voids_filled_at_the_finest_zoom_jump_no_more_than_the_terrain_around_them() {
    let test =
        "web::srtm_voids_filled_at_the_finest_zoom_jump_no_more_than_the_terrain_around_them";
    let Some(tif) = terrain_tests::data::kit_file(test, "srtm_geotiff/mt_rainier_90m.tif") else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = tmp.path().join("db");
    let summary = build(&tif, &db, &[]);
    assert!(summary.contains("filled 9033 no-data samples"), "{summary}");
    let server = TestServer::start(&db);
    let base = server.base_url();
    let tilejson = json(&format!("{base}/v1/terrarium.json")).await;
    let template = tilejson["tiles"][0].as_str().expect("tile URL").to_string();
    let z = tilejson["maxzoom"].as_u64().expect("maxzoom") as u32;
    let bounds: Vec<f64> = tilejson["bounds"]
        .as_array()
        .expect("bounds")
        .iter()
        .map(|v| v.as_f64().expect("number"))
        .collect();
    let (w, h, samples) = terrain_tests::data::geotiff_i16(&tif);
    let void = |c: i64, r: i64| {
        c >= 0
            && r >= 0
            && c < i64::from(w)
            && r < i64::from(h)
            && samples[(r * i64::from(w) + c) as usize] == -32768
    };
    // The bounds are the corner samples' places: sample (c, r) of a pixel's centre.
    let step = (
        (bounds[2] - bounds[0]) / f64::from(w - 1),
        (bounds[3] - bounds[1]) / f64::from(h - 1),
    );
    let tile = |lon: f64, lat: f64| {
        let n = f64::from(1u32 << z);
        let lat = lat.to_radians();
        (
            ((lon + 180.0) / 360.0 * n).floor() as u32,
            ((1.0 - (lat.tan() + 1.0 / lat.cos()).ln() / std::f64::consts::PI) / 2.0 * n).floor()
                as u32,
        )
    };
    let (x0, y0) = tile(bounds[0], bounds[3]);
    let (x1, y1) = tile(bounds[2], bounds[1]);
    // Per pixel pair (east and south neighbours, both on the terrain), the jump between
    // them, by where the pixels' four nearest samples are.
    let (mut inside, mut away, mut pairs, mut inside_pairs) = (0.0f64, 0.0f64, 0u64, 0u64);
    for ty in y0..=y1 {
        for tx in x0..=x1 {
            let url = template
                .replace("{z}", &z.to_string())
                .replace("{x}", &tx.to_string())
                .replace("{y}", &ty.to_string());
            let answer = get(&url).await;
            assert_eq!(answer.status, 200, "{url}");
            let image = image::load_from_memory(&answer.body)
                .expect("PNG")
                .to_rgb8();
            let place = |i: u32, j: u32| {
                let (lon, lat) = pixel_lon_lat(z, tx, ty, i, j);
                let (c, r) = ((lon - bounds[0]) / step.0, (bounds[3] - lat) / step.1);
                let on = c >= 0.0 && r >= 0.0 && c <= f64::from(w - 1) && r <= f64::from(h - 1);
                let support = [
                    (c.floor(), r.floor()),
                    (c.ceil(), r.floor()),
                    (c.floor(), r.ceil()),
                    (c.ceil(), r.ceil()),
                ];
                let voids = support
                    .iter()
                    .filter(|&&(c, r)| void(c as i64, r as i64))
                    .count();
                (on, voids, terrarium_value(&image.get_pixel(i, j).0))
            };
            for j in 0..256 {
                for i in 0..256 {
                    let a = place(i, j);
                    for (ni, nj) in [(i + 1, j), (i, j + 1)] {
                        if ni == 256 || nj == 256 {
                            continue;
                        }
                        let b = place(ni, nj);
                        if !(a.0 && b.0) {
                            continue;
                        }
                        let jump = (a.2 - b.2).abs();
                        pairs += 1;
                        // Inside: both pixels made of filled samples alone; away: neither
                        // touching one. (On a void's rim a pixel mixes the two.)
                        if a.1 == 4 && b.1 == 4 {
                            inside = inside.max(jump);
                            inside_pairs += 1;
                        } else if a.1 == 0 && b.1 == 0 {
                            away = away.max(jump);
                        }
                    }
                }
            }
        }
    }
    println!(
        "zoom {z}: {pairs} neighbouring pixel pairs, {inside_pairs} inside filled voids; the largest jump inside them {inside:.1} m, away from them {away:.1} m"
    );
    assert!(
        inside_pairs > 1000 && away > 0.0,
        "both kinds of pairs were seen"
    );
    assert!(
        inside <= away,
        "a filled void jumps {inside:.1} m between neighbouring pixels, the terrain around it at most {away:.1} m"
    );
}
