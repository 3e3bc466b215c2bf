//! Our own client in a browser tab: the wasm build of the client (`web/`, built into
//! `viewer/dist/client` by `scripts/build-web.sh`) flies the default flight in headless
//! Chromium (WebGPU on SwiftShader, and WebGL2 on SwiftShader through ANGLE as a browser
//! without WebGPU), driven by `tests/browser/client.mjs`, against a real server, beside the
//! native client's flight of the same cameras on lavapipe: over jacksboro (bundled) and over
//! the data kit's himalaya_4097 in 16 MiB.
//!
//! Its own test binary, so it runs alone: SwiftShader takes both cores for minutes, and
//! beside the other end-to-end tests it would stretch their timing (a method's data meshed
//! later than a still flight measures its memory).
//!
//! Needs what the browser tests need (`bash viewer/setup.sh`) and the page
//! (`bash scripts/build-web.sh`; `scripts/test.sh` runs both); without them the test says
//! NOT RUN, and fails when `REQUIRE_BROWSER=1` (CI).

use std::io::Write;
use std::process::Command;
use terrain_tests::browser::{browser_ready, chromium, repo, serve};
use terrain_tests::data::{jacksboro, kit_file, run_binary};
use terrain_tests::fixtures::{Options, database};

const WIDTH: u32 = 960;
const HEIGHT: u32 = 540;
/// A fixed triangle budget, so that both clients draw the same triangles whatever their
/// frame times (the page's SwiftShader and the native lavapipe differ).
const FIXED_BUDGET: &str = "60000";
/// The page's frame may differ from the native one as a browser's screenshot may differ
/// from its golden image: at most this share of the pixels by more than
/// [`CHANNEL_TOLERANCE`] in a channel (two rasterisers, SwiftShader in Chromium and
/// lavapipe, and their texture filtering, an edge or a texel apart).
use terrain_tests::golden::{CHANNEL_TOLERANCE, MAX_DIFFERING_SHARE};

/// Whether the page is built; says NOT RUN (or fails under `REQUIRE_BROWSER=1`) when not.
fn page_built(test: &str) -> bool {
    let wasm = repo().join("viewer/dist/client/pkg/terrain_web_bg.wasm");
    if wasm.exists() {
        return true;
    }
    let required = std::env::var("REQUIRE_BROWSER").is_ok_and(|v| v == "1");
    assert!(
        !required,
        "{test}: REQUIRE_BROWSER=1 but {} is missing (run `bash scripts/build-web.sh`)",
        wasm.display()
    );
    let _ = writeln!(
        std::io::stderr(),
        "NOT RUN: {test} needs the wasm client's page (run `bash scripts/build-web.sh`)"
    );
    false
}

/// Runs `tests/browser/client.mjs` with `args`, writing into `out`; its `result.json`.
fn drive(args: &[&str], out: &std::path::Path) -> serde_json::Value {
    let output = Command::new("node")
        .arg(repo().join("tests/browser/client.mjs"))
        .args(args)
        .arg("--out")
        .arg(out)
        .arg("--chromium")
        .arg(chromium())
        .output()
        .expect("node runs");
    std::fs::read(out.join("result.json"))
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok())
        .unwrap_or_else(|| {
            panic!(
                "client.mjs wrote no result.json: {}",
                String::from_utf8_lossy(&output.stderr)
            )
        })
}

/// What the page draws with: the browser's WebGPU, or WebGL2 in a browser without it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Backend {
    WebGpu,
    WebGl2,
}

impl Backend {
    /// wgpu's name of it, as the page reports it.
    fn reported(self) -> &'static str {
        match self {
            Backend::WebGpu => "BrowserWebGpu",
            Backend::WebGl2 => "Gl",
        }
    }
}

/// What a flight of both clients gave.
struct Flown {
    /// The native flight's directory (its `frames/frame-NNNNNN.png`).
    native: std::path::PathBuf,
    /// The frames both wrote, in order.
    frames: Vec<u64>,
    /// The page's directory (`frame-N.png`, `settled.png`, `result.json`).
    page: std::path::PathBuf,
    result: serde_json::Value,
    /// The limit both flew under, bytes.
    limit: u64,
    size: [u32; 2],
    /// Peaks over the page's frames: resident bytes, the wasm heap.
    peak: u64,
    heap_peak: u64,
    seconds: f64,
}

/// How both clients fly the default flight.
#[derive(Debug, Clone, Copy)]
struct Flight<'a> {
    memory_kib: u64,
    /// Frames a second of flight.
    fps: u32,
    size: [u32; 2],
    /// Whether the page then draws on until the scene settles (`settled.png`).
    settle: bool,
    /// What the page draws with.
    backend: Backend,
    method: &'a str,
}

/// Flies the default flight over `db` natively and in the page as `flight` says, with
/// [`FIXED_BUDGET`]; checks what holds for every page flight (no error, no failed or
/// external request, the backend asked for, the limit at every frame's end) and returns
/// both.
fn fly_both(name: &str, db: &std::path::Path, flight: Flight<'_>) -> Flown {
    let Flight {
        memory_kib,
        fps,
        size,
        settle,
        backend,
        method,
    } = flight;
    let [width, height] = size;
    let tmp = tempfile::tempdir().expect("tmp");
    let server = serve(db, tmp.path(), &[]);
    let base = server.base_url().to_string();
    let memory = format!("{memory_kib}KiB");

    // The native flight: its frames every 30 and the last.
    let native = repo().join(format!("tests/out/web_client/{name}/native"));
    let _ = std::fs::remove_dir_all(&native);
    let (ok, stdout, stderr) = run_binary(
        "terrain-client",
        &[
            "fly".as_ref(),
            "--server".as_ref(),
            base.as_ref(),
            "--out".as_ref(),
            native.as_os_str(),
            "--memory".as_ref(),
            memory.as_ref(),
            "--fixed-budget".as_ref(),
            FIXED_BUDGET.as_ref(),
            "--fps".as_ref(),
            fps.to_string().as_ref(),
            "--size".as_ref(),
            format!("{width}x{height}").as_ref(),
            "--method".as_ref(),
            method.as_ref(),
            "--quiet".as_ref(),
        ],
    );
    assert!(ok, "{name}: native flight failed: {stdout}{stderr}");
    let mut frames: Vec<u64> = std::fs::read_dir(native.join("frames"))
        .expect("frames")
        .filter_map(|e| {
            let name = e.ok()?.file_name().into_string().ok()?;
            name.strip_prefix("frame-")?
                .strip_suffix(".png")?
                .parse()
                .ok()
        })
        .collect();
    frames.sort_unstable();
    assert!(frames.len() >= 3, "{name}: frames {frames:?}");
    let last = *frames.last().expect("a frame");

    // The page: the same flight, frame by frame, stopping at the native frames.
    let out = repo().join(format!("tests/out/web_client/{name}/page"));
    let _ = std::fs::remove_dir_all(&out);
    let stops: Vec<String> = frames.iter().map(u64::to_string).collect();
    let page = format!(
        "{base}/view/client/index.html?mode=flight&memory={memory}&fixed_budget={FIXED_BUDGET}&flight_fps={fps}&method={method}"
    );
    let started = std::time::Instant::now();
    let (w, h, stop_list) = (width.to_string(), height.to_string(), stops.join(","));
    let mut args = vec![
        "--page",
        &page,
        "--frames",
        &stop_list,
        "--timeout-s",
        "600",
    ];
    args.extend(["--width", &w, "--height", &h]);
    if settle {
        args.extend(["--settle-frames", "600"]);
    }
    if backend == Backend::WebGl2 {
        args.push("--no-webgpu");
    }
    let result = drive(&args, &out);
    assert_eq!(
        result["ok"], true,
        "{name}: the page did not fly: {} ({page}); console: {}",
        result["reason"], result["console_messages"]
    );
    for key in [
        "errors",
        "console_errors",
        "failed_requests",
        "external_requests",
    ] {
        let list = result[key].as_array().map_or(0, Vec::len);
        assert_eq!(list, 0, "{name}: {key}: {}", result[key]);
    }
    assert_eq!(
        result["info"]["backend"],
        backend.reported(),
        "{name}: the page should draw with {backend:?}: {}",
        result["info"]
    );

    // The limit held at every frame's end, and it is the native flight's limit.
    let history = result["history"].as_array().expect("history");
    assert!(
        history.len() as u64 > last,
        "{name}: {} frames",
        history.len()
    );
    let limit = (memory_kib << 10) * 9 / 10;
    let (mut peak, mut heap_peak) = (0, 0);
    for s in history {
        let resident = s["resident_bytes"].as_u64().expect("resident_bytes");
        assert_eq!(s["limit_bytes"].as_u64(), Some(limit), "{name}: {s}");
        assert!(
            resident <= limit,
            "{name}: frame {}: {resident} bytes over the limit {limit}",
            s["frame"]
        );
        peak = peak.max(resident);
        heap_peak = heap_peak.max(s["wasm_heap_bytes"].as_u64().unwrap_or(0));
    }
    // The limit binds on the tiles' methods: the tiles at every texture level would not fit.
    // (The projected grids hold an atlas of heights instead, which it need not bind.)
    let grid = method == "pgm" || method == "projective-grid";
    assert!(
        grid || peak as f64 > 0.9 * limit as f64,
        "{name}: the limit never bound: peak {peak} of {limit} bytes"
    );
    Flown {
        native,
        frames,
        page: out,
        result,
        limit,
        size,
        peak,
        heap_peak,
        seconds: started.elapsed().as_secs_f64(),
    }
}

fn open(path: &std::path::Path, size: [u32; 2]) -> image::RgbaImage {
    let image = image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .into_rgba8();
    assert_eq!(image.dimensions(), (size[0], size[1]), "{}", path.display());
    image
}

/// The page's frame `k` and the native one's.
fn pair(flown: &Flown, k: u64) -> (image::RgbaImage, image::RgbaImage) {
    (
        open(&flown.page.join(format!("frame-{k}.png")), flown.size),
        open(
            &flown.native.join(format!("frames/frame-{k:06}.png")),
            flown.size,
        ),
    )
}

/// Pixels of terrain (anything but the sky's clear colour, [`terrain_client::render::SKY`]
/// written to an sRGB target).
fn terrain_pixels(image: &image::RgbaImage) -> u64 {
    let srgb = |c: f64| {
        let s = if c <= 0.003_130_8 {
            12.92 * c
        } else {
            1.055 * c.powf(1.0 / 2.4) - 0.055
        };
        (s * 255.0).round() as i32
    };
    let sky = terrain_client::render::SKY.map(srgb);
    image
        .pixels()
        .filter(|p| (0..3).any(|i| (i32::from(p.0[i]) - sky[i]).abs() > 3))
        .count() as u64
}

#[test]
fn the_wasm_client_flies_jacksboro_in_chromium_within_its_limit_as_the_native_one_draws_it() {
    jacksboro_in_the_page_as_natively(
        "the_wasm_client_flies_jacksboro_in_chromium_within_its_limit_as_the_native_one_draws_it",
        Backend::WebGpu,
        "strip-masks",
    );
}

/// WebGL2's vertex shaders read no storage buffers: the page reads the samples from a
/// texture there, and draws the strip masks and the planar shadow as natively.
#[test]
fn on_webgl2_the_wasm_client_draws_jacksboro_with_strip_masks_and_the_planar_shadow_as_natively() {
    jacksboro_in_the_page_as_natively(
        "on_webgl2_the_wasm_client_draws_jacksboro_with_strip_masks_and_the_planar_shadow_as_natively",
        Backend::WebGl2,
        "strip-masks",
    );
}

/// The quadtree patches in the page: their values are zstd frames, which the page reads
/// with a decoder in Rust (ruzstd), and it draws them as the native client does.
#[test]
fn the_wasm_client_draws_jacksboros_quadtree_patches_as_natively() {
    jacksboro_in_the_page_as_natively(
        "the_wasm_client_draws_jacksboros_quadtree_patches_as_natively",
        Backend::WebGpu,
        "quadtree-patches",
    );
}

/// The same on WebGL2: the patches' vertices are vertex buffers, which it has.
#[test]
fn on_webgl2_the_wasm_client_draws_jacksboros_quadtree_patches_as_natively() {
    jacksboro_in_the_page_as_natively(
        "on_webgl2_the_wasm_client_draws_jacksboros_quadtree_patches_as_natively",
        Backend::WebGl2,
        "quadtree-patches",
    );
}

/// The projected grids in the page (WebGPU: their shaders read storage buffers): persistent
/// grid mapping and the error-bounded projective grid with its ray casting.
#[test]
fn the_wasm_client_draws_jacksboro_with_the_projected_grids_as_natively() {
    for method in ["pgm", "projective-grid"] {
        jacksboro_in_the_page_as_natively(
            "the_wasm_client_draws_jacksboro_with_the_projected_grids_as_natively",
            Backend::WebGpu,
            method,
        );
    }
}

/// The default flight over jacksboro with `method` (and the planar shadow) in 2 MiB, in the
/// page drawing with `backend` and natively: every stop draws terrain, and the settled page
/// draws the native flight's last frame within the golden tolerance.
fn jacksboro_in_the_page_as_natively(test: &str, backend: Backend, method: &str) {
    if !browser_ready(test) || !page_built(test) {
        return;
    }
    let name = &format!("jacksboro-{method}-{backend:?}");
    let options = if method == "quadtree-patches" {
        Options::WithPatches
    } else {
        Options::Defaults
    };
    // 2 MiB: small enough that the limit binds (jacksboro's tiles at every texture level
    // would not fit). The projected grids need more (their atlas and screen grid), and
    // SwiftShader draws them slowly (half a second a frame): 4 MiB, a sixth of the frames
    // (the same flight at 5 frames a second) and a quarter of the pixels.
    let db = database(&jacksboro(), options);
    let grid = method == "pgm" || method == "projective-grid";
    let (memory_kib, fps, size) = if grid {
        (4096, 5, [WIDTH / 2, HEIGHT / 2])
    } else {
        (2048, 30, [WIDTH, HEIGHT])
    };
    let flown = fly_both(
        name,
        &db,
        Flight {
            memory_kib,
            fps,
            size,
            settle: true,
            backend,
            method,
        },
    );
    // Every stop but the first (frame 0, before any tile has arrived) drew terrain.
    let total = f64::from(size[0] * size[1]);
    for &k in &flown.frames[1..] {
        let (page, _) = pair(&flown, k);
        let drawn = terrain_pixels(&page) as f64 / total;
        assert!(
            drawn > 0.3,
            "{name} frame {k}: only {drawn:.3} of it is terrain"
        );
    }
    // Once settled, the page draws the native flight's last frame.
    let last = *flown.frames.last().expect("frames");
    let settled = &flown.result["settled"];
    assert_eq!(
        settled["settled"], true,
        "the page never settled: {settled}"
    );
    let (page_last, native_last) = pair(&flown, last);
    let page_settled = open(&flown.page.join("settled.png"), flown.size);
    let share =
        |a, b| terrain_tests::golden::differing_pixels_by(a, b, CHANNEL_TOLERANCE) as f64 / total;
    let (last_share, settled_share) = (
        share(&page_last, &native_last),
        share(&page_settled, &native_last),
    );
    println!(
        "web client, {name}: {} frames in {:.1} s ({}); peak resident {} of {} bytes, wasm heap peak {}; \
         last frame {last}: {:.2}% of the pixels differ from the native frame by more than {CHANNEL_TOLERANCE} \
         ({:.2}% once settled, frame {})",
        flown.result["history"].as_array().map_or(0, Vec::len),
        flown.seconds,
        flown.result["info"]["backend"],
        flown.peak,
        flown.limit,
        flown.heap_peak,
        100.0 * last_share,
        100.0 * settled_share,
        settled["frame"]
    );
    assert!(
        settled_share <= MAX_DIFFERING_SHARE,
        "the settled page differs from the native last frame on {:.2}% of the pixels (at most {:.2}%): see {}",
        100.0 * settled_share,
        100.0 * MAX_DIFFERING_SHARE,
        flown.page.display()
    );
}

/// The least share of the native frame's terrain pixels the page's frame of the same camera
/// has: terrain to the horizon in 16 MiB.
const HORIZON_SHARE: f64 = 0.99;

#[test]
fn the_wasm_client_draws_himalaya_to_the_horizon_in_16_mib_as_the_native_one_does() {
    let test = "the_wasm_client_draws_himalaya_to_the_horizon_in_16_mib_as_the_native_one_does";
    let Some(heights) = kit_file(test, "himalaya_4097/g10g_himalaya_4097.png") else {
        return;
    };
    if !browser_ready(test) || !page_built(test) {
        return;
    }
    let db = database(&heights, Options::Defaults);
    // The default flight at 10 frames a second of flight (the same path and cameras as at
    // 30, a third of the frames) at a quarter of the pixels: SwiftShader draws a few frames
    // a second, and coverage needs no more.
    let flown = fly_both(
        "himalaya",
        &db,
        Flight {
            memory_kib: 16 << 10,
            fps: 10,
            size: [WIDTH / 2, HEIGHT / 2],
            settle: false,
            backend: Backend::WebGpu,
            method: "strip-masks",
        },
    );
    let mut worst = (f64::INFINITY, 0);
    let mut lines = Vec::new();
    for &k in &flown.frames {
        let (page, native) = pair(&flown, k);
        let (p, n) = (terrain_pixels(&page), terrain_pixels(&native));
        if n == 0 {
            continue;
        }
        let share = p as f64 / n as f64;
        lines.push(format!("{k}: {p}/{n}"));
        if share < worst.0 {
            worst = (share, k);
        }
    }
    println!(
        "web client, himalaya in 16 MiB: {} frames in {:.1} s; peak resident {} of {} bytes, wasm heap peak {}; \
         terrain pixels, page against native, at the worst frame {}: {:.4} ({})",
        flown.result["history"].as_array().map_or(0, Vec::len),
        flown.seconds,
        flown.peak,
        flown.limit,
        flown.heap_peak,
        worst.1,
        worst.0,
        lines.join(", ")
    );
    assert!(lines.len() >= 3, "too few frames with terrain: {lines:?}");
    assert!(
        worst.0 >= HORIZON_SHARE,
        "himalaya frame {}: the page has {:.4} of the native frame's terrain pixels (at least {HORIZON_SHARE}): see {}",
        worst.1,
        worst.0,
        flown.page.display()
    );
}

/// On WebGL2, a method that needs what WebGL2 lacks is refused with the reason, and the
/// page fetches nothing for it.
#[test]
fn on_webgl2_a_method_it_cannot_draw_is_refused_with_the_reason() {
    let test = "on_webgl2_a_method_it_cannot_draw_is_refused_with_the_reason";
    if !browser_ready(test) || !page_built(test) {
        return;
    }
    let tmp = tempfile::tempdir().expect("tmp");
    let db = database(&jacksboro(), Options::Defaults);
    let server = serve(&db, tmp.path(), &[]);
    for (method, lacking) in [
        ("geomipmap", "BASE_VERTEX"),
        ("projective-grid", "VERTEX_STORAGE"),
    ] {
        let out = tmp.path().join(method);
        let page = format!(
            "{}/view/client/index.html?method={method}",
            server.base_url()
        );
        let result = drive(
            &[
                "--page",
                &page,
                "--frames",
                "1",
                "--no-webgpu",
                "--timeout-s",
                "60",
            ],
            &out,
        );
        assert_eq!(result["ok"], false, "{method} drew on WebGL2: {result}");
        let said = result["console_errors"].to_string();
        assert!(
            said.contains(&format!("--method {method} needs"))
                && said.contains(lacking)
                && said.contains("strip-masks and reference draw here"),
            "{method}: the page did not say why: {said} ({})",
            result["reason"]
        );
        assert_eq!(
            result["failed_requests"].as_array().map_or(0, Vec::len),
            0,
            "{result}"
        );
    }
}

#[test]
fn the_page_flies_where_the_keys_and_the_mouse_steer_it() {
    let test = "the_page_flies_where_the_keys_and_the_mouse_steer_it";
    if !browser_ready(test) || !page_built(test) {
        return;
    }
    let tmp = tempfile::tempdir().expect("tmp");
    let db = database(&jacksboro(), Options::Defaults);
    let server = serve(&db, tmp.path(), &[]);
    let out = repo().join("tests/out/web_client/steer");
    let _ = std::fs::remove_dir_all(&out);
    let page = format!(
        "{}/view/client/index.html?mode=fly&memory=16MiB",
        server.base_url()
    );
    let result = drive(
        &[
            "--page",
            &page,
            "--frames",
            "30",
            "--steer",
            "--timeout-s",
            "120",
            "--width",
            "480",
            "--height",
            "270",
        ],
        &out,
    );
    assert_eq!(
        result["ok"], true,
        "{}: {}",
        result["reason"], result["console_messages"]
    );
    for key in ["errors", "console_errors", "failed_requests"] {
        assert_eq!(
            result[key].as_array().map_or(0, Vec::len),
            0,
            "{key}: {}",
            result[key]
        );
    }
    let camera = |key: &str| -> Vec<f64> {
        result["steer"][key]
            .as_array()
            .unwrap_or_else(|| panic!("steer.{key}: {}", result["steer"]))
            .iter()
            .map(|v| v.as_f64().expect("number"))
            .collect()
    };
    let (before, after_key, after_drag) =
        (camera("before"), camera("after_key"), camera("after_drag"));
    // It starts looking north (yaw -pi/2 is towards -y, y running south) and W flies forward.
    assert!(
        after_key[1] < before[1] - 1.0,
        "W did not fly north: {before:?} -> {after_key:?}"
    );
    assert!(
        (after_key[0] - before[0]).abs() < 1e-6,
        "W moved sideways: {before:?} -> {after_key:?}"
    );
    // A drag of 200 px to the right turns the view right by 200 x 0.003 rad.
    let turned = (after_drag[3] - after_key[3]).rem_euclid(std::f64::consts::TAU);
    let expected = 200.0 * terrain_client::fly::LOOK_RADIANS_PER_PIXEL;
    assert!(
        (turned - expected).abs() < 0.05,
        "the drag turned the view by {turned} rad, not {expected}"
    );
    // The panel: each setting reaches the client.
    assert_eq!(
        result["steer"]["target_fps"].as_f64(),
        Some(30.0),
        "{}",
        result["steer"]
    );
    assert_eq!(
        result["steer"]["limit_bytes"].as_u64(),
        Some((8u64 << 20) * 9 / 10),
        "{}",
        result["steer"]
    );
    assert!(
        result["steer"]["method"]
            .as_str()
            .is_some_and(|m| m.starts_with("geomipmap")),
        "{}",
        result["steer"]
    );
    let view = image::open(out.join("steer.png"))
        .expect("steer.png")
        .into_rgba8();
    assert!(
        terrain_pixels(&view) > u64::from(480u32 * 270) / 4,
        "the flown view shows little terrain"
    );
}
