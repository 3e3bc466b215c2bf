//! GeoMipMaps (Brodersen 2005) as a method: each tile is cut into GeoMipMaps of 9x9
//! samples ([`blocks`]), and each visible one is drawn at the coarsest level whose error,
//! projected by the frame's bound at its own box, stays within `--max-error-px`, each side
//! stitched to its neighbour's level ([`stitching`]): crack-free, no budget, no filler.
//! Tiles are bound MapBlock by MapBlock with their textures, as the paper draws them
//! ([`super::MethodConfig::uses_texture_blocks`]).
//!
//! Levels of the pyramid: a tile of a coarser level is one more GeoMipMap, its level errors
//! raised by its own distance from full resolution. Stitching joins tiles of one level; a
//! side that borders a tile of another level (a seam, [`crate::lod::levels::seams`]) hangs a
//! skirt from its edge samples instead, down past the cracks the two edges can leave.

pub mod blocks;
pub mod stitching;

use self::blocks::{BlockErrors, Blocks};
use self::stitching::{self as levels, Stitch};
use super::{Build, LodMethod, MethodBytes, MethodConfig, MethodInput, MethodKind, MethodOutput};
use crate::lod::needed;
use crate::lod::plan::{self, Candidate, Layout, LodSettings};
use crate::lod::strips::MaskSet;
use crate::render::{Camera, Frame, Gpu, IndexSet, TileExtras};
use glam::DVec3;
use std::collections::HashMap;
use terrain_shared::{Heights, TileId, TileRecord};
use web_time::Instant;

/// What an index set of [`GeoMipMaps`] draws.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
enum SetKey {
    /// A tile stitched to its neighbours' levels.
    Stitch(Stitch),
    /// A skirt along one side (0 north, 1 east, 2 south, 3 west) hanging from the samples
    /// that side is stitched at (a GeoMipMap level).
    Skirt { side: u8, level: u32 },
}

impl SetKey {
    /// The set's strip for a block of `blocks`, numbered as the tile's north-west block
    /// ([`Blocks::to_tile`]), and the triangles it draws.
    fn indices(self, blocks: Blocks) -> (Vec<u32>, u32) {
        let (local, triangles) = self.block_indices(blocks.size());
        (
            local.into_iter().map(|i| blocks.to_tile(i)).collect(),
            triangles,
        )
    }

    /// The set's strip on a block of `n` samples a side, numbered within the block.
    fn block_indices(self, n: u32) -> (Vec<u32>, u32) {
        match self {
            SetKey::Stitch(stitch) => (
                levels::strip(n, stitch),
                levels::triangles(n, stitch).len() as u32,
            ),
            SetKey::Skirt { side, level } => {
                // A side stitched at level j keeps every 2^j-th sample: mask level 2^j - 1.
                let sides: [Option<u32>; 4] =
                    std::array::from_fn(|k| (k == usize::from(side)).then(|| (1u32 << level) - 1));
                (
                    super::fillers::skirt_strip_sides(n, sides),
                    super::fillers::skirt_triangles_sides(n, sides),
                )
            }
        }
    }
}

/// The sets a tile with `stitch` draws: its stitch, then a skirt along each side marked in
/// `skirts` (north, east, south, west) at the level that side is stitched at.
fn sets_of(stitch: Stitch, skirts: [bool; 4]) -> impl Iterator<Item = SetKey> {
    std::iter::once(SetKey::Stitch(stitch)).chain((0..4u8).filter_map(move |side| {
        skirts[usize::from(side)].then_some(SetKey::Skirt {
            side,
            level: stitch.sides[usize::from(side)],
        })
    }))
}

/// The GeoMipMaps method. See the module documentation.
#[derive(Debug)]
pub struct GeoMipMaps {
    lod: LodSettings,
    /// The strip masks' triangle counts: the common yardstick of triangles needed.
    masks: MaskSet,
    /// How a tile is cut into GeoMipMaps.
    blocks: Blocks,
    /// Per resident tile, its blocks' level errors and heights, computed from its heights
    /// when it arrives.
    block_errors: HashMap<TileId, BlockErrors>,
    /// Index sets drawn lately, shared by every tile, with the frame each was last drawn
    /// in: a set unused for [`super::strip_masks::KEEP_UNUSED_FRAMES`] frames is dropped.
    /// A skirt is a set of its own (one side at one level), drawn after the tile's stitch,
    /// so seams add at most 4 x levels small sets rather than multiplying the stitches.
    index_sets: HashMap<SetKey, (IndexSet, u64)>,
    frame: u64,
    /// GPU bytes of the coarsest level's unstitched set: what [`LodMethod::reserved_bytes`]
    /// keeps room for besides the tables.
    coarsest_set_bytes: u64,
}

impl GeoMipMaps {
    pub fn new(config: &MethodConfig, with: &Build<'_>) -> GeoMipMaps {
        let n = with.manifest.tile_size;
        let blocks = Blocks::new(n);
        let coarsest = blocks.levels() - 1;
        let (indices, _) = SetKey::Stitch(Stitch::new(coarsest, [None; 4])).indices(blocks);
        let coarsest_set_bytes = 4 * (indices.len() as u64).max(1);
        GeoMipMaps {
            lod: config.lod,
            masks: MaskSet::new(n),
            blocks,
            block_errors: HashMap::new(),
            index_sets: HashMap::new(),
            frame: 0,
            coarsest_set_bytes,
        }
    }
}

impl GeoMipMaps {
    /// Whether set `key` is held, or can be made within `room` (taking its bytes out of it),
    /// dropping sets no frame drew lately to make room if need be.
    fn affordable(&mut self, key: SetKey, room: &mut u64) -> bool {
        if self.index_sets.contains_key(&key) {
            return true;
        }
        let (indices, _) = key.indices(self.blocks);
        let bytes = 4 * (indices.len() as u64).max(1);
        if *room < bytes {
            *room += self.trim(bytes - *room);
        }
        if *room < bytes {
            return false;
        }
        *room -= bytes;
        true
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
        let blocks = self.blocks;
        let chosen = choose_levels(
            frame.camera(),
            frame.viewport(),
            input.layout,
            input.tiles,
            &ranked.visible,
            &self.block_errors,
            blocks,
            self.lod.max_error_px,
        );
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
        let mut sets_of_tile: Vec<Vec<(SetKey, u32)>> = Vec::with_capacity(ranked.visible.len());
        let coarsest = blocks.levels() - 1;
        let reserved = SetKey::Stitch(Stitch::new(coarsest, [None; 4]));
        let mut room = input.room;
        let mut degraded = 0;
        let mut extras = Vec::with_capacity(ranked.visible.len());
        let last = blocks.per_side - 1;
        for (&i, &importance) in ranked.visible.iter().zip(&ranked.importances) {
            let tile = &input.tiles[i];
            let id = tile.id;
            let Some(levels_of) = chosen.get(&id) else {
                continue;
            };
            // Block (bx, by)'s level, blocks of the tiles around counted on: `None` where
            // nothing is drawn.
            let level_at = |bx: i64, by: i64| -> Option<u32> {
                let per = i64::from(blocks.per_side);
                let (tx, ty) = (
                    i64::from(id.x) + bx.div_euclid(per),
                    i64::from(id.y) + by.div_euclid(per),
                );
                if tx < 0 || ty < 0 {
                    return None;
                }
                let levels = chosen.get(&TileId::at(id.level, tx as u32, ty as u32))?;
                levels[(by.rem_euclid(per) * per + bx.rem_euclid(per)) as usize]
            };
            let mut keys = Vec::new();
            let mut finest = coarsest;
            for (b, level) in levels_of.iter().enumerate() {
                let Some(level) = *level else {
                    continue;
                };
                let (bx, by) = blocks.at(b);
                let (x, y) = (i64::from(bx), i64::from(by));
                let stitch = Stitch::new(
                    level,
                    [
                        level_at(x, y - 1),
                        level_at(x + 1, y),
                        level_at(x, y + 1),
                        level_at(x - 1, y),
                    ],
                );
                // A side on the tile's edge that borders another level of the pyramid
                // hangs a skirt.
                let on_edge = [by == 0, bx == last, by == last, bx == 0];
                let skirts: [bool; 4] = std::array::from_fn(|k| tile.seams[k] && on_edge[k]);
                let base = blocks.base_vertex(bx, by);
                // Each set the block needs, made if the limit has room for it; without
                // room, the unstitched set of its level (cracks may show along the stitched
                // sides), else the coarsest level's, which the reservation holds; a skirt
                // without room is left out.
                for key in sets_of(stitch, skirts) {
                    let usable = match key {
                        SetKey::Stitch(_) => {
                            [key, SetKey::Stitch(Stitch::new(level, [None; 4])), reserved]
                                .into_iter()
                                .find(|&k| k == reserved || self.affordable(k, &mut room))
                        }
                        SetKey::Skirt { .. } => {
                            Some(key).filter(|&k| self.affordable(k, &mut room))
                        }
                    };
                    let Some(key) = usable else {
                        degraded += 1;
                        continue;
                    };
                    if let SetKey::Stitch(s) = key {
                        degraded += u32::from(s != stitch);
                        finest = finest.min(s.level);
                    }
                    let (set, used) = self.index_sets.entry(key).or_insert_with(|| {
                        let (indices, triangles) = key.indices(blocks);
                        (IndexSet::new(&gpu, &indices, triangles), now)
                    });
                    *used = now;
                    plan.triangles += u64::from(set.triangles);
                    keys.push((key, base));
                }
            }
            if keys.is_empty() {
                continue;
            }
            plan.draws.push(plan::Draw { id, level: finest });
            plan.importances.push(importance);
            sets_of_tile.push(keys);
            extras.push(TileExtras {
                floor_m: (tile.min_m - skirt_depth_m(input.layout, tile)) as f32,
                ..TileExtras::default()
            });
        }
        let lod_ms = started.elapsed().as_secs_f64() * 1e3;

        let tiles: Vec<(TileId, TileExtras)> = plan
            .draws
            .iter()
            .zip(extras)
            .map(|(d, extras)| (d.id, extras))
            .collect();
        let slots = frame.prepare_tiles(&tiles);
        let mut keys_of: Vec<&[(SetKey, u32)]> = vec![&[]; tiles.len()];
        for (keys, slot) in sets_of_tile.iter().zip(&slots) {
            if let Some(slot) = *slot {
                keys_of[slot] = keys;
            }
        }
        let order = frame.draw_order();
        let mut pass = frame.last_pass();
        for slot in order {
            if keys_of[slot].is_empty() {
                continue;
            }
            pass.bind_tile(slot);
            for (key, base) in keys_of[slot] {
                let set = &self.index_sets[key].0;
                pass.draw_from(set, *base as i32);
                pass.stats_mut().triangles += u64::from(set.triangles);
            }
        }
        pass.stats_mut().degraded_draws += degraded;
        drop(pass);
        MethodOutput::of_plan(plan, lod_ms)
    }

    fn tile_resident(&mut self, _gpu: &Gpu, id: TileId, heights: &Heights) {
        let samples = heights.to_metres_f32();
        self.block_errors
            .insert(id, BlockErrors::new(&samples, self.blocks));
    }

    fn tile_evicted(&mut self, id: TileId) {
        self.block_errors.remove(&id);
    }

    fn tile_bytes(&self, id: TileId) -> u64 {
        self.block_errors.get(&id).map_or(0, BlockErrors::bytes)
    }

    fn expected_tile_bytes(&self, _tile: &TileRecord) -> u64 {
        BlockErrors::bytes_for(self.blocks.count(), self.blocks.levels() as usize)
    }

    fn shared_bytes(&self) -> MethodBytes {
        MethodBytes {
            cpu: self.masks.bytes(),
            gpu: self.index_sets.values().map(|(set, _)| set.bytes()).sum(),
        }
    }

    /// The coarsest level's unstitched set, with which every tile can be drawn; the others
    /// are made as frames need them, when the limit has room.
    fn reserved_bytes(&self, _viewport: [u32; 2]) -> u64 {
        self.masks.bytes() + self.coarsest_set_bytes
    }

    /// Sets the last frame did not draw (nor this one, while it draws), least recently
    /// drawn first.
    fn trim(&mut self, bytes: u64) -> u64 {
        let now = self.frame;
        let mut stale: Vec<(u64, SetKey)> = self
            .index_sets
            .iter()
            .filter(|(_, (_, last))| *last < now)
            .map(|(key, (_, last))| (*last, *key))
            .collect();
        stale.sort_by_key(|(last, _)| *last);
        let mut freed = 0;
        for (_, key) in stale {
            if freed >= bytes {
                break;
            }
            freed += self
                .index_sets
                .remove(&key)
                .map_or(0, |(set, _)| set.bytes());
        }
        freed
    }
}

/// How far skirts reach below a tile's lowest point: a tenth of a level-0 tile and twice
/// the tile's own distance from full resolution. The two edges of a seam lie within their
/// tiles' errors of the true surface, which is above that point.
fn skirt_depth_m(layout: &Layout, tile: &Candidate<'_>) -> f64 {
    super::fillers::filler_depth_m(layout.tile_extent_m())
        + 2.0 * f64::from(tile.error_minima_m.first().copied().unwrap_or(0.0))
}

/// Per tile of `visible` (indices into `tiles`), the level of each of its blocks, `None`
/// for a block outside the view: the coarsest level whose error, raised by the tile's own
/// distance from full resolution, projects within `threshold_px` anywhere in the block's
/// box. A tile whose heights have not been measured yet draws every block at level 0.
#[allow(clippy::too_many_arguments)]
fn choose_levels(
    camera: &Camera,
    viewport: [u32; 2],
    layout: &Layout,
    tiles: &[Candidate<'_>],
    visible: &[usize],
    errors: &HashMap<TileId, BlockErrors>,
    blocks: Blocks,
    threshold_px: f64,
) -> HashMap<TileId, Vec<Option<u32>>> {
    let projection = plan::error_projection(camera, viewport);
    let frustum = camera.frustum(f64::from(viewport[0]) / f64::from(viewport[1].max(1)));
    let eye = DVec3::from(camera.position);
    let mut chosen = HashMap::with_capacity(visible.len());
    for &i in visible {
        let tile = &tiles[i];
        // A coarser level of the pyramid is that far from full resolution already.
        let deviation = tile.error_minima_m.first().copied().unwrap_or(0.0);
        let [x0, y0] = layout.tile_origin_m(tile.id);
        let extent = layout.tile_extent_m_at(tile.id.level);
        let side = [
            extent[0] / f64::from(blocks.per_side),
            extent[1] / f64::from(blocks.per_side),
        ];
        let measured = errors.get(&tile.id);
        // Skirts hang below the blocks on a seam: cull those with their skirt.
        let floor = tile.min_m - skirt_depth_m(layout, tile);
        let levels = (0..blocks.count())
            .map(|b| {
                let (bx, by) = blocks.at(b);
                let [lo, hi] =
                    measured.map_or([tile.min_m, tile.max_m], |m| m.range_m(b).map(f64::from));
                let min = [
                    x0 + f64::from(bx) * side[0],
                    y0 + f64::from(by) * side[1],
                    lo,
                ];
                let max = [min[0] + side[0], min[1] + side[1], hi];
                let bottom = if tile.seams.iter().any(|&s| s) {
                    floor.min(lo)
                } else {
                    lo
                };
                let (a, b_) = (
                    Camera::to_render(DVec3::new(min[0], min[1], bottom) - eye),
                    Camera::to_render(DVec3::from(max) - eye),
                );
                if !frustum.intersects_box(a.min(b_), a.max(b_)) {
                    return None;
                }
                let k = projection.pixels_per_metre(min, max, threshold_px);
                Some(measured.map_or(0, |m| {
                    needed::coarsest_level_within_raised(m.minima(b), deviation, k, threshold_px)
                }))
            })
            .collect();
        chosen.insert(tile.id, levels);
    }
    chosen
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flat_block_is_drawn_at_its_coarsest_level_beside_a_rough_one() {
        // A 17x17 tile of four blocks, flat but for a ridge across block (1, 1).
        let n = 17;
        let blocks = Blocks::new(n);
        let mut samples = vec![100.0f32; (n * n) as usize];
        for y in 9..17 {
            samples[(y * n + 12) as usize] = 130.0;
        }
        let errors = BlockErrors::new(&samples, blocks);
        // At 0.01 px a metre the ridge's 30 m project to 0.3 px: every block at its
        // coarsest level. At 1 px a metre only the ridge's block needs full resolution.
        let levels = |k: f64, deviation: f32| -> Vec<u32> {
            (0..blocks.count())
                .map(|b| needed::coarsest_level_within_raised(errors.minima(b), deviation, k, 1.0))
                .collect()
        };
        let coarsest = blocks.levels() - 1;
        assert_eq!(levels(0.01, 0.0), [coarsest; 4]);
        assert_eq!(levels(1.0, 0.0), [coarsest, coarsest, coarsest, 0]);
        // A tile already far from full resolution is held to its own deviation too.
        assert_eq!(levels(1.0, 2.0), [0; 4]);
    }

    #[test]
    fn a_seam_adds_a_skirt_along_its_side_only_at_the_level_it_is_stitched_at() {
        let n = 17;
        let stitch = Stitch::new(2, [Some(2), Some(1), None, Some(2)]);
        assert_eq!(
            sets_of(stitch, [false; 4]).collect::<Vec<_>>(),
            [SetKey::Stitch(stitch)]
        );
        let sets: Vec<SetKey> = sets_of(stitch, [false, true, false, false]).collect();
        assert_eq!(
            sets,
            [SetKey::Stitch(stitch), SetKey::Skirt { side: 1, level: 1 }]
        );
        let (plain, _) = sets[0].block_indices(n);
        assert_eq!(plain, levels::strip(n, stitch));
        let (skirt, triangles) = sets[1].block_indices(n);
        // The east side is stitched at level 1 (every other sample): 8 cells, 16 triangles.
        assert_eq!(triangles, 16);
        let feet: Vec<u32> = skirt
            .iter()
            .copied()
            .filter(|&i| i != levels::RESTART && i >= n * n)
            .collect();
        assert_eq!(feet.len(), 9);
        // Every foot hangs under a sample of the east column.
        assert!(feet.iter().all(|&f| (f - n * n) % n == n - 1), "{feet:?}");
    }
}
