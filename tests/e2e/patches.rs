//! The quadtree progressive patches against a real server: the routes, golden images on
//! jacksboro, the guarantee on the Puget Sound and himalaya_4097 sweeps, geomorphing
//! against popping.

use std::time::Duration;
use terrain_client::eval::accuracy::{self, AccuracyArgs};
use terrain_client::eval::session::Session;
use terrain_client::eval::stability::{self, StabilityArgs};
use terrain_client::lod::budget::BudgetMode;
use terrain_client::method::MethodKind;
use terrain_client::render::Camera;
use terrain_client::scene::RenderConfig;
use terrain_tests::data::{jacksboro, kit_file};
use terrain_tests::golden;
use terrain_tests::server::TestServer;

const WIDTH: u32 = 320;
const HEIGHT: u32 = 240;

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime")
}

/// The data kit's `relative` built with the patches into a temporary directory and served;
/// `None` (the test said NOT RUN) without the kit or a GPU.
fn serve_kit_with_patches(test: &str, relative: &str) -> Option<(tempfile::TempDir, TestServer)> {
    let input = kit_file(test, relative)?;
    golden::gpu(test)?;
    let tmp = tempfile::tempdir().expect("tempdir");
    let db =
        terrain_tests::fixtures::database(&input, terrain_tests::fixtures::Options::WithPatches);
    let server = TestServer::start(&db);
    Some((tmp, server))
}

/// The index and every body are served with immutable, content-versioned URLs and strong
/// entity tags; a database without patches answers 404 with the way to build them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_server_serves_the_patches_and_says_when_there_are_none() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = terrain_tests::fixtures::database(
        &jacksboro(),
        terrain_tests::fixtures::Options::WithPatches,
    );
    let server = TestServer::start(&db);
    let client = reqwest::Client::new();
    let get = |path: String| {
        let client = client.clone();
        let url = format!("{}{path}", server.base_url());
        async move { client.get(url).send().await.expect("answer") }
    };
    let manifest = get(terrain_shared::routes::MANIFEST.to_string()).await;
    let manifest = terrain_shared::Manifest::from_json(&manifest.bytes().await.expect("body"))
        .expect("manifest");
    let info = manifest
        .patches
        .clone()
        .expect("the manifest lists the patches");
    let cv = manifest.content_version.clone();
    let index = get(terrain_shared::routes::patch_index(&cv)).await;
    assert_eq!(index.status(), 200);
    assert!(
        index.headers()["cache-control"]
            .to_str()
            .expect("ascii")
            .contains("immutable")
    );
    let index = index.bytes().await.expect("body");
    assert_eq!(
        terrain_shared::manifest::content_hash(&index),
        info.index.hash
    );
    let entries =
        terrain_shared::quadtree::decode_index(&index, manifest.tile_count()).expect("decodes");
    for ((id, _), entry) in manifest.tiles().zip(&entries) {
        let body = get(terrain_shared::routes::patch(&cv, id)).await;
        assert_eq!(body.status(), 200, "{id}");
        assert_eq!(
            body.headers()["etag"].to_str().expect("ascii"),
            format!("\"{}\"", entry.hash_hex())
        );
        assert_eq!(body.bytes().await.expect("bytes").len() as u32, entry.bytes);
    }
    // The same database without patches.
    let plain = terrain_tests::data::build_jacksboro(&tmp.path().join("plain"));
    let server = TestServer::start(&plain.out);
    let cv = &plain.manifest.content_version;
    let refused = client
        .get(format!(
            "{}{}",
            server.base_url(),
            terrain_shared::routes::patch_index(cv)
        ))
        .send()
        .await
        .expect("answer");
    assert_eq!(refused.status(), 404);
    let text = refused.text().await.expect("text");
    assert!(text.contains("--patches"), "{text}");
}

/// Two views of jacksboro, as the other methods' golden images.
fn cameras(extent: [f64; 2]) -> Vec<(&'static str, Camera)> {
    vec![
        (
            "across",
            Camera::looking_at(
                [-0.1 * extent[0], 1.1 * extent[1], 9000.0],
                [0.5 * extent[0], 0.5 * extent[1], 300.0],
            ),
        ),
        (
            "low",
            Camera::new([0.3 * extent[0], 0.7 * extent[1], 900.0], -0.6, -0.25),
        ),
    ]
}

/// Golden images of the patches on jacksboro, each frame within the guarantee against the
/// full-resolution reference drawn in the same session, with morphing on and off.
#[test]
fn quadtree_patches_over_jacksboro_match_their_golden_images() {
    let test = "patches::quadtree_patches_over_jacksboro_match_their_golden_images";
    if golden::gpu(test).is_none() {
        return;
    }
    let db = terrain_tests::fixtures::database(
        &jacksboro(),
        terrain_tests::fixtures::Options::WithPatches,
    );
    let server = TestServer::start(&db);
    runtime().block_on(async {
        let config = RenderConfig {
            budget: BudgetMode::Fixed(u32::MAX),
            ..RenderConfig::default()
        };
        let mut session = Session::open(server.base_url(), None, config, (WIDTH, HEIGHT))
            .await
            .expect("session");
        let extent = session.manifest.extent_m;
        for (view, camera) in cameras(extent) {
            let centre = session.centre();
            assert!(session.settle(centre, &camera, Duration::from_secs(120)).await.expect("loads"));
            let (reference, _) = session.reference(&camera).expect("reference");
            for geomorph in [true, false] {
                let mut render = RenderConfig {
                    method: MethodKind::QuadtreePatches,
                    ..config
                };
                render.lod.geomorph = geomorph;
                assert!(
                    session
                        .prepare(centre, &camera, render, Duration::from_secs(120))
                        .await
                        .expect("patches load")
                );
                let measured = session.measure(&camera, render, &reference, 1.0, 1).expect("measured");
                let m = &measured.measures;
                let name = format!(
                    "jacksboro-quadtree-patches-{view}{}",
                    if geomorph { "" } else { "-no-morph" }
                );
                eprintln!(
                    "{name}: {} triangles, error mean {:.3} / p99 {:.2} / max {:.2} px, {} crack px, {} holes, PSNR {:.1} dB",
                    measured.report.stats.triangles,
                    m.error.mean_px,
                    m.error.p99_px,
                    m.error.max_px,
                    m.crack_pixels,
                    m.hole_pixels,
                    m.psnr_db,
                );
                assert!(measured.report.stats.triangles > 0, "{name}: drew nothing");
                assert!(m.error.terrain_pixels > u64::from(WIDTH * HEIGHT / 8), "{name}: the terrain is in view");
                assert!(m.error.p99_px <= 1.0, "{name}: p99 {} px", m.error.p99_px);
                assert_eq!(m.hole_pixels, 0, "{name}: the flanges leave no hole");
                golden::compare(&name, &measured.capture.color, golden::Match::on(&session.gpu));
            }
        }
        session.close();
    });
}

/// The guarantee (Yusov and Turlapov, section 3.7): at a tolerance of 1 px, on every camera of
/// the sweep, once every patch the frame asked for has arrived, no more pixels are past 1 px
/// than the reference's own (the measure's floor) plus one in ten thousand, and the flanges
/// leave at most a pixel in ten thousand open (where a flange's edge meets a neighbour's
/// between two of its samples).
///
/// The allowance is for single pixels whose depth is nowhere near their eight neighbours',
/// which all lie on the true surface (seen over himalaya_4097 from 198 km up: a point
/// kilometres above the ground, in the reference's frame as in the patches', and the same
/// with the flanges off). The likely cause is the rasterizer's depth of a triangle seen
/// edge-on, taken at a pixel centre its snapped edges cover and the exact triangle does
/// not. Such a pixel is one measure among 200,000 but can be several pixels off, so the
/// maximum is printed, and checked past the allowance: the largest error once the allowed
/// count of largest ones is set aside stays within max(1 px, the reference's own maximum).
fn guarantee_holds_over(test: &str, relative: &str) {
    let Some((tmp, server)) = serve_kit_with_patches(test, relative) else {
        return;
    };
    let mut args = AccuracyArgs {
        max_errors_px: vec![1.0],
        repeats: 1,
        popping_frames: 0,
        ..AccuracyArgs::new(server.base_url(), tmp.path().join("acc"))
    };
    args.variants.methods = vec![MethodKind::QuadtreePatches];
    let report = runtime().block_on(accuracy::run(&args)).expect("sweep");
    assert_eq!(report.rows.len(), 8);
    let mut failures = Vec::new();
    for (row, floor) in report.rows.iter().zip(&report.reference_errors) {
        let m = &row.measured;
        let e = &m.measures.error;
        println!(
            "camera {}: p99 {:.3} px, max {:.3} px (the reference's own max {:.3}), {} above {} px (the reference: {}), mean {:.4} px, {} triangles, {} holes in {} terrain pixels{}",
            row.camera,
            e.p99_px,
            e.max_px,
            floor.max_px,
            e.above_threshold,
            report.threshold_px,
            floor.above_threshold,
            e.mean_px,
            m.report.stats.triangles,
            m.measures.hole_pixels,
            e.terrain_pixels,
            if row.settled { "" } else { "; NOT SETTLED" },
        );
        assert!(
            m.report.stats.triangles > 0,
            "camera {}: drew nothing",
            row.camera
        );
        if !row.settled {
            failures.push(format!(
                "camera {}: measured before the scene settled: {}",
                row.camera,
                row.unsettled.as_deref().unwrap_or("?")
            ));
        }
        let allowance = e.terrain_pixels / 10_000;
        if e.above_threshold > floor.above_threshold + allowance {
            failures.push(format!(
                "camera {}: {} pixels above {} px, more than the reference's own {} plus one in ten thousand ({allowance})",
                row.camera, e.above_threshold, report.threshold_px, floor.above_threshold
            ));
        }
        if e.max_after_px(allowance) > report.threshold_px.max(floor.max_px) {
            failures.push(format!(
                "camera {}: {:.3} px once the {allowance} largest errors are set aside, max {:.3} px (the reference's own {:.3})",
                row.camera,
                e.max_after_px(allowance),
                e.max_px,
                floor.max_px
            ));
        }
        if m.measures.hole_pixels * 10_000 > e.terrain_pixels {
            failures.push(format!(
                "camera {}: {} holes",
                row.camera, m.measures.hole_pixels
            ));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

#[test]
fn quadtree_patches_keep_every_pixel_within_a_pixel_over_puget_sound() {
    guarantee_holds_over(
        "patches::quadtree_patches_keep_every_pixel_within_a_pixel_over_puget_sound",
        "puget_sound_1k/ps_height_1k.png",
    );
}

#[test]
fn quadtree_patches_keep_every_pixel_within_a_pixel_over_himalaya() {
    let test = "patches::quadtree_patches_keep_every_pixel_within_a_pixel_over_himalaya";
    if !terrain_tests::tier::full(test) {
        return;
    }
    guarantee_holds_over(test, "himalaya_4097/g10g_himalaya_4097.png");
}

/// Popping (done when 4): on the sweep's approach over Puget Sound, at the tolerances where
/// a patch switch is larger than what every step changes anyway (8 and 16 px), the largest
/// step stands out of its neighbours at least three times less with geomorphing and
/// texture morphing on than off, in colour and in depth.
#[test]
fn geomorphing_takes_the_jump_out_of_a_level_switch_over_puget_sound() {
    let test = "patches::geomorphing_takes_the_jump_out_of_a_level_switch";
    let Some((tmp, server)) = serve_kit_with_patches(test, "puget_sound_1k/ps_height_1k.png")
    else {
        return;
    };
    let run = |morph: bool| {
        let mut args = AccuracyArgs {
            max_errors_px: vec![8.0, 16.0],
            cameras: 1,
            repeats: 1,
            ..AccuracyArgs::new(
                server.base_url(),
                tmp.path().join(if morph { "on" } else { "off" }),
            )
        };
        args.error.no_morph = !morph;
        args.variants.methods = vec![MethodKind::QuadtreePatches];
        let report = runtime().block_on(accuracy::run(&args)).expect("sweep");
        report
            .summaries
            .iter()
            .map(|s| {
                (
                    s.config.knob.to_string(),
                    s.popping.expect("popping measured"),
                )
            })
            .collect::<Vec<_>>()
    };
    let (on, off) = (run(true), run(false));
    assert_eq!(on.len(), 2);
    for ((knob, on), (_, off)) in on.iter().zip(&off) {
        println!(
            "{knob}: jump colour {:.3} on / {:.3} off, depth {:.4} % on / {:.4} % off; mean colour {:.3} / {:.3}",
            on.colour_jump,
            off.colour_jump,
            on.depth_jump_pct,
            off.depth_jump_pct,
            on.colour_mean,
            off.colour_mean
        );
        assert!(
            on.colour_jump * 3.0 < off.colour_jump && on.depth_jump_pct * 3.0 < off.depth_jump_pct,
            "{knob}: {on:?} with morphing, {off:?} without"
        );
    }
}

/// The stability matrix's scenarios of any terrain over Puget Sound, whose patches need
/// more than the 64 MiB limit: no failure, and what the scene counts and holds (CPU and
/// GPU) stays within the limit in every frame, patches included.
#[test]
fn quadtree_patches_stay_within_memory_in_the_stability_matrix() {
    let test = "patches::quadtree_patches_stay_within_memory_in_the_stability_matrix";
    let Some((tmp, server)) = serve_kit_with_patches(test, "puget_sound_1k/ps_height_1k.png")
    else {
        return;
    };
    let mut args = StabilityArgs {
        frames: 10,
        ..StabilityArgs::new(server.base_url(), tmp.path().join("stability"))
    };
    args.variants.methods = vec![MethodKind::QuadtreePatches];
    let report = runtime().block_on(stability::run(&args)).expect("matrix");
    crate::accuracy::check_matrix(&report);
    let generic = stability::SCENARIOS
        .iter()
        .filter(|s| s.dataset.is_none())
        .count();
    assert_eq!(report.runs.len(), generic);
}
