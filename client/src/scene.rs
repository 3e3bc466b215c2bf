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
//! when rendering, its GPU samples and texture and what the method holds for it. What the
//! method may hold for no tile in particular ([`LodMethod::reserved_bytes`]) comes off the
//! limit first; the pager admits a belt, the current tile's too, only if it fits at the
//! coarsest texture; finer levels are paid from what is left; what a frame's draw made past
//! the reservation comes off at its end ([`Scene::draw`]). The invariant
//! ([`crate::memory::MEMORY_INVARIANT`]):
//!
//! At the end of every frame, the bytes the client holds for the terrain (every resident
//! tile's heights, textures and GPU copies, and all the drawing method holds, CPU and GPU)
//! are at most the memory limit, `--limit-percent` (90 by default) of `--memory`. There is
//! no exception: a limit too small for what the method reserves plus the coarsest level of
//! the pyramid held whole (with one level, its largest tile) is refused at start with the
//! least `--memory` that would do. The limit does not cover the program, its render targets
//! and pipelines, or the graphics driver's own memory; a flight reports them beside it
//! (heap, GPU allocations, resident set).

use crate::lod::budget::{BudgetMode, FrameCost, FrameRateController};
use crate::lod::plan::{Candidate, FramePlan, Layout, LodSettings};
use crate::memory::{LeastLimit, TileBytes};
use crate::method::{self, CrackFiller, LodMethod, MethodConfig, MethodInput, MethodKind};
use crate::page::{self, Decision, PagerConfig, PagerView};
use crate::render::textures::{TextureCandidate, extra_costs, share_texture_budget};
use crate::render::{Camera, Gpu, RenderStats, Renderer};
use crate::requests::{FailureKind, FetchEvent, Fetcher, Want};
use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::{Duration, Instant};
use terrain_shared::{Manifest, TileId};

/// Requests of one tile that may fail (each after the fetcher's own retries) before the
/// tile is given up: with a corrupt body fetched twice a request, a tile that is bad at the
/// source costs 8 GETs, not one every frame for the rest of the flight.
pub const TILE_REQUESTS_BEFORE_GIVING_UP: u32 = 4;
/// Wait before a failed tile is asked for again; it doubles with each failure (1, 2, 4 s),
/// so a server restarting is waited for and a bad tile is given up some 7 s after it
/// first failed.
pub const TILE_RETRY_DELAY: Duration = Duration::from_secs(1);

/// One level's paging in a frame.
#[derive(Debug, Clone)]
pub struct LevelDecision {
    pub level: u32,
    /// The level's grid and its share of the limit ([`page::level_shares`]).
    pub pager: PagerConfig,
    /// Its decision; its tile ids are of level 0 numbering, `level` says which level.
    pub decision: Decision,
}

/// Why a scene cannot go on.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The server refused a tile (4xx): it will never arrive, so the square of belts can
    /// never complete.
    #[error("tile {id} failed: {message}")]
    TileFailed { id: TileId, message: String },
}

/// How a scene renders.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderConfig {
    pub method: MethodKind,
    pub lod: LodSettings,
    pub filler: CrackFiller,
    pub budget: BudgetMode,
    /// Texture uploads at most per frame, so that a burst of arrivals cannot stall one.
    pub uploads_per_frame: usize,
    /// For methods drawing with MapBlocks ([`MethodConfig::uses_texture_blocks`]): the
    /// largest block texture side, texels (`None`: the adapter's limit).
    pub texture_block_limit: Option<u32>,
    /// Whether those methods use MapBlocks at all (`false`: every tile with its own
    /// texture, for comparison).
    pub texture_blocks: bool,
    /// Give the method only the tiles of the square of complete belts (the strip-mask
    /// paper's rendering); `false` (the default) gives it every resident tile: cached ones
    /// outside the square and those of a belt still arriving.
    pub square_only: bool,
    /// The projected grids' size and options.
    pub grid: crate::method::GridSettings,
}

impl RenderConfig {
    /// What the method is built and configured with.
    pub fn method_config(&self) -> MethodConfig {
        MethodConfig {
            kind: self.method,
            lod: self.lod,
            filler: self.filler,
            texture_blocks: self.texture_blocks,
            grid: self.grid,
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
            square_only: false,
            grid: crate::method::GridSettings::default(),
        }
    }
}

/// A tile held in memory.
#[derive(Debug, Clone)]
struct ResidentTile {
    /// Shared with the renderer, which makes samples of them when it draws the tile.
    heights: Arc<terrain_shared::Heights>,
    /// Suffix minima of its per-mask errors against the full-resolution surface
    /// ([`crate::lod::needed`]): from its tile blob.
    error_minima: Vec<f32>,
    /// Hash and size of each texture level, coarsest first: from its tile blob.
    texture_blobs: Vec<terrain_shared::Blob>,
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
    /// Level 0's decision (the full-resolution square).
    pub decision: Decision,
    /// Every paged level's decision, level 0 first, with its share of the limit.
    pub levels: Vec<LevelDecision>,
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
    /// Time from the start of the draw to its submission (and to the GPU's completion with
    /// [`Scene::wait_for_each_frame`]; otherwise it includes the wait for the frame before).
    pub draw_ms: f64,
    /// The fewest triangles that keep every drawn tile's projected error within
    /// [`LodSettings::max_error_px`] ([`crate::lod::needed`]).
    pub triangles_needed: u64,
    /// The method that drew, e.g. `strip-masks/planar-shadow`.
    pub method: String,
    /// The frame's wall time, from the `frame_started` given to [`Scene::draw`] to the end
    /// of its draw (its wait for the frame before it included): what the frame-rate
    /// controller measures.
    pub frame_ms: f64,
    /// What the frame-rate controller expected the frame to take, at the rate it had
    /// measured before it (`None` before its first measurement, or when no target applies).
    pub predicted_ms: Option<f64>,
    /// The frame rate the controller aims for: `None` with a fixed budget, or with a method
    /// that shares no triangle budget ([`method::LodMethod::uses_budget`]).
    pub target_fps: Option<f64>,
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
    /// Per-tile error tables: the manifest's strip-mask errors and what the method holds
    /// on the CPU (its tables, strips).
    pub cpu_lod: u64,
    /// Pooled sample buffers (only tiles drawn lately hold one) and textures.
    pub gpu: crate::render::GpuResidency,
    /// The method's GPU bytes (index sets, buffers of its own).
    pub method_gpu: u64,
}

impl GeometryMemory {
    /// Geometry bytes: heights, error tables, sample buffers and the method's GPU bytes.
    pub fn bytes(&self) -> u64 {
        self.cpu_heights + self.cpu_lod + self.gpu.sample_bytes + self.method_gpu
    }

    /// [`GeometryMemory::bytes`] per resident sample.
    pub fn per_sample(&self) -> f64 {
        self.bytes() as f64 / self.samples.max(1) as f64
    }

    /// GPU geometry per resident sample (the samples held on the GPU and the method's index
    /// sets and buffers) if every resident tile held its samples there: the most the GPU
    /// keeps for this resident set, what the strip-mask paper counts.
    pub fn gpu_per_sample_all_held(&self) -> f64 {
        let per_slot = self
            .gpu
            .sample_bytes
            .checked_div(self.gpu.sample_buffers)
            .unwrap_or(0);
        (per_slot * self.gpu.tiles + self.method_gpu) as f64 / self.samples.max(1) as f64
    }
}

impl std::fmt::Display for GeometryMemory {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let per = |b: u64| b as f64 / self.samples.max(1) as f64;
        write!(
            f,
            "{:.2} B/sample: heights {:.2}, error tables {:.3}, GPU samples {:.2} ({} of {} tiles hold a buffer), method GPU (index sets) {:.3}; GPU geometry {:.2} B/sample, {:.2} with every resident tile's samples held",
            self.per_sample(),
            per(self.cpu_heights),
            per(self.cpu_lod),
            per(self.gpu.sample_bytes),
            self.gpu.sample_buffers,
            self.gpu.tiles,
            per(self.method_gpu),
            per(self.gpu.sample_bytes + self.method_gpu),
            self.gpu_per_sample_all_held(),
        )
    }
}

/// The rendering half of a scene.
#[derive(Debug)]
struct Rendering {
    renderer: Renderer,
    method: Box<dyn LodMethod>,
    /// Method data asked of the fetcher and not yet arrived.
    data_pending: HashSet<(TileId, u32)>,
    controller: FrameRateController,
    config: RenderConfig,
    /// Whether each frame is waited for ([`Scene::wait_for_each_frame`]).
    wait_for_gpu: bool,
    /// The terrain's GPU allocations after the last frame (the tiles' epoch and the method's
    /// GPU bytes): a frame after which they changed waits for the GPU.
    allocations: ((u64, u64, u64), u64),
    /// Target texture level per tile (index as `tiles`), from the last texture budget.
    texture_target: Vec<u32>,
    /// Importance per tile in the last planned frame (0 when not visible).
    importance: Vec<f64>,
    /// Per tile, the extra bytes of each texture level ([`extra_costs`]), from its tile
    /// blob (empty while not resident).
    texture_costs: Vec<Vec<u64>>,
    /// Pixels of the frames it draws: what the method's reservation depends on
    /// ([`LodMethod::reserved_bytes`]); set by [`Scene::set_viewport`], or by a draw into a
    /// target of another size.
    viewport: [u32; 2],
}

/// A tile whose requests failed: when it may be asked for again.
#[derive(Debug, Clone)]
struct TileFailures {
    failures: u32,
    retry_at: Instant,
}

/// A tile the scene stopped asking for, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnavailableTile {
    pub id: TileId,
    /// Requests that failed.
    pub failures: u32,
    /// The last failure, with its whole cause chain.
    pub error: String,
}

/// What [`Scene::replace_manifest`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reconciled {
    /// Same grid: resident tiles whose blobs are unchanged stay, the others were dropped.
    Kept { kept: u64, dropped: u64 },
    /// The grid changed shape (tiles, tile size, raster, spacing or texture levels): the
    /// scene cannot hold the new tiles, and a new one must be made.
    Reshaped,
}

/// Resident tiles, paging, and optionally rendering. See the module documentation.
#[derive(Debug)]
pub struct Scene {
    manifest: Arc<Manifest>,
    layout: Layout,
    /// Level 0's grid and the whole limit; each level's share is worked out per frame.
    pager: PagerConfig,
    /// Levels paged and drawn: 1 is level 0 alone (the strip-mask paper's single
    /// resolution), the manifest's level count the whole pyramid.
    levels_used: u32,
    /// How the levels share the limit.
    level_policy: page::LevelPolicy,
    /// Per tile of every level (the manifest's dense order), as below.
    tiles: Vec<Option<ResidentTile>>,
    /// Bytes per tile at the coarsest texture (what the pager sees).
    base_bytes: Vec<u64>,
    expected_bytes: Vec<u64>,
    in_flight: Vec<bool>,
    pub tiles_fetched: u64,
    pub evicted_unused_bytes: u64,
    /// Per tile, whether it is in the square of complete belts (as of the last update).
    in_square: Vec<bool>,
    rendering: Option<Rendering>,
    /// Tiles whose requests failed and that are waiting to be asked for again.
    failing: HashMap<TileId, TileFailures>,
    /// Tiles given up, in the order they were.
    pub unavailable: Vec<UnavailableTile>,
    /// Tile requests made again after one failed (each made at least one GET).
    pub requests_repeated: u64,
}

/// A server's manifest and the fetcher that streams its tiles: what [`Scene::connect`]
/// gives, and what every scene is made from.
#[derive(Debug)]
pub struct Connection {
    pub manifest: Arc<Manifest>,
    pub fetcher: Fetcher,
}

impl Connection {
    /// A scene of the manifest's tiles holding at most `memory_limit` bytes (the pager's
    /// limit), making the nearest tile current from off the terrain unless told not to;
    /// with `render`, drawn by its GPU into targets of its format.
    pub fn scene(
        &self,
        memory_limit: u64,
        nearest_when_outside: bool,
        render: Option<(Gpu, wgpu::TextureFormat, RenderConfig)>,
    ) -> Scene {
        let grid = self.manifest.grid(0);
        let pager = PagerConfig {
            columns: grid.columns,
            rows: grid.rows,
            memory_limit,
            nearest_when_outside,
            current_over_limit: true,
        };
        Scene::new(Arc::clone(&self.manifest), pager, render)
    }
}

impl Scene {
    /// The one way to a server: fetches its manifest (checked) and makes the fetcher that
    /// streams its tiles with `config`, its requests running on `runtime` (which needs its
    /// time driver: backoff sleeps there).
    pub async fn connect(
        server: &str,
        config: crate::requests::FetcherConfig,
        runtime: tokio::runtime::Handle,
    ) -> Result<Connection, crate::http_client::FetchError> {
        let client = crate::http_client::TileClient::new(server)?
            .with_max_manifest_bytes(config.max_manifest_bytes);
        let manifest = Arc::new(crate::requests::fetch_manifest(&client, &config).await?);
        let fetcher = Fetcher::new(client, Arc::clone(&manifest), config, runtime);
        Ok(Connection { manifest, fetcher })
    }

    /// A scene of `manifest`'s tiles paged by `pager`; with `render`, drawn by `gpu` into
    /// targets of `format`.
    pub fn new(
        manifest: Arc<Manifest>,
        pager: PagerConfig,
        render: Option<(Gpu, wgpu::TextureFormat, RenderConfig)>,
    ) -> Scene {
        let count = manifest.tile_count();
        let layout = Layout::of(&manifest);
        let rendering = render.map(|(gpu, format, config)| {
            let renderer = Renderer::new(&gpu, format, layout);
            let method = build_method(&renderer, &manifest, &config);
            let mut r = Rendering {
                renderer,
                method,
                data_pending: HashSet::new(),
                controller: FrameRateController::new(
                    config.budget,
                    crate::render::frame::FRAMES_IN_FLIGHT as usize,
                ),
                config,
                wait_for_gpu: false,
                allocations: Default::default(),
                texture_target: vec![0; count],
                importance: vec![0.0; count],
                texture_costs: vec![Vec::new(); count],
                viewport: [1, 1],
            };
            r.set_texture_blocks(&manifest);
            r
        });
        let expected_bytes = manifest
            .tiles()
            .map(|(_, t)| match &rendering {
                Some(r) => r.expected_tile_bytes(&manifest, t).total(),
                None => expected_tile_bytes(&manifest, t, 0).total(),
            })
            .collect();
        Scene {
            expected_bytes,
            layout,
            pager,
            levels_used: manifest.level_count(),
            level_policy: page::LevelPolicy::default(),
            tiles: vec![None; count],
            base_bytes: vec![0; count],
            in_flight: vec![false; count],
            tiles_fetched: 0,
            evicted_unused_bytes: 0,
            in_square: vec![false; count],
            rendering,
            manifest,
            failing: HashMap::new(),
            unavailable: Vec::new(),
            requests_repeated: 0,
        }
    }

    /// Takes `manifest`, a newer one of the same server (its database was rebuilt), in
    /// place of the scene's. With the same grid, resident tiles whose heights and held
    /// texture levels have the same hashes stay; the others are dropped, to be fetched
    /// again from the new content; the method is built again for the new manifest. A grid
    /// of another shape cannot be taken: [`Reconciled::Reshaped`], and nothing changes.
    pub fn replace_manifest(&mut self, manifest: Arc<Manifest>) -> Reconciled {
        let old = &self.manifest;
        let same_shape = old.levels.len() == manifest.levels.len()
            && old
                .levels
                .iter()
                .zip(&manifest.levels)
                .all(|(a, b)| a.grid == b.grid && a.raster == b.raster)
            && old.tile_size == manifest.tile_size
            && old.spacing_m == manifest.spacing_m
            && old.mask_levels == manifest.mask_levels
            && old.texture.size == manifest.texture.size
            && old.texture.levels == manifest.texture.levels
            && old.texture.format == manifest.texture.format;
        if !same_shape {
            return Reconciled::Reshaped;
        }
        let (mut kept, mut dropped) = (0, 0);
        let changed: Vec<TileId> = self
            .manifest
            .tiles()
            .zip(manifest.tiles())
            .zip(&self.tiles)
            .filter(|(_, tile)| tile.is_some())
            .filter_map(|(((id, before), (_, after)), _)| {
                // The tile blob's hash covers its heights, its errors and its textures'
                // hashes: the same hash, the same tile.
                if before.hash == after.hash {
                    kept += 1;
                    None
                } else {
                    dropped += 1;
                    Some(id)
                }
            })
            .collect();
        for id in changed {
            self.drop_tile(id);
        }
        self.manifest = Arc::clone(&manifest);
        self.layout = Layout::of(&manifest);
        self.failing.clear();
        self.unavailable.clear();
        match &self.rendering {
            Some(r) => {
                let method = build_method(&r.renderer, &manifest, &r.config);
                // Teaches the method the kept tiles and recounts every tile's bytes and
                // what the pager expects of each.
                self.install(method);
            }
            None => {
                for (expected, (_, record)) in self.expected_bytes.iter_mut().zip(manifest.tiles())
                {
                    *expected = expected_tile_bytes(&manifest, record, 0).total();
                }
            }
        }
        Reconciled::Kept { kept, dropped }
    }

    /// Pages and draws level 0 alone (`false`: the strip-mask paper's single resolution,
    /// what a one-level database does anyway) or the whole pyramid (`true`, the default).
    /// Tiles of the levels left out are dropped.
    pub fn use_levels(&mut self, all: bool) {
        self.levels_used = if all { self.manifest.level_count() } else { 1 };
        let coarser: Vec<TileId> = self
            .manifest
            .tiles()
            .zip(&self.tiles)
            .filter(|((id, _), tile)| id.level >= self.levels_used && tile.is_some())
            .map(|((id, _), _)| id)
            .collect();
        for id in coarser {
            self.drop_tile(id);
        }
    }

    /// Shares the limit between the levels by `policy` from the next update on.
    pub fn set_level_policy(&mut self, policy: page::LevelPolicy) {
        self.level_policy = policy;
    }

    /// Levels paged and drawn (see [`Scene::use_levels`]).
    pub fn levels_used(&self) -> u32 {
        self.levels_used
    }

    /// Drops resident tile `id`, everywhere it is held.
    fn drop_tile(&mut self, id: TileId) {
        let Some(i) = self.manifest.index(id) else {
            return;
        };
        if let Some(tile) = self.tiles[i].take()
            && !tile.used
        {
            self.evicted_unused_bytes += tile.downloaded;
        }
        self.base_bytes[i] = 0;
        if let Some(r) = &mut self.rendering {
            r.texture_costs[i] = Vec::new();
            r.renderer.tiles.remove_tile(id);
            r.method.tile_evicted(id);
            r.data_pending.retain(|(tile, _)| *tile != id);
        }
    }

    /// Frames will be `size` pixels (width, height): what the method's reservation is
    /// worked out for ([`LodMethod::reserved_bytes`]; a draw into a target of another size
    /// sets it too). Nothing happens without rendering.
    pub fn set_viewport(&mut self, size: [u32; 2]) {
        if let Some(r) = &mut self.rendering {
            r.viewport = size;
        }
    }

    /// Makes `limit` the memory limit from the next frame on.
    pub fn set_memory_limit(&mut self, limit: u64) {
        self.pager.memory_limit = limit;
    }

    /// The least memory limit under which this scene draws anything and holds its limit:
    /// what the method reserves for frames of the viewport ([`Scene::set_viewport`]) and the
    /// coarsest level used, held whole (with one level, the largest tile: the current
    /// tile must fit). A flight, a window or a benchmark refuses a smaller limit at start.
    pub fn least_limit(&self) -> LeastLimit {
        let coarsest = self.levels_used.saturating_sub(1);
        let start = self.manifest.level_offset(coarsest);
        let level = &self.expected_bytes
            [start..start + self.manifest.levels[coarsest as usize].tiles.len()];
        LeastLimit {
            method_bytes: self.reserve(),
            tiles_bytes: if self.levels_used > 1 {
                level.iter().sum()
            } else {
                level.iter().copied().max().unwrap_or(0)
            },
            whole_level: self.levels_used > 1,
        }
    }

    /// The largest number of bytes one tile will hold once resident, and that tile: what
    /// a memory limit must at least allow.
    pub fn largest_tile(&self) -> Option<(TileId, u64)> {
        self.expected_bytes
            .iter()
            .zip(self.manifest.tiles())
            .map(|(&bytes, (id, _))| (id, bytes))
            .max_by_key(|&(_, bytes)| bytes)
    }

    /// Position of `id` in the dense per-tile vectors (`usize::MAX`, which no vector
    /// holds, for a tile outside the grids: `get` then finds nothing).
    fn index(&self, id: TileId) -> usize {
        self.manifest.index(id).unwrap_or(usize::MAX)
    }

    /// Bytes the scene holds for the terrain, as the memory limit counts them: every
    /// resident tile's (heights, encoded textures, what the method holds for it, its GPU
    /// samples and texture copies as charged) and the method's shared bytes (index sets,
    /// buffers of its own). The pager and the texture budget keep this under the limit.
    pub fn resident_bytes(&self) -> u64 {
        let tiles: u64 = self.tiles.iter().flatten().map(|t| t.bytes.total()).sum();
        tiles
            + self
                .rendering
                .as_ref()
                .map_or(0, |r| r.method.shared_bytes().total())
    }

    /// Measures of the last frame only the method knows ([`LodMethod::frame_measures`]);
    /// waits for the GPU. Empty without rendering.
    pub fn method_measures(&mut self) -> Vec<(&'static str, f64)> {
        self.rendering.as_mut().map_or_else(Vec::new, |r| {
            let gpu = r.renderer.gpu().clone();
            r.method.frame_measures(&gpu)
        })
    }

    /// Bytes of every GPU allocation held for the terrain now (labelled
    /// [`crate::render::tiles::TERRAIN_LABEL`]): pooled sample buffers, tile textures,
    /// MapBlock textures, and the method's own (index sets, buffers). 0 without rendering.
    pub fn gpu_bytes(&self) -> u64 {
        self.rendering.as_ref().map_or(0, |r| {
            r.renderer.tiles.residency().total() + r.method.gpu_bytes()
        })
    }

    /// Bytes the scene holds on the CPU for the terrain: heights, encoded textures, and
    /// what the method holds there.
    pub fn cpu_bytes(&self) -> u64 {
        let tiles: u64 = self
            .tiles
            .iter()
            .flatten()
            .map(|t| t.bytes.decoded_heights + t.bytes.textures)
            .sum();
        let method = self.rendering.as_ref().map_or(0, |r| {
            let per_tile: u64 = self.tiles.iter().flatten().map(|t| t.bytes.method).sum();
            (per_tile + r.method.shared_bytes().total()).saturating_sub(r.method.gpu_bytes())
        });
        tiles + method
    }

    /// The decoded heights of resident tile `id`; `None` when it is not resident.
    pub fn tile_heights(&self, id: TileId) -> Option<&terrain_shared::Heights> {
        self.tiles
            .get(self.index(id))?
            .as_ref()
            .map(|t| t.heights.as_ref())
    }

    /// The manifest of the terrain.
    pub fn manifest(&self) -> &Arc<Manifest> {
        &self.manifest
    }

    /// The device the scene renders with, if it renders.
    pub fn gpu(&self) -> Option<&Gpu> {
        self.rendering.as_ref().map(|r| r.renderer.gpu())
    }

    /// Finest texture level resident tile `id` holds on the GPU.
    pub fn texture_level(&self, id: TileId) -> Option<u32> {
        self.rendering
            .as_ref()
            .and_then(|r| r.renderer.tiles.texture_level(id))
    }

    /// What the scene keeps for its geometry now (see [`GeometryMemory`]).
    pub fn geometry_memory(&self) -> GeometryMemory {
        let resident = self.tiles.iter().flatten();
        GeometryMemory {
            samples: self.resident_tiles() * u64::from(self.manifest.tile_size).pow(2),
            cpu_heights: resident.map(|t| t.bytes.decoded_heights).sum(),
            cpu_lod: self
                .tiles
                .iter()
                .flatten()
                .map(|t| 4 * t.error_minima.len() as u64)
                .sum::<u64>()
                + self.rendering.as_ref().map_or(0, |r| {
                    let per_tile: u64 = self.tiles.iter().flatten().map(|t| t.bytes.method).sum();
                    per_tile + r.method.shared_bytes().cpu
                }),
            gpu: self
                .rendering
                .as_ref()
                .map_or_else(Default::default, |r| r.renderer.tiles.residency()),
            method_gpu: self.rendering.as_ref().map_or(0, |r| r.method.gpu_bytes()),
        }
    }

    /// Whether tile `id` (of any level) is resident.
    pub fn is_resident(&self, id: TileId) -> bool {
        self.tiles.get(self.index(id)).is_some_and(Option::is_some)
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
    /// starts the frame-rate controller again. Resident tiles stay. Nothing happens without
    /// rendering.
    pub fn reconfigure(&mut self, config: RenderConfig) {
        let Some(r) = &mut self.rendering else {
            return;
        };
        let method = (config.method != r.config.method)
            .then(|| build_method(&r.renderer, &self.manifest, &config));
        if method.is_none() {
            // Same method: new settings, and whatever it learnt of the tiles stays.
            r.method.configure(&config.method_config());
        }
        if config.budget != r.config.budget {
            r.controller = FrameRateController::new(
                config.budget,
                crate::render::frame::FRAMES_IN_FLIGHT as usize,
            );
        }
        r.config = config;
        match method {
            Some(method) => self.install(method),
            None => self.recount(),
        }
    }

    /// Draws later frames with the method `make` builds (one of the scene's configuration's
    /// kind, or any other [`LodMethod`]). Resident tiles stay; the method learns them.
    /// Nothing happens without rendering.
    pub fn use_method(&mut self, make: impl FnOnce(&method::Build<'_>) -> Box<dyn LodMethod>) {
        let Some(r) = &self.rendering else {
            return;
        };
        let method = make(&method::Build {
            gpu: r.renderer.gpu(),
            format: r.renderer.format(),
            frame_layout: r.renderer.frame_bind_group_layout(),
            manifest: &self.manifest,
        });
        self.install(method);
    }

    /// Makes `method` the scene's, teaching it the resident tiles.
    fn install(&mut self, method: Box<dyn LodMethod>) {
        let Some(r) = &mut self.rendering else {
            return;
        };
        r.method = method;
        r.data_pending.clear();
        let gpu = r.renderer.gpu().clone();
        for ((id, _), tile) in self.manifest.tiles().zip(&self.tiles) {
            if let Some(tile) = tile {
                r.method.tile_resident(&gpu, id, &tile.heights);
            }
        }
        self.recount();
    }

    /// MapBlocks as the configuration wants, and what each tile is charged and the pager
    /// expects of each, after a change of method or settings.
    fn recount(&mut self) {
        let Some(r) = &mut self.rendering else {
            return;
        };
        r.set_texture_blocks(&self.manifest);
        let copies = r.config.method_config().texture_copies();
        // What each tile is charged, and what the pager expects of each, follow the method
        // and the copies of each GPU texture.
        for (i, ((id, record), tile)) in self.manifest.tiles().zip(&mut self.tiles).enumerate() {
            self.expected_bytes[i] = r.expected_tile_bytes(&self.manifest, record).total();
            if let Some(tile) = tile {
                r.texture_costs[i] = extra_costs(&self.manifest, &tile.texture_blobs, copies);
                tile.bytes.gpu = r.renderer.tiles.tile_bytes(id);
                tile.bytes.method = r.method.tile_bytes(id);
                self.base_bytes[i] = r.base_bytes(&self.manifest, record, tile);
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

    /// Makes [`Scene::draw`] wait for each frame to finish on the GPU, so that its
    /// [`DrawReport::draw_ms`] and GPU time are that frame's: for measurements (the
    /// evaluation). Off by default: a flight or a window never waits for its frames.
    pub fn wait_for_each_frame(&mut self, wait: bool) {
        if let Some(r) = &mut self.rendering {
            r.wait_for_gpu = wait;
        }
    }

    /// The last frame's depth buffer (see [`Renderer::read_depth`]).
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
        let method_done = self
            .rendering
            .as_ref()
            .is_none_or(|r| r.data_pending.is_empty() && r.method.settled());
        self.in_flight.iter().all(|f| !f) && textures_done && method_done
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
        let grid = self.manifest.grid(0);
        let (columns, rows) = (grid.columns, grid.rows);
        let tx = ((sx / cells).floor() as u32).min(columns.saturating_sub(1));
        let ty = ((sy / cells).floor() as u32).min(rows.saturating_sub(1));
        let (u, v) = (sx - f64::from(tx) * cells, sy - f64::from(ty) * cells);
        if u > cells || v > cells {
            return None;
        }
        let tile = self.tiles.get(self.index(TileId::new(tx, ty)))?.as_ref()?;
        let last = self.layout.tile_size as usize - 1;
        let (c0, r0) = (
            (u.floor() as usize).min(last - 1),
            (v.floor() as usize).min(last - 1),
        );
        let (fu, fv) = (u - c0 as f64, v - r0 as f64);
        let h = |c: usize, r: usize| tile.heights.metres(c, r);
        Some(terrain_shared::mask::cell_height(
            h(c0, r0),
            h(c0 + 1, r0),
            h(c0, r0 + 1),
            h(c0 + 1, r0 + 1),
            fu,
            fv,
        ))
    }

    /// Deliveries, paging and the texture budget for a viewpoint at `position` (metres).
    pub fn update(
        &mut self,
        fetcher: &mut Fetcher,
        frame: u64,
        position: [f64; 3],
    ) -> Result<Update, SceneError> {
        for event in fetcher.poll() {
            self.deliver(event)?;
        }
        fetcher.mark_pending(&mut self.in_flight, &self.manifest);
        // A resident tile waiting for a finer texture is not "in flight" for the pager.
        for (flag, tile) in self.in_flight.iter_mut().zip(&self.tiles) {
            *flag &= tile.is_none();
        }
        // What the method holds, or may hold, for no tile in particular comes off the
        // tiles' share, and what is left is shared between the levels.
        let limit = self.pager.memory_limit.saturating_sub(self.reserve());
        let ranges: Vec<std::ops::Range<usize>> = (0..self.levels_used)
            .map(|k| {
                let start = self.manifest.level_offset(k);
                start..start + self.manifest.levels[k as usize].tiles.len()
            })
            .collect();
        let whole: Vec<u64> = ranges
            .iter()
            .map(|r| self.expected_bytes[r.clone()].iter().sum())
            .collect();
        let shares = page::shares_by(self.level_policy, limit, &whole);
        let now = Instant::now();
        self.in_square.fill(false);
        let mut levels = Vec::with_capacity(ranges.len());
        for (k, range) in ranges.into_iter().enumerate() {
            let level = k as u32;
            let grid = self.manifest.grid(level);
            // The paper's pager fetches the current tile even when it alone takes the
            // resident bytes over the limit. Here no level does: a current tile that does
            // not fit waits while cached belts are dropped to make room, so the limit holds
            // on every frame. A limit too small for the coarsest level used, which is held
            // whole, is refused at start ([`Scene::least_limit`]).
            let pager = PagerConfig {
                columns: grid.columns,
                rows: grid.rows,
                memory_limit: shares[k],
                current_over_limit: false,
                ..self.pager
            };
            let extent = self.layout.tile_extent_m_at(level);
            let view = PagerView {
                viewpoint: [position[0] / extent[0], position[1] / extent[1]],
                resident_bytes: &self.base_bytes[range.clone()],
                in_flight: &self.in_flight[range.clone()],
                expected_bytes: Some(&self.expected_bytes[range.clone()]),
            };
            let decision = page::decide(&pager, &view);
            let tag = |ids: &[TileId]| -> Vec<TileId> {
                ids.iter().map(|id| id.with_level(level)).collect()
            };
            fetcher.cancel(&tag(&decision.cancel));
            let evict = tag(&decision.evict);
            fetcher.cancel(&evict);
            for id in evict {
                self.drop_tile(id);
            }
            for (rank, id) in tag(&decision.fetch).into_iter().enumerate() {
                // A tile that failed waits out its delay; one given up is not asked for again.
                if let Some(failing) = self.failing.get(&id) {
                    if failing.failures >= TILE_REQUESTS_BEFORE_GIVING_UP || now < failing.retry_at
                    {
                        continue;
                    }
                    self.requests_repeated += 1;
                }
                // Earlier frames' requests go first; within a frame, coarser levels first
                // (they cover the most screen), then the pager's order.
                let order = (u64::from(self.levels_used - level) << 16) | rank as u64;
                fetcher.request(id, Want::Tile, (frame << 20) | order.min((1 << 18) - 1));
                if let Some(i) = self.manifest.index(id) {
                    self.in_flight[i] = true;
                }
            }
            for id in page::square_tiles(&pager, decision.current, decision.complete_belts) {
                let i = self.index(id.with_level(level));
                if let Some(flag) = self.in_square.get_mut(i) {
                    *flag = true;
                }
                if let Some(Some(tile)) = self.tiles.get_mut(i) {
                    tile.used = true;
                }
            }
            levels.push(LevelDecision {
                level,
                pager,
                decision,
            });
        }
        let decision = levels
            .first()
            .map(|l| l.decision.clone())
            .unwrap_or_else(|| {
                page::decide(
                    &self.pager,
                    &PagerView {
                        viewpoint: [0.0, 0.0],
                        resident_bytes: &[],
                        in_flight: &[],
                        expected_bytes: None,
                    },
                )
            });
        self.request_method_data(fetcher, frame);
        let texture_budget = self.share_textures(fetcher, frame);
        Ok(Update {
            decision,
            levels,
            texture_budget,
        })
    }

    /// Bytes kept for what the method holds for no tile in particular: what it may reach
    /// ([`LodMethod::reserved_bytes`]) or what it holds, whichever is more.
    fn reserve(&self) -> u64 {
        self.rendering.as_ref().map_or(0, |r| {
            r.method
                .reserved_bytes(r.viewport)
                .max(r.method.shared_bytes().total())
        })
    }

    /// Asks the fetcher for the data the method wants of resident tiles, once each.
    fn request_method_data(&mut self, fetcher: &mut Fetcher, frame: u64) {
        let Some(r) = &mut self.rendering else {
            return;
        };
        for want in r.method.wants() {
            let i = self.manifest.index(want.id).unwrap_or(usize::MAX);
            if self.tiles.get(i).is_none_or(Option::is_none)
                || !r.data_pending.insert((want.id, want.key))
            {
                continue;
            }
            // After the tiles of this frame and the textures, in the order asked.
            let priority = (frame << 20) | (1 << 19) | (1 << 18);
            fetcher.request_data(
                want.id, want.key, want.path, want.hash, want.bytes, priority,
            );
        }
    }

    fn deliver(&mut self, event: FetchEvent) -> Result<(), SceneError> {
        match event {
            FetchEvent::Tile {
                id,
                heights,
                heights_bytes,
                mask_errors_m,
                texture,
                coarsest_texture,
                ..
            } => {
                let Some(i) = self.manifest.index(id) else {
                    return Ok(());
                };
                let heights = Arc::new(heights);
                let error_minima = crate::lod::needed::suffix_minima(&mask_errors_m);
                let mut bytes = TileBytes {
                    decoded_heights: std::mem::size_of_val(heights.codes.as_slice()) as u64
                        + error_table_bytes(&self.manifest),
                    textures: coarsest_texture.len() as u64,
                    ..TileBytes::default()
                };
                let mut uploaded_levels = 0;
                if let Some(r) = &mut self.rendering {
                    r.renderer.tiles.upload_tile(id, Arc::clone(&heights));
                    let gpu = r.renderer.gpu().clone();
                    r.method.tile_resident(&gpu, id, &heights);
                    if let Some(image) = decode_texture(&coarsest_texture, id, 0) {
                        r.renderer.tiles.upload_texture(id, 0, &[image]);
                        uploaded_levels = 1;
                    }
                    bytes.gpu = r.renderer.tiles.tile_bytes(id);
                    bytes.method = r.method.tile_bytes(id);
                    let copies = r.config.method_config().texture_copies();
                    r.texture_costs[i] = extra_costs(&self.manifest, &texture, copies);
                }
                // What the method expects to hold for it and does not yet (data that arrive
                // after the tile) is reserved, so that the pager does not fill that room.
                let reserved =
                    self.rendering
                        .as_ref()
                        .zip(self.manifest.tile(id))
                        .map_or(0, |(r, record)| {
                            r.method
                                .expected_tile_bytes(record)
                                .saturating_sub(bytes.method)
                        });
                self.base_bytes[i] = bytes.total() + reserved;
                self.tiles[i] = Some(ResidentTile {
                    heights,
                    error_minima,
                    texture_blobs: texture,
                    downloaded: heights_bytes + coarsest_texture.len() as u64,
                    textures: vec![coarsest_texture],
                    uploaded_levels,
                    undecodable_from: (uploaded_levels == 0 && self.rendering.is_some())
                        .then_some(0),
                    bytes,
                    used: false,
                });
                self.tiles_fetched += 1;
                self.failing.remove(&id);
            }
            FetchEvent::TextureLevel {
                id, level, bytes, ..
            } => {
                let Some(i) = self.manifest.index(id) else {
                    return Ok(());
                };
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
            FetchEvent::Data { id, key, bytes } => {
                let Some(i) = self.manifest.index(id) else {
                    return Ok(());
                };
                if let (Some(r), Some(tile)) = (&mut self.rendering, &mut self.tiles[i])
                    && r.data_pending.remove(&(id, key))
                {
                    tile.downloaded += bytes.len() as u64;
                    let gpu = r.renderer.gpu().clone();
                    r.method.data_arrived(&gpu, id, key, bytes);
                    tile.bytes.method = r.method.tile_bytes(id);
                    if let Some(record) = self.manifest.tile(id) {
                        self.base_bytes[i] = r.base_bytes(&self.manifest, record, tile);
                    }
                    // Data that changes what the method expects of other tiles (an index).
                    if r.method.bytes_changed() {
                        self.recount();
                    }
                }
            }
            FetchEvent::Failed {
                id, error, want, ..
            } => {
                // A tile the server refuses (4xx) will never arrive: the flight cannot
                // complete its square, so it stops with the server's reason. Corrupt or
                // unreachable tiles are asked for again on a later frame.
                if let (Want::Data(key), Some(r)) = (want, &mut self.rendering) {
                    // Asked again on a later frame, if the method still wants it.
                    r.data_pending.remove(&(id, key));
                }
                if want == Want::Tile && FailureKind::of(&error) == FailureKind::Permanent {
                    return Err(SceneError::TileFailed {
                        id,
                        message: error.chain(),
                    });
                }
                if want != Want::Tile {
                    tracing::warn!(tile = %id, ?want, "request failed: {}", error.chain());
                    return Ok(());
                }
                let failing = self.failing.entry(id).or_insert(TileFailures {
                    failures: 0,
                    retry_at: Instant::now(),
                });
                failing.failures += 1;
                let delay = TILE_RETRY_DELAY * (1 << (failing.failures - 1).min(16));
                failing.retry_at = Instant::now() + delay;
                if failing.failures >= TILE_REQUESTS_BEFORE_GIVING_UP {
                    tracing::warn!(
                        tile = %id,
                        "tile given up after {} failed requests; the square will not grow past it: {}",
                        failing.failures,
                        error.chain()
                    );
                    self.unavailable.push(UnavailableTile {
                        id,
                        failures: failing.failures,
                        error: error.chain(),
                    });
                } else {
                    tracing::warn!(
                        tile = %id,
                        "tile request failed; asking again in {:.0} s: {}",
                        delay.as_secs_f64(),
                        error.chain()
                    );
                }
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
        let shared = r
            .method
            .reserved_bytes(r.viewport)
            .max(r.method.shared_bytes().total());
        let budget = self
            .pager
            .memory_limit
            .saturating_sub(base + coming + shared);
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
            let id = self.manifest.id_at(i);
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
                if let Some(blob) = tile.texture_blobs.get(next as usize) {
                    fetcher.request_texture(id, next, blob.clone(), priority);
                }
            }
            if changed {
                // The kept levels are on the GPU already: copy them there.
                r.renderer
                    .tiles
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
                if !r.renderer.tiles.refine_texture(id, level as u32, &image) {
                    let images: Option<Vec<image::RgbaImage>> = tile.textures[..=level]
                        .iter()
                        .enumerate()
                        .map(|(l, b)| decode_texture(b, id, l as u32))
                        .collect();
                    let Some(images) = images else {
                        break;
                    };
                    r.renderer.tiles.upload_texture(id, level as u32, &images);
                }
                tile.uploaded_levels = level + 1;
                uploads += 1;
            }
            tile.bytes.gpu = r.renderer.tiles.tile_bytes(id);
        }
        budget
    }

    /// Plans and renders a frame seen from `camera` into `target`, then feeds its time to
    /// the frame-rate controller. `frame_started` is when the frame's work began, so that
    /// the controller sees the whole frame: for frames drawn back to back (a flight), the
    /// end of the draw before it; after a wait that is no work of the frame's (a window's
    /// vsync), the end of that wait. `None` when not rendering.
    pub fn draw(
        &mut self,
        target: &wgpu::TextureView,
        camera: &Camera,
        frame_started: Instant,
    ) -> Option<DrawReport> {
        let r = self.rendering.as_mut()?;
        let started = Instant::now();
        let size = target.texture().size();
        r.viewport = [size.width, size.height];
        let levels_drawn = if r.method.full_resolution_only() {
            1
        } else {
            self.levels_used
        };
        let chosen = crate::lod::levels::choose(
            &self.manifest,
            &self.layout,
            levels_drawn,
            camera,
            [size.width, size.height],
            r.config.lod.max_error_px,
            |id| {
                let i = self.manifest.index(id)?;
                let tile = self.tiles[i].as_ref()?;
                let record = self.manifest.tile(id)?;
                (self.in_square[i] || !r.config.square_only).then(|| crate::lod::levels::Held {
                    min_m: f64::from(record.min_m),
                    max_m: f64::from(record.max_m),
                    deviation_m: tile.error_minima.first().copied().unwrap_or(0.0),
                })
            },
        );
        let seams = crate::lod::levels::seams(&chosen);
        let candidates: Vec<Candidate> = chosen
            .iter()
            .zip(seams)
            .filter_map(|(&id, seams)| {
                let i = self.manifest.index(id)?;
                let tile = self.tiles[i].as_ref()?;
                Some(Candidate {
                    seams,
                    ..Candidate::new(id, self.manifest.tile(id)?, &tile.error_minima)
                })
            })
            .collect();
        let resident: Vec<(TileId, f32)> = if r.method.needs_every_resident_tile() {
            (0..levels_drawn)
                .flat_map(|level| {
                    let offset = self.manifest.level_offset(level);
                    let columns = self.manifest.grid(level).columns.max(1);
                    let count = self.manifest.levels[level as usize].tiles.len();
                    (0..count).map(move |k| {
                        let id = TileId::at(level, k as u32 % columns, k as u32 / columns);
                        (offset + k, id)
                    })
                })
                .filter_map(|(i, id)| {
                    let tile = self.tiles[i].as_ref()?;
                    Some((id, tile.error_minima.first().copied().unwrap_or(0.0)))
                })
                .collect()
        } else {
            Vec::new()
        };
        let room = self
            .pager
            .memory_limit
            .saturating_sub(self.resident_bytes())
            + self.sheddable_texture_bytes();
        let r = self.rendering.as_mut()?;
        let input = MethodInput {
            layout: &self.layout,
            tiles: &candidates,
            resident: &resident,
            budget: r.controller.budget(),
            room,
        };
        let mut frame = r.renderer.begin_frame(target, camera);
        let out = r.method.draw(&input, &mut frame);
        let mut stats = frame.finish();
        let (plan, lod_ms) = (out.plan, out.lod_ms);
        r.importance.fill(0.0);
        let mut drawn = vec![false; self.tiles.len()];
        for (id, importance) in out.importance {
            if let Some(i) = self.manifest.index(id) {
                r.importance[i] = importance;
                drawn[i] = true;
            }
        }
        for d in &plan.draws {
            if let Some(i) = self.manifest.index(d.id) {
                drawn[i] = true;
            }
        }
        // What the method holds per tile changed (its own data meshed since): counted again.
        if r.method.bytes_changed() {
            self.recount();
        }
        // A method's index sets and buffers grow as frames need them: what they took past
        // the limit comes off at once, so that the limit holds at the frame's end.
        stats.squeezed_tiles = self.enforce_limit(&drawn, camera.position);
        // A frame that made, replaced or dropped GPU allocations of the terrain waits for
        // its completion: what it dropped is still used by the frames in flight, and is
        // freed only once they finish, so the memory limit holds at every frame's end.
        // The others (a steady view) do not wait.
        let r = self.rendering.as_mut()?;
        let allocations = (r.renderer.tiles.allocation_epoch(), r.method.gpu_bytes());
        let changed = allocations != r.allocations;
        r.allocations = allocations;
        if r.wait_for_gpu || changed {
            match r.renderer.wait_for_gpu() {
                Ok(gpu_ms) => stats.gpu_ms = gpu_ms,
                Err(e) => tracing::warn!(error = %e, "the frame did not finish"),
            }
        }
        let draw_ms = started.elapsed().as_secs_f64() * 1e3;
        let frame_s = frame_started.elapsed().as_secs_f64();
        // Only a method that shares the budget out adapts to it; the others (GeoMipMaps,
        // the grids, the patches, the reference) are set by their error threshold or grid.
        let target_fps = if r.method.uses_budget() {
            r.controller.target_fps()
        } else {
            None
        };
        let predicted_ms = target_fps
            .and(r.controller.predicted_seconds(stats.triangles))
            .map(|s| s * 1e3);
        if r.method.uses_budget() {
            r.controller.next_budget(FrameCost {
                triangles: stats.triangles,
                wanted: if r.config.lod.cap_at_needed {
                    plan.triangles_needed
                } else {
                    u64::MAX
                },
                seconds: frame_s,
            });
        }
        Some(DrawReport {
            triangles_needed: plan.triangles_needed,
            method: r.method.name(),
            plan,
            stats,
            lod_ms,
            draw_ms,
            frame_ms: frame_s * 1e3,
            predicted_ms,
            target_fps,
        })
    }

    /// Brings what the scene holds back under its limit at a frame's end, when the
    /// method's index sets grew past its reservation during the draw: first what the method
    /// holds and the frame did not use ([`LodMethod::trim`]), then finer texture levels,
    /// least important tiles first, then resident tiles the frame did not draw, then tiles
    /// it drew, least important and farthest from `eye` first; never a tile of the coarsest
    /// level used, which is held whole. Returns the tiles dropped (0 unless the method's
    /// working set outgrew what the pager left it); the pager sees the room they leave
    /// taken by the method on the next frame, and does not fetch them again into it.
    fn enforce_limit(&mut self, drawn: &[bool], eye: [f64; 3]) -> u32 {
        let limit = self.pager.memory_limit;
        if self.resident_bytes() <= limit {
            return 0;
        }
        let over = self.resident_bytes().saturating_sub(limit);
        if let Some(r) = &mut self.rendering {
            r.method.trim(over);
        }
        self.shed_textures();
        let mut squeezed = 0;
        if self.resident_bytes() > limit {
            let coarsest = self.levels_used.saturating_sub(1);
            let mut order: Vec<usize> = (0..self.tiles.len())
                .filter(|&i| self.tiles[i].is_some() && self.manifest.id_at(i).level < coarsest)
                .collect();
            let importance = |i: usize| {
                self.rendering
                    .as_ref()
                    .map_or(0.0, |r| r.importance.get(i).copied().unwrap_or(0.0))
            };
            let distance = |i: usize| {
                let id = self.manifest.id_at(i);
                let [x0, y0] = self.layout.tile_origin_m(id);
                let [w, h] = self.layout.tile_extent_m_at(id.level);
                (x0 + w / 2.0 - eye[0]).hypot(y0 + h / 2.0 - eye[1])
            };
            order.sort_by(|&a, &b| {
                drawn[a]
                    .cmp(&drawn[b])
                    .then(importance(a).total_cmp(&importance(b)))
                    .then(distance(b).total_cmp(&distance(a)))
            });
            for i in order {
                if self.resident_bytes() <= limit {
                    break;
                }
                let id = self.manifest.id_at(i);
                self.drop_tile(id);
                squeezed += 1;
            }
            if squeezed > 0 {
                tracing::debug!(
                    tiles = squeezed,
                    "the method's index sets outgrew its reservation: tiles dropped to keep the limit"
                );
            }
        }
        squeezed
    }

    /// Bytes that dropping every resident tile's finer texture levels would free (what
    /// [`Scene::shed_textures`] can give back): their encoded bytes, and their GPU texture
    /// past the coarsest level.
    fn sheddable_texture_bytes(&self) -> u64 {
        let Some(r) = &self.rendering else {
            return 0;
        };
        let copies = r.renderer.tiles.texture_copies();
        let coarsest =
            copies * coarsest_rgba_bytes(&self.manifest) + r.renderer.tiles.sample_buffer_bytes();
        self.tiles
            .iter()
            .flatten()
            .filter(|t| t.textures.len() > 1)
            .map(|t| {
                t.textures[1..].iter().map(|b| b.len() as u64).sum::<u64>()
                    + t.bytes.gpu.saturating_sub(coarsest)
            })
            .sum()
    }

    /// Drops finer texture levels, least important tiles first, while the scene holds more
    /// than its limit.
    fn shed_textures(&mut self) {
        let mut over = self
            .resident_bytes()
            .saturating_sub(self.pager.memory_limit);
        let Some(r) = &mut self.rendering else {
            return;
        };
        if over == 0 {
            return;
        }
        let mut order: Vec<usize> = (0..self.tiles.len())
            .filter(|&i| self.tiles[i].as_ref().is_some_and(|t| t.textures.len() > 1))
            .collect();
        order.sort_by(|&a, &b| r.importance[a].total_cmp(&r.importance[b]).then(b.cmp(&a)));
        for i in order {
            let Some(tile) = &mut self.tiles[i] else {
                continue;
            };
            let id = self.manifest.id_at(i);
            while over > 0 && tile.textures.len() > 1 {
                let before = tile.bytes.total();
                if let Some(dropped) = tile.textures.pop() {
                    tile.bytes.textures -= dropped.len() as u64;
                }
                let keep = tile.textures.len().min(tile.uploaded_levels);
                r.renderer.tiles.coarsen_texture(id, keep as u32);
                tile.uploaded_levels = keep;
                tile.bytes.gpu = r.renderer.tiles.tile_bytes(id);
                over = over.saturating_sub(before.saturating_sub(tile.bytes.total()));
            }
            if over == 0 {
                break;
            }
        }
    }

    /// Height of the nearest sample under `position` of the finest resident level there.
    pub fn ground_under(&self, position: [f64; 3]) -> Option<f64> {
        let cells = f64::from(self.layout.tile_size - 1);
        (0..self.levels_used).find_map(|level| {
            let extent = self.layout.tile_extent_m_at(level);
            let (tx, ty) = (position[0] / extent[0], position[1] / extent[1]);
            let grid = self.manifest.grid(level);
            if tx < 0.0 || ty < 0.0 || tx >= f64::from(grid.columns) || ty >= f64::from(grid.rows) {
                return None;
            }
            let id = TileId::at(level, tx as u32, ty as u32);
            let tile = self.tiles.get(self.index(id))?.as_ref()?;
            let x = ((tx - tx.floor()) * cells).round() as usize;
            let y = ((ty - ty.floor()) * cells).round() as usize;
            Some(tile.heights.metres(x, y))
        })
    }
}

/// Builds `config`'s method for `renderer`'s device and targets.
fn build_method(
    renderer: &Renderer,
    manifest: &Manifest,
    config: &RenderConfig,
) -> Box<dyn LodMethod> {
    method::build(
        &config.method_config(),
        &method::Build {
            gpu: renderer.gpu(),
            format: renderer.format(),
            frame_layout: renderer.frame_bind_group_layout(),
            manifest,
        },
    )
}

impl Rendering {
    /// What a tile holds once resident at its coarsest texture: [`expected_tile_bytes`]
    /// with this configuration's texture copies, and what the method expects to hold for it.
    fn expected_tile_bytes(
        &self,
        manifest: &Manifest,
        tile: &terrain_shared::TileRecord,
    ) -> TileBytes {
        TileBytes {
            method: self.method.expected_tile_bytes(tile),
            ..expected_tile_bytes(manifest, tile, self.config.method_config().texture_copies())
        }
    }

    /// What the pager counts for resident `tile`: its bytes at its coarsest texture (finer
    /// levels are paid from the texture budget) and what the method holds for it, or
    /// expects to hold once its data are in, whichever is more.
    fn base_bytes(
        &self,
        manifest: &Manifest,
        record: &terrain_shared::TileRecord,
        tile: &ResidentTile,
    ) -> u64 {
        let copies = self.renderer.tiles.texture_copies();
        let gpu_texture = if tile.uploaded_levels > 0 {
            coarsest_rgba_bytes(manifest)
        } else {
            // The grey texel it draws with until a level decodes.
            4
        };
        tile.bytes.decoded_heights
            + tile.textures.first().map_or(0, |t| t.len() as u64)
            + self.renderer.tiles.sample_buffer_bytes()
            + copies * gpu_texture
            // What the method holds, or expects to hold once its data are in.
            + tile.bytes.method.max(self.method.expected_tile_bytes(record))
    }

    /// MapBlocks on or off as the method wants, and the texture costs that follow (a block
    /// texture copies its tiles' textures).
    fn set_texture_blocks(&mut self, manifest: &Manifest) {
        let blocks = self.config.method_config().uses_texture_blocks();
        self.renderer.tiles.set_texture_blocks(blocks.then(|| {
            let grid = manifest.grid(0);
            crate::render::blocks::BlockLayout::new(
                [grid.columns, grid.rows],
                manifest
                    .texture
                    .level_size(manifest.texture.levels.saturating_sub(1)),
                self.config
                    .texture_block_limit
                    .unwrap_or(self.renderer.tiles.max_texture_side()),
            )
        }));
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
/// samples (16-bit codes, [`crate::render::mesh`]) and the coarsest level as RGBA, `gpu_texture_copies` times
/// ([`RenderConfig::texture_copies`]; 0 when not rendering: no GPU bytes at all).
pub fn expected_tile_bytes(
    manifest: &Manifest,
    tile: &terrain_shared::TileRecord,
    gpu_texture_copies: u64,
) -> TileBytes {
    let samples = u64::from(manifest.tile_size).pow(2);
    TileBytes {
        decoded_heights: samples * std::mem::size_of::<i32>() as u64 + error_table_bytes(manifest),
        textures: tile.coarsest_texture_bytes,
        method: 0,
        gpu: if gpu_texture_copies > 0 {
            4 * crate::render::mesh::words_for(samples)
                + gpu_texture_copies * coarsest_rgba_bytes(manifest)
        } else {
            0
        },
    }
}

/// Bytes of a resident tile's error table (the suffix minima of its mask errors, `f32`),
/// counted with its heights.
fn error_table_bytes(manifest: &Manifest) -> u64 {
    4 * u64::from(manifest.mask_levels)
}

/// GPU bytes of a tile's coarsest texture level as RGBA.
fn coarsest_rgba_bytes(manifest: &Manifest) -> u64 {
    u64::from(manifest.texture.level_size(0)).pow(2) * 4
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::http_client::FetchError;
    use terrain_shared::manifest::{ImageFormat, RasterSize, TextureInfo, TextureSource};
    use terrain_shared::{Blob, Heights, TileRecord};

    const SPACING: f64 = 10.0;

    /// Two 3-sample tiles side by side (5 x 3 samples), 10 m apart, one 2-byte texture level;
    /// level 1 above them, one tile.
    fn manifest() -> Arc<Manifest> {
        Arc::new(Manifest::with_geometry(
            "test",
            RasterSize {
                width: 5,
                height: 3,
            },
            3,
            [SPACING, SPACING],
            TextureInfo {
                format: ImageFormat::Png,
                source: TextureSource::Generated,
                size: 1,
                levels: 1,
                level_bytes: Vec::new(),
            },
            |_| TileRecord {
                hash: Blob::of(b"tile").hash,
                bytes: 7,
                coarsest_texture_bytes: 2,
                min_m: 0.0,
                max_m: 8.0,
                roughness_m: 0.0,
            },
        ))
    }

    fn scene(limit: u64) -> Scene {
        let manifest = manifest();
        let pager = PagerConfig {
            columns: 2,
            rows: 1,
            memory_limit: limit,
            nearest_when_outside: true,
            current_over_limit: true,
        };
        Scene::new(manifest, pager, None)
    }

    fn heights(codes: [i32; 9]) -> Heights {
        Heights {
            width: 3,
            height: 3,
            quantum_m: 1.0,
            offset_m: 0.0,
            codes: codes.to_vec(),
        }
    }

    fn arrive(scene: &mut Scene, x: u32, codes: [i32; 9]) {
        scene
            .deliver(FetchEvent::Tile {
                id: TileId::new(x, 0),
                heights: heights(codes),
                heights_bytes: 7,
                mask_errors_m: vec![0.0; 2],
                texture: vec![Blob::of(b"tx")],
                coarsest_texture: bytes::Bytes::from_static(b"tx"),
                attempts: 1,
                elapsed: std::time::Duration::ZERO,
                decode: std::time::Duration::ZERO,
            })
            .expect("delivered");
    }

    #[test]
    fn the_true_surface_splits_each_cell_along_the_masks_diagonal() {
        let mut scene = scene(1 << 20);
        // Tile 0: zero but its centre sample (1, 1), at 8 m.
        arrive(&mut scene, 0, [0, 0, 0, 0, 8, 0, 0, 0, 0]);
        // Cell (0, 0): corners 0, 0, 0 and 8 at (1, 1), the south-east one. Split along the
        // south-west/north-east diagonal, the north-west half is flat at 0 and the
        // south-east half rises to 8: half way from the diagonal to the corner is 4 m. The
        // other diagonal would put 4 m at the cell's centre instead of 0.
        assert_eq!(scene.surface_height(5.0, 5.0), Some(0.0), "on the diagonal");
        let h = scene.surface_height(7.5, 7.5).expect("resident");
        assert!((h - 4.0).abs() < 1e-9, "{h}");
        assert_eq!(
            scene.surface_height(7.5, 7.5),
            Some(terrain_shared::mask::cell_height(
                0.0, 0.0, 0.0, 8.0, 0.75, 0.75
            ))
        );
        assert_eq!(scene.surface_height(2.5, 2.5), Some(0.0), "the flat half");
        // Off the terrain, or over a tile not resident: no surface.
        assert_eq!(scene.surface_height(-1.0, 5.0), None);
        assert_eq!(scene.surface_height(5.0, 25.0), None);
        assert_eq!(scene.surface_height(25.0, 5.0), None, "tile 1 not resident");
        assert_eq!(scene.ground_under([11.0, 9.0, 100.0]), Some(8.0));
        assert_eq!(scene.ground_under([31.0, 9.0, 100.0]), None);
    }

    #[test]
    fn without_rendering_a_tile_holds_its_heights_and_texture_and_nothing_on_the_gpu() {
        let mut scene = scene(1 << 20);
        assert_eq!(scene.resident_bytes(), 0);
        arrive(&mut scene, 1, [1; 9]);
        // Nine 32-bit codes, the error table (two f32) and the two-byte coarsest texture level.
        assert_eq!(scene.resident_bytes(), 9 * 4 + 2 * 4 + 2);
        assert_eq!(scene.cpu_bytes(), scene.resident_bytes());
        assert_eq!(scene.gpu_bytes(), 0);
        assert_eq!(scene.resident_tiles(), 1);
        let record = scene.manifest().tile(TileId::new(1, 0)).expect("tile 1");
        assert_eq!(
            expected_tile_bytes(scene.manifest(), record, 0).total(),
            scene.resident_bytes(),
            "the pager's expectation is what the tile holds"
        );
        // Rendering adds the GPU samples (16-bit codes, two a 32-bit word: 5 words for 9) and
        // each texture copy.
        let rendered = expected_tile_bytes(scene.manifest(), record, 2);
        assert_eq!(rendered.gpu, 5 * 4 + 2 * 4);
    }

    #[test]
    fn a_new_manifest_keeps_the_tiles_whose_hashes_did_not_change_and_refuses_another_grid() {
        let mut scene = scene(1 << 20);
        arrive(&mut scene, 0, [1; 9]);
        arrive(&mut scene, 1, [2; 9]);
        let mut rebuilt = (*manifest()).clone();
        rebuilt.content_version = "1".into();
        rebuilt.levels[0].tiles[1].hash = Blob::of(b"other tile").hash;
        assert_eq!(
            scene.replace_manifest(Arc::new(rebuilt.clone())),
            Reconciled::Kept {
                kept: 1,
                dropped: 1
            }
        );
        assert_eq!(scene.resident_tiles(), 1);
        assert_eq!(
            scene.ground_under([5.0, 5.0, 100.0]),
            Some(1.0),
            "tile 0 kept"
        );
        assert_eq!(
            scene.ground_under([31.0, 5.0, 100.0]),
            None,
            "tile 1 dropped"
        );
        assert_eq!(scene.manifest().content_version, "1");
        assert_eq!(scene.resident_bytes(), 9 * 4 + 2 * 4 + 2);
        // Another grid cannot be taken: the caller starts a new scene.
        let mut reshaped = rebuilt;
        reshaped.tile_size = 5;
        assert_eq!(
            scene.replace_manifest(Arc::new(reshaped)),
            Reconciled::Reshaped
        );
        assert_eq!(scene.manifest().content_version, "1");
    }

    #[test]
    fn a_refused_tile_stops_the_scene_and_a_failed_request_does_not() {
        let mut scene = scene(1 << 20);
        let failed = |status: u16| FetchEvent::Failed {
            id: TileId::new(0, 0),
            want: Want::Tile,
            error: FetchError::Http {
                url: "http://test/heights".into(),
                status: reqwest::StatusCode::from_u16(status).expect("status"),
                body: String::new(),
            },
            attempts: 1,
        };
        assert!(scene.deliver(failed(503)).is_ok(), "asked again later");
        let refused = scene.deliver(failed(404));
        assert!(
            matches!(refused, Err(SceneError::TileFailed { id, .. }) if id == TileId::new(0, 0)),
            "{refused:?}"
        );
        // A texture level a tile does not have is dropped, not added.
        arrive(&mut scene, 0, [0; 9]);
        let before = scene.resident_bytes();
        scene
            .deliver(FetchEvent::TextureLevel {
                id: TileId::new(0, 0),
                level: 3,
                bytes: bytes::Bytes::from_static(b"far too fine"),
                elapsed: std::time::Duration::ZERO,
            })
            .expect("delivered");
        assert_eq!(scene.resident_bytes(), before);
    }
}
