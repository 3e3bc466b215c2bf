//! The index sets methods draw tiles with ([`IndexSet`]), and a render pass of a frame
//! ([`FramePass`]): binding a tile's parameters and samples,
//! the tile pipeline or a method's own, and drawing index sets, counted in the frame's
//! statistics.

use super::{Prepared, RenderStats, Renderer};
use crate::render::gpu::Gpu;

/// An index buffer a method draws tiles with (through the tile pipeline: indices below
/// `n * n` are samples, see `terrain.wgsl` for the others).
#[derive(Debug)]
pub struct IndexSet {
    pub buffer: wgpu::Buffer,
    /// Indices.
    pub len: u32,
    /// Triangles it draws (strip joins not counted).
    pub triangles: u32,
}

impl IndexSet {
    /// Uploads `indices` (a strip) drawing `triangles` triangles. Labelled as terrain
    /// memory ([`crate::render::tiles::TERRAIN_LABEL`]).
    pub fn new(gpu: &Gpu, indices: &[u32], triangles: u32) -> IndexSet {
        let bytes: &[u8] = bytemuck::cast_slice(indices);
        let buffer = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("terrain/index set"),
            size: (bytes.len() as u64).max(4),
            usage: wgpu::BufferUsages::INDEX | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        gpu.queue.write_buffer(&buffer, 0, bytes);
        IndexSet {
            buffer,
            len: indices.len() as u32,
            triangles,
        }
    }

    /// GPU bytes.
    pub fn bytes(&self) -> u64 {
        self.buffer.size()
    }
}

/// A render pass of a frame. See the module documentation.
#[derive(Debug)]
pub struct FramePass<'p> {
    pub(super) pass: wgpu::RenderPass<'static>,
    pub(super) renderer: &'p Renderer,
    pub(super) prepared: &'p Prepared,
    pub(super) stats: &'p mut RenderStats,
    /// The MapBlock whose texture is bound.
    pub(super) bound: Option<[u32; 2]>,
    /// Whether the tiles' parameters and samples (group 1) are bound.
    pub(super) tiles_bound: bool,
    /// The tile bound last (its instance index), and the index buffer set last.
    pub(super) slot: u32,
    pub(super) index_buffer: Option<wgpu::Buffer>,
    /// The tile pipeline set (`Some(true)`: the clipped one), `None` after another.
    pub(super) pipeline: Option<bool>,
    pub(super) clip_everything: bool,
}

impl FramePass<'_> {
    /// The pass itself, for a method's own pipeline (set it, draw, then
    /// [`FramePass::use_tile_pipeline`] before binding tiles again).
    pub fn raw(&mut self) -> &mut wgpu::RenderPass<'static> {
        &mut self.pass
    }

    /// Makes the tile pipeline be set again at the next [`FramePass::bind_tile`] (after a
    /// pipeline of the method's own).
    pub fn use_tile_pipeline(&mut self) {
        self.pipeline = None;
        self.bound = None;
        self.tiles_bound = false;
        self.index_buffer = None;
    }

    /// Clips every tile bound from now on at the terrain's edge, not only the padded ones:
    /// for what a method draws that may reach past it from any tile (a planar shadow).
    pub fn clip_everything(&mut self) {
        self.clip_everything = true;
    }

    /// Makes prepared tile `slot` the one drawn next, binding its texture (a MapBlock's only
    /// when the block changes); the tiles' parameters and samples are bound once a pass.
    pub fn bind_tile(&mut self, slot: usize) {
        let r = self.renderer;
        let clipped = self.clip_everything || self.prepared.clipped[slot];
        if self.pipeline != Some(clipped) {
            self.pass.set_pipeline(if clipped {
                &r.clipped_pipeline
            } else {
                &r.tile_pipeline
            });
            self.pipeline = Some(clipped);
        }
        if !self.tiles_bound
            && let Some((group, _)) = &r.tiles_group
        {
            self.pass.set_bind_group(1, group, &[]);
            self.pass.set_vertex_buffer(0, r.tile_params.slice(..));
            self.tiles_bound = true;
        }
        self.slot = slot as u32;
        let block = self.prepared.blocks[slot];
        if block.is_none() || block != self.bound {
            let (group, _) = r.tiles.binding_of(self.prepared.ids[slot], block);
            self.pass.set_bind_group(2, group, &[]);
            self.stats.texture_binds += 1;
            self.bound = block;
        }
    }

    /// Draws `set` for the tile bound last (the draw's instance index is the tile's slot);
    /// counts a draw call.
    pub fn draw(&mut self, set: &IndexSet) {
        self.draw_from(set, 0);
    }

    /// Draws `set` for the bound tile with every index but the restart raised by
    /// `base_vertex` (the shader's `vertex_index` includes it): one set drawn at several
    /// places of a tile.
    pub fn draw_from(&mut self, set: &IndexSet, base_vertex: i32) {
        if self.index_buffer.as_ref() != Some(&set.buffer) {
            self.pass
                .set_index_buffer(set.buffer.slice(..), wgpu::IndexFormat::Uint32);
            self.index_buffer = Some(set.buffer.clone());
        }
        self.pass
            .draw_indexed(0..set.len, base_vertex, self.slot..self.slot + 1);
        self.stats.draw_calls += 1;
    }

    /// The frame's stats, for what a method counts itself.
    pub fn stats_mut(&mut self) -> &mut RenderStats {
        self.stats
    }
}
