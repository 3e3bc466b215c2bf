//! One frame's plan: which resident tiles are in view, their importance, and the mask
//! each draws. Pure: the caller passes the camera, the tiles and the frame's budget.

use crate::lod::budget::{self, Allocation};
use crate::lod::importance::{self, HeightMeasure, TileView};
use crate::lod::needed;
use crate::lod::strips::MaskSet;
use crate::render::camera::Camera;
pub use crate::render::layout::Layout;
use glam::DVec3;
use terrain_shared::TileId;

/// A tile that could be drawn: resident, with its GPU data.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate<'a> {
    pub id: TileId,
    /// Lowest and highest sample, metres (the manifest's).
    pub min_m: f64,
    pub max_m: f64,
    pub roughness_m: f64,
    /// Suffix minima of the maximum vertical error of each mask level against the
    /// full-resolution surface, metres ([`needed::suffix_minima`] of its tile blob's
    /// `mask_errors_m`); `[0]` is the tile's own distance from full resolution (0 at
    /// level 0).
    pub error_minima_m: &'a [f32],
    /// Sides (north, east, south, west) that border a drawn tile of another level of the
    /// pyramid ([`crate::lod::levels::seams`]).
    pub seams: [bool; 4],
}

impl<'a> Candidate<'a> {
    /// The candidate of tile `id`, as the manifest describes it, with its error minima.
    pub fn new(
        id: TileId,
        record: &terrain_shared::TileRecord,
        error_minima_m: &'a [f32],
    ) -> Candidate<'a> {
        Candidate {
            id,
            min_m: f64::from(record.min_m),
            max_m: f64::from(record.max_m),
            roughness_m: f64::from(record.roughness_m),
            error_minima_m,
            seams: [false; 4],
        }
    }
}

/// What one tile draws this frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Draw {
    pub id: TileId,
    /// The level the method draws it at (0 is full resolution).
    pub level: u32,
}

/// How the frame shares its detail.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LodSettings {
    /// Weight of distance in the importance (the paper's alpha); height gets the rest.
    pub alpha: f64,
    pub height: HeightMeasure,
    /// Screen-space error threshold, pixels, of the fewest triangles a frame needs
    /// ([`crate::lod::needed`]) and of the cap below.
    pub max_error_px: f64,
    /// No tile is offered more triangles than the coarsest mask within `max_error_px`
    /// needs: what it would not use goes to the other tiles (model no more than the scene
    /// needs: a flat tile draws its coarsest mask).
    pub cap_at_needed: bool,
    /// Whether methods that can morph between levels do (the quadtree patches).
    pub geomorph: bool,
}

/// Default of [`LodSettings::max_error_px`], pixels.
pub const DEFAULT_MAX_ERROR_PX: f64 = 1.0;

impl Default for LodSettings {
    fn default() -> LodSettings {
        LodSettings {
            alpha: importance::DEFAULT_ALPHA,
            height: HeightMeasure::default(),
            max_error_px: DEFAULT_MAX_ERROR_PX,
            cap_at_needed: true,
            geomorph: true,
        }
    }
}

/// One frame's decisions.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FramePlan {
    /// Visible tiles in decreasing importance, with their masks.
    pub draws: Vec<Draw>,
    /// Importance of each draw, same order.
    pub importances: Vec<f64>,
    /// Global triangle budget this frame was planned with.
    pub budget: u32,
    /// Triangles the chosen masks draw (fillers and strip joins not counted).
    pub triangles: u64,
    /// Per draw, the coarsest level whose projected error is within the threshold.
    pub needed_levels: Vec<u32>,
    /// Triangles of `needed_levels`: the fewest that keep every drawn tile's projected
    /// error within [`LodSettings::max_error_px`].
    pub triangles_needed: u64,
}

impl FramePlan {
    /// Tiles drawn per mask level, finest level first: the CSV's histogram.
    pub fn level_histogram(&self) -> Vec<(u32, u32)> {
        let mut counts = std::collections::BTreeMap::new();
        for d in &self.draws {
            *counts.entry(d.level).or_insert(0u32) += 1;
        }
        counts.into_iter().collect()
    }
}

/// The tiles of `tiles` in `camera`'s view (by bounding box, on a viewport of `aspect`),
/// as indices into `tiles`.
pub fn visible_tiles(
    camera: &Camera,
    aspect: f64,
    layout: &Layout,
    tiles: &[Candidate],
) -> Vec<usize> {
    let frustum = camera.frustum(aspect);
    let eye = DVec3::from(camera.position);
    (0..tiles.len())
        .filter(|&i| {
            let tile = &tiles[i];
            let extent = layout.tile_extent_m_at(tile.id.level);
            let [x0, y0] = layout.tile_origin_m(tile.id);
            let lo = DVec3::new(x0, y0, tile.min_m) - eye;
            let hi = DVec3::new(x0 + extent[0], y0 + extent[1], tile.max_m) - eye;
            let (lo_r, hi_r) = (Camera::to_render(lo), Camera::to_render(hi));
            frustum.intersects_box(lo_r.min(hi_r), lo_r.max(hi_r))
        })
        .collect()
}

/// The error bound of `camera`'s frames on a viewport of `viewport` pixels.
pub fn error_projection(camera: &Camera, viewport: [u32; 2]) -> needed::ErrorProjection {
    needed::ErrorProjection::new(
        camera.position,
        camera.direction().to_array(),
        camera.fov_y,
        viewport,
        camera.near,
    )
}

/// Pixels per metre of vertical error, at most, anywhere `tile` is drawn
/// ([`needed::ErrorProjection::pixels_per_metre`]).
pub fn tile_pixels_per_metre(
    projection: &needed::ErrorProjection,
    layout: &Layout,
    id: TileId,
    height_m: [f64; 2],
    threshold_px: f64,
) -> f64 {
    let extent = layout.tile_extent_m_at(id.level);
    let [x0, y0] = layout.tile_origin_m(id);
    projection.pixels_per_metre(
        [x0, y0, height_m[0]],
        [x0 + extent[0], y0 + extent[1], height_m[1]],
        threshold_px,
    )
}

/// The tiles of a frame in view, with what every method needs of them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Ranked {
    /// Indices into the candidates, in candidate order.
    pub visible: Vec<usize>,
    /// Visual importance of each, summing to 1.
    pub importances: Vec<f64>,
    /// Strip-mask level each needs to stay within the error threshold.
    pub needed_levels: Vec<u32>,
    /// Pixels per metre of vertical error, at most, anywhere each is drawn
    /// ([`tile_pixels_per_metre`]): what any method compares its own level errors with.
    pub pixels_per_metre: Vec<f64>,
}

/// Culls `tiles` against the camera's frustum (by bounding box) on a viewport of
/// `viewport` pixels (width, height), and gives each visible tile its importance and the
/// strip-mask level it needs. Shared by every per-tile method.
pub fn rank_visible(
    camera: &Camera,
    viewport: [u32; 2],
    layout: &Layout,
    tiles: &[Candidate],
    settings: &LodSettings,
) -> Ranked {
    let aspect = f64::from(viewport[0]) / f64::from(viewport[1].max(1));
    let eye = DVec3::from(camera.position);
    let projection = error_projection(camera, viewport);
    let visible = visible_tiles(camera, aspect, layout, tiles);
    let mut views = Vec::with_capacity(visible.len());
    let mut needed_levels = Vec::with_capacity(visible.len());
    let mut pixels_per_metre = Vec::with_capacity(visible.len());
    for &i in &visible {
        let tile = &tiles[i];
        let extent = layout.tile_extent_m_at(tile.id.level);
        let [x0, y0] = layout.tile_origin_m(tile.id);
        let lo = DVec3::new(x0, y0, tile.min_m) - eye;
        let hi = DVec3::new(x0 + extent[0], y0 + extent[1], tile.max_m) - eye;
        let k = tile_pixels_per_metre(
            &projection,
            layout,
            tile.id,
            [tile.min_m, tile.max_m],
            settings.max_error_px,
        );
        needed_levels.push(needed::coarsest_level_within(
            tile.error_minima_m,
            k,
            settings.max_error_px,
        ));
        pixels_per_metre.push(k);
        views.push(TileView {
            distance_m: ((lo + hi) * 0.5).length(),
            bbox_height_m: tile.max_m - tile.min_m,
            roughness_m: tile.roughness_m,
        });
    }
    Ranked {
        importances: importance::importance(&views, settings.alpha, settings.height),
        visible,
        needed_levels,
        pixels_per_metre,
    }
}

/// Culls `tiles` against the camera's frustum (by bounding box), ranks the visible ones by
/// importance ([`rank_visible`]) and shares `budget` triangles among them, on a viewport
/// of `viewport` pixels (width, height).
pub fn plan_frame(
    camera: &Camera,
    viewport: [u32; 2],
    layout: &Layout,
    tiles: &[Candidate],
    budget: u32,
    masks: &MaskSet,
    settings: &LodSettings,
) -> FramePlan {
    let Ranked {
        visible,
        importances,
        needed_levels,
        ..
    } = rank_visible(camera, viewport, layout, tiles, settings);
    let caps: Vec<u32> = if settings.cap_at_needed {
        needed_levels
            .iter()
            .map(|&l| masks.triangle_count(l))
            .collect()
    } else {
        Vec::new()
    };
    let mut allocations: Vec<Allocation> = Vec::with_capacity(visible.len());
    budget::share_into(
        &importances,
        &caps,
        &mut Vec::new(),
        budget,
        masks,
        &mut allocations,
    );
    let mut plan = FramePlan {
        budget,
        ..FramePlan::default()
    };
    for a in allocations {
        plan.draws.push(Draw {
            id: tiles[visible[a.tile]].id,
            level: a.level,
        });
        plan.importances.push(importances[a.tile]);
        plan.triangles += u64::from(a.triangles);
        let needed = needed_levels[a.tile];
        plan.needed_levels.push(needed);
        plan.triangles_needed += u64::from(masks.triangle_count(needed));
    }
    plan
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Per-level errors growing with the level, as on rough terrain.
    static ROUGH: [f32; 16] = [
        0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 5.5, 6.0, 6.5, 7.0, 7.5,
    ];

    fn grid(columns: u32, rows: u32) -> Vec<Candidate<'static>> {
        let mut out = Vec::new();
        for y in 0..rows {
            for x in 0..columns {
                out.push(Candidate {
                    id: TileId::new(x, y),
                    min_m: 0.0,
                    max_m: 100.0,
                    roughness_m: 1.0,
                    error_minima_m: &ROUGH,
                    seams: [false; 4],
                });
            }
        }
        out
    }

    #[test]
    fn tiles_behind_the_camera_are_culled_and_near_tiles_get_finer_masks() {
        let layout = Layout {
            tile_size: 17,
            spacing_m: [10.0, 10.0],
            extent_m: [1280.0, 1280.0],
        };
        // 8x8 tiles of 160 m; camera at the west edge, mid-way south, looking east.
        let camera = Camera::new([-1.0, 640.0, 300.0], 0.0, -0.3);
        let masks = MaskSet::new(17);
        let plan = plan_frame(
            &camera,
            [300, 200],
            &layout,
            &grid(8, 8),
            3000,
            &masks,
            &LodSettings::default(),
        );
        assert!(
            !plan.draws.is_empty() && plan.draws.len() < 64,
            "{}",
            plan.draws.len()
        );
        assert!(plan.triangles <= 3000);
        let sum: f64 = plan.importances.iter().sum();
        assert!((sum - 1.0).abs() < 1e-9);
        // The most important (first) tile is a near one and draws the finest mask of all.
        let first = plan.draws[0];
        assert!(first.id.x <= 1, "{first:?}");
        assert!(plan.draws.iter().all(|d| d.level >= first.level));
        // Camera looking east: nothing is drawn from a column west of it (there is none)
        // and the tile rows far north and south are partly out of the 55-degree view.
        let camera_west = Camera::new([-1.0, 640.0, 300.0], std::f64::consts::PI, -0.3);
        let none = plan_frame(
            &camera_west,
            [300, 200],
            &layout,
            &grid(8, 8),
            3000,
            &masks,
            &LodSettings::default(),
        );
        assert!(
            none.draws.is_empty(),
            "looking away from the terrain draws nothing"
        );
    }

    #[test]
    fn flat_tiles_get_the_coarsest_mask_and_their_triangles_go_to_rough_ones() {
        static FLAT: [f32; 16] = [0.0; 16];
        let layout = Layout {
            tile_size: 17,
            spacing_m: [10.0, 10.0],
            extent_m: [1280.0, 1280.0],
        };
        let masks = MaskSet::new(17);
        let camera = Camera::new([-1.0, 640.0, 300.0], 0.0, -0.3);
        // Every other tile is flat sea.
        let mut tiles = grid(8, 8);
        for t in tiles
            .iter_mut()
            .filter(|t| (t.id.x + t.id.y).is_multiple_of(2))
        {
            t.error_minima_m = &FLAT;
            t.min_m = 0.0;
            t.max_m = 0.0;
        }
        let capped = plan_frame(
            &camera,
            [300, 200],
            &layout,
            &tiles,
            20_000,
            &masks,
            &LodSettings::default(),
        );
        let flat = |id: TileId| (id.x + id.y).is_multiple_of(2);
        assert!(capped.draws.iter().any(|d| flat(d.id)));
        for (d, needed) in capped.draws.iter().zip(&capped.needed_levels) {
            if flat(d.id) {
                assert_eq!(d.level, masks.coarsest_level(), "{d:?}");
                assert_eq!(*needed, masks.coarsest_level());
            }
            // Masks of equal triangle counts are interchangeable: the finer is taken.
            assert!(
                masks.triangle_count(d.level) <= masks.triangle_count(*needed),
                "never more triangles than needed: {d:?}"
            );
        }
        // The budget is more than the frame needs, so the cap, not the budget, binds: the
        // frame draws no more than it needs, leaving budget unused.
        assert!(
            capped.triangles_needed < 20_000,
            "the budget exceeds the need: {}",
            capped.triangles_needed
        );
        assert!(
            capped.triangles <= capped.triangles_needed,
            "{} triangles drawn, {} needed",
            capped.triangles,
            capped.triangles_needed
        );
        let uncapped = plan_frame(
            &camera,
            [300, 200],
            &layout,
            &tiles,
            20_000,
            &masks,
            &LodSettings {
                cap_at_needed: false,
                ..LodSettings::default()
            },
        );
        assert!(
            uncapped
                .draws
                .iter()
                .any(|d| flat(d.id) && d.level < masks.coarsest_level()),
            "without the cap near flat tiles take fine masks"
        );
        assert_eq!(uncapped.triangles_needed, capped.triangles_needed);
    }
}
