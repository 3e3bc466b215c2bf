//! The projected grids' copy of the terrain: one atlas of height pyramids and one of
//! colours, a slot per tile, fed from the tiles the pager makes resident.
//!
//! Livny et al. keep nested clipmaps centred on the viewer in one texture and update them
//! with L-shaped strips as the viewer moves (F-shaped over the whole atlas). Here the
//! nesting is the pager's: each level of the pyramid holds a square of tiles around the
//! viewpoint, and the atlas gives each resident tile a slot, nearest rings first and, within a
//! ring, coarse before fine ([`slot_order`]); when the viewer moves, the tiles entering the
//! squares (an L-shaped belt per level) are the only ones copied in. The shader finds a
//! place's tile through a table with an entry per tile of every level, so no texture is
//! bound per level and no branch picks one.
//!
//! A slot ([`SlotLayout`]) holds the tile's heights as its mip 0, averaged mips down to two
//! samples a side (the pyramids of both papers: each coarser sample the `[1 2 1]^2 / 16`
//! mean of the finer ones), and min/max blocks at every mip above 0 (Löffler et al.'s min
//! and max pyramids, which the error and the ray casting read). Heights are `f32` metres:
//! 8 bytes per sample in all. A colour slot holds the tile's texture mips that fit its side.
//!
//! Every allocation is labelled `terrain/` and counted ([`Atlas::bytes`]): the slots in use
//! are charged to their tiles, the rest to the method.

use crate::render::tiles::mip_chain_bytes;
use crate::render::{Gpu, TileStore};
use std::collections::{HashMap, HashSet};
use terrain_shaders::{GRID_MAX_MIPS, SlotInfo};
use terrain_shared::{Manifest, TileId};

/// Largest side of a colour slot, texels: a tile's texture above it is copied from the mip
/// that fits.
pub const MAX_COLOUR_SIDE: u32 = 256;
/// Slots the atlas grows and shrinks by: it grows to a multiple of this and gives slots
/// back once it holds twice this many more than its tiles need (each resize copies every
/// tile in again), so it holds at most `2 * CAPACITY_STEP - 1` slots no tile uses: what
/// [`Atlas::reserved_bytes`] keeps room for. 2 keeps that to three slots (about 660 KiB
/// for tiles of 129^2 samples with 128^2 textures) while a square growing by belts of 8 or
/// more tiles still resizes once a belt.
pub const CAPACITY_STEP: u32 = 2;
/// Most slots an atlas holds, whatever the adapter allows.
pub const MAX_SLOTS: u32 = 4096;

/// Where each mip of a slot lies in the slot's floats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MipLayout {
    /// First float of the averaged heights of this mip, `side * side` of them.
    pub averaged: u32,
    /// First float of the min/max blocks (pairs) of this mip; unused at mip 0.
    pub blocks: u32,
    /// Samples per side: `2^(n - m) + 1`.
    pub side: u32,
    /// Blocks per side: `2^(n - m)` (a block spans `2^m` cells of the tile).
    pub per_side: u32,
}

/// The layout of one slot of the height atlas, for tiles of `2^n + 1` samples a side.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SlotLayout {
    /// The exponent `n`.
    pub n: u32,
    pub mips: Vec<MipLayout>,
    /// Floats per slot.
    pub floats: u32,
}

impl SlotLayout {
    /// The layout for tiles of `tile_size` samples a side (`2^n + 1`, `n` at most
    /// [`GRID_MAX_MIPS`] - 1).
    pub fn new(tile_size: u32) -> SlotLayout {
        let n = (tile_size - 1)
            .trailing_zeros()
            .min(GRID_MAX_MIPS as u32 - 1);
        let mut mips = Vec::with_capacity(n as usize + 1);
        let mut at = 0;
        for m in 0..=n {
            let side = (1 << (n - m)) + 1;
            mips.push(MipLayout {
                averaged: at,
                blocks: 0,
                side,
                per_side: 1 << (n - m),
            });
            at += side * side;
        }
        for mip in mips.iter_mut().skip(1) {
            mip.blocks = at;
            at += 2 * mip.per_side * mip.per_side;
        }
        SlotLayout {
            n,
            mips,
            floats: at,
        }
    }

    /// The slot's floats for a tile of `samples` (row-major, `(2^n + 1)^2` heights, metres).
    pub fn fill(&self, samples: &[f32]) -> Vec<f32> {
        let mut out = vec![0.0f32; self.floats as usize];
        let side0 = self.mips[0].side as usize;
        out[..side0 * side0].copy_from_slice(&samples[..side0 * side0]);
        for m in 1..self.mips.len() {
            let (fine, coarse) = (self.mips[m - 1], self.mips[m]);
            let (fs, cs) = (fine.side as usize, coarse.side as usize);
            let (before, after) = out.split_at_mut(coarse.averaged as usize);
            let src = &before[fine.averaged as usize..fine.averaged as usize + fs * fs];
            let dst = &mut after[..cs * cs];
            for y in 0..cs {
                for x in 0..cs {
                    dst[y * cs + x] = tent(src, fs, 2 * x, 2 * y);
                }
            }
        }
        // Min/max blocks: mip 1 from the samples (3 x 3 each), each next from its four
        // children, whose union is its block (they share their edges).
        for m in 1..self.mips.len() {
            let mip = self.mips[m];
            let k = mip.per_side as usize;
            for by in 0..k {
                for bx in 0..k {
                    let (lo, hi) = if m == 1 {
                        let mut r = (f32::INFINITY, f32::NEG_INFINITY);
                        for y in 2 * by..=2 * by + 2 {
                            for x in 2 * bx..=2 * bx + 2 {
                                let h = samples[y * side0 + x];
                                r = (r.0.min(h), r.1.max(h));
                            }
                        }
                        r
                    } else {
                        let child = self.mips[m - 1];
                        let ck = child.per_side as usize;
                        let mut r = (f32::INFINITY, f32::NEG_INFINITY);
                        for (cx, cy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                            let i = child.blocks as usize + 2 * ((2 * by + cy) * ck + 2 * bx + cx);
                            r = (r.0.min(out[i]), r.1.max(out[i + 1]));
                        }
                        r
                    };
                    let i = mip.blocks as usize + 2 * (by * k + bx);
                    out[i] = lo;
                    out[i + 1] = hi;
                }
            }
        }
        out
    }
}

/// The `[1 2 1]^2 / 16` mean around sample `(x, y)` of a `side`-square raster; a neighbour
/// past the edge is extrapolated linearly (`2 h(x) - h(x + 1)`), so a plane stays a plane.
fn tent(src: &[f32], side: usize, x: usize, y: usize) -> f32 {
    let at = |x: usize, y: usize| src[y * side + x];
    let row = |y: usize| {
        let c = at(x, y);
        let l = if x > 0 {
            at(x - 1, y)
        } else {
            2.0 * c - at(x + 1, y)
        };
        let r = if x + 1 < side {
            at(x + 1, y)
        } else {
            2.0 * c - at(x - 1, y)
        };
        (l + 2.0 * c + r) / 4.0
    };
    let c = row(y);
    let u = if y > 0 {
        row(y - 1)
    } else {
        2.0 * c - row(y + 1)
    };
    let d = if y + 1 < side {
        row(y + 1)
    } else {
        2.0 * c - row(y - 1)
    };
    (u + 2.0 * c + d) / 4.0
}

/// Texels per colour slot side for `manifest`'s textures.
pub fn colour_side(manifest: &Manifest) -> u32 {
    manifest
        .texture
        .size
        .clamp(1, MAX_COLOUR_SIDE)
        .next_power_of_two()
        .min(MAX_COLOUR_SIDE)
}

/// GPU bytes of one slot of an atlas for `manifest`'s tiles, known before any GPU work:
/// what a projected grid holds per tile.
pub fn slot_bytes_for(manifest: &Manifest) -> u64 {
    slot_bytes(&SlotLayout::new(manifest.tile_size), colour_side(manifest))
}

fn slot_bytes(layout: &SlotLayout, colour_side: u32) -> u64 {
    u64::from(layout.floats) * 4 + size_of::<SlotInfo>() as u64 + colour_slot_bytes(colour_side)
}

/// GPU bytes of one colour slot of `side` texels with its mips.
fn colour_slot_bytes(side: u32) -> u64 {
    mip_chain_bytes(side, side, side.trailing_zeros() + 1)
}

/// The order in which resident tiles get slots: by ring around the viewpoint at their own
/// level (the Chebyshev distance, in tiles, from the tile of that level under the
/// viewpoint), then coarse before fine: equal squares of tiles per level, nested, as
/// clipmaps are.
pub fn slot_order(tiles: &[TileId], viewpoint_samples: [f64; 2], cells: u32) -> Vec<TileId> {
    let ring = |id: &TileId| {
        let side = f64::from(cells) * f64::from(1u32 << id.level.min(31));
        let cx = (viewpoint_samples[0] / side).floor();
        let cy = (viewpoint_samples[1] / side).floor();
        (f64::from(id.x) - cx)
            .abs()
            .max((f64::from(id.y) - cy).abs()) as u64
    };
    let mut out = tiles.to_vec();
    out.sort_by_key(|id| (ring(id), std::cmp::Reverse(id.level), id.y, id.x));
    out
}

/// A tile in the atlas.
#[derive(Debug, Clone, Copy)]
struct Slot {
    index: u32,
    /// The version of the tile's texture copied into the colour atlas.
    texture_version: Option<u64>,
}

/// What [`Atlas::update`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct AtlasUpdate {
    /// Tiles copied in (heights and colour).
    pub placed: u32,
    /// Tiles whose colour was copied again (their texture changed).
    pub recoloured: u32,
    pub evicted: u32,
}

/// The GPU atlases and the table that finds a tile's slot. See the module documentation.
#[derive(Debug)]
pub struct Atlas {
    pub layout: SlotLayout,
    /// Texels per colour slot side, and colour mips.
    pub colour_side: u32,
    colour_mips: u32,
    colour_per_row: u32,
    /// The most colour slots a row of the colour atlas holds (the adapter's texture side).
    per_row_max: u32,
    capacity: u32,
    max_capacity: u32,
    heights: wgpu::Buffer,
    infos: wgpu::Buffer,
    table: wgpu::Buffer,
    colour: wgpu::Texture,
    table_cpu: Vec<u32>,
    table_dirty: bool,
    slots: HashMap<TileId, Slot>,
    free: Vec<u32>,
    /// Per level, where its tiles start in the table, its columns and rows.
    pub levels: Vec<[u32; 3]>,
    /// Bumped when the buffers are made anew (bind groups must be too).
    pub generation: u64,
}

impl Atlas {
    /// An empty atlas for `manifest`'s tiles.
    pub fn new(gpu: &Gpu, manifest: &Manifest) -> Atlas {
        let layout = SlotLayout::new(manifest.tile_size);
        let colour_side = colour_side(manifest);
        let limits = gpu.device.limits();
        let slot_floats_bytes = u64::from(layout.floats) * 4;
        let by_buffer = (limits.max_storage_buffer_binding_size / slot_floats_bytes)
            .min(limits.max_buffer_size / slot_floats_bytes) as u32;
        let per_side = (limits.max_texture_dimension_2d / colour_side).max(1);
        let max_capacity = by_buffer.min(per_side * per_side).clamp(1, MAX_SLOTS);
        let levels = (0..manifest.level_count())
            .map(|l| {
                let g = manifest.grid(l);
                [manifest.level_offset(l) as u32, g.columns, g.rows]
            })
            .collect();
        let table_cpu = vec![0u32; manifest.tile_count().max(1)];
        let (heights, infos, colour, colour_per_row) =
            allocate(gpu, &layout, colour_side, 0, max_capacity);
        let table = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("terrain/grid atlas table"),
            size: (table_cpu.len() * 4) as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        Atlas {
            colour_mips: colour_side.trailing_zeros() + 1,
            per_row_max: (limits.max_texture_dimension_2d / colour_side).max(1),
            layout,
            colour_side,
            colour_per_row,
            capacity: 0,
            max_capacity,
            heights,
            infos,
            table,
            colour,
            table_cpu,
            table_dirty: true,
            slots: HashMap::new(),
            free: Vec::new(),
            levels,
            generation: 0,
        }
    }

    /// Slots the atlas can hold at most.
    pub fn max_capacity(&self) -> u32 {
        self.max_capacity
    }

    /// Tiles in the atlas.
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    /// Whether `id` has a slot.
    pub fn holds(&self, id: TileId) -> bool {
        self.slots.contains_key(&id)
    }

    /// GPU bytes of one slot: heights, its info and its colour mips.
    pub fn slot_bytes(&self) -> u64 {
        slot_bytes(&self.layout, self.colour_side)
    }

    /// What each resident tile is charged: a slot, and its share of the colour slots a
    /// colour atlas of several rows leaves unused at the end of its last row (fewer than
    /// one a row, [`allocate`]).
    pub fn tile_charge(&self) -> u64 {
        self.slot_bytes()
            + colour_slot_bytes(self.colour_side).div_ceil(u64::from(self.per_row_max))
    }

    /// The most the atlas holds beyond what its tiles are charged ([`Atlas::tile_charge`]):
    /// the table that finds each tile's slot (GPU and CPU), the slots no tile uses (at most
    /// `2 * CAPACITY_STEP - 1`, one at least), and one colour slot of a last row's rounding.
    pub fn reserved_bytes(&self) -> u64 {
        2 * 4 * self.table_cpu.len() as u64
            + u64::from(2 * CAPACITY_STEP - 1) * self.slot_bytes()
            + colour_slot_bytes(self.colour_side)
    }

    /// Bytes of the table on the CPU (its copy on the GPU is in [`Atlas::bytes`]).
    pub fn table_cpu_bytes(&self) -> u64 {
        4 * self.table_cpu.len() as u64
    }

    /// What the atlas holds beyond what its tiles with slots are charged, CPU table included.
    pub fn unused_bytes(&self) -> u64 {
        (self.bytes() + 4 * self.table_cpu.len() as u64)
            .saturating_sub(self.slots.len() as u64 * self.tile_charge())
    }

    /// Every GPU byte the atlas holds.
    pub fn bytes(&self) -> u64 {
        self.heights.size() + self.infos.size() + self.table.size() + colour_bytes(&self.colour)
    }

    /// The colour atlas's size in texels, and slots per row.
    pub fn colour_size(&self) -> [u32; 2] {
        [self.colour.width(), self.colour.height()]
    }

    pub fn heights_buffer(&self) -> &wgpu::Buffer {
        &self.heights
    }

    pub fn infos_buffer(&self) -> &wgpu::Buffer {
        &self.infos
    }

    pub fn table_buffer(&self) -> &wgpu::Buffer {
        &self.table
    }

    pub fn colour_texture(&self) -> &wgpu::Texture {
        &self.colour
    }

    /// Gives slots to the first tiles of `wanted` (in [`slot_order`], each with its distance
    /// from the full-resolution surface, metres) that fit, takes them from the others, and
    /// copies in what changed: a new tile's heights and colour, a texture that changed.
    /// Copies are recorded into `encoder`.
    pub fn update(
        &mut self,
        gpu: &Gpu,
        encoder: &mut wgpu::CommandEncoder,
        tiles: &TileStore,
        manifest: &Manifest,
        wanted: &[(TileId, f32)],
    ) -> AtlasUpdate {
        let mut report = AtlasUpdate::default();
        let deviation_of: HashMap<TileId, f32> = wanted.iter().copied().collect();
        let keep: Vec<TileId> = wanted
            .iter()
            .map(|&(id, _)| id)
            .filter(|&id| tiles.contains(id) && manifest.index(id).is_some())
            .take(self.max_capacity as usize)
            .collect();
        let keep_set: HashSet<TileId> = keep.iter().copied().collect();
        let leaving: Vec<TileId> = self
            .slots
            .keys()
            .filter(|id| !keep_set.contains(id))
            .copied()
            .collect();
        for id in leaving {
            self.release(id, manifest);
            report.evicted += 1;
        }
        let needed = keep.len() as u32;
        if needed > self.capacity || self.capacity >= needed + 2 * CAPACITY_STEP {
            self.resize(gpu, needed, manifest);
        }
        for &id in &keep {
            let index = match self.slots.get(&id) {
                Some(slot) => slot.index,
                None => {
                    let Some(index) = self.free.pop() else {
                        break;
                    };
                    let Some(heights) = tiles.heights(id) else {
                        self.free.push(index);
                        continue;
                    };
                    let floats = self.layout.fill(&heights.to_metres_f32());
                    gpu.queue.write_buffer(
                        &self.heights,
                        u64::from(index) * u64::from(self.layout.floats) * 4,
                        bytemuck::cast_slice(&floats),
                    );
                    self.slots.insert(
                        id,
                        Slot {
                            index,
                            texture_version: None,
                        },
                    );
                    if let Some(entry) = manifest.index(id) {
                        self.table_cpu[entry] = index + 1;
                        self.table_dirty = true;
                    }
                    report.placed += 1;
                    index
                }
            };
            let Some((texture, version)) = tiles.texture_of(id) else {
                continue;
            };
            let slot = self.slots.get_mut(&id).expect("placed above");
            if slot.texture_version == Some(version) {
                continue;
            }
            if slot.texture_version.is_some() {
                report.recoloured += 1;
            }
            slot.texture_version = Some(version);
            let colour = copy_colour(
                encoder,
                texture,
                &self.colour,
                self.colour_side,
                self.colour_mips,
                self.place_of(index),
            );
            let record = manifest.tile(id).expect("checked above");
            let deviation = deviation_of.get(&id).copied().unwrap_or(0.0);
            let info = SlotInfo {
                bounds: [deviation, record.min_m, record.max_m, 0.0],
                colour,
            };
            gpu.queue.write_buffer(
                &self.infos,
                u64::from(index) * size_of::<SlotInfo>() as u64,
                bytemuck::bytes_of(&info),
            );
        }
        if self.table_dirty {
            gpu.queue
                .write_buffer(&self.table, 0, bytemuck::cast_slice(&self.table_cpu));
            self.table_dirty = false;
        }
        report
    }

    /// Forgets `id` at once (its tile left).
    pub fn release(&mut self, id: TileId, manifest: &Manifest) {
        if let Some(slot) = self.slots.remove(&id) {
            self.free.push(slot.index);
            if let Some(entry) = manifest.index(id) {
                self.table_cpu[entry] = 0;
                self.table_dirty = true;
            }
        }
    }

    fn place_of(&self, index: u32) -> [u32; 2] {
        [index % self.colour_per_row, index / self.colour_per_row]
    }

    /// Makes room for `needed` slots, rounded up to [`CAPACITY_STEP`] (up to the most), or
    /// gives back what is held past that: the buffers are made anew and every tile is copied
    /// in again.
    fn resize(&mut self, gpu: &Gpu, needed: u32, manifest: &Manifest) {
        let capacity = needed
            .div_ceil(CAPACITY_STEP)
            .saturating_mul(CAPACITY_STEP)
            .min(self.max_capacity);
        let (heights, infos, colour, per_row) = allocate(
            gpu,
            &self.layout,
            self.colour_side,
            capacity,
            self.max_capacity,
        );
        self.heights = heights;
        self.infos = infos;
        self.colour = colour;
        self.colour_per_row = per_row;
        self.capacity = capacity;
        let ids: Vec<TileId> = self.slots.keys().copied().collect();
        for id in ids {
            self.release(id, manifest);
        }
        self.free = (0..capacity).rev().collect();
        self.generation += 1;
    }
}

fn colour_bytes(texture: &wgpu::Texture) -> u64 {
    mip_chain_bytes(texture.width(), texture.height(), texture.mip_level_count())
}

/// Buffers and the colour texture for `capacity` slots (at least one, so bindings are never
/// empty).
fn allocate(
    gpu: &Gpu,
    layout: &SlotLayout,
    colour_side: u32,
    capacity: u32,
    max_capacity: u32,
) -> (wgpu::Buffer, wgpu::Buffer, wgpu::Texture, u32) {
    let slots = capacity.max(1);
    let heights = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("terrain/grid height atlas"),
        size: u64::from(slots) * u64::from(layout.floats) * 4,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let infos = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("terrain/grid slot infos"),
        size: u64::from(slots) * size_of::<SlotInfo>() as u64,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let max_side = gpu.device.limits().max_texture_dimension_2d;
    let per_row_max = (max_side / colour_side).max(1).min(max_capacity.max(1));
    // Rows as full as each other: the last one lacks fewer slots than there are rows.
    let rows = slots.div_ceil(per_row_max);
    let per_row = slots.div_ceil(rows);
    let colour = gpu.device.create_texture(&wgpu::TextureDescriptor {
        label: Some("terrain/grid colour atlas"),
        size: wgpu::Extent3d {
            width: per_row * colour_side,
            height: rows * colour_side,
            depth_or_array_layers: 1,
        },
        mip_level_count: colour_side.trailing_zeros() + 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: wgpu::TextureFormat::Rgba8UnormSrgb,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    });
    (heights, infos, colour, per_row)
}

/// Copies the mips of a tile's `texture` that fit a colour slot of `side` texels into the
/// slot at `place` of `atlas`; returns the slot's colour info (place, finest and coarsest
/// mip held). A texture that is not a square of a power of two leaves the slot grey-less:
/// only its coarsest mip, unwritten.
fn copy_colour(
    encoder: &mut wgpu::CommandEncoder,
    texture: &wgpu::Texture,
    atlas: &wgpu::Texture,
    side: u32,
    mips: u32,
    place: [u32; 2],
) -> [u32; 4] {
    let top = texture.width();
    if top != texture.height() || !top.is_power_of_two() {
        return [place[0], place[1], mips - 1, mips - 1];
    }
    // Tile mip `src` lands in slot mip `dst`.
    let (src0, dst0) = if top >= side {
        ((top / side).trailing_zeros(), 0)
    } else {
        (0, (side / top).trailing_zeros())
    };
    let count = (texture.mip_level_count() - src0.min(texture.mip_level_count())).min(mips - dst0);
    for k in 0..count {
        let (src, dst) = (src0 + k, dst0 + k);
        let texels = side >> dst;
        encoder.copy_texture_to_texture(
            wgpu::TexelCopyTextureInfo {
                texture,
                mip_level: src,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::TexelCopyTextureInfo {
                texture: atlas,
                mip_level: dst,
                origin: wgpu::Origin3d {
                    x: place[0] * texels,
                    y: place[1] * texels,
                    z: 0,
                },
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::Extent3d {
                width: texels,
                height: texels,
                depth_or_array_layers: 1,
            },
        );
    }
    if count == 0 {
        return [place[0], place[1], mips - 1, mips - 1];
    }
    [place[0], place[1], dst0, dst0 + count - 1]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::Rng;

    fn check_bounds(layout: &SlotLayout, samples: &[f32], floats: &[f32]) {
        let side = layout.mips[0].side as usize;
        for mip in &layout.mips[1..] {
            let span = (side - 1) / mip.per_side as usize;
            for by in 0..mip.per_side as usize {
                for bx in 0..mip.per_side as usize {
                    let mut lo = f32::INFINITY;
                    let mut hi = f32::NEG_INFINITY;
                    for y in by * span..=(by + 1) * span {
                        for x in bx * span..=(bx + 1) * span {
                            lo = lo.min(samples[y * side + x]);
                            hi = hi.max(samples[y * side + x]);
                        }
                    }
                    let i = mip.blocks as usize + 2 * (by * mip.per_side as usize + bx);
                    assert_eq!(
                        (floats[i], floats[i + 1]),
                        (lo, hi),
                        "block ({bx}, {by}) of a {span}-cell mip"
                    );
                }
            }
        }
    }

    #[test]
    fn min_max_blocks_are_the_extremes_of_the_samples_they_cover() {
        let mut rng = Rng(7);
        for tile_size in [3u32, 5, 17, 33] {
            let layout = SlotLayout::new(tile_size);
            let samples: Vec<f32> = (0..tile_size * tile_size)
                .map(|_| rng.range_f32(-300.0, 700.0).round())
                .collect();
            let floats = layout.fill(&samples);
            assert_eq!(floats.len(), layout.floats as usize);
            check_bounds(&layout, &samples, &floats);
        }
    }

    #[test]
    fn averaged_mips_keep_a_plane_and_end_at_two_samples_a_side() {
        let layout = SlotLayout::new(17);
        assert_eq!(layout.mips.len(), 5);
        assert_eq!(layout.mips.last().map(|m| m.side), Some(2));
        let plane = |x: f32, y: f32| 3.0 * x - 2.0 * y + 100.0;
        let samples: Vec<f32> = (0..17 * 17)
            .map(|i| plane((i % 17) as f32, (i / 17) as f32))
            .collect();
        let floats = layout.fill(&samples);
        for (m, mip) in layout.mips.iter().enumerate() {
            let step = (1 << m) as f32;
            for y in 0..mip.side {
                for x in 0..mip.side {
                    let got = floats[(mip.averaged + y * mip.side + x) as usize];
                    let want = plane(x as f32 * step, y as f32 * step);
                    assert!(
                        (got - want).abs() < 1e-3,
                        "mip {m} ({x}, {y}): {got} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn averaged_mips_smooth_a_spike() {
        let layout = SlotLayout::new(9);
        let mut samples = vec![0.0f32; 81];
        samples[4 * 9 + 4] = 16.0;
        let floats = layout.fill(&samples);
        let mip1 = layout.mips[1];
        // The spike's sample carries weight 4/16 at mip 1.
        let centre = floats[(mip1.averaged + 2 * mip1.side + 2) as usize];
        assert!((centre - 4.0).abs() < 1e-6, "{centre}");
    }

    #[test]
    fn slots_go_to_nearer_rings_first_and_coarse_before_fine_within_a_ring() {
        let cells = 4;
        let tiles = vec![
            TileId::at(0, 5, 5),
            TileId::at(0, 0, 0),
            TileId::at(1, 0, 0),
            TileId::at(0, 1, 0),
            TileId::at(1, 2, 2),
        ];
        // The viewpoint in tile (0, 0) of both levels.
        let order = slot_order(&tiles, [1.0, 1.0], cells);
        assert_eq!(
            order,
            vec![
                TileId::at(1, 0, 0),
                TileId::at(0, 0, 0),
                TileId::at(0, 1, 0),
                TileId::at(1, 2, 2),
                TileId::at(0, 5, 5),
            ]
        );
    }
}
