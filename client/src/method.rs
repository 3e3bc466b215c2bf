//! The seam between the scene and a level-of-detail method.
//!
//! Each frame the scene hands the method what it knows (the camera, the viewport, the
//! resident tiles as the manifest describes them, the frame's triangle budget) and the
//! renderer holding those tiles on the GPU; the method decides what to draw, draws it into
//! the target and says what it drew ([`MethodOutput`]). The scene does not know how.
//!
//! - **Per-tile methods** (strip masks here; GeoMipMaps) choose an index set per visible
//!   tile and draw it with [`TerrainRenderer::render`], whose vertex shader turns sample
//!   indices into positions.
//! - **Screen-grid methods** (a projected grid draws one screen-sized mesh) keep their own
//!   GPU state, fed by [`LodMethod::tile_resident`] and [`LodMethod::tile_evicted`] as tiles
//!   come and go, and draw it into the same target; their [`FramePlan`] has no per-tile
//!   draws.
//!
//! The **reference** of the accuracy measures ([`crate::eval`]) is a method too: every
//! visible resident tile at the finest mask, no budget, no filler ([`MethodKind::Reference`]).

use crate::lod::strips::MaskSet;
use crate::render::plan::{self, Candidate, FramePlan, Layout, LodSettings};
use crate::render::{Camera, CrackFiller, RenderStats, TerrainRenderer};
use std::sync::Arc;
use std::time::Instant;
use terrain_shared::{Heights, TileId};

/// What a method is told about the frame.
#[derive(Debug, Clone, Copy)]
pub struct MethodInput<'a> {
    pub camera: &'a Camera,
    /// Width and height of the target, pixels.
    pub viewport: [u32; 2],
    pub layout: &'a Layout,
    /// The resident tiles.
    pub tiles: &'a [Candidate<'a>],
    /// The frame's triangle budget: the frame-rate controller's, or a fixed one.
    pub budget: u32,
}

/// What a method drew.
#[derive(Debug, Clone, Default)]
pub struct MethodOutput {
    pub plan: FramePlan,
    pub stats: RenderStats,
    /// CPU time of the method's decisions (culling, error and budget), milliseconds.
    pub lod_ms: f64,
}

/// A level-of-detail method (see the module documentation).
pub trait LodMethod: std::fmt::Debug + Send {
    /// Its name in tables and charts, e.g. `strip-masks/planar-shadow`.
    fn name(&self) -> String;

    /// Decides and draws one frame into `target` (cleared first).
    fn draw(
        &mut self,
        input: &MethodInput<'_>,
        renderer: &mut TerrainRenderer,
        target: &wgpu::TextureView,
    ) -> MethodOutput;

    /// Draws later frames with these settings (the method stays the same kind).
    fn configure(&mut self, lod: LodSettings, filler: CrackFiller);

    /// A tile became resident (for methods keeping their own copy of the terrain).
    fn tile_resident(&mut self, _id: TileId, _heights: &Heights) {}

    /// A tile was evicted.
    fn tile_evicted(&mut self, _id: TileId) {}

    /// Bytes of what the method keeps per tile (error tables), for the memory report.
    fn lod_bytes(&self) -> u64 {
        0
    }
}

/// The methods a flight or a benchmark can run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum MethodKind {
    /// Strip masks: a global triangle budget shared by importance, one precomputed strip
    /// per mask level, cracks filled by the crack filler.
    #[default]
    StripMasks,
    /// Every visible tile at full resolution: no budget, no filler. What the accuracy
    /// measures compare against.
    Reference,
    /// GeoMipMaps (Brodersen 2005): per tile the coarsest level (every 2^k-th sample)
    /// whose projected error is within `--max-error-px`, borders stitched by adding the
    /// finer neighbour's vertices: crack-free, no budget, no filler.
    Geomipmap,
}

impl MethodKind {
    pub fn name(self) -> &'static str {
        match self {
            MethodKind::StripMasks => "strip-masks",
            MethodKind::Reference => "reference",
            MethodKind::Geomipmap => "geomipmap",
        }
    }

    /// Whether the method fills cracks with a [`CrackFiller`] (the others are crack-free
    /// by construction, or have no tiles).
    pub fn uses_filler(self) -> bool {
        matches!(self, MethodKind::StripMasks)
    }

    /// Whether the method draws tiles block by block with MapBlock textures
    /// ([`crate::render::blocks`]), as the GeoMipMaps paper does.
    pub fn uses_texture_blocks(self) -> bool {
        matches!(self, MethodKind::Geomipmap)
    }
}

/// Builds the method `kind` with the given settings, sharing `masks` with the renderer.
pub fn build(
    kind: MethodKind,
    lod: LodSettings,
    filler: CrackFiller,
    masks: Arc<MaskSet>,
) -> Box<dyn LodMethod> {
    match kind {
        MethodKind::StripMasks => Box::new(StripMasks {
            lod,
            filler,
            masks,
            reference: false,
        }),
        MethodKind::Geomipmap => Box::new(GeoMipMaps {
            lod,
            masks,
            error_minima: std::collections::HashMap::new(),
            counts: std::collections::HashMap::new(),
        }),
        MethodKind::Reference => Box::new(StripMasks {
            lod: LodSettings {
                cap_at_needed: false,
                ..lod
            },
            filler: CrackFiller::None,
            masks,
            reference: true,
        }),
    }
}

/// Strip masks (the strip-mask paper): per frame, culling, importance, the budget shared
/// greedily, one mask per tile, cracks filled by `filler`. As the reference it ignores the
/// budget and draws every tile at level 0.
#[derive(Debug)]
struct StripMasks {
    lod: LodSettings,
    filler: CrackFiller,
    masks: Arc<MaskSet>,
    reference: bool,
}

impl LodMethod for StripMasks {
    fn name(&self) -> String {
        if self.reference {
            MethodKind::Reference.name().to_string()
        } else {
            crate::eval::Variants::name(MethodKind::StripMasks, self.filler)
        }
    }

    fn configure(&mut self, lod: LodSettings, filler: CrackFiller) {
        if self.reference {
            // The reference keeps full resolution: no cap, no filler.
            self.lod = LodSettings {
                cap_at_needed: false,
                ..lod
            };
        } else {
            self.lod = lod;
            self.filler = filler;
        }
    }

    fn draw(
        &mut self,
        input: &MethodInput<'_>,
        renderer: &mut TerrainRenderer,
        target: &wgpu::TextureView,
    ) -> MethodOutput {
        let started = Instant::now();
        let budget = if self.reference {
            u32::MAX
        } else {
            input.budget
        };
        let mut plan = plan::plan_frame(
            input.camera,
            input.viewport,
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
        let stats = renderer.render(target, input.camera, &plan.draws, self.filler);
        MethodOutput {
            plan,
            stats,
            lod_ms,
        }
    }
}

/// GeoMipMaps (see [`crate::lod::geomipmap`]): the coarsest level within the error
/// threshold per visible tile, each side stitched to its neighbour's level.
#[derive(Debug)]
struct GeoMipMaps {
    lod: LodSettings,
    /// Shares the tile size with the strip masks; the importances come from the same
    /// planner (they rank textures).
    masks: Arc<MaskSet>,
    /// Per resident tile, the suffix minima of its levels' errors, computed from its
    /// heights when it arrives.
    error_minima: std::collections::HashMap<TileId, Vec<f32>>,
    /// Triangles of each index set drawn so far.
    counts: std::collections::HashMap<crate::lod::geomipmap::Stitch, u32>,
}

impl LodMethod for GeoMipMaps {
    fn name(&self) -> String {
        MethodKind::Geomipmap.name().to_string()
    }

    fn configure(&mut self, lod: LodSettings, _filler: CrackFiller) {
        // Crack-free by construction: no filler.
        self.lod = lod;
    }

    fn draw(
        &mut self,
        input: &MethodInput<'_>,
        renderer: &mut TerrainRenderer,
        target: &wgpu::TextureView,
    ) -> MethodOutput {
        use crate::lod::geomipmap::{Stitch, triangles};
        use crate::lod::needed;
        let started = Instant::now();
        // Culling, importances (they rank the textures) and the strip-mask levels needed
        // (the common yardstick of triangles needed), as the strip masks have them; no
        // budget plays a part.
        let ranked = plan::rank_visible(
            input.camera,
            input.viewport,
            input.layout,
            input.tiles,
            &self.lod,
        );
        // The error bound per visible tile, as the planner computed it for the strip masks'
        // needed levels, compared with this method's own level errors.
        let threshold = self.lod.max_error_px;
        let mut levels = std::collections::HashMap::with_capacity(ranked.visible.len());
        for (&i, &k) in ranked.visible.iter().zip(&ranked.pixels_per_metre) {
            let tile = &input.tiles[i];
            let level = self.error_minima.get(&tile.id).map_or(0, |minima| {
                needed::coarsest_level_within(minima, k, threshold)
            });
            levels.insert(tile.id, level);
        }
        let n = input.layout.tile_size;
        let mut plan = plan::FramePlan {
            budget: input.budget,
            importances: ranked.importances,
            triangles_needed: ranked
                .needed_levels
                .iter()
                .map(|&l| u64::from(self.masks.triangle_count(l)))
                .sum(),
            needed_levels: ranked.needed_levels,
            ..plan::FramePlan::default()
        };
        let mut drawn = 0u64;
        for &i in &ranked.visible {
            let id = input.tiles[i].id;
            let level = levels[&id];
            let near = |dx: i64, dy: i64| {
                let (x, y) = (i64::from(id.x) + dx, i64::from(id.y) + dy);
                (x >= 0 && y >= 0)
                    .then(|| levels.get(&TileId::new(x as u32, y as u32)).copied())
                    .flatten()
            };
            let stitch = Stitch::new(level, [near(0, -1), near(1, 0), near(0, 1), near(-1, 0)]);
            plan.draws.push(plan::Draw {
                id,
                level,
                stitch: Some(stitch),
            });
            drawn += u64::from(
                *self
                    .counts
                    .entry(stitch)
                    .or_insert_with(|| triangles(n, stitch).len() as u32),
            );
        }
        plan.triangles = drawn;
        let lod_ms = started.elapsed().as_secs_f64() * 1e3;
        let stats = renderer.render(target, input.camera, &plan.draws, CrackFiller::None);
        MethodOutput {
            plan,
            stats,
            lod_ms,
        }
    }

    fn tile_resident(&mut self, id: TileId, heights: &Heights) {
        let samples = heights.to_metres_f32();
        let errors = crate::lod::geomipmap::level_errors(&samples, u32::from(heights.width));
        self.error_minima
            .insert(id, crate::lod::needed::suffix_minima(&errors));
    }

    fn tile_evicted(&mut self, id: TileId) {
        self.error_minima.remove(&id);
    }

    fn lod_bytes(&self) -> u64 {
        self.error_minima.values().map(|m| 4 * m.len() as u64).sum()
    }
}
