//! The terrain renderer: GPU resources of resident tiles and one render pass per frame.
//!
//! A tile drawn has a storage buffer of its samples (height and normal, 8 bytes each, see
//! [`super::mesh`]) from a pool of buffers handed to the tiles drawn, least recently used
//! first ([`super::pool`], the GeoMipMaps paper's VBO manager): a resident tile keeps only
//! its heights (shared with the scene) until it is drawn. Each tile has a texture holding
//! the finest level it has so far, with the coarser levels as its mips; with MapBlocks on
//! ([`super::blocks`]), tiles are drawn block by block with their block's texture, bound once
//! per block. Every mask level has one index buffer, built and uploaded the first
//! time a tile draws it and shared by every tile (the strip-mask paper's section 5.1); the
//! shader turns an index into a position from the tile's origin and spacing. Cracks between
//! tiles of different levels are filled by [`CrackFiller`].
//!
//! `render` draws into any `TextureView` of the renderer's format: an offscreen texture for
//! the headless flight and tests, or a window's surface for the viewer.

use super::blocks::{BlockLayout, BlockRect};
use super::camera::Camera;
use super::gpu::Gpu;
use super::mesh;
use super::plan::{Draw, Layout};
use super::pool::LruPool;
use std::collections::HashMap;
use std::sync::Arc;
use terrain_shaders::{FrameUniform, Sample, TileUniform};
use terrain_shared::{Heights, TileId};

/// Background colour: what a crack shows when nothing fills it.
pub const SKY: [f64; 3] = [0.55, 0.71, 0.88];
/// Depth format of the renderer's depth buffer (reversed: cleared to 0, nearer is greater).
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Largest stretch of a planar shadow's corner projection ([`shadow_corner`]).
pub const SHADOW_MAX_STRETCH: f32 = 64.0;
/// Share of the light that is ambient.
pub const AMBIENT: f32 = 0.45;

/// How cracks between tiles of different mask levels are filled (section 5.4).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum CrackFiller {
    /// Nothing: cracks show the background.
    None,
    /// Vertical bands along each tile's border down below the tile (the paper's filleting).
    Skirts,
    /// A textured quad under each tile, its corners projected from the viewpoint onto a
    /// plane below the tile (the paper's method).
    #[default]
    PlanarShadow,
}

impl CrackFiller {
    pub fn name(self) -> &'static str {
        match self {
            CrackFiller::None => "none",
            CrackFiller::Skirts => "skirts",
            CrackFiller::PlanarShadow => "planar-shadow",
        }
    }
}

/// What one frame drew.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RenderStats {
    /// Triangles of the tiles' masks (strip joins not counted).
    pub triangles: u64,
    /// Triangles of the crack fillers.
    pub filler_triangles: u64,
    pub draw_calls: u32,
    /// Texture bind groups set: one per tile, or one per MapBlock with blocks on.
    pub texture_binds: u32,
    /// Tiles whose samples were uploaded to a pooled buffer this frame (they had none).
    pub sample_uploads: u32,
    /// CPU time of uniforms, command encoding and submission.
    pub encode_ms: f64,
    /// GPU time of the render pass, when the adapter has timestamp queries.
    pub gpu_ms: Option<f64>,
}

/// What the renderer holds on the GPU ([`TerrainRenderer::resident_gpu`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct GpuResidency {
    /// Resident tiles.
    pub tiles: u64,
    /// Sample buffers in the pool (at most one per resident tile; only drawn tiles get one).
    pub sample_buffers: u64,
    pub sample_bytes: u64,
    /// The tiles' own textures, every mip.
    pub texture_bytes: u64,
    /// MapBlock textures.
    pub block_bytes: u64,
    /// Shared index sets (strips, skirts, stitched GeoMipMap sets).
    pub index_bytes: u64,
}

/// A resident tile on the GPU.
#[derive(Debug)]
struct GpuTile {
    /// Its heights, shared with the scene; turned into samples when it gets a buffer.
    heights: Arc<Heights>,
    texture: wgpu::Texture,
    texture_group: wgpu::BindGroup,
    /// Changes with every change of the texture (unique across tiles), so a MapBlock knows
    /// when to assemble its texture again.
    texture_version: u64,
    /// Finest texture level uploaded (manifest numbering: 0 is the coarsest).
    texture_level: Option<u32>,
    min_m: f64,
    /// Heights of the corners: north-west, south-west, north-east, south-east.
    corners_m: [f64; 4],
    sample_bytes: u64,
    texture_bytes: u64,
}

/// A pooled buffer of one tile's samples, with its bind group.
#[derive(Debug)]
struct PooledSamples {
    buffer: wgpu::Buffer,
    group: wgpu::BindGroup,
}

/// A MapBlock's assembled texture.
#[derive(Debug)]
struct Block {
    /// Its resident tiles and their texture versions when it was assembled.
    members: Vec<(TileId, u64)>,
    /// The tiles drawn with it: those whose texture is at the block's level (the others,
    /// still coarser, are drawn with their own until they catch up).
    holds: std::collections::HashSet<TileId>,
    rect: BlockRect,
    group: wgpu::BindGroup,
    bytes: u64,
}

/// MapBlocks: the layout and the blocks assembled so far.
#[derive(Debug)]
struct Blocks {
    layout: BlockLayout,
    assembled: HashMap<[u32; 2], Block>,
}

/// Where the planar shadow puts a tile corner at `corner` (render space, relative to the
/// camera at the origin): on the ray from the camera through it, where the ray meets the
/// horizontal plane at height `plane` (also camera-relative), below the tile. Near grazing
/// angles, or with the corner above the camera, the stretch is capped at
/// [`SHADOW_MAX_STRETCH`]: the shadow then misses (the method's known failure), but stays
/// finite. With the camera below the plane there is nothing to project from, and the corner
/// is laid on the plane.
pub fn shadow_corner(corner: glam::DVec3, plane: f64) -> glam::DVec3 {
    if plane >= 0.0 {
        return glam::DVec3::new(corner.x, plane, corner.z);
    }
    let t = -plane / (-corner.y).max(-plane / f64::from(SHADOW_MAX_STRETCH));
    corner * t
}

#[derive(Debug)]
struct Timestamps {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    readback: wgpu::Buffer,
    period_ns: f32,
}

/// The terrain renderer. See the module documentation.
#[derive(Debug)]
pub struct TerrainRenderer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    layout: Layout,
    masks: std::sync::Arc<crate::lod::strips::MaskSet>,
    frame_buffer: wgpu::Buffer,
    frame_group: wgpu::BindGroup,
    sample_group_layout: wgpu::BindGroupLayout,
    texture_group_layout: wgpu::BindGroupLayout,
    uniform_layout: wgpu::BindGroupLayout,
    tile_uniforms: wgpu::Buffer,
    tile_uniform_group: wgpu::BindGroup,
    uniform_capacity: u64,
    uniform_stride: u64,
    /// The one pipeline: surfaces, skirts and shadows differ only by their indices.
    surface_pipeline: wgpu::RenderPipeline,
    sampler: wgpu::Sampler,
    strips: HashMap<u32, (wgpu::Buffer, u32)>,
    /// GeoMipMap index sets: buffer, index count, triangles.
    stitched: HashMap<crate::lod::geomipmap::Stitch, (wgpu::Buffer, u32, u32)>,
    /// Indices of the shadow's four corners (`terrain_shaders::shadow_base`).
    quad: wgpu::Buffer,
    skirts: HashMap<u32, (wgpu::Buffer, u32)>,
    tiles: HashMap<TileId, GpuTile>,
    pool: LruPool<TileId, PooledSamples>,
    blocks: Option<Blocks>,
    next_texture_version: u64,
    depth: Option<(wgpu::Texture, wgpu::TextureView)>,
    /// Whether the depth buffer is kept after a frame, for [`TerrainRenderer::read_depth`].
    keep_depth: bool,
    timestamps: Option<Timestamps>,
    max_texture_side: u32,
}

impl TerrainRenderer {
    /// A renderer drawing into targets of `format`, for tiles laid out as `layout`, sharing
    /// `masks` with the level-of-detail planner.
    pub fn new(
        gpu: &Gpu,
        format: wgpu::TextureFormat,
        layout: Layout,
        masks: std::sync::Arc<crate::lod::strips::MaskSet>,
    ) -> TerrainRenderer {
        let device = gpu.device.clone();
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("terrain"),
            source: wgpu::ShaderSource::Wgsl(terrain_shaders::TERRAIN.into()),
        });
        let uniform_entry = |dynamic: bool, size: u64| wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: dynamic,
                min_binding_size: wgpu::BufferSize::new(size),
            },
            count: None,
        };
        let frame_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("frame"),
            entries: &[uniform_entry(false, size_of::<FrameUniform>() as u64)],
        });
        let uniform_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tile uniforms"),
            entries: &[uniform_entry(true, size_of::<TileUniform>() as u64)],
        });
        let sample_group_layout =
            device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("tile samples"),
                entries: &[wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::VERTEX,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Storage { read_only: true },
                        has_dynamic_offset: false,
                        min_binding_size: wgpu::BufferSize::new(size_of::<Sample>() as u64),
                    },
                    count: None,
                }],
            });
        let texture_group_layout =
            device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
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
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("terrain"),
            bind_group_layouts: &[
                Some(&frame_layout),
                Some(&uniform_layout),
                Some(&sample_group_layout),
                Some(&texture_group_layout),
            ],
            immediate_size: 0,
        });
        let pipeline = |entry: &str, strip_index_format: Option<wgpu::IndexFormat>| {
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some(entry),
                layout: Some(&pipeline_layout),
                vertex: wgpu::VertexState {
                    module: &shader,
                    entry_point: Some(entry),
                    compilation_options: Default::default(),
                    buffers: &[],
                },
                primitive: wgpu::PrimitiveState {
                    topology: wgpu::PrimitiveTopology::TriangleStrip,
                    strip_index_format,
                    // Terrain is seen from below too (a camera under the surface); strips
                    // and skirts are drawn two-sided.
                    cull_mode: None,
                    ..Default::default()
                },
                depth_stencil: Some(wgpu::DepthStencilState {
                    format: DEPTH_FORMAT,
                    depth_write_enabled: Some(true),
                    depth_compare: Some(wgpu::CompareFunction::Greater),
                    stencil: Default::default(),
                    bias: Default::default(),
                }),
                multisample: Default::default(),
                fragment: Some(wgpu::FragmentState {
                    module: &shader,
                    entry_point: Some(terrain_shaders::entry::FRAGMENT),
                    compilation_options: Default::default(),
                    targets: &[Some(wgpu::ColorTargetState {
                        format,
                        blend: None,
                        write_mask: wgpu::ColorWrites::ALL,
                    })],
                }),
                multiview_mask: None,
                cache: None,
            })
        };
        let surface_pipeline = pipeline(
            terrain_shaders::entry::SURFACE,
            Some(wgpu::IndexFormat::Uint32),
        );

        let frame_buffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("frame"),
            size: size_of::<FrameUniform>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let frame_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("frame"),
            layout: &frame_layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: frame_buffer.as_entire_binding(),
            }],
        });
        let uniform_stride = u64::from(device.limits().min_uniform_buffer_offset_alignment)
            .max(size_of::<TileUniform>() as u64);
        let (tile_uniforms, tile_uniform_group) =
            uniform_buffer(&device, &uniform_layout, 64, uniform_stride);
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("tile"),
            address_mode_u: wgpu::AddressMode::ClampToEdge,
            address_mode_v: wgpu::AddressMode::ClampToEdge,
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            mipmap_filter: wgpu::MipmapFilterMode::Linear,
            ..Default::default()
        });
        let timestamps = gpu.has_timestamps().then(|| Timestamps {
            set: device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("frame time"),
                ty: wgpu::QueryType::Timestamp,
                count: 2,
            }),
            resolve: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("timestamps"),
                size: 16,
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }),
            readback: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("timestamps readback"),
                size: 16,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            period_ns: gpu.queue.get_timestamp_period(),
        });
        let quad = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("shadow quad"),
            size: 16,
            usage: wgpu::BufferUsages::INDEX | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let corner = terrain_shaders::shadow_base(layout.tile_size);
        gpu.queue.write_buffer(
            &quad,
            0,
            bytemuck::cast_slice(&[corner, corner + 1, corner + 2, corner + 3]),
        );
        TerrainRenderer {
            quad,
            queue: gpu.queue.clone(),
            layout,
            masks,
            frame_buffer,
            frame_group,
            sample_group_layout,
            texture_group_layout,
            uniform_layout,
            tile_uniforms,
            tile_uniform_group,
            uniform_capacity: 64,
            uniform_stride,
            surface_pipeline,
            sampler,
            strips: HashMap::new(),
            stitched: HashMap::new(),
            skirts: HashMap::new(),
            tiles: HashMap::new(),
            pool: LruPool::default(),
            blocks: None,
            next_texture_version: 0,
            depth: None,
            keep_depth: false,
            timestamps,
            max_texture_side: device.limits().max_texture_dimension_2d,
            device,
        }
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
            .map_or(0, |t| t.sample_bytes + copies * t.texture_bytes)
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

    /// Bytes of one tile's sample buffer.
    pub fn sample_buffer_bytes(&self) -> u64 {
        u64::from(self.layout.tile_size).pow(2) * size_of::<Sample>() as u64
    }

    /// What the renderer holds on the GPU now.
    pub fn resident_gpu(&self) -> GpuResidency {
        GpuResidency {
            tiles: self.tiles.len() as u64,
            sample_buffers: self.pool.len() as u64,
            sample_bytes: self.pool.len() as u64 * self.sample_buffer_bytes(),
            texture_bytes: self.tiles.values().map(|t| t.texture_bytes).sum(),
            block_bytes: self
                .blocks
                .as_ref()
                .map_or(0, |b| b.assembled.values().map(|b| b.bytes).sum()),
            index_bytes: self
                .strips
                .values()
                .chain(self.skirts.values())
                .map(|(b, _)| b.size())
                .chain(self.stitched.values().map(|(b, _, _)| b.size()))
                .sum(),
        }
    }

    /// The largest texture side the adapter takes.
    pub fn max_texture_side(&self) -> u32 {
        self.max_texture_side
    }

    /// Draws tiles block by block with MapBlock textures cut by `layout` (`None`: each tile
    /// with its own texture).
    pub fn set_texture_blocks(&mut self, layout: Option<BlockLayout>) {
        if self.blocks.as_ref().map(|b| b.layout) != layout {
            self.blocks = layout.map(|layout| Blocks {
                layout,
                assembled: HashMap::new(),
            });
        }
    }

    /// Makes `id` resident with its heights; it draws with a grey texture until
    /// [`TerrainRenderer::upload_texture`], and gets a sample buffer from the pool when it is
    /// drawn. Returns the GPU bytes charged for its samples.
    pub fn upload_tile(&mut self, id: TileId, heights: Arc<Heights>, min_m: f64) -> u64 {
        let texture = self.texture(&[image::RgbaImage::from_pixel(
            1,
            1,
            image::Rgba([128, 128, 128, 255]),
        )]);
        let texture_group = self.texture_bind_group(&texture);
        let last = self.layout.tile_size as usize - 1;
        let corners_m = [(0, 0), (0, last), (last, 0), (last, last)]
            .map(|(column, row)| f64::from(heights.metres(column, row) as f32));
        // A tile that comes back starts afresh: its old buffer may hold other samples.
        self.release_samples(id);
        let texture_version = self.bump_version();
        let sample_bytes = self.sample_buffer_bytes();
        self.tiles.insert(
            id,
            GpuTile {
                sample_bytes,
                heights,
                texture,
                texture_group,
                texture_version,
                texture_level: None,
                min_m,
                corners_m,
                texture_bytes: 4,
            },
        );
        self.forget_block_of(id);
        sample_bytes
    }

    fn bump_version(&mut self) -> u64 {
        self.next_texture_version += 1;
        self.next_texture_version
    }

    /// Drops `id`'s block texture at once (it is assembled again when next drawn), so an
    /// evicted tile's block does not hold GPU memory until its block is drawn again.
    fn forget_block_of(&mut self, id: TileId) {
        if let Some(blocks) = &mut self.blocks {
            let key = blocks.layout.block_of(id);
            blocks.assembled.remove(&key);
        }
    }

    fn release_samples(&mut self, id: TileId) {
        let keep = self.tiles.len();
        self.pool.release(id, keep);
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
        let texture_group = self.texture_bind_group(&texture);
        let version = self.bump_version();
        if let Some(tile) = self.tiles.get_mut(&id) {
            tile.texture = texture;
            tile.texture_group = texture_group;
            tile.texture_version = version;
            tile.texture_level = Some(level.saturating_sub(dropped));
            tile.texture_bytes = bytes;
        }
        bytes
    }

    /// Adds `image`, manifest level `level`, as the new top mip of `id`'s texture, which
    /// must hold exactly the levels below it: those are copied on the GPU, not decoded and
    /// uploaded again. Returns false, changing nothing, when that does not hold (no texture
    /// yet, a gap, a size that is not twice the current top, or over the device's limit);
    /// the caller then uploads every level with [`TerrainRenderer::upload_texture`].
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

    /// Keeps the depth buffer of every later frame for [`TerrainRenderer::read_depth`]
    /// (stored and copyable, which costs some speed; off by default).
    pub fn keep_depth(&mut self, keep: bool) {
        if keep != self.keep_depth {
            self.keep_depth = keep;
            self.depth = None;
        }
    }

    /// The last frame's depth buffer, row-major from the top left: reversed depth, 0 where
    /// nothing was drawn (the background). Needs [`TerrainRenderer::keep_depth`].
    pub fn read_depth(&self) -> Result<Vec<f32>, super::GpuError> {
        let (Some((texture, _)), true) = (&self.depth, self.keep_depth) else {
            return Err(super::GpuError::Readback(
                "no depth kept: call keep_depth(true) before rendering".into(),
            ));
        };
        let bytes = super::offscreen::read_texture(&self.device, &self.queue, texture, 4)?;
        Ok(bytemuck::pod_collect_to_vec(&bytes))
    }

    /// Frees `id`'s GPU resources.
    pub fn remove_tile(&mut self, id: TileId) {
        if self.tiles.remove(&id).is_some() {
            self.release_samples(id);
            self.forget_block_of(id);
        }
    }

    /// Draws `draws` seen from `camera` into `target` (cleared to [`SKY`] first), fills
    /// cracks with `filler`, and waits for the GPU to finish.
    pub fn render(
        &mut self,
        target: &wgpu::TextureView,
        camera: &Camera,
        draws: &[Draw],
        filler: CrackFiller,
    ) -> RenderStats {
        let started = std::time::Instant::now();
        let size = target.texture().size();
        let aspect = f64::from(size.width) / f64::from(size.height.max(1));
        self.ensure_depth(size.width, size.height);
        let drawn: Vec<&Draw> = draws
            .iter()
            .filter(|d| self.tiles.contains_key(&d.id))
            .collect();
        self.ensure_uniform_capacity(drawn.len() as u64);
        for d in &drawn {
            if let Some(stitch) = d.stitch {
                self.ensure_stitched(stitch);
                continue;
            }
            self.ensure_strip(d.level);
            if filler == CrackFiller::Skirts {
                self.ensure_skirt(d.level);
            }
        }
        let (sample_slots, sample_uploads) = self.pool_samples(&drawn);
        let block_keys = self.frame_blocks(&drawn);
        let block_rect = |slot: usize| {
            let key = block_keys[slot]?;
            Some(self.blocks.as_ref()?.assembled.get(&key)?.rect)
        };

        // Uniforms: the frame's, then one slot per drawn tile.
        let light = Camera::to_render(glam::DVec3::new(
            -0.5,
            -0.5,
            std::f64::consts::FRAC_1_SQRT_2,
        ))
        .normalize();
        // The anchor: the sample nearest the camera. Positions are built from sample
        // indices relative to it (see the shader), exact in f32.
        let anchor = [
            (camera.position[0] / self.layout.spacing_m[0]).round(),
            (camera.position[1] / self.layout.spacing_m[1]).round(),
        ];
        let frame = FrameUniform {
            view_proj: camera.view_proj_f32(aspect).to_cols_array_2d(),
            light_dir: [light.x as f32, light.y as f32, light.z as f32, 0.0],
            params: [AMBIENT, 0.0, 0.0, 0.0],
            camera: [
                (camera.position[0] - anchor[0] * self.layout.spacing_m[0]) as f32,
                camera.position[2] as f32,
                (camera.position[1] - anchor[1] * self.layout.spacing_m[1]) as f32,
                0.0,
            ],
        };
        self.queue
            .write_buffer(&self.frame_buffer, 0, bytemuck::bytes_of(&frame));
        let mut uniforms = vec![0u8; (self.uniform_stride * drawn.len() as u64) as usize];
        let n = self.layout.tile_size;
        let extent = self.layout.tile_extent_m();
        for (slot, d) in drawn.iter().enumerate() {
            let tile = &self.tiles[&d.id];
            let cells = f64::from(n - 1);
            // Filler depth below the tile: a tenth of its side, at least 1 m.
            let drop = (0.1 * extent[0].min(extent[1])).max(1.0);
            let [x0, y0] = self.layout.tile_origin_m(d.id);
            let plane = tile.min_m - drop - camera.position[2];
            let mut shadow = [[0.0f32; 4]; 4];
            for (k, corner) in shadow.iter_mut().enumerate() {
                let (east, south) = ((k / 2) as f64 * extent[0], (k % 2) as f64 * extent[1]);
                let p = shadow_corner(
                    glam::DVec3::new(
                        x0 + east - camera.position[0],
                        tile.corners_m[k] - camera.position[2],
                        y0 + south - camera.position[1],
                    ),
                    plane,
                );
                *corner = [p.x as f32, p.y as f32, p.z as f32, 1.0];
            }
            let u = TileUniform {
                origin: [
                    (f64::from(d.id.x) * cells - anchor[0]) as f32,
                    0.0,
                    (f64::from(d.id.y) * cells - anchor[1]) as f32,
                    0.0,
                ],
                spacing: [
                    self.layout.spacing_m[0] as f32,
                    self.layout.spacing_m[1] as f32,
                    n as f32,
                    (tile.min_m - drop) as f32,
                ],
                shadow,
                uv: block_rect(slot).map_or([0.0, 0.0, 1.0, 1.0], |r| r.uv(d.id)),
            };
            let at = slot * self.uniform_stride as usize;
            uniforms[at..at + size_of::<TileUniform>()].copy_from_slice(bytemuck::bytes_of(&u));
        }
        if !uniforms.is_empty() {
            self.queue.write_buffer(&self.tile_uniforms, 0, &uniforms);
        }

        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("frame"),
            });
        let mut stats = RenderStats {
            sample_uploads,
            ..RenderStats::default()
        };
        // Tiles block by block (each block's texture bound once), then those drawn with
        // their own textures, in the plan's order within each.
        let mut order: Vec<usize> = (0..drawn.len()).collect();
        order.sort_by_key(|&slot| (block_keys[slot].is_none(), block_keys[slot]));
        let texture_group = |slot: usize| -> (&wgpu::BindGroup, Option<[u32; 2]>) {
            match (block_keys[slot], &self.blocks) {
                (Some(key), Some(blocks)) => (&blocks.assembled[&key].group, Some(key)),
                _ => (&self.tiles[&drawn[slot].id].texture_group, None),
            }
        };
        // Binds tile `slot`'s uniforms, samples and texture; a block's texture only when the
        // block changes (`bound`). Counts texture binds.
        let bind_tile = |pass: &mut wgpu::RenderPass<'_>,
                         slot: usize,
                         bound: &mut Option<[u32; 2]>,
                         binds: &mut u32| {
            let offset = (slot as u64 * self.uniform_stride) as u32;
            pass.set_bind_group(1, &self.tile_uniform_group, &[offset]);
            pass.set_bind_group(2, &self.pool.get(sample_slots[slot]).group, &[]);
            let (group, block) = texture_group(slot);
            if block.is_none() || block != *bound {
                pass.set_bind_group(3, group, &[]);
                *binds += 1;
                *bound = block;
            }
        };
        {
            let depth = &self.depth.as_ref().expect("ensured above").1;
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("terrain"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: target,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color {
                            r: SKY[0],
                            g: SKY[1],
                            b: SKY[2],
                            a: 1.0,
                        }),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: depth,
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Clear(0.0),
                        store: if self.keep_depth {
                            wgpu::StoreOp::Store
                        } else {
                            wgpu::StoreOp::Discard
                        },
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: self.timestamps.as_ref().map(|t| {
                    wgpu::RenderPassTimestampWrites {
                        query_set: &t.set,
                        beginning_of_pass_write_index: Some(0),
                        end_of_pass_write_index: Some(1),
                    }
                }),
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_bind_group(0, &self.frame_group, &[]);
            pass.set_pipeline(&self.surface_pipeline);
            let mut bound: Option<[u32; 2]> = None;
            for &slot in &order {
                let d = drawn[slot];
                bind_tile(&mut pass, slot, &mut bound, &mut stats.texture_binds);
                if let Some(stitch) = d.stitch {
                    // GeoMipMaps are crack-free by construction: no filler.
                    let (buffer, len, triangles) = &self.stitched[&stitch];
                    pass.set_index_buffer(buffer.slice(..), wgpu::IndexFormat::Uint32);
                    pass.draw_indexed(0..*len, 0, 0..1);
                    stats.triangles += u64::from(*triangles);
                    stats.draw_calls += 1;
                    continue;
                }
                let (buffer, len) = &self.strips[&d.level];
                pass.set_index_buffer(buffer.slice(..), wgpu::IndexFormat::Uint32);
                pass.draw_indexed(0..*len, 0, 0..1);
                stats.triangles += u64::from(self.masks.triangle_count(d.level));
                stats.draw_calls += 1;
                if filler == CrackFiller::Skirts {
                    let (buffer, len) = &self.skirts[&d.level];
                    pass.set_index_buffer(buffer.slice(..), wgpu::IndexFormat::Uint32);
                    pass.draw_indexed(0..*len, 0, 0..1);
                    stats.filler_triangles += u64::from(mesh::skirt_triangles(n, d.level));
                    stats.draw_calls += 1;
                }
            }
            if filler == CrackFiller::PlanarShadow {
                pass.set_index_buffer(self.quad.slice(..), wgpu::IndexFormat::Uint32);
                let mut bound: Option<[u32; 2]> = None;
                for &slot in order.iter().filter(|&&slot| drawn[slot].stitch.is_none()) {
                    bind_tile(&mut pass, slot, &mut bound, &mut stats.texture_binds);
                    pass.draw_indexed(0..4, 0, 0..1);
                    stats.filler_triangles += 2;
                    stats.draw_calls += 1;
                }
            }
        }
        if let Some(t) = &self.timestamps {
            encoder.resolve_query_set(&t.set, 0..2, &t.resolve, 0);
            encoder.copy_buffer_to_buffer(&t.resolve, 0, &t.readback, 0, 16);
        }
        self.queue.submit([encoder.finish()]);
        stats.encode_ms = started.elapsed().as_secs_f64() * 1e3;
        if let Some(t) = &self.timestamps {
            let slice = t.readback.slice(..);
            slice.map_async(wgpu::MapMode::Read, |_| {});
            let _ = self.device.poll(wgpu::PollType::wait_indefinitely());
            if let Ok(data) = slice.get_mapped_range() {
                let stamps: &[u64] = bytemuck::cast_slice(&data);
                let ticks = stamps[1].saturating_sub(stamps[0]);
                stats.gpu_ms = Some(ticks as f64 * f64::from(t.period_ns) / 1.0e6);
            }
            t.readback.unmap();
        } else {
            let _ = self.device.poll(wgpu::PollType::wait_indefinitely());
        }
        stats
    }

    fn ensure_depth(&mut self, width: u32, height: u32) {
        if let Some((texture, _)) = &self.depth
            && texture.width() == width
            && texture.height() == height
        {
            return;
        }
        let texture = self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("depth"),
            size: wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: DEPTH_FORMAT,
            usage: if self.keep_depth {
                wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC
            } else {
                wgpu::TextureUsages::RENDER_ATTACHMENT
            },
            view_formats: &[],
        });
        let view = texture.create_view(&Default::default());
        self.depth = Some((texture, view));
    }

    fn ensure_uniform_capacity(&mut self, slots: u64) {
        if slots <= self.uniform_capacity {
            return;
        }
        let capacity = slots.next_power_of_two();
        let (buffer, group) = uniform_buffer(
            &self.device,
            &self.uniform_layout,
            capacity,
            self.uniform_stride,
        );
        self.tile_uniforms = buffer;
        self.tile_uniform_group = group;
        self.uniform_capacity = capacity;
    }

    fn ensure_strip(&mut self, level: u32) {
        if !self.strips.contains_key(&level) {
            let indices = self.masks.strip(level);
            let buffer = self.index_buffer(indices);
            self.strips.insert(level, (buffer, indices.len() as u32));
        }
    }

    fn ensure_stitched(&mut self, stitch: crate::lod::geomipmap::Stitch) {
        if !self.stitched.contains_key(&stitch) {
            let n = self.layout.tile_size;
            let indices = crate::lod::geomipmap::strip(n, stitch);
            let triangles = crate::lod::geomipmap::triangles(n, stitch).len() as u32;
            let buffer = self.index_buffer(&indices);
            self.stitched
                .insert(stitch, (buffer, indices.len() as u32, triangles));
        }
    }

    fn ensure_skirt(&mut self, level: u32) {
        if !self.skirts.contains_key(&level) {
            let indices = mesh::skirt_strip(self.layout.tile_size, level);
            let buffer = self.index_buffer(&indices);
            self.skirts.insert(level, (buffer, indices.len() as u32));
        }
    }

    fn index_buffer(&self, indices: &[u32]) -> wgpu::Buffer {
        let bytes: &[u8] = bytemuck::cast_slice(indices);
        let buffer = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("mask strip"),
            size: bytes.len() as u64,
            usage: wgpu::BufferUsages::INDEX | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        self.queue.write_buffer(&buffer, 0, bytes);
        buffer
    }

    /// A texture with `levels` (coarsest first) as its mips, finest as mip 0.
    fn texture(&self, levels: &[image::RgbaImage]) -> wgpu::Texture {
        let finest = &levels[levels.len() - 1];
        let texture = self.blank_texture(finest.width(), finest.height(), levels.len() as u32);
        for (mip, image) in levels.iter().rev().enumerate() {
            self.write_mip(&texture, mip as u32, image);
        }
        texture
    }

    /// A tile texture of `mips` levels whose top mip is `width` x `height`, contents undefined.
    fn blank_texture(&self, width: u32, height: u32, mips: u32) -> wgpu::Texture {
        self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("tile texture"),
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
        let texture = self.blank_texture(side, side, mips);
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
            encoder.copy_texture_to_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &tile.texture,
                    mip_level: old_mip,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                wgpu::TexelCopyTextureInfo {
                    texture: &texture,
                    mip_level: new_mip,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                wgpu::Extent3d {
                    width: mip_side,
                    height: mip_side,
                    depth_or_array_layers: 1,
                },
            );
        }
        if let Some(image) = top {
            self.write_mip(&texture, 0, image);
        }
        self.queue.submit([encoder.finish()]);
        let texture_group = self.texture_bind_group(&texture);
        let bytes = mip_chain_bytes(side, side, mips);
        let version = self.bump_version();
        if let Some(tile) = self.tiles.get_mut(&id) {
            tile.texture = texture;
            tile.texture_group = texture_group;
            tile.texture_version = version;
            tile.texture_level = Some(level);
            tile.texture_bytes = bytes;
        }
    }

    fn texture_bind_group(&self, texture: &wgpu::Texture) -> wgpu::BindGroup {
        let view = texture.create_view(&Default::default());
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tile texture"),
            layout: &self.texture_group_layout,
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

    /// Hands each drawn tile a sample buffer from the pool, uploading the samples of those
    /// that had none; returns the slots and the number of uploads.
    fn pool_samples(&mut self, drawn: &[&Draw]) -> (Vec<usize>, u32) {
        // What a shrinking pool drops is freed with it.
        drop(self.pool.begin_frame());
        let bytes = self.sample_buffer_bytes();
        let mut uploads = 0;
        let mut slots = Vec::with_capacity(drawn.len());
        for d in drawn {
            let (device, layout) = (&self.device, &self.sample_group_layout);
            let got = self.pool.acquire(d.id, || {
                let buffer = device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("tile samples"),
                    size: bytes,
                    usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                });
                let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("tile samples"),
                    layout,
                    entries: &[wgpu::BindGroupEntry {
                        binding: 0,
                        resource: buffer.as_entire_binding(),
                    }],
                });
                PooledSamples { buffer, group }
            });
            if got.needs_upload() {
                let samples = mesh::tile_samples(&self.tiles[&d.id].heights, self.layout.spacing_m);
                self.queue.write_buffer(
                    &self.pool.get(got.slot()).buffer,
                    0,
                    bytemuck::cast_slice(&samples),
                );
                uploads += 1;
            }
            slots.push(got.slot());
        }
        (slots, uploads)
    }

    /// With MapBlocks on, the block of each drawn tile whose texture is assembled (blocks
    /// whose tiles changed are assembled again first); `None` for a tile drawn with its own
    /// texture (blocks off, or a block with a tile still untextured).
    fn frame_blocks(&mut self, drawn: &[&Draw]) -> Vec<Option<[u32; 2]>> {
        let Some(layout) = self.blocks.as_ref().map(|b| b.layout) else {
            return vec![None; drawn.len()];
        };
        let keys: std::collections::BTreeSet<[u32; 2]> =
            drawn.iter().map(|d| layout.block_of(d.id)).collect();
        for key in keys {
            self.assemble_block(layout, key);
        }
        let assembled = &self.blocks.as_ref().expect("blocks on").assembled;
        drawn
            .iter()
            .map(|d| {
                let key = layout.block_of(d.id);
                assembled
                    .get(&key)
                    .is_some_and(|b| b.holds.contains(&d.id))
                    .then_some(key)
            })
            .collect()
    }

    /// Assembles block `key`'s texture from its resident tiles' textures, unless it is
    /// current: the mips of every tile at the finest level any of them holds, copied side by
    /// side. A tile still at a coarser level (or untextured) is left out of the block and
    /// drawn with its own texture, so no tile is drawn coarser than it holds.
    fn assemble_block(&mut self, layout: BlockLayout, key: [u32; 2]) {
        let members: Vec<(TileId, u64)> = layout
            .members(key)
            .filter_map(|id| self.tiles.get(&id).map(|t| (id, t.texture_version)))
            .collect();
        let blocks = self.blocks.as_mut().expect("blocks on");
        if blocks
            .assembled
            .get(&key)
            .is_some_and(|b| b.members == members)
        {
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
        let mips = mips.min(side.ilog2() + 1);
        let [w, h] = rect.size();
        let texture = self.blank_texture(w * side, h * side, mips);
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("map block"),
            });
        for id in &sources {
            let [x, y] = rect.texel_origin(*id, side);
            for mip in 0..mips {
                let s = side >> mip;
                encoder.copy_texture_to_texture(
                    wgpu::TexelCopyTextureInfo {
                        texture: &self.tiles[id].texture,
                        mip_level: mip,
                        origin: wgpu::Origin3d::ZERO,
                        aspect: wgpu::TextureAspect::All,
                    },
                    wgpu::TexelCopyTextureInfo {
                        texture: &texture,
                        mip_level: mip,
                        origin: wgpu::Origin3d {
                            x: x >> mip,
                            y: y >> mip,
                            z: 0,
                        },
                        aspect: wgpu::TextureAspect::All,
                    },
                    wgpu::Extent3d {
                        width: s,
                        height: s,
                        depth_or_array_layers: 1,
                    },
                );
            }
        }
        self.queue.submit([encoder.finish()]);
        let bytes = mip_chain_bytes(w * side, h * side, mips);
        let group = self.texture_bind_group(&texture);
        self.blocks.as_mut().expect("blocks on").assembled.insert(
            key,
            Block {
                members,
                holds: sources.into_iter().collect(),
                rect,
                group,
                bytes,
            },
        );
    }
}

/// Bytes of an RGBA texture of `mips` levels whose top is `width` x `height`.
fn mip_chain_bytes(width: u32, height: u32, mips: u32) -> u64 {
    (0..mips)
        .map(|m| u64::from((width >> m).max(1)) * u64::from((height >> m).max(1)) * 4)
        .sum()
}

fn uniform_buffer(
    device: &wgpu::Device,
    layout: &wgpu::BindGroupLayout,
    slots: u64,
    stride: u64,
) -> (wgpu::Buffer, wgpu::BindGroup) {
    let buffer = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("tile uniforms"),
        size: slots * stride,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("tile uniforms"),
        layout,
        entries: &[wgpu::BindGroupEntry {
            binding: 0,
            resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                buffer: &buffer,
                offset: 0,
                size: wgpu::BufferSize::new(size_of::<TileUniform>() as u64),
            }),
        }],
    });
    (buffer, group)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    #[test]
    fn a_shadow_corner_lies_on_the_ray_through_the_corner_and_on_the_plane() {
        let corner = DVec3::new(300.0, -500.0, -800.0);
        let p = shadow_corner(corner, -600.0);
        assert!((p.y + 600.0).abs() < 1e-9, "on the plane: {p:?}");
        assert!(
            p.normalize().dot(corner.normalize()) > 1.0 - 1e-12,
            "on the ray"
        );
        assert!(p.length() > corner.length(), "beyond the corner");
        // Grazing: the stretch is capped, the point stays finite and on the ray.
        let grazing = shadow_corner(DVec3::new(1000.0, -0.001, 0.0), -100.0);
        assert!((grazing.length() / 1000.0 - f64::from(SHADOW_MAX_STRETCH)).abs() < 1e-6);
        // Camera below the plane: laid on the plane under the corner.
        assert_eq!(shadow_corner(corner, 10.0), DVec3::new(300.0, 10.0, -800.0));
    }
}
