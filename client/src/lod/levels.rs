//! Which level of the pyramid draws each part of the terrain this frame.
//!
//! A tile of level `k + 1` covers four of level `k` (those in its grid), drawn from every
//! other sample. Each frame the terrain is cut into resident tiles of mixed levels that
//! cover it without overlap, top-down from the coarsest level used:
//!
//! - a tile out of the view frustum (by its box: its bounds are those of the full-resolution
//!   surface under it) is left out with everything under it;
//! - a resident tile is drawn when its own surface is within the pixel threshold of the
//!   full-resolution surface at its projected distance (its mask-0 error, which the builder
//!   measured against full resolution, times [`crate::lod::needed::ErrorProjection`]'s
//!   pixels per metre), or when one of its children is not resident; otherwise its children
//!   are visited instead. Level 0 is always drawn when reached;
//! - a tile not resident is replaced by whatever of its children is.
//!
//! So each part of the terrain is drawn from the coarsest level its screen-space error
//! allows, and no finer, when that level and the levels above it are resident; else from
//! the finest resident one above. Within a chosen tile the method still picks a strip mask
//! (or a GeoMipMap level) by its budget and its own error table. Pure: no IO, no GPU.

use crate::lod::plan::{self, Layout};
use crate::render::camera::Camera;
use glam::DVec3;
use std::collections::HashSet;
use terrain_shared::{Manifest, TileId};

/// What the choice needs of a resident tile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Held {
    /// Bounds of the full-resolution surface under it, metres.
    pub min_m: f64,
    pub max_m: f64,
    /// Largest vertical distance of its own surface (mask 0) from the full-resolution
    /// surface, metres: its tile blob's first mask error.
    pub deviation_m: f32,
}

/// The tiles that draw this frame, from levels `0..levels_used` of `manifest`, seen by
/// `camera` on a viewport of `viewport` pixels with `threshold_px` the error allowed;
/// `held` gives what is known of a resident tile (`None`: not resident or not to be drawn).
pub fn choose(
    manifest: &Manifest,
    layout: &Layout,
    levels_used: u32,
    camera: &Camera,
    viewport: [u32; 2],
    threshold_px: f64,
    held: impl Fn(TileId) -> Option<Held>,
) -> Vec<TileId> {
    let top = levels_used.clamp(1, manifest.level_count().max(1)) - 1;
    let aspect = f64::from(viewport[0]) / f64::from(viewport[1].max(1));
    let frustum = camera.frustum(aspect);
    let eye = DVec3::from(camera.position);
    let projection = plan::error_projection(camera, viewport);
    let visible = |id: TileId, min_m: f64, max_m: f64| {
        let extent = layout.tile_extent_m_at(id.level);
        let [x0, y0] = layout.tile_origin_m(id);
        let lo = Camera::to_render(DVec3::new(x0, y0, min_m) - eye);
        let hi = Camera::to_render(DVec3::new(x0 + extent[0], y0 + extent[1], max_m) - eye);
        frustum.intersects_box(lo.min(hi), lo.max(hi))
    };
    let grid = manifest.grid(top);
    let mut stack: Vec<TileId> = (0..grid.rows)
        .flat_map(|y| (0..grid.columns).map(move |x| TileId::at(top, x, y)))
        .collect();
    let mut chosen = Vec::new();
    while let Some(id) = stack.pop() {
        let Some(record) = manifest.tile(id) else {
            continue;
        };
        if !visible(id, f64::from(record.min_m), f64::from(record.max_m)) {
            continue;
        }
        let Some(tile) = held(id) else {
            stack.extend(manifest.children(id));
            continue;
        };
        if id.level == 0 {
            chosen.push(id);
            continue;
        }
        let per_metre = plan::tile_pixels_per_metre(
            &projection,
            layout,
            id,
            [tile.min_m, tile.max_m],
            threshold_px,
        );
        let fine_enough = f64::from(tile.deviation_m) * per_metre <= threshold_px;
        let children = manifest.children(id);
        if fine_enough || !children.iter().all(|&c| held(c).is_some()) {
            chosen.push(id);
        } else {
            stack.extend(children);
        }
    }
    chosen
}

/// Per tile of `chosen` (a cut of the pyramid, as [`choose`] makes), which of its sides
/// (north, east, south, west) border a chosen tile of another level: where the two edges
/// are sampled differently and a crack can open whatever the methods' own stitching does
/// (GeoMipMaps stitch tiles of one level only).
pub fn seams(chosen: &[TileId]) -> Vec<[bool; 4]> {
    let drawn: HashSet<TileId> = chosen.iter().copied().collect();
    // Every tile with a chosen tile under it (a finer level draws its area).
    let mut above = HashSet::new();
    for &id in chosen {
        let mut t = id;
        while t.level < 31 {
            t = t.parent();
            if !above.insert(t) {
                break;
            }
        }
    }
    let coarser_drawn = |mut t: TileId| {
        while t.level < 31 {
            t = t.parent();
            if drawn.contains(&t) {
                return true;
            }
        }
        false
    };
    chosen
        .iter()
        .map(|id| {
            [(0i64, -1i64), (1, 0), (0, 1), (-1, 0)].map(|(dx, dy)| {
                let (x, y) = (i64::from(id.x) + dx, i64::from(id.y) + dy);
                let (Ok(x), Ok(y)) = (u32::try_from(x), u32::try_from(y)) else {
                    return false;
                };
                let next = TileId::at(id.level, x, y);
                !drawn.contains(&next) && (above.contains(&next) || coarser_drawn(next))
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seams_are_the_sides_facing_another_level() {
        // Level 1 tile (0, 0) drawn as its four children; its east neighbour (1, 0) whole.
        let chosen = [
            TileId::new(0, 0),
            TileId::new(1, 0),
            TileId::new(0, 1),
            TileId::new(1, 1),
            TileId::at(1, 1, 0),
        ];
        let s = seams(&chosen);
        // North, east, south, west.
        assert_eq!(s[0], [false; 4], "a child inside the block");
        assert_eq!(
            s[1],
            [false, true, false, false],
            "faces the coarser tile east"
        );
        assert_eq!(s[3], [false, true, false, false]);
        assert_eq!(
            s[4],
            [false, false, false, true],
            "faces the finer tiles west"
        );
        // One level: no seams anywhere.
        assert!(seams(&chosen[..4]).iter().all(|s| *s == [false; 4]));
    }
}
