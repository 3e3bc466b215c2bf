//! The crack fillers of the strip-mask method (the strip-mask paper's section 5.4): skirts
//! (a vertical band down from every kept border sample) and the planar shadow (a textured
//! quad under each tile, its corners projected from the viewpoint onto a plane below it).
//! Their geometry is drawn through the tile pipeline: the shader places the indices past a
//! tile's samples (`terrain_shaders::skirt_base`, `terrain_shaders::shadow_base`).

use terrain_shared::mask;

/// Largest stretch of a planar shadow's corner projection ([`shadow_corner`]).
pub const SHADOW_MAX_STRETCH: f32 = 64.0;

/// How cracks between tiles of different mask levels are filled (section 5.4).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum CrackFiller {
    /// Nothing: cracks show the background.
    None,
    /// Vertical bands along each tile's border down below the tile (the paper's filleting).
    Skirts,
    /// A textured quad under each tile, its corners projected from the viewpoint onto a
    /// plane below the tile (the paper's method). It shows wherever the quad is not hidden,
    /// not only in cracks: past skylines and in front of lower tiles too.
    #[default]
    PlanarShadow,
}

impl CrackFiller {
    pub fn name(self) -> &'static str {
        match self {
            CrackFiller::None => "none",
            CrackFiller::Skirts => "skirts",
            CrackFiller::PlanarShadow => "planar-shadow",
        }
    }
}

/// Depth of the filler plane below a tile's lowest sample: a tenth of its side, at least
/// 1 m.
pub fn filler_depth_m(tile_extent_m: [f64; 2]) -> f64 {
    (0.1 * tile_extent_m[0].min(tile_extent_m[1])).max(1.0)
}

/// Where the planar shadow puts a tile corner at `corner` (render space, relative to the
/// camera at the origin): on the ray from the camera through it, where the ray meets the
/// horizontal plane at height `plane` (also camera-relative), below the tile. Near grazing
/// angles, or with the corner above the camera, the stretch is capped at
/// [`SHADOW_MAX_STRETCH`]: the shadow then misses (the method's known failure), but stays
/// finite. With the camera below the plane there is nothing to project from, and the corner
/// is laid on the plane.
pub fn shadow_corner(corner: glam::DVec3, plane: f64) -> glam::DVec3 {
    if plane >= 0.0 {
        return glam::DVec3::new(corner.x, plane, corner.z);
    }
    let t = -plane / (-corner.y).max(-plane / f64::from(SHADOW_MAX_STRETCH));
    corner * t
}

/// The skirts of mask `level` as one triangle strip: along each edge of the tile, a
/// vertical band from each kept border sample (index `i`) down to its foot (index
/// `tile_size^2 + i`, which the shader places at the skirt's bottom). Edges are joined by
/// repeated indices, like the mask strips. The strip-mask paper's "filleting" (section 5.4).
pub fn skirt_strip(tile_size: u32, level: u32) -> Vec<u32> {
    skirt_strip_sides(tile_size, [Some(level); 4])
}

/// Skirts along some sides only (north, east, south, west), each hanging from the samples
/// mask `sides[k]` keeps on it (`None`: no skirt on that side), as one triangle strip.
pub fn skirt_strip_sides(tile_size: u32, sides: [Option<u32>; 4]) -> Vec<u32> {
    let n = tile_size;
    let last = n - 1;
    let feet = terrain_shaders::skirt_base(n);
    // Each edge walks its kept samples in order round the tile (north west to east, east
    // north to south, south east to west, west south to north); `kept` is not symmetric,
    // so the last two walk it backwards.
    let forward = |level: u32| mask::kept_indices(tile_size, level);
    let backward = |level: u32| {
        let mut kept = mask::kept_indices(tile_size, level);
        kept.reverse();
        kept
    };
    let edges: Vec<(Vec<u32>, u32, u32)> = [
        sides[0].map(|l| (forward(l), 0, 1)),         // north: k
        sides[1].map(|l| (forward(l), last, n)),      // east: k * n + last
        sides[2].map(|l| (backward(l), last * n, 1)), // south: last * n + k
        sides[3].map(|l| (backward(l), 0, n)),        // west: k * n
    ]
    .into_iter()
    .flatten()
    .collect();
    let mut strip: Vec<u32> = Vec::with_capacity(edges.iter().map(|e| 2 * e.0.len() + 2).sum());
    for (ks, first, step) in &edges {
        let at = |k: u32| first + k * step;
        if let Some(&previous) = strip.last() {
            strip.push(previous);
            strip.push(at(ks[0]));
        }
        for &k in ks {
            let i = at(k);
            strip.push(i);
            strip.push(feet + i);
        }
    }
    strip
}

/// Triangles a skirt strip draws (joins not counted): two per kept border cell, four edges.
pub fn skirt_triangles(tile_size: u32, level: u32) -> u32 {
    skirt_triangles_sides(tile_size, [Some(level); 4])
}

/// Triangles [`skirt_strip_sides`] draws (joins not counted).
pub fn skirt_triangles_sides(tile_size: u32, sides: [Option<u32>; 4]) -> u32 {
    sides
        .iter()
        .flatten()
        .map(|&l| 2 * (mask::kept_indices(tile_size, l).len() as u32 - 1))
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    #[test]
    fn a_shadow_corner_lies_on_the_ray_through_the_corner_and_on_the_plane() {
        let corner = DVec3::new(300.0, -500.0, -800.0);
        let p = shadow_corner(corner, -600.0);
        assert!((p.y + 600.0).abs() < 1e-9, "on the plane: {p:?}");
        assert!(
            p.normalize().dot(corner.normalize()) > 1.0 - 1e-12,
            "on the ray"
        );
        assert!(p.length() > corner.length(), "beyond the corner");
        // Grazing: the stretch is capped, the point stays finite and on the ray.
        let grazing = shadow_corner(DVec3::new(1000.0, -0.001, 0.0), -100.0);
        assert!((grazing.length() / 1000.0 - f64::from(SHADOW_MAX_STRETCH)).abs() < 1e-6);
        // Camera below the plane: laid on the plane under the corner.
        assert_eq!(shadow_corner(corner, 10.0), DVec3::new(300.0, 10.0, -800.0));
    }

    #[test]
    fn skirts_hang_from_every_kept_border_sample_and_only_those() {
        for (n, level) in [(5, 0), (9, 2), (129, 5), (129, 127)] {
            let strip = skirt_strip(n, level);
            let kept = mask::kept_indices(n, level);
            let mut border: Vec<u32> = strip.iter().copied().filter(|&i| i < n * n).collect();
            border.sort_unstable();
            border.dedup();
            let last = n - 1;
            let mut expected: Vec<u32> = Vec::new();
            for &a in &kept {
                for &b in &kept {
                    if a == 0 || a == last || b == 0 || b == last {
                        expected.push(b * n + a);
                    }
                }
            }
            expected.sort_unstable();
            expected.dedup();
            assert_eq!(border, expected, "tile {n} level {level}");
            // Every foot sits under a border sample.
            assert!(
                strip
                    .iter()
                    .all(|&i| i < n * n || expected.contains(&(i - n * n)))
            );
            // Drawn (non-degenerate) triangles: each has two distinct samples and a foot, or
            // two feet and a sample.
            let drawn = strip
                .windows(3)
                .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
                .count() as u32;
            assert_eq!(drawn, skirt_triangles(n, level), "tile {n} level {level}");
        }
    }
}
