//! The quadtree progressive patches of a database (Yusov and Turlapov 2007; the shared
//! geometry is [`terrain_shared::quadtree`]), built from the whole level-0 raster after
//! the tiles.
//!
//! 1. **Pyramid**: the cell-centred layers, each from the one below by the order-4 Neville
//!    interpolating filter, borders extended by the nearest sample.
//! 2. **Patches of the finest meta level** (the level-0 tiles) start from the full
//!    quadtree and merge, finest level first, every node whose four children are active
//!    while the triangles the merge makes (`ΔT`) stay within the tolerance: the largest
//!    vertical distance from a level-0 sample under a triangle to the triangle's plane
//!    (section 3.4's `Err(ΔT) < τ`, measured against the samples themselves). The
//!    triangles a merge makes are found along the merged node's border
//!    ([`quadtree::triangles_of_leaf`]); a merge is undone at its first triangle past the
//!    tolerance, and a triangle's samples are those of each row's span inside it.
//! 3. **Coarser meta levels** start from their children's active vertices one level up
//!    (the children's finest level dropped), take the error of that start as their
//!    tolerance, and merge the same way. Their errors too are measured against every
//!    level-0 sample: the paper's cheaper estimate (child error plus distance to the
//!    children's surface) was not needed at the sizes measured (`BENCHMARKS.md`).
//! 4. **Bodies**: each patch's split bits from its parent's quarter and the heights it
//!    adds ([`quadtree::encode_patch`]); the index gives each one's hash, size, error and
//!    height bounds.
//!
//! Memory: the raster and its pyramid are held whole (about 11 bytes a sample), unlike
//! the tiles' bands; the patches are opt-in (`--patches`).

use super::BuildError;
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use terrain_shared::quadtree::{self, Cut, Parent, PatchEntry, Tree, Vertex};
use terrain_shared::{Manifest, TileId};

const SUBCODES: f64 = quadtree::SUBCODES as f64;

/// The cell-centred pyramid, in [`quadtree::SUBCODES`] (unrounded).
#[derive(Debug)]
pub struct Pyramid {
    levels: Vec<(Vec<f64>, usize, usize)>,
}

impl Pyramid {
    /// Levels `0..=top` from the level-0 codes.
    pub fn new(codes: &[i32], width: usize, height: usize, top: u32) -> Pyramid {
        let level0: Vec<f64> = codes.iter().map(|&c| f64::from(c) * SUBCODES).collect();
        let mut levels = vec![(level0, width, height)];
        for _ in 0..top {
            let (fine, w, h) = levels.last().expect("level 0");
            levels.push(quadtree::neville(fine, *w, *h));
        }
        Pyramid { levels }
    }

    /// Vertex `(x, y)` of level `k`, clamped into the level.
    pub fn at(&self, k: u32, x: i64, y: i64) -> f64 {
        let (data, w, h) = &self.levels[k as usize];
        let x = x.clamp(0, *w as i64 - 1) as usize;
        let y = y.clamp(0, *h as i64 - 1) as usize;
        data[y * w + x]
    }

    /// Row `y` of the level-0 samples, inside the raster.
    fn row(&self, y: usize) -> &[f64] {
        let (data, w, _) = &self.levels[0];
        &data[y * w..(y + 1) * w]
    }

    /// The height code of vertex `v` of patch `(level, x, y)` (see the module docs of
    /// [`terrain_shared::quadtree`]: ring vertices are means across the side, but on a far
    /// side moved out to the terrain's last sample, `snapped`, the outer vertex alone).
    pub fn vertex(&self, tree: Tree, id: TileId, snapped: [bool; 2], v: Vertex) -> i32 {
        let (x, y) = (i64::from(id.x), i64::from(id.y));
        let k = |l: u8| id.level + tree.n - u32::from(l);
        let h = match v {
            Vertex::Node { l, i, j } => {
                self.at(k(l), (x << l) + i64::from(i), (y << l) + i64::from(j))
            }
            Vertex::Side { side, l, k: along } => {
                let a = i64::from(along);
                let (lo_x, lo_y) = (x << l, y << l);
                let (hi_x, hi_y) = ((x + 1) << l, (y + 1) << l);
                let pair = match side {
                    0 => [(lo_x + a, lo_y - 1), (lo_x + a, lo_y)],
                    1 if snapped[0] => [(hi_x, lo_y + a), (hi_x, lo_y + a)],
                    1 => [(hi_x - 1, lo_y + a), (hi_x, lo_y + a)],
                    2 if snapped[1] => [(lo_x + a, hi_y), (lo_x + a, hi_y)],
                    2 => [(lo_x + a, hi_y - 1), (lo_x + a, hi_y)],
                    _ => [(lo_x - 1, lo_y + a), (lo_x, lo_y + a)],
                };
                pair.iter()
                    .map(|&(px, py)| self.at(k(l), px, py))
                    .sum::<f64>()
                    / 2.0
            }
            Vertex::Corner { corner, l } => {
                let cx = if matches!(corner, 1 | 2) {
                    (x + 1) << l
                } else {
                    x << l
                };
                let cy = if matches!(corner, 2 | 3) {
                    (y + 1) << l
                } else {
                    y << l
                };
                let far_x = snapped[0] && matches!(corner, 1 | 2);
                let far_y = snapped[1] && matches!(corner, 2 | 3);
                let (ax, ay) = (
                    if far_x { cx } else { cx - 1 },
                    if far_y { cy } else { cy - 1 },
                );
                [(ax, ay), (cx, ay), (ax, cy), (cx, cy)]
                    .iter()
                    .map(|&(px, py)| self.at(k(l), px, py))
                    .sum::<f64>()
                    / 4.0
            }
        };
        h.round().clamp(f64::from(i32::MIN), f64::from(i32::MAX)) as i32
    }
}

/// The samples of one row of a triangle's bounding span, and what weighs them.
struct Span<'a> {
    samples: &'a [f64],
    /// Column of `samples[0]`.
    first: usize,
    /// The corners: sample column, row and height.
    p: &'a [[f64; 3]; 3],
    /// `e2x (y - p0y)` and `e1x (y - p0y)`.
    c: [f64; 2],
    /// `e1y` and `e2y`.
    e: [f64; 2],
}

impl Span<'_> {
    /// The largest of `worst` and the distances of the span's samples inside the triangle
    /// to its plane; `weigh` divides a weight's numerator by the determinant (a
    /// monomorphised closure, so that a division is not paid where a multiplication does).
    #[inline(always)]
    fn worst(&self, mut worst: f64, weigh: impl Fn(f64) -> f64) -> f64 {
        let eps = 1e-9;
        let p = self.p;
        for (k, &sample) in self.samples.iter().enumerate() {
            let dx = (self.first + k) as f64 - p[0][0];
            let w1 = weigh(dx * self.e[1] - self.c[0]);
            let w2 = weigh(self.c[1] - dx * self.e[0]);
            let w0 = 1.0 - w1 - w2;
            if w0 < -eps || w1 < -eps || w2 < -eps {
                continue;
            }
            let z = w0 * p[0][2] + w1 * p[1][2] + w2 * p[2][2];
            let distance = (sample - z).abs();
            // Heights are finite: no NaN for `max` to take care of.
            if distance > worst {
                worst = distance;
            }
        }
        worst
    }
}

/// A triangle in samples ([`Patch::placed`]): corners, determinant, and its bounding box's
/// first column and row and last column and row.
type Placed = ([[f64; 3]; 3], f64, [usize; 2], [f64; 2]);

/// One patch while it is built.
struct Patch<'a> {
    pyramid: &'a Pyramid,
    tree: Tree,
    id: TileId,
    far: [f32; 2],
    raster: [usize; 2],
}

impl Patch<'_> {
    /// Which far sides were moved out to the terrain's last sample.
    fn snapped(&self) -> [bool; 2] {
        let extent = self.tree.extent() as f32;
        self.far.map(|f| f > extent)
    }

    fn height(&self, v: Vertex) -> i32 {
        self.pyramid.vertex(self.tree, self.id, self.snapped(), v)
    }

    /// Largest vertical distance, in codes, from a level-0 sample under triangle `t` to
    /// its plane.
    fn error(&self, t: &[Vertex; 3]) -> f64 {
        self.error_within(t, f64::INFINITY)
    }

    /// Triangle `t` in samples: its corners (column, row, height), its determinant and the
    /// raster's samples in its bounding box (first column and row, last column and row);
    /// `None` when it is flat or has no sample under it.
    fn placed(&self, t: &[Vertex; 3]) -> Option<Placed> {
        let p = t.map(|v| {
            let [sx, sy] = quadtree::sample_of(
                self.tree,
                self.id.level,
                self.id.x,
                self.id.y,
                v.position(self.tree, self.far),
            );
            [sx, sy, f64::from(self.height(v))]
        });
        let det =
            (p[1][0] - p[0][0]) * (p[2][1] - p[0][1]) - (p[2][0] - p[0][0]) * (p[1][1] - p[0][1]);
        if det.abs() < 1e-12 {
            return None;
        }
        let lo = |a: usize| p.iter().map(|q| q[a]).fold(f64::INFINITY, f64::min);
        let hi = |a: usize| p.iter().map(|q| q[a]).fold(f64::NEG_INFINITY, f64::max);
        let x0 = lo(0).ceil().max(0.0) as usize;
        let y0 = lo(1).ceil().max(0.0) as usize;
        let x1 = hi(0).floor().min(self.raster[0] as f64 - 1.0);
        let y1 = hi(1).floor().min(self.raster[1] as f64 - 1.0);
        if x1 < 0.0 || y1 < 0.0 {
            return None;
        }
        Some((p, det, [x0, y0], [x1, y1]))
    }

    /// [`Patch::error`] where it is at most `limit`; past it, some distance past it (the
    /// samples left are not measured).
    fn error_within(&self, t: &[Vertex; 3], limit: f64) -> f64 {
        let Some((p, det, [x0, y0], [x1, y1])) = self.placed(t) else {
            return 0.0;
        };
        let eps = 1e-9;
        // The weights of corners 1 and 2 are linear along a row: `w1 = (x - p0x) e2y / det
        // - c1`, `w2 = c2 - (x - p0x) e1y / det`, and `w0 = 1 - w1 - w2`. Each bounds the
        // row's samples inside the triangle; the bounds are widened by a sample, so that
        // rounding cannot drop one, and every sample between them is tested as before.
        let (e1x, e1y) = (p[1][0] - p[0][0], p[1][1] - p[0][1]);
        let (e2x, e2y) = (p[2][0] - p[0][0], p[2][1] - p[0][1]);
        // Dividing by a power of two is multiplying by its exact inverse: the same bits,
        // without a division per sample.
        let inverse = (det.to_bits() & ((1 << 52) - 1) == 0).then(|| 1.0 / det);
        let mut worst: f64 = 0.0;
        for sy in y0..=y1 as usize {
            let fy = sy as f64;
            // Each weight as `slope * (x - p0x) + at_p0x`, from its formula below.
            let weights = [
                (e2y / det, -(e2x * (fy - p[0][1])) / det),
                (-e1y / det, (e1x * (fy - p[0][1])) / det),
            ];
            let (mut from, mut to) = (x0 as f64, x1);
            let mut sum = (0.0, 1.0);
            for (slope, at) in weights {
                // slope * (x - p0x) + at >= -eps
                if slope > 0.0 {
                    from = from.max(p[0][0] + (-eps - at) / slope - 1.0);
                } else if slope < 0.0 {
                    to = to.min(p[0][0] + (-eps - at) / slope + 1.0);
                }
                sum = (sum.0 + slope, sum.1 - at);
            }
            // w0 = 1 - w1 - w2 >= -eps: (s1 + s2) (x - p0x) <= 1 - a1 - a2 + eps
            let (slope, rest) = sum;
            if slope > 0.0 {
                to = to.min(p[0][0] + (rest + eps) / slope + 1.0);
            } else if slope < 0.0 {
                from = from.max(p[0][0] + (rest + eps) / slope - 1.0);
            }
            if from > to {
                continue;
            }
            let (c1, c2) = (e2x * (fy - p[0][1]), e1x * (fy - p[0][1]));
            let row = self.pyramid.row(sy);
            let (from, to) = (
                from.ceil() as usize,
                (to.floor() as usize).min(row.len() - 1),
            );
            if from > to {
                continue;
            }
            let span = Span {
                samples: &row[from..=to],
                first: from,
                p: &p,
                c: [c1, c2],
                e: [e1y, e2y],
            };
            worst = match inverse {
                Some(inverse) => span.worst(worst, |n| n * inverse),
                None => span.worst(worst, |n| n / det),
            };
            if worst > limit {
                return worst;
            }
        }
        worst
    }

    /// The largest error of the full cut's triangles, for a patch of the finest meta
    /// level. Only the cells along the border have a ring vertex; every other triangle
    /// joins three adjacent samples, has no other sample under it and passes through its
    /// own, so its error is 0 and it is not measured.
    fn full_cut_error(&self) -> f64 {
        let cut = Cut::full(self.tree);
        let p = self.tree.side();
        [
            (0..p + 1, 0..1),
            (0..p + 1, p..p + 1),
            (0..1, 1..p),
            (p..p + 1, 1..p),
        ]
        .into_iter()
        .flat_map(|(a, b)| quadtree::triangles_in(&cut, a, b))
        .map(|t| self.error(&t))
        .fold(0.0, f64::max)
    }

    /// Merges nodes finest level first while the triangles a merge makes stay within
    /// `tolerance` codes; returns the cut and the largest error of its triangles.
    fn simplify(&self, mut cut: Cut, start_error: f64, tolerance: f64) -> (Cut, f64) {
        let n = self.tree.n;
        let mut error = start_error;
        let mut made = Vec::new();
        for l in (0..n).rev() {
            for j in 0..1u32 << l {
                for i in 0..1u32 << l {
                    if !cut.is_split(l, i, j)
                        || (0..4).any(|c| cut.is_split(l + 1, 2 * i + c % 2, 2 * j + c / 2))
                        || !cut.reached(l, i, j)
                    {
                        continue;
                    }
                    cut.set_split(l, i, j, false);
                    // Floating-point noise is not an error (a plane merges at tolerance 0).
                    let limit = tolerance + 1e-6;
                    // The merge is undone at the first triangle past the limit.
                    let mut worst: f64 = 0.0;
                    quadtree::triangles_of_leaf(&cut, (l, i, j), &mut made);
                    for t in &made {
                        worst = worst.max(self.error_within(t, limit));
                        if worst > limit {
                            break;
                        }
                    }
                    if worst <= limit {
                        error = error.max(worst);
                    } else {
                        cut.set_split(l, i, j, true);
                    }
                }
            }
        }
        (cut, error)
    }
}

/// What the patches take, for the build's report.
#[derive(Debug, Clone, Copy)]
pub struct Stats {
    /// Every body's header and split bits: the progressive representation.
    pub split_bytes: u64,
    /// Every body's compressed heights.
    pub height_bytes: u64,
    pub bodies_bytes: u64,
    pub index_bytes: u64,
    /// Active vertices of the finest patches.
    pub active_vertices: u64,
    pub elapsed: std::time::Duration,
}

impl Stats {
    pub fn of(built: &Built, index_bytes: u64, elapsed: std::time::Duration) -> Stats {
        let split: u64 = built
            .bodies
            .iter()
            .map(|b| {
                let bits = b
                    .get(8..12)
                    .map_or(0, |w| u32::from_le_bytes([w[0], w[1], w[2], w[3]]));
                12 + u64::from(bits).div_ceil(8)
            })
            .sum();
        let bodies: u64 = built.bodies.iter().map(|b| b.len() as u64).sum();
        Stats {
            split_bytes: split,
            height_bytes: bodies - split,
            bodies_bytes: bodies,
            index_bytes,
            active_vertices: built.active_vertices,
            elapsed,
        }
    }
}

/// A patch's body, its index entry and its active vertices.
type Encoded = (Vec<u8>, PatchEntry, u64);

/// What [`build`] made: per tile of the manifest, in its order, the body and the index
/// entry.
#[derive(Debug)]
pub struct Built {
    pub bodies: Vec<Vec<u8>>,
    pub entries: Vec<PatchEntry>,
    /// Active vertices over every patch, and level-0 samples.
    pub active_vertices: u64,
}

/// Builds every patch of `manifest`'s pyramid from the level-0 `codes` (see the module
/// docs). `tolerance_m`: the finest patches' world-space tolerance.
pub fn build(
    codes: &[i32],
    manifest: &Manifest,
    tolerance_m: f64,
    zstd_level: i32,
    progress: &(dyn Fn(usize, usize) + Sync),
    cancel: &AtomicBool,
) -> Result<Built, BuildError> {
    let tree = Tree::for_tile_size(manifest.tile_size);
    let (w, h) = (
        manifest.raster.width as usize,
        manifest.raster.height as usize,
    );
    let top = manifest.levels.len() as u32 - 1;
    let pyramid = Pyramid::new(codes, w, h, top + tree.n);
    let quantum = manifest.heights.quantum_m / SUBCODES;
    let tolerance = (tolerance_m / quantum).max(0.0);
    let total: usize = manifest.levels.iter().map(|l| l.tiles.len()).sum();
    let done = AtomicUsize::new(0);

    // Cuts and errors (codes), level by level, finest first.
    let mut cuts: Vec<Vec<(Cut, f64)>> = Vec::new();
    for (level, info) in manifest.levels.iter().enumerate() {
        let level = level as u32;
        let grid = [info.grid.columns, info.grid.rows];
        let made: Vec<Result<(Cut, f64), BuildError>> = (0..info.tiles.len())
            .into_par_iter()
            .map(|index| {
                if cancel.load(Ordering::Relaxed) {
                    return Err(BuildError::Cancelled);
                }
                let (x, y) = (index as u32 % grid[0], index as u32 / grid[0]);
                let id = TileId::at(level, x, y);
                let patch = Patch {
                    pyramid: &pyramid,
                    tree,
                    id,
                    far: quadtree::far_edge(tree, level, x, y, [w as u32, h as u32], grid),
                    raster: [w, h],
                };
                let start_error = |start: &Cut| {
                    quadtree::triangulate(start)
                        .iter()
                        .map(|t| patch.error(t))
                        .fold(0.0, f64::max)
                };
                let made = if level == 0 {
                    // The full patch is exact but where its ring lies on the terrain's
                    // last sample (a raster of 2^k + 1 samples): measured all the same.
                    let e = patch.full_cut_error();
                    patch.simplify(Cut::full(tree), e, tolerance.max(e))
                } else {
                    let below = &manifest.levels[level as usize - 1].grid;
                    let children: [Option<&Cut>; 4] = std::array::from_fn(|q| {
                        let (cx, cy) = (2 * x + q as u32 % 2, 2 * y + q as u32 / 2);
                        (cx < below.columns && cy < below.rows).then(|| {
                            &cuts[level as usize - 1][(cy * below.columns + cx) as usize].0
                        })
                    });
                    let start = Cut::from_children(tree, children);
                    let e = start_error(&start);
                    patch.simplify(start, e, e.max(tolerance))
                };
                let d = done.fetch_add(1, Ordering::Relaxed) + 1;
                progress(d, total * 2);
                Ok(made)
            })
            .collect();
        cuts.push(made.into_iter().collect::<Result<_, _>>()?);
    }

    // Bodies, each against its parent's cut and heights.
    let node_heights = |id: TileId, cut: &Cut| -> quadtree::NodeHeights {
        cut.leaves()
            .into_iter()
            .map(|(l, i, j)| {
                let v = Vertex::Node {
                    l: l as u8,
                    i: i as u16,
                    j: j as u16,
                };
                // Nodes do not depend on the ring's placement.
                ((l, i, j), pyramid.vertex(tree, id, [false; 2], v))
            })
            .collect()
    };
    let mut bodies = Vec::with_capacity(total);
    let mut entries = Vec::with_capacity(total);
    let mut active = 0u64;
    for (level, info) in manifest.levels.iter().enumerate() {
        let level = level as u32;
        let columns = info.grid.columns;
        let parents: HashMap<TileId, quadtree::NodeHeights> = if level < top {
            let above = &manifest.levels[level as usize + 1].grid;
            (0..above.columns * above.rows)
                .into_par_iter()
                .map(|index| {
                    let id = TileId::at(level + 1, index % above.columns, index / above.columns);
                    (
                        id,
                        node_heights(id, &cuts[level as usize + 1][index as usize].0),
                    )
                })
                .collect()
        } else {
            HashMap::new()
        };
        let made: Vec<Result<Encoded, BuildError>> = (0..info.tiles.len())
            .into_par_iter()
            .map(|index| {
                if cancel.load(Ordering::Relaxed) {
                    return Err(BuildError::Cancelled);
                }
                let id = TileId::at(level, index as u32 % columns, index as u32 / columns);
                let (cut, error) = &cuts[level as usize][index];
                let parent_id = TileId::at(level + 1, id.x / 2, id.y / 2);
                let parent = (level < top).then(|| {
                    let above = &manifest.levels[level as usize + 1].grid;
                    let p = (parent_id.y * above.columns + parent_id.x) as usize;
                    Parent {
                        cut: &cuts[level as usize + 1][p].0,
                        heights: &parents[&parent_id],
                        quarter: (id.x % 2, id.y % 2),
                    }
                });
                let grid = [columns, info.grid.rows];
                let far = quadtree::far_edge(tree, level, id.x, id.y, [w as u32, h as u32], grid);
                let snapped = far.map(|f| f > tree.extent() as f32);
                let height = |v: Vertex| pyramid.vertex(tree, id, snapped, v);
                let triangles = quadtree::triangulate(cut);
                let body = quadtree::encode_triangulated_patch(
                    cut,
                    &triangles,
                    parent.as_ref(),
                    height,
                    level == 0,
                    zstd_level,
                );
                let (lo, hi) = triangles
                    .iter()
                    .flatten()
                    .map(|&v| height(v))
                    .fold((i32::MAX, i32::MIN), |(lo, hi), c| (lo.min(c), hi.max(c)));
                let metres = |c: i32| (manifest.heights.offset_m + quantum * f64::from(c)) as f32;
                let digest = blake3::hash(&body);
                let mut hash = [0; 16];
                hash.copy_from_slice(&digest.as_bytes()[..16]);
                let entry = PatchEntry {
                    hash,
                    bytes: body.len() as u32,
                    error_m: (error * quantum) as f32,
                    min_m: metres(lo),
                    max_m: metres(hi),
                    mesh: quadtree::MeshCounts::of(cut, &triangles),
                };
                let d = done.fetch_add(1, Ordering::Relaxed) + 1;
                progress(d, total * 2);
                Ok((body, entry, cut.leaves().len() as u64))
            })
            .collect();
        for m in made {
            let (body, entry, leaves) = m?;
            bodies.push(body);
            entries.push(entry);
            if level == 0 {
                active += leaves;
            }
        }
    }
    Ok(Built {
        bodies,
        entries,
        active_vertices: active,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rough codes for a `w x h` raster: a saw of steps of `step` over a saddle.
    fn rough_codes(w: usize, h: usize, step: i32) -> Vec<i32> {
        (0..h)
            .flat_map(|y| {
                (0..w).map(move |x| ((x * 37 + y * 91) % 23) as i32 * step + (x * y) as i32)
            })
            .collect()
    }

    /// Patch `id` of a `grid` of patches over a `raster` of `pyramid`.
    fn patch_at(
        pyramid: &Pyramid,
        tree: Tree,
        id: TileId,
        raster: [usize; 2],
        grid: [u32; 2],
    ) -> Patch<'_> {
        let size = raster.map(|r| r as u32);
        Patch {
            pyramid,
            tree,
            id,
            far: quadtree::far_edge(tree, id.level, id.x, id.y, size, grid),
            raster,
        }
    }

    /// Brute force: the triangulation's surface against every level-0 sample in the patch.
    fn brute_error(
        pyramid: &Pyramid,
        tree: Tree,
        id: TileId,
        cut: &Cut,
        raster: [usize; 2],
        grid: [u32; 2],
    ) -> f64 {
        let far = quadtree::far_edge(
            tree,
            id.level,
            id.x,
            id.y,
            [raster[0] as u32, raster[1] as u32],
            grid,
        );
        let patch = Patch {
            pyramid,
            tree,
            id,
            far,
            raster,
        };
        quadtree::triangulate(cut)
            .iter()
            .map(|t| patch.error(t))
            .fold(0.0, f64::max)
    }

    #[test]
    fn a_plane_merges_to_the_root_and_a_bump_keeps_its_vertices() {
        let tree = Tree { n: 3 };
        let (w, h) = (65usize, 65usize);
        let plane: Vec<i32> = (0..h)
            .flat_map(|y| (0..w).map(move |x| (3 * x + 2 * y) as i32))
            .collect();
        let pyramid = Pyramid::new(&plane, w, h, 6);
        // Away from the raster's border, where the clamped extension bends the plane.
        let id = TileId::at(0, 3, 3);
        let far = quadtree::far_edge(tree, 0, 3, 3, [65, 65], [8, 8]);
        let patch = Patch {
            pyramid: &pyramid,
            tree,
            id,
            far,
            raster: [w, h],
        };
        let (cut, error) = patch.simplify(Cut::full(tree), 0.0, 0.0);
        assert_eq!(
            cut.leaves().len(),
            1,
            "a plane needs its root alone: {:?}",
            cut.leaves()
        );
        assert!(error <= 1e-9);
        let mut bump = plane.clone();
        bump[28 * w + 28] += 50;
        let pyramid = Pyramid::new(&bump, w, h, 6);
        let patch = Patch {
            pyramid: &pyramid,
            ..patch
        };
        let (cut, error) = patch.simplify(Cut::full(tree), 0.0, 0.0);
        assert!(cut.is_leaf(3, 4, 4), "the bump's sample stays active");
        assert!(error <= 1e-9);
        assert!(cut.leaves().len() < 30, "{} active", cut.leaves().len());
    }

    #[test]
    fn a_full_patch_of_the_finest_meta_level_is_exact() {
        let tree = Tree { n: 3 };
        let (w, h) = (33usize, 33usize);
        let codes: Vec<i32> = (0..h)
            .flat_map(|y| (0..w).map(move |x| ((x * 37 + y * 91) % 23) as i32 * 4 + (x * y) as i32))
            .collect();
        let pyramid = Pyramid::new(&codes, w, h, 6);
        for (x, y) in [(0, 0), (1, 2), (3, 3)] {
            let id = TileId::at(0, x, y);
            let far = quadtree::far_edge(tree, 0, x, y, [33, 33], [4, 4]);
            let patch = Patch {
                pyramid: &pyramid,
                tree,
                id,
                far,
                raster: [w, h],
            };
            for t in quadtree::triangulate(&Cut::full(tree)) {
                let e = patch.error(&t);
                // Only the ring on the raster's last sample row or column is off.
                assert!(e < 1e-9, "patch {x},{y}: {t:?} error {e}");
            }
        }
    }

    #[test]
    fn the_error_a_patch_reports_bounds_its_surface_against_every_sample() {
        let tree = Tree { n: 3 };
        let (w, h) = (21usize, 17usize);
        let codes: Vec<i32> = (0..h)
            .flat_map(|y| (0..w).map(move |x| ((x * 37 + y * 91) % 23) as i32 * 4 + (x * y) as i32))
            .collect();
        let pyramid = Pyramid::new(&codes, w, h, 6);
        let grid = [3, 3];
        for tol in [0.0, 5.0, 20.0] {
            for (x, y) in [(0, 0), (2, 1), (2, 2)] {
                let id = TileId::at(0, x, y);
                let far = quadtree::far_edge(tree, 0, x, y, [w as u32, h as u32], grid);
                let patch = Patch {
                    pyramid: &pyramid,
                    tree,
                    id,
                    far,
                    raster: [w, h],
                };
                let (cut, error) = patch.simplify(Cut::full(tree), 0.0, tol);
                let brute = brute_error(&pyramid, tree, id, &cut, [w, h], grid);
                assert!(
                    brute <= error + 1e-9,
                    "tolerance {tol}: brute {brute} > reported {error}"
                );
                assert!(error <= tol + 1e-9);
            }
        }
    }

    /// The full cut's error from its border cells is its error from every triangle, on
    /// rasters of `2^k + 1` samples (the ring on the last sample) and of other sizes (the
    /// far patches past the terrain), because every other triangle's error is exactly 0.
    #[test]
    fn the_full_cuts_error_from_its_border_is_its_error_from_every_triangle() {
        let tree = Tree { n: 3 };
        let p = tree.side();
        let mut inner = 0;
        for (w, h) in [(33usize, 33usize), (21, 17), (9, 30), (40, 12)] {
            let pyramid = Pyramid::new(&rough_codes(w, h, 4), w, h, 6);
            let g = super::super::tiles::Grid::covering(w as u32, h as u32, p + 1);
            let grid = [g.columns, g.rows];
            for y in 0..grid[1] {
                for x in 0..grid[0] {
                    let id = TileId::at(0, x, y);
                    let patch = patch_at(&pyramid, tree, id, [w, h], grid);
                    let full = Cut::full(tree);
                    for t in quadtree::triangles_in(&full, 1..p, 1..p) {
                        assert_eq!(patch.error(&t), 0.0, "{w}x{h} patch {x},{y}: {t:?}");
                        inner += 1;
                    }
                    let every = brute_error(&pyramid, tree, id, &full, [w, h], grid);
                    assert_eq!(patch.full_cut_error(), every, "{w}x{h} patch {x},{y}");
                }
            }
        }
        assert!(inner > 1000, "{inner} inner triangles");
    }

    /// The measure before the spans, kept as the reference: every sample of the triangle's
    /// bounding box, tested by its barycentric weights.
    fn reference_error(patch: &Patch, t: &[Vertex; 3]) -> f64 {
        let Some((p, det, [x0, y0], [x1, y1])) = patch.placed(t) else {
            return 0.0;
        };
        let mut worst: f64 = 0.0;
        for sy in y0..=y1 as usize {
            for sx in x0..=x1 as usize {
                let (fx, fy) = (sx as f64, sy as f64);
                let w1 = ((fx - p[0][0]) * (p[2][1] - p[0][1])
                    - (p[2][0] - p[0][0]) * (fy - p[0][1]))
                    / det;
                let w2 = ((p[1][0] - p[0][0]) * (fy - p[0][1])
                    - (fx - p[0][0]) * (p[1][1] - p[0][1]))
                    / det;
                let w0 = 1.0 - w1 - w2;
                if w0 < -1e-9 || w1 < -1e-9 || w2 < -1e-9 {
                    continue;
                }
                let z = w0 * p[0][2] + w1 * p[1][2] + w2 * p[2][2];
                worst = worst.max((patch.pyramid.row(sy)[sx] - z).abs());
            }
        }
        worst
    }

    /// A triangle's error, measured over the samples of each row's span, is the error
    /// over every sample of its bounding box, to the bit; within a limit, it is that
    /// error where it is at most the limit and past the limit where it is past it. On
    /// patches of three meta levels, with their rings on and off the terrain's edge.
    #[test]
    fn the_error_of_a_triangle_is_every_sample_under_it_measured() {
        let tree = Tree { n: 3 };
        let p = tree.side();
        let mut measured = 0;
        for (w, h) in [(33usize, 33usize), (21, 17), (40, 12)] {
            let pyramid = Pyramid::new(&rough_codes(w, h, 40), w, h, 6);
            let g = super::super::tiles::Grid::covering(w as u32, h as u32, p + 1);
            for level in 0..3u32 {
                let grid = [g.columns, g.rows].map(|c| c.div_ceil(1 << level));
                for y in 0..grid[1] {
                    for x in 0..grid[0] {
                        let id = TileId::at(level, x, y);
                        let patch = patch_at(&pyramid, tree, id, [w, h], grid);
                        let mut cuts = vec![Cut::full(tree), Cut::root(tree)];
                        for tol in [0.0, 30.0, 300.0] {
                            cuts.push(patch.simplify(Cut::full(tree), 0.0, tol).0);
                        }
                        for cut in &cuts {
                            for t in quadtree::triangulate(cut) {
                                let reference = reference_error(&patch, &t);
                                assert_eq!(patch.error(&t), reference, "{t:?}");
                                for limit in [reference / 2.0, reference, reference * 2.0 + 1.0] {
                                    let within = patch.error_within(&t, limit);
                                    if reference <= limit {
                                        assert_eq!(within, reference, "{t:?} within {limit}");
                                    } else {
                                        assert!(within > limit, "{t:?}: {within} within {limit}");
                                    }
                                }
                                measured += usize::from(reference > 0.0);
                            }
                        }
                    }
                }
            }
        }
        assert!(measured > 1000, "{measured} triangles with an error");
    }
}
