//! One frame's plan: which resident tiles are in view, their importance, and the mask
//! each draws. Pure: the caller passes the camera, the tiles and the frame's budget.

use super::camera::Camera;
use crate::lod::budget::{self, Allocation};
use crate::lod::importance::{self, HeightMeasure, TileView};
use crate::lod::strips::MaskSet;
use glam::DVec3;
use terrain_shared::TileId;

/// A tile that could be drawn: resident, with its GPU data.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    pub id: TileId,
    /// Lowest and highest sample, metres (the manifest's).
    pub min_m: f64,
    pub max_m: f64,
    pub roughness_m: f64,
}

/// The terrain's geometry: enough to place any tile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Layout {
    pub tile_size: u32,
    /// Metres between samples, east and south.
    pub spacing_m: [f64; 2],
}

impl Layout {
    /// Metres a tile spans, east and south.
    pub fn tile_extent_m(&self) -> [f64; 2] {
        let cells = f64::from(self.tile_size - 1);
        [cells * self.spacing_m[0], cells * self.spacing_m[1]]
    }

    /// World position of a tile's sample (0, 0), metres.
    pub fn tile_origin_m(&self, id: TileId) -> [f64; 2] {
        let e = self.tile_extent_m();
        [f64::from(id.x) * e[0], f64::from(id.y) * e[1]]
    }
}

/// What one tile draws this frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Draw {
    pub id: TileId,
    /// Strip-mask level.
    pub level: u32,
}

/// How the frame shares its detail.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LodSettings {
    /// Weight of distance in the importance (the paper's alpha); height gets the rest.
    pub alpha: f64,
    pub height: HeightMeasure,
}

impl Default for LodSettings {
    fn default() -> LodSettings {
        LodSettings {
            alpha: importance::DEFAULT_ALPHA,
            height: HeightMeasure::default(),
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

/// Culls `tiles` against the camera's frustum (by bounding box), ranks the visible ones by
/// importance and shares `budget` triangles among them.
pub fn plan_frame(
    camera: &Camera,
    aspect: f64,
    layout: &Layout,
    tiles: &[Candidate],
    budget: u32,
    masks: &MaskSet,
    settings: &LodSettings,
) -> FramePlan {
    let frustum = camera.frustum(aspect);
    let eye = DVec3::from(camera.position);
    let extent = layout.tile_extent_m();
    let mut visible = Vec::new();
    let mut views = Vec::new();
    for tile in tiles {
        let [x0, y0] = layout.tile_origin_m(tile.id);
        let lo = DVec3::new(x0, y0, tile.min_m) - eye;
        let hi = DVec3::new(x0 + extent[0], y0 + extent[1], tile.max_m) - eye;
        let (lo_r, hi_r) = (Camera::to_render(lo), Camera::to_render(hi));
        if !frustum.intersects_box(lo_r.min(hi_r), lo_r.max(hi_r)) {
            continue;
        }
        visible.push(tile.id);
        views.push(TileView {
            distance_m: ((lo + hi) * 0.5).length(),
            bbox_height_m: tile.max_m - tile.min_m,
            roughness_m: tile.roughness_m,
        });
    }
    let importances = importance::importance(&views, settings.alpha, settings.height);
    let allocations: Vec<Allocation> = budget::share(&importances, &mut Vec::new(), budget, masks);
    let mut plan = FramePlan {
        budget,
        ..FramePlan::default()
    };
    for a in allocations {
        plan.draws.push(Draw {
            id: visible[a.tile],
            level: a.level,
        });
        plan.importances.push(importances[a.tile]);
        plan.triangles += u64::from(a.triangles);
    }
    plan
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(columns: u32, rows: u32) -> Vec<Candidate> {
        let mut out = Vec::new();
        for y in 0..rows {
            for x in 0..columns {
                out.push(Candidate {
                    id: TileId::new(x, y),
                    min_m: 0.0,
                    max_m: 100.0,
                    roughness_m: 1.0,
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
        };
        // 8x8 tiles of 160 m; camera at the west edge, mid-way south, looking east.
        let camera = Camera::new([-1.0, 640.0, 300.0], 0.0, -0.3);
        let masks = MaskSet::new(17);
        let plan = plan_frame(
            &camera,
            1.5,
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
            1.5,
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
}
