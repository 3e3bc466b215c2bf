//! The clients people already use, in a real browser: MapLibre GL JS (Terrarium through
//! TileJSON, and the PMTiles export through MapLibre's PMTiles protocol) and CesiumJS
//! (quantized-mesh), driven in headless Chromium by `tests/browser/check.mjs` against a
//! real server, on the bundled jacksboro DEM and on an SRTM GeoTIFF of the data kit.
//!
//! Each run checks elevations the client reports at 20 source samples against the source
//! raster (read here, not through the builder; MapLibre's also against the source resampled
//! here to the finest zoom's pixels), Cesium's against the served quantized-mesh tiles
//! decoded here (within a centimetre), that the client saw no error (map and
//! provider error events, failed requests, console errors), and a screenshot against a
//! golden image.
//!
//! Needs `node`, Chromium and `viewer/` set up (`bash viewer/setup.sh`, which
//! `scripts/test.sh` runs); without them the tests say NOT RUN, and fail when
//! `REQUIRE_BROWSER=1` (CI).

use std::path::Path;
use std::process::Command;
use terrain_tests::browser::{browser_ready, chromium, repo, serve};
use terrain_tests::data::{geotiff_i16, jacksboro, kit_file, png_codes, run_binary};

/// Screenshot size: small, to keep SwiftShader's frames quick.
const WIDTH: u32 = 800;
const HEIGHT: u32 = 500;
/// Terrarium's quantum, metres.
const TERRARIUM_QUANTUM: f64 = 1.0 / 256.0;

/// A source raster: size, samples in metres (`None` for no-data) and where sample (0, 0)
/// is, with the step, degrees.
struct Source {
    width: u32,
    height: u32,
    metres: Vec<Option<f64>>,
    origin: (f64, f64),
    step: (f64, f64),
}

impl Source {
    fn at(&self, c: u32, r: u32) -> Option<f64> {
        self.metres[(r * self.width + c) as usize]
    }

    fn lon_lat(&self, c: u32, r: u32) -> (f64, f64) {
        (
            self.origin.0 + f64::from(c) * self.step.0,
            self.origin.1 - f64::from(r) * self.step.1,
        )
    }

    /// 20 samples with data spread over `[west, south, east, north]` (degrees), which
    /// must overlap the raster.
    fn points(&self, area: [f64; 4]) -> Vec<(u32, u32)> {
        let mut out = Vec::new();
        let mut k = 0u32;
        while out.len() < 20 && k < 100_000 {
            // A low-discrepancy walk (golden ratio steps) over the area.
            let fx = (f64::from(k) * 0.618_033_988_75).fract();
            let fy = (f64::from(k) * 0.754_877_666_2 + 0.3).fract();
            k += 1;
            let lon = area[0] + (area[2] - area[0]) * fx;
            let lat = area[3] - (area[3] - area[1]) * fy;
            let c = ((lon - self.origin.0) / self.step.0).round();
            let r = ((self.origin.1 - lat) / self.step.1).round();
            if c < 1.0
                || r < 1.0
                || c >= f64::from(self.width - 1)
                || r >= f64::from(self.height - 1)
            {
                continue;
            }
            if self.at(c as u32, r as u32).is_some() {
                out.push((c as u32, r as u32));
            }
        }
        assert_eq!(out.len(), 20, "no 20 samples with data in {area:?}");
        out
    }

    /// Largest minus smallest sample within `radius` samples of `(c, r)`: any value
    /// interpolated from samples in that window differs from the sample by no more.
    fn spread(&self, c: u32, r: u32, radius: f64) -> f64 {
        let k = radius.ceil() as i64;
        let (mut lo, mut hi) = (f64::MAX, f64::MIN);
        for dr in -k..=k {
            for dc in -k..=k {
                let (cc, rr) = (i64::from(c) + dc, i64::from(r) + dr);
                if cc < 0 || rr < 0 || cc >= i64::from(self.width) || rr >= i64::from(self.height) {
                    continue;
                }
                if let Some(h) = self.at(cc as u32, rr as u32) {
                    lo = lo.min(h);
                    hi = hi.max(h);
                }
            }
        }
        hi - lo
    }
}

impl Source {
    /// Bilinear value at fractional sample `(c, r)`, `None` off the raster or on no-data.
    fn bilinear(&self, c: f64, r: f64) -> Option<f64> {
        if c < 0.0 || r < 0.0 || c > f64::from(self.width - 1) || r > f64::from(self.height - 1) {
            return None;
        }
        let (c0, r0) = (c.floor() as u32, r.floor() as u32);
        let (c1, r1) = ((c0 + 1).min(self.width - 1), (r0 + 1).min(self.height - 1));
        let (fc, fr) = (c - f64::from(c0), r - f64::from(r0));
        let top = self.at(c0, r0)? * (1.0 - fc) + self.at(c1, r0)? * fc;
        let bottom = self.at(c0, r1)? * (1.0 - fc) + self.at(c1, r1)? * fc;
        Some(top * (1.0 - fr) + bottom * fr)
    }

    /// What MapLibre should answer at `(lon, lat)` from Terrarium tiles of `zoom` made from
    /// this source: the source's bilinear value at the centres of the four pixels around
    /// the point, interpolated bilinearly between them.
    /// `None` where a sample it needs is no-data (the builder filled those its own way).
    fn mercator_model(&self, lon: f64, lat: f64, zoom: u32) -> Option<f64> {
        let world = 256.0 * f64::from(1u32 << zoom);
        let y_of = |lat: f64| {
            let l = lat.to_radians();
            (1.0 - (l.tan() + 1.0 / l.cos()).ln() / std::f64::consts::PI) / 2.0 * world
        };
        let (px, py) = ((lon + 180.0) / 360.0 * world - 0.5, y_of(lat) - 0.5);
        let (i0, j0) = (px.floor(), py.floor());
        let (fx, fy) = (px - i0, py - j0);
        let value = |i: f64, j: f64| {
            let lon = (i + 0.5) / world * 360.0 - 180.0;
            let lat = (std::f64::consts::PI * (1.0 - 2.0 * (j + 0.5) / world))
                .sinh()
                .atan()
                .to_degrees();
            let c = (lon - self.origin.0) / self.step.0;
            let r = (self.origin.1 - lat) / self.step.1;
            self.bilinear(c, r)
        };
        let top = value(i0, j0)? * (1.0 - fx) + value(i0 + 1.0, j0)? * fx;
        let bottom = value(i0, j0 + 1.0)? * (1.0 - fx) + value(i0 + 1.0, j0 + 1.0)? * fx;
        Some(top * (1.0 - fy) + bottom * fy)
    }
}

/// How far MapLibre may be from [`Source::mercator_model`]: Terrarium's quantum, and the
/// 32-bit floats the tiles are decoded and interpolated in (measured: 0.002 m at most).
const MODEL_TOLERANCE: f64 = 0.01;

/// What `check.mjs` wrote.
struct Run {
    elevations: Vec<Option<f64>>,
    screenshot: image::RgbaImage,
    result: serde_json::Value,
}

/// Runs the page once in Chromium; panics with what went wrong when the page did not get
/// ready or saw any error.
fn run_page(name: &str, url: &str, points: &[(f64, f64)], out: &Path) -> Run {
    let dir = out.join(name);
    std::fs::create_dir_all(&dir).expect("out dir");
    let points_json: Vec<serde_json::Value> = points
        .iter()
        .map(|&(lon, lat)| serde_json::json!({"lon": lon, "lat": lat}))
        .collect();
    let points_path = dir.join("points.json");
    std::fs::write(
        &points_path,
        serde_json::to_vec(&points_json).expect("JSON"),
    )
    .expect("write");
    let started = std::time::Instant::now();
    let output = Command::new("node")
        .arg(repo().join("tests/browser/check.mjs"))
        .args(["--page", url, "--timeout-s", "120"])
        .arg("--points")
        .arg(&points_path)
        .arg("--out")
        .arg(&dir)
        .args([
            "--width",
            &WIDTH.to_string(),
            "--height",
            &HEIGHT.to_string(),
        ])
        .arg("--chromium")
        .arg(chromium())
        .output()
        .expect("node runs");
    let result: serde_json::Value = std::fs::read(dir.join("result.json"))
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok())
        .unwrap_or_else(|| {
            panic!(
                "{name}: check.mjs wrote no result.json: {}",
                String::from_utf8_lossy(&output.stderr)
            )
        });
    assert_eq!(
        result["ok"], true,
        "{name}: the page did not get ready: {} ({url})",
        result["reason"]
    );
    for key in ["errors", "console_errors", "failed_requests"] {
        let list = result[key].as_array().map_or(0, Vec::len);
        assert_eq!(list, 0, "{name}: {key}: {}", result[key]);
    }
    let elevations = result["elevations"]
        .as_array()
        .expect("elevations")
        .iter()
        .map(serde_json::Value::as_f64)
        .collect();
    let screenshot = image::open(dir.join("screenshot.png"))
        .expect("screenshot")
        .into_rgba8();
    println!(
        "{name}: ready in {:.1} s ({:.1} s with Chromium's start), {} requests",
        result["seconds"].as_f64().unwrap_or(0.0),
        started.elapsed().as_secs_f64(),
        result["requests"]
    );
    Run {
        elevations,
        screenshot,
        result,
    }
}

/// The URL `check.mjs` opens.
fn page(base: &str, query: &str) -> String {
    format!("{base}/view/index.html?status=0&{query}")
}

/// A JSON document from the server.
/// Most a height Cesium reports may differ from the served tile's surface at the same
/// point: its interpolation within the triangle against ours, in floats.
const CESIUM_TOLERANCE_M: f64 = 0.01;

/// The height of the served quantized-mesh surface at (`lon`, `lat`), from the tile of
/// `level` holding it (the geographic TMS scheme: `x` from the west, `y` from the south),
/// fetched from `template` (layer.json's) and decoded here.
fn served_mesh_height(base: &str, template: &str, level: u32, lon: f64, lat: f64) -> f64 {
    use std::io::Read as _;
    use terrain_server::web::quantized_mesh::{self, GeoRect};
    let d = 180.0 / f64::from(1u32 << level);
    let (x, y) = (
        ((lon + 180.0) / d).floor() as u32,
        ((lat + 90.0) / d).floor() as u32,
    );
    // layer.json's template is a path from the server's root.
    let url = format!(
        "{base}{}",
        template
            .replace("{z}", &level.to_string())
            .replace("{x}", &x.to_string())
            .replace("{y}", &y.to_string())
    );
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let gzipped = runtime.block_on(async {
        let response = reqwest::get(&url)
            .await
            .unwrap_or_else(|e| panic!("GET {url}: {e}"));
        assert!(
            response.status().is_success(),
            "GET {url}: {}",
            response.status()
        );
        response.bytes().await.expect("body")
    });
    let mut bytes = Vec::new();
    flate2::read::GzDecoder::new(&gzipped[..])
        .read_to_end(&mut bytes)
        .expect("a gzipped tile");
    let tile = quantized_mesh::decode(&bytes).expect("a quantized-mesh tile");
    let rect = GeoRect {
        west: -180.0 + f64::from(x) * d,
        south: -90.0 + f64::from(y) * d,
        east: -180.0 + f64::from(x + 1) * d,
        north: -90.0 + f64::from(y + 1) * d,
    };
    quantized_mesh::height_at(&tile, &rect, lon, lat).expect("the point is inside its tile")
}

fn fetch_json(url: &str) -> serde_json::Value {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    runtime.block_on(async {
        let response = reqwest::get(url)
            .await
            .unwrap_or_else(|e| panic!("GET {url}: {e}"));
        assert!(
            response.status().is_success(),
            "GET {url}: {}",
            response.status()
        );
        let bytes = response.bytes().await.expect("body");
        serde_json::from_slice(&bytes).unwrap_or_else(|e| panic!("{url}: {e}"))
    })
}

fn build_db(input: &Path, out: &Path) {
    let (ok, _, stderr) = run_binary(
        "terrain-server",
        &[
            "build".as_ref(),
            "--quiet".as_ref(),
            input.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
        ],
    );
    assert!(ok, "{stderr}");
}

/// One dataset through both clients and the PMTiles protocol.
fn check_dataset(
    name: &str,
    input: &Path,
    source: &Source,
    maplibre_camera: &str,
    cesium_camera: &str,
) {
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = tmp.path().join("db");
    build_db(input, &db);
    let archive = tmp.path().join(format!("{name}.pmtiles"));
    let (ok, _, stderr) = run_binary(
        "terrain-server",
        &[
            "export".as_ref(),
            db.as_os_str(),
            "--pmtiles".as_ref(),
            archive.as_os_str(),
        ],
    );
    assert!(ok, "{stderr}");
    let server = serve(&db, tmp.path(), &[&archive]);
    let base = server.base_url();
    let out = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../target/browser")
        .join(name);
    let _ = std::fs::remove_dir_all(&out);

    // MapLibre, straight down one zoom past the finest DEM tiles, so that it reads those.
    let tilejson = fetch_json(&format!("{base}/v1/terrarium.json"));
    let max_zoom = tilejson["maxzoom"].as_u64().expect("maxzoom") as u32;
    let bounds: Vec<f64> = tilejson["bounds"]
        .as_array()
        .expect("bounds")
        .iter()
        .filter_map(serde_json::Value::as_f64)
        .collect();
    let (lon, lat) = ((bounds[0] + bounds[2]) / 2.0, (bounds[1] + bounds[3]) / 2.0);
    let camera = format!("lon={lon}&lat={lat}&zoom={}", max_zoom + 2);
    // The points: in the middle 70% of that view, so that they lie on tiles it loaded.
    let world = 256.0 * f64::from(4u32 << max_zoom);
    let half_lon = 0.35 * f64::from(WIDTH) / world * 360.0;
    let half_lat = 0.35 * f64::from(HEIGHT) / world * 360.0 * lat.to_radians().cos();
    let samples = source.points([
        lon - half_lon,
        lat - half_lat,
        lon + half_lon,
        lat + half_lat,
    ]);
    let points: Vec<(f64, f64)> = samples.iter().map(|&(c, r)| source.lon_lat(c, r)).collect();
    let truth: Vec<f64> = samples
        .iter()
        .map(|&(c, r)| source.at(c, r).expect("data"))
        .collect();
    let top = run_page(
        "maplibre-top",
        &page(base, &format!("client=maplibre&texture=0&{camera}")),
        &points,
        &out,
    );
    // The DEM tiles it read: every point must lie on a tile of the finest zoom.
    let log = top.result["request_log"].to_string();
    let pixel_m = 2.0 * std::f64::consts::PI * 6_378_137.0 * lat.to_radians().cos()
        / (256.0 * f64::from(1u32 << max_zoom));
    let spacing_m = (source.step.0.to_radians() * lat.to_radians().cos())
        .min(source.step.1.to_radians())
        * 6_378_137.0;
    // A pixel is interpolated from samples within one sample of its centre, MapLibre
    // interpolates pixels within one pixel of the point: so within this many samples.
    let radius = pixel_m / spacing_m + 1.0;
    let (mut worst, mut worst_bound) = (0.0f64, 0.0f64);
    for (i, ((&(c, r), want), got)) in samples.iter().zip(&truth).zip(&top.elevations).enumerate() {
        let got = got.unwrap_or_else(|| panic!("{name}: MapLibre has no elevation at point {i}"));
        let bound = source.spread(c, r, radius) + TERRARIUM_QUANTUM;
        assert!(
            (got - want).abs() <= bound,
            "{name}: MapLibre at sample ({c}, {r}) says {got:.2} m, the source {want} m: more than the {bound:.2} m its neighbourhood allows (request log {log})"
        );
        worst = worst.max((got - want).abs());
        worst_bound = worst_bound.max(bound);
    }
    println!(
        "{name}: MapLibre at 20 samples within {worst:.2} m of the source (bounds up to {worst_bound:.2} m: Terrarium's 1/256 m plus the heights' spread within {radius:.1} samples, zoom {max_zoom}'s {pixel_m:.0} m pixels)"
    );
    // Tighter: the source resampled at the centres of zoom max_zoom's pixels, then
    // interpolated between pixel centres as MapLibre does, computed here from the source.
    let (mut worst_model, mut modelled) = (0.0f64, 0);
    for (&(lon, lat), got) in points.iter().zip(&top.elevations) {
        if let Some(model) = source.mercator_model(lon, lat, max_zoom) {
            worst_model = worst_model.max((got.expect("elevation") - model).abs());
            modelled += 1;
        }
    }
    println!(
        "{name}: MapLibre within {worst_model:.3} m of the source resampled to zoom {max_zoom}'s pixels and interpolated between their centres at the {modelled} points with no void nearby"
    );
    assert!(
        modelled >= 15,
        "{name}: only {modelled} points away from voids"
    );
    assert!(
        worst_model <= MODEL_TOLERANCE,
        "{name}: MapLibre is {worst_model:.3} m from the source resampled to zoom {max_zoom}'s pixels (allowed {MODEL_TOLERANCE} m)"
    );
    assert!(
        log.contains(&format!("/terrarium/{max_zoom}/")),
        "{name}: zoom {max_zoom} never read: {log}"
    );

    // The PMTiles archive through MapLibre's PMTiles protocol: the same elevations.
    let pm = run_page(
        "maplibre-pmtiles",
        &page(
            base,
            &format!(
                "client=maplibre&texture=0&source=pmtiles&pmtiles={base}/view/{name}.pmtiles&{camera}"
            ),
        ),
        &points,
        &out,
    );
    for (i, (a, b)) in top.elevations.iter().zip(&pm.elevations).enumerate() {
        let (a, b) = (
            a.expect("TileJSON"),
            b.unwrap_or_else(|| panic!("{name}: PMTiles point {i}")),
        );
        assert!(
            (a - b).abs() < 1e-6,
            "{name}: point {i}: TileJSON {a} m, PMTiles {b} m"
        );
    }
    println!("{name}: the PMTiles archive gives the same 20 elevations");

    // The picture: pitched, with the texture and hill shading.
    let pitched = run_page(
        "maplibre",
        &page(base, &format!("client=maplibre&{maplibre_camera}")),
        &[],
        &out,
    );
    terrain_tests::golden::compare(
        &format!("browser-{name}-maplibre"),
        &pitched.screenshot,
        terrain_tests::golden::Match::Tolerant,
    );

    // Cesium: the most detailed tiles. What it reports at each point is checked against the
    // surface of the tile it read, decoded here from the served bytes (a bound that owes
    // nothing to the server's own statements: only Cesium's interpolation and float
    // rounding lie between them); the distance to the source is printed beside the error
    // layer.json states, which `web::jacksboro_quantized_mesh_tiles_stay_within_the_error_layer_json_states`
    // measures at every sample.
    let layer = fetch_json(&format!("{base}/v1/cesium/layer.json"));
    let finest = layer["maxzoom"].as_u64().expect("maxzoom") as u32;
    let stated = layer["max_error_m"][finest as usize]
        .as_f64()
        .expect("max_error_m");
    let template = layer["tiles"][0].as_str().expect("template").to_string();
    let cesium = run_page(
        "cesium",
        &page(base, &format!("client=cesium&{cesium_camera}")),
        &points,
        &out,
    );
    let (mut worst_served, mut worst_source) = (0.0f64, 0.0f64);
    for (i, ((&(lon, lat), want), got)) in points
        .iter()
        .zip(&truth)
        .zip(&cesium.elevations)
        .enumerate()
    {
        let got = got.unwrap_or_else(|| panic!("{name}: Cesium has no height at point {i}"));
        let served = served_mesh_height(base, &template, finest, lon, lat);
        assert!(
            (got - served).abs() <= CESIUM_TOLERANCE_M,
            "{name}: Cesium at point {i} ({lon}, {lat}) says {got:.3} m, the level {finest} tile it read holds {served:.3} m there"
        );
        worst_served = worst_served.max((got - served).abs());
        worst_source = worst_source.max((got - want).abs());
    }
    println!(
        "{name}: Cesium at 20 points within {worst_served:.4} m of the served level {finest} tiles (allowed {CESIUM_TOLERANCE_M} m), {worst_source:.2} m of the source (level {finest}'s stated error {stated:.2} m)"
    );
    terrain_tests::golden::compare(
        &format!("browser-{name}-cesium"),
        &cesium.screenshot,
        terrain_tests::golden::Match::Tolerant,
    );
}

#[test]
fn maplibre_and_cesium_read_jacksboro_as_its_source_says() {
    let test = "maplibre_and_cesium_read_jacksboro_as_its_source_says";
    if !browser_ready(test) {
        return;
    }
    let (width, height, codes) = png_codes(&jacksboro());
    let source = Source {
        width,
        height,
        metres: codes.iter().map(|&c| Some(f64::from(c))).collect(),
        // dataset.json: north_west_corner_deg and spacing_deg.
        origin: (-84.41375, 36.73292),
        step: (0.000_833_333_333_333_333_4, 0.000_833_333_333_333_333_4),
    };
    check_dataset(
        "jacksboro",
        &jacksboro(),
        &source,
        "lon=-84.24625&lat=36.59&zoom=9.8&pitch=60&bearing=20",
        "lon=-84.25&lat=36.36&height=14000&heading=0&pitch=-38",
    );
}

#[test]
fn maplibre_and_cesium_read_an_srtm_geotiff_as_its_source_says() {
    let test = "maplibre_and_cesium_read_an_srtm_geotiff_as_its_source_says";
    let Some(tif) = kit_file(test, "srtm_geotiff/mt_rainier_90m.tif") else {
        return;
    };
    if !browser_ready(test) {
        return;
    }
    let (width, height, samples) = geotiff_i16(&tif);
    // The GeoTIFF's own tags (read with the tiff crate here): the step, and the tie point,
    // a pixel's corner unless the raster type key says PixelIsPoint.
    let (origin, step) = {
        let file = std::fs::File::open(&tif).expect("tif");
        let mut decoder = tiff::decoder::Decoder::new(std::io::BufReader::new(file)).expect("TIFF");
        let scale = decoder
            .get_tag_f64_vec(tiff::tags::Tag::Unknown(33550))
            .expect("ModelPixelScale");
        let tie = decoder
            .get_tag_f64_vec(tiff::tags::Tag::Unknown(33922))
            .expect("ModelTiepoint");
        let keys = decoder
            .get_tag_u16_vec(tiff::tags::Tag::Unknown(34735))
            .expect("GeoKeyDirectory");
        let point = keys[4..].chunks_exact(4).any(|k| k[0] == 1025 && k[3] == 2);
        let half = if point { 0.0 } else { 0.5 };
        (
            (
                tie[3] + (half - tie[0]) * scale[0],
                tie[4] - (half - tie[1]) * scale[1],
            ),
            (scale[0], scale[1]),
        )
    };
    let source = Source {
        width,
        height,
        metres: samples
            .iter()
            .map(|&v| (v != -32768).then_some(f64::from(v)))
            .collect(),
        origin,
        step,
    };
    check_dataset(
        "mt_rainier",
        &tif,
        &source,
        "lon=-121.76&lat=46.74&zoom=10.4&pitch=55&bearing=0",
        "lon=-121.76&lat=46.60&height=12000&heading=0&pitch=-30",
    );
}

#[test]
fn maplibre_at_a_high_dem_edge_draws_the_surface_level_with_it_not_a_wall() {
    let test = "maplibre_at_a_high_dem_edge_draws_the_surface_level_with_it_not_a_wall";
    if !browser_ready(test) {
        return;
    }
    let (width, height, codes) = png_codes(&jacksboro());
    let source = Source {
        width,
        height,
        metres: codes.iter().map(|&c| Some(f64::from(c))).collect(),
        origin: (-84.41375, 36.73292),
        step: (0.000_833_333_333_333_333_4, 0.000_833_333_333_333_333_4),
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = tmp.path().join("db");
    build_db(&jacksboro(), &db);
    let server = serve(&db, tmp.path(), &[]);
    let base = server.base_url();
    let max_zoom = fetch_json(&format!("{base}/v1/terrarium.json"))["maxzoom"]
        .as_u64()
        .expect("maxzoom") as u32;
    // The highest of the four edges, by the mean of its samples.
    let edge_mean = |samples: Vec<(u32, u32)>| {
        samples
            .iter()
            .filter_map(|&(c, r)| source.at(c, r))
            .sum::<f64>()
            / samples.len() as f64
    };
    let (w, h) = (width - 1, height - 1);
    let edges: [(&str, Vec<(u32, u32)>); 4] = [
        ("north", (0..=w).map(|c| (c, 0)).collect()),
        ("south", (0..=w).map(|c| (c, h)).collect()),
        ("west", (0..=h).map(|r| (0, r)).collect()),
        ("east", (0..=h).map(|r| (w, r)).collect()),
    ];
    let (side, samples) = edges
        .into_iter()
        .max_by(|a, b| edge_mean(a.1.clone()).total_cmp(&edge_mean(b.1.clone())))
        .expect("four edges");
    let mean = edge_mean(samples.clone());
    // Points two samples outside the edge at ten places along its middle half, and the edge
    // sample each faces.
    let (dc, dr) = match side {
        "north" => (0.0, -2.0),
        "south" => (0.0, 2.0),
        "west" => (-2.0, 0.0),
        _ => (2.0, 0.0),
    };
    let along: Vec<(u32, u32)> = (0..10)
        .map(|k| samples[samples.len() / 4 + k * samples.len() / 20])
        .collect();
    let points: Vec<(f64, f64)> = along
        .iter()
        .map(|&(c, r)| {
            (
                source.origin.0 + (f64::from(c) + dc) * source.step.0,
                source.origin.1 - (f64::from(r) + dr) * source.step.1,
            )
        })
        .collect();
    let (lon, lat) = source.lon_lat(along[5].0, along[5].1);
    let out = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/browser/jacksboro-edge");
    let _ = std::fs::remove_dir_all(&out);
    let top = run_page(
        "maplibre-edge-top",
        &page(
            base,
            &format!(
                "client=maplibre&texture=0&lon={lon}&lat={lat}&zoom={}",
                max_zoom + 1
            ),
        ),
        &points,
        &out,
    );
    let pixel_m = 2.0 * std::f64::consts::PI * 6_378_137.0 * lat.to_radians().cos()
        / (256.0 * f64::from(1u32 << max_zoom));
    let spacing_m = source.step.1.to_radians() * 6_378_137.0;
    let radius = pixel_m / spacing_m + 3.0;
    let mut worst = 0.0f64;
    for (&(c, r), got) in along.iter().zip(&top.elevations) {
        let got = got.unwrap_or_else(|| panic!("MapLibre has no elevation off the {side} edge"));
        let edge = source.at(c, r).expect("data");
        // Off the terrain the surface stays at the edge's height (within what the samples
        // near it spread over): before, it fell to 0 m, a wall of the edge's height.
        let bound = source.spread(c, r, radius) + TERRARIUM_QUANTUM;
        assert!(
            (got - edge).abs() <= bound,
            "two samples off the {side} edge at ({c}, {r}): MapLibre says {got:.1} m, the edge {edge} m (allowed {bound:.1} m)"
        );
        worst = worst.max((got - edge).abs());
    }
    println!(
        "the {side} edge (mean {mean:.0} m): off it MapLibre's surface is within {worst:.1} m of the edge's height at 10 places"
    );
    // The picture: from over the terrain, low, looking out across the edge (a wall would
    // stand there, as high as the edge).
    let bearing = match side {
        "north" => 0,
        "south" => 180,
        "west" => 270,
        _ => 90,
    };
    let pitched = run_page(
        "maplibre-edge",
        &page(
            base,
            &format!("client=maplibre&lon={lon}&lat={lat}&zoom=11.5&pitch=72&bearing={bearing}"),
        ),
        &[],
        &out,
    );
    terrain_tests::golden::compare(
        "browser-jacksboro-maplibre-edge",
        &pitched.screenshot,
        terrain_tests::golden::Match::Tolerant,
    );
}
