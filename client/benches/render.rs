//! `cargo bench -p terrain-client --bench render`: the renderer's frame time against a
//! floor, on this machine's adapter.
//!
//! A synthetic 12 x 12 grid of 129-sample tiles (rolling hills plus ridges, so importance and
//! budget sharing have something to rank) is drawn by the strip-mask method from a fixed
//! oblique camera, with fixed global budgets from 25k to 3M triangles.
//!
//! **The floor**, measured in the same run and interleaved with it: the same triangles as
//! one static mesh (the drawn tiles' strips, translated into one 1537 x 1537 grid of the same
//! samples, joined by primitive restarts) drawn in one call, through the same renderer, the
//! same shaders and the same target. Every figure is printed as a ratio to it: what the
//! per-tile work (uniforms, bindings, one draw per tile, the paper's planar shadows) costs
//! beyond the triangles themselves.
//!
//! Frames are timed as a run queues them: `BLOCK` frames back to back, then a wait for the
//! GPU to finish the last one (the renderer itself never waits for a frame); the time per
//! frame is the block's time over `BLOCK`, and a row reports the median of `BLOCKS` blocks.
//! Without an adapter it says NOT RUN and exits 0 (with REQUIRE_GPU=1 it fails).

mod common;

use common::cpu_model;
use std::sync::Arc;
use std::time::{Duration, Instant};
use terrain_client::lod::plan::{Candidate, Draw, Layout, LodSettings, plan_frame};
use terrain_client::lod::strips::MaskSet;
use terrain_client::method::strip_masks::StripMasks;
use terrain_client::method::{CrackFiller, MethodConfig, MethodKind};
use terrain_client::render::{Camera, Gpu, IndexSet, Offscreen, Renderer, TileExtras};
use terrain_shared::{Heights, TileId};

const SIDE: u32 = 12;
const N: u32 = 129;
const SPACING: f64 = 30.0;
/// Frames timed back to back per block, and blocks per row.
const BLOCK: usize = 4;
const BLOCKS: usize = 5;
const BUDGETS: [u32; 8] = [
    25_000, 50_000, 100_000, 200_000, 400_000, 800_000, 1_600_000, 3_000_000,
];

fn height(x: f64, y: f64) -> f64 {
    300.0 * (x / 2100.0).sin() * (y / 1700.0).cos()
        + 120.0 * ((x + 2.0 * y) / 430.0).sin().abs()
        + 40.0 * (x / 97.0).sin() * (y / 83.0).sin()
        + 600.0
}

/// Height codes (decimetres) of `side` x `side` samples from sample `(x0, y0)`.
fn codes(x0: u32, y0: u32, side: u32) -> Vec<i32> {
    let mut codes = Vec::with_capacity((side * side) as usize);
    for r in 0..side {
        for c in 0..side {
            let x = f64::from(x0 + c) * SPACING;
            let y = f64::from(y0 + r) * SPACING;
            codes.push((height(x, y) * 10.0).round() as i32);
        }
    }
    codes
}

fn heights(codes: Vec<i32>, side: u32) -> Arc<Heights> {
    Arc::new(Heights {
        width: side as u16,
        height: side as u16,
        quantum_m: 0.1,
        offset_m: 0.0,
        codes,
    })
}

fn texture() -> image::RgbaImage {
    image::RgbaImage::from_fn(64, 64, |x, y| {
        image::Rgba([90 + (x * 2) as u8, 140, 70 + (y * 2) as u8, 255])
    })
}

/// The floor's renderer: the whole grid as one tile of `SIDE * (N - 1) + 1` samples.
struct Floor {
    renderer: Renderer,
    side: u32,
}

impl Floor {
    fn new(gpu: &Gpu, format: wgpu::TextureFormat) -> Floor {
        let side = SIDE * (N - 1) + 1;
        let cells = f64::from(side - 1);
        let layout = Layout {
            tile_size: side,
            spacing_m: [SPACING, SPACING],
            extent_m: [cells * SPACING; 2],
        };
        let mut renderer = Renderer::new(gpu, format, layout);
        let id = TileId::new(0, 0);
        renderer
            .tiles
            .upload_tile(id, heights(codes(0, 0, side), side));
        renderer.tiles.upload_texture(id, 0, &[texture()]);
        Floor { renderer, side }
    }

    /// The drawn tiles' strips as one strip over the floor's grid, joined by restarts.
    fn mesh(&self, gpu: &Gpu, masks: &MaskSet, draws: &[Draw]) -> IndexSet {
        let mut indices = Vec::new();
        let mut triangles = 0;
        for d in draws {
            let (x0, y0) = (d.id.x * (N - 1), d.id.y * (N - 1));
            if !indices.is_empty() {
                indices.push(u32::MAX);
            }
            indices.extend(
                masks
                    .strip(d.level)
                    .iter()
                    .map(|&i| (y0 + i / N) * self.side + x0 + i % N),
            );
            triangles += masks.triangle_count(d.level);
        }
        IndexSet::new(gpu, &indices, triangles)
    }
}

/// Waits for every frame queued so far (the bench's own wait, off the renderer's path).
fn drain(gpu: &Gpu) {
    gpu.device
        .poll(wgpu::PollType::Wait {
            submission_index: None,
            timeout: Some(Duration::from_secs(60)),
        })
        .expect("the GPU finished within a minute");
}

/// Milliseconds per frame of `frame` run `BLOCK` times back to back, median of `BLOCKS`
/// blocks, interleaved with the same for `other` so that both see the same machine.
fn interleaved(
    gpu: &Gpu,
    mut frame: impl FnMut() -> u64,
    mut other: impl FnMut() -> u64,
) -> ((f64, u64), (f64, u64)) {
    let block = |f: &mut dyn FnMut() -> u64| {
        let started = Instant::now();
        let mut triangles = 0;
        for _ in 0..BLOCK {
            triangles = f();
        }
        drain(gpu);
        (
            started.elapsed().as_secs_f64() * 1e3 / BLOCK as f64,
            triangles,
        )
    };
    // Warm-up: buffers grown, strips built, pipelines compiled.
    block(&mut frame);
    block(&mut other);
    let (mut a, mut b) = (Vec::new(), Vec::new());
    let (mut ta, mut tb) = (0, 0);
    for _ in 0..BLOCKS {
        let (ms, t) = block(&mut frame);
        a.push(ms);
        ta = t;
        let (ms, t) = block(&mut other);
        b.push(ms);
        tb = t;
    }
    ((median(&mut a), ta), (median(&mut b), tb))
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    println!(
        "machine: {} ({} cores)",
        cpu_model(),
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    let gpu = match Gpu::headless() {
        Ok(gpu) => gpu,
        Err(e) => {
            assert!(!terrain_client::render::gpu::gpu_required(), "{e}");
            println!("NOT RUN: no graphics adapter: {e}");
            return;
        }
    };
    println!("adapter: {}", gpu.description());
    let cells = f64::from(N - 1);
    let layout = Layout {
        tile_size: N,
        spacing_m: [SPACING, SPACING],
        extent_m: [f64::from(SIDE) * cells * SPACING; 2],
    };
    let masks = Arc::new(MaskSet::new(N));
    let format = terrain_client::render::offscreen::OFFSCREEN_FORMAT;
    let mut renderer = Renderer::new(&gpu, format, layout);
    let mut floor = Floor::new(&gpu, format);
    let mut method = StripMasks::new(
        &MethodConfig {
            kind: MethodKind::StripMasks,
            lod: LodSettings::default(),
            filler: CrackFiller::None,
            texture_blocks: false,
            grid: Default::default(),
        },
        N,
    );
    let mut candidates = Vec::new();
    for ty in 0..SIDE {
        for tx in 0..SIDE {
            let id = TileId::new(tx, ty);
            let codes = codes(tx * (N - 1), ty * (N - 1), N);
            let (lo, hi) = (
                *codes.iter().min().expect("samples"),
                *codes.iter().max().expect("samples"),
            );
            renderer.tiles.upload_tile(id, heights(codes, N));
            renderer.tiles.upload_texture(id, 0, &[texture()]);
            candidates.push(Candidate {
                id,
                min_m: f64::from(lo) / 10.0,
                max_m: f64::from(hi) / 10.0,
                roughness_m: f64::from(hi - lo) / 100.0,
                // Synthetic tiles have no measured mask errors: no error cap applies.
                error_minima_m: &[],
                // One grid, one level: no side borders a tile of another level.
                seams: [false; 4],
            });
        }
    }
    let extent = f64::from(SIDE) * cells * SPACING;
    let camera = Camera::looking_at(
        [extent * 0.5, extent * 1.02, 2600.0],
        [extent * 0.5, extent * 0.45, 500.0],
    );
    println!(
        "\n{BLOCK} frames back to back per block, median of {BLOCKS} blocks, after a warm-up \
         block; the floor's blocks interleaved with the renderer's"
    );
    // RENDER_BENCH_QUICK=1: the first table's 200k and 3M rows only.
    let quick = std::env::var("RENDER_BENCH_QUICK").is_ok_and(|v| v == "1");
    let configs = [
        (960, 540, CrackFiller::None),
        (960, 540, CrackFiller::PlanarShadowPaper),
        (1920, 1080, CrackFiller::None),
    ];
    for (width, height, filler) in configs.into_iter().take(if quick { 1 } else { 3 }) {
        let target = Offscreen::new(&gpu, width, height);
        println!(
            "\n{width}x{height}, crack filler {} (the floor draws the surface's triangles only)\n",
            filler.name()
        );
        println!(
            "| global budget | tiles drawn | triangles drawn | frame (ms) | floor (ms) | ratio to the floor | floor triangles/s (M) |"
        );
        println!("|---:|---:|---:|---:|---:|---:|---:|");
        for budget in BUDGETS
            .into_iter()
            .filter(|b| !quick || [200_000, 3_000_000].contains(b))
        {
            let plan = plan_frame(
                &camera,
                [width, height],
                &layout,
                &candidates,
                budget,
                &masks,
                &LodSettings {
                    cap_at_needed: false,
                    ..LodSettings::default()
                },
            );
            let mut draws = plan.draws.clone();
            let mesh = floor.mesh(&gpu, &masks, &draws);
            let floor_tile = [(TileId::new(0, 0), TileExtras::default())];
            let ((ms, triangles), (floor_ms, floor_triangles)) = interleaved(
                &gpu,
                || {
                    let mut frame = renderer.begin_frame(&target.view, &camera);
                    // No memory limit: every index set has room.
                    method.draw_levels(
                        &mut frame,
                        &layout,
                        &candidates,
                        &mut draws,
                        filler,
                        u64::MAX,
                    );
                    let stats = frame.finish();
                    stats.triangles
                },
                || {
                    let mut frame = floor.renderer.begin_frame(&target.view, &camera);
                    let slots = frame.prepare_tiles(&floor_tile);
                    let mut pass = frame.last_pass();
                    pass.bind_tile(slots[0].expect("resident"));
                    pass.draw(&mesh);
                    drop(pass);
                    frame.finish();
                    u64::from(mesh.triangles)
                },
            );
            assert_eq!(
                triangles, floor_triangles,
                "the floor draws the same triangles"
            );
            println!(
                "| {budget} | {} | {triangles} | {ms:.2} | {floor_ms:.2} | {:.2}x | {:.2} |",
                draws.len(),
                ms / floor_ms,
                triangles as f64 / (floor_ms / 1e3) / 1e6,
            );
        }
    }
}
