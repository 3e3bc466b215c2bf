//! GeoMipMaps (Brodersen 2005) as a method: per visible tile the coarsest level whose
//! error, projected by the frame's bound, stays within `--max-error-px`, each side stitched
//! to its neighbour's level ([`crate::lod::geomipmap`]): crack-free, no budget, no filler.
//! Tiles are bound block by block with MapBlock textures, as the paper draws them
//! ([`super::MethodConfig::uses_texture_blocks`]).

use super::{Build, LodMethod, MethodBytes, MethodConfig, MethodInput, MethodKind, MethodOutput};
use crate::lod::geomipmap::{self as levels, Stitch};
use crate::lod::needed;
use crate::lod::plan::{self, LodSettings};
use crate::lod::strips::MaskSet;
use crate::render::{Frame, Gpu, IndexSet, TileExtras};
use std::collections::HashMap;
use std::time::Instant;
use terrain_shared::{Heights, TileId, TileRecord};

/// The GeoMipMaps method. See the module documentation.
#[derive(Debug)]
pub struct GeoMipMaps {
    lod: LodSettings,
    /// The strip masks' triangle counts: the common yardstick of triangles needed.
    masks: MaskSet,
    /// Per resident tile, the suffix minima of its levels' errors, computed from its
    /// heights when it arrives.
    error_minima: HashMap<TileId, Vec<f32>>,
    /// Index sets drawn lately, shared by every tile, with the frame each was last drawn
    /// in: a set unused for [`super::strip_masks::KEEP_UNUSED_FRAMES`] frames is dropped.
    index_sets: HashMap<Stitch, (IndexSet, u64)>,
    frame: u64,
}

impl GeoMipMaps {
    pub fn new(config: &MethodConfig, with: &Build<'_>) -> GeoMipMaps {
        GeoMipMaps {
            lod: config.lod,
            masks: MaskSet::new(with.manifest.tile_size),
            error_minima: HashMap::new(),
            index_sets: HashMap::new(),
            frame: 0,
        }
    }
}

impl LodMethod for GeoMipMaps {
    fn name(&self) -> String {
        MethodKind::Geomipmap.name().to_string()
    }

    fn configure(&mut self, config: &MethodConfig) {
        // Crack-free by construction: no filler.
        self.lod = config.lod;
    }

    fn draw(&mut self, input: &MethodInput<'_>, frame: &mut Frame<'_>) -> MethodOutput {
        let started = Instant::now();
        // Culling, importances (they rank the textures) and the strip-mask levels needed
        // (the common yardstick of triangles needed); no budget plays a part.
        let ranked = plan::rank_visible(
            frame.camera(),
            frame.viewport(),
            input.layout,
            input.tiles,
            &self.lod,
        );
        // The error bound per visible tile, as the planner computed it for the strip masks'
        // needed levels, compared with this method's own level errors.
        let threshold = self.lod.max_error_px;
        let mut chosen = HashMap::with_capacity(ranked.visible.len());
        for (&i, &k) in ranked.visible.iter().zip(&ranked.pixels_per_metre) {
            let tile = &input.tiles[i];
            let level = self.error_minima.get(&tile.id).map_or(0, |minima| {
                needed::coarsest_level_within(minima, k, threshold)
            });
            chosen.insert(tile.id, level);
        }
        let n = input.layout.tile_size;
        let mut plan = plan::FramePlan {
            budget: input.budget,
            triangles_needed: ranked
                .needed_levels
                .iter()
                .map(|&l| u64::from(self.masks.triangle_count(l)))
                .sum(),
            needed_levels: ranked.needed_levels,
            ..plan::FramePlan::default()
        };
        let gpu = frame.gpu().clone();
        self.frame += 1;
        let now = self.frame;
        self.index_sets
            .retain(|_, (_, used)| now - *used <= super::strip_masks::KEEP_UNUSED_FRAMES);
        let mut stitches = Vec::with_capacity(ranked.visible.len());
        for (&i, &importance) in ranked.visible.iter().zip(&ranked.importances) {
            let id = input.tiles[i].id;
            let level = chosen[&id];
            let near = |dx: i64, dy: i64| {
                let (x, y) = (i64::from(id.x) + dx, i64::from(id.y) + dy);
                (x >= 0 && y >= 0)
                    .then(|| chosen.get(&TileId::new(x as u32, y as u32)).copied())
                    .flatten()
            };
            let stitch = Stitch::new(level, [near(0, -1), near(1, 0), near(0, 1), near(-1, 0)]);
            let (set, used) = self.index_sets.entry(stitch).or_insert_with(|| {
                let set = IndexSet::new(
                    &gpu,
                    &levels::strip(n, stitch),
                    levels::triangles(n, stitch).len() as u32,
                );
                (set, now)
            });
            *used = now;
            plan.draws.push(plan::Draw { id, level });
            plan.importances.push(importance);
            plan.triangles += u64::from(set.triangles);
            stitches.push(stitch);
        }
        let lod_ms = started.elapsed().as_secs_f64() * 1e3;

        let tiles: Vec<(TileId, TileExtras)> = plan
            .draws
            .iter()
            .map(|d| (d.id, TileExtras::default()))
            .collect();
        let slots = frame.prepare_tiles(&tiles);
        let mut stitch_of = vec![None; tiles.len()];
        for (stitch, slot) in stitches.iter().zip(&slots) {
            if let Some(slot) = *slot {
                stitch_of[slot] = Some(*stitch);
            }
        }
        let order = frame.draw_order();
        let mut pass = frame.last_pass();
        for slot in order {
            let Some(stitch) = stitch_of[slot] else {
                continue;
            };
            let set = &self.index_sets[&stitch].0;
            pass.bind_tile(slot);
            pass.draw(set);
            pass.stats_mut().triangles += u64::from(set.triangles);
        }
        drop(pass);
        MethodOutput::of_plan(plan, lod_ms)
    }

    fn tile_resident(&mut self, _gpu: &Gpu, id: TileId, heights: &Heights) {
        let samples = heights.to_metres_f32();
        let errors = levels::level_errors(&samples, u32::from(heights.width));
        self.error_minima.insert(id, needed::suffix_minima(&errors));
    }

    fn tile_evicted(&mut self, id: TileId) {
        self.error_minima.remove(&id);
    }

    fn tile_bytes(&self, id: TileId) -> u64 {
        self.error_minima.get(&id).map_or(0, |m| 4 * m.len() as u64)
    }

    fn expected_tile_bytes(&self, _tile: &TileRecord) -> u64 {
        4 * u64::from(levels::level_count(self.masks.tile_size()))
    }

    fn shared_bytes(&self) -> MethodBytes {
        MethodBytes {
            cpu: self.masks.bytes(),
            gpu: self.index_sets.values().map(|(set, _)| set.bytes()).sum(),
        }
    }
}
