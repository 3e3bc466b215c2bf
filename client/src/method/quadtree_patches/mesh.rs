//! A patch's mesh: its body decoded against its parent's data, its vertices (own place and
//! height, the morph target's, the flange flag) and indices (surface, then flanges), built
//! on the method's worker thread; and the surface a patch's triangles make, which the
//! tests compare with the full-resolution heights; and the bytes a patch's mesh holds.

use super::VERTEX_BYTES;
use std::sync::Arc;
use terrain_shared::TileId;
use terrain_shared::quadtree::{self, FastMap, Parent, PatchData, PatchEntry, Tree, Vertex};

/// What the method will hold for patch bodies of `body_bytes` together, estimated from
/// their size alone (a body spends about 2 bytes an active vertex, which becomes a vertex,
/// its share of the triangles' 16-bit indices and of the flanges, and its decoded height):
/// for sizing a whole database from its manifest, before the index is in.
/// [`expected_bytes`] is the bound per patch.
pub fn estimated_bytes(body_bytes: u64) -> u64 {
    body_bytes * (VERTEX_BYTES + 12 + 32) / 2
}

/// The most the method holds for a patch of `entry` at a tree of `tree` and `level`: its
/// body while it waits to be meshed, then its mesh (every vertex of the surface and of the
/// flanges' feet, 32 bytes; the surface's and flanges' indices, 16-bit when the vertices
/// allow) and its decoded data ([`data_bytes`] at most: a node a surface vertex, a border
/// entry a ring vertex). Known from the index before the body arrives, so the pager can
/// make room for it.
pub fn expected_bytes(entry: &PatchEntry, tree: Tree, level: u32) -> u64 {
    let m = entry.mesh;
    let vertices = u64::from(m.vertices) + u64::from(m.ring);
    let index_bytes = if vertices <= u64::from(u16::MAX) + 1 {
        2
    } else {
        4
    };
    let indices = 3 * u64::from(m.triangles) + 6 * u64::from(m.ring);
    let gpu = vertices * VERTEX_BYTES + indices * index_bytes;
    let cpu = if level == 0 {
        0
    } else {
        u64::from(m.vertices) * 32 + u64::from(m.ring) * 24
    } + (tree.nodes() / 8 + 64) as u64;
    u64::from(entry.bytes) + gpu + cpu
}

/// The most a patch of `tree` can hold ([`expected_bytes`] of the full triangulation, with
/// a body of 4 bytes a vertex): what the pager expects of a tile while the index that says
/// better is on its way, so that it does not fill with tiles whose patches do not fit.
pub fn most_bytes(tree: Tree) -> u64 {
    let full = quadtree::Cut::full(tree);
    let mesh = quadtree::MeshCounts::of(&full, &quadtree::triangulate(&full));
    let entry = PatchEntry {
        hash: [0; 16],
        bytes: 4 * mesh.vertices,
        error_m: 0.0,
        min_m: 0.0,
        max_m: 0.0,
        mesh,
    };
    expected_bytes(&entry, tree, 1)
}

/// CPU bytes a decoded patch holds (its maps' entries, about).
pub(super) fn data_bytes(data: &PatchData) -> u64 {
    (data.nodes.len() * 32 + data.border.len() * 24 + data.cut.tree.nodes() / 8 + 64) as u64
}

/// Height of the surface `triangles` make at `p`, or `None` outside them.
pub(super) fn surface_at(triangles: &[[[f32; 3]; 3]], p: [f32; 2]) -> Option<f32> {
    for t in triangles {
        let [a, b, c] = *t;
        let det = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
        if det.abs() < 1e-12 {
            continue;
        }
        let w1 = ((p[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (p[1] - a[1])) / det;
        let w2 = ((b[0] - a[0]) * (p[1] - a[1]) - (p[0] - a[0]) * (b[1] - a[1])) / det;
        let w0 = 1.0 - w1 - w2;
        let eps = -1e-4;
        if w0 >= eps && w1 >= eps && w2 >= eps {
            return Some(w0 * a[2] + w1 * b[2] + w2 * c[2]);
        }
    }
    None
}

/// A patch's triangles with positions (patch units) and heights (metres).
pub(super) fn placed(
    tree: Tree,
    far: [f32; 2],
    data: &PatchData,
    metres: impl Fn(i32) -> f32,
) -> Vec<[[f32; 3]; 3]> {
    quadtree::triangulate(&data.cut)
        .iter()
        .map(|t| {
            t.map(|v| {
                let [x, y] = v.position(tree, far);
                [x, y, metres(height_of(data, v))]
            })
        })
        .collect()
}

pub(super) fn height_of(data: &PatchData, v: Vertex) -> i32 {
    match v {
        Vertex::Node { l, i, j } => data
            .nodes
            .get(&(u32::from(l), u32::from(i), u32::from(j)))
            .copied()
            .unwrap_or(0),
        _ => data.border.get(&v).copied().unwrap_or(0),
    }
}

/// A built patch: its data, its vertices (8 words each), its indices (16-bit when its
/// vertices allow) and its triangles.
pub(super) type Mesh = (Arc<PatchData>, Vec<u32>, Indices, u32);

/// Index data, 16-bit when the vertices allow.
#[derive(Debug)]
pub(super) enum Indices {
    U16(Vec<u16>),
    U32(Vec<u32>),
}

/// Decodes a body against its parent and makes its vertices (own place and height, its
/// morph target's, the flange flag) and indices (surface, then flanges).
pub(super) fn build_mesh(
    tree: Tree,
    id: TileId,
    far: [f32; 2],
    parent: Option<(TileId, Arc<PatchData>, [f32; 2])>,
    (offset_m, subcode_m): (f64, f64),
    spacing: [f64; 2],
    body: &[u8],
) -> Result<Mesh, String> {
    let metres = |c: i32| (offset_m + subcode_m * f64::from(c)) as f32;
    let quarter = (id.x % 2, id.y % 2);
    let link = parent.as_ref().map(|(_, p, _)| Parent {
        cut: &p.cut,
        heights: &p.nodes,
        quarter,
    });
    let data = quadtree::decode_patch(tree, link.as_ref(), id.level == 0, body)
        .map_err(|e| e.to_string())?;
    let triangles = quadtree::triangulate(&data.cut);
    let parent_surface = parent
        .as_ref()
        .map(|(_, p, pfar)| placed(tree, *pfar, p, metres));
    let extent = tree.extent() as f32;
    // Parent units are twice the child's; the child's quarter starts at `quarter * extent`
    // of the child's units in the parent's doubled frame.
    let to_child = |p: [f32; 2]| {
        [
            2.0 * p[0] - quarter.0 as f32 * extent,
            2.0 * p[1] - quarter.1 as f32 * extent,
        ]
    };
    let to_parent = |p: [f32; 2]| {
        [
            (p[0] + quarter.0 as f32 * extent) / 2.0,
            (p[1] + quarter.1 as f32 * extent) / 2.0,
        ]
    };
    let mut index_of: FastMap<Vertex, u32> = FastMap::default();
    let mut vertices: Vec<f32> = Vec::new();
    let push = |v: Vertex, flange: bool, vertices: &mut Vec<f32>| -> u32 {
        let [x, y] = v.position(tree, far);
        let h = metres(height_of(&data, v));
        let (target, th) = match (&link, &parent_surface) {
            (Some(link), Some(surface)) => match v {
                Vertex::Node { l, i, j } => {
                    let (pl, pi, pj) = link.leaf_above(u32::from(l), u32::from(i), u32::from(j));
                    let at = tree.node_position(pl, pi, pj).map(|c| c as f32);
                    let ph = link.heights.get(&(pl, pi, pj)).copied().map_or(h, metres);
                    (to_child(at), ph)
                }
                _ => {
                    // A ring vertex stays on its side, at the place its inner neighbour's
                    // target has along it, on the parent's surface.
                    let along = match v {
                        Vertex::Side { side, l, k } => {
                            let (k, last) = (u32::from(k), (1u32 << l) - 1);
                            let (ni, nj) = match side {
                                0 => (k, 0),
                                1 => (last, k),
                                2 => (k, last),
                                _ => (0, k),
                            };
                            let (pl, pi, pj) = link.leaf_above(u32::from(l), ni, nj);
                            let at = to_child(tree.node_position(pl, pi, pj).map(|c| c as f32));
                            match side {
                                0 | 2 => [at[0], y],
                                _ => [x, at[1]],
                            }
                        }
                        _ => [x, y],
                    };
                    let ph = surface_at(surface, to_parent(along)).unwrap_or(h);
                    (along, ph)
                }
            },
            _ => ([x, y], h),
        };
        let index = (vertices.len() / 8) as u32;
        vertices.extend_from_slice(&[
            x,
            y,
            h,
            target[0],
            target[1],
            th,
            f32::from(u8::from(flange)),
            0.0,
        ]);
        index
    };
    let mut indices = Vec::with_capacity(triangles.len() * 3);
    for t in &triangles {
        for v in t {
            let k = match index_of.get(v) {
                Some(&k) => k,
                None => {
                    let k = push(*v, false, &mut vertices);
                    index_of.insert(*v, k);
                    k
                }
            };
            indices.push(k);
        }
    }
    let surface = triangles.len() as u32;
    let ring = quadtree::border_loop(&data.cut);
    let mut feet = FastMap::default();
    for v in &ring {
        let k = push(*v, true, &mut vertices);
        feet.insert(*v, k);
    }
    // Normals: area-weighted over the surface's triangles, in render space (x east, y up,
    // z south); a flange's foot takes its top's.
    let unit = f64::from(1u32 << (tree.n + id.level)) / f64::from(tree.extent());
    let [sx, sy] = [spacing[0] * unit, spacing[1] * unit];
    let count = vertices.len() / 8;
    let mut normals = vec![[0.0f64; 3]; count];
    for t in indices.chunks_exact(3) {
        let t = [t[0], t[1], t[2]];
        let p = t.map(|k| {
            let v = &vertices[k as usize * 8..];
            [f64::from(v[0]) * sx, f64::from(v[2]), f64::from(v[1]) * sy]
        });
        let (a, b) = (
            [p[1][0] - p[0][0], p[1][1] - p[0][1], p[1][2] - p[0][2]],
            [p[2][0] - p[0][0], p[2][1] - p[0][1], p[2][2] - p[0][2]],
        );
        let mut n = [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ];
        if n[1] < 0.0 {
            n = n.map(|c| -c);
        }
        for &k in &t {
            for c in 0..3 {
                normals[k as usize][c] += n[c];
            }
        }
    }
    for v in &ring {
        if let Some(&top) = index_of.get(v) {
            normals[feet[v] as usize] = normals[top as usize];
        }
    }
    let mut flange_triangles = 0;
    for w in 0..ring.len() {
        let (a, b) = (ring[w], ring[(w + 1) % ring.len()]);
        let (Some(&ta), Some(&tb)) = (index_of.get(&a), index_of.get(&b)) else {
            continue;
        };
        let (fa, fb) = (feet[&a], feet[&b]);
        indices.extend_from_slice(&[ta, tb, fb, ta, fb, fa]);
        flange_triangles += 2;
    }
    let words: Vec<u32> = vertices
        .chunks_exact(8)
        .zip(&normals)
        .flat_map(|(v, n)| {
            let length = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().max(1e-12);
            let packed = terrain_shaders::pack_normal(n.map(|c| (c / length) as f32));
            v[..7]
                .iter()
                .map(|f| f.to_bits())
                .chain(std::iter::once(packed))
                .collect::<Vec<_>>()
        })
        .collect();
    let indices = if count <= usize::from(u16::MAX) + 1 {
        Indices::U16(indices.iter().map(|&k| k as u16).collect())
    } else {
        Indices::U32(indices)
    };
    Ok((Arc::new(data), words, indices, surface + flange_triangles))
}
