//! Strip masks (Pouderoux and Marvie 2005): per frame, culling, importance, the global
//! triangle budget shared greedily ([`crate::lod`]), one precomputed strip per mask level
//! shared by every tile (section 5.1), cracks filled by a [`CrackFiller`] (section 5.4).
//! As the reference of the accuracy measures it ignores the budget and draws every visible
//! tile at mask 0, with no filler.

use super::fillers::{self, CrackFiller};
use super::{LodMethod, MethodBytes, MethodConfig, MethodInput, MethodKind, MethodOutput};
use crate::lod::plan::{self, Candidate, LodSettings};
use crate::lod::strips::MaskSet;
use crate::render::{Frame, IndexSet, TileExtras};
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;
use terrain_shared::TileId;

/// The strip-mask method. See the module documentation.
#[derive(Debug)]
pub struct StripMasks {
    lod: LodSettings,
    filler: CrackFiller,
    masks: Arc<MaskSet>,
    reference: bool,
    /// One index set per mask level drawn so far, shared by every tile.
    strips: HashMap<u32, IndexSet>,
    /// The skirts of each mask level drawn with skirts so far.
    skirts: HashMap<u32, IndexSet>,
    /// The planar shadow's four corners (`terrain_shaders::shadow_base`), made when first
    /// drawn.
    quad: Option<IndexSet>,
    /// Frames drawn, and the last frame each mask level was drawn in: index sets unused
    /// for [`KEEP_UNUSED_FRAMES`] are dropped.
    frame: u64,
    last_used: HashMap<u32, u64>,
}

/// Frames an index set is kept after its level was last drawn.
pub const KEEP_UNUSED_FRAMES: u64 = 30;

impl StripMasks {
    /// The method for tiles of `tile_size` samples a side (it makes its GPU index sets as
    /// frames need them).
    pub fn new(config: &MethodConfig, tile_size: u32) -> StripMasks {
        let mut method = StripMasks {
            lod: config.lod,
            filler: config.filler,
            masks: Arc::new(MaskSet::new(tile_size)),
            reference: config.kind == MethodKind::Reference,
            strips: HashMap::new(),
            skirts: HashMap::new(),
            quad: None,
            frame: 0,
            last_used: HashMap::new(),
        };
        method.configure(config);
        method
    }

    /// Where the planar shadow puts tile `id`'s corners this frame, and the plane below it
    /// (also the skirts' bottom).
    fn extras(
        frame: &Frame<'_>,
        layout: &plan::Layout,
        filler: CrackFiller,
        id: TileId,
        min_m: f64,
    ) -> TileExtras {
        // The plane's depth is a tenth of a level-0 tile's side at every level: a coarser
        // tile spans more, but the cracks along its sides are no deeper for it.
        let floor = min_m - fillers::filler_depth_m(layout.tile_extent_m());
        let extent = layout.tile_extent_m_at(id.level);
        let mut extras = TileExtras {
            floor_m: floor as f32,
            ..TileExtras::default()
        };
        if filler != CrackFiller::PlanarShadow {
            return extras;
        }
        let Some(heights) = frame.tiles().heights(id) else {
            return extras;
        };
        let eye = frame.camera().position;
        let last = layout.tile_size as usize - 1;
        let [x0, y0] = layout.tile_origin_m(id);
        let plane = floor - eye[2];
        for (k, corner) in extras.points.iter_mut().enumerate() {
            // North-west, south-west, north-east, south-east.
            let (column, row) = ((k / 2) * last, (k % 2) * last);
            let height = f64::from(heights.metres(column, row) as f32);
            let p = fillers::shadow_corner(
                glam::DVec3::new(
                    x0 + (k / 2) as f64 * extent[0] - eye[0],
                    height - eye[2],
                    y0 + (k % 2) as f64 * extent[1] - eye[1],
                ),
                plane,
            );
            *corner = [p.x as f32, p.y as f32, p.z as f32, 1.0];
        }
        extras
    }

    /// Draws `draws` (resident tiles of `tiles` at their mask levels) into `frame`, cracks
    /// filled by `filler`: the drawing half of [`LodMethod::draw`], for a plan made
    /// elsewhere.
    pub fn draw_levels(
        &mut self,
        frame: &mut Frame<'_>,
        layout: &plan::Layout,
        tiles: &[Candidate<'_>],
        draws: &[plan::Draw],
        filler: CrackFiller,
    ) {
        let gpu = frame.gpu().clone();
        let n = self.masks.tile_size();
        self.frame += 1;
        for d in draws {
            self.last_used.insert(d.level, self.frame);
        }
        let now = self.frame;
        self.last_used
            .retain(|_, &mut used| now - used <= KEEP_UNUSED_FRAMES);
        let used = &self.last_used;
        self.strips.retain(|level, _| used.contains_key(level));
        self.skirts.retain(|level, _| used.contains_key(level));
        for d in draws {
            let masks = &self.masks;
            self.strips.entry(d.level).or_insert_with(|| {
                IndexSet::new(&gpu, &masks.build(d.level), masks.triangle_count(d.level))
            });
            if filler == CrackFiller::Skirts {
                self.skirts.entry(d.level).or_insert_with(|| {
                    IndexSet::new(
                        &gpu,
                        &fillers::skirt_strip(n, d.level),
                        fillers::skirt_triangles(n, d.level),
                    )
                });
            }
        }
        if filler == CrackFiller::PlanarShadow && self.quad.is_none() {
            let corner = terrain_shaders::shadow_base(n);
            self.quad = Some(IndexSet::new(
                &gpu,
                &[corner, corner + 1, corner + 2, corner + 3],
                2,
            ));
        }
        let min_m: HashMap<TileId, f64> = tiles.iter().map(|t| (t.id, t.min_m)).collect();
        let tiles: Vec<(TileId, TileExtras)> = draws
            .iter()
            .map(|d| {
                let min_m = min_m.get(&d.id).copied().unwrap_or(0.0);
                (d.id, Self::extras(frame, layout, filler, d.id, min_m))
            })
            .collect();
        let slots = frame.prepare_tiles(&tiles);
        let mut level_of = vec![0; tiles.len()];
        for (d, slot) in draws.iter().zip(&slots) {
            if let Some(slot) = *slot {
                level_of[slot] = d.level;
            }
        }
        let order = frame.draw_order();
        let mut pass = frame.last_pass();
        for &slot in &order {
            let level = level_of[slot];
            pass.bind_tile(slot);
            let strip = &self.strips[&level];
            pass.draw(strip);
            pass.stats_mut().triangles += u64::from(strip.triangles);
            if filler == CrackFiller::Skirts {
                let skirt = &self.skirts[&level];
                pass.draw(skirt);
                pass.stats_mut().filler_triangles += u64::from(skirt.triangles);
            }
        }
        if let (CrackFiller::PlanarShadow, Some(quad)) = (filler, &self.quad) {
            // After every surface, so the depth test hides the shadows where tiles cover
            // them. A shadow reaches past its tile, so past the terrain's edge too.
            pass.clip_everything();
            for &slot in &order {
                pass.bind_tile(slot);
                pass.draw(quad);
                pass.stats_mut().filler_triangles += u64::from(quad.triangles);
            }
        }
    }
}

impl LodMethod for StripMasks {
    fn full_resolution_only(&self) -> bool {
        self.reference
    }

    fn name(&self) -> String {
        if self.reference {
            MethodKind::Reference.name().to_string()
        } else {
            MethodKind::StripMasks.name_with(self.filler)
        }
    }

    fn configure(&mut self, config: &MethodConfig) {
        if self.reference {
            // The reference keeps full resolution: no cap, no filler.
            self.lod = LodSettings {
                cap_at_needed: false,
                ..config.lod
            };
            self.filler = CrackFiller::None;
        } else {
            self.lod = config.lod;
            self.filler = config.filler;
        }
    }

    fn draw(&mut self, input: &MethodInput<'_>, frame: &mut Frame<'_>) -> MethodOutput {
        let started = Instant::now();
        let budget = if self.reference {
            u32::MAX
        } else {
            input.budget
        };
        let mut plan = plan::plan_frame(
            frame.camera(),
            frame.viewport(),
            input.layout,
            input.tiles,
            budget,
            &self.masks,
            &self.lod,
        );
        if self.reference {
            // Full resolution whatever the importances made of the budget.
            for d in &mut plan.draws {
                d.level = 0;
            }
            plan.triangles = plan.draws.len() as u64 * u64::from(self.masks.triangle_count(0));
        }
        let lod_ms = started.elapsed().as_secs_f64() * 1e3;

        self.draw_levels(frame, input.layout, input.tiles, &plan.draws, self.filler);
        MethodOutput::of_plan(plan, lod_ms)
    }

    fn shared_bytes(&self) -> MethodBytes {
        MethodBytes {
            cpu: self.masks.bytes(),
            gpu: self
                .strips
                .values()
                .chain(self.skirts.values())
                .chain(&self.quad)
                .map(IndexSet::bytes)
                .sum(),
        }
    }
}
