//! The seam between the scene and a level-of-detail method, and the methods.
//!
//! A method is built with the GPU ([`Build`]) and keeps whatever it draws with: its index
//! sets, pipelines and buffers of its own, its own copy of the terrain, data of its own it
//! asks the scene to fetch ([`LodMethod::wants`]). Each frame the scene hands it what it
//! knows (the camera, the viewport, the resident tiles as the manifest describes them, the
//! frame's triangle budget) and a [`Frame`] to record into; the method decides, draws, and
//! says what it drew and how much each tile matters ([`MethodOutput::importance`], which
//! ranks the tiles' textures). The scene does not know how.
//!
//! - [`strip_masks`]: the strip-mask paper's method (a global budget shared by importance,
//!   one precomputed strip per mask level, [`fillers`] for the cracks), and the
//!   full-resolution reference of the accuracy measures ([`crate::eval`]).
//! - [`geomipmap`]: GeoMipMaps, each side stitched to its neighbour's level (the index sets
//!   and level errors in [`geomipmap::stitching`]).
//! - [`projected_grid`]: persistent grid mapping and the error-bounded projective grid, a
//!   screen grid cast from an auxiliary camera ([`projected_grid::geometry`]) onto their own
//!   copy of the terrain ([`projected_grid::atlas`]).
//! - [`quadtree_patches`]: quadtree progressive patches with a guaranteed error and
//!   geomorphing.
//!
//! Each method is one folder: its pure decisions beside its GPU part. What methods share
//! stays here ([`fillers`], the crack fillers of strip masks and GeoMipMaps) or in
//! [`crate::lod`] (culling, importance, the budget, the mask set).
//!
//! **Memory.** Every byte a method holds, CPU or GPU, is counted: per resident tile
//! ([`LodMethod::tile_bytes`], expected before it arrives: [`LodMethod::expected_tile_bytes`])
//! and for no tile in particular ([`LodMethod::shared_bytes`]). The scene adds them to what
//! the pager and the texture budget see, so they stay inside the memory limit.

pub mod fillers;
pub mod geomipmap;
pub mod projected_grid;
pub mod quadtree_patches;
pub mod strip_masks;

pub use fillers::CrackFiller;
pub use projected_grid::GridSettings;

use crate::lod::plan::{Candidate, FramePlan, Layout, LodSettings};
use crate::render::{Frame, Gpu};
use bytes::Bytes;
use terrain_shared::{Heights, Manifest, TileId, TileRecord};

/// What a method is told about the frame.
#[derive(Debug, Clone, Copy)]
pub struct MethodInput<'a> {
    pub layout: &'a Layout,
    /// The resident tiles the frame draws: a cut of the pyramid (the reference: level 0).
    pub tiles: &'a [Candidate<'a>],
    /// Every resident tile of every level, with its distance from the full-resolution
    /// surface (metres), for a method that keeps its own copy of the terrain
    /// ([`LodMethod::needs_every_resident_tile`]); empty for the others.
    pub resident: &'a [(TileId, f32)],
    /// The frame's triangle budget: the frame-rate controller's, or a fixed one.
    pub budget: u32,
    /// Bytes the method may add this frame (index sets, buffers) and the memory limit still
    /// hold at the frame's end: what the limit leaves, and the finer texture levels that
    /// will be dropped for it. What it holds and the frame does not use it may drop to make
    /// more ([`LodMethod::trim`]). Past that it draws with what it has, coarser.
    pub room: u64,
}

/// What a method drew.
#[derive(Debug, Clone, Default)]
pub struct MethodOutput {
    /// Its decisions: the tiles it drew per level (empty for a method without per-tile
    /// draws), the triangles it drew and needed.
    pub plan: FramePlan,
    /// How much each tile it saw matters this frame (summing to about 1 over the visible
    /// tiles): what ranks the tiles' textures, whatever the method draws.
    pub importance: Vec<(TileId, f64)>,
    /// CPU time of the method's decisions (culling, error and budget), milliseconds.
    pub lod_ms: f64,
}

impl MethodOutput {
    /// The output of a per-tile method: its plan, each drawn tile's importance from it.
    pub fn of_plan(plan: FramePlan, lod_ms: f64) -> MethodOutput {
        MethodOutput {
            importance: plan
                .draws
                .iter()
                .zip(&plan.importances)
                .map(|(d, &i)| (d.id, i))
                .collect(),
            plan,
            lod_ms,
        }
    }
}

/// Bytes a method holds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MethodBytes {
    pub cpu: u64,
    pub gpu: u64,
}

impl MethodBytes {
    pub fn total(&self) -> u64 {
        self.cpu + self.gpu
    }
}

/// Data of its own a method wants for a resident tile, fetched by the scene's fetcher
/// (bounded, prioritised, retried, hash-checked like the tiles) and handed back with
/// [`LodMethod::data_arrived`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DataWant {
    pub id: TileId,
    /// The method's own number for the piece (a level, a patch).
    pub key: u32,
    /// The server path, as [`terrain_shared::routes`] makes them.
    pub path: String,
    /// The BLAKE3 hash the body must have (first 128 bits, hex), when known.
    pub hash: Option<String>,
    /// Its size, when known: a longer body is refused as it arrives
    /// ([`crate::http_client::FetchError::TooLarge`]).
    pub bytes: Option<u64>,
}

/// The settings a method is built and configured with; each takes what applies to it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MethodConfig {
    pub kind: MethodKind,
    pub lod: LodSettings,
    /// The crack filler, for methods with cracks to fill.
    pub filler: CrackFiller,
    /// Whether methods that draw with MapBlock textures use them (`false`: every tile with
    /// its own texture, for comparison).
    pub texture_blocks: bool,
    /// The projected grids' size and options.
    pub grid: GridSettings,
}

impl MethodConfig {
    /// Whether tiles are bound block by block with MapBlock textures
    /// ([`crate::render::blocks`]), as the GeoMipMaps paper draws them.
    pub fn uses_texture_blocks(&self) -> bool {
        self.kind == MethodKind::Geomipmap && self.texture_blocks
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

/// What a method is built with.
#[derive(Debug, Clone, Copy)]
pub struct Build<'a> {
    pub gpu: &'a Gpu,
    /// The format of the targets it draws into.
    pub format: wgpu::TextureFormat,
    /// The layout of bind group 0 (the frame's uniforms) of every pass, for pipelines of
    /// its own ([`crate::render::Renderer::frame_bind_group_layout`]).
    pub frame_layout: &'a wgpu::BindGroupLayout,
    pub manifest: &'a Manifest,
}

/// A level-of-detail method (see the module documentation).
pub trait LodMethod: std::fmt::Debug + Send {
    /// Its name in tables and charts, e.g. `strip-masks/planar-shadow`.
    fn name(&self) -> String;

    /// Whether it draws level 0 of the pyramid alone, whatever the other levels hold (the
    /// full-resolution reference); the others are given tiles of every level used.
    fn full_resolution_only(&self) -> bool {
        false
    }

    /// Whether it shares [`MethodInput::budget`] out, so that the frame-rate controller's
    /// budget sets what it draws (strip masks); the others draw what their error threshold
    /// or grid sets, and no target frame rate applies to them.
    fn uses_budget(&self) -> bool {
        false
    }

    /// Whether it wants [`MethodInput::resident`]: every resident tile, not only the cut.
    fn needs_every_resident_tile(&self) -> bool {
        false
    }

    /// Measures of the last frame only the method knows, read back from the GPU (waiting
    /// for it: for the evaluation, not the render loop), as (name, value).
    fn frame_measures(&mut self, _gpu: &Gpu) -> Vec<(&'static str, f64)> {
        Vec::new()
    }

    /// Decides and draws one frame into `frame` (its first pass clears the target).
    fn draw(&mut self, input: &MethodInput<'_>, frame: &mut Frame<'_>) -> MethodOutput;

    /// Draws later frames with these settings (the method stays the same kind).
    fn configure(&mut self, config: &MethodConfig);

    /// A tile became resident (for methods keeping their own copy of the terrain).
    fn tile_resident(&mut self, _gpu: &Gpu, _id: TileId, _heights: &Heights) {}

    /// A tile was evicted: the method drops what it holds for it.
    fn tile_evicted(&mut self, _id: TileId) {}

    /// Data of its own the method wants now (asked for once each until it arrives or its
    /// tile leaves; the scene fetches it for resident tiles only).
    fn wants(&mut self) -> Vec<DataWant> {
        Vec::new()
    }

    /// Whether what it holds for its tiles, or expects to hold for tiles not in yet, changed
    /// since it was last asked (its data arrived or was built later than the tile): the
    /// scene then counts every tile again, so the pager sees the bytes held and expected.
    fn bytes_changed(&mut self) -> bool {
        false
    }

    /// Whether it holds everything it wants of the resident tiles, with nothing in the
    /// making: what the accuracy measures wait for, with the tiles.
    fn settled(&self) -> bool {
        true
    }

    /// A piece of data it wanted arrived, hash-checked.
    fn data_arrived(&mut self, _gpu: &Gpu, _id: TileId, _key: u32, _bytes: Bytes) {}

    /// Bytes it holds for resident tile `id`, CPU and GPU.
    fn tile_bytes(&self, _id: TileId) -> u64 {
        0
    }

    /// Bytes it will hold for `tile` once resident (the pager's expectation, from the
    /// manifest alone).
    fn expected_tile_bytes(&self, _tile: &TileRecord) -> u64 {
        0
    }

    /// Bytes it holds for no tile in particular (index sets, grids, pipelines' buffers).
    fn shared_bytes(&self) -> MethodBytes {
        MethodBytes::default()
    }

    /// What [`LodMethod::shared_bytes`] may reach for frames of `viewport` pixels, as far as
    /// the method can tell before it draws: the buffers it makes whatever it draws (a
    /// grid, an error buffer of the viewport's size), the slack its buffers grow by, and an
    /// allowance for the index sets it makes as frames need them. The scene keeps this
    /// much of the limit (or what the method holds, if more) before any tile gets a byte,
    /// and refuses a limit that cannot hold it with the coarsest level
    /// (`Scene::least_limit`). Index sets past the allowance come off the tiles at the
    /// frame's end: [`LodMethod::trim`] first.
    fn reserved_bytes(&self, _viewport: [u32; 2]) -> u64 {
        self.shared_bytes().total()
    }

    /// Drops what it holds for no tile in particular and the last frame did not use (index
    /// sets made for earlier frames), least recently used first, until `bytes` are freed or
    /// nothing such is left; returns the bytes freed. What the last frame drew with stays.
    fn trim(&mut self, _bytes: u64) -> u64 {
        0
    }

    /// Of [`LodMethod::tile_bytes`] over the resident tiles and [`LodMethod::shared_bytes`],
    /// the GPU part.
    fn gpu_bytes(&self) -> u64 {
        self.shared_bytes().gpu
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
    /// Persistent grid mapping (Livny et al.): a uniform screen grid cast onto the terrain
    /// each frame from an auxiliary camera, heights from averaged pyramids blended across
    /// levels. Knob: `--grid`.
    Pgm,
    /// The error-bounded projective grid (Löffler et al.): the screen grid warped to square
    /// cells on the ground, its error from min/max pyramids, rays cast where it passes
    /// `--max-error-px`. Knobs: `--grid`, `--max-error-px`.
    ProjectiveGrid,
    /// Quadtree progressive patches (Yusov and Turlapov 2007): per tile an adaptive
    /// triangulation with a guaranteed world-space error, streamed coarse to fine, drawn
    /// where its projected error is within `--max-error-px`, geomorphed (`--no-morph` to
    /// turn off). Needs a database built with `--patches`.
    QuadtreePatches,
}

impl MethodKind {
    pub fn name(self) -> &'static str {
        match self {
            MethodKind::StripMasks => "strip-masks",
            MethodKind::Reference => "reference",
            MethodKind::Geomipmap => "geomipmap",
            MethodKind::Pgm => "pgm",
            MethodKind::ProjectiveGrid => "projective-grid",
            MethodKind::QuadtreePatches => "quadtree-patches",
        }
    }

    /// Whether the method fills cracks with a [`CrackFiller`] (the others are crack-free
    /// by construction, or have no tiles).
    pub fn uses_filler(self) -> bool {
        matches!(self, MethodKind::StripMasks)
    }

    /// The coarsest level it draws a tile of `tile_size` samples a side at.
    pub fn coarsest_level(self, tile_size: u32) -> u32 {
        match self {
            MethodKind::Geomipmap => geomipmap::blocks::Blocks::new(tile_size).levels() - 1,
            MethodKind::StripMasks
            | MethodKind::Reference
            | MethodKind::Pgm
            | MethodKind::ProjectiveGrid
            | MethodKind::QuadtreePatches => terrain_shared::mask::level_count(tile_size) - 1,
        }
    }

    /// Whether it draws a screen grid (the projected grids), whose knob is the grid's size.
    pub fn is_projected_grid(self) -> bool {
        matches!(self, MethodKind::Pgm | MethodKind::ProjectiveGrid)
    }

    /// Its name with `filler` where it has one, e.g. `strip-masks/skirts`: the name the
    /// method gives itself ([`LodMethod::name`]), known before it is built.
    pub fn name_with(self, filler: CrackFiller) -> String {
        if self.uses_filler() {
            format!("{}/{}", self.name(), filler.name())
        } else {
            self.name().to_string()
        }
    }
}

/// Whether `manifest`'s database holds what `kind` needs: the quadtree patches need a
/// database built with `--patches`. The error says how to get one.
pub fn check_database(kind: MethodKind, manifest: &Manifest) -> Result<(), String> {
    if kind == MethodKind::QuadtreePatches && manifest.patches.is_none() {
        return Err(format!(
            "--method quadtree-patches needs a database with quadtree patches, and {:?} has none: build it with `terrain-server build --patches`",
            manifest.dataset
        ));
    }
    if kind == MethodKind::QuadtreePatches
        && let Some(p) = &manifest.patches
        && p.format != terrain_shared::quadtree::FORMAT
    {
        return Err(format!(
            "--method quadtree-patches reads patches of format {:?}, and {:?} holds {:?}: build it again with this version's `terrain-server build --patches`",
            terrain_shared::quadtree::FORMAT,
            manifest.dataset,
            p.format
        ));
    }
    Ok(())
}

/// Whether a device with `downlevel` draws method `kind`, or a sentence saying what it
/// lacks. Everything but WebGL2 has it all; on WebGL2 the strip masks (and the reference)
/// draw, with every crack filler, reading the samples from a texture
/// ([`crate::render::SampleStore::Texture`]).
pub fn check_gpu(kind: MethodKind, downlevel: wgpu::DownlevelFlags) -> Result<(), String> {
    use wgpu::DownlevelFlags as F;
    let (needs, why) = match kind {
        MethodKind::StripMasks | MethodKind::Reference => return Ok(()),
        MethodKind::Geomipmap => (
            F::BASE_VERTEX,
            "it draws every block of a tile from one index set placed by a base vertex",
        ),
        MethodKind::Pgm | MethodKind::ProjectiveGrid => (
            F::VERTEX_STORAGE | F::FRAGMENT_WRITABLE_STORAGE,
            "its shaders read the heights' atlas from storage buffers and count pixels in one",
        ),
        // Its vertices are vertex buffers: nothing past WebGL2's.
        MethodKind::QuadtreePatches => return Ok(()),
    };
    if downlevel.contains(needs) {
        return Ok(());
    }
    Err(format!(
        "--method {} needs {:?}, which this graphics backend lacks (WebGL2 does): {why}. \
         strip-masks and reference draw here",
        kind.name(),
        needs.difference(downlevel)
    ))
}

/// Builds the method `config.kind`.
pub fn build(config: &MethodConfig, with: &Build<'_>) -> Box<dyn LodMethod> {
    match config.kind {
        MethodKind::StripMasks | MethodKind::Reference => Box::new(strip_masks::StripMasks::new(
            config,
            with.manifest.tile_size,
        )),
        MethodKind::Geomipmap => Box::new(geomipmap::GeoMipMaps::new(config, with)),
        MethodKind::Pgm | MethodKind::ProjectiveGrid => {
            Box::new(projected_grid::ProjectedGrid::new(config, with))
        }
        MethodKind::QuadtreePatches => {
            Box::new(quadtree_patches::QuadtreePatches::new(config, with))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use wgpu::DownlevelFlags as F;

    #[test]
    fn a_device_without_what_a_method_draws_with_refuses_it_by_name() {
        // WebGL2's: no base vertex, no storage buffers.
        let webgl2 = F::all() - F::BASE_VERTEX - F::VERTEX_STORAGE - F::FRAGMENT_WRITABLE_STORAGE;
        for kind in [
            MethodKind::StripMasks,
            MethodKind::Reference,
            MethodKind::QuadtreePatches,
        ] {
            assert_eq!(check_gpu(kind, webgl2), Ok(()), "{}", kind.name());
        }
        for (kind, lacking) in [
            (MethodKind::Geomipmap, "BASE_VERTEX"),
            (MethodKind::Pgm, "VERTEX_STORAGE"),
            (MethodKind::ProjectiveGrid, "FRAGMENT_WRITABLE_STORAGE"),
        ] {
            let refused = check_gpu(kind, webgl2).expect_err(kind.name());
            assert!(
                refused.contains(lacking)
                    && refused.starts_with(&format!("--method {}", kind.name())),
                "{refused}"
            );
            assert_eq!(check_gpu(kind, F::all()), Ok(()), "{}", kind.name());
        }
    }
}
