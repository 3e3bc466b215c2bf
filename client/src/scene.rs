//! The scene: resident tiles, paged under the memory limit, streamed by the fetcher, and,
//! when a GPU is given, uploaded, textured within a budget and drawn. The headless flight
//! and the windowed viewer both drive one, a frame at a time.
//!
//! Per frame, [`Scene::update`]: deliveries become resident tiles (uploaded to the GPU when
//! rendering); the pure pager ([`crate::page::decide`]) sees the viewpoint, the tiles'
//! bytes at their coarsest texture, and what is in flight, and decides; cancellations,
//! evictions and requests follow; then the texture budget (what the limit leaves once the
//! tiles in flight are paid for) sets how fine each tile's texture goes, dropping levels at
//! once and asking for finer ones one at a time. [`Scene::draw`] then plans the frame
//! (culling, importance, budget sharing, masks) and renders it, and feeds the frame's time
//! back to the frame-rate controller. Nothing waits on the network: a frame takes what has
//! arrived.
//!
//! **Memory.** A tile's bytes are its decoded heights and encoded texture levels (CPU) plus,
//! when rendering, its GPU samples and texture. The pager admits a belt only if it fits at
//! the coarsest texture; finer levels are paid from what is left, so the total stays under
//! the limit whatever arrives.

use crate::fetcher::{FailureKind, FetchEvent, Fetcher, Want};
use crate::flight::FlightError;
use crate::lod::budget::{BudgetMode, FrameRateController};
use crate::lod::strips::MaskSet;
use crate::memory::TileBytes;
use crate::method::{self, LodMethod, MethodInput, MethodKind};
use crate::page::{self, Decision, PagerConfig, PagerView};
use crate::render::plan::{Candidate, FramePlan, Layout, LodSettings};
use crate::render::textures::{TextureCandidate, extra_costs, share_texture_budget};
use crate::render::{Camera, CrackFiller, Gpu, RenderStats, TerrainRenderer};
use std::sync::Arc;
use std::time::Instant;
use terrain_shared::{Manifest, TileId};

/// How a scene renders.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderConfig {
    pub method: MethodKind,
    pub lod: LodSettings,
    pub filler: CrackFiller,
    pub budget: BudgetMode,
    /// Texture uploads at most per frame, so that a burst of arrivals cannot stall one.
    pub uploads_per_frame: usize,
    /// For methods drawing with MapBlocks ([`MethodKind::uses_texture_blocks`]): the largest
    /// block texture side, texels (`None`: the adapter's limit).
    pub texture_block_limit: Option<u32>,
    /// Whether those methods use MapBlocks at all (`false`: every tile with its own
    /// texture, for comparison).
    pub texture_blocks: bool,
}

impl RenderConfig {
    /// Whether this configuration draws with MapBlocks.
    pub fn uses_texture_blocks(&self) -> bool {
        self.method.uses_texture_blocks() && self.texture_blocks
    }

    /// Copies of each tile's GPU texture this configuration holds (see
    /// [`crate::render::blocks::TEXTURE_COPIES`]).
    pub fn texture_copies(&self) -> u64 {
        if self.uses_texture_blocks() {
            crate::render::blocks::TEXTURE_COPIES
        } else {
            1
        }
    }
}

impl Default for RenderConfig {
    fn default() -> RenderConfig {
        RenderConfig {
            method: MethodKind::default(),
            lod: LodSettings::default(),
            filler: CrackFiller::default(),
            budget: BudgetMode::default(),
            uploads_per_frame: 8,
            texture_block_limit: None,
            texture_blocks: true,
        }
    }
}

/// A tile held in memory.
#[derive(Debug, Clone)]
struct ResidentTile {
    /// Shared with the renderer, which makes samples of them when it draws the tile.
    heights: Arc<terrain_shared::Heights>,
    /// Encoded texture levels held, coarsest first.
    textures: Vec<bytes::Bytes>,
    /// Levels of `textures` on the GPU (0 before the first upload).
    uploaded_levels: usize,
    /// The first texture level that did not decode: it and finer ones are not asked for
    /// again (their hash was verified, so fetching again would give the same bytes).
    undecodable_from: Option<usize>,
    bytes: TileBytes,
    downloaded: u64,
    /// Whether it was ever part of the complete square.
    used: bool,
}

/// What [`Scene::update`] decided this frame.
#[derive(Debug, Clone)]
pub struct Update {
    pub decision: Decision,
    /// Bytes the texture budget had this frame.
    pub texture_budget: u64,
}

/// What [`Scene::draw`] did this frame.
#[derive(Debug, Clone, Default)]
pub struct DrawReport {
    pub plan: FramePlan,
    pub stats: RenderStats,
    /// Time of the method's decisions (culling, importance, budget sharing, masks).
    pub lod_ms: f64,
    /// Time from the start of the draw to the GPU's completion.
    pub draw_ms: f64,
    /// The fewest triangles that keep every drawn tile's projected error within
    /// [`LodSettings::max_error_px`] ([`crate::lod::needed`]).
    pub triangles_needed: u64,
    /// The method that drew, e.g. `strip-masks/planar-shadow`.
    pub method: String,
}

/// The bytes a scene keeps for its terrain's geometry ([`Scene::geometry_memory`]): what the
/// GeoMipMaps paper counts in its bytes per sample (heights, level-of-detail data, index
/// sets), textures apart.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct GeometryMemory {
    /// Samples of the resident tiles (shared borders counted in each tile, as stored).
    pub samples: u64,
    /// Decoded height codes (CPU), shared with the renderer.
    pub cpu_heights: u64,
    /// Per-tile error tables: the manifest's strip-mask errors and the method's own.
    pub cpu_lod: u64,
    /// Pooled sample buffers (only tiles drawn lately hold one), index sets and textures.
    pub gpu: crate::render::GpuResidency,
}

impl GeometryMemory {
    /// Geometry bytes: heights, error tables, sample buffers and index sets.
    pub fn bytes(&self) -> u64 {
        self.cpu_heights + self.cpu_lod + self.gpu.sample_bytes + self.gpu.index_bytes
    }

    /// [`GeometryMemory::bytes`] per resident sample.
    pub fn per_sample(&self) -> f64 {
        self.bytes() as f64 / self.samples.max(1) as f64
    }
}

impl std::fmt::Display for GeometryMemory {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let per = |b: u64| b as f64 / self.samples.max(1) as f64;
        write!(
            f,
            "{:.2} B/sample: heights {:.2}, error tables {:.3}, GPU samples {:.2} ({} of {} tiles hold a buffer), index sets {:.3}",
            self.per_sample(),
            per(self.cpu_heights),
            per(self.cpu_lod),
            per(self.gpu.sample_bytes),
            self.gpu.sample_buffers,
            self.gpu.tiles,
            per(self.gpu.index_bytes),
        )
    }
}

/// The rendering half of a scene.
#[derive(Debug)]
struct Rendering {
    renderer: TerrainRenderer,
    masks: Arc<MaskSet>,
    method: Box<dyn LodMethod>,
    controller: FrameRateController,
    config: RenderConfig,
    /// Target texture level per tile (index as `tiles`), from the last texture budget.
    texture_target: Vec<u32>,
    /// Importance per tile in the last planned frame (0 when not visible).
    importance: Vec<f64>,
    /// Per tile, the extra bytes of each texture level ([`extra_costs`]), from the manifest.
    texture_costs: Vec<Vec<u64>>,
}

/// Resident tiles, paging, and optionally rendering. See the module documentation.
#[derive(Debug)]
pub struct Scene {
    manifest: Arc<Manifest>,
    layout: Layout,
    pager: PagerConfig,
    tiles: Vec<Option<ResidentTile>>,
    /// Bytes per tile at the coarsest texture (what the pager sees).
    base_bytes: Vec<u64>,
    expected_bytes: Vec<u64>,
    in_flight: Vec<bool>,
    /// Per tile, the suffix minima of its per-mask errors ([`crate::lod::needed`]).
    error_minima: Vec<Vec<f32>>,
    pub tiles_fetched: u64,
    pub evicted_unused_bytes: u64,
    rendering: Option<Rendering>,
}

impl Scene {
    /// A scene of `manifest`'s tiles paged by `pager`; with `render`, drawn by `gpu` into
    /// targets of `format`.
    pub fn new(
        manifest: Arc<Manifest>,
        pager: PagerConfig,
        render: Option<(Gpu, wgpu::TextureFormat, RenderConfig)>,
    ) -> Scene {
        let count = manifest.tiles.len();
        let layout = Layout {
            tile_size: manifest.tile_size,
            spacing_m: manifest.spacing_m,
        };
        let rendering = render.map(|(gpu, format, config)| {
            let masks = Arc::new(MaskSet::new(manifest.tile_size));
            let mut r = Rendering {
                renderer: TerrainRenderer::new(&gpu, format, layout, Arc::clone(&masks)),
                method: method::build(config.method, config.lod, config.filler, Arc::clone(&masks)),
                masks,
                controller: FrameRateController::new(config.budget),
                config,
                texture_target: vec![0; count],
                importance: vec![0.0; count],
                texture_costs: Vec::new(),
            };
            r.set_texture_blocks(&manifest);
            r
        });
        let copies = rendering.as_ref().map_or(0, |r| r.config.texture_copies());
        Scene {
            expected_bytes: manifest
                .tiles
                .iter()
                .map(|t| expected_tile_bytes(&manifest, t, copies).total())
                .collect(),
            layout,
            pager,
            tiles: vec![None; count],
            base_bytes: vec![0; count],
            in_flight: vec![false; count],
            error_minima: manifest
                .tiles
                .iter()
                .map(|t| crate::lod::needed::suffix_minima(&t.mask_errors_m))
                .collect(),
            tiles_fetched: 0,
            evicted_unused_bytes: 0,
            rendering,
            manifest,
        }
    }

    fn index(&self, id: TileId) -> usize {
        id.y as usize * self.manifest.grid.columns as usize + id.x as usize
    }

    /// Bytes held by resident tiles, textures included.
    pub fn resident_bytes(&self) -> u64 {
        self.tiles.iter().flatten().map(|t| t.bytes.total()).sum()
    }

    /// What the scene keeps for its geometry now (see [`GeometryMemory`]).
    pub fn geometry_memory(&self) -> GeometryMemory {
        let resident = self.tiles.iter().flatten();
        GeometryMemory {
            samples: self.resident_tiles() * u64::from(self.manifest.tile_size).pow(2),
            cpu_heights: resident.map(|t| t.bytes.decoded_heights).sum(),
            cpu_lod: self
                .error_minima
                .iter()
                .map(|m| 4 * m.len() as u64)
                .sum::<u64>()
                + self.rendering.as_ref().map_or(0, |r| r.method.lod_bytes()),
            gpu: self
                .rendering
                .as_ref()
                .map_or_else(Default::default, |r| r.renderer.resident_gpu()),
        }
    }

    pub fn resident_tiles(&self) -> u64 {
        self.tiles.iter().filter(|t| t.is_some()).count() as u64
    }

    /// Tiles the pager counts as in flight.
    pub fn in_flight(&self) -> u64 {
        self.in_flight.iter().filter(|&&f| f).count() as u64
    }

    pub fn memory_limit(&self) -> u64 {
        self.pager.memory_limit
    }

    /// Draws later frames with `config`'s method and settings; a different budget mode
    /// starts the frame-rate controller again. Resident tiles stay. Nothing happens without rendering.
    pub fn reconfigure(&mut self, config: RenderConfig) {
        if let Some(r) = &mut self.rendering {
            if config.method == r.config.method {
                // Same method: new settings, and whatever it learnt of the tiles stays.
                r.method.configure(config.lod, config.filler);
            } else {
                r.method = method::build(
                    config.method,
                    config.lod,
                    config.filler,
                    Arc::clone(&r.masks),
                );
                // The new method learns the tiles already resident.
                for (record, tile) in self.manifest.tiles.iter().zip(&self.tiles) {
                    if let Some(tile) = tile {
                        r.method.tile_resident(record.id(), &tile.heights);
                    }
                }
            }
            if config.budget != r.config.budget {
                r.controller = FrameRateController::new(config.budget);
            }
            let before = r.config.texture_copies();
            r.config = config;
            r.set_texture_blocks(&self.manifest);
            let after = r.config.texture_copies();
            if after != before {
                // Blocks on or off: what each tile is charged, and what the pager expects
                // of each, change with the copies of its GPU texture.
                let coarsest = coarsest_rgba_bytes(&self.manifest);
                let tiles = self.manifest.tiles.iter().zip(&mut self.tiles);
                for (i, (record, tile)) in tiles.enumerate() {
                    self.expected_bytes[i] =
                        expected_tile_bytes(&self.manifest, record, after).total();
                    if let Some(tile) = tile {
                        tile.bytes.gpu = r.renderer.tile_bytes(record.id());
                        if tile.uploaded_levels > 0 {
                            self.base_bytes[i] =
                                self.base_bytes[i] + after * coarsest - before * coarsest;
                        }
                    }
                }
            }
        }
    }

    /// The triangle budget of the next frame (`None` when not rendering).
    pub fn budget(&self) -> Option<u32> {
        self.rendering.as_ref().map(|r| r.controller.budget())
    }

    /// Keeps each frame's depth buffer for [`Scene::read_depth`] (slower; for measuring).
    pub fn keep_depth(&mut self, keep: bool) {
        if let Some(r) = &mut self.rendering {
            r.renderer.keep_depth(keep);
        }
    }

    /// The last frame's depth buffer (see [`TerrainRenderer::read_depth`]).
    pub fn read_depth(&self) -> Option<Result<Vec<f32>, crate::render::GpuError>> {
        self.rendering.as_ref().map(|r| r.renderer.read_depth())
    }

    /// Whether every tile is resident with every texture level it is meant to have and
    /// nothing is in flight: what the accuracy measures wait for.
    pub fn settled(&self) -> bool {
        let textures_done = self.rendering.as_ref().is_none_or(|r| {
            self.tiles
                .iter()
                .zip(&r.texture_target)
                .all(|(t, &target)| {
                    t.as_ref().is_none_or(|t| {
                        let held = t
                            .textures
                            .len()
                            .min(t.undecodable_from.unwrap_or(usize::MAX));
                        t.uploaded_levels >= held
                            && (t.textures.len() > target as usize || t.undecodable_from.is_some())
                    })
                })
        });
        self.in_flight.iter().all(|f| !f) && textures_done
    }

    /// Height of the true surface at world point `(x, y)` (metres), as full resolution
    /// draws it: the resident samples, each cell split along the diagonal the strips use
    /// (`terrain_shared::mask`). `None` off the terrain or over a tile not resident.
    pub fn surface_height(&self, x: f64, y: f64) -> Option<f64> {
        let cells = f64::from(self.layout.tile_size - 1);
        let (sx, sy) = (x / self.layout.spacing_m[0], y / self.layout.spacing_m[1]);
        if !(sx >= 0.0 && sy >= 0.0) {
            return None;
        }
        let (columns, rows) = (self.manifest.grid.columns, self.manifest.grid.rows);
        let tx = ((sx / cells).floor() as u32).min(columns.saturating_sub(1));
        let ty = ((sy / cells).floor() as u32).min(rows.saturating_sub(1));
        let (u, v) = (sx - f64::from(tx) * cells, sy - f64::from(ty) * cells);
        if u > cells || v > cells {
            return None;
        }
        let tile = self.tiles[self.index(TileId::new(tx, ty))].as_ref()?;
        let last = self.layout.tile_size as usize - 1;
        let (c0, r0) = (
            (u.floor() as usize).min(last - 1),
            (v.floor() as usize).min(last - 1),
        );
        let (fu, fv) = (u - c0 as f64, v - r0 as f64);
        let h = |c: usize, r: usize| tile.heights.metres(c, r);
        // Split along the diagonal from (c0, r1) to (c1, r0).
        Some(if fu + fv <= 1.0 {
            let h00 = h(c0, r0);
            h00 + fu * (h(c0 + 1, r0) - h00) + fv * (h(c0, r0 + 1) - h00)
        } else {
            let h11 = h(c0 + 1, r0 + 1);
            h11 + (1.0 - fu) * (h(c0, r0 + 1) - h11) + (1.0 - fv) * (h(c0 + 1, r0) - h11)
        })
    }

    /// Deliveries, paging and the texture budget for a viewpoint at `position` (metres).
    pub fn update(
        &mut self,
        fetcher: &mut Fetcher,
        frame: u64,
        position: [f64; 3],
    ) -> Result<Update, FlightError> {
        for event in fetcher.poll() {
            self.deliver(event)?;
        }
        fetcher.mark_pending(&mut self.in_flight, self.manifest.grid.columns);
        // A resident tile waiting for a finer texture is not "in flight" for the pager.
        for (flag, tile) in self.in_flight.iter_mut().zip(&self.tiles) {
            *flag &= tile.is_none();
        }
        let extent = self.layout.tile_extent_m();
        let view = PagerView {
            viewpoint: [position[0] / extent[0], position[1] / extent[1]],
            resident_bytes: &self.base_bytes,
            in_flight: &self.in_flight,
            expected_bytes: Some(&self.expected_bytes),
        };
        let decision = page::decide(&self.pager, &view);
        fetcher.cancel(&decision.cancel);
        fetcher.cancel(&decision.evict);
        for &id in &decision.evict {
            let i = self.index(id);
            if let Some(tile) = self.tiles[i].take()
                && !tile.used
            {
                self.evicted_unused_bytes += tile.downloaded;
            }
            self.base_bytes[i] = 0;
            if let Some(r) = &mut self.rendering {
                r.renderer.remove_tile(id);
                r.method.tile_evicted(id);
            }
        }
        for (rank, &id) in decision.fetch.iter().enumerate() {
            // Earlier frames' requests go first; within a frame, the pager's order.
            fetcher.request(id, Want::Tile, (frame << 20) | rank as u64);
            let i = self.index(id);
            self.in_flight[i] = true;
        }
        for id in page::square_tiles(&self.pager, decision.current, decision.complete_belts) {
            let i = self.index(id);
            if let Some(tile) = &mut self.tiles[i] {
                tile.used = true;
            }
        }
        let texture_budget = self.share_textures(fetcher, frame);
        Ok(Update {
            decision,
            texture_budget,
        })
    }

    fn deliver(&mut self, event: FetchEvent) -> Result<(), FlightError> {
        match event {
            FetchEvent::Tile {
                id,
                heights,
                heights_bytes,
                coarsest_texture,
                ..
            } => {
                let i = self.index(id);
                let heights = Arc::new(heights);
                let mut bytes = TileBytes {
                    decoded_heights: std::mem::size_of_val(heights.codes.as_slice()) as u64,
                    textures: coarsest_texture.len() as u64,
                    ..TileBytes::default()
                };
                let mut uploaded_levels = 0;
                if let Some(r) = &mut self.rendering {
                    let record = &self.manifest.tiles[i];
                    r.renderer
                        .upload_tile(id, Arc::clone(&heights), f64::from(record.min_m));
                    r.method.tile_resident(id, &heights);
                    if let Some(image) = decode_texture(&coarsest_texture, id, 0) {
                        r.renderer.upload_texture(id, 0, &[image]);
                        uploaded_levels = 1;
                    }
                    bytes.gpu = r.renderer.tile_bytes(id);
                }
                let base = bytes.total();
                self.base_bytes[i] = base;
                self.tiles[i] = Some(ResidentTile {
                    heights,
                    downloaded: heights_bytes + coarsest_texture.len() as u64,
                    textures: vec![coarsest_texture],
                    uploaded_levels,
                    undecodable_from: (uploaded_levels == 0 && self.rendering.is_some())
                        .then_some(0),
                    bytes,
                    used: false,
                });
                self.tiles_fetched += 1;
            }
            FetchEvent::TextureLevel { id, level, bytes } => {
                let i = self.index(id);
                let target = self.rendering.as_ref().map_or(0, |r| r.texture_target[i]);
                if let Some(tile) = &mut self.tiles[i]
                    && level as usize == tile.textures.len()
                    && level <= target
                {
                    tile.bytes.textures += bytes.len() as u64;
                    tile.downloaded += bytes.len() as u64;
                    tile.textures.push(bytes);
                }
            }
            FetchEvent::Failed {
                id, error, want, ..
            } => {
                // A tile the server refuses (4xx) will never arrive: the flight cannot
                // complete its square, so it stops with the server's reason. Corrupt or
                // unreachable tiles are asked for again on a later frame.
                if want == Want::Tile && FailureKind::of(&error) == FailureKind::Permanent {
                    return Err(FlightError::TileFailed {
                        id,
                        message: error.to_string(),
                    });
                }
                tracing::warn!(tile = %id, error = %error, "request failed after retries; it will be made again");
            }
        }
        Ok(())
    }

    /// Shares the texture budget, drops levels over it, uploads levels that arrived and
    /// requests the next finer level of tiles under their target. Returns the budget.
    fn share_textures(&mut self, fetcher: &mut Fetcher, frame: u64) -> u64 {
        let Some(r) = &mut self.rendering else {
            return 0;
        };
        let base: u64 = self.base_bytes.iter().sum();
        let coming: u64 = self
            .in_flight
            .iter()
            .zip(&self.expected_bytes)
            .filter(|(f, _)| **f)
            .map(|(_, b)| b)
            .sum();
        let budget = self.pager.memory_limit.saturating_sub(base + coming);
        let mut indices = Vec::new();
        let mut candidates = Vec::new();
        for (i, tile) in self.tiles.iter().enumerate() {
            if tile.is_none() {
                continue;
            }
            indices.push(i);
            candidates.push(TextureCandidate {
                importance: r.importance[i],
                extra_cost: &r.texture_costs[i],
            });
        }
        let targets = share_texture_budget(&candidates, budget);
        // Levels to keep: what each tile holds, unless the held levels together exceed the
        // budget; then the least important tiles drop to their target first. Dropping only
        // when the limit demands it keeps textures from being dropped and fetched again as
        // importances shift from frame to frame.
        let held = |i: usize| self.tiles[i].as_ref().map_or(1, |t| t.textures.len()) as u32 - 1;
        let mut keep: Vec<u32> = indices.iter().map(|&i| held(i)).collect();
        let mut spent: u64 = keep
            .iter()
            .zip(&candidates)
            .map(|(&l, c)| c.extra_cost.get(l as usize).copied().unwrap_or(0))
            .sum();
        if spent > budget {
            let mut by_importance: Vec<usize> = (0..indices.len()).collect();
            by_importance.sort_by(|&a, &b| {
                candidates[a]
                    .importance
                    .total_cmp(&candidates[b].importance)
                    .then(b.cmp(&a))
            });
            for k in by_importance {
                if spent <= budget {
                    break;
                }
                if keep[k] > targets[k] {
                    let cost = &candidates[k].extra_cost;
                    spent -= cost[keep[k] as usize] - cost[targets[k] as usize];
                    keep[k] = targets[k];
                }
            }
        }
        let mut uploads = 0;
        for (k, (&i, &target)) in indices.iter().zip(&targets).enumerate() {
            r.texture_target[i] = target.max(keep[k]);
            let Some(tile) = &mut self.tiles[i] else {
                continue;
            };
            let id = self.manifest.tiles[i].id();
            let kept = keep[k] as usize + 1;
            let mut changed = false;
            if tile.textures.len() > kept {
                // Over the limit: drop the finer levels now.
                for dropped in tile.textures.drain(kept..) {
                    tile.bytes.textures -= dropped.len() as u64;
                }
                changed = true;
            } else if tile.textures.len() < target as usize + 1
                && tile
                    .undecodable_from
                    .is_none_or(|l| tile.textures.len() < l)
            {
                let next = tile.textures.len() as u32;
                let priority = (frame << 20) | (1 << 19) | (candidates.len() as u64 - 1);
                fetcher.request(id, Want::TextureLevel(next), priority);
            }
            if changed {
                // The kept levels are on the GPU already: copy them there.
                r.renderer
                    .coarsen_texture(id, tile.textures.len().min(tile.uploaded_levels) as u32);
                tile.uploaded_levels = tile.uploaded_levels.min(tile.textures.len());
            }
            let decodable = tile
                .textures
                .len()
                .min(tile.undecodable_from.unwrap_or(usize::MAX));
            while tile.uploaded_levels < decodable && uploads < r.config.uploads_per_frame {
                // Only the new level is decoded; the coarser ones are copied on the GPU. If
                // that cannot be done (no level uploaded yet), every level is uploaded.
                let level = tile.uploaded_levels;
                let Some(image) = decode_texture(&tile.textures[level], id, level as u32) else {
                    for dropped in tile.textures.drain(level..) {
                        tile.bytes.textures -= dropped.len() as u64;
                    }
                    tile.undecodable_from = Some(level);
                    break;
                };
                if !r.renderer.refine_texture(id, level as u32, &image) {
                    let images: Option<Vec<image::RgbaImage>> = tile.textures[..=level]
                        .iter()
                        .enumerate()
                        .map(|(l, b)| decode_texture(b, id, l as u32))
                        .collect();
                    let Some(images) = images else {
                        break;
                    };
                    r.renderer.upload_texture(id, level as u32, &images);
                }
                tile.uploaded_levels = level + 1;
                uploads += 1;
            }
            tile.bytes.gpu = r.renderer.tile_bytes(id);
        }
        budget
    }

    /// Plans and renders a frame seen from `camera` into `target`, then feeds its time to
    /// the frame-rate controller. `frame_started` is when the frame began (its update
    /// included), so the controller sees the whole frame. `None` when not rendering.
    pub fn draw(
        &mut self,
        target: &wgpu::TextureView,
        camera: &Camera,
        frame_started: Instant,
    ) -> Option<DrawReport> {
        let r = self.rendering.as_mut()?;
        let started = Instant::now();
        let size = target.texture().size();
        let candidates: Vec<Candidate> = self
            .tiles
            .iter()
            .zip(&self.manifest.tiles)
            .zip(&self.error_minima)
            .filter(|((t, _), _)| t.is_some())
            .map(|((_, record), minima)| Candidate::new(record, minima))
            .collect();
        let input = MethodInput {
            camera,
            viewport: [size.width, size.height],
            layout: &self.layout,
            tiles: &candidates,
            budget: r.controller.budget(),
        };
        let out = r.method.draw(&input, &mut r.renderer, target);
        let (plan, stats, lod_ms) = (out.plan, out.stats, out.lod_ms);
        r.importance.fill(0.0);
        let columns = self.manifest.grid.columns as usize;
        for (d, &imp) in plan.draws.iter().zip(&plan.importances) {
            r.importance[d.id.y as usize * columns + d.id.x as usize] = imp;
        }
        let draw_ms = started.elapsed().as_secs_f64() * 1e3;
        let frame_s = frame_started.elapsed().as_secs_f64();
        r.controller
            .next_budget(u32::try_from(stats.triangles).unwrap_or(u32::MAX), frame_s);
        Some(DrawReport {
            triangles_needed: plan.triangles_needed,
            method: r.method.name(),
            plan,
            stats,
            lod_ms,
            draw_ms,
        })
    }

    /// Height of the nearest sample under `position`, if its tile is resident.
    pub fn ground_under(&self, position: [f64; 3]) -> Option<f64> {
        let extent = self.layout.tile_extent_m();
        let cells = f64::from(self.layout.tile_size - 1);
        let (tx, ty) = (position[0] / extent[0], position[1] / extent[1]);
        if tx < 0.0
            || ty < 0.0
            || tx >= f64::from(self.manifest.grid.columns)
            || ty >= f64::from(self.manifest.grid.rows)
        {
            return None;
        }
        let tile = self.tiles[self.index(TileId::new(tx as u32, ty as u32))].as_ref()?;
        let x = ((tx - tx.floor()) * cells).round() as usize;
        let y = ((ty - ty.floor()) * cells).round() as usize;
        Some(tile.heights.metres(x, y))
    }
}

impl Rendering {
    /// MapBlocks on or off as the method wants, and the texture costs that follow (a block
    /// texture copies its tiles' textures).
    fn set_texture_blocks(&mut self, manifest: &Manifest) {
        let blocks = self.config.uses_texture_blocks();
        self.renderer.set_texture_blocks(blocks.then(|| {
            crate::render::blocks::BlockLayout::new(
                [manifest.grid.columns, manifest.grid.rows],
                manifest
                    .texture
                    .level_size(manifest.texture.levels.saturating_sub(1)),
                self.config
                    .texture_block_limit
                    .unwrap_or(self.renderer.max_texture_side()),
            )
        }));
        let copies = self.config.texture_copies();
        self.texture_costs = manifest
            .tiles
            .iter()
            .map(|t| extra_costs(manifest, t, copies))
            .collect();
    }
}

/// Decodes one texture level; a level that does not decode is logged and left out (the
/// tile keeps its coarser texture: its hash was verified, so this is a format the client
/// cannot read, not a transfer error).
fn decode_texture(bytes: &[u8], id: TileId, level: u32) -> Option<image::RgbaImage> {
    match image::load_from_memory(bytes) {
        Ok(image) => Some(image.into_rgba8()),
        Err(e) => {
            tracing::warn!(tile = %id, level, error = %e, "texture level does not decode");
            None
        }
    }
}

/// What a tile holds once resident at its coarsest texture, known from the manifest before
/// it is fetched: decoded codes and the coarsest level's bytes, plus, when rendering, its GPU
/// samples (8 bytes each) and the coarsest level as RGBA, `gpu_texture_copies` times
/// ([`RenderConfig::texture_copies`]; 0 when not rendering: no GPU bytes at all).
pub fn expected_tile_bytes(
    manifest: &Manifest,
    tile: &terrain_shared::TileRecord,
    gpu_texture_copies: u64,
) -> TileBytes {
    let samples = u64::from(manifest.tile_size).pow(2);
    TileBytes {
        decoded_heights: samples * std::mem::size_of::<i32>() as u64,
        textures: tile.texture.first().map_or(0, |level| level.bytes),
        vertices: 0,
        gpu: if gpu_texture_copies > 0 {
            samples * size_of::<terrain_shaders::Sample>() as u64
                + gpu_texture_copies * coarsest_rgba_bytes(manifest)
        } else {
            0
        },
    }
}

/// GPU bytes of a tile's coarsest texture level as RGBA.
fn coarsest_rgba_bytes(manifest: &Manifest) -> u64 {
    u64::from(manifest.texture.level_size(0)).pow(2) * 4
}
