//! Pager benchmark: time per paging decision over a realistic flight, against the cost floor
//! of any pager that looks at every tile, measured in the same run.
//!
//! ```text
//! cargo bench -p terrain-client --bench pager
//! ```
//!
//! A 64x64 grid (4096 tiles) of tiles of 150 to 250 KiB each (heights, decoded heights and a
//! texture chain are of that order for 129^2 tiles), a memory limit of 19x19 average tiles,
//! so that about 10 belts fit, and a viewpoint flying a Lissajous curve across the grid at
//! about 0.01 tiles a frame (at 60 fps, a 129-sample tile of 10 m samples every 1.7 s: 770
//! m/s, a fast jet) with a jump to the far side every 5000 frames. A simulated fetcher delivers each requested tile 2 to 20
//! frames later (30 to 330 ms at 60 fps) and honours cancellations. Each frame times one
//! [`decide`] and, as the baseline, one plain pass summing `resident_bytes`. The target is
//! under 50 us a decision.

mod common;
use common::{Random, Stats, cpu_model};

use std::hint::black_box;
use std::time::Instant;
use terrain_client::page::{PagerConfig, PagerView, decide};

const SIDE: u32 = 64;
const FRAMES: usize = 20_000;
/// Tiles in the square that should fit: belts 0 to 9 around the current tile.
const SQUARE_TILES: u64 = 19 * 19;
const TILE_BYTES: std::ops::RangeInclusive<u64> = 150 << 10..=250 << 10;
const DELAY_FRAMES: std::ops::RangeInclusive<u64> = 2..=20;
const SPEED_TILES_PER_FRAME: f64 = 0.01;
const JUMP_EVERY_FRAMES: usize = 5000;

fn main() {
    println!(
        "machine: {} ({} cores); one thread",
        cpu_model(),
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    let mut random = Random(0x5eed);
    let tiles = (SIDE * SIDE) as usize;
    let span = TILE_BYTES.end() - TILE_BYTES.start() + 1;
    let sizes: Vec<u64> = (0..tiles)
        .map(|_| TILE_BYTES.start() + random.below(span))
        .collect();
    let mean_tile = sizes.iter().sum::<u64>() / tiles as u64;
    let config = PagerConfig::new(SIDE, SIDE, SQUARE_TILES * mean_tile);

    let mut resident = vec![0u64; tiles];
    let mut in_flight = vec![false; tiles];
    let mut arrives_at = vec![0usize; tiles];
    let (mut decide_ns, mut floor_ns) = (Vec::with_capacity(FRAMES), Vec::with_capacity(FRAMES));
    let (mut fetched, mut evicted, mut cancelled, mut belts_sum, mut peak_used) =
        (0usize, 0usize, 0usize, 0u64, 0u64);
    let mut phase = 0.0f64;
    for frame in 0..FRAMES {
        for i in 0..tiles {
            if in_flight[i] && arrives_at[i] <= frame {
                in_flight[i] = false;
                resident[i] = sizes[i];
            }
        }
        // A Lissajous curve over the middle 80% of the grid; the phase advances so that the
        // viewpoint moves at about SPEED_TILES_PER_FRAME, and half a turn at each jump.
        if frame > 0 && frame % JUMP_EVERY_FRAMES == 0 {
            phase += std::f64::consts::PI;
        }
        phase += SPEED_TILES_PER_FRAME / (0.4 * f64::from(SIDE) * 2.0);
        let centre = f64::from(SIDE) / 2.0;
        let viewpoint = [
            centre + 0.4 * f64::from(SIDE) * (2.0 * phase).sin(),
            centre + 0.4 * f64::from(SIDE) * (3.0 * phase).cos(),
        ];

        // Sizes known before fetching, as the flight passes them from the manifest.
        let view = PagerView {
            viewpoint,
            resident_bytes: &resident,
            in_flight: &in_flight,
            expected_bytes: Some(&sizes),
        };
        let started = Instant::now();
        let decision = black_box(decide(&config, black_box(&view)));
        decide_ns.push(started.elapsed().as_nanos() as u64);
        let started = Instant::now();
        black_box(black_box(&resident).iter().sum::<u64>());
        floor_ns.push(started.elapsed().as_nanos() as u64);

        for id in &decision.cancel {
            in_flight[config.index(*id)] = false;
        }
        for id in &decision.evict {
            resident[config.index(*id)] = 0;
        }
        for id in &decision.fetch {
            let i = config.index(*id);
            in_flight[i] = true;
            arrives_at[i] = frame
                + (DELAY_FRAMES.start()
                    + random.below(DELAY_FRAMES.end() - DELAY_FRAMES.start() + 1))
                    as usize;
        }
        fetched += decision.fetch.len();
        evicted += decision.evict.len();
        cancelled += decision.cancel.len();
        belts_sum += u64::from(decision.complete_belts);
        peak_used = peak_used.max(decision.used_bytes);
    }

    let mib = |b: u64| b as f64 / f64::from(1 << 20);
    println!(
        "flight: {SIDE}x{SIDE} grid, {FRAMES} frames, limit {:.1} MiB ({SQUARE_TILES} tiles of {:.0} KiB), peak used {:.1} MiB",
        mib(config.memory_limit),
        mean_tile as f64 / 1024.0,
        mib(peak_used)
    );
    println!(
        "        mean complete belts {:.2}, tiles fetched {fetched}, evicted {evicted}, cancelled {cancelled}",
        belts_sum as f64 / FRAMES as f64
    );
    let decide_stats = Stats::of(&mut decide_ns);
    let floor_stats = Stats::of(&mut floor_ns);
    println!("| per frame | mean us | median us | p99 us | max us |");
    println!("|---|---|---|---|---|");
    println!("{}", decide_stats.row("decide"));
    println!("{}", floor_stats.row("baseline: sum resident_bytes"));
    println!(
        "decide / baseline: {:.1}x mean, {:.1}x median; target < 50 us per decision: {}",
        decide_stats.mean / floor_stats.mean,
        decide_stats.median / floor_stats.median,
        if decide_stats.p99 < 50.0 {
            "met (p99)"
        } else {
            "MISSED (p99)"
        }
    );
}
