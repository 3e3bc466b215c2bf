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
//! (one cell) a tile with finer neighbours is a fan around its centre sample.
//!
//! **Index sets** are keyed by [`Stitch`] (own level and the four stitch levels), built on
//! first use and shared by every tile, as strips separated by primitive restarts
//! ([`RESTART`]).

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
    let (mut centre, border) = parts(n, stitch);
    centre.extend(border);
    centre
}

/// The triangles of the centre region and of the rest (trapezoids, or the one-cell tile).
fn parts(n: u32, stitch: Stitch) -> (Vec<Triangle>, Vec<Triangle>) {
    let last = n - 1;
    let s = 1u32 << stitch.level;
    let at = |x: u32, y: u32| y * n + x;
    let cells = last / s;
    let mut out = Vec::new();
    let mut centre = Vec::new();
    if cells == 1 {
        if stitch.sides.iter().all(|&l| l == stitch.level) {
            out.push([at(0, 0), at(0, last), at(last, 0)]);
            out.push([at(0, last), at(last, 0), at(last, last)]);
        } else {
            // A fan around the centre over the boundary, each side at its stitch step.
            let c = at(last / 2, last / 2);
            let ring = boundary(n, stitch);
            for k in 0..ring.len() {
                out.push([c, ring[k], ring[(k + 1) % ring.len()]]);
            }
        }
        return (centre, out);
    }
    // Centre: cells whose corners are all at least one step inside.
    for r in 1..cells - 1 {
        for c in 1..cells - 1 {
            let (x0, y0, x1, y1) = (c * s, r * s, (c + 1) * s, (r + 1) * s);
            centre.push([at(x0, y0), at(x0, y1), at(x1, y0)]);
            centre.push([at(x0, y1), at(x1, y0), at(x1, y1)]);
        }
    }
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
    (centre, out)
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
    let (_, border) = parts(n, stitch);
    let mut out = Vec::new();
    for r in 1..cells.saturating_sub(1) {
        for c in 1..cells {
            out.push(r * s * n + c * s);
            out.push((r + 1) * s * n + c * s);
        }
        out.push(RESTART);
    }
    for t in &border {
        out.extend_from_slice(t);
        out.push(RESTART);
    }
    out
}

/// Maximum vertical error, metres, of each level of a tile's `samples` (`n x n` heights,
/// row-major), against the full resolution: for every sample, the distance to the level's
/// surface (its triangles with no stitching) above or below it. Level 0 has none.
pub fn level_errors(samples: &[f32], n: u32) -> Vec<f32> {
    (0..level_count(n))
        .map(|level| {
            let stitch = Stitch {
                level,
                sides: [level; 4],
            };
            max_error(samples, n, &triangles(n, stitch))
        })
        .collect()
}

/// Largest distance between a sample and the surface of `triangles` at its position.
fn max_error(samples: &[f32], n: u32, triangles: &[Triangle]) -> f32 {
    let xy = |i: u32| (f64::from(i % n), f64::from(i / n));
    let mut worst = 0.0f64;
    for t in triangles {
        let [(ax, ay), (bx, by), (cx, cy)] = t.map(xy);
        let [ha, hb, hc] = t.map(|i| f64::from(samples[i as usize]));
        let det = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay);
        if det == 0.0 {
            continue;
        }
        let (x0, x1) = (ax.min(bx).min(cx) as u32, ax.max(bx).max(cx) as u32);
        let (y0, y1) = (ay.min(by).min(cy) as u32, ay.max(by).max(cy) as u32);
        for y in y0..=y1 {
            for x in x0..=x1 {
                let (px, py) = (f64::from(x), f64::from(y));
                // Barycentric weights; a sample on an edge belongs to both triangles.
                let wb = ((px - ax) * (cy - ay) - (cx - ax) * (py - ay)) / det;
                let wc = ((bx - ax) * (py - ay) - (px - ax) * (by - ay)) / det;
                let wa = 1.0 - wb - wc;
                if wa < -1e-9 || wb < -1e-9 || wc < -1e-9 {
                    continue;
                }
                let surface = wa * ha + wb * hb + wc * hc;
                let h = f64::from(samples[(y * n + x) as usize]);
                worst = worst.max((surface - h).abs());
            }
        }
    }
    worst as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::{BTreeSet, HashMap};

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
