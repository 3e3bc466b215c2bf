//! GeoMipMaps (Brodersen 2005): a tile drawn at level `k` keeps every `2^k`-th sample, and
//! cracks are avoided by *adding* vertices: the border of a coarser tile takes the samples
//! of its finer neighbour's shared edge, so both draw the same edge (the paper's five
//! regions and Figure 4).
//!
//! **Regions.** At step `s = 2^k` the centre region is the grid of cells not touching the
//! border, drawn as one strip per row of cells (split along the diagonal of
//! `terrain_shared::mask`, from `(c0, r1)` to `(c1, r0)`). Each side is a trapezoid between
//! its outer edge, sampled at the *stitch step* `min(s, 2^neighbour)`, and the centre's
//! boundary one step `s` inside, triangulated by zipping the two rows of vertices. Two
//! neighbours stitch their shared edge at the same step (the finer one's), so the edge's
//! vertices are the same on both sides: no T-junction, no crack. Corners are shared by
//! adjacent trapezoids along the diagonals from the tile's corners. At the coarsest level
//! (one cell) a tile with finer neighbours is a fan around its centre sample. Level 0, whose
//! neighbours are never finer, is the full-resolution grid as the strip masks' level 0 (and
//! the reference) draws it: all centre, no trapezoid.
//!
//! **Index sets** are keyed by [`Stitch`] (own level and the four stitch levels), built on
//! first use and shared by every tile, as strips separated by primitive restarts
//! ([`RESTART`]).

use std::collections::HashSet;

/// Strip index that restarts the strip (wgpu's primitive restart for 32-bit indices).
pub const RESTART: u32 = u32::MAX;

/// Levels of a tile of `tile_size = 2^m + 1` samples: `0..=m` (level `m` is one cell).
pub fn level_count(tile_size: u32) -> u32 {
    (tile_size - 1).trailing_zeros() + 1
}

/// What one tile draws: its level and the level each side is stitched at.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Stitch {
    pub level: u32,
    /// Stitch level of the north, east, south and west sides: the finer of this tile's
    /// level and its neighbour's (a neighbour not drawn counts as this tile's level).
    pub sides: [u32; 4],
}

impl Stitch {
    /// The stitch of a tile at `level` whose neighbours (north, east, south, west) draw
    /// `neighbours` (`None`: not drawn).
    pub fn new(level: u32, neighbours: [Option<u32>; 4]) -> Stitch {
        Stitch {
            level,
            sides: neighbours.map(|n| n.map_or(level, |n| n.min(level))),
        }
    }
}

/// A triangle as three sample indices.
pub type Triangle = [u32; 3];

/// The triangles of `stitch` on a tile of `n` samples a side (see the module docs).
pub fn triangles(n: u32, stitch: Stitch) -> Vec<Triangle> {
    let mut out = centre(n, stitch.level);
    out.extend(border(n, stitch));
    out
}

/// The triangles of the centre region at `level`: the cells whose corners are all at least
/// one step inside, split along the anti-diagonal. Empty when the tile has under 3 cells a
/// side.
fn centre(n: u32, level: u32) -> Vec<Triangle> {
    let s = 1u32 << level;
    let cells = (n - 1) / s;
    let at = |x: u32, y: u32| y * n + x;
    let mut out = Vec::new();
    let (first, end) = centre_cells(cells, level);
    for r in first..end {
        for c in first..end {
            let (x0, y0, x1, y1) = (c * s, r * s, (c + 1) * s, (r + 1) * s);
            out.push([at(x0, y0), at(x0, y1), at(x1, y0)]);
            out.push([at(x0, y1), at(x1, y0), at(x1, y1)]);
        }
    }
    out
}

/// The triangles outside the centre region: the four trapezoids, or the one-cell tile
/// (two triangles when no side is stitched finer, else a [`fan`]).
/// The rows (and columns) of cells of the centre region, `first..end`: those one step inside
/// the border, or at level 0 every cell. Level 0 has no border region: its neighbours are
/// never finer, so it is the full-resolution grid, split as the strip masks split it (and
/// as the reference is drawn), not with the trapezoids' corner diagonals.
fn centre_cells(cells: u32, level: u32) -> (u32, u32) {
    if level == 0 {
        (0, cells)
    } else {
        (1, cells.saturating_sub(1))
    }
}

fn border(n: u32, stitch: Stitch) -> Vec<Triangle> {
    if stitch.level == 0 {
        return Vec::new();
    }
    let last = n - 1;
    let s = 1u32 << stitch.level;
    let at = |x: u32, y: u32| y * n + x;
    let cells = last / s;
    if cells == 1 {
        if stitch.sides.iter().all(|&l| l == stitch.level) {
            return vec![
                [at(0, 0), at(0, last), at(last, 0)],
                [at(0, last), at(last, 0), at(last, last)],
            ];
        }
        return fan(n, stitch);
    }
    let mut out = Vec::new();
    // The four trapezoids: (along, depth) mapped to (x, y) per side.
    let sides: [&dyn Fn(u32, u32) -> (u32, u32); 4] = [
        &|u, v| (u, v),
        &|u, v| (last - v, u),
        &|u, v| (u, last - v),
        &|u, v| (v, u),
    ];
    for (side, map) in sides.iter().enumerate() {
        let t = 1u32 << stitch.sides[side];
        let outer: Vec<u32> = (0..=last).step_by(t as usize).collect();
        let inner: Vec<u32> = (s..=last - s).step_by(s as usize).collect();
        let vertex = |u: u32, v: u32| {
            let (x, y) = map(u, v);
            at(x, y)
        };
        let (mut i, mut j) = (0, 0);
        while i + 1 < outer.len() || j + 1 < inner.len() {
            let advance_outer = if j + 1 == inner.len() {
                true
            } else if i + 1 == outer.len() {
                false
            } else {
                outer[i + 1] <= inner[j + 1]
            };
            if advance_outer {
                out.push([
                    vertex(outer[i], 0),
                    vertex(outer[i + 1], 0),
                    vertex(inner[j], s),
                ]);
                i += 1;
            } else {
                out.push([
                    vertex(outer[i], 0),
                    vertex(inner[j], s),
                    vertex(inner[j + 1], s),
                ]);
                j += 1;
            }
        }
    }
    out
}

/// A one-cell tile as a fan around its centre sample over the [`boundary`], each side at
/// its stitch step. Each triangle has both outer vertices on one side, so it depends on
/// that side's stitch level only.
fn fan(n: u32, stitch: Stitch) -> Vec<Triangle> {
    let last = n - 1;
    let c = (last / 2) * n + last / 2;
    let ring = boundary(n, stitch);
    (0..ring.len())
        .map(|k| [c, ring[k], ring[(k + 1) % ring.len()]])
        .collect()
}

/// The boundary of a one-cell tile, clockwise from the north-west corner, each side
/// sampled at its stitch step.
fn boundary(n: u32, stitch: Stitch) -> Vec<u32> {
    let last = n - 1;
    let at = |x: u32, y: u32| y * n + x;
    let step = |side: usize| 1usize << stitch.sides[side];
    let mut ring = Vec::new();
    ring.extend((0..last).step_by(step(0)).map(|x| at(x, 0)));
    ring.extend((0..last).step_by(step(1)).map(|y| at(last, y)));
    ring.extend((0..last).step_by(step(2)).map(|x| at(last - x, last)));
    ring.extend((0..last).step_by(step(3)).map(|y| at(0, last - y)));
    ring
}

/// The index buffer of `stitch` for a triangle-strip pipeline with primitive restart: one
/// strip per row of centre cells (west to east, north vertex first, as the strip masks),
/// then each border triangle as a strip of its own. Draws exactly [`triangles`].
pub fn strip(n: u32, stitch: Stitch) -> Vec<u32> {
    let s = 1u32 << stitch.level;
    let cells = (n - 1) / s;
    let mut out = Vec::new();
    let (first, end) = centre_cells(cells, stitch.level);
    for r in first..end {
        for c in first..=end {
            out.push(r * s * n + c * s);
            out.push((r + 1) * s * n + c * s);
        }
        out.push(RESTART);
    }
    for t in &border(n, stitch) {
        out.extend_from_slice(t);
        out.push(RESTART);
    }
    out
}

/// Maximum vertical error, in the units of `samples`, of each level of a tile of `n x n`
/// heights (row-major) against the full-resolution surface, over every triangulation the
/// level can draw; `[0]` is 0.
///
/// **What it bounds.** The full-resolution surface `F` is the piecewise-linear interpolant
/// of the samples on the unit cells, each split along its anti-diagonal from `(c0, r1)` to
/// `(c1, r0)` (the strip masks' level 0). Entry `k >= 1` is, exactly (up to `f64`
/// rounding, then rounded up to `f32`), the largest `|P_T(p) - F(p)|` over every point `p`
/// of every triangle `T` that level `k` can draw under *any* stitch, `P_T` being `T`'s
/// plane. So whatever its neighbours, a tile drawn at level `k` is nowhere, not only at its
/// samples, further than `level_errors(..)[k]` above or below `F`: the renderer can take
/// it as an upper bound. Entry 0 is 0: level 0 draws `F` itself (see [`centre_cells`]).
///
/// **Which triangles.** The centre region does not depend on the stitch. Each trapezoid
/// depends only on its own side's stitch level, and so does each triangle of the one-cell
/// fan (both its outer vertices are on one side), so every triangle level `k` draws is in
/// the centre, in the trapezoids of `Stitch { level: k, sides: [j; 4] }` for `j in 0..=k`,
/// or, at a one-cell level, in its two-triangle split or in the fans with every side at a
/// `j in 0..=k` (a fan side at the tile's own level `k`, drawn when another side is finer,
/// is in no `[j; 4]` triangulation). The border triangles, and their edges, are
/// deduplicated before being measured; the centre is measured once.
///
/// **Why the points measured suffice.** In `T` the grid lines `x = i`, `y = j` and
/// `x + y = l` (integers) bound `F`'s pieces, convex polygons on each of which both `P_T`
/// and `F`, hence `P_T - F`, are linear: its extremes lie at the pieces' vertices. These are
/// `T`'s vertices and the samples inside or on `T` (where grid lines meet each other), and
/// the points where `T`'s edges cross grid lines; all of them are measured. An edge that
/// is itself horizontal, vertical or anti-diagonal crosses the other lines at samples only,
/// but the trapezoids' zipped edges, the fans' spokes and the corners' main diagonals cross
/// them in between, where the error can exceed every sample's: along such an edge every
/// triangle's plane is the interpolation of the edge's ends, so each crossing is measured
/// once per edge.
///
/// Panics if `samples.len() != n * n` (a caller bug).
pub fn level_errors(samples: &[f32], n: u32) -> Vec<f32> {
    assert_eq!(
        samples.len(),
        (n as usize) * (n as usize),
        "samples must be n^2"
    );
    let grid = Grid { samples, n };
    (0..level_count(n))
        .map(|level| {
            if level == 0 {
                return 0.0;
            }
            let every = |j| Stitch {
                level,
                sides: [j; 4],
            };
            let mut border_sets = Vec::new();
            if (n - 1) >> level == 1 {
                border_sets.push(border(n, every(level)));
                border_sets.extend((0..=level).map(|j| fan(n, every(j))));
            } else {
                border_sets.extend((0..=level).map(|j| border(n, every(j))));
            }
            let mut drawn: HashSet<Triangle> = HashSet::new();
            // Edges crossing grid lines between samples. Along an edge a triangle's plane is
            // the interpolation of the edge's ends, so the error at a crossing depends on
            // the edge alone, and the many edges that triangles and stitches share are
            // measured once.
            let mut edges: HashSet<(u32, u32)> = HashSet::new();
            for mut t in border_sets.into_iter().flatten() {
                t.sort_unstable();
                if drawn.insert(t) {
                    for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[0], t[2])] {
                        if grid.crosses_between_samples(a, b) {
                            edges.insert((a, b));
                        }
                    }
                }
            }
            // The centre's edges are horizontal, vertical or anti-diagonal: samples suffice.
            let worst = centre(n, level)
                .iter()
                .chain(&drawn)
                .map(|t| grid.sample_error(t))
                .chain(edges.iter().map(|&(a, b)| grid.crossing_error(a, b)))
                .fold(0.0f64, f64::max);
            round_up(worst)
        })
        .collect()
}

/// `v` as the nearest `f32` at or above it.
fn round_up(v: f64) -> f32 {
    let r = v as f32;
    if f64::from(r) < v { r.next_up() } else { r }
}

/// A tile's samples and the level-0 surface `F` they span (see [`level_errors`]).
struct Grid<'a> {
    samples: &'a [f32],
    n: u32,
}

impl Grid<'_> {
    fn height(&self, x: i64, y: i64) -> f64 {
        f64::from(self.samples[(y * i64::from(self.n) + x) as usize])
    }

    fn xy(&self, i: u32) -> (i64, i64) {
        (i64::from(i % self.n), i64::from(i / self.n))
    }

    /// `F` at a point of the tile: the plane of the level-0 triangle holding it.
    fn fine(&self, x: f64, y: f64) -> f64 {
        let last = i64::from(self.n) - 1;
        let x0 = (x.floor() as i64).clamp(0, last - 1);
        let y0 = (y.floor() as i64).clamp(0, last - 1);
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        if fx + fy <= 1.0 {
            let h00 = self.height(x0, y0);
            h00 + fx * (self.height(x0 + 1, y0) - h00) + fy * (self.height(x0, y0 + 1) - h00)
        } else {
            let h11 = self.height(x0 + 1, y0 + 1);
            h11 + (1.0 - fx) * (self.height(x0, y0 + 1) - h11)
                + (1.0 - fy) * (self.height(x0 + 1, y0) - h11)
        }
    }

    /// Whether the edge between samples `a` and `b` crosses a grid line `x = i`, `y = j` or
    /// `x + y = k` anywhere but at a sample: it is not horizontal, vertical or
    /// anti-diagonal.
    fn crosses_between_samples(&self, a: u32, b: u32) -> bool {
        let ((ax, ay), (bx, by)) = (self.xy(a), self.xy(b));
        let (dx, dy) = (bx - ax, by - ay);
        dx != 0 && dy != 0 && dx + dy != 0
    }

    /// Largest `|P - F|` where the edge from sample `a` to sample `b` crosses the grid
    /// lines, `P` being the interpolation of its ends' heights (any triangle's plane along
    /// it).
    fn crossing_error(&self, a: u32, b: u32) -> f64 {
        let ((ax, ay), (bx, by)) = (self.xy(a), self.xy(b));
        let (dx, dy) = (bx - ax, by - ay);
        let (ha, hb) = (self.height(ax, ay), self.height(bx, by));
        let mut worst = 0.0f64;
        // Along the edge x, y and x + y change by dx, dy and dx + dy: each crosses the
        // integers strictly between its ends at the parameters k / |d|, 0 < k < |d|.
        for d in [dx.abs(), dy.abs(), (dx + dy).abs()] {
            for k in 1..d {
                let t = k as f64 / d as f64;
                let (x, y) = (ax as f64 + t * dx as f64, ay as f64 + t * dy as f64);
                worst = worst.max((ha + t * (hb - ha) - self.fine(x, y)).abs());
            }
        }
        worst
    }

    /// Largest distance between triangle `t`'s plane and the samples inside or on it.
    fn sample_error(&self, t: &Triangle) -> f64 {
        let p = t.map(|i| self.xy(i));
        let h = t.map(|i| f64::from(self.samples[i as usize]));
        let [(ax, ay), (bx, by), (cx, cy)] = p;
        let det = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay);
        if det == 0 {
            return 0.0;
        }
        // The plane: P(x, y) = h[0] + gx (x - ax) + gy (y - ay).
        let (dbh, dch, det) = (h[1] - h[0], h[2] - h[0], det as f64);
        let gx = (dbh * (cy - ay) as f64 - (by - ay) as f64 * dch) / det;
        let gy = ((bx - ax) as f64 * dch - dbh * (cx - ax) as f64) / det;
        let edges = [(p[0], p[1]), (p[1], p[2]), (p[2], p[0])];
        let mut worst = 0.0f64;
        for y in ay.min(by).min(cy)..=ay.max(by).max(cy) {
            // The triangle's x-range on row y, from its edges' crossings of the row. These
            // are rationals of denominator |dy| < n, so one that is not an integer is at
            // least 1 / n from one, and the 1e-9 margins round exactly.
            let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
            for &((px, py), (qx, qy)) in &edges {
                if y < py.min(qy) || y > py.max(qy) {
                    continue;
                }
                let (x0, x1) = if py == qy {
                    (px.min(qx) as f64, px.max(qx) as f64)
                } else {
                    let x = px as f64 + (y - py) as f64 * (qx - px) as f64 / (qy - py) as f64;
                    (x, x)
                };
                lo = lo.min(x0);
                hi = hi.max(x1);
            }
            let plane_row = h[0] + gy * (y - ay) as f64;
            for x in (lo - 1e-9).ceil() as i64..=(hi + 1e-9).floor() as i64 {
                let plane = plane_row + gx * (x - ax) as f64;
                worst = worst.max((plane - self.height(x, y)).abs());
            }
        }
        worst
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::{BTreeSet, HashMap};
    use web_time::Instant;

    /// The exact error of one triangle: its samples and its edges' crossings.
    fn triangle_error(samples: &[f32], n: u32, t: &Triangle) -> f64 {
        let grid = Grid { samples, n };
        let crossings =
            [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])].map(|(a, b)| grid.crossing_error(a, b));
        crossings.into_iter().fold(grid.sample_error(t), f64::max)
    }

    use crate::testing::Rng;

    /// Heights of a few kinds: smooth hills plus noise, rough noise, or small integers
    /// (ties and flat patches).
    fn random_heights(n: u32, seed: u64) -> Vec<f32> {
        let mut rng = Rng(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1);
        let kind = seed % 3;
        let (fx, fy, phase) = (
            rng.range_f32(0.1, 1.5),
            rng.range_f32(0.1, 1.5),
            rng.range_f32(0.0, 6.0),
        );
        (0..n * n)
            .map(|i| {
                let (x, y) = ((i % n) as f32, (i / n) as f32);
                match kind {
                    0 => 20.0 * (fx * x + phase).sin() * (fy * y).cos() + rng.range_f32(-3.0, 3.0),
                    1 => rng.range_f32(-50.0, 50.0),
                    _ => (rng.next() % 5) as f32 - 2.0,
                }
            })
            .collect()
    }

    /// The old measure: the largest distance between a sample and the surface of
    /// `triangles` at its position, at the samples only.
    fn sample_error(samples: &[f32], n: u32, triangles: &[Triangle]) -> f32 {
        let xy = |i: u32| (f64::from(i % n), f64::from(i / n));
        let mut worst = 0.0f64;
        for t in triangles {
            let [(ax, ay), (bx, by), (cx, cy)] = t.map(xy);
            let [ha, hb, hc] = t.map(|i| f64::from(samples[i as usize]));
            let det = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay);
            let (x0, x1) = (ax.min(bx).min(cx) as u32, ax.max(bx).max(cx) as u32);
            let (y0, y1) = (ay.min(by).min(cy) as u32, ay.max(by).max(cy) as u32);
            for y in y0..=y1 {
                for x in x0..=x1 {
                    let (px, py) = (f64::from(x), f64::from(y));
                    let wb = ((px - ax) * (cy - ay) - (cx - ax) * (py - ay)) / det;
                    let wc = ((bx - ax) * (py - ay) - (px - ax) * (by - ay)) / det;
                    let wa = 1.0 - wb - wc;
                    if wa < -1e-9 || wb < -1e-9 || wc < -1e-9 {
                        continue;
                    }
                    let surface = wa * ha + wb * hb + wc * hc;
                    worst = worst.max((surface - f64::from(samples[(y * n + x) as usize])).abs());
                }
            }
        }
        worst as f32
    }

    /// The old `level_errors`: unstitched triangulations, at the samples only.
    fn old_level_errors(samples: &[f32], n: u32) -> Vec<f32> {
        (0..level_count(n))
            .map(|level| {
                let stitch = Stitch {
                    level,
                    sides: [level; 4],
                };
                sample_error(samples, n, &triangles(n, stitch))
            })
            .collect()
    }

    /// Interpolates `h` at `p` in triangle `abc` if `p` is inside or on it; all points in
    /// integer units (exact inside test).
    fn barycentric(p: (i64, i64), v: [(i64, i64); 3], h: [f64; 3]) -> Option<f64> {
        let cross = |o: (i64, i64), a: (i64, i64), b: (i64, i64)| {
            (a.0 - o.0) * (b.1 - o.1) - (a.1 - o.1) * (b.0 - o.0)
        };
        let area = cross(v[0], v[1], v[2]);
        let w = [
            cross(p, v[1], v[2]),
            cross(v[0], p, v[2]),
            cross(v[0], v[1], p),
        ];
        let inside = w.iter().all(|&w| w.signum() * area.signum() >= 0);
        inside.then(|| (0..3).map(|k| w[k] as f64 * h[k]).sum::<f64>() / area as f64)
    }

    /// The level-0 surface at the point `(x, y) / d` (integer units of `1 / d`), by point
    /// location among the two triangles of its cell.
    fn fine_at(samples: &[f32], n: u32, d: i64, x: i64, y: i64) -> f64 {
        let last = i64::from(n) - 1;
        let (cx, cy) = ((x / d).min(last - 1), (y / d).min(last - 1));
        let corner = |i: i64, j: i64| {
            let h = f64::from(samples[((cy + j) * i64::from(n) + cx + i) as usize]);
            (((cx + i) * d, (cy + j) * d), h)
        };
        for tri in [[(0, 0), (0, 1), (1, 0)], [(0, 1), (1, 0), (1, 1)]] {
            let c = tri.map(|(i, j)| corner(i, j));
            if let Some(v) = barycentric((x, y), c.map(|c| c.0), c.map(|c| c.1)) {
                return v;
            }
        }
        panic!("({x}, {y}) / {d} is in no cell of the tile");
    }

    /// The largest distance between triangle `t`'s plane and the level-0 surface over the
    /// points of `t` on the grid of step `1 / d`.
    fn dense_error(samples: &[f32], n: u32, t: &Triangle, d: i64) -> f64 {
        let v = t.map(|i| (i64::from(i % n) * d, i64::from(i / n) * d));
        let h = t.map(|i| f64::from(samples[i as usize]));
        let (x0, x1) = (v.iter().map(|p| p.0).min(), v.iter().map(|p| p.0).max());
        let (y0, y1) = (v.iter().map(|p| p.1).min(), v.iter().map(|p| p.1).max());
        let (Some(x0), Some(x1), Some(y0), Some(y1)) = (x0, x1, y0, y1) else {
            return 0.0;
        };
        let mut worst = 0.0f64;
        for y in y0..=y1 {
            for x in x0..=x1 {
                if let Some(drawn) = barycentric((x, y), v, h) {
                    worst = worst.max((drawn - fine_at(samples, n, d, x, y)).abs());
                }
            }
        }
        worst
    }

    /// Per level, the largest distance between the level-0 surface and any stitch's drawn
    /// surface, on the grid of step `1 / d`. The drawn surface on a triangle is its plane,
    /// so each distinct triangle is measured once and shared by the stitches drawing it.
    fn dense_level_errors(samples: &[f32], n: u32, d: i64) -> Vec<f64> {
        let mut worst = vec![0.0f64; level_count(n) as usize];
        let mut memo: HashMap<[u32; 3], f64> = HashMap::new();
        for stitch in all_stitches(n) {
            for t in triangles(n, stitch) {
                let mut key = t;
                key.sort_unstable();
                let e = *memo
                    .entry(key)
                    .or_insert_with(|| dense_error(samples, n, &t, d));
                let w = &mut worst[stitch.level as usize];
                *w = w.max(e);
            }
        }
        worst
    }

    /// The least common multiple of 16 and of the `|dx|`, `|dy|` and `|dx + dy|` of every
    /// edge any stitch draws: on the grid of that step lie all samples and all points where
    /// an edge crosses a grid line `x = i`, `y = j` or `x + y = k`.
    fn crossing_step(n: u32) -> i64 {
        let gcd = |mut a: i64, mut b: i64| {
            while b != 0 {
                (a, b) = (b, a % b);
            }
            a
        };
        let mut step = 16i64;
        for stitch in all_stitches(n) {
            for t in triangles(n, stitch) {
                for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                    let dx = i64::from(b % n) - i64::from(a % n);
                    let dy = i64::from(b / n) - i64::from(a / n);
                    for d in [dx.abs(), dy.abs(), (dx + dy).abs()] {
                        if d > 0 {
                            step = step / gcd(step, d) * d;
                        }
                    }
                }
            }
        }
        step
    }

    /// Twice the signed area of a triangle on the sample grid.
    fn area2(n: u32, t: &Triangle) -> i64 {
        let p = |i: u32| (i64::from(i % n), i64::from(i / n));
        let [(ax, ay), (bx, by), (cx, cy)] = t.map(p);
        (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
    }

    fn all_stitches(n: u32) -> Vec<Stitch> {
        let levels = level_count(n);
        let mut out = Vec::new();
        for level in 0..levels {
            for code in 0..(level + 1).pow(4) {
                let mut sides = [0; 4];
                let mut c = code;
                for side in &mut sides {
                    *side = c % (level + 1);
                    c /= level + 1;
                }
                out.push(Stitch { level, sides });
            }
        }
        out
    }

    #[test]
    fn every_index_set_covers_the_tile_once_without_degenerate_triangles() {
        for n in [3, 5, 9, 17] {
            let full = 2 * i64::from((n - 1) * (n - 1));
            for stitch in all_stitches(n) {
                let tris = triangles(n, stitch);
                let mut total = 0;
                for t in &tris {
                    let a = area2(n, t).abs();
                    assert!(a > 0, "degenerate {t:?} in {stitch:?}, n = {n}");
                    total += a;
                }
                assert_eq!(total, full, "{stitch:?}, n = {n}: the tile is covered once");
                // Every edge is shared by at most two triangles and, inside the tile, by
                // exactly two: no T-junction, no overlap.
                let mut edges: HashMap<(u32, u32), u32> = HashMap::new();
                for t in &tris {
                    for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                        *edges.entry((a.min(b), a.max(b))).or_default() += 1;
                    }
                }
                for (&(a, b), &count) in &edges {
                    let (ax, ay, bx, by) = (a % n, a / n, b % n, b / n);
                    let on_border = (ax == 0 && bx == 0)
                        || (ay == 0 && by == 0)
                        || (ax == n - 1 && bx == n - 1)
                        || (ay == n - 1 && by == n - 1);
                    let expected = if on_border { 1 } else { 2 };
                    assert_eq!(count, expected, "edge {a}-{b} of {stitch:?}, n = {n}");
                }
            }
        }
    }

    /// The vertices a tile's triangles use on one side (0 north, 1 east, 2 south, 3 west),
    /// as positions along that side.
    fn side_vertices(n: u32, tris: &[Triangle], side: usize) -> BTreeSet<u32> {
        let last = n - 1;
        tris.iter()
            .flatten()
            .filter_map(|&i| {
                let (x, y) = (i % n, i / n);
                match side {
                    0 => (y == 0).then_some(x),
                    1 => (x == last).then_some(y),
                    2 => (y == last).then_some(x),
                    _ => (x == 0).then_some(y),
                }
            })
            .collect()
    }

    #[test]
    fn neighbours_at_any_pair_of_levels_draw_their_shared_edge_with_the_same_vertices() {
        let n = 17;
        let levels = level_count(n);
        for a in 0..levels {
            for b in 0..levels {
                // Tile A west of tile B: A's east side meets B's west side.
                let sa = Stitch::new(a, [None, Some(b), None, None]);
                let sb = Stitch::new(b, [None, None, None, Some(a)]);
                let east = side_vertices(n, &triangles(n, sa), 1);
                let west = side_vertices(n, &triangles(n, sb), 3);
                assert_eq!(east, west, "levels {a} and {b}");
                let finer = 1 << a.min(b);
                assert_eq!(east.len() as u32, (n - 1) / finer + 1);
            }
        }
    }

    #[test]
    fn errors_grow_with_the_level_and_vanish_on_a_plane() {
        let n = 17;
        let plane: Vec<f32> = (0..n * n)
            .map(|i| (i % n) as f32 * 0.5 + (i / n) as f32)
            .collect();
        assert!(level_errors(&plane, n).iter().all(|&e| e < 1e-4));
        let bump: Vec<f32> = (0..n * n)
            .map(|i| {
                let (x, y) = ((i % n) as f32 - 8.0, (i / n) as f32 - 8.0);
                100.0 / (1.0 + x * x + y * y)
            })
            .collect();
        let errors = level_errors(&bump, n);
        assert_eq!(errors.len(), 5);
        assert_eq!(errors[0], 0.0);
        assert!(errors[4] > 50.0, "{errors:?}");
        assert!(errors[1] > 0.0);
    }

    #[test]
    fn level_errors_bound_every_stitched_triangulation_between_the_samples_too() {
        // n = 5: the grid holds every crossing, so the dense maximum is the exact one.
        let exact_step = crossing_step(5);
        assert!(exact_step <= 64, "step {exact_step}");
        for (n, d, seeds) in [(5, exact_step, 0..30), (9, 16, 0..6), (17, 16, 0..3)] {
            let mut widest_gap = 0.0f64;
            for seed in seeds {
                let samples = random_heights(n, seed);
                let errors = level_errors(&samples, n);
                let dense = dense_level_errors(&samples, n, d);
                assert_eq!(errors[0], 0.0);
                // Level 0 draws `F` itself: its dense error is 0 too.
                for (level, (&e, &m)) in errors.iter().zip(&dense).enumerate() {
                    assert!(
                        m <= f64::from(e) + 1e-4,
                        "n = {n}, seed {seed}, level {level}: {m} above the bound {e}"
                    );
                    if n == 5 {
                        assert!(
                            f64::from(e) <= m + 1e-4,
                            "n = {n}, seed {seed}, level {level}: bound {e} not reached ({m})"
                        );
                    }
                    widest_gap = widest_gap.max(f64::from(e) - m);
                }
            }
            eprintln!("n = {n}, 1/{d} grid: bound - dense maximum <= {widest_gap:.5}");
        }
    }

    #[test]
    fn a_valley_along_the_main_diagonal_is_missed_by_the_samples() {
        // V-shaped valley along the main diagonal, which the level-0 cells cross along
        // their anti-diagonals. At the second coarsest level (two cells a side, no centre)
        // every drawn triangle lies on one side of the valley, so every sample is exactly on
        // the coarse surface; the level-0 surface rises to 0.5 at each diagonal cell's
        // centre, where the coarse surface is 0.
        for n in [5, 17] {
            let samples: Vec<f32> = (0..n * n)
                .map(|i| ((i % n) as f32 - (i / n) as f32).abs() / 2.0)
                .collect();
            let level = level_count(n) - 2;
            let old = old_level_errors(&samples, n)[level as usize];
            let stitched: Vec<Triangle> = all_stitches(n)
                .into_iter()
                .filter(|s| s.level == level)
                .flat_map(|s| triangles(n, s))
                .collect();
            let at_samples = sample_error(&samples, n, &stitched);
            let new = level_errors(&samples, n)[level as usize];
            let dense = dense_level_errors(&samples, n, 16)[level as usize];
            eprintln!(
                "valley, n = {n}, level {level}: old {old}, stitched at the samples \
                 {at_samples}, new {new}, dense {dense}"
            );
            assert_eq!(old, 0.0);
            assert_eq!(at_samples, 0.0);
            assert!((new - 0.5).abs() < 1e-6, "{new}");
            assert!((f64::from(new) - dense).abs() < 1e-6, "{new} vs {dense}");
        }
    }

    #[test]
    fn a_stitched_kink_exceeds_every_sample_error_and_the_unstitched_error() {
        // n = 5, level 1, the north side stitched at level 0: the trapezoid zips (0, 0),
        // (1, 0), (2, 0) to (2, 2), so (0,0)-(1,0)-(2,2) and (1,0)-(2,0)-(2,2) fold along
        // (1,0)-(2,2) by the spike at (1, 0). The level-0 edge (1,1)-(2,1) crosses that fold
        // at (1.5, 1), where the first plane is 0.5 and the level-0 surface -1: 1.5, while
        // no sample of any stitch is off by more than 1 and the unstitched level is flat (0),
        // so its exact error is 1 too.
        let n = 5;
        let mut samples = vec![0.0f32; 25];
        samples[1] = 1.0; // (1, 0)
        samples[6] = -1.0; // (1, 1)
        samples[7] = -1.0; // (2, 1)
        let old = old_level_errors(&samples, n)[1];
        let unstitched = triangles(
            n,
            Stitch {
                level: 1,
                sides: [1; 4],
            },
        );
        let unstitched_exact = unstitched
            .iter()
            .map(|t| triangle_error(&samples, n, t))
            .fold(0.0, f64::max);
        let stitched: Vec<Triangle> = all_stitches(n)
            .into_iter()
            .filter(|s| s.level == 1)
            .flat_map(|s| triangles(n, s))
            .collect();
        let at_samples = sample_error(&samples, n, &stitched);
        let new = level_errors(&samples, n)[1];
        let dense = dense_level_errors(&samples, n, crossing_step(n))[1];
        let fold = triangle_error(&samples, n, &[0, 1, 12]);
        eprintln!(
            "kink: old {old}, unstitched exact {unstitched_exact}, stitched at the samples \
             {at_samples}, (0,0)-(1,0)-(2,2) exact {fold}, new {new}, dense {dense}"
        );
        assert_eq!(old, 1.0);
        assert!((unstitched_exact - 1.0).abs() < 1e-9);
        assert_eq!(at_samples, 1.0);
        assert!((fold - 1.5).abs() < 1e-9, "{fold}");
        assert!(new >= 1.5 && new > old, "{new} vs {old}");
        assert!((f64::from(new) - dense).abs() < 1e-6, "{new} vs {dense}");
    }

    #[test]
    fn full_size_tiles_are_measured_quickly_and_above_the_old_measure() {
        for (n, seed) in [(65, 1), (129, 2), (257, 3)] {
            let samples = random_heights(n, seed * 3);
            // Best and worst of a few runs: the machine may be busy.
            let mut times = Vec::new();
            let mut errors = Vec::new();
            for _ in 0..5 {
                let started = Instant::now();
                errors = level_errors(&samples, n);
                times.push(started.elapsed().as_secs_f64() * 1e3);
            }
            let best = times.iter().copied().fold(f64::INFINITY, f64::min);
            let worst = times.iter().copied().fold(0.0, f64::max);
            eprintln!(
                "level_errors, {n}x{n}: {best:.2} ms best of 5 ({worst:.2} ms worst, {} levels)",
                errors.len()
            );
            let old = old_level_errors(&samples, n);
            assert_eq!(errors.len(), level_count(n) as usize);
            assert_eq!(errors[0], 0.0);
            for (level, (&e, &o)) in errors.iter().zip(&old).enumerate() {
                assert!(
                    e.is_finite() && e >= o,
                    "n = {n}, level {level}: {e} < old {o}"
                );
            }
            eprintln!("  new {errors:.2?}\n  old {old:.2?}");
        }
    }

    /// The triangles a strip with restarts draws, as sorted index triples.
    fn strip_triangles(indices: &[u32]) -> BTreeSet<[u32; 3]> {
        let mut out = BTreeSet::new();
        for run in indices.split(|&i| i == RESTART) {
            for w in run.windows(3) {
                let mut t = [w[0], w[1], w[2]];
                t.sort_unstable();
                if t[0] != t[1] && t[1] != t[2] {
                    out.insert(t);
                }
            }
        }
        out
    }

    #[test]
    fn the_strips_draw_exactly_the_triangles() {
        for n in [5, 9, 17] {
            for stitch in all_stitches(n) {
                let expected: BTreeSet<[u32; 3]> = triangles(n, stitch)
                    .into_iter()
                    .map(|mut t| {
                        t.sort_unstable();
                        t
                    })
                    .collect();
                assert_eq!(strip_triangles(&strip(n, stitch)), expected, "{stitch:?}");
            }
        }
    }
}
