//! The crack fillers of the strip-mask method (the strip-mask paper's section 5.4): skirts
//! (a vertical band down from every kept border sample), the paper's planar shadow (a
//! textured quad under each tile, its corners projected from the viewpoint onto a plane
//! below it) and our default, the planar shadow cut to the bands where cracks can open
//! ([`band_strip`]). Their geometry is drawn through the tile pipeline: the shader places the
//! indices past a tile's samples (`terrain_shaders::skirt_base`,
//! `terrain_shaders::shadow_base`, `terrain_shaders::band_base`).

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
    /// The planar shadow only where a crack can open: a band along each side whose
    /// neighbour draws it through other samples, from the side down to the crack's bottom,
    /// pushed back in depth towards the plane there (at most a pixel's footprint).
    #[default]
    PlanarShadow,
    /// The paper's planar shadow: a textured quad under each tile, its corners projected
    /// onto a plane a tenth of a tile's side below the tile. It also shows past the
    /// terrain's border, and through a crack it shows a point far below the surface.
    PlanarShadowPaper,
    /// Not a filler: skirts deep under every side that has a drawn neighbour, drawn by the
    /// evaluation to find the pixels a crack opens ([`crate::eval::frame::measure`]). A
    /// side whose neighbour draws the same edge hides its skirt under the neighbour's
    /// surface, so the skirts show exactly through the cracks (their tops reach a
    /// thirty-second of a pixel above the side, twice the planar shadow's sliver, so that
    /// a pixel the shadow's sliver covers counts as the crack's).
    #[value(skip)]
    CrackProbe,
}

impl CrackFiller {
    pub fn name(self) -> &'static str {
        match self {
            CrackFiller::None => "none",
            CrackFiller::Skirts => "skirts",
            CrackFiller::PlanarShadow => "planar-shadow",
            CrackFiller::PlanarShadowPaper => "planar-shadow-paper",
            CrackFiller::CrackProbe => "crack-probe",
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

/// Sample (column, row) at position `k` along side `side` (north, east, south, west) of a
/// tile of `tile_size` samples a side, counted west to east or north to south: the order
/// of `terrain_shaders::band_base`'s indices.
pub fn side_sample(tile_size: u32, side: usize, k: u32) -> (u32, u32) {
    let last = tile_size - 1;
    match side {
        0 => (k, 0),
        1 => (last, k),
        2 => (k, last),
        _ => (0, k),
    }
}

/// What a tile's side faces where a crack can open, for the planar shadow's band along it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Across {
    /// A tile of the same pyramid level drawn at mask `0`: the two tiles draw the side as
    /// polylines through the shared samples their masks keep, and the crack lies between.
    Mask(u32),
    /// Tiles of another pyramid level (a seam), sampled on another grid.
    Seam,
}

/// Positions along a side (0..`tile_size`) where the band of a tile drawn at mask `level`
/// has vertices: the samples either polyline bends at (its own mask's and, across a mask
/// change, the neighbour's), or its own mask's across a seam.
pub fn band_samples(tile_size: u32, level: u32, across: Across) -> Vec<u32> {
    let mut kept = mask::kept_indices(tile_size, level);
    if let Across::Mask(theirs) = across {
        kept.extend(mask::kept_indices(tile_size, theirs));
        kept.sort_unstable();
        kept.dedup();
    }
    kept
}

/// Whether a side drawn at masks `level` and `neighbour` (tiles of one level) can open a
/// crack: whether the two keep different samples along it.
pub fn masks_differ(tile_size: u32, level: u32, neighbour: u32) -> bool {
    mask::kept_indices(tile_size, level) != mask::kept_indices(tile_size, neighbour)
}

/// The planar shadow's bands of a tile drawn at mask `level` along the sides that face
/// `sides[s]` (north, east, south, west; `None`: no band), as one triangle strip. A band
/// hangs only from a side whose neighbour draws it through other samples (another mask, or
/// another level of the pyramid): not from the terrain's border, nor from a side drawn the
/// same on both sides. On screen it covers what a skirt down to the crack's bottom would
/// (and a sliver of a pixel more, which closes the T-junctions between the polylines'
/// bends), so it fills the crack, but in depth it lies behind the side, pushed back
/// towards the plane at the crack's bottom (at most a pixel's footprint), behind the
/// surfaces in front. Along each side, a quad between consecutive [`band_samples`] `k`,
/// each the polyline's point at sample `k` (index `band_base + s * n + k`) and its foot on
/// the plane (`band_base + 4n + s * n + k`, `n` = `tile_size`). The shader places both
/// (`terrain.wgsl`, `shadow_band`). Sides are joined by repeated indices.
pub fn band_strip(tile_size: u32, level: u32, sides: [Option<Across>; 4]) -> Vec<u32> {
    let n = tile_size;
    let base = terrain_shaders::band_base(n);
    let mut strip: Vec<u32> = Vec::new();
    for (side, across) in sides.iter().enumerate() {
        let Some(across) = *across else { continue };
        let top = |k: u32| base + side as u32 * n + k;
        let foot = |k: u32| base + 4 * n + side as u32 * n + k;
        let samples = band_samples(n, level, across);
        if let Some(&previous) = strip.last() {
            strip.push(previous);
            strip.push(top(samples[0]));
        }
        for &k in &samples {
            strip.push(top(k));
            strip.push(foot(k));
        }
    }
    strip
}

/// Triangles [`band_strip`] draws (joins not counted): two per pair of consecutive band
/// samples and side.
pub fn band_triangles(tile_size: u32, level: u32, sides: [Option<Across>; 4]) -> u32 {
    sides
        .iter()
        .flatten()
        .map(|&across| 2 * (band_samples(tile_size, level, across).len() as u32 - 1))
        .sum()
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
    fn bands_run_along_the_sides_asked_for_and_cover_each_once() {
        let n = 17;
        let base = terrain_shaders::band_base(n);
        for (level, sides) in [
            (0, [Some(Across::Mask(3)), None, None, None]),
            (3, [None, Some(Across::Mask(0)), Some(Across::Seam), None]),
            (2, [Some(Across::Mask(4)); 4]),
            (5, [None, None, None, Some(Across::Seam)]),
        ] {
            let strip = band_strip(n, level, sides);
            for (side, across) in sides.iter().enumerate() {
                let s = side as u32;
                // The tops and feet of this side, as positions along it.
                let tops: Vec<u32> = strip
                    .iter()
                    .filter(|&&i| i >= base + s * n && i < base + (s + 1) * n)
                    .map(|&i| i - base - s * n)
                    .collect();
                let feet: Vec<u32> = strip
                    .iter()
                    .filter(|&&i| i >= base + (4 + s) * n && i < base + (5 + s) * n)
                    .map(|&i| i - base - (4 + s) * n)
                    .collect();
                let mut unique = tops.clone();
                unique.sort_unstable();
                unique.dedup();
                match across {
                    None => assert!(tops.is_empty() && feet.is_empty(), "side {side}"),
                    Some(across) => {
                        // Every sample either polyline bends at.
                        let mut expected = mask::kept_indices(n, level);
                        if let Across::Mask(theirs) = across {
                            expected.extend(mask::kept_indices(n, *theirs));
                        }
                        expected.sort_unstable();
                        expected.dedup();
                        assert_eq!(unique, expected, "level {level} side {side}");
                        let mut unique_feet = feet.clone();
                        unique_feet.dedup();
                        assert_eq!(unique_feet, expected, "level {level} side {side}");
                    }
                }
            }
            assert!(strip.iter().all(|&i| i >= base && i < base + 8 * n));
            // With a top at height 1 and a foot at 0 over position k, the triangles of each
            // side tile the rectangle 0..n-1 by 0..1: their areas add up to n - 1.
            let place = |i: u32| {
                let e = i - base;
                (
                    (e % (4 * n)) / n,
                    f64::from(e % n),
                    f64::from(u8::from(e < 4 * n)),
                )
            };
            for (side, across) in sides.iter().enumerate() {
                let area: f64 = strip
                    .windows(3)
                    .map(|t| t.iter().map(|&i| place(i)).collect::<Vec<_>>())
                    .filter(|t| t.iter().all(|v| v.0 == side as u32))
                    .map(|t| {
                        ((t[1].1 - t[0].1) * (t[2].2 - t[0].2)
                            - (t[2].1 - t[0].1) * (t[1].2 - t[0].2))
                            .abs()
                            / 2.0
                    })
                    .sum();
                let expected = if across.is_some() {
                    f64::from(n - 1)
                } else {
                    0.0
                };
                assert_eq!(area, expected, "level {level} side {side}");
            }
            let drawn = strip
                .windows(3)
                .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
                .count() as u32;
            assert_eq!(drawn, band_triangles(n, level, sides), "level {level}");
        }
        assert!(band_strip(n, 0, [None; 4]).is_empty());
    }

    #[test]
    fn masks_differ_unless_they_keep_the_same_border_samples() {
        assert!(!masks_differ(17, 3, 3));
        assert!(masks_differ(17, 0, 1));
        // A 6-sample side: levels 2 and 3 keep [0, 3, 5] and [0, 4, 5].
        assert!(masks_differ(6, 2, 3));
        // Past the last level every mask keeps the two corners only.
        assert!(!masks_differ(6, 4, 9));
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
