//! Quadtree progressive patches (Yusov and Turlapov 2007): the geometry the builder and
//! the client must agree on.
//!
//! **Vertices quadtree.** The heights pyramid is cell-centred: a vertex of pyramid level
//! `k + 1` sits at the centre of its four children of level `k` (level 0 is the DEM), and
//! its height is the order-4 Neville interpolating filter over the 4x4 children around it
//! ([`neville`]). A vertex of level `k` with indices `(i, j)` lies at sample
//! `(i + 0.5) 2^k - 0.5`, so level-0 vertices are the samples themselves.
//!
//! **Patches.** The meta quadtree is the tile pyramid: patch `(L, x, y)` is tile
//! `(L, x, y)`, and its sub-quadtree has levels `0..=n` (`2^n = tile_size - 1`), patch
//! level `l` being pyramid level `L + n - l`. Its region runs from sample
//! `x 2^(n+L) - 0.5` for `2^(n+L)` samples (half a sample off the tile's, whose borders are
//! samples). Positions inside a patch are in *patch units*, half its finest spacing, from 0
//! to `2 * 2^n`; a node `(l, i, j)` lies at `((2i + 1) 2^(n-l), (2j + 1) 2^(n-l))`.
//!
//! **Triangulation** ([`triangulate`]). A patch's active vertices are the leaves of an
//! unbalanced quadtree ([`Cut`]). Each level is ringed by border vertices on the patch's
//! sides ([`Vertex::Side`], [`Vertex::Corner`]), whose heights are the mean of the two (four)
//! vertices of that level nearest them, across the side. The triangulation is the
//! regular triangulation of the finest level and its ring (diagonal from `(c0, r1)` to
//! `(c1, r0)`, as [`crate::mask`]), every vertex moved onto its active ancestor (a ring
//! vertex onto the ring vertex beside its inner neighbour's ancestor), degenerate triangles
//! dropped: the paper's rule, its figures 4 and 5.
//!
//! **Progressive representation** ([`encode_splits`], [`decode_splits`]). A child patch's
//! tree refines its parent's over the child's quarter: one bit per node that the parent
//! leaves a leaf (or that a split creates), set when the node splits.

use std::collections::HashMap;

/// A map keyed by small integers (nodes, vertices, grid points), hashed with foldhash: a
/// patch's decoding, triangulation and meshing look each vertex up several times, and
/// SipHash (the standard map's) took about a third of a client's time meshing patches.
pub type FastMap<K, V> = HashMap<K, V, foldhash::fast::RandomState>;
/// A set of the same keys, hashed the same way ([`FastMap`]).
pub type FastSet<K> = std::collections::HashSet<K, foldhash::fast::RandomState>;
/// Heights of a patch's active nodes, keyed by `(level, i, j)`.
pub type NodeHeights = FastMap<(u32, u32, u32), i32>;

/// Name and version of the patch data, in the manifest.
pub const FORMAT: &str = "quadtree-patches/2";

/// Patch heights are codes of an eighth of the database's quantum: a coarse vertex at a
/// cell's centre lies between samples, and on a plane through whole codes it lands on an
/// eighth (a half, a quarter...) of a code, which whole codes would round off the plane.
/// A body stores the finest nodes of the finest patches, which are samples, in whole codes.
pub const SUBCODES: i32 = 8;

/// Weights of the order-4 Neville interpolating filter along one axis, for the fine
/// samples at `2i - 1, 2i, 2i + 1, 2i + 2` (the cubic through four points, at their middle).
pub const NEVILLE: [f64; 4] = [-1.0 / 16.0, 9.0 / 16.0, 9.0 / 16.0, -1.0 / 16.0];

/// One level coarser: the 4x4 tensor Neville filter over `fine` (`width` x `height`,
/// row-major), borders extended by the nearest sample. Returns the coarse raster and its
/// size (`ceil(width / 2)` x `ceil(height / 2)`).
pub fn neville(fine: &[f64], width: usize, height: usize) -> (Vec<f64>, usize, usize) {
    let (cw, ch) = (width.div_ceil(2), height.div_ceil(2));
    let at = |x: isize, y: isize| {
        let x = x.clamp(0, width as isize - 1) as usize;
        let y = y.clamp(0, height as isize - 1) as usize;
        fine[y * width + x]
    };
    // Separable: rows first into a (cw x height) raster, then columns.
    let mut rows = vec![0.0; cw * height];
    for y in 0..height {
        for i in 0..cw {
            let x0 = 2 * i as isize - 1;
            rows[y * cw + i] = (0..4)
                .map(|m| NEVILLE[m] * at(x0 + m as isize, y as isize))
                .sum();
        }
    }
    let row_at = |x: usize, y: isize| rows[y.clamp(0, height as isize - 1) as usize * cw + x];
    let mut out = vec![0.0; cw * ch];
    for j in 0..ch {
        let y0 = 2 * j as isize - 1;
        for i in 0..cw {
            out[j * cw + i] = (0..4)
                .map(|m| NEVILLE[m] * row_at(i, y0 + m as isize))
                .sum();
        }
    }
    (out, cw, ch)
}

/// The shape of every patch's sub-quadtree: levels `0..=n`, `2^n` finest vertices a side.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Tree {
    pub n: u32,
}

impl Tree {
    /// The tree of a pyramid of tiles of `tile_size = 2^n + 1` samples a side.
    pub fn for_tile_size(tile_size: u32) -> Tree {
        Tree {
            n: (tile_size - 1).trailing_zeros(),
        }
    }

    /// Finest vertices a side, `2^n`.
    pub fn side(self) -> u32 {
        1 << self.n
    }

    /// Nodes of the whole tree, `(4^(n+1) - 1) / 3`.
    pub fn nodes(self) -> usize {
        ((1usize << (2 * (self.n + 1))) - 1) / 3
    }

    /// Index of node `(l, i, j)` in level order.
    pub fn index(self, l: u32, i: u32, j: u32) -> usize {
        ((1usize << (2 * l)) - 1) / 3 + (j as usize) * (1usize << l) + i as usize
    }

    /// Position of node `(l, i, j)` in patch units.
    pub fn node_position(self, l: u32, i: u32, j: u32) -> [u32; 2] {
        let s = 1 << (self.n - l);
        [(2 * i + 1) * s, (2 * j + 1) * s]
    }

    /// Side of the patch in patch units, `2^(n+1)`.
    pub fn extent(self) -> u32 {
        2 << self.n
    }
}

/// A vertex of a patch's triangulation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Vertex {
    /// A node `(l, i, j)` of the sub-quadtree.
    Node { l: u8, i: u16, j: u16 },
    /// A ring vertex of level `l` on side `side` (0: v = 0, 1: u = max, 2: v = max,
    /// 3: u = 0), beside node `k` of that level along the side.
    Side { side: u8, l: u8, k: u16 },
    /// A corner of level `l` (0: (0, 0), 1: (max, 0), 2: (max, max), 3: (0, max)).
    Corner { corner: u8, l: u8 },
}

/// One word per vertex (a derived hash writes the variant and each field apart, and the
/// patch builder hashes triangles of vertices by the million).
impl std::hash::Hash for Vertex {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        state.write_u64(self.key());
    }
}

impl Vertex {
    /// The vertex packed in a `u64`, one to one: the variant, then its fields.
    fn key(self) -> u64 {
        match self {
            Vertex::Node { l, i, j } => (u64::from(l) << 32) | (u64::from(i) << 16) | u64::from(j),
            Vertex::Side { side, l, k } => {
                (1 << 48) | (u64::from(side) << 32) | (u64::from(l) << 16) | u64::from(k)
            }
            Vertex::Corner { corner, l } => (2 << 48) | (u64::from(corner) << 16) | u64::from(l),
        }
    }

    /// Position in patch units; `far` is where sides 1 and 2 lie (the patch's extent, or
    /// the terrain's edge where it runs past the last patch).
    pub fn position(self, tree: Tree, far: [f32; 2]) -> [f32; 2] {
        let s = |l: u8, k: u16| ((2 * u32::from(k) + 1) << (tree.n - u32::from(l))) as f32;
        match self {
            Vertex::Node { l, i, j } => [s(l, i), s(l, j)],
            Vertex::Side { side, l, k } => match side {
                0 => [s(l, k), 0.0],
                1 => [far[0], s(l, k)],
                2 => [s(l, k), far[1]],
                _ => [0.0, s(l, k)],
            },
            Vertex::Corner { corner, .. } => match corner {
                0 => [0.0, 0.0],
                1 => [far[0], 0.0],
                2 => [far[0], far[1]],
                _ => [0.0, far[1]],
            },
        }
    }

    /// Its level in the sub-quadtree.
    pub fn level(self) -> u32 {
        match self {
            Vertex::Node { l, .. } | Vertex::Side { l, .. } | Vertex::Corner { l, .. } => {
                u32::from(l)
            }
        }
    }

    /// Whether it lies on the patch's border (a ring vertex).
    pub fn on_border(self) -> bool {
        !matches!(self, Vertex::Node { .. })
    }
}

/// The active vertices of a patch: the leaves of an unbalanced quadtree, kept as a split
/// flag per node (a finest node never splits).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Cut {
    pub tree: Tree,
    split: Vec<bool>,
}

impl Cut {
    /// Every node above the finest level split: the full-resolution patch.
    pub fn full(tree: Tree) -> Cut {
        let mut split = vec![true; tree.nodes()];
        let finest = tree.index(tree.n, 0, 0);
        split[finest..].iter_mut().for_each(|s| *s = false);
        Cut { tree, split }
    }

    /// Only the root: one active vertex.
    pub fn root(tree: Tree) -> Cut {
        Cut {
            tree,
            split: vec![false; tree.nodes()],
        }
    }

    pub fn is_split(&self, l: u32, i: u32, j: u32) -> bool {
        self.split[self.tree.index(l, i, j)]
    }

    /// Splits or merges node `(l, i, j)`; a finest node is never split.
    pub fn set_split(&mut self, l: u32, i: u32, j: u32, split: bool) {
        let index = self.tree.index(l, i, j);
        self.split[index] = split && l < self.tree.n;
    }

    /// Whether node `(l, i, j)` is reached: every ancestor split.
    pub fn reached(&self, l: u32, i: u32, j: u32) -> bool {
        (0..l).all(|a| self.is_split(a, i >> (l - a), j >> (l - a)))
    }

    /// Whether node `(l, i, j)` is active: reached and not split.
    pub fn is_leaf(&self, l: u32, i: u32, j: u32) -> bool {
        !self.is_split(l, i, j) && self.reached(l, i, j)
    }

    /// The active node over finest vertex `(i, j)`: `(level, i, j)`.
    pub fn leaf_of(&self, i: u32, j: u32) -> (u32, u32, u32) {
        let n = self.tree.n;
        let mut l = 0;
        while l < n && self.is_split(l, i >> (n - l), j >> (n - l)) {
            l += 1;
        }
        (l, i >> (n - l), j >> (n - l))
    }

    /// The active node over node `(l, i, j)` (itself when it is a leaf; a leaf under it
    /// is not looked for): `(level, i, j)`.
    pub fn leaf_above(&self, l: u32, i: u32, j: u32) -> (u32, u32, u32) {
        let mut a = 0;
        while a < l && self.is_split(a, i >> (l - a), j >> (l - a)) {
            a += 1;
        }
        (a, i >> (l - a), j >> (l - a))
    }

    /// The active nodes, in level order.
    pub fn leaves(&self) -> Vec<(u32, u32, u32)> {
        let mut out = Vec::new();
        let mut stack = vec![(0u32, 0u32, 0u32)];
        while let Some((l, i, j)) = stack.pop() {
            if self.is_split(l, i, j) {
                for (di, dj) in [(1, 1), (0, 1), (1, 0), (0, 0)] {
                    stack.push((l + 1, 2 * i + di, 2 * j + dj));
                }
            } else {
                out.push((l, i, j));
            }
        }
        // Indices are distinct: an unstable sort gives the one order.
        out.sort_unstable_by_key(|&(l, i, j)| self.tree.index(l, i, j));
        out
    }

    /// Nodes split, the number of merges a full patch went through undone.
    pub fn splits(&self) -> usize {
        self.split.iter().filter(|s| **s).count()
    }

    /// The cut the parent gives quarter `(qx, qy)` of itself, seen as the child's tree:
    /// node `(l, i, j)` of the child is node `(l + 1, qx 2^l + i, qy 2^l + j)` of the
    /// parent; the child's finest level has nothing above it in the parent.
    pub fn quarter(&self, qx: u32, qy: u32) -> Cut {
        let tree = self.tree;
        let mut child = Cut::root(tree);
        if !self.is_split(0, 0, 0) {
            return child;
        }
        for l in 0..tree.n {
            let side = 1 << l;
            for j in 0..side {
                for i in 0..side {
                    let split = self.is_split(l + 1, qx * side + i, qy * side + j);
                    child.set_split(l, i, j, split);
                }
            }
        }
        child
    }

    /// The parent's starting cut from its children's (`None`: a quarter past the
    /// terrain): each child's nodes one level up, the children's finest level dropped.
    pub fn from_children(tree: Tree, children: [Option<&Cut>; 4]) -> Cut {
        let mut cut = Cut::root(tree);
        cut.set_split(0, 0, 0, true);
        for (q, child) in children.iter().enumerate() {
            let Some(child) = child else { continue };
            let (qx, qy) = (q as u32 % 2, q as u32 / 2);
            for l in 0..tree.n {
                let side = 1 << l;
                for j in 0..side {
                    for i in 0..side {
                        if child.is_split(l, i, j) {
                            cut.set_split(l + 1, qx * side + i, qy * side + j, true);
                        }
                    }
                }
            }
        }
        cut
    }
}

/// The active vertex a vertex of the extended finest grid moves onto: `(a, b)` in
/// `0..=side + 1`, the ring at 0 and `side + 1`.
pub fn representative(cut: &Cut, a: u32, b: u32) -> Vertex {
    let p = cut.tree.side();
    let inner = |a: u32| a.clamp(1, p) - 1;
    representative_on(cut.tree, a, b, cut.leaf_of(inner(a), inner(b)))
}

/// [`representative`] given the active node over the vertex's inner neighbour.
fn representative_on(tree: Tree, a: u32, b: u32, (l, i, j): (u32, u32, u32)) -> Vertex {
    let p = tree.side();
    let (ring_u, ring_v) = (a == 0 || a == p + 1, b == 0 || b == p + 1);
    let (l8, i16, j16) = (l as u8, i as u16, j as u16);
    match (ring_u, ring_v) {
        (false, false) => Vertex::Node {
            l: l8,
            i: i16,
            j: j16,
        },
        (false, true) => Vertex::Side {
            side: if b == 0 { 0 } else { 2 },
            l: l8,
            k: i16,
        },
        (true, false) => Vertex::Side {
            side: if a == 0 { 3 } else { 1 },
            l: l8,
            k: j16,
        },
        (true, true) => Vertex::Corner {
            corner: match (a == 0, b == 0) {
                (true, true) => 0,
                (false, true) => 1,
                (false, false) => 2,
                (true, false) => 3,
            },
            l: l8,
        },
    }
}

/// The two triangles of cell `(a, b)` of the extended grid (corners `(a, b)` to
/// `(a + 1, b + 1)`), counter-clockwise, split by the diagonal from `(a, b + 1)` to
/// `(a + 1, b)`.
pub fn cell_triangles(a: u32, b: u32) -> [[(u32, u32); 3]; 2] {
    [
        [(a, b), (a + 1, b), (a, b + 1)],
        [(a + 1, b), (a + 1, b + 1), (a, b + 1)],
    ]
}

/// A triangle as three vertices, rotated so the smallest comes first (orientation kept).
pub fn canonical(t: [Vertex; 3]) -> [Vertex; 3] {
    let m = (0..3).min_by_key(|&k| t[k]).unwrap_or(0);
    [t[m], t[(m + 1) % 3], t[(m + 2) % 3]]
}

/// The triangles cells `a0..a1` x `b0..b1` of the extended grid give under `cut`,
/// degenerate ones dropped, each once.
pub fn triangles_in(
    cut: &Cut,
    a: std::ops::Range<u32>,
    b: std::ops::Range<u32>,
) -> Vec<[Vertex; 3]> {
    // Each corner's representative, looked up by its place in the range (cells reach one
    // past their own corner).
    let width = a.end.saturating_sub(a.start) as usize + 1;
    let height = b.end.saturating_sub(b.start) as usize + 1;
    let mut reps: Vec<Option<Vertex>> = vec![None; width * height];
    let mut rep = |x: u32, y: u32| {
        let k = (y - b.start) as usize * width + (x - a.start) as usize;
        *reps[k].get_or_insert_with(|| representative(cut, x, y))
    };
    let mut seen = FastSet::default();
    let mut out = Vec::new();
    for y in b.clone() {
        for x in a.clone() {
            for tri in cell_triangles(x, y) {
                let t = [
                    rep(tri[0].0, tri[0].1),
                    rep(tri[1].0, tri[1].1),
                    rep(tri[2].0, tri[2].1),
                ];
                if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
                    continue;
                }
                let t = canonical(t);
                if seen.insert(t) {
                    out.push(t);
                }
            }
        }
    }
    out
}

/// The triangles of `cut` with a corner on leaf `(l, i, j)`: a corner of the extended grid
/// whose inner vertex lies under the node, so that it moves onto the node or onto the
/// node's ring vertex. Each once, sorted, in `out` (cleared first: a caller that merges
/// node after node reuses one vector, and does not allocate for each).
///
/// When the node's four children have just been merged into it, these are exactly the
/// triangles the merge made: those corners moved, no other did, and the vertices they
/// moved onto were not active before. It is what [`triangles_in`] over the node's cells
/// gives after the merge less what it gave before, found without listing either: a cell
/// whose four corners are inner vertices under the node moves them all onto it and makes
/// only flat triangles, so only the cells along the node's border are visited.
pub fn triangles_of_leaf(cut: &Cut, (l, i, j): (u32, u32, u32), out: &mut Vec<[Vertex; 3]>) {
    debug_assert!(cut.is_leaf(l, i, j), "({l}, {i}, {j}) is not a leaf");
    let p = cut.tree.side();
    let s = 1u32 << (cut.tree.n - l);
    let inner = |a: u32| a.clamp(1, p) - 1;
    let under = |(a, b): (u32, u32)| inner(a) / s == i && inner(b) / s == j;
    // Cell `a`'s corners `a` and `a + 1` both inner vertices under index `k`'s span.
    let inside = |a: u32, k: u32| a > k * s && a < (k + 1) * s;
    out.clear();
    for b in j * s..((j + 1) * s + 1).min(p + 1) {
        let b_inside = inside(b, j);
        let mut a = i * s;
        let a_end = ((i + 1) * s + 1).min(p + 1);
        while a < a_end {
            if b_inside && inside(a, i) {
                a = (i + 1) * s;
                continue;
            }
            // Corners (a, b), (a + 1, b), (a, b + 1), (a + 1, b + 1), looked up once.
            let corners = [(a, b), (a + 1, b), (a, b + 1), (a + 1, b + 1)];
            let moved = corners.map(under);
            // A corner under the leaf moves onto it (or its ring vertex) without a search.
            let reps = [0, 1, 2, 3].map(|c| {
                let (x, y) = corners[c];
                if moved[c] {
                    representative_on(cut.tree, x, y, (l, i, j))
                } else {
                    representative(cut, x, y)
                }
            });
            // `cell_triangles`' two triangles, as corners of the cell.
            for tri in [[0, 1, 2], [1, 3, 2]] {
                if !tri.iter().any(|&c| moved[c]) {
                    continue;
                }
                let t = tri.map(|c| reps[c]);
                if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
                    continue;
                }
                out.push(canonical(t));
            }
            a += 1;
        }
    }
    // By the packed vertices, which order as the vertices do.
    out.sort_unstable_by_key(|t| t.map(Vertex::key));
    out.dedup();
}

/// The patch's whole triangulation under `cut` (see the module documentation).
pub fn triangulate(cut: &Cut) -> Vec<[Vertex; 3]> {
    let p = cut.tree.side();
    triangles_in(cut, 0..p + 1, 0..p + 1)
}

/// The ring vertices along the patch's border in order around it (counter-clockwise from
/// corner 0), each once: the border edges of the triangulation join consecutive ones.
pub fn border_loop(cut: &Cut) -> Vec<Vertex> {
    let p = cut.tree.side();
    let mut ring = Vec::new();
    let mut push = |v: Vertex| {
        if ring.last() != Some(&v) {
            ring.push(v);
        }
    };
    for a in 0..=p {
        push(representative(cut, a, 0));
    }
    for b in 0..=p {
        push(representative(cut, p + 1, b));
    }
    for a in (1..=p + 1).rev() {
        push(representative(cut, a, p + 1));
    }
    for b in (1..=p + 1).rev() {
        push(representative(cut, 0, b));
    }
    if ring.len() > 1 && ring.first() == ring.last() {
        ring.pop();
    }
    ring
}

/// Bits to and from bytes, least significant first.
#[derive(Debug, Default, Clone)]
pub struct Bits {
    pub bytes: Vec<u8>,
    pub len: usize,
}

impl Bits {
    pub fn push(&mut self, bit: bool) {
        if self.len.is_multiple_of(8) {
            self.bytes.push(0);
        }
        if bit {
            self.bytes[self.len / 8] |= 1 << (self.len % 8);
        }
        self.len += 1;
    }

    pub fn get(&self, k: usize) -> Option<bool> {
        (k < self.len).then(|| self.bytes[k / 8] & (1 << (k % 8)) != 0)
    }
}

/// The nodes the progressive representation visits, in order: every node of `cut`'s tree
/// reached, above the finest level, that `given` leaves unsplit (a leaf of `given`, or a
/// node under one).
fn visit(given: &Cut, cut: &Cut, mut f: impl FnMut(u32, u32, u32, bool) -> bool) {
    let n = cut.tree.n;
    let mut stack = vec![(0u32, 0u32, 0u32)];
    while let Some((l, i, j)) = stack.pop() {
        if l >= n {
            continue;
        }
        let split = if given.is_split(l, i, j) {
            true
        } else {
            f(l, i, j, cut.is_split(l, i, j))
        };
        if split {
            for (di, dj) in [(1, 1), (0, 1), (1, 0), (0, 0)] {
                stack.push((l + 1, 2 * i + di, 2 * j + dj));
            }
        }
    }
}

/// The bits that turn `given` (what the parent gives, [`Cut::quarter`]; the root patch:
/// [`Cut::root`]) into `cut`, which must refine it.
pub fn encode_splits(given: &Cut, cut: &Cut) -> Bits {
    let mut bits = Bits::default();
    visit(given, cut, |_, _, _, split| {
        bits.push(split);
        split
    });
    bits
}

/// The cut `bits` make of `given`, or `None` when they run out.
pub fn decode_splits(given: &Cut, bits: &Bits) -> Option<Cut> {
    let mut cut = given.clone();
    let mut k = 0;
    let mut ok = true;
    visit(given, &given.clone(), |l, i, j, _| {
        let bit = bits.get(k).unwrap_or_else(|| {
            ok = false;
            false
        });
        k += 1;
        cut.set_split(l, i, j, bit);
        bit
    });
    (ok && k == bits.len).then_some(cut)
}

/// What a parent patch gives a child: its cut and the heights of its active nodes, and
/// which quarter of it the child is.
#[derive(Debug, Clone, Copy)]
pub struct Parent<'a> {
    pub cut: &'a Cut,
    pub heights: &'a NodeHeights,
    pub quarter: (u32, u32),
}

impl Parent<'_> {
    /// The child's node `(l, i, j)` as the parent's node.
    pub fn node(&self, l: u32, i: u32, j: u32) -> (u32, u32, u32) {
        let (qx, qy) = self.quarter;
        (l + 1, (qx << l) + i, (qy << l) + j)
    }

    /// The parent's active node over the child's node `(l, i, j)`: its morph target.
    pub fn leaf_above(&self, l: u32, i: u32, j: u32) -> (u32, u32, u32) {
        let (pl, pi, pj) = self.node(l, i, j);
        self.cut.leaf_above(pl, pi, pj)
    }

    /// Whether the parent holds the child's node `(l, i, j)` as an active node (the
    /// child's finest level is finer than any of the parent's).
    pub fn holds(&self, l: u32, i: u32, j: u32) -> bool {
        let (pl, pi, pj) = self.node(l, i, j);
        pl <= self.cut.tree.n && self.cut.is_leaf(pl, pi, pj)
    }

    /// The cut the parent gives the child.
    pub fn given(&self) -> Cut {
        self.cut.quarter(self.quarter.0, self.quarter.1)
    }
}

/// A patch as the client holds it: its cut, the heights of its active nodes (height codes
/// of the manifest's quantum) and of the ring vertices its triangulation uses.
#[derive(Debug, Clone, PartialEq)]
pub struct PatchData {
    pub cut: Cut,
    pub nodes: NodeHeights,
    pub border: FastMap<Vertex, i32>,
}

/// Why a patch body was refused.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum PatchError {
    #[error("patch data is {0} bytes, shorter than its header")]
    Short(usize),
    #[error("patch data does not start with the quadtree-patches magic")]
    Magic,
    #[error("patch data is for trees of depth {found}, the database's are {expected}")]
    Depth { expected: u32, found: u32 },
    #[error("patch data's split bits do not make a tree that refines its parent's")]
    Splits,
    #[error("patch data's heights do not decompress: {0}")]
    Compressed(String),
    #[error("patch data holds {found} heights where its tree needs {expected}")]
    Heights { expected: usize, found: usize },
    #[error("the patch index is {found} bytes, {expected} expected")]
    IndexSize { expected: usize, found: usize },
}

const PATCH_MAGIC: &[u8; 4] = b"QTP1";
const INDEX_MAGIC: &[u8; 4] = b"QTPI";
/// Largest patch body a client accepts: a full tree's bits and every height at 5 bytes.
pub fn max_patch_bytes(tree: Tree) -> usize {
    16 + tree.nodes() / 8 + 16 * tree.nodes() + 4096
}

fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

fn unzigzag(v: u64) -> i64 {
    ((v >> 1) as i64) ^ -((v & 1) as i64)
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn varints(bytes: &[u8]) -> Option<Vec<u64>> {
    let mut out = Vec::new();
    let mut v = 0u64;
    let mut shift = 0;
    for &b in bytes {
        if shift > 63 {
            return None;
        }
        v |= u64::from(b & 0x7f) << shift;
        if b & 0x80 == 0 {
            out.push(v);
            v = 0;
            shift = 0;
        } else {
            shift += 7;
        }
    }
    (shift == 0).then_some(out)
}

/// The nodes a patch's body carries heights for, in order: its active nodes the parent
/// does not hold as active nodes too, with the height each is predicted from (the
/// parent's active node over it; 0 for the root patch).
fn new_nodes(cut: &Cut, parent: Option<&Parent<'_>>) -> Vec<((u32, u32, u32), i32)> {
    cut.leaves()
        .into_iter()
        .filter_map(|(l, i, j)| match parent {
            None => Some(((l, i, j), 0)),
            Some(p) => {
                if p.holds(l, i, j) {
                    None
                } else {
                    let above = p.leaf_above(l, i, j);
                    Some(((l, i, j), p.heights.get(&above).copied().unwrap_or(0)))
                }
            }
        })
        .collect()
}

/// The ring vertices `triangles` use, in order.
pub fn border_vertices(triangles: &[[Vertex; 3]]) -> Vec<Vertex> {
    let mut ring: Vec<Vertex> = triangles
        .iter()
        .flatten()
        .copied()
        .filter(|v| v.on_border())
        .collect();
    ring.sort();
    ring.dedup();
    ring
}

/// A patch's body: the split bits from what `parent` gives (the root patch: from its root
/// alone), then one zstd frame of the heights it adds, zigzag varints: each new active
/// node's difference from its parent's active node over it, then each ring vertex's
/// difference from the one before. `height` gives any vertex's height code.
pub fn encode_patch(
    cut: &Cut,
    parent: Option<&Parent<'_>>,
    height: impl Fn(Vertex) -> i32,
    finest_are_samples: bool,
    zstd_level: i32,
) -> Vec<u8> {
    let triangles = triangulate(cut);
    encode_triangulated_patch(
        cut,
        &triangles,
        parent,
        height,
        finest_are_samples,
        zstd_level,
    )
}

/// [`encode_patch`] given the cut's triangulation, for a caller that has it already.
pub fn encode_triangulated_patch(
    cut: &Cut,
    triangles: &[[Vertex; 3]],
    parent: Option<&Parent<'_>>,
    height: impl Fn(Vertex) -> i32,
    finest_are_samples: bool,
    zstd_level: i32,
) -> Vec<u8> {
    let tree = cut.tree;
    let given = parent.map_or_else(|| Cut::root(tree), Parent::given);
    let bits = encode_splits(&given, cut);
    let mut values = Vec::new();
    for ((l, i, j), predicted) in new_nodes(cut, parent) {
        let h = height(Vertex::Node {
            l: l as u8,
            i: i as u16,
            j: j as u16,
        });
        let (h, predicted) = if finest_are_samples && l == tree.n {
            (h.div_euclid(SUBCODES), predicted.div_euclid(SUBCODES))
        } else {
            (h, predicted)
        };
        put_varint(&mut values, zigzag(i64::from(h) - i64::from(predicted)));
    }
    let mut previous = 0i64;
    for v in border_vertices(triangles) {
        let h = i64::from(height(v));
        put_varint(&mut values, zigzag(h - previous));
        previous = h;
    }
    let mut out = Vec::with_capacity(12 + bits.bytes.len() + values.len() / 2);
    out.extend_from_slice(PATCH_MAGIC);
    out.extend_from_slice(&[tree.n as u8, 0, 0, 0]);
    out.extend_from_slice(&(bits.len as u32).to_le_bytes());
    out.extend_from_slice(&bits.bytes);
    out.extend_from_slice(&compress(&values, zstd_level));
    out
}

/// One zstd frame of a patch's values (empty if zstd fails, which it does not on a buffer).
#[cfg(not(target_arch = "wasm32"))]
fn compress(values: &[u8], level: i32) -> Vec<u8> {
    zstd::bulk::compress(values, level).unwrap_or_default()
}

/// A patch's values, at most `max` bytes.
#[cfg(not(target_arch = "wasm32"))]
fn decompress(frame: &[u8], max: usize) -> Result<Vec<u8>, String> {
    zstd::bulk::decompress(frame, max).map_err(|e| e.to_string())
}

/// The browser build has no zstd C library (it does not build for the page without a C
/// toolchain for it): it reads patches (with ruzstd) but does not write them.
#[cfg(target_arch = "wasm32")]
fn compress(_values: &[u8], _level: i32) -> Vec<u8> {
    Vec::new()
}

/// A patch's values, at most `max` bytes, read with ruzstd ([`crate::zstd_frames`]).
#[cfg(target_arch = "wasm32")]
fn decompress(frame: &[u8], max: usize) -> Result<Vec<u8>, String> {
    crate::zstd_frames::decode_frames(frame, max).map_err(|e| e.to_string())
}

/// Decodes a patch's body against what its parent gives; any bytes give a patch or an
/// error, never a panic.
pub fn decode_patch(
    tree: Tree,
    parent: Option<&Parent<'_>>,
    finest_are_samples: bool,
    bytes: &[u8],
) -> Result<PatchData, PatchError> {
    if bytes.len() < 12 {
        return Err(PatchError::Short(bytes.len()));
    }
    if &bytes[..4] != PATCH_MAGIC {
        return Err(PatchError::Magic);
    }
    if u32::from(bytes[4]) != tree.n {
        return Err(PatchError::Depth {
            expected: tree.n,
            found: u32::from(bytes[4]),
        });
    }
    let len = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize;
    if len > tree.nodes() {
        return Err(PatchError::Splits);
    }
    let bit_bytes = len.div_ceil(8);
    let rest = &bytes[12..];
    if rest.len() < bit_bytes {
        return Err(PatchError::Short(bytes.len()));
    }
    let bits = Bits {
        bytes: rest[..bit_bytes].to_vec(),
        len,
    };
    let given = parent.map_or_else(|| Cut::root(tree), Parent::given);
    let cut = decode_splits(&given, &bits).ok_or(PatchError::Splits)?;
    let values =
        decompress(&rest[bit_bytes..], max_patch_bytes(tree)).map_err(PatchError::Compressed)?;
    let values =
        varints(&values).ok_or_else(|| PatchError::Compressed("a varint runs on".into()))?;
    let new = new_nodes(&cut, parent);
    let ring = border_vertices(&triangulate(&cut));
    if values.len() != new.len() + ring.len() {
        return Err(PatchError::Heights {
            expected: new.len() + ring.len(),
            found: values.len(),
        });
    }
    let clamp = |v: i64| v.clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32;
    let mut nodes = NodeHeights::default();
    if let Some(p) = parent {
        for (l, i, j) in cut.leaves() {
            if p.holds(l, i, j) {
                let pn = p.node(l, i, j);
                nodes.insert((l, i, j), p.heights.get(&pn).copied().unwrap_or(0));
            }
        }
    }
    for ((node, predicted), &v) in new.iter().zip(&values) {
        let h = if finest_are_samples && node.0 == tree.n {
            (i64::from(predicted.div_euclid(SUBCODES)) + unzigzag(v)) * i64::from(SUBCODES)
        } else {
            i64::from(*predicted) + unzigzag(v)
        };
        nodes.insert(*node, clamp(h));
    }
    let mut border = FastMap::default();
    let mut previous = 0i64;
    for (vertex, &v) in ring.iter().zip(&values[new.len()..]) {
        previous += unzigzag(v);
        border.insert(*vertex, clamp(previous));
    }
    Ok(PatchData { cut, nodes, border })
}

/// What the index says of one patch (one per tile, in the manifest's tile order).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PatchEntry {
    /// BLAKE3 of the body, first 16 bytes.
    pub hash: [u8; 16],
    pub bytes: u32,
    /// Its world-space error: the largest vertical distance of its triangulation from the
    /// full-resolution samples under it, metres.
    pub error_m: f32,
    /// Height bounds of its vertices, metres.
    pub min_m: f32,
    pub max_m: f32,
    /// Its triangulation's size ([`MeshCounts::of`]): what a client's mesh of it holds is
    /// known before the body arrives.
    pub mesh: MeshCounts,
}

/// The size of a patch's triangulation: distinct vertices and triangles of its surface
/// ([`triangulate`]), and vertices of the ring around it ([`border_loop`]), which a client
/// hangs its flanges from.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MeshCounts {
    pub vertices: u32,
    pub triangles: u32,
    pub ring: u32,
}

impl MeshCounts {
    /// The counts of `cut`'s triangulation, `triangles` ([`triangulate`] of it).
    pub fn of(cut: &Cut, triangles: &[[Vertex; 3]]) -> MeshCounts {
        let distinct: FastSet<Vertex> = triangles.iter().flatten().copied().collect();
        MeshCounts {
            vertices: distinct.len() as u32,
            triangles: triangles.len() as u32,
            ring: border_loop(cut).len() as u32,
        }
    }
}

impl PatchEntry {
    /// The hash in the manifest's spelling (lowercase hex).
    pub fn hash_hex(&self) -> String {
        self.hash.iter().map(|b| format!("{b:02x}")).collect()
    }
}

/// Bytes per index entry.
pub const INDEX_ENTRY_BYTES: usize = 44;

/// The patch index: `QTPI`, the count, then 44 bytes per patch: hash, body size, error,
/// height bounds, then the mesh counts (vertices, triangles, ring).
pub fn encode_index(entries: &[PatchEntry]) -> Vec<u8> {
    let mut out = Vec::with_capacity(8 + entries.len() * INDEX_ENTRY_BYTES);
    out.extend_from_slice(INDEX_MAGIC);
    out.extend_from_slice(&(entries.len() as u32).to_le_bytes());
    for e in entries {
        out.extend_from_slice(&e.hash);
        out.extend_from_slice(&e.bytes.to_le_bytes());
        for f in [e.error_m, e.min_m, e.max_m] {
            out.extend_from_slice(&f.to_le_bytes());
        }
        for n in [e.mesh.vertices, e.mesh.triangles, e.mesh.ring] {
            out.extend_from_slice(&n.to_le_bytes());
        }
    }
    out
}

/// Decodes an index of `count` patches.
pub fn decode_index(bytes: &[u8], count: usize) -> Result<Vec<PatchEntry>, PatchError> {
    let expected = 8 + count * INDEX_ENTRY_BYTES;
    if bytes.len() != expected || &bytes[..4] != INDEX_MAGIC {
        return Err(PatchError::IndexSize {
            expected,
            found: bytes.len(),
        });
    }
    let word = |b: &[u8]| [b[0], b[1], b[2], b[3]];
    if u32::from_le_bytes(word(&bytes[4..8])) as usize != count {
        return Err(PatchError::IndexSize {
            expected,
            found: bytes.len(),
        });
    }
    Ok(bytes[8..]
        .chunks_exact(INDEX_ENTRY_BYTES)
        .map(|c| {
            let mut hash = [0; 16];
            hash.copy_from_slice(&c[..16]);
            let f = |k: usize| f32::from_le_bytes(word(&c[20 + 4 * k..]));
            let n = |k: usize| u32::from_le_bytes(word(&c[32 + 4 * k..]));
            PatchEntry {
                hash,
                bytes: u32::from_le_bytes(word(&c[16..20])),
                error_m: f(0),
                min_m: f(1),
                max_m: f(2),
                mesh: MeshCounts {
                    vertices: n(0),
                    triangles: n(1),
                    ring: n(2),
                },
            }
        })
        .collect())
}

/// Where a patch's far sides lie, in patch units: its extent, or the terrain's last sample
/// where that runs past the last patch of its row or column (cell-centred patches end half
/// a sample before a tile pyramid whose raster is `2^k + 1` samples wide).
pub fn far_edge(
    tree: Tree,
    level: u32,
    x: u32,
    y: u32,
    raster: [u32; 2],
    grid: [u32; 2],
) -> [f32; 2] {
    let extent = tree.extent() as f64;
    let span = f64::from(1u32 << (tree.n + level));
    let unit = span / extent;
    std::array::from_fn(|axis| {
        let index = [x, y][axis];
        let origin = f64::from(index) * span - 0.5;
        let edge = (f64::from(raster[axis]) - 1.0 - origin) / unit;
        if index + 1 == grid[axis] && edge > extent {
            edge as f32
        } else {
            extent as f32
        }
    })
}

/// Sample coordinates of a point at `p` patch units in patch `(level, x, y)`.
pub fn sample_of(tree: Tree, level: u32, x: u32, y: u32, p: [f32; 2]) -> [f64; 2] {
    let span = f64::from(1u32 << (tree.n + level));
    let unit = span / tree.extent() as f64;
    [
        f64::from(x) * span - 0.5 + f64::from(p[0]) * unit,
        f64::from(y) * span - 0.5 + f64::from(p[1]) * unit,
    ]
}

/// Signed area of a triangle (positive: counter-clockwise).
pub fn area(p: [[f32; 2]; 3]) -> f64 {
    let [a, b, c] = p.map(|q| [f64::from(q[0]), f64::from(q[1])]);
    0.5 * ((b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random_cut(tree: Tree, seed: u64, keep: f64) -> Cut {
        // Merge bottom-up at random, as the builder does (only mergeable nodes).
        let mut cut = Cut::full(tree);
        let mut s = seed;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 33) as f64 / (1u64 << 31) as f64
        };
        for l in (0..tree.n).rev() {
            let side = 1 << l;
            for j in 0..side {
                for i in 0..side {
                    let mergeable =
                        (0..4).all(|c| !cut.is_split(l + 1, 2 * i + c % 2, 2 * j + c / 2));
                    if mergeable && next() > keep {
                        cut.set_split(l, i, j, false);
                    }
                }
            }
        }
        cut
    }

    #[test]
    fn every_cut_triangulates_the_patch_once_without_folds() {
        for n in 1..=5 {
            let tree = Tree { n };
            for seed in 0..40 {
                let cut = random_cut(tree, seed, [0.2, 0.5, 0.8][seed as usize % 3]);
                let tris = triangulate(&cut);
                let e = tree.extent() as f32;
                let mut total = 0.0;
                for t in &tris {
                    let a = area(t.map(|v| v.position(tree, [e, e])));
                    assert!(a > 0.0, "n {n} seed {seed}: folded or flat {t:?} area {a}");
                    total += a;
                }
                assert!(
                    (total - f64::from(e * e)).abs() < 1e-6,
                    "n {n} seed {seed}: covers {total} of {}",
                    e * e
                );
            }
        }
    }

    /// What a merge makes, found from the node's border alone, is what listing the node's
    /// cells before and after the merge finds.
    #[test]
    fn the_triangles_of_a_merged_leaf_are_what_the_merge_made() {
        let mut merges = 0;
        let mut found = Vec::new();
        for n in 1..=5 {
            let tree = Tree { n };
            for seed in 0..24 {
                let mut cut = random_cut(tree, seed, [0.3, 0.6, 0.9][seed as usize % 3]);
                let p = tree.side();
                for l in (0..n).rev() {
                    let s = 1u32 << (n - l);
                    for j in 0..1u32 << l {
                        for i in 0..1u32 << l {
                            let mergeable = cut.is_split(l, i, j)
                                && cut.reached(l, i, j)
                                && (0..4)
                                    .all(|c| !cut.is_split(l + 1, 2 * i + c % 2, 2 * j + c / 2));
                            if !mergeable {
                                continue;
                            }
                            let a = i * s..((i + 1) * s + 1).min(p + 1);
                            let b = j * s..((j + 1) * s + 1).min(p + 1);
                            let before: FastSet<[Vertex; 3]> =
                                triangles_in(&cut, a.clone(), b.clone())
                                    .into_iter()
                                    .collect();
                            cut.set_split(l, i, j, false);
                            let mut made: Vec<_> = triangles_in(&cut, a, b)
                                .into_iter()
                                .filter(|t| !before.contains(t))
                                .collect();
                            made.sort_unstable();
                            assert!(!made.is_empty());
                            triangles_of_leaf(&cut, (l, i, j), &mut found);
                            assert_eq!(found, made, "n {n} seed {seed} node ({l}, {i}, {j})");
                            merges += 1;
                            if (seed + u64::from(i + j)) % 3 == 0 {
                                cut.set_split(l, i, j, true);
                            }
                        }
                    }
                }
            }
        }
        assert!(merges > 1000, "{merges} merges checked");
    }

    #[test]
    fn a_full_cut_is_the_regular_grid_and_a_root_cut_a_fan_of_eight() {
        let tree = Tree { n: 3 };
        assert_eq!(triangulate(&Cut::full(tree)).len(), 2 * 9 * 9);
        assert_eq!(triangulate(&Cut::root(tree)).len(), 8);
    }

    #[test]
    fn splits_round_trip_through_bits_from_the_parents_quarter() {
        let tree = Tree { n: 4 };
        for seed in 0..30 {
            let parent = random_cut(tree, seed, 0.3);
            for q in 0..4 {
                let given = parent.quarter(q % 2, q / 2);
                // A child refines what its parent gives.
                let mut child = random_cut(tree, seed + 100, 0.7);
                for l in 0..tree.n {
                    for j in 0..1 << l {
                        for i in 0..1 << l {
                            if given.is_split(l, i, j) {
                                child.set_split(l, i, j, true);
                            }
                        }
                    }
                }
                let bits = encode_splits(&given, &child);
                assert_eq!(decode_splits(&given, &bits).as_ref(), Some(&child));
                let mut short = bits.clone();
                if short.len > 0 {
                    short.len -= 1;
                    assert_eq!(decode_splits(&given, &short), None);
                }
            }
        }
    }

    #[test]
    fn the_neville_filter_keeps_a_cubic_exactly_inside() {
        let (w, h) = (16, 12);
        let f = |x: f64, y: f64| 0.1 * x * x * x - x * y + 2.0 * y * y - 3.0;
        let fine: Vec<f64> = (0..h)
            .flat_map(|y| (0..w).map(move |x| f(x as f64, y as f64)))
            .collect();
        let (coarse, cw, ch) = neville(&fine, w, h);
        assert_eq!((cw, ch), (8, 6));
        for j in 1..ch - 1 {
            for i in 1..cw - 1 {
                let (x, y) = (2.0 * i as f64 + 0.5, 2.0 * j as f64 + 0.5);
                assert!((coarse[j * cw + i] - f(x, y)).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn patches_round_trip_and_refuse_every_truncation() {
        let tree = Tree { n: 3 };
        let height = |v: Vertex| match v {
            Vertex::Node { l, i, j } => i32::from(l) * 100 + i32::from(i) * 7 - i32::from(j) * 3,
            Vertex::Side { side, l, k } => {
                i32::from(side) * 1000 + i32::from(l) * 10 + i32::from(k)
            }
            Vertex::Corner { corner, l } => -i32::from(corner) - 50 * i32::from(l),
        };
        let node_h = |(l, i, j): (u32, u32, u32)| {
            height(Vertex::Node {
                l: l as u8,
                i: i as u16,
                j: j as u16,
            })
        };
        let root_cut = random_cut(tree, 3, 0.4);
        let bytes = encode_patch(&root_cut, None, height, false, 3);
        let root = decode_patch(tree, None, false, &bytes).expect("the root decodes");
        assert_eq!(root.cut, root_cut);
        for (&node, &h) in &root.nodes {
            assert_eq!(h, node_h(node));
        }
        for (&v, &h) in &root.border {
            assert_eq!(h, height(v));
        }
        for q in 0..4 {
            let parent = Parent {
                cut: &root.cut,
                heights: &root.nodes,
                quarter: (q % 2, q / 2),
            };
            let given = parent.given();
            let mut cut = Cut::full(tree);
            for l in 0..tree.n {
                for j in 0..1 << l {
                    for i in 0..1 << l {
                        if !given.is_split(l, i, j) && l > 1 && q % 2 == 0 {
                            cut.set_split(l, i, j, false);
                        }
                    }
                }
            }
            let bytes = encode_patch(&cut, Some(&parent), height, false, 3);
            let child = decode_patch(tree, Some(&parent), false, &bytes).expect("a child decodes");
            assert_eq!(child.cut, cut);
            for (&(l, i, j), &h) in &child.nodes {
                // A node the parent holds comes with the parent's height (the same vertex
                // of the pyramid); the others from the body.
                if parent.holds(l, i, j) {
                    assert_eq!(h, node_h(parent.node(l, i, j)));
                } else {
                    assert_eq!(h, node_h((l, i, j)));
                }
            }
            for k in 0..bytes.len() {
                assert!(decode_patch(tree, Some(&parent), false, &bytes[..k]).is_err());
            }
        }
    }

    #[test]
    fn the_index_round_trips_and_refuses_a_wrong_count() {
        let e = PatchEntry {
            hash: [7; 16],
            bytes: 12,
            error_m: 0.5,
            min_m: -3.0,
            max_m: 9.0,
            mesh: MeshCounts {
                vertices: 5,
                triangles: 4,
                ring: 4,
            },
        };
        let bytes = encode_index(&[e, e]);
        assert_eq!(decode_index(&bytes, 2).expect("decodes"), vec![e, e]);
        assert!(decode_index(&bytes, 3).is_err());
        assert!(decode_index(&bytes[..bytes.len() - 1], 2).is_err());
    }

    #[test]
    fn the_border_loop_closes_around_the_patch() {
        let tree = Tree { n: 3 };
        for seed in 0..20 {
            let cut = random_cut(tree, seed, 0.5);
            let ring = border_loop(&cut);
            assert!(ring.iter().all(|v| v.on_border()));
            let corners = ring
                .iter()
                .filter(|v| matches!(v, Vertex::Corner { .. }))
                .count();
            assert_eq!(corners, 4);
        }
    }

    #[test]
    fn the_last_patches_reach_the_terrains_last_sample() {
        let tree = Tree { n: 3 };
        // 33 samples: 4 patches of 8 end half a sample short of sample 32 unless the last
        // one's far side moves out to it; 30 samples end inside the last patch.
        for (width, grid) in [(33u32, 4u32), (30, 4), (65, 8)] {
            for x in 0..grid {
                let far = far_edge(tree, 0, x, 0, [width, width], [grid, grid]);
                let right = sample_of(tree, 0, x, 0, [far[0], 0.0])[0];
                if x + 1 == grid {
                    assert!(
                        right >= f64::from(width - 1),
                        "{width}: patch {x} ends at {right}"
                    );
                } else {
                    assert_eq!(far[0], tree.extent() as f32);
                    let next = sample_of(tree, 0, x + 1, 0, [0.0, 0.0])[0];
                    assert_eq!(right, next, "patches meet");
                }
            }
        }
    }
}
