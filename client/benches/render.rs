//! `cargo bench -p terrain-client --bench render`: triangles per second on this machine's
//! adapter. A synthetic 8 x 8 grid of 129-sample tiles (rolling hills plus ridges, so
//! importance and budget sharing have something to rank) is drawn from a fixed oblique
//! camera, with fixed global budgets from 25k to 800k triangles: at 960 x 540 with the
//! planar shadow and without a filler, and at 320 x 180 without (where fill costs least and
//! the rate is closest to the adapter's vertex throughput). The baseline, measured in the same run, is the same frame with no tile drawn
//! (clear, uniforms, submission and the wait for the GPU): the marginal rate subtracts it.
//! Without an adapter it says NOT RUN and exits 0 (with REQUIRE_GPU=1 it fails).

mod common;

use common::{Stats, cpu_model};
use std::sync::Arc;
use std::time::Instant;
use terrain_client::lod::plan::{Candidate, Layout, LodSettings, plan_frame};
use terrain_client::lod::strips::MaskSet;
use terrain_client::method::strip_masks::StripMasks;
use terrain_client::method::{CrackFiller, MethodConfig, MethodKind};
use terrain_client::render::{Camera, Gpu, Offscreen, Renderer};
use terrain_shared::{Heights, TileId};

const SIDE: u32 = 8;
const N: u32 = 129;
const SPACING: f64 = 30.0;
const FRAMES: usize = 15;

fn height(x: f64, y: f64) -> f64 {
    300.0 * (x / 2100.0).sin() * (y / 1700.0).cos()
        + 120.0 * ((x + 2.0 * y) / 430.0).sin().abs()
        + 40.0 * (x / 97.0).sin() * (y / 83.0).sin()
        + 600.0
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
            let mut codes = Vec::with_capacity((N * N) as usize);
            for r in 0..N {
                for c in 0..N {
                    let x = (f64::from(tx) * cells + f64::from(c)) * SPACING;
                    let y = (f64::from(ty) * cells + f64::from(r)) * SPACING;
                    codes.push((height(x, y) * 10.0).round() as i32);
                }
            }
            let (lo, hi) = (
                *codes.iter().min().expect("samples"),
                *codes.iter().max().expect("samples"),
            );
            let heights = Heights {
                width: N as u16,
                height: N as u16,
                quantum_m: 0.1,
                offset_m: 0.0,
                codes,
            };
            renderer.tiles.upload_tile(id, std::sync::Arc::new(heights));
            let texture = image::RgbaImage::from_fn(64, 64, |x, y| {
                image::Rgba([90 + (x * 2) as u8, 140, 70 + (y * 2) as u8, 255])
            });
            renderer.tiles.upload_texture(id, 0, &[texture]);
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
    for (width, height, filler) in [
        (960, 540, CrackFiller::PlanarShadow),
        (960, 540, CrackFiller::None),
        (320, 180, CrackFiller::None),
    ] {
        table(
            &gpu,
            &mut renderer,
            &mut method,
            &layout,
            &masks,
            &candidates,
            &camera,
            width,
            height,
            filler,
        );
    }
}

/// One table: frame times and triangle rates for growing budgets at one size and filler.
#[allow(clippy::too_many_arguments)]
fn table(
    gpu: &Gpu,
    renderer: &mut Renderer,
    method: &mut StripMasks,
    layout: &Layout,
    masks: &MaskSet,
    candidates: &[Candidate],
    camera: &Camera,
    width: u32,
    height: u32,
    filler: CrackFiller,
) {
    let target = Offscreen::new(gpu, width, height);
    println!(
        "\n{FRAMES} frames per row after 3 warm-up frames, {width}x{height}, crack filler {}; times in ms\n",
        filler.name()
    );
    println!(
        "| global budget | tiles drawn | triangles drawn | median frame (ms) | p99 (ms) | triangles/s (M) | marginal triangles/s (M) |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|");
    let mut empty_ms = 0.0;
    for budget in [0u32, 25_000, 50_000, 100_000, 200_000, 400_000, 800_000] {
        let plan = plan_frame(
            camera,
            [width, height],
            layout,
            candidates,
            budget,
            masks,
            &LodSettings {
                cap_at_needed: false,
                ..LodSettings::default()
            },
        );
        let draws = if budget == 0 {
            Vec::new()
        } else {
            plan.draws.clone()
        };
        let mut samples = Vec::with_capacity(FRAMES);
        let mut triangles = 0;
        for frame in 0..FRAMES + 3 {
            let started = Instant::now();
            let mut recording = renderer.begin_frame(&target.view, camera);
            method.draw_levels(&mut recording, layout, candidates, &draws, filler);
            let stats = recording.finish();
            let ns = started.elapsed().as_nanos() as u64;
            triangles = stats.triangles + stats.filler_triangles;
            if frame >= 3 {
                samples.push(ns);
            }
        }
        let stats = Stats::of(&mut samples);
        let ms = stats.median / 1000.0;
        if budget == 0 {
            empty_ms = ms;
            println!(
                "| baseline: nothing drawn | 0 | 0 | {ms:.2} | {:.2} | - | - |",
                stats.p99 / 1000.0
            );
            continue;
        }
        let rate = triangles as f64 / (ms / 1e3) / 1e6;
        let marginal = triangles as f64 / ((ms - empty_ms).max(1e-6) / 1e3) / 1e6;
        println!(
            "| {budget} | {} | {triangles} | {ms:.2} | {:.2} | {rate:.2} | {marginal:.2} |",
            draws.len(),
            stats.p99 / 1000.0
        );
    }
}
