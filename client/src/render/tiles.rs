//! Resident tiles on the GPU, shared by every method: their sample buffers and textures.
//!
//! A tile drawn has a slot of its samples (16-bit height codes, 2 bytes each, see
//! [`super::mesh`]) in one storage buffer (or, on WebGL2, one integer texture:
//! `arena`) shared by every tile (the sample arena, bound once a pass). Slots are
//! handed to the tiles drawn, least recently used first ([`super::pool`],
//! the GeoMipMaps paper's VBO manager): a resident tile keeps only its heights (shared with
//! the scene) until it is drawn. The arena holds exactly as many slots as the pool: it grows
//! when a frame needs more, and is compacted (its live slots copied into a smaller buffer)
//! when the pool shrinks, so it never holds more than the tiles it is charged to. Each tile has a texture holding
//! the finest level it has so far, with the coarser levels as its mips; with MapBlocks on
//! ([`super::blocks`]), tiles are bound block by block with their block's texture.
//!
//! Every allocation made here is labelled with [`TERRAIN_LABEL`] first, so the allocator's
//! report can be checked against [`TileStore::residency`].

use super::arena::Arena;
use super::blocks::{BlockLayout, BlockRect, Blocks};
use super::gpu::{Gpu, SampleStore};
use super::layout::Layout;
use super::mesh;
use super::pool::LruPool;
use std::collections::HashMap;
use std::sync::Arc;
use terrain_shared::{Heights, TileId};

/// First part of the label of every GPU allocation held for the terrain (samples, textures,
/// blocks, a method's index sets and buffers): what the memory limit covers.
pub const TERRAIN_LABEL: &str = "terrain/";

/// Labels of the allocations made here.
pub mod label {
    pub use super::super::arena::label::{EMPTY_SAMPLES, SAMPLES};
    pub const TEXTURE: &str = "terrain/tile texture";
    pub const BLOCK: &str = "terrain/map block";
}

/// What the tiles hold on the GPU ([`TileStore::residency`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct GpuResidency {
    /// Resident tiles.
    pub tiles: u64,
    /// Sample slots in the arena (at most one per resident tile; only drawn tiles get one).
    pub sample_buffers: u64,
    pub sample_bytes: u64,
    /// The tiles' own textures, every mip.
    pub texture_bytes: u64,
    /// MapBlock textures.
    pub block_bytes: u64,
}

impl GpuResidency {
    /// Every byte above.
    pub fn total(&self) -> u64 {
        self.sample_bytes + self.texture_bytes + self.block_bytes
    }
}

/// A resident tile on the GPU.
#[derive(Debug)]
pub(super) struct GpuTile {
    /// Its heights, shared with the scene; turned into samples when it gets a buffer.
    pub(super) heights: Arc<Heights>,
    pub(super) texture: wgpu::Texture,
    pub(super) texture_group: wgpu::BindGroup,
    /// Changes with every change of the texture (unique across tiles).
    pub(super) texture_version: u64,
    /// Finest texture level uploaded (manifest numbering: 0 is the coarsest).
    pub(super) texture_level: Option<u32>,
    texture_bytes: u64,
    /// The code base and shift of its samples in the arena ([`mesh::pack_codes`]), set when
    /// they are uploaded.
    code_base: (i32, u32),
}

/// The bind group layouts of the sample arena (group 1) and of a tile's texture (group 2),
/// shared with the pipelines that draw tiles.
#[derive(Debug)]
pub struct TileBindings {
    pub samples: wgpu::BindGroupLayout,
    pub texture: wgpu::BindGroupLayout,
}

/// The resident tiles' GPU resources. See the module documentation.
#[derive(Debug)]
pub struct TileStore {
    device: wgpu::Device,
    queue: wgpu::Queue,
    layout: Layout,
    bindings: TileBindings,
    sampler: wgpu::Sampler,
    pub(super) tiles: HashMap<TileId, GpuTile>,
    /// Each slot's value is its position in the arena.
    pub(super) pool: LruPool<TileId, u32>,
    pub(super) arena: Arena,
    /// Where the arena is kept: what the device's vertex shaders read.
    store: SampleStore,
    /// Arena positions no pool slot holds.
    free_positions: Vec<u32>,
    /// The most slots the arena may hold: what one storage binding and one buffer of the
    /// device take, or one texture.
    max_slots: u32,
    /// Tiles left undrawn for want of a slot, over the renderer's life (logged once).
    pub(super) refused: u64,
    pub(super) blocks: Option<Blocks>,
    next_texture_version: u64,
    max_texture_side: u32,
}

impl TileStore {
    pub(super) fn new(gpu: &Gpu, layout: Layout) -> TileStore {
        let device = gpu.device.clone();
        let store = gpu.samples;
        let samples = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tile samples"),
            entries: &[Arena::layout_entry(store)],
        });
        let texture = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tile texture"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: true },
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 1,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                    count: None,
                },
            ],
        });
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("tile"),
            address_mode_u: wgpu::AddressMode::ClampToEdge,
            address_mode_v: wgpu::AddressMode::ClampToEdge,
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            mipmap_filter: wgpu::MipmapFilterMode::Linear,
            ..Default::default()
        });
        TileStore {
            max_texture_side: device.limits().max_texture_dimension_2d,
            queue: gpu.queue.clone(),
            device,
            layout,
            bindings: TileBindings { samples, texture },
            sampler,
            tiles: HashMap::new(),
            pool: LruPool::default(),
            arena: Arena::new(&gpu.device, store, 0, slot_words(layout), 0),
            store,
            free_positions: Vec::new(),
            max_slots: Arena::max_slots(store, &gpu.device.limits(), slot_words(layout)),
            refused: 0,
            blocks: None,
            next_texture_version: 0,
        }
    }

    /// The bind group layouts of a tile's samples and texture.
    pub fn bindings(&self) -> &TileBindings {
        &self.bindings
    }

    /// Whether `id` is resident.
    pub fn contains(&self, id: TileId) -> bool {
        self.tiles.contains_key(&id)
    }

    /// The heights of resident tile `id`.
    pub fn heights(&self, id: TileId) -> Option<&Arc<Heights>> {
        self.tiles.get(&id).map(|t| &t.heights)
    }

    /// `id`'s texture (the finest level it holds as mip 0, coarser ones below) and its
    /// version, which changes whenever the texture does: for a method keeping a copy.
    pub fn texture_of(&self, id: TileId) -> Option<(&wgpu::Texture, u64)> {
        self.tiles.get(&id).map(|t| (&t.texture, t.texture_version))
    }

    /// Finest texture level `id` holds on the GPU.
    pub fn texture_level(&self, id: TileId) -> Option<u32> {
        self.tiles.get(&id).and_then(|t| t.texture_level)
    }

    /// GPU bytes charged to `id`: a sample buffer (whether or not the pool holds one for
    /// it now: at most one per resident tile) and its texture, twice with MapBlocks on
    /// (its copy in the block texture is at most as fine).
    pub fn tile_bytes(&self, id: TileId) -> u64 {
        let copies = self.texture_copies();
        self.tiles
            .get(&id)
            .map_or(0, |t| self.sample_buffer_bytes() + copies * t.texture_bytes)
    }

    /// Copies of each tile's GPU texture held: [`super::blocks::TEXTURE_COPIES`] with
    /// MapBlocks on, else 1.
    pub fn texture_copies(&self) -> u64 {
        if self.blocks.is_some() {
            super::blocks::TEXTURE_COPIES
        } else {
            1
        }
    }

    /// Changes whenever an allocation made here is made, replaced or dropped (a texture, the
    /// arena, a tile): a frame after which it changed waits for the GPU, so that what was
    /// dropped is freed (see `Scene::draw`).
    pub fn allocation_epoch(&self) -> (u64, u64, u64) {
        (
            self.next_texture_version,
            self.arena.generation,
            self.residency().total(),
        )
    }

    /// The most tiles whose samples the arena holds at once (the device's limits on one
    /// buffer, or one texture); a frame drawing more leaves the rest undrawn (logged).
    pub fn sample_slots(&self) -> u32 {
        self.max_slots
    }

    /// Lowers [`TileStore::sample_slots`] to `slots` (at least 1), as a smaller device
    /// would: for tests of a frame drawing more tiles than the arena holds.
    pub fn limit_sample_slots(&mut self, slots: u32) {
        self.max_slots = self.max_slots.min(slots.max(1));
    }

    /// Bytes of one tile's slot in the sample arena.
    pub fn sample_buffer_bytes(&self) -> u64 {
        4 * self.slot_words()
    }

    /// Words of one tile's slot.
    fn slot_words(&self) -> u64 {
        slot_words(self.layout)
    }

    /// What the tiles hold on the GPU now: every allocation made here.
    pub fn residency(&self) -> GpuResidency {
        GpuResidency {
            tiles: self.tiles.len() as u64,
            sample_buffers: u64::from(self.arena.slots),
            sample_bytes: self.arena.bytes(),
            texture_bytes: self.tiles.values().map(|t| t.texture_bytes).sum(),
            block_bytes: self.blocks.as_ref().map_or(0, Blocks::bytes),
        }
    }

    /// The largest texture side the adapter takes.
    pub fn max_texture_side(&self) -> u32 {
        self.max_texture_side
    }

    /// Binds tiles block by block with MapBlock textures cut by `layout` (`None`: each tile
    /// with its own texture).
    pub fn set_texture_blocks(&mut self, layout: Option<BlockLayout>) {
        if self.blocks.as_ref().map(|b| b.layout) != layout {
            self.blocks = layout.map(Blocks::new);
        }
    }

    /// Whether MapBlocks are on.
    pub fn texture_blocks(&self) -> Option<BlockLayout> {
        self.blocks.as_ref().map(|b| b.layout)
    }

    /// Makes `id` resident with its heights; it draws with a grey texture until
    /// [`TileStore::upload_texture`], and gets a sample buffer from the pool when it is
    /// drawn. Returns the GPU bytes charged for it.
    pub fn upload_tile(&mut self, id: TileId, heights: Arc<Heights>) -> u64 {
        let texture = self.texture(&[image::RgbaImage::from_pixel(
            1,
            1,
            image::Rgba([128, 128, 128, 255]),
        )]);
        let texture_group = self.texture_bind_group(&texture);
        // A tile that comes back starts afresh: its old buffer may hold other samples.
        self.release_samples(id);
        let texture_version = self.bump_version();
        self.tiles.insert(
            id,
            GpuTile {
                heights,
                texture,
                texture_group,
                texture_version,
                texture_level: None,
                texture_bytes: 4,
                code_base: (0, 0),
            },
        );
        self.forget_block_of(id);
        self.tile_bytes(id)
    }

    fn bump_version(&mut self) -> u64 {
        self.next_texture_version += 1;
        self.next_texture_version
    }

    /// Drops `id`'s block texture at once (it is assembled again when next drawn), so a
    /// block never holds a copy of a texture its tile no longer has.
    fn forget_block_of(&mut self, id: TileId) {
        if let Some(blocks) = &mut self.blocks {
            blocks.forget(id);
        }
    }

    fn release_samples(&mut self, id: TileId) {
        let keep = self.tiles.len();
        if let Some(position) = self.pool.release(id, keep) {
            self.free_positions.push(position);
            self.fit_arena();
        }
    }

    /// Makes the arena hold exactly the pool's slots: a larger one when the pool grew, a
    /// compacted smaller one when it shrank (live slots copied on the GPU, positions
    /// renumbered).
    fn fit_arena(&mut self) {
        let wanted = self.pool.len() as u32;
        if wanted == self.arena.slots && self.free_positions.is_empty() {
            return;
        }
        let arena = Arena::new(
            &self.device,
            self.store,
            wanted,
            self.slot_words(),
            self.arena.generation + 1,
        );
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("sample arena"),
            });
        let old = &self.arena;
        for (next, position) in (0u32..).zip(self.pool.values_mut()) {
            if *position < old.slots {
                old.copy_slot(&mut encoder, *position, &arena, next);
            }
            *position = next;
        }
        self.queue.submit([encoder.finish()]);
        self.free_positions.clear();
        self.arena = arena;
    }

    /// Replaces `id`'s texture by `levels`, coarsest first: the last is the finest and the
    /// texture's top mip, `level` its manifest level. Levels whose side exceeds the
    /// device's limit are left out. Returns the texture's GPU bytes (0 for an absent tile).
    pub fn upload_texture(&mut self, id: TileId, level: u32, levels: &[image::RgbaImage]) -> u64 {
        if !self.tiles.contains_key(&id) || levels.is_empty() {
            return 0;
        }
        let fitting: Vec<image::RgbaImage> = levels
            .iter()
            .filter(|l| l.width().max(l.height()) <= self.max_texture_side)
            .cloned()
            .collect();
        if fitting.is_empty() {
            return 0;
        }
        let dropped = (levels.len() - fitting.len()) as u32;
        let texture = self.texture(&fitting);
        let bytes: u64 = fitting
            .iter()
            .map(|l| u64::from(l.width()) * u64::from(l.height()) * 4)
            .sum();
        self.set_texture(id, texture, level.saturating_sub(dropped), bytes);
        bytes
    }

    fn set_texture(&mut self, id: TileId, texture: wgpu::Texture, level: u32, bytes: u64) {
        let texture_group = self.texture_bind_group(&texture);
        let version = self.bump_version();
        if let Some(tile) = self.tiles.get_mut(&id) {
            tile.texture = texture;
            tile.texture_group = texture_group;
            tile.texture_version = version;
            tile.texture_level = Some(level);
            tile.texture_bytes = bytes;
        }
        self.forget_block_of(id);
    }

    /// Adds `image`, manifest level `level`, as the new top mip of `id`'s texture, which
    /// must hold exactly the levels below it: those are copied on the GPU, not decoded and
    /// uploaded again. Returns false, changing nothing, when that does not hold (no texture
    /// yet, a gap, a size that is not twice the current top, or over the device's limit);
    /// the caller then uploads every level with [`TileStore::upload_texture`].
    pub fn refine_texture(&mut self, id: TileId, level: u32, image: &image::RgbaImage) -> bool {
        let Some(tile) = self.tiles.get(&id) else {
            return false;
        };
        let (side, mips) = (image.width(), tile.texture.mip_level_count());
        if tile.texture_level.map(|l| l + 1) != Some(level)
            || image.height() != side
            || tile.texture.width() * 2 != side
            || side > self.max_texture_side
        {
            return false;
        }
        let copies: Vec<(u32, u32)> = (0..mips).map(|m| (m, m + 1)).collect();
        self.replace_texture(id, level, side, mips + 1, &copies, Some(image));
        true
    }

    /// Keeps only `id`'s coarsest `levels` texture levels (at least one), copying them on
    /// the GPU. Nothing happens when it holds no more than that.
    pub fn coarsen_texture(&mut self, id: TileId, levels: u32) {
        let Some(tile) = self.tiles.get(&id) else {
            return;
        };
        let (mips, Some(finest)) = (tile.texture.mip_level_count(), tile.texture_level) else {
            return;
        };
        let keep = levels.max(1);
        if keep >= mips {
            return;
        }
        let dropped = mips - keep;
        let side = (tile.texture.width() >> dropped).max(1);
        let copies: Vec<(u32, u32)> = (0..keep).map(|m| (m + dropped, m)).collect();
        self.replace_texture(id, finest - dropped, side, keep, &copies, None);
    }

    /// Frees `id`'s GPU resources.
    pub fn remove_tile(&mut self, id: TileId) {
        if self.tiles.remove(&id).is_some() {
            self.release_samples(id);
            self.forget_block_of(id);
        }
    }

    /// A texture with `levels` (coarsest first) as its mips, finest as mip 0.
    fn texture(&self, levels: &[image::RgbaImage]) -> wgpu::Texture {
        let finest = &levels[levels.len() - 1];
        let texture = blank_texture(
            &self.device,
            label::TEXTURE,
            finest.width(),
            finest.height(),
            levels.len() as u32,
        );
        for (mip, image) in levels.iter().rev().enumerate() {
            self.write_mip(&texture, mip as u32, image);
        }
        texture
    }

    fn write_mip(&self, texture: &wgpu::Texture, mip: u32, image: &image::RgbaImage) {
        self.queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture,
                mip_level: mip,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            image.as_raw(),
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(4 * image.width()),
                rows_per_image: Some(image.height()),
            },
            wgpu::Extent3d {
                width: image.width(),
                height: image.height(),
                depth_or_array_layers: 1,
            },
        );
    }

    /// Replaces `id`'s texture by one of `mips` levels whose top mip is `side` texels,
    /// filled by copying `old_mip -> new_mip` pairs from the current texture on the GPU and
    /// writing `top` (when given) as mip 0. `level` is the new finest manifest level.
    fn replace_texture(
        &mut self,
        id: TileId,
        level: u32,
        side: u32,
        mips: u32,
        copies: &[(u32, u32)],
        top: Option<&image::RgbaImage>,
    ) {
        let texture = blank_texture(&self.device, label::TEXTURE, side, side, mips);
        let Some(tile) = self.tiles.get(&id) else {
            return;
        };
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("texture levels"),
            });
        for &(old_mip, new_mip) in copies {
            let mip_side = (side >> new_mip).max(1);
            copy_square(
                &mut encoder,
                (&tile.texture, old_mip, [0, 0]),
                (&texture, new_mip, [0, 0]),
                mip_side,
            );
        }
        if let Some(image) = top {
            self.write_mip(&texture, 0, image);
        }
        self.queue.submit([encoder.finish()]);
        self.set_texture(id, texture, level, mip_chain_bytes(side, side, mips));
    }

    pub(super) fn texture_bind_group(&self, texture: &wgpu::Texture) -> wgpu::BindGroup {
        let view = texture.create_view(&Default::default());
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tile texture"),
            layout: &self.bindings.texture,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(&view),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::Sampler(&self.sampler),
                },
            ],
        })
    }

    /// Hands each of `ids` (resident) a slot of the sample arena, uploading the samples of
    /// those that had none; returns each one's first word in the arena, its code base and
    /// shift (`None`: no room this frame, [`TileStore::sample_slots`] are in use), and the
    /// number of uploads.
    pub(super) fn pool_samples(&mut self, ids: &[TileId]) -> (Vec<Option<[i32; 3]>>, u32) {
        if let Some((position, _)) = self.pool.begin_frame() {
            // What a shrinking pool drops leaves a hole, closed below.
            self.free_positions.push(position);
        }
        let mut fresh = Vec::new();
        let mut held = std::collections::HashSet::with_capacity(ids.len());
        let mut next = self.arena.slots + self.free_positions.len() as u32;
        let mut refused = 0;
        for &id in ids {
            if self.pool.slot_of(id).is_none()
                && self.pool.used_this_frame() >= self.max_slots as usize
            {
                refused += 1;
                continue;
            }
            let free = &mut self.free_positions;
            let got = self.pool.acquire(id, || {
                // A new slot: a position past the arena's end, made room for below.
                next += 1;
                free.pop().unwrap_or(next - 1)
            });
            if got.needs_upload() {
                fresh.push(id);
            }
            held.insert(id);
        }
        if refused > 0 {
            if self.refused == 0 {
                tracing::warn!(
                    tiles = ids.len(),
                    slots = self.max_slots,
                    "more tiles drawn than the sample arena holds on this device: the rest are \
                     left out of the frame"
                );
            }
            self.refused += refused;
        }
        // Fresh slots past the arena's end, or holes: the arena is made to fit first, and
        // everything is uploaded after (a compaction renumbers positions).
        self.fit_arena();
        let words = self.slot_words();
        let mut codes = std::collections::HashMap::with_capacity(fresh.len());
        for &id in &fresh {
            let packed = mesh::pack_codes(&self.tiles[&id].heights);
            let slot = self.pool.slot_of(id).expect("acquired this frame");
            let position = *self.pool.get(slot);
            self.arena.write(&self.queue, position, &packed.words);
            codes.insert(id, (packed.base, packed.shift));
        }
        let uploads = fresh.len() as u32;
        let out = ids
            .iter()
            .map(|id| {
                if !held.contains(id) {
                    return None;
                }
                let slot = self.pool.slot_of(*id).expect("acquired this frame");
                let first = i64::from(*self.pool.get(slot)) * words as i64;
                let (base, shift) = match codes.get(id) {
                    Some(&c) => c,
                    None => self.tiles[id].code_base,
                };
                Some([i32::try_from(first).unwrap_or(i32::MAX), base, shift as i32])
            })
            .collect();
        for (id, c) in codes {
            if let Some(t) = self.tiles.get_mut(&id) {
                t.code_base = c;
            }
        }
        (out, uploads)
    }

    /// With MapBlocks on, the block of each of `ids` whose texture is assembled (blocks
    /// whose tiles changed are assembled again first); `None` for a tile bound with its own
    /// texture (blocks off, or a tile its block does not hold).
    pub(super) fn frame_blocks(&mut self, ids: &[TileId]) -> Vec<Option<[u32; 2]>> {
        let Some(layout) = self.texture_blocks() else {
            return vec![None; ids.len()];
        };
        // MapBlocks gather level-0 tiles; a tile of a coarser level draws with its own
        // texture (it already covers the area of a block of tiles).
        let keys: std::collections::BTreeSet<[u32; 2]> = ids
            .iter()
            .filter(|id| id.level == 0)
            .map(|&id| layout.block_of(id))
            .collect();
        for key in keys {
            self.assemble_block(layout, key);
        }
        let blocks = self.blocks.as_ref().expect("blocks on");
        ids.iter()
            .map(|&id| {
                let key = layout.block_of(id);
                (id.level == 0 && blocks.holds(key, id)).then_some(key)
            })
            .collect()
    }

    /// The bind group and uv rectangle `id` is drawn with: its block's when `block` is set,
    /// else its own.
    pub(super) fn binding_of(
        &self,
        id: TileId,
        block: Option<[u32; 2]>,
    ) -> (&wgpu::BindGroup, [f32; 4]) {
        if let (Some(key), Some(blocks)) = (block, &self.blocks)
            && let Some(b) = blocks.assembled.get(&key)
        {
            return (&b.group, b.rect.uv(id));
        }
        (&self.tiles[&id].texture_group, [0.0, 0.0, 1.0, 1.0])
    }

    /// Assembles block `key`'s texture from its resident tiles' textures, unless it is
    /// current: the mips of every tile at the finest level any of them holds, copied side by
    /// side. A tile still at a coarser level (or untextured) is left out of the block and
    /// drawn with its own texture, so no tile is drawn coarser than it holds. A block is
    /// made only of a full rectangle of such tiles, so its texture holds no texel that is
    /// not a copy of a held tile texture (no holes, charged to nobody).
    fn assemble_block(&mut self, layout: BlockLayout, key: [u32; 2]) {
        let members: Vec<(TileId, u64)> = layout
            .members(key)
            .filter_map(|id| self.tiles.get(&id).map(|t| (id, t.texture_version)))
            .collect();
        let blocks = self.blocks.as_mut().expect("blocks on");
        if blocks.is_current(key, &members) {
            return;
        }
        blocks.assembled.remove(&key);
        let Some(level) = members
            .iter()
            .filter_map(|(id, _)| self.tiles[id].texture_level)
            .max()
        else {
            return;
        };
        // The tiles at that level, square, all of one side; the mips all of them have.
        let (mut side, mut mips) = (None, u32::MAX);
        let mut sources = Vec::with_capacity(members.len());
        for (id, _) in &members {
            let tile = &self.tiles[id];
            let (width, count) = (tile.texture.width(), tile.texture.mip_level_count());
            if tile.texture_level != Some(level)
                || tile.texture.height() != width
                || *side.get_or_insert(width) != width
            {
                continue;
            }
            mips = mips.min(count);
            sources.push(*id);
        }
        let (Some(side), Some(rect)) = (side, BlockRect::around(sources.iter().copied())) else {
            return;
        };
        let [w, h] = rect.size();
        if u64::from(w) * u64::from(h) != sources.len() as u64 || sources.len() < 2 {
            // Holes (a tile not resident, or coarser), or a single tile: its own texture
            // serves as well.
            blocks_mut(&mut self.blocks).remember_unassembled(key, members);
            return;
        }
        let mips = mips.min(side.ilog2() + 1);
        let texture = blank_texture(&self.device, label::BLOCK, w * side, h * side, mips);
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("map block"),
            });
        for id in &sources {
            let [x, y] = rect.texel_origin(*id, side);
            for mip in 0..mips {
                copy_square(
                    &mut encoder,
                    (&self.tiles[id].texture, mip, [0, 0]),
                    (&texture, mip, [x >> mip, y >> mip]),
                    side >> mip,
                );
            }
        }
        self.queue.submit([encoder.finish()]);
        let bytes = mip_chain_bytes(w * side, h * side, mips);
        let group = self.texture_bind_group(&texture);
        blocks_mut(&mut self.blocks).insert(key, members, sources, rect, group, bytes);
    }
}

fn blocks_mut(blocks: &mut Option<Blocks>) -> &mut Blocks {
    blocks.as_mut().expect("blocks on")
}

/// Words of one tile's slot in the sample arena.
fn slot_words(layout: Layout) -> u64 {
    mesh::words_for(u64::from(layout.tile_size).pow(2))
}

/// A tile texture of `mips` levels whose top mip is `width` x `height`, contents undefined.
pub(super) fn blank_texture(
    device: &wgpu::Device,
    label: &str,
    width: u32,
    height: u32,
    mips: u32,
) -> wgpu::Texture {
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        },
        mip_level_count: mips,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: wgpu::TextureFormat::Rgba8UnormSrgb,
        // COPY_SRC: a finer or coarser replacement copies the levels it keeps from it.
        usage: wgpu::TextureUsages::TEXTURE_BINDING
            | wgpu::TextureUsages::COPY_DST
            | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    })
}

/// Copies a `side` x `side` square from `(texture, mip, origin)` to another.
fn copy_square(
    encoder: &mut wgpu::CommandEncoder,
    from: (&wgpu::Texture, u32, [u32; 2]),
    to: (&wgpu::Texture, u32, [u32; 2]),
    side: u32,
) {
    fn info<'t>(
        (texture, mip, [x, y]): (&'t wgpu::Texture, u32, [u32; 2]),
    ) -> wgpu::TexelCopyTextureInfo<'t> {
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: mip,
            origin: wgpu::Origin3d { x, y, z: 0 },
            aspect: wgpu::TextureAspect::All,
        }
    }
    let (from, to) = (info(from), info(to));
    encoder.copy_texture_to_texture(
        from,
        to,
        wgpu::Extent3d {
            width: side.max(1),
            height: side.max(1),
            depth_or_array_layers: 1,
        },
    );
}

/// Bytes of an RGBA texture of `mips` levels whose top is `width` x `height`.
pub fn mip_chain_bytes(width: u32, height: u32, mips: u32) -> u64 {
    (0..mips)
        .map(|m| u64::from((width >> m).max(1)) * u64::from((height >> m).max(1)) * 4)
        .sum()
}
