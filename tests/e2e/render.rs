//! Rendering with a real adapter (lavapipe in CI) over the jacksboro fixture, served by a
//! real server and fetched over HTTP: golden images of fixed cameras, crack filling counted,
//! and a rendered flight's records.

use std::path::Path;
use terrain_client::flight::{FlightArgs, RenderArgs, StreamArgs, fly};
use terrain_client::http_client::TileClient;
use terrain_client::lod::needed::suffix_minima;
use terrain_client::lod::plan::{Candidate, Draw, Layout, LodSettings, plan_frame};
use terrain_client::lod::strips::MaskSet;
use terrain_client::memory::MemorySize;
use terrain_client::method::strip_masks::StripMasks;
use terrain_client::method::{CrackFiller, MethodConfig, MethodKind};
use terrain_client::render::{Camera, Gpu, GpuError, Offscreen, Renderer, SampleStore, TileStore};
use terrain_shared::{Manifest, TileId};
use terrain_tests::data::build_jacksboro;
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

/// Every tile of jacksboro's level 0 (the full-resolution grid these tests draw the methods
/// on), fetched from a real server: heights, mask errors and all texture levels.
struct Terrain {
    manifest: Manifest,
    tiles: Vec<Fetched>,
}

struct Fetched {
    id: TileId,
    heights: terrain_shared::Heights,
    /// Per mask level, its error (from the tile blob).
    mask_errors_m: Vec<f32>,
    textures: Vec<image::RgbaImage>,
}

fn fetch_jacksboro(dir: &Path) -> Terrain {
    let report = build_jacksboro(dir);
    let server = TestServer::start(&report.out);
    runtime().block_on(async {
        let client = TileClient::new(server.base_url()).expect("client");
        let manifest = client.manifest().await.expect("manifest");
        let mut tiles = Vec::new();
        for (id, _) in manifest.tiles().filter(|(id, _)| id.level == 0) {
            let tile = client.tile(&manifest, id).await.expect("tile");
            let mut textures = Vec::new();
            for (level, blob) in tile.texture.iter().enumerate() {
                let bytes = client
                    .texture(&manifest, id, level as u32, Some(blob))
                    .await
                    .expect("texture");
                textures.push(
                    image::load_from_memory(&bytes)
                        .expect("texture decodes")
                        .into_rgba8(),
                );
            }
            tiles.push(Fetched {
                id,
                heights: tile.heights,
                mask_errors_m: tile.mask_errors_m,
                textures,
            });
        }
        assert_eq!(tiles.len(), manifest.levels[0].tiles.len());
        Terrain { manifest, tiles }
    })
}

fn layout(manifest: &Manifest) -> Layout {
    Layout::of(manifest)
}

/// The candidates of `terrain`'s tiles, with the error minima `minima` (one per tile).
fn candidates<'a>(terrain: &Terrain, minima: &'a [Vec<f32>]) -> Vec<Candidate<'a>> {
    terrain
        .tiles
        .iter()
        .zip(minima)
        .map(|(t, m)| {
            let record = terrain.manifest.tile(t.id).expect("in grid");
            Candidate::new(t.id, record, m)
        })
        .collect()
}

/// The renderer and the strip-mask method drawing given plans of jacksboro's tiles.
struct Painter<'a> {
    gpu: &'a Gpu,
    terrain: &'a Terrain,
    renderer: Renderer,
    method: StripMasks,
}

impl<'a> Painter<'a> {
    /// Every tile resident, its texture given by `textures` (all levels: see
    /// [`Painter::finest`]).
    fn new(
        gpu: &'a Gpu,
        terrain: &'a Terrain,
        textures: &dyn Fn(&mut TileStore, TileId, &[image::RgbaImage]),
    ) -> Painter<'a> {
        let format = terrain_client::render::offscreen::OFFSCREEN_FORMAT;
        let mut renderer = Renderer::new(gpu, format, layout(&terrain.manifest));
        for tile in &terrain.tiles {
            renderer
                .tiles
                .upload_tile(tile.id, std::sync::Arc::new(tile.heights.clone()));
            textures(&mut renderer.tiles, tile.id, &tile.textures);
        }
        let method = StripMasks::new(
            &MethodConfig {
                kind: MethodKind::StripMasks,
                lod: LodSettings::default(),
                filler: CrackFiller::None,
                texture_blocks: false,
                grid: Default::default(),
            },
            terrain.manifest.tile_size,
        );
        Painter {
            gpu,
            terrain,
            renderer,
            method,
        }
    }

    /// Every tile at its finest texture.
    fn finest(gpu: &'a Gpu, terrain: &'a Terrain) -> Painter<'a> {
        Painter::new(gpu, terrain, &|tiles, id, levels| {
            tiles.upload_texture(id, levels.len() as u32 - 1, levels);
        })
    }

    fn draw(&mut self, camera: &Camera, draws: &[Draw], filler: CrackFiller) -> image::RgbaImage {
        let target = Offscreen::new(self.gpu, WIDTH, HEIGHT);
        let minima = vec![Vec::new(); self.terrain.tiles.len()];
        let tiles = candidates(self.terrain, &minima);
        let layout = layout(&self.terrain.manifest);
        let mut frame = self.renderer.begin_frame(&target.view, camera);
        let mut draws = draws.to_vec();
        // No memory limit here: every index set has room.
        self.method
            .draw_levels(&mut frame, &layout, &tiles, &mut draws, filler, u64::MAX);
        frame.finish();
        target.read(self.gpu).expect("read back")
    }
}

/// The fixed cameras of the golden images, over the 29.9 x 31.8 km fixture (heights 236 to
/// 1076 m).
fn cameras() -> Vec<(&'static str, Camera)> {
    vec![
        (
            "jacksboro-overview",
            Camera::looking_at([-4000.0, 38000.0, 9000.0], [15000.0, 15000.0, 500.0]),
        ),
        (
            "jacksboro-low-north",
            Camera::looking_at([15000.0, 33000.0, 1500.0], [15000.0, 12000.0, 500.0]),
        ),
        (
            "jacksboro-close",
            Camera::looking_at([6000.0, 6000.0, 2600.0], [12000.0, 11000.0, 600.0]),
        ),
    ]
}

#[test]
fn fixed_cameras_over_jacksboro_match_their_golden_images() {
    let Some(gpu) = golden::gpu("render::fixed_cameras_over_jacksboro_match_their_golden_images")
    else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let terrain = fetch_jacksboro(tmp.path());
    let masks = std::sync::Arc::new(MaskSet::new(terrain.manifest.tile_size));
    let mut painter = Painter::finest(&gpu, &terrain);
    let minima: Vec<Vec<f32>> = terrain
        .tiles
        .iter()
        .map(|t| suffix_minima(&t.mask_errors_m))
        .collect();
    let tiles = candidates(&terrain, &minima);
    for (name, camera) in cameras() {
        let plan = golden_plan(&terrain, &tiles, &masks, &camera);
        assert!(!plan.draws.is_empty(), "{name}: the terrain is in view");
        assert!(
            plan.triangles <= 60_000,
            "{name}: {} triangles",
            plan.triangles
        );
        let image = painter.draw(&camera, &plan.draws, CrackFiller::PlanarShadow);
        golden::compare(name, &image, golden::Match::on(&gpu));
    }
}

/// What `camera` draws of `tiles` at a fixed budget of 60k triangles (golden images must not
/// depend on the machine's speed), every tile by its share alone: the renderer is under
/// test, not the error cap.
fn golden_plan(
    terrain: &Terrain,
    tiles: &[Candidate<'_>],
    masks: &std::sync::Arc<MaskSet>,
    camera: &Camera,
) -> terrain_client::lod::plan::FramePlan {
    plan_frame(
        camera,
        [WIDTH, HEIGHT],
        &layout(&terrain.manifest),
        tiles,
        60_000,
        masks,
        &LodSettings {
            cap_at_needed: false,
            ..LodSettings::default()
        },
    )
}

/// The first golden camera and the tiles it draws at a 60k budget, every tile by its
/// share alone (no error cap).
fn overview_plan(terrain: &Terrain) -> (Camera, Vec<Draw>) {
    let masks = std::sync::Arc::new(MaskSet::new(terrain.manifest.tile_size));
    let minima = vec![Vec::new(); terrain.tiles.len()];
    let tiles = candidates(terrain, &minima);
    let (_, camera) = cameras().remove(0);
    let plan = golden_plan(terrain, &tiles, &masks, &camera);
    (camera, plan.draws)
}

/// The sample arena (one GPU buffer of every drawn tile's 16-bit codes) grows when a frame
/// draws more tiles, and is compacted as the pool of slots shrinks back, one slot a frame:
/// through both, each tile still draws its own samples, pixel for pixel as a renderer that
/// uploads them afresh, and the arena holds exactly the slots in use.
#[test]
fn the_sample_arena_keeps_every_tiles_samples_as_it_grows_and_is_compacted() {
    let test = "render::the_sample_arena_keeps_every_tiles_samples_as_it_grows_and_is_compacted";
    let Some(gpu) = golden::gpu(test) else {
        return;
    };
    arena_grows_and_compacts(&gpu);
}

/// The same with the arena in a texture, as on WebGL2 (rows of words: slots cross rows,
/// and compaction copies them between rows).
#[test]
fn the_sample_arena_in_a_texture_keeps_every_tiles_samples_as_it_grows_and_is_compacted() {
    let test = "render::the_sample_arena_in_a_texture_keeps_every_tiles_samples_as_it_grows_and_is_compacted";
    let Some(gpu) = golden::gpu(test) else {
        return;
    };
    arena_grows_and_compacts(&gpu.with_samples(SampleStore::Texture));
}

/// The arena's samples read from a texture (WebGL2's path, here on the native adapter) draw
/// every golden camera, with each crack filler, pixel for pixel as from the storage buffer;
/// the texture holds the slots' bytes and less than a row more.
#[test]
fn samples_read_from_a_texture_draw_what_the_storage_buffer_draws() {
    let test = "render::samples_read_from_a_texture_draw_what_the_storage_buffer_draws";
    let Some(gpu) = golden::gpu(test) else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let terrain = fetch_jacksboro(tmp.path());
    let textured = gpu.clone().with_samples(SampleStore::Texture);
    let mut buffer = Painter::finest(&gpu, &terrain);
    let mut texture = Painter::finest(&textured, &terrain);
    let masks = std::sync::Arc::new(MaskSet::new(terrain.manifest.tile_size));
    let minima = vec![Vec::new(); terrain.tiles.len()];
    let tiles = candidates(&terrain, &minima);
    let sky = buffer.draw(&cameras()[0].1, &[], CrackFiller::None);
    for (name, camera) in cameras() {
        let plan = golden_plan(&terrain, &tiles, &masks, &camera);
        for filler in [
            CrackFiller::PlanarShadow,
            CrackFiller::PlanarShadowPaper,
            CrackFiller::Skirts,
        ] {
            let expected = buffer.draw(&camera, &plan.draws, filler);
            let got = texture.draw(&camera, &plan.draws, filler);
            assert!(
                golden::differing_pixels(&expected, &sky) > u64::from(WIDTH * HEIGHT) / 10,
                "{name}: terrain in view"
            );
            assert_eq!(
                golden::differing_pixels(&expected, &got),
                0,
                "{name}, {filler:?}: the texture's samples draw otherwise"
            );
        }
        let (b, t) = (
            buffer.renderer.tiles.residency(),
            texture.renderer.tiles.residency(),
        );
        assert_eq!(b.sample_buffers, t.sample_buffers, "{name}");
        let row = 4 * u64::from(terrain_shaders::SAMPLE_TEXTURE_WIDTH);
        assert!(
            t.sample_bytes >= b.sample_bytes && t.sample_bytes < b.sample_bytes + row,
            "{name}: the texture holds {} bytes for {} of slots",
            t.sample_bytes,
            b.sample_bytes
        );
    }
}

fn arena_grows_and_compacts(gpu: &Gpu) {
    let gpu = gpu.clone();
    let tmp = tempfile::tempdir().expect("tempdir");
    let terrain = fetch_jacksboro(tmp.path());
    let (camera, all) = overview_plan(&terrain);
    // Every other tile of the frame: the pool shrinks to these, one slot a frame.
    let some: Vec<Draw> = all.iter().step_by(2).cloned().collect();
    assert!(
        all.len() >= 4 && some.len() < all.len(),
        "{} tiles drawn",
        all.len()
    );
    let mut painter = Painter::finest(&gpu, &terrain);
    let first = painter.draw(&camera, &all, CrackFiller::None);
    assert_eq!(
        painter.renderer.tiles.residency().sample_buffers,
        all.len() as u64,
        "one slot per tile drawn"
    );
    let mut shrunk = first.clone();
    for _ in 0..all.len() {
        shrunk = painter.draw(&camera, &some, CrackFiller::None);
    }
    assert_eq!(
        painter.renderer.tiles.residency().sample_buffers,
        some.len() as u64,
        "the arena was compacted to the slots in use"
    );
    let fresh = Painter::finest(&gpu, &terrain).draw(&camera, &some, CrackFiller::None);
    assert_eq!(
        golden::differing_pixels(&fresh, &shrunk),
        0,
        "after the compactions the kept tiles draw their own samples"
    );
    let again = painter.draw(&camera, &all, CrackFiller::None);
    assert_eq!(
        golden::differing_pixels(&first, &again),
        0,
        "grown again, every tile draws its own samples"
    );
}

/// A frame drawing more tiles than the sample arena holds (a device with small buffers)
/// draws those it has room for, in order, and leaves the rest out: no panic, no tile drawn
/// with another's samples.
#[test]
fn a_frame_with_more_tiles_than_the_arena_holds_draws_those_it_has_room_for() {
    let test = "render::a_frame_with_more_tiles_than_the_arena_holds_draws_those_it_has_room_for";
    let Some(gpu) = golden::gpu(test) else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let terrain = fetch_jacksboro(tmp.path());
    let (camera, all) = overview_plan(&terrain);
    assert!(all.len() > 3, "{} tiles drawn", all.len());
    let mut painter = Painter::finest(&gpu, &terrain);
    painter.renderer.tiles.limit_sample_slots(3);
    let limited = painter.draw(&camera, &all, CrackFiller::None);
    assert_eq!(painter.renderer.tiles.residency().sample_buffers, 3);
    let first_three = Painter::finest(&gpu, &terrain).draw(&camera, &all[..3], CrackFiller::None);
    assert_eq!(
        golden::differing_pixels(&first_three, &limited),
        0,
        "the three tiles with room are drawn, the others left out"
    );
    let everything = Painter::finest(&gpu, &terrain).draw(&camera, &all, CrackFiller::None);
    assert!(golden::differing_pixels(&everything, &limited) > 0);
}

#[test]
fn the_adapter_is_vulkan_when_a_gpu_is_required() {
    let test = "render::the_adapter_is_vulkan_when_a_gpu_is_required";
    // Asking for Vulkan gives a Vulkan adapter or an error, never another backend: what
    // `REQUIRE_GPU=1` relies on so that nothing renders on the GL fallback.
    match Gpu::headless_with(true) {
        Ok(gpu) => {
            let description = gpu.description();
            eprintln!("adapter: {description}");
            assert_eq!(
                gpu.adapter.get_info().backend,
                terrain_client::render::gpu::Backend::Vulkan,
                "{description}"
            );
        }
        Err(e) => {
            assert!(
                matches!(e, GpuError::NoAdapter(_) | GpuError::NotVulkan(_)),
                "{e}"
            );
            assert!(
                !terrain_client::render::gpu::gpu_required(),
                "{test}: REQUIRE_GPU=1 but {e}"
            );
            eprintln!("NOT RUN: {test} needs a Vulkan adapter: {e}");
        }
    }
}

/// Pixels where `reference` shows terrain and `frame` shows the sky: holes in the surface.
fn crack_pixels(reference: &image::RgbaImage, frame: &image::RgbaImage, sky: [u8; 4]) -> u64 {
    reference
        .pixels()
        .zip(frame.pixels())
        .filter(|(r, f)| r.0 != sky && f.0 == sky)
        .count() as u64
}

/// Sky pixels whose four neighbours are all terrain.
fn enclosed_sky_pixels(frame: &image::RgbaImage, sky: [u8; 4]) -> u64 {
    let (w, h) = frame.dimensions();
    let mut count = 0;
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            if frame.get_pixel(x, y).0 == sky
                && [(x - 1, y), (x + 1, y), (x, y - 1), (x, y + 1)]
                    .iter()
                    .all(|&(a, b)| frame.get_pixel(a, b).0 != sky)
            {
                count += 1;
            }
        }
    }
    count
}

#[test]
fn planar_shadows_and_skirts_leave_fewer_sky_pixels_between_tiles_of_different_levels() {
    let test = "render::planar_shadows_and_skirts_leave_fewer_sky_pixels_between_tiles_of_different_levels";
    let Some(gpu) = golden::gpu(test) else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let terrain = fetch_jacksboro(tmp.path());
    let mut painter = Painter::finest(&gpu, &terrain);
    let sky = painter
        .draw(&cameras()[0].1, &[], CrackFiller::None)
        .get_pixel(0, 0)
        .0;
    let mut totals = [0u64; 4];
    // The golden cameras, but the low one looks north from inside the terrain: from
    // outside, the DEM's southern edge is in view, where a coarse mask's surface ends
    // elsewhere on screen than the full-resolution one (a silhouette, not a crack between
    // tiles, and nothing a filler is for).
    let mut crack_cameras = cameras();
    crack_cameras[1] = (
        "jacksboro-low-north-inside",
        Camera::looking_at([15000.0, 28000.0, 1500.0], [15000.0, 8000.0, 500.0]),
    );
    for (name, camera) in crack_cameras {
        let all: Vec<TileId> = terrain.tiles.iter().map(|t| t.id).collect();
        // The reference: every tile at the finest mask, no filler: no crack anywhere.
        let finest: Vec<Draw> = all.iter().map(|&id| Draw { id, level: 0 }).collect();
        let reference = painter.draw(&camera, &finest, CrackFiller::None);
        // A checkerboard of the finest and a coarse mask: every shared edge is a crack.
        let mixed: Vec<Draw> = all
            .iter()
            .map(|&id| Draw {
                id,
                level: if (id.x + id.y) % 2 == 0 { 0 } else { 31 },
            })
            .collect();
        let mut counts = [0u64; 4];
        for (k, filler) in [
            CrackFiller::None,
            CrackFiller::Skirts,
            CrackFiller::PlanarShadow,
            CrackFiller::PlanarShadowPaper,
        ]
        .into_iter()
        .enumerate()
        {
            let frame = painter.draw(&camera, &mixed, filler);
            counts[k] = crack_pixels(&reference, &frame, sky);
            if name == "jacksboro-overview" && filler != CrackFiller::Skirts {
                golden::compare(
                    &format!("jacksboro-cracks-{}", filler.name()),
                    &frame,
                    golden::Match::on(&gpu),
                );
            }
            if filler == CrackFiller::PlanarShadow {
                // Every shared side of the checkerboard changes mask: the bands close every
                // crack, so no sky pixel is left inside the terrain.
                assert_eq!(
                    enclosed_sky_pixels(&frame, sky),
                    0,
                    "{name}: the planar shadow leaves no hole"
                );
            }
        }
        eprintln!(
            "{name}: sky pixels where the reference has terrain: none {}, skirts {}, planar-shadow {}, planar-shadow-paper {}",
            counts[0], counts[1], counts[2], counts[3]
        );
        // Neighbouring tiles at the same level meet vertex for vertex: with no filler, no
        // sky pixel lies inside the terrain (all four neighbours terrain), where a hairline
        // crack along a shared border would show.
        assert_eq!(
            enclosed_sky_pixels(&reference, sky),
            0,
            "{name}: tiles at the same level leave no hairline crack"
        );
        let mixed_none = painter.draw(&camera, &mixed, CrackFiller::None);
        if name == "jacksboro-overview" {
            assert!(
                enclosed_sky_pixels(&mixed_none, sky) > 0,
                "the enclosed-pixel count does see cracks between different levels"
            );
        }
        for k in 0..4 {
            totals[k] += counts[k];
        }
    }
    eprintln!(
        "all cameras: none {}, skirts {}, planar-shadow {}, planar-shadow-paper {}",
        totals[0], totals[1], totals[2], totals[3]
    );
    assert!(
        totals[0] > 100,
        "the mixed levels do open cracks: {}",
        totals[0]
    );
    assert!(
        totals[2] * 4 < totals[0],
        "planar shadows fill at least three quarters of the cracks: {} against {}",
        totals[2],
        totals[0]
    );
    assert!(
        totals[1] * 4 < totals[0],
        "skirts fill at least three quarters of the cracks: {} against {}",
        totals[1],
        totals[0]
    );
    assert!(
        totals[3] * 4 < totals[0],
        "the paper's planar shadows fill at least three quarters of the cracks: {} against {}",
        totals[3],
        totals[0]
    );
}

/// Pixels of `filled` that differ from `bare` (the same frame without a filler) outside the
/// span of `reference`'s terrain in their column (the full-resolution frame, which has no
/// crack): the filler showing past the terrain's silhouette, where no crack can be.
fn filler_past_the_terrain(
    reference: &image::RgbaImage,
    bare: &image::RgbaImage,
    filled: &image::RgbaImage,
    sky: [u8; 4],
) -> u64 {
    let (w, h) = bare.dimensions();
    let mut count = 0;
    for x in 0..w {
        let terrain: Vec<u32> = (0..h)
            .filter(|&y| reference.get_pixel(x, y).0 != sky)
            .collect();
        let (top, bottom) = (terrain.first().copied(), terrain.last().copied());
        count += (0..h)
            .filter(|&y| {
                let outside = match (top, bottom) {
                    (Some(top), Some(bottom)) => y < top || y > bottom,
                    _ => true,
                };
                outside && bare.get_pixel(x, y) != filled.get_pixel(x, y)
            })
            .count() as u64;
    }
    count
}

#[test]
fn a_tile_on_the_dems_border_draws_no_planar_shadow_past_the_border() {
    let test = "render::a_tile_on_the_dems_border_draws_no_planar_shadow_past_the_border";
    let Some(gpu) = golden::gpu(test) else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let terrain = fetch_jacksboro(tmp.path());
    let mut painter = Painter::finest(&gpu, &terrain);
    let sky = painter
        .draw(&cameras()[0].1, &[], CrackFiller::None)
        .get_pixel(0, 0)
        .0;
    let extent = terrain.manifest.extent_m;
    // A checkerboard of the finest and a coarse mask (a crack along every shared side),
    // seen from outside the terrain: from beyond each corner, looking back at it over the
    // two borders that meet there. A filler pixel outside the full-resolution frame's
    // terrain in its column shows past the border (or past the far skyline).
    let mixed: Vec<Draw> = terrain
        .tiles
        .iter()
        .map(|t| Draw {
            id: t.id,
            level: if (t.id.x + t.id.y) % 2 == 0 { 0 } else { 31 },
        })
        .collect();
    let mut paper_total = 0;
    let corners = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)];
    // High above the terrain (heights 236 to 1076 m), and low, under its highest points,
    // where the open side of the terrain faces the camera.
    for ((cx, cy), height) in corners.into_iter().flat_map(|c| [(c, 2500.0), (c, 700.0)]) {
        let corner = [cx * extent[0], cy * extent[1]];
        // Away from the terrain, east or west and south or north.
        let away = [2.0 * cx - 1.0, 2.0 * cy - 1.0];
        // The low camera nearer, looking further in.
        let (out, inside) = if height > 1000.0 {
            ([6000.0, 7000.0], 6000.0)
        } else {
            ([2500.0, 3000.0], 8000.0)
        };
        let camera = Camera::looking_at(
            [
                corner[0] + out[0] * away[0],
                corner[1] + out[1] * away[1],
                height,
            ],
            [
                corner[0] - inside * away[0],
                corner[1] - inside * away[1],
                400.0,
            ],
        );
        let bare = painter.draw(&camera, &mixed, CrackFiller::None);
        let finest: Vec<Draw> = mixed.iter().map(|d| Draw { level: 0, ..*d }).collect();
        let reference = painter.draw(&camera, &finest, CrackFiller::None);
        let terrain_pixels = bare.pixels().filter(|p| p.0 != sky).count();
        assert!(
            terrain_pixels > (WIDTH * HEIGHT / 40) as usize,
            "corner {corner:?} from {height} m is in view: {terrain_pixels} pixels"
        );
        let banded = painter.draw(&camera, &mixed, CrackFiller::PlanarShadow);
        let paper = painter.draw(&camera, &mixed, CrackFiller::PlanarShadowPaper);
        let past = filler_past_the_terrain(&reference, &bare, &banded, sky);
        let paper_past = filler_past_the_terrain(&reference, &bare, &paper, sky);
        let filled = bare
            .pixels()
            .zip(banded.pixels())
            .filter(|(a, b)| a != b)
            .count();
        eprintln!(
            "corner {corner:?} from {height} m: the planar shadow shows in {filled} pixels, {past} past the terrain's silhouette; the paper's, {paper_past}"
        );
        if height > 1000.0 {
            assert!(
                filled > 0,
                "corner {corner:?} from {height} m: the planar shadow fills the cracks in view"
            );
        }
        assert_eq!(
            past, 0,
            "corner {corner:?} from {height} m: the planar shadow shows past the border"
        );
        paper_total += paper_past;
    }
    // The measure sees a shadow past the border where there is one: the paper's, a quad
    // under each border tile, does show there.
    assert!(
        paper_total > 0,
        "the paper's planar shadow shows past the border: {paper_total} pixels"
    );
}

#[test]
fn a_rendered_flight_draws_within_its_budgets_and_writes_frames_csv_and_charts() {
    let test =
        "render::a_rendered_flight_draws_within_its_budgets_and_writes_frames_csv_and_charts";
    if golden::gpu(test).is_none() {
        return;
    }
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_jacksboro(tmp.path());
    let server = TestServer::start(&report.out);
    let expected: u64 = report
        .manifest
        .tiles()
        .map(|(_, t)| terrain_client::flight::expected_tile_bytes(&report.manifest, t, 1).total())
        .sum();
    // Room for every tile of every level at its coarsest texture and a little more: finer
    // texture levels must fit in what is left.
    let memory = expected * 12 / 10 * 100 / 90;
    let mut stream = StreamArgs::new(server.base_url(), Some(MemorySize(memory)));
    stream.concurrency = 4;
    let args = FlightArgs {
        fps: 10.0,
        frame_every: 40,
        render: RenderArgs {
            size: (160, 120),
            fixed_budget: Some(20_000),
            ..RenderArgs::default()
        },
        ..FlightArgs::new(stream, tmp.path().join("flight"))
    };
    let summary = runtime().block_on(fly(&args)).expect("flight");
    let text = std::fs::read_to_string(&summary.csv).expect("csv");
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let column = |name: &str| header.iter().position(|h| *h == name).expect(name);
    let mut finer_textures = false;
    let mut drew = false;
    let (mut some_tile_coarser, mut some_tile_finer) = (false, false);
    let tile_size = report.manifest.tile_size;
    for line in lines {
        let row: Vec<&str> = line.split(',').collect();
        let int = |name: &str| row[column(name)].parse::<u64>().expect(name);
        // The GPU's share is part of what the limit counts, and the limit holds.
        assert!(
            int("gpu_bytes") <= int("resident_bytes")
                && int("resident_bytes") <= int("memory_limit_bytes"),
            "frame {}: {} GPU bytes, {} counted, limit {}",
            row[0],
            int("gpu_bytes"),
            int("resident_bytes"),
            int("memory_limit_bytes")
        );
        assert!(
            int("resident_bytes") <= int("memory_limit_bytes"),
            "frame {}: {} > {}",
            row[0],
            int("resident_bytes"),
            int("memory_limit_bytes")
        );
        assert_eq!(int("global_budget"), 20_000);
        let visible = int("visible_tiles");
        // Every visible tile draws at least its coarsest mask (2 triangles); beyond that
        // the budget holds.
        assert!(
            int("triangles") <= 20_000.max(2 * visible),
            "frame {}: {} triangles",
            row[0],
            int("triangles")
        );
        let histogram = row[column("mask_levels")];
        let tiles_in_histogram: u64 = histogram
            .split(';')
            .filter(|s| !s.is_empty())
            .map(|pair| {
                pair.split(':')
                    .nth(1)
                    .expect("level:count")
                    .parse::<u64>()
                    .expect("count")
            })
            .sum();
        assert_eq!(tiles_in_histogram, visible, "frame {}", row[0]);
        // What a frame needs is a judgement per tile: neither every tile at full
        // resolution nor every tile at its coarsest mask, over the flight.
        let needed = int("triangles_needed");
        let full = u64::from(terrain_shared::mask::triangle_count(tile_size, 0));
        let coarsest = u64::from(terrain_shared::mask::triangle_count(
            tile_size,
            tile_size - 2,
        ));
        some_tile_coarser |= needed < full * visible;
        some_tile_finer |= needed > coarsest * visible;
        assert!(row[column("frame_ms")].parse::<f64>().expect("frame_ms") > 0.0);
        drew |= int("triangles") > 0;
        finer_textures |= int("texture_budget_bytes") > 0;
    }
    assert!(drew, "the flight drew triangles");
    assert!(
        some_tile_coarser,
        "some frame needs less than full resolution everywhere"
    );
    assert!(
        some_tile_finer,
        "some frame needs more than the coarsest mask everywhere"
    );
    assert!(finer_textures, "the limit left room for finer textures");
    assert!(
        summary.frames_written.len() >= 3,
        "{:?}",
        summary.frames_written
    );
    for frame in &summary.frames_written {
        let image = image::open(frame).expect("a PNG frame").into_rgba8();
        assert_eq!(image.dimensions(), (160, 120));
    }
    // The last frame, over the centre with every tile resident, shows terrain, not sky.
    let last = image::open(summary.frames_written.last().expect("frames"))
        .expect("png")
        .into_rgba8();
    let sky = last.get_pixel(0, 0).0;
    let terrain = last.pixels().filter(|p| p.0 != sky).count();
    assert!(terrain > 160 * 120 / 3, "{terrain} terrain pixels");
    assert_eq!(summary.charts.len(), 2);
    assert!(summary.charts[1].ends_with("render.png") && summary.charts[1].exists());
}

#[test]
fn textures_refined_and_coarsened_on_the_gpu_render_as_if_uploaded_whole() {
    let test = "render::textures_refined_and_coarsened_on_the_gpu_render_as_if_uploaded_whole";
    let Some(gpu) = golden::gpu(test) else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let terrain = fetch_jacksboro(tmp.path());
    let camera = cameras()[2].1;
    let draws: Vec<Draw> = terrain
        .tiles
        .iter()
        .map(|t| Draw { id: t.id, level: 4 })
        .collect();
    let render_with = |levels_of: &dyn Fn(&mut TileStore, TileId, &[image::RgbaImage])| {
        Painter::new(&gpu, &terrain, levels_of).draw(&camera, &draws, CrackFiller::PlanarShadow)
    };
    // Every level at once, against the coarsest then each finer level added on the GPU.
    let whole = render_with(&|r, id, levels| {
        r.upload_texture(id, levels.len() as u32 - 1, levels);
    });
    let refined = render_with(&|r, id, levels| {
        r.upload_texture(id, 0, &levels[..1]);
        for (level, image) in levels.iter().enumerate().skip(1) {
            assert!(
                r.refine_texture(id, level as u32, image),
                "{id} level {level}"
            );
            assert_eq!(r.texture_level(id), Some(level as u32));
        }
        // A level that does not follow the finest held is refused.
        assert!(!r.refine_texture(id, levels.len() as u32 + 1, &levels[0]));
    });
    assert_eq!(golden::differing_pixels(&whole, &refined), 0);
    // The two coarsest levels uploaded, against all of them cut down to two on the GPU.
    let two = render_with(&|r, id, levels| {
        r.upload_texture(id, 1, &levels[..2]);
    });
    let coarsened = render_with(&|r, id, levels| {
        r.upload_texture(id, levels.len() as u32 - 1, levels);
        r.coarsen_texture(id, 2);
        assert_eq!(r.texture_level(id), Some(1));
    });
    assert_eq!(golden::differing_pixels(&two, &coarsened), 0);
    assert!(
        golden::differing_pixels(&whole, &two) > 0,
        "the levels do show"
    );
}

/// Pixels of `capture` showing a point past the terrain's edge (more than `tolerance_m`
/// outside `[0, extent]` east or south).
fn pixels_past_the_edge(
    capture: &terrain_client::eval::frame::Capture,
    extent_m: [f64; 2],
    tolerance_m: f64,
) -> u64 {
    capture
        .points
        .iter()
        .flatten()
        .filter(|p| {
            p[0] < -tolerance_m
                || p[1] < -tolerance_m
                || p[0] > extent_m[0] + tolerance_m
                || p[1] > extent_m[1] + tolerance_m
        })
        .count() as u64
}

#[test]
fn the_padding_of_the_last_tiles_is_never_drawn_whatever_the_filler() {
    use terrain_client::eval::session::Session;
    use terrain_client::lod::budget::BudgetMode;
    use terrain_client::scene::RenderConfig;
    let test = "render::the_padding_of_the_last_tiles_is_never_drawn_whatever_the_filler";
    if golden::gpu(test).is_none() {
        return;
    }
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_jacksboro(tmp.path());
    let server = TestServer::start(&report.out);
    runtime().block_on(async {
        let config = RenderConfig {
            // Golden images must not depend on the machine's speed.
            budget: BudgetMode::Fixed(60_000),
            ..RenderConfig::default()
        };
        let mut session = Session::open(server.base_url(), None, config, (WIDTH, HEIGHT))
            .await
            .expect("session");
        let manifest = session.manifest.clone();
        let extent = manifest.extent_m;
        // The last column and row of tiles are padded: the grid spans more than the DEM.
        let cells = f64::from(manifest.tile_size - 1);
        let grid = manifest.grid(0);
        assert!(f64::from(grid.columns) * cells * manifest.spacing_m[0] > extent[0]);
        assert!(f64::from(grid.rows) * cells * manifest.spacing_m[1] > extent[1]);
        // From beyond the south-east corner, looking back at it.
        let camera = Camera::looking_at(
            [extent[0] + 6000.0, extent[1] + 7000.0, 3500.0],
            [extent[0] - 6000.0, extent[1] - 6000.0, 400.0],
        );
        let tolerance = 0.5 * manifest.spacing_m[0].min(manifest.spacing_m[1]);
        // Level 0 alone, the golden images' single resolution, then the whole pyramid (the
        // scene's default: the far side of the corner is drawn from coarser levels, whose
        // last tiles are padded too).
        for levels in [false, true] {
            session.scene.use_levels(levels);
            let centre = session.centre();
            assert!(
                session
                    .settle(centre, &camera, std::time::Duration::from_secs(120))
                    .await
                    .expect("loads")
            );
            for filler in [
                CrackFiller::PlanarShadow,
                CrackFiller::Skirts,
                CrackFiller::None,
            ] {
                let (capture, report) = session
                    .capture(&camera, RenderConfig { filler, ..config })
                    .expect("capture");
                let past = pixels_past_the_edge(&capture, extent, tolerance);
                let terrain = capture.terrain_pixels();
                let coarser = report.plan.draws.iter().filter(|d| d.id.level > 0).count();
                let name = format!("jacksboro-corner-{}", filler.name());
                eprintln!(
                    "{} ({}): {terrain} terrain pixels, {past} past the edge, {coarser} of {} tiles drawn above level 0",
                    filler.name(),
                    if levels { "every level" } else { "level 0" },
                    report.plan.draws.len()
                );
                assert!(
                    terrain > u64::from(WIDTH * HEIGHT / 10),
                    "the corner is in view: {terrain} pixels"
                );
                assert_eq!(
                    past,
                    0,
                    "{}: terrain drawn past the DEM's edge",
                    filler.name()
                );
                if levels {
                    assert!(coarser > 0, "{}: the far side is drawn coarser", filler.name());
                    if let Some(share) = golden::differing_share(&name, &capture.color) {
                        eprintln!(
                            "{name} with every level: {:.2}% of the pixels differ from level 0's golden image",
                            100.0 * share
                        );
                    }
                } else {
                    assert_eq!(coarser, 0, "{}: level 0 alone", filler.name());
                    golden::compare(&name, &capture.color, golden::Match::on(&session.gpu));
                }
            }
        }
        session.close();
    });
}
