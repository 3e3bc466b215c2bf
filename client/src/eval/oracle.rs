//! An oracle triangle count: the fewest triangles a mesh of one tile needs so that no
//! sample is off by more than a given number of pixels. Methods are compared against it.
//!
//! **Tile.** A tile has `n x n` height samples, row-major, with `n = 2^k + 1` and `k >= 1`.
//! Sample `(col, row)` sits at index `row * n + col`.
//!
//! **Mesh family.** The meshes are right-triangulated irregular networks (RTIN), as in the
//! Martini library. Two root triangles split the square along the diagonal from
//! `(0, n - 1)` to `(n - 1, 0)`: the diagonal of `terrain_shared::mask`, from `(c0, r1)` to
//! `(c1, r0)`. A triangle `(a, b, c)` has its hypotenuse from `a` to `b` and its right angle
//! at `c`. Splitting it at the hypotenuse midpoint `m` gives the children `(c, a, m)` and
//! `(b, c, m)`, as Martini does. A triangle whose legs are one sample long cannot split.
//! All triangles wind the same way.
//!
//! **Error.** A sample's error is `|h - mesh height| * ppm(col, row)` pixels, with `ppm`
//! the caller's pixels per metre. A triangle's error is the largest over the samples inside
//! it or on its edges, against the plane through its three corners.
//!
//! **Valid mesh.** Every leaf triangle has an error of at most `threshold_px`. The mesh is
//! conforming: when a triangle splits, the triangle across its hypotenuse (if inside the
//! tile) splits too, so there is no T-junction. Its triangle count is its number of leaves:
//! two plus the number of split triangles.
//!
//! **Minimum.** Refine top-down: split every present triangle whose error is above the
//! threshold, then split what conformity forces, and repeat on the children. Every valid
//! mesh makes these splits. A present triangle that is too coarse must split in any valid
//! mesh. A split forces its hypotenuse neighbour, and that triangle's ancestors, to split
//! in any conforming mesh. So, by induction over the greedy splits, each one is in every
//! valid mesh's split set. The greedy mesh is itself valid, so it is the unique smallest.
//!
//! **Algorithm.** A triangle and its hypotenuse neighbour share their hypotenuse midpoint,
//! so splits are tracked per midpoint sample (Martini's vertices). Activating a sample
//! splits both triangles of its diamond. They must be present first, so the midpoints of
//! their parents are activated before. A triangle's error is scanned only when it becomes
//! present and has not been split already, and the scan stops at the first sample above
//! the threshold. The cost is at most `O(n^2 log n)`.
//!
//! **Bad input.** When `n` is not `2^k + 1` with `k >= 1`, `n * n` does not fit a `u32`,
//! or `heights.len() != n * n`, the count is 0 and the mesh is empty. Heights and `ppm`
//! are assumed free of NaN.

/// Leaves of the smallest valid conforming RTIN over the tile (see the module docs).
pub fn rtin_triangles(
    heights: &[f32],
    n: u32,
    ppm: impl Fn(u32, u32) -> f64,
    threshold_px: f64,
) -> u64 {
    Refinement::run(heights, n, &ppm, threshold_px).map_or(0, |r| 2 + r.splits)
}

/// The same mesh, as triangles of sample indices (row * n + col), for checking.
pub fn rtin_mesh(
    heights: &[f32],
    n: u32,
    ppm: impl Fn(u32, u32) -> f64,
    threshold_px: f64,
) -> Vec<[u32; 3]> {
    Refinement::run(heights, n, &ppm, threshold_px).map_or_else(Vec::new, |r| r.leaves())
}

/// Every triangle of the bisection hierarchy, in heap order: the roots are ids 2 and 3,
/// and the children of id `i` are `2i` and `2i + 1` (ids 0 and 1 are unused).
struct Hierarchy {
    n: u32,
    /// Corners `[a, b, c]` of each id: hypotenuse `a`-`b`, right angle at `c`.
    tris: Vec<[u32; 3]>,
    /// The first id that cannot split: ids from here on have legs one sample long.
    first_finest: usize,
    /// Per sample, the ids whose hypotenuse midpoint it is (its diamond); 0 when none.
    diamonds: Vec<[usize; 2]>,
}

impl Hierarchy {
    fn new(n: u32) -> Option<Hierarchy> {
        if n < 3 || !(n - 1).is_power_of_two() || u64::from(n).pow(2) > u64::from(u32::MAX) {
            return None;
        }
        let k = (n - 1).trailing_zeros();
        let first_finest = 1usize.checked_shl(2 * k + 1)?;
        let total = first_finest.checked_mul(2)?;
        let s = n - 1;
        let index = |col: u32, row: u32| row * n + col;
        let mut tris = vec![[0u32; 3]; total];
        tris[2] = [index(0, s), index(s, 0), index(0, 0)];
        tris[3] = [index(s, 0), index(0, s), index(s, s)];
        let mut diamonds = vec![[0usize; 2]; (n * n) as usize];
        for id in 2..first_finest {
            let [a, b, c] = tris[id];
            let m = midpoint(n, a, b);
            tris[2 * id] = [c, a, m];
            tris[2 * id + 1] = [b, c, m];
            let diamond = &mut diamonds[m as usize];
            let slot = usize::from(diamond[0] != 0);
            diamond[slot] = id;
        }
        Some(Hierarchy {
            n,
            tris,
            first_finest,
            diamonds,
        })
    }

    /// The hypotenuse midpoint of a triangle that can split.
    fn mid(&self, id: usize) -> usize {
        let [a, b, _] = self.tris[id];
        midpoint(self.n, a, b) as usize
    }
}

/// The sample halfway between samples `a` and `b`.
fn midpoint(n: u32, a: u32, b: u32) -> u32 {
    (a / n + b / n) / 2 * n + (a % n + b % n) / 2
}

/// The smallest valid mesh of one tile: which midpoints are active (split on both sides).
struct Refinement {
    hierarchy: Hierarchy,
    active: Vec<bool>,
    splits: u64,
}

impl Refinement {
    fn run(
        heights: &[f32],
        n: u32,
        ppm: &impl Fn(u32, u32) -> f64,
        threshold_px: f64,
    ) -> Option<Refinement> {
        // Checked before building the hierarchy, whose size follows `n`.
        if heights.len() as u64 != u64::from(n).pow(2) {
            return None;
        }
        let hierarchy = Hierarchy::new(n)?;
        let mut r = Refinement {
            active: vec![false; heights.len()],
            hierarchy,
            splits: 0,
        };
        // Present triangles not yet looked at.
        let mut pending = vec![2, 3];
        while let Some(id) = pending.pop() {
            if id >= r.hierarchy.first_finest {
                continue;
            }
            let m = r.hierarchy.mid(id);
            if !r.active[m] && r.too_coarse(id, heights, ppm, threshold_px) {
                r.activate(m, &mut pending);
            }
        }
        Some(r)
    }

    /// Splits both triangles of the diamond of sample `m`, after their parents, and queues
    /// their children.
    fn activate(&mut self, m: usize, pending: &mut Vec<usize>) {
        if self.active[m] {
            return;
        }
        self.active[m] = true;
        let diamond = self.hierarchy.diamonds[m];
        for id in diamond.into_iter().filter(|&id| id >= 4) {
            let parent_mid = self.hierarchy.mid(id / 2);
            self.activate(parent_mid, pending);
        }
        for id in diamond.into_iter().filter(|&id| id != 0) {
            self.splits += 1;
            pending.extend([2 * id, 2 * id + 1]);
        }
    }

    /// Whether some sample inside triangle `id` or on its edges is off its plane by more
    /// than `threshold_px` pixels.
    fn too_coarse(
        &self,
        id: usize,
        heights: &[f32],
        ppm: &impl Fn(u32, u32) -> f64,
        threshold_px: f64,
    ) -> bool {
        let n = self.hierarchy.n;
        let corners = self.hierarchy.tris[id];
        let [a, b, c] = corners.map(|i| (i64::from(i % n), i64::from(i / n)));
        let [ha, hb, hc] = corners.map(|i| f64::from(heights[i as usize]));
        let edge = |u: (i64, i64), v: (i64, i64), p: (i64, i64)| {
            (v.0 - u.0) * (p.1 - u.1) - (v.1 - u.1) * (p.0 - u.0)
        };
        let area2 = edge(a, b, c);
        let sign = area2.signum();
        let area2 = (area2 * sign) as f64;
        let (x0, x1) = (a.0.min(b.0).min(c.0), a.0.max(b.0).max(c.0));
        let (y0, y1) = (a.1.min(b.1).min(c.1), a.1.max(b.1).max(c.1));
        for y in y0..=y1 {
            for x in x0..=x1 {
                let p = (x, y);
                let (wa, wb, wc) = (
                    sign * edge(b, c, p),
                    sign * edge(c, a, p),
                    sign * edge(a, b, p),
                );
                if wa < 0 || wb < 0 || wc < 0 {
                    continue;
                }
                let plane = (wa as f64 * ha + wb as f64 * hb + wc as f64 * hc) / area2;
                let h = f64::from(heights[(y * i64::from(n) + x) as usize]);
                if (h - plane).abs() * ppm(x as u32, y as u32) > threshold_px {
                    return true;
                }
            }
        }
        false
    }

    /// The leaf triangles, depth first.
    fn leaves(&self) -> Vec<[u32; 3]> {
        let h = &self.hierarchy;
        let mut out = Vec::new();
        let mut stack = vec![3, 2];
        while let Some(id) = stack.pop() {
            if id < h.first_finest && self.active[h.mid(id)] {
                stack.extend([2 * id + 1, 2 * id]);
            } else {
                out.push(h.tris[id]);
            }
        }
        out
    }
}

/// What regular grids need per block, beside the oracle: for a tile cut into square
/// blocks of `block` cells, each block drawn as its own regular grid at the coarsest step
/// that keeps every sample of the block within `threshold_px` at `ppm_of_block(column,
/// row)` (the block's pixels per metre, at its own nearest point), the triangles of the
/// blocks' grids summed. `geomipmap` takes power-of-two steps (a GeoMipMap level), `strip`
/// any step (a strip mask: a grid of every `s`th sample and the last). Seams between blocks
/// of different steps are not counted: this is a floor for selection by block, the finer the
/// block the nearer the oracle. Zero for bad input (as [`rtin_triangles`]) or a `block`
/// that does not divide `n - 1`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BlockGrids {
    pub geomipmap: u64,
    pub strip: u64,
}

pub fn block_grid_triangles(
    heights: &[f32],
    n: u32,
    block: u32,
    ppm_of_block: impl Fn(u32, u32) -> f64,
    threshold_px: f64,
) -> BlockGrids {
    let cells = n.saturating_sub(1);
    let square = (n as usize).checked_mul(n as usize);
    if n < 3 || !cells.is_power_of_two() || square != Some(heights.len()) {
        return BlockGrids::default();
    }
    if block == 0 || block > cells || !cells.is_multiple_of(block) {
        return BlockGrids::default();
    }
    let blocks = cells / block;
    let mut out = BlockGrids::default();
    for br in 0..blocks {
        for bc in 0..blocks {
            let (c0, r0) = (bc * block, br * block);
            let limit = (threshold_px / ppm_of_block(bc, br)) as f32;
            // The block as a tile of its own: a grid of step `s` from its corner (the last
            // cell shorter) is its strip mask of level `s - 1`, whose error the masks' own
            // measure gives.
            let mut own = Vec::with_capacity(((block + 1) * (block + 1)) as usize);
            for r in r0..=r0 + block {
                own.extend_from_slice(
                    &heights[(r * n + c0) as usize..=(r * n + c0 + block) as usize],
                );
            }
            let within =
                |s: u32| terrain_shared::mask::max_vertical_error(&own, block + 1, s - 1) <= limit;
            let grid = |s: u32| 2 * u64::from(block.div_ceil(s)).pow(2);
            let mut s = block;
            while s > 1 && !within(s) {
                s /= 2;
            }
            out.geomipmap += grid(s);
            let mut s = block;
            while s > 1 && !within(s) {
                s -= 1;
            }
            out.strip += grid(s);
        }
    }
    out
}

/// The fewest triangles one strip mask of the whole tile needs (the strip-mask paper's
/// method draws one mask a tile) to keep every sample within `threshold_px`, each sample's
/// error projected at the sample itself by `ppm(column, row)`: what such a method needs
/// under the tightest sound bound there is, since a bound over a region can only raise a
/// sample's projected error, never lower it. The coarsest mask level within the threshold,
/// searched from the coarsest (errors are not monotone in the level); level 0, the full
/// tile, always is. A mask's surface is `terrain_shared::mask`'s, in the builder's `f32`
/// arithmetic ([`terrain_shared::mask::max_vertical_error`]). Zero for bad input, as [`rtin_triangles`].
pub fn one_mask_triangles(
    heights: &[f32],
    n: u32,
    ppm: impl Fn(u32, u32) -> f64,
    threshold_px: f64,
) -> u64 {
    let square = (n as usize).checked_mul(n as usize);
    if n < 2 || square != Some(heights.len()) {
        return 0;
    }
    // The error each sample may have, metres.
    let allowed: Vec<f64> = (0..n * n)
        .map(|i| threshold_px / ppm(i % n, i / n))
        .collect();
    let within = |level: u32| -> bool {
        let kept = terrain_shared::mask::kept_indices(n, level);
        let at = |c: u32, r: u32| heights[(r * n + c) as usize];
        for rows in kept.windows(2) {
            let (r0, r1) = (rows[0], rows[1]);
            for cols in kept.windows(2) {
                let (c0, c1) = (cols[0], cols[1]);
                let (h00, h10, h01, h11) = (at(c0, r0), at(c1, r0), at(c0, r1), at(c1, r1));
                for r in r0..=r1 {
                    let v = (r - r0) as f32 / (r1 - r0) as f32;
                    for c in c0..=c1 {
                        let u = (c - c0) as f32 / (c1 - c0) as f32;
                        let surface = terrain_shared::mask::cell_height(h00, h10, h01, h11, u, v);
                        let i = (r * n + c) as usize;
                        if f64::from((heights[i] - surface).abs()) > allowed[i] {
                            return false;
                        }
                    }
                }
            }
        }
        true
    };
    let level = (1..terrain_shared::mask::level_count(n))
        .rev()
        .find(|&l| within(l))
        .unwrap_or(0);
    u64::from(terrain_shared::mask::triangle_count(n, level))
}

#[cfg(test)]
mod tests {

    #[test]
    fn one_mask_per_tile_takes_the_coarsest_level_every_sample_allows() {
        let n = 17;
        let plane: Vec<f32> = (0..n * n)
            .map(|i| (i % n) as f32 * 0.5 + (i / n) as f32)
            .collect();
        // A plane is one cell (two triangles) at any depth.
        assert_eq!(one_mask_triangles(&plane, n, |_, _| 1.0, 1.0), 2);
        // A spike of 1 m at (5, 5), seen at 10 px a metre there and a thousandth of that
        // elsewhere: only masks keeping column and row 5 hold it within 1 px, the coarsest
        // of them the grid of every 5th sample (4 x 4 cells, 32 triangles).
        let mut spike = plane.clone();
        spike[(5 * n + 5) as usize] += 1.0;
        let near_spike = |c: u32, r: u32| if (c, r) == (5, 5) { 10.0 } else { 1e-3 };
        assert_eq!(one_mask_triangles(&spike, n, near_spike, 1.0), 32);
        // Seen from far off (a tenth of a pixel a metre) it needs nothing.
        assert_eq!(one_mask_triangles(&spike, n, |_, _| 0.1, 1.0), 2);
        // Everywhere near: every sample exact, the full tile (16 x 16 cells).
        assert_eq!(one_mask_triangles(&spike, n, |_, _| 1e6, 1.0), 512);
        // Bad input counts nothing.
        assert_eq!(one_mask_triangles(&spike[1..], n, near_spike, 1.0), 0);
    }

    #[test]
    fn block_grids_keep_a_plane_coarse_and_refine_only_the_block_with_a_spike() {
        let n = 17;
        let plane: Vec<f32> = (0..n * n)
            .map(|i| (i % n) as f32 * 0.5 + (i / n) as f32)
            .collect();
        for block in [16, 8, 4, 2] {
            let blocks = u64::from(16 / block).pow(2);
            let g = block_grid_triangles(&plane, n, block, |_, _| 1.0, 0.01);
            assert_eq!(
                g,
                BlockGrids {
                    geomipmap: 2 * blocks,
                    strip: 2 * blocks
                },
                "{block}"
            );
        }
        // A spike of 10 m at (5, 5): with blocks of 4 only the block holding it refines,
        // to full resolution (4 x 4 cells); the other 15 stay at one cell.
        let mut spike = plane.clone();
        spike[(5 * n + 5) as usize] += 10.0;
        let g = block_grid_triangles(&spike, n, 4, |_, _| 1.0, 1.0);
        assert_eq!(g.geomipmap, 15 * 2 + 2 * 16);
        // A strip mask of step 3 keeps samples 0, 3 and 4 of the block (4 cells as 2):
        // sample 1 of the block, the spike's, is off the grid, so it goes to step 1 too.
        assert_eq!(g.strip, 15 * 2 + 2 * 16);
        // A ridge along column 2 of a 4-cell tile, its slopes linear: a grid of every 2nd
        // sample holds it exactly (2 x 2 cells), one of every 3rd or 4th does not.
        let ridge: Vec<f32> = (0..25)
            .map(|i: i32| 10.0 - 5.0 * ((i % 5) - 2).abs() as f32)
            .collect();
        assert_eq!(
            block_grid_triangles(&ridge, 5, 4, |_, _| 1.0, 1.0),
            BlockGrids {
                geomipmap: 8,
                strip: 8
            }
        );
        // Far away (a tenth of a pixel a metre) the spike is within the threshold.
        let far = block_grid_triangles(&spike, n, 4, |_, _| 0.05, 1.0);
        assert_eq!(
            far,
            BlockGrids {
                geomipmap: 32,
                strip: 32
            }
        );
        // Bad input counts nothing.
        assert_eq!(
            block_grid_triangles(&spike, n, 3, |_, _| 1.0, 1.0),
            BlockGrids::default()
        );
        assert_eq!(
            block_grid_triangles(&spike[1..], n, 4, |_, _| 1.0, 1.0),
            BlockGrids::default()
        );
    }
    use super::*;
    use std::collections::{BTreeSet, HashMap, HashSet};
    use std::time::Instant;

    use crate::testing::Rng;

    type Point = (i64, i64);

    fn point(n: u32, i: u32) -> Point {
        (i64::from(i % n), i64::from(i / n))
    }

    /// Twice the signed area of `(a, b, c)`.
    fn cross(a: Point, b: Point, c: Point) -> i64 {
        (b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0)
    }

    /// Largest error in pixels of a triangle against the samples inside it or on its edges.
    fn triangle_error(
        heights: &[f32],
        n: u32,
        ppm: &dyn Fn(u32, u32) -> f64,
        [a, b, c]: [Point; 3],
    ) -> f64 {
        let area = cross(a, b, c) as f64;
        let h = |p: Point| f64::from(heights[(p.1 * i64::from(n) + p.0) as usize]);
        let mut worst = 0.0f64;
        for y in a.1.min(b.1).min(c.1)..=a.1.max(b.1).max(c.1) {
            for x in a.0.min(b.0).min(c.0)..=a.0.max(b.0).max(c.0) {
                let p = (x, y);
                // Barycentric coordinates: all in [0, 1] inside or on an edge.
                let (u, v, w) = (
                    cross(p, b, c) as f64 / area,
                    cross(a, p, c) as f64 / area,
                    cross(a, b, p) as f64 / area,
                );
                if u < 0.0 || v < 0.0 || w < 0.0 {
                    continue;
                }
                let plane = u * h(a) + v * h(b) + w * h(c);
                worst = worst.max((h(p) - plane).abs() * ppm(x as u32, y as u32));
            }
        }
        worst
    }

    /// Whether every sample is within `threshold` of every leaf containing it.
    fn is_valid(
        heights: &[f32],
        n: u32,
        ppm: &dyn Fn(u32, u32) -> f64,
        threshold: f64,
        mesh: &[[u32; 3]],
    ) -> bool {
        mesh.iter()
            .all(|t| triangle_error(heights, n, ppm, t.map(|i| point(n, i))) <= threshold)
    }

    /// Whether the leaves tile the square exactly once, wind alike and have no T-junction
    /// (no vertex strictly inside another leaf's edge).
    fn is_conforming_cover(n: u32, mesh: &[[u32; 3]]) -> bool {
        let s = i64::from(n - 1);
        let areas: Vec<i64> = mesh
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| point(n, i));
                cross(a, b, c)
            })
            .collect();
        let alike = areas.iter().all(|&a| a < 0) || areas.iter().all(|&a| a > 0);
        if !alike || areas.iter().map(|a| a.abs()).sum::<i64>() != 2 * s * s {
            return false;
        }
        let vertices: HashSet<Point> = mesh.iter().flatten().map(|&i| point(n, i)).collect();
        mesh.iter().all(|t| {
            let [a, b, c] = t.map(|i| point(n, i));
            [(a, b), (b, c), (c, a)].into_iter().all(|(p, q)| {
                let (dx, dy) = (q.0 - p.0, q.1 - p.1);
                let steps = dx.abs().max(dy.abs());
                let (sx, sy) = (dx.signum(), dy.signum());
                (1..steps).all(|i| !vertices.contains(&(p.0 + i * sx, p.1 + i * sy)))
            })
        })
    }

    /// Triangles as sets of corners, for comparing meshes regardless of order.
    fn as_set(mesh: &[[u32; 3]]) -> BTreeSet<[u32; 3]> {
        mesh.iter()
            .map(|t| {
                let mut t = *t;
                t.sort_unstable();
                t
            })
            .collect()
    }

    /// One node of an independently built bisection hierarchy.
    struct Node {
        corners: [Point; 3],
        parent: Option<usize>,
        /// The conformity group (shared hypotenuse) of a node that can split.
        group: Option<usize>,
    }

    /// Every conforming RTIN of a tile of `n` samples: each as the indices of its leaves
    /// into the returned nodes.
    fn all_meshes(n: u32) -> (Vec<Node>, Vec<Vec<usize>>) {
        let s = i64::from(n - 1);
        let mut nodes = vec![
            Node {
                corners: [(0, s), (s, 0), (0, 0)],
                parent: None,
                group: None,
            },
            Node {
                corners: [(s, 0), (0, s), (s, s)],
                parent: None,
                group: None,
            },
        ];
        // Split nodes in order; children are appended, so this visits the whole hierarchy.
        let mut groups: HashMap<[Point; 2], usize> = HashMap::new();
        let mut i = 0;
        while i < nodes.len() {
            let [a, b, c] = nodes[i].corners;
            if (a.0 + b.0) % 2 == 0 && (a.1 + b.1) % 2 == 0 {
                let m = ((a.0 + b.0) / 2, (a.1 + b.1) / 2);
                // A triangle and its neighbour across the hypotenuse split together.
                let key = if a < b { [a, b] } else { [b, a] };
                let next = groups.len();
                nodes[i].group = Some(*groups.entry(key).or_insert(next));
                for corners in [[c, a, m], [b, c, m]] {
                    nodes.push(Node {
                        corners,
                        parent: Some(i),
                        group: None,
                    });
                }
            }
            i += 1;
        }
        // A split needs the parents of the group's triangles split.
        let mut needs = vec![0u64; groups.len()];
        for node in &nodes {
            if let (Some(g), Some(p)) = (node.group, node.parent)
                && let Some(parent_group) = nodes[p].group
            {
                needs[g] |= 1 << parent_group;
            }
        }
        let mut meshes = Vec::new();
        for mask in 0u64..1 << groups.len() {
            let closed = (0..groups.len())
                .filter(|&g| mask >> g & 1 == 1)
                .all(|g| needs[g] & !mask == 0);
            if !closed {
                continue;
            }
            let split = |g: Option<usize>| g.is_some_and(|g| mask >> g & 1 == 1);
            let leaves = (0..nodes.len())
                .filter(|&i| nodes[i].parent.is_none_or(|p| split(nodes[p].group)))
                .filter(|&i| !split(nodes[i].group))
                .collect();
            meshes.push(leaves);
        }
        (nodes, meshes)
    }

    /// A random tile: a tilted plane plus one spike, rough noise or gentle waves.
    fn random_tile(rng: &mut Rng, n: u32, kind: u32) -> Vec<f32> {
        let (tx, ty) = (rng.range(-2.0, 2.0), rng.range(-2.0, 2.0));
        let amp = rng.range(0.0, 4.0);
        let (fx, fy) = (rng.range(0.1, 1.5), rng.range(0.1, 1.5));
        let spike = (rng.next() % u64::from(n * n)) as u32;
        (0..n * n)
            .map(|i| {
                let (x, y) = (f64::from(i % n), f64::from(i / n));
                let bump = match kind % 3 {
                    0 => amp * f64::from(u8::from(i == spike)),
                    1 => rng.range(-amp, amp),
                    _ => amp * (fx * x).sin() * (fy * y).cos(),
                };
                (tx * x + ty * y + bump) as f32
            })
            .collect()
    }

    #[test]
    fn brute_force_agrees_with_every_conforming_mesh_of_a_5x5_tile() {
        let n = 5;
        let (nodes, meshes) = all_meshes(n);
        assert!(meshes.len() > 100, "only {} meshes", meshes.len());
        let ppm = |c: u32, _r: u32| 1.0 + 0.5 * f64::from(c);
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        let mut counts = BTreeSet::new();
        for tile in 0..60 {
            let heights = random_tile(&mut rng, n, tile);
            let errors: Vec<f64> = nodes
                .iter()
                .map(|node| triangle_error(&heights, n, &ppm, node.corners))
                .collect();
            for threshold in [0.1, 0.5, 2.0, 8.0] {
                let valid: Vec<&Vec<usize>> = meshes
                    .iter()
                    .filter(|leaves| leaves.iter().all(|&i| errors[i] <= threshold))
                    .collect();
                let best = valid.iter().map(|leaves| leaves.len()).min().unwrap_or(0);
                let got = rtin_triangles(&heights, n, ppm, threshold);
                assert_eq!(got, best as u64, "tile {tile}, threshold {threshold}");
                counts.insert(got);

                // The minimum is unique and is the returned mesh.
                let mesh = rtin_mesh(&heights, n, ppm, threshold);
                let smallest: Vec<BTreeSet<[u32; 3]>> = valid
                    .iter()
                    .filter(|leaves| leaves.len() == best)
                    .map(|leaves| {
                        let tris: Vec<[u32; 3]> = leaves
                            .iter()
                            .map(|&i| nodes[i].corners.map(|p| (p.1 * i64::from(n) + p.0) as u32))
                            .collect();
                        as_set(&tris)
                    })
                    .collect();
                assert_eq!(
                    smallest,
                    vec![as_set(&mesh)],
                    "tile {tile}, threshold {threshold}"
                );
                assert_eq!(mesh.len() as u64, got);
                assert!(is_valid(&heights, n, &ppm, threshold, &mesh));
                assert!(is_conforming_cover(n, &mesh));
            }
        }
        assert!(counts.len() >= 6, "too few distinct counts: {counts:?}");
    }

    #[test]
    fn planes_need_two_triangles_and_rough_data_at_zero_needs_all() {
        let mut rng = Rng(7);
        for n in [3, 5, 9, 65, 129] {
            let (a, b, c) = (
                rng.range(-50.0, 50.0),
                rng.range(-3.0, 3.0),
                rng.range(-3.0, 3.0),
            );
            let plane: Vec<f32> = (0..n * n)
                .map(|i| (a + b * f64::from(i % n) + c * f64::from(i / n)) as f32)
                .collect();
            assert_eq!(rtin_triangles(&plane, n, |_, _| 1.0, 1e-3), 2, "n {n}");
        }
        for n in [3, 5, 9, 17, 33] {
            let rough: Vec<f32> = (0..n * n).map(|_| rng.range(0.0, 10.0) as f32).collect();
            let full = 2 * u64::from(n - 1).pow(2);
            assert_eq!(rtin_triangles(&rough, n, |_, _| 1.0, 0.0), full, "n {n}");
            let mesh = rtin_mesh(&rough, n, |_, _| 1.0, 0.0);
            assert_eq!(mesh.len() as u64, full);
            assert!(is_conforming_cover(n, &mesh));
        }
    }

    #[test]
    fn large_tiles_are_valid_conforming_and_monotone_in_the_threshold() {
        let mut rng = Rng(42);
        for n in [65u32, 129] {
            let heights = random_tile(&mut rng, n, 2);
            let heights: Vec<f32> = heights
                .iter()
                .map(|h| h + rng.range(0.0, 0.3) as f32)
                .collect();
            let ppm = |_c: u32, r: u32| 0.5 + 3.0 * f64::from(r) / f64::from(n);
            let mut last = u64::MAX;
            let mut counts = Vec::new();
            for threshold in [0.05, 0.2, 1.0, 5.0] {
                let mesh = rtin_mesh(&heights, n, ppm, threshold);
                let count = rtin_triangles(&heights, n, ppm, threshold);
                assert_eq!(mesh.len() as u64, count);
                assert!((2..=2 * u64::from(n - 1).pow(2)).contains(&count));
                assert!(count <= last, "n {n}: {count} after {last}");
                assert!(is_valid(&heights, n, &ppm, threshold, &mesh), "n {n}");
                assert!(is_conforming_cover(n, &mesh), "n {n}");
                last = count;
                counts.push(count);
            }
            assert!(counts[0] > counts[3], "n {n}: {counts:?}");
        }
    }

    #[test]
    fn bad_input_gives_nothing() {
        for n in [0u32, 1, 2, 4, 6, 10] {
            let heights = vec![0.0f32; (n * n) as usize];
            assert_eq!(rtin_triangles(&heights, n, |_, _| 1.0, 1.0), 0, "n {n}");
            assert!(rtin_mesh(&heights, n, |_, _| 1.0, 1.0).is_empty());
        }
        assert_eq!(rtin_triangles(&[0.0; 24], 5, |_, _| 1.0, 1.0), 0);
        assert!(rtin_mesh(&[0.0; 26], 5, |_, _| 1.0, 1.0).is_empty());
        assert_eq!(rtin_triangles(&[0.0; 25], 5, |_, _| 1.0, 1.0), 2);
    }

    /// `cargo test --release -p terrain-client --lib eval::oracle -- --ignored --nocapture`
    #[test]
    #[ignore = "timing; run in release"]
    fn timing() {
        let mut rng = Rng(3);
        for n in [129u32, 257] {
            let heights: Vec<f32> = random_tile(&mut rng, n, 2)
                .iter()
                .map(|h| h + rng.range(0.0, 0.2) as f32)
                .collect();
            let ppm = |_c: u32, r: u32| 0.5 + 3.0 * f64::from(r) / f64::from(n);
            for threshold in [0.0, 0.1, 1.0] {
                let start = Instant::now();
                let runs = 20;
                let mut count = 0;
                for _ in 0..runs {
                    count = rtin_triangles(&heights, n, ppm, threshold);
                }
                let ms = start.elapsed().as_secs_f64() * 1e3 / f64::from(runs);
                println!("n {n}, threshold {threshold}: {count} triangles, {ms:.2} ms");
            }
        }
    }
}
