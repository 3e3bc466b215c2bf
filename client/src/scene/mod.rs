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
//! This module holds the scene's state and what reads it; three parts change it, one
//! concern each: [`residency`] (deliveries, paging, requests and their retries, a new
//! manifest reconciled, evictions at the end of a frame), [`textures`] (the texture budget)
//! and [`drawing`] (the method, the frame-rate controller, the draw and its GPU bytes).
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
use crate::render::textures::{
    TextureCandidate, extra_costs, most_important_first, share_texture_budget,
};
use crate::render::{Camera, Gpu, RenderStats, Renderer};
use crate::requests::{FailureKind, FetchEvent, Fetcher, Want};
use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::Duration;
use terrain_shared::{Manifest, TileId};
use web_time::Instant;

mod drawing;
mod residency;
mod textures;

pub use drawing::GeometryMemory;
use drawing::build_method;
use textures::decode_texture;

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
        runtime: impl Into<crate::requests::Spawner>,
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
        self.tile_bytes()
            + self
                .rendering
                .as_ref()
                .map_or(0, |r| r.method.shared_bytes().total())
    }

    /// Bytes the scene holds for its resident tiles alone, as the memory limit counts them
    /// ([`Scene::resident_bytes`] without the method's shared bytes).
    pub fn tile_bytes(&self) -> u64 {
        self.tiles.iter().flatten().map(|t| t.bytes.total()).sum()
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

    /// Whether every tile is resident with every texture level it is meant to have and
    /// nothing is in flight: what the accuracy measures wait for.
    pub fn settled(&self) -> bool {
        self.unsettled().is_none()
    }

    /// What keeps the scene from having settled (see [`Scene::settled`]), in words: tiles in
    /// flight, textures short of their target level, the method's data pending or in the
    /// making. `None` once settled.
    pub fn unsettled(&self) -> Option<String> {
        let textures_short = self.rendering.as_ref().map_or(0, |r| {
            self.tiles
                .iter()
                .zip(&r.texture_target)
                .filter(|(t, target)| {
                    t.as_ref().is_some_and(|t| {
                        let held = t
                            .textures
                            .len()
                            .min(t.undecodable_from.unwrap_or(usize::MAX));
                        !(t.uploaded_levels >= held
                            && (t.textures.len() > **target as usize
                                || t.undecodable_from.is_some()))
                    })
                })
                .count()
        });
        let (data_pending, method_busy) = self
            .rendering
            .as_ref()
            .map_or((0, false), |r| (r.data_pending.len(), !r.method.settled()));
        let in_flight = self.in_flight();
        let mut parts = Vec::new();
        if in_flight > 0 {
            parts.push(format!("{in_flight} tile(s) in flight"));
        }
        if textures_short > 0 {
            parts.push(format!(
                "{textures_short} tile(s) short of their texture level"
            ));
        }
        if data_pending > 0 {
            parts.push(format!(
                "{data_pending} request(s) of the method's data pending"
            ));
        }
        if method_busy {
            parts.push("the method still making or waiting for its data".to_string());
        }
        (!parts.is_empty()).then(|| parts.join(", "))
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

/// What a tile of the byte oracle costs ([`Scene::bytes_needed`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NeededBytes {
    /// Held, as the pager counts the tile at its coarsest texture.
    pub held: u64,
    /// Downloaded: the tile blob and its coarsest texture level.
    pub downloaded: u64,
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
        arrive_with_errors(scene, TileId::new(x, 0), codes, vec![0.0; 2]);
    }

    fn arrive_with_errors(scene: &mut Scene, id: TileId, codes: [i32; 9], errors_m: Vec<f32>) {
        scene
            .deliver(FetchEvent::Tile {
                id,
                heights: heights(codes),
                heights_bytes: 7,
                mask_errors_m: errors_m,
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

    /// The byte oracle: the coarsest resident tile whose deviation projects within the
    /// threshold, else its children; what each costs.
    #[test]
    fn the_byte_oracle_takes_the_coarsest_tile_within_the_threshold() {
        let mut scene = scene(1 << 20);
        arrive(&mut scene, 0, [0; 9]);
        arrive(&mut scene, 1, [0; 9]);
        let near = Camera::looking_at([25.0, 10.0, 30.0], [25.0, 10.0, 0.0]);
        let far = Camera::looking_at([25.0, 10.0, 100_000.0], [25.0, 10.0, 0.0]);
        let needed = |scene: &Scene, camera: &Camera| {
            let mut ids: Vec<(TileId, NeededBytes)> = scene.bytes_needed(camera, [640, 360], 1.0);
            ids.sort_by_key(|(id, _)| (id.level, id.x, id.y));
            ids
        };
        // Without the level-1 tile, its children, near or far.
        let level_0 = NeededBytes {
            held: expected_tile_bytes(
                scene.manifest(),
                scene.manifest().tile(TileId::new(0, 0)).expect("tile"),
                0,
            )
            .total(),
            downloaded: 7 + 2,
        };
        for camera in [&near, &far] {
            assert_eq!(
                needed(&scene, camera),
                vec![(TileId::new(0, 0), level_0), (TileId::new(1, 0), level_0)]
            );
        }
        // The level-1 tile, 5 m from full resolution: enough from 100 km (0.02 px), not
        // from 30 m.
        arrive_with_errors(&mut scene, TileId::at(1, 0, 0), [0; 9], vec![5.0, 5.0]);
        assert_eq!(
            needed(&scene, &far)
                .iter()
                .map(|(id, _)| *id)
                .collect::<Vec<_>>(),
            vec![TileId::at(1, 0, 0)]
        );
        assert_eq!(
            needed(&scene, &near)
                .iter()
                .map(|(id, _)| *id)
                .collect::<Vec<_>>(),
            vec![TileId::new(0, 0), TileId::new(1, 0)]
        );
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
