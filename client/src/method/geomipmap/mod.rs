//! GeoMipMaps (Brodersen 2005) as a method: per visible tile the coarsest level whose
//! error, projected by the frame's bound, stays within `--max-error-px`, each side stitched
//! to its neighbour's level ([`stitching`]): crack-free, no budget, no filler.
//! Tiles are bound block by block with MapBlock textures, as the paper draws them
//! ([`super::MethodConfig::uses_texture_blocks`]).
//!
//! Levels of the pyramid: a tile of a coarser level is one more GeoMipMap, its level errors
//! raised by its own distance from full resolution. Stitching joins tiles of one level; a
//! side that borders a tile of another level (a seam, [`crate::lod::levels::seams`]) hangs a
//! skirt from its edge samples instead, down past the cracks the two edges can leave.

pub mod stitching;

use self::stitching::{self as levels, Stitch};
use super::{Build, LodMethod, MethodBytes, MethodConfig, MethodInput, MethodKind, MethodOutput};
use crate::lod::needed;
use crate::lod::plan::{self, LodSettings};
use crate::lod::strips::MaskSet;
use crate::render::{Frame, Gpu, IndexSet, TileExtras};
use std::collections::HashMap;
use std::time::Instant;
use terrain_shared::{Heights, TileId, TileRecord};

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
    fn indices(self, n: u32) -> (Vec<u32>, u32) {
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
    /// Per resident tile, the suffix minima of its levels' errors, computed from its
    /// heights when it arrives.
    error_minima: HashMap<TileId, Vec<f32>>,
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
        let coarsest = levels::level_count(n) - 1;
        let (indices, _) = SetKey::Stitch(Stitch::new(coarsest, [None; 4])).indices(n);
        let coarsest_set_bytes = 4 * (indices.len() as u64).max(1);
        GeoMipMaps {
            lod: config.lod,
            masks: MaskSet::new(n),
            error_minima: HashMap::new(),
            index_sets: HashMap::new(),
            frame: 0,
            coarsest_set_bytes,
        }
    }
}

impl GeoMipMaps {
    /// Whether set `key` is held, or can be made within `room` (taking its bytes out of it),
    /// dropping sets no frame drew lately to make room if need be.
    fn affordable(&mut self, key: SetKey, n: u32, room: &mut u64) -> bool {
        if self.index_sets.contains_key(&key) {
            return true;
        }
        let (indices, _) = key.indices(n);
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
        // The error bound per visible tile, as the planner computed it for the strip masks'
        // needed levels, compared with this method's own level errors.
        let threshold = self.lod.max_error_px;
        let mut chosen = HashMap::with_capacity(ranked.visible.len());
        for (&i, &k) in ranked.visible.iter().zip(&ranked.pixels_per_metre) {
            let tile = &input.tiles[i];
            // A coarser level of the pyramid is that far from full resolution already.
            let deviation = tile.error_minima_m.first().copied().unwrap_or(0.0);
            let level = self.error_minima.get(&tile.id).map_or(0, |minima| {
                let raised: Vec<f32> = minima.iter().map(|e| e + deviation).collect();
                needed::coarsest_level_within(&raised, k, threshold)
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
        let coarsest = levels::level_count(n) - 1;
        let reserved = SetKey::Stitch(Stitch::new(coarsest, [None; 4]));
        let mut room = input.room;
        let mut degraded = 0;
        let mut extras = Vec::with_capacity(ranked.visible.len());
        for (&i, &importance) in ranked.visible.iter().zip(&ranked.importances) {
            let tile = &input.tiles[i];
            let id = tile.id;
            let level = chosen[&id];
            let near = |dx: i64, dy: i64| {
                let (x, y) = (i64::from(id.x) + dx, i64::from(id.y) + dy);
                (x >= 0 && y >= 0)
                    .then(|| {
                        chosen
                            .get(&TileId::at(id.level, x as u32, y as u32))
                            .copied()
                    })
                    .flatten()
            };
            let stitch = Stitch::new(level, [near(0, -1), near(1, 0), near(0, 1), near(-1, 0)]);
            // Each set the tile needs, made if the limit has room for it; without room, the
            // unstitched set of its level (cracks may show along the stitched sides), else
            // the coarsest level's, which the reservation holds; a skirt without room is
            // left out.
            let mut keys = Vec::with_capacity(5);
            let mut drawn_level = level;
            for key in sets_of(stitch, tile.seams) {
                let usable = match key {
                    SetKey::Stitch(_) => [
                        key,
                        SetKey::Stitch(Stitch::new(level, [None; 4])),
                        SetKey::Stitch(Stitch::new(coarsest, [None; 4])),
                    ]
                    .into_iter()
                    .find(|&k| k == reserved || self.affordable(k, n, &mut room)),
                    SetKey::Skirt { .. } => Some(key).filter(|&k| self.affordable(k, n, &mut room)),
                };
                let Some(key) = usable else {
                    degraded += 1;
                    continue;
                };
                if let SetKey::Stitch(s) = key {
                    degraded += u32::from(s != stitch);
                    drawn_level = s.level;
                }
                let (set, used) = self.index_sets.entry(key).or_insert_with(|| {
                    let (indices, triangles) = key.indices(n);
                    (IndexSet::new(&gpu, &indices, triangles), now)
                });
                *used = now;
                plan.triangles += u64::from(set.triangles);
                keys.push(key);
            }
            plan.draws.push(plan::Draw {
                id,
                level: drawn_level,
            });
            plan.importances.push(importance);
            stitches.push(keys);
            // Skirts reach below the tile's lowest point by a tenth of a level-0 tile and
            // twice its own distance from full resolution: the two edges of a seam lie
            // within their tiles' errors of the true surface, which is above that point.
            let depth = super::fillers::filler_depth_m(input.layout.tile_extent_m())
                + 2.0 * f64::from(tile.error_minima_m.first().copied().unwrap_or(0.0));
            extras.push(TileExtras {
                floor_m: (tile.min_m - depth) as f32,
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
        let mut keys_of: Vec<&[SetKey]> = vec![&[]; tiles.len()];
        for (keys, slot) in stitches.iter().zip(&slots) {
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
            for key in keys_of[slot] {
                let set = &self.index_sets[key].0;
                pass.draw(set);
                pass.stats_mut().triangles += u64::from(set.triangles);
            }
        }
        pass.stats_mut().degraded_draws += degraded;
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

#[cfg(test)]
mod tests {
    use super::*;

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
        let (plain, _) = sets[0].indices(n);
        assert_eq!(plain, levels::strip(n, stitch));
        let (skirt, triangles) = sets[1].indices(n);
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
