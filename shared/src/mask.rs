//! Strip-mask geometry: which samples a mask level keeps and how it triangulates them.
//!
//! Mask level `l` of a tile of `n x n` samples keeps the samples whose row and column
//! indices are multiples of `l + 1`, and always the last row and column, so every mask
//! covers the whole tile and meets its neighbours' borders (strip-mask paper, section
//! 5.1: a tile has `n - 1` masks). Level 0 is the full tile.
//!
//! The builder uses this module to tabulate, per tile and level, the largest vertical
//! error of the mask against the full tile; the renderer uses it to build the strips.
//! Both must triangulate identically, so the convention lives here, once:
//!
//! **Invariant:** each cell between kept rows `r0 < r1` and kept columns `c0 < c1` is
//! split along the diagonal from `(c0, r1)` to `(c1, r0)`: the one a triangle strip walking
//! a row pair west to east, north vertex first, produces.

/// Number of mask levels of a tile with `tile_size` samples per side.
pub fn level_count(tile_size: u32) -> u32 {
    tile_size.saturating_sub(1)
}

/// Sample indices along one side kept by mask `level`: multiples of `level + 1`, then the last.
pub fn kept_indices(tile_size: u32, level: u32) -> Vec<u32> {
    if tile_size == 0 {
        return Vec::new();
    }
    let last = tile_size - 1;
    let step = level.saturating_add(1);
    let mut kept: Vec<u32> = (0..=last).step_by(step as usize).collect();
    if kept.last() != Some(&last) {
        kept.push(last);
    }
    kept
}

/// Triangles drawn by mask `level` (strip joins not counted).
pub fn triangle_count(tile_size: u32, level: u32) -> u32 {
    let cells = kept_indices(tile_size, level).len().saturating_sub(1) as u32;
    2 * cells * cells
}

/// A number a cell's height is interpolated in (`f32` for the builder's tables, `f64` for
/// the client's true surface): the same arithmetic either way.
pub trait Height:
    Copy
    + PartialOrd
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
{
    const ONE: Self;
}

impl Height for f32 {
    const ONE: f32 = 1.0;
}

impl Height for f64 {
    const ONE: f64 = 1.0;
}

/// Height at `(u, v)` (each in `[0, 1]`, east and south) of a cell whose corners are `h00`
/// (north-west), `h10` (north-east), `h01` (south-west) and `h11` (south-east), split along
/// the diagonal from `(c0, r1)` to `(c1, r0)` (`u + v = 1`) as every mask draws it.
pub fn cell_height<T: Height>(h00: T, h10: T, h01: T, h11: T, u: T, v: T) -> T {
    if u + v <= T::ONE {
        h00 + u * (h10 - h00) + v * (h01 - h00)
    } else {
        h11 + (T::ONE - u) * (h01 - h11) + (T::ONE - v) * (h10 - h11)
    }
}

/// Largest vertical distance, in the units of `samples`, between the full tile and mask
/// `level`, over every sample of the tile. `samples` is row-major `tile_size^2`.
///
/// Panics if `samples.len() != tile_size^2` (a caller bug, never data-dependent).
///
/// The builder measures every level of every tile (128 levels of 129^2 samples each), so
/// the loop runs over whole rows of samples, each column's cell read from per-column
/// arrays, and is compiled also for AVX2 and AVX-512, the CPU choosing at run time
/// (`multiversion`): built for the baseline x86-64 (SSE2) alone, it is slower than the
/// per-cell loop it replaced. Rust never fuses a multiplication and an addition, so every
/// version computes the reference's operations in its order; the tests hold the version
/// this CPU picks to the reference, bit for bit.
#[multiversion::multiversion(targets("x86_64+avx+avx2+avx512f", "x86_64+avx+avx2"))]
pub fn max_vertical_error(samples: &[f32], tile_size: u32, level: u32) -> f32 {
    let n = tile_size as usize;
    assert_eq!(samples.len(), n * n, "samples must be tile_size^2");
    if level == 0 || n < 2 {
        return 0.0;
    }
    let kept: Vec<usize> = kept_indices(tile_size, level)
        .into_iter()
        .map(|k| k as usize)
        .collect();
    // Each column's cell (its corners' columns) and `u` across it. A kept column inside
    // the tile is the first of the cell on its right here, and the last of the cell on
    // its left in `edges`: every cell measures both its sides, as the reference does.
    let mut cell = vec![(0usize, 0usize); n];
    let mut u = vec![0.0f32; n];
    let mut edges = Vec::new();
    for cols in kept.windows(2) {
        let (c0, c1) = (cols[0], cols[1]);
        let du = (c1 - c0) as f32;
        for x in c0..c1 {
            cell[x] = (c0, c1);
            u[x] = (x - c0) as f32 / du;
        }
        if c1 < n - 1 {
            edges.push((c0, c1));
        }
    }
    let last = kept[kept.len() - 2];
    cell[n - 1] = (last, n - 1);
    u[n - 1] = 1.0; // `du / du`, which is exactly 1, as in the reference
    // Per column, what `cell_height` reads of a band of rows: the corners and their
    // differences, in its operations and order (so the same bits).
    let mut corner = [vec![0.0f32; n], vec![0.0f32; n]]; // h00, h11
    let mut diff = [
        vec![0.0f32; n], // h10 - h00
        vec![0.0f32; n], // h01 - h00
        vec![0.0f32; n], // h01 - h11
        vec![0.0f32; n], // h10 - h11
    ];
    // A running maximum per column, so that the loop over a row vectorises; the maximum of
    // finite values is exact in any order.
    let mut worst = vec![0.0f32; n];
    let mut edge_worst = 0.0f32;
    for rows in kept.windows(2) {
        let (r0, r1) = (rows[0], rows[1]);
        let dv = (r1 - r0) as f32;
        let (top, bottom) = (
            &samples[r0 * n..(r0 + 1) * n],
            &samples[r1 * n..(r1 + 1) * n],
        );
        for x in 0..n {
            let (c0, c1) = cell[x];
            let (h00, h10, h01, h11) = (top[c0], top[c1], bottom[c0], bottom[c1]);
            corner[0][x] = h00;
            corner[1][x] = h11;
            diff[0][x] = h10 - h00;
            diff[1][x] = h01 - h00;
            diff[2][x] = h01 - h11;
            diff[3][x] = h10 - h11;
        }
        for y in r0..=r1 {
            let v = (y - r0) as f32 / dv;
            let row = &samples[y * n..(y + 1) * n];
            let columns = row
                .iter()
                .zip(&u)
                .zip(corner[0].iter().zip(&corner[1]))
                .zip(diff[0].iter().zip(&diff[1]))
                .zip(diff[2].iter().zip(&diff[3]))
                .zip(worst.iter_mut());
            for (((((&h, &u), (&h00, &h11)), (&d1, &g)), (&e1, &k)), worst) in columns {
                // `cell_height`: both triangles computed and one chosen, which vectorises.
                let north_west = h00 + u * d1 + v * g;
                let south_east = h11 + (1.0 - u) * e1 + (1.0 - v) * k;
                let surface = if u + v <= 1.0 { north_west } else { south_east };
                *worst = larger(*worst, (h - surface).abs());
            }
            for &(c0, c1) in &edges {
                let (h00, h10, h01, h11) = (top[c0], top[c1], bottom[c0], bottom[c1]);
                let surface = cell_height(h00, h10, h01, h11, 1.0, v);
                edge_worst = larger(edge_worst, (row[c1] - surface).abs());
            }
        }
    }
    worst.into_iter().fold(edge_worst, larger)
}

/// The larger of two distances: `f32::max` for the finite numbers heights are, in the
/// one instruction a vector unit has for it (`f32::max`'s care for NaN costs two more).
#[inline(always)]
fn larger(a: f32, b: f32) -> f32 {
    if a > b { a } else { b }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The direct definition: every cell, every sample, one at a time.
    fn max_vertical_error_reference(samples: &[f32], tile_size: u32, level: u32) -> f32 {
        let n = tile_size as usize;
        if level == 0 {
            return 0.0;
        }
        let at = |x: usize, y: usize| samples[y * n + x];
        let kept = kept_indices(tile_size, level);
        let mut worst = 0.0f32;
        for rows in kept.windows(2) {
            let (r0, r1) = (rows[0] as usize, rows[1] as usize);
            for cols in kept.windows(2) {
                let (c0, c1) = (cols[0] as usize, cols[1] as usize);
                let (h00, h10, h01, h11) = (at(c0, r0), at(c1, r0), at(c0, r1), at(c1, r1));
                let (du, dv) = ((c1 - c0) as f32, (r1 - r0) as f32);
                for y in r0..=r1 {
                    let v = (y - r0) as f32 / dv;
                    for x in c0..=c1 {
                        let u = (x - c0) as f32 / du;
                        let surface = cell_height(h00, h10, h01, h11, u, v);
                        worst = worst.max((at(x, y) - surface).abs());
                    }
                }
            }
        }
        worst
    }

    proptest::proptest! {
        /// The fast loop gives the reference's error to the bit, on any tile and level.
        #[test]
        fn the_fast_error_is_the_reference_error_exactly(
            side in 2u32..40, seed in proptest::prelude::any::<u64>(), scale in 0.001f32..5000.0
        ) {
            let mut state = seed;
            let samples: Vec<f32> = (0..side * side)
                .map(|_| {
                    state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                    ((state >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * scale
                })
                .collect();
            for level in 0..level_count(side) {
                let fast = max_vertical_error(&samples, side, level);
                let reference = max_vertical_error_reference(&samples, side, level);
                proptest::prop_assert_eq!(fast.to_bits(), reference.to_bits(), "level {}", level);
            }
        }
    }

    #[test]
    fn the_fast_error_is_the_reference_error_on_a_full_size_tile() {
        let n = 129u32;
        let samples: Vec<f32> = (0..n * n)
            .map(|i| {
                let (x, y) = ((i % n) as f32, (i / n) as f32);
                (x * 0.37).sin() * 40.0 + (y * 0.11).cos() * 90.0 + (x * y * 0.013).sin() * 7.0
            })
            .collect();
        for level in 0..level_count(n) {
            assert_eq!(
                max_vertical_error(&samples, n, level).to_bits(),
                max_vertical_error_reference(&samples, n, level).to_bits(),
                "level {level}"
            );
        }
    }

    #[test]
    fn kept_indices_follow_the_papers_figure_4() {
        // A 6x6 grid: levels 2 and 3 both keep three indices per side, so both draw 8 triangles.
        assert_eq!(kept_indices(6, 0), vec![0, 1, 2, 3, 4, 5]);
        assert_eq!(kept_indices(6, 1), vec![0, 2, 4, 5]);
        assert_eq!(kept_indices(6, 2), vec![0, 3, 5]);
        assert_eq!(kept_indices(6, 3), vec![0, 4, 5]);
        assert_eq!(kept_indices(6, 4), vec![0, 5]);
        assert_eq!(level_count(6), 5);
        let counts: Vec<u32> = (0..5).map(|l| triangle_count(6, l)).collect();
        assert_eq!(counts, vec![50, 18, 8, 8, 2]);
    }

    #[test]
    fn planes_have_no_error_at_any_level() {
        let n = 17u32;
        let plane: Vec<f32> = (0..n * n)
            .map(|i| 3.0 * (i % n) as f32 - 2.0 * (i / n) as f32)
            .collect();
        for level in 0..level_count(n) {
            assert!(max_vertical_error(&plane, n, level) < 1e-3, "level {level}");
        }
    }

    #[test]
    fn a_single_spike_is_the_error_of_every_mask_that_drops_it() {
        let n = 9u32;
        let mut samples = vec![0.0f32; 81];
        samples[4 * 9 + 3] = 10.0; // (x 3, y 4): dropped by level 1 (even indices), kept by level 2
        assert_eq!(max_vertical_error(&samples, n, 0), 0.0);
        assert_eq!(max_vertical_error(&samples, n, 1), 10.0);
        assert_eq!(max_vertical_error(&samples, n, 3), 10.0);
    }

    #[test]
    fn the_diagonal_runs_from_south_west_to_north_east() {
        // One 3x3 cell at level 1 with the north-west and south-east corners lifted to 8.
        // Split along south-west/north-east the centre lies on a diagonal of zeros, so these
        // samples are exactly the mask's surface; the other diagonal would put 8 at the centre.
        let samples = [8.0, 4.0, 0.0, 4.0, 0.0, 4.0, 0.0, 4.0, 8.0];
        assert_eq!(max_vertical_error(&samples, 3, 1), 0.0);
    }
}
