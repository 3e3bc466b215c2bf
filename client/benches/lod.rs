//! LOD benchmark: CPU time per frame of choosing every visible tile's mask (importance,
//! greedy budget sharing, mask selection), against a floor measured in the same run.
//!
//! ```text
//! cargo bench -p terrain-client --bench lod
//! ```
//!
//! 4096 visible tiles (a 64x64 grid, as in benches/pager.rs) of 129^2 samples at 10 m, so
//! 1280 m a tile; bounding-box heights of 0 to 1500 m and roughness of 0 to 40 m drawn once
//! per tile. The viewpoint circles the grid's middle at 2 km altitude, moving 20 m a frame.
//! Each frame's global budget is 4 M triangles (about 1000 per tile, an eighth of a full
//! tile on average). Each frame times [`importance_into`] + [`share_into`] (which selects
//! every mask) and, as the baseline, one pass computing the tiles' distances to the
//! viewpoint: the least any importance must do. The same run times GeoMipMaps' selection
//! for the same tiles (each tile's level within 1 px, then its four stitches). The target is under 0.5 ms a frame.

mod common;
use common::{Random, Stats, cpu_model};

use std::hint::black_box;
use std::time::Instant;
use terrain_client::lod::budget::{Allocation, share_into};
use terrain_client::lod::importance::{DEFAULT_ALPHA, HeightMeasure, TileView, importance_into};
use terrain_client::lod::needed::{ErrorProjection, coarsest_level_within, suffix_minima};
use terrain_client::lod::strips::MaskSet;
use terrain_client::method::geomipmap::stitching::Stitch;

const SIDE: u32 = 64;
const TILE_SIZE: u32 = 129;
const TILE_M: f64 = 1280.0;
const FRAMES: usize = 5_000;
const GLOBAL_BUDGET: u32 = 4 << 20;
const ALTITUDE_M: f64 = 2_000.0;
const SPEED_M_PER_FRAME: f64 = 20.0;
const TARGET_US: f64 = 500.0;

fn main() {
    println!(
        "machine: {} ({} cores); one thread",
        cpu_model(),
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    let tiles = (SIDE * SIDE) as usize;
    let mut random = Random(0x10d);
    let centres: Vec<[f64; 2]> = (0..tiles)
        .map(|i| {
            let (x, y) = ((i as u32 % SIDE) as f64, (i as u32 / SIDE) as f64);
            [(x + 0.5) * TILE_M, (y + 0.5) * TILE_M]
        })
        .collect();
    let heights: Vec<(f64, f64)> = (0..tiles)
        .map(|_| (random.unit() * 1500.0, random.unit() * 40.0))
        .collect();
    let masks = MaskSet::new(TILE_SIZE);
    // Per-level maximum errors: up to twice the roughness at the coarsest level.
    // Their suffix minima are computed once per tile, as the scene does from the manifest.
    let errors: Vec<Vec<f32>> = heights
        .iter()
        .map(|&(_, roughness)| {
            suffix_minima(
                &(0..masks.level_count())
                    .map(|l| {
                        (2.0 * roughness * f64::from(l) / f64::from(masks.level_count())) as f32
                    })
                    .collect::<Vec<f32>>(),
            )
        })
        .collect();
    let mut caps: Vec<u32> = Vec::with_capacity(tiles);
    // GeoMipMaps: 8 levels (every 2^k-th sample), errors growing with the step.
    let geomip_levels = terrain_client::method::geomipmap::stitching::level_count(TILE_SIZE);
    let geomip_errors: Vec<Vec<f32>> = heights
        .iter()
        .map(|&(_, roughness)| {
            suffix_minima(
                &(0..geomip_levels)
                    .map(|k| (2.0 * roughness * f64::from((1u32 << k) - 1) / 127.0) as f32)
                    .collect::<Vec<f32>>(),
            )
        })
        .collect();
    let (mut geomip_levels_now, mut stitches) = (vec![0u32; tiles], Vec::with_capacity(tiles));
    let mut geomip_ns = Vec::with_capacity(FRAMES);
    for level in 0..masks.level_count() {
        black_box(masks.strip(level)); // built once, outside the timed frames
    }

    let mut views: Vec<TileView> = Vec::with_capacity(tiles);
    let mut distances: Vec<f64> = Vec::with_capacity(tiles);
    let (mut importances, mut order, mut allocations) =
        (Vec::new(), Vec::new(), Vec::<Allocation>::new());
    let (mut lod_ns, mut floor_ns) = (Vec::with_capacity(FRAMES), Vec::with_capacity(FRAMES));
    let (mut cap_ns, mut plain_ns) = (Vec::with_capacity(FRAMES), Vec::with_capacity(FRAMES));
    let mut plain = Vec::<Allocation>::new();
    let (mut drawn_sum, mut finest_sum) = (0u64, 0u64);
    let middle = f64::from(SIDE) * TILE_M / 2.0;
    let radius = middle / 2.0;
    for frame in 0..FRAMES {
        let eye = eye_at(frame, middle, radius);
        let distance = |c: &[f64; 2]| {
            let (dx, dy) = (c[0] - eye[0], c[1] - eye[1]);
            (dx * dx + dy * dy + eye[2] * eye[2]).sqrt()
        };

        let start = Instant::now();
        distances.clear();
        distances.extend(centres.iter().map(distance));
        black_box(&distances);
        floor_ns.push(start.elapsed().as_nanos() as u64);

        views.clear();
        views.extend(distances.iter().zip(&heights).map(
            |(&distance_m, &(bbox_height_m, roughness_m))| TileView {
                distance_m,
                bbox_height_m,
                roughness_m,
            },
        ));
        let start = Instant::now();
        importance_into(
            black_box(&views),
            DEFAULT_ALPHA,
            HeightMeasure::BoundingBox,
            &mut importances,
        );
        let caps_started = Instant::now();
        let projection = projection_at(frame, middle, radius);
        caps.clear();
        caps.extend(
            centres
                .iter()
                .zip(&heights)
                .zip(&errors)
                .map(|((c, &(top, _)), errs)| {
                    let half = TILE_M / 2.0;
                    let k = projection.pixels_per_metre(
                        [c[0] - half, c[1] - half, 0.0],
                        [c[0] + half, c[1] + half, top],
                        1.0,
                    );
                    let level = coarsest_level_within(errs, k, 1.0);
                    masks.triangle_count(level)
                }),
        );
        cap_ns.push(caps_started.elapsed().as_nanos() as u64);
        share_into(
            &importances,
            &caps,
            &mut order,
            GLOBAL_BUDGET,
            &masks,
            &mut allocations,
        );
        black_box(&allocations);
        lod_ns.push(start.elapsed().as_nanos() as u64);

        // The paper's plain sharing, without caps, for comparison.
        let plain_started = Instant::now();
        importance_into(
            black_box(&views),
            DEFAULT_ALPHA,
            HeightMeasure::BoundingBox,
            &mut importances,
        );
        share_into(
            &importances,
            &[],
            &mut order,
            GLOBAL_BUDGET,
            &masks,
            &mut plain,
        );
        black_box(&plain);
        plain_ns.push(plain_started.elapsed().as_nanos() as u64);

        drawn_sum += allocations
            .iter()
            .map(|a| u64::from(a.triangles))
            .sum::<u64>();
        finest_sum += allocations
            .iter()
            .map(|a| a.level)
            .min()
            .map_or(0, u64::from);
    }

    // GeoMipMaps' selection over the same path, in a loop of its own so that neither
    // measurement disturbs the other's caches.
    for frame in 0..FRAMES {
        // GeoMipMaps' selection: each tile's level within 1 px, then its stitches.
        let geomip_started = Instant::now();
        let projection = projection_at(frame, middle, radius);
        for (i, ((c, &(top, _)), errs)) in
            centres.iter().zip(&heights).zip(&geomip_errors).enumerate()
        {
            let half = TILE_M / 2.0;
            let k = projection.pixels_per_metre(
                [c[0] - half, c[1] - half, 0.0],
                [c[0] + half, c[1] + half, top],
                1.0,
            );
            geomip_levels_now[i] = coarsest_level_within(errs, k, 1.0);
        }
        stitches.clear();
        let side = SIDE as usize;
        stitches.extend((0..tiles).map(|i| {
            let (x, y) = (i % side, i / side);
            let level = |j: usize| Some(geomip_levels_now[j]);
            Stitch::new(
                geomip_levels_now[i],
                [
                    if y > 0 { level(i - side) } else { None },
                    if x + 1 < side { level(i + 1) } else { None },
                    if y + 1 < side { level(i + side) } else { None },
                    if x > 0 { level(i - 1) } else { None },
                ],
            )
        }));
        black_box(&stitches);
        geomip_ns.push(geomip_started.elapsed().as_nanos() as u64);
    }

    let (lod, floor) = (Stats::of(&mut lod_ns), Stats::of(&mut floor_ns));
    println!(
        "{tiles} visible tiles of {TILE_SIZE}^2, global budget {GLOBAL_BUDGET} triangles, {FRAMES} frames"
    );
    println!(
        "mean triangles drawn {:.0} ({:.1}% of the budget); mean finest level {:.1}",
        drawn_sum as f64 / FRAMES as f64,
        100.0 * drawn_sum as f64 / (FRAMES as f64 * f64::from(GLOBAL_BUDGET)),
        finest_sum as f64 / FRAMES as f64
    );
    println!("| per frame | mean us | median us | p99 us | max us |");
    println!("|---|---|---|---|---|");
    println!("{}", lod.row("importance + error caps + share + select"));
    println!("{}", Stats::of(&mut cap_ns).row("of which the error caps"));
    println!(
        "{}",
        Stats::of(&mut plain_ns).row("importance + share + select, no caps")
    );
    println!(
        "{}",
        Stats::of(&mut geomip_ns).row("GeoMipMaps: levels within 1 px + stitches")
    );
    println!("{}", floor.row("baseline: distances only"));
    println!(
        "lod / baseline: {:.1}x mean, {:.1}x median; target < {TARGET_US} us per frame: {}",
        lod.mean / floor.mean,
        lod.median / floor.median,
        if lod.p99 < TARGET_US {
            "met (p99)"
        } else {
            "MISSED (p99)"
        }
    );
}

/// The viewpoint of `frame`: circling the grid's middle at `radius`, at the altitude.
/// The error bound of frame `frame`: from [`eye_at`], looking along the path, 20 degrees
/// down, 0.96 rad of vertical field of view on 1920x1080.
fn projection_at(frame: usize, middle: f64, radius: f64) -> ErrorProjection {
    let angle = frame as f64 * SPEED_M_PER_FRAME / radius;
    let pitch = -20f64.to_radians();
    ErrorProjection::new(
        eye_at(frame, middle, radius),
        [
            -angle.sin() * pitch.cos(),
            angle.cos() * pitch.cos(),
            pitch.sin(),
        ],
        0.96,
        [1920, 1080],
        1.0,
    )
}

fn eye_at(frame: usize, middle: f64, radius: f64) -> [f64; 3] {
    let angle = frame as f64 * SPEED_M_PER_FRAME / radius;
    [
        middle + radius * angle.cos(),
        middle + radius * angle.sin(),
        ALTITUDE_M,
    ]
}
