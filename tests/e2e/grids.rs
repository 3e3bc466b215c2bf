//! The projected grids (persistent grid mapping and the error-bounded projective grid)
//! against a real server: golden images on jacksboro, the projective grid's guarantee on
//! the Puget Sound flight, and their bytes inside the memory limit.

use std::time::Duration;
use terrain_client::eval::accuracy::{self, AccuracyArgs};
use terrain_client::eval::session::Session;
use terrain_client::lod::budget::BudgetMode;
use terrain_client::method::{GridSettings, MethodKind};
use terrain_client::render::Camera;
use terrain_client::scene::RenderConfig;
use terrain_tests::data::{build_jacksboro, kit_file};
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

/// Two views of jacksboro: across the ridges from the south-west, and low over them
/// looking at the horizon (the auxiliary camera's case).
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
            "horizon",
            Camera::new([0.3 * extent[0], 0.7 * extent[1], 900.0], -0.6, 0.0),
        ),
    ]
}

/// Golden images of both grids (lavapipe renders them bit for bit the same on every run;
/// the tolerance of [`golden::compare`] leaves room for other adapters), each frame close to
/// the full-resolution reference drawn in the same session, and the projective grid's
/// pixels past the threshold all ray cast.
#[test]
fn projected_grids_over_jacksboro_match_their_golden_images() {
    let test = "grids::projected_grids_over_jacksboro_match_their_golden_images";
    if golden::gpu(test).is_none() {
        return;
    }
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_jacksboro(tmp.path());
    let server = TestServer::start(&report.out);
    runtime().block_on(async {
        let config = RenderConfig {
            budget: BudgetMode::Fixed(u32::MAX),
            grid: GridSettings {
                size: [128, 96],
                ..GridSettings::default()
            },
            ..RenderConfig::default()
        };
        let mut session = Session::open(server.base_url(), None, config, (WIDTH, HEIGHT))
            .await
            .expect("session");
        let extent = session.manifest.extent_m;
        for (view, camera) in cameras(extent) {
            let centre = session.centre();
            assert!(
                session
                    .settle(centre, &camera, Duration::from_secs(120))
                    .await
                    .expect("loads")
            );
            let (reference, _) = session.reference(&camera).expect("reference");
            for method in [MethodKind::Pgm, MethodKind::ProjectiveGrid] {
                let measured = session
                    .measure(&camera, RenderConfig { method, ..config }, &reference, 1.0, 1)
                    .expect("measured");
                let m = &measured.measures;
                let name = format!("jacksboro-{}-{view}", method.name());
                eprintln!(
                    "{name}: {} triangles, error mean {:.3} / p99 {:.2} / max {:.2} px, {} crack px, {:?}",
                    measured.report.stats.triangles,
                    m.error.mean_px,
                    m.error.p99_px,
                    m.error.max_px,
                    m.crack_pixels,
                    measured.method_measures
                );
                assert_eq!(measured.report.stats.triangles, 2 * 127 * 95);
                assert!(
                    m.error.terrain_pixels > u64::from(WIDTH * HEIGHT / 4),
                    "{name}: the terrain is in view"
                );
                // Within a few percent of the reference's terrain: no part of the view is
                // left unsampled (the auxiliary camera's job).
                assert!(
                    m.crack_pixels * 50 <= m.reference_terrain_pixels,
                    "{name}: {} of {} terrain pixels missing",
                    m.crack_pixels,
                    m.reference_terrain_pixels
                );
                if method == MethodKind::ProjectiveGrid {
                    let error = measured.method_measure("error_pixels_pct").expect("counted");
                    let cast = measured.method_measure("ray_cast_pct").expect("counted");
                    assert!(cast >= error, "{name}: every pixel past the threshold is ray cast");
                    assert!(
                        m.error.p99_px <= 1.0,
                        "{name}: p99 {} px with ray casting",
                        m.error.p99_px
                    );
                }
                golden::compare(&name, &measured.capture.color, golden::Match::on(&session.gpu));
            }
        }
        session.close();
    });
}

/// The guarantee of the error-bounded projective grid (Löffler et al.): with ray casting in
/// every pixel whose error passes 1 px, the screen-space error of every pixel (the maximum,
/// not only the 99th percentile) stays within 1 px on every camera of the Puget Sound
/// flight, with at most a pixel in ten thousand a hole; the rays are walked in at most 20%
/// of the pixels of every camera, and the grid's triangles are at most twice the oracle's
/// over the cameras. Without ray casting the same grid leaves pixels past 1 px (so the rays
/// are what holds it: the deliberate break). The shares of pixels past the threshold,
/// marked and ray cast are printed; `docs/evaluation.md` reports them per grid size.
#[test]
fn the_projective_grid_with_ray_casting_keeps_every_pixel_within_a_pixel_over_puget_sound() {
    let Some(png) = kit_file(
        "projective grid over puget",
        "puget_sound_1k/ps_height_1k.png",
    ) else {
        return;
    };
    let Some(_) = golden::gpu("grids::the_projective_grid_with_ray_casting_keeps_every_pixel")
    else {
        return;
    };
    let db = terrain_tests::fixtures::database(&png, terrain_tests::fixtures::Options::Defaults);
    let server = TestServer::start(&db);
    hold_the_projective_grid_guarantee(&server);
}

/// The same guarantee over jacksboro (the repository's own DEM): every pixel within 1 px,
/// the rays in at most 20% of the pixels, the triangles at most twice the oracle's.
#[test]
fn the_projective_grid_with_ray_casting_keeps_every_pixel_within_a_pixel_over_jacksboro() {
    let Some(_) =
        golden::gpu("grids::the_projective_grid_with_ray_casting_keeps_every_pixel_jacksboro")
    else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_jacksboro(tmp.path());
    let server = TestServer::start(&report.out);
    hold_the_projective_grid_guarantee(&server);
}

/// The accuracy sweep's default flight (8 cameras, 640x360) with the projective grid at
/// 256x144 and 1 px, with and without ray casting; see the tests above.
fn hold_the_projective_grid_guarantee(server: &TestServer) {
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut worst_without = 0.0f64;
    for ray_casting in [true, false] {
        let mut args = AccuracyArgs {
            grids: vec![(256, 144)],
            repeats: 1,
            popping_frames: 0,
            no_ray_casting: !ray_casting,
            ..AccuracyArgs::new(
                server.base_url(),
                tmp.path().join(format!("acc-{ray_casting}")),
            )
        };
        args.variants.methods = vec![MethodKind::ProjectiveGrid];
        let report = runtime().block_on(accuracy::run(&args)).expect("sweep");
        assert_eq!(report.rows.len(), 8);
        if ray_casting {
            let [summary] = report.summaries.as_slice() else {
                panic!("one configuration: {:?}", report.summaries.len());
            };
            println!(
                "{:.0} triangles a frame, the oracle {:.0}: {:.2}x",
                summary.triangles, summary.oracle_triangles, summary.used_over_oracle
            );
            assert!(
                summary.used_over_oracle > 0.0 && summary.used_over_oracle <= 2.0,
                "{:.2}x the oracle's triangles",
                summary.used_over_oracle
            );
            // The summary's guarantee table: every camera holds it, within twice the oracle.
            let guarantees = accuracy::guarantees(&report);
            let [g] = guarantees.as_slice() else {
                panic!("one method at its setting: {guarantees:?}");
            };
            assert_eq!(g.cameras_held, 8, "{g:?}");
            assert!(g.over_oracle <= 2.0, "{g:?}");
        }
        for row in &report.rows {
            let m = &row.measured;
            let e = &m.measures.error;
            println!(
                "ray casting {ray_casting}, camera {}: p99 {:.3} px, max {:.3} px, mean {:.4} px, {} holes, {} cracks; error pixels {:?} %, marked {:?} %, ray cast {:?} %",
                row.camera,
                e.p99_px,
                e.max_px,
                e.mean_px,
                m.measures.hole_pixels,
                m.measures.crack_pixels,
                m.method_measure("error_pixels_pct"),
                m.method_measure("marked_pct"),
                m.method_measure("ray_cast_pct"),
            );
            if ray_casting {
                if m.measures.hole_pixels > 0 {
                    let path = std::env::temp_dir().join(format!("grid-holes-{}.png", row.camera));
                    let _ = m.capture.color.save(&path);
                    eprintln!("the frame is at {}", path.display());
                }
                assert!(e.p99_px <= 1.0, "camera {}: {e:?}", row.camera);
                // The bound is on every pixel, not on most: the largest error too.
                assert!(e.max_px <= 1.0, "camera {}: max {e:?}", row.camera);
                // A ray may slip between two triangles where it meets a cell's edge
                // exactly: a pixel in ten thousand at most.
                assert!(
                    m.measures.hole_pixels * 10_000 <= e.terrain_pixels,
                    "camera {}: {} holes",
                    row.camera,
                    m.measures.hole_pixels
                );
                let error = m.method_measure("error_pixels_pct").expect("counted");
                let marked = m.method_measure("marked_pct").expect("counted");
                let cast = m.method_measure("ray_cast_pct").expect("counted");
                assert!(error > 0.0 && marked >= error, "camera {}", row.camera);
                assert!(
                    cast <= 20.0,
                    "camera {}: rays walked in {cast:.1}% of the pixels",
                    row.camera
                );
            } else {
                worst_without = worst_without.max(e.max_px);
            }
        }
    }
    assert!(
        worst_without > 1.0,
        "without ray casting some pixel passes 1 px (worst {worst_without})"
    );
}

/// Memory below what the grid itself needs is the grid's own weak spot; above it, the
/// atlas, the grid, the error buffer and every tile stay within the limit.
#[test]
fn projected_grids_hold_no_more_than_the_limit() {
    let test = "grids::projected_grids_hold_no_more_than_the_limit";
    if golden::gpu(test).is_none() {
        return;
    }
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_jacksboro(tmp.path());
    let server = TestServer::start(&report.out);
    runtime().block_on(async {
        let limit = 4 << 20;
        for method in [MethodKind::Pgm, MethodKind::ProjectiveGrid] {
            let config = RenderConfig {
                method,
                ..RenderConfig::default()
            };
            let mut session =
                Session::open(server.base_url(), Some(limit), config, (WIDTH, HEIGHT))
                    .await
                    .expect("session");
            let extent = session.manifest.extent_m;
            let mut worst = 0u64;
            // Along the diagonal, looking ahead: tiles come and go.
            for k in 0..24 {
                let t = f64::from(k) / 23.0;
                let position = [t * extent[0], t * extent[1], 2500.0];
                let camera = Camera::new(position, 0.8, -0.4);
                session.update(position).await.expect("update");
                session.draw(&camera);
                let held = session.scene.cpu_bytes() + session.scene.gpu_bytes();
                worst = worst.max(held).max(session.scene.resident_bytes());
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            eprintln!(
                "{}: held at most {:.2} MiB of {:.2} MiB",
                method.name(),
                worst as f64 / (1 << 20) as f64,
                limit as f64 / (1 << 20) as f64
            );
            assert!(worst > limit / 4, "{}: tiles arrived", method.name());
            assert!(
                worst <= limit,
                "{}: {worst} bytes over {limit}",
                method.name()
            );
            session.close();
        }
    });
}
