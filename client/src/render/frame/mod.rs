//! The renderer every method draws through, and one frame's recording.
//!
//! [`Renderer`] holds what every method shares: the device and queue, the frame's uniforms,
//! the depth buffer (and its read-back), GPU timestamps, the resident tiles
//! ([`super::tiles::TileStore`]) and the tile pipeline: the shader that turns a tile's sample
//! indices into positions, for methods that draw tiles with index sets of their own.
//!
//! A method records a frame through [`Frame`]: it prepares the tiles it draws
//! ([`Frame::prepare_tiles`]: a sample buffer each, MapBlock textures, per-tile uniforms),
//! then opens render passes on the target ([`Frame::pass`]: the first clears it to [`SKY`]),
//! binds tiles and draws its index sets ([`FramePass::bind_tile`], [`FramePass::draw`]), or
//! sets a pipeline of its own ([`FramePass::raw`]); [`Frame::finish`] submits.
//!
//! **Frames in flight.** Up to [`FRAMES_IN_FLIGHT`] frames are queued: [`Frame::finish`]
//! submits, then waits (bounded by [`GPU_TIMEOUT`]) only for the frame before it, so the
//! CPU records frame `k + 1` while the GPU draws frame `k`. GPU timestamps go to a ring of
//! read-back buffers mapped asynchronously; a frame reports the GPU time of the latest
//! frame whose read-back has arrived ([`RenderStats::gpu_ms`]). A caller that must see a
//! frame finished calls [`Renderer::wait_for_gpu`]: a measurement, a read-back of the
//! image, and `Scene::draw` after a frame that made, replaced or dropped GPU allocations
//! (what it dropped is freed only once the frames using it finish).
//!
//! **Few state changes.** The frame's tiles' parameters are one buffer of per-instance
//! vertex attributes (a draw's first instance picks its tile: attributes are fetched once a
//! draw, where a storage array would be read again by every vertex) and the resident tiles'
//! samples one storage buffer (the sample arena, [`super::tiles`], group 1), both bound once
//! a pass. Between two tiles only the texture (group 2, skipped within a MapBlock) and the
//! index buffer (skipped when the same) change.
//!
//! Nothing past the terrain's edge ([`Layout::extent_m`]) is drawn: tiles that hold padding
//! (the last of a row or column) are drawn with a fragment shader that discards what lies
//! past it, as is whatever a method marks ([`FramePass::clip_everything`]); the others keep
//! the early depth test a `discard` would turn off.

mod pass;

pub use self::pass::{FramePass, IndexSet};

use super::camera::Camera;
use super::gpu::{GPU_TIMEOUT, Gpu};
use super::layout::Layout;
use super::tiles::TileStore;
use terrain_shaders::{FrameUniform, TileUniform};
use terrain_shared::TileId;
use web_time::Instant;

/// Background colour: what a crack shows when nothing fills it.
pub const SKY: [f64; 3] = [0.55, 0.71, 0.88];
/// Depth format of the renderer's depth buffer (reversed: cleared to 0, nearer is greater).
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Render passes of a frame whose GPU time is measured (a pair of timestamps each): the
/// frame's time runs from the first's start to the last timed one's end.
const TIMED_PASSES: u32 = 4;
/// Share of the light that is ambient.
pub const AMBIENT: f32 = 0.45;
/// Frames queued on the GPU at most: [`Frame::finish`] waits for the one before it.
pub const FRAMES_IN_FLIGHT: u64 = 2;
/// `TileUniform` as per-instance attributes, locations 0 to 8 (`Tile` in `terrain.wgsl`).
const TILE_ATTRIBUTES: [wgpu::VertexAttribute; 9] = wgpu::vertex_attr_array![
    0 => Float32x4, 1 => Float32x4, 2 => Float32x4, 3 => Float32x4, 4 => Float32x4,
    5 => Float32x4, 6 => Float32x4, 7 => Sint32x4, 8 => Float32x4
];
/// Read-back buffers of the timestamp ring: a frame whose buffers are all still pending is
/// not timed.
const TIMESTAMP_RING: usize = 4;

/// What one frame drew.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RenderStats {
    /// Triangles of the terrain's surface (strip joins not counted).
    pub triangles: u64,
    /// Triangles drawn to fill cracks.
    pub filler_triangles: u64,
    pub draw_calls: u32,
    /// Texture bind groups set: one per tile, or one per MapBlock with blocks on.
    pub texture_binds: u32,
    /// Tiles whose samples were uploaded to a pooled buffer this frame (they had none).
    pub sample_uploads: u32,
    /// Resident tiles dropped at the frame's end to keep the memory limit, when the
    /// method's buffers outgrew what the pager left it (`Scene::draw`).
    pub squeezed_tiles: u32,
    /// Tiles drawn coarser than chosen, or without their crack filler or stitching, because
    /// the memory limit had no room for the index set they needed
    /// ([`crate::method::MethodInput::room`]).
    pub degraded_draws: u32,
    /// CPU time of uniforms, command encoding and submission.
    pub encode_ms: f64,
    /// GPU time of the render passes of the latest frame whose timestamps have been read
    /// back (this frame's after [`Renderer::wait_for_gpu`]; an earlier one's otherwise), when
    /// the adapter has timestamp queries.
    pub gpu_ms: Option<f64>,
}

/// What a method gives for each tile it draws through the tile pipeline, beyond what the
/// renderer knows: a height below the tile (metres above the datum) and four points in
/// render space (north-west, south-west, north-east, south-east), which the shader's
/// indices past the samples use (`terrain.wgsl`); zero when unused.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TileExtras {
    pub floor_m: f32,
    pub points: [[f32; 4]; 4],
}

#[derive(Debug)]
struct Timestamps {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    ring: Vec<Readback>,
    period_ns: f32,
}

/// One read-back buffer of the timestamp ring.
#[derive(Debug)]
struct Readback {
    buffer: wgpu::Buffer,
    /// Set (by the map callback) once the buffer is mapped: `Some(frame, passes timed)`
    /// while a frame's timestamps are in it.
    pending: Option<(u64, u32)>,
    mapped: std::sync::Arc<std::sync::atomic::AtomicU8>,
}

/// [`Readback::mapped`]: still pending, mapped, or failed.
const MAP_PENDING: u8 = 0;
const MAP_DONE: u8 = 1;
const MAP_FAILED: u8 = 2;

/// The shared renderer. See the module documentation.
#[derive(Debug)]
pub struct Renderer {
    gpu: Gpu,
    format: wgpu::TextureFormat,
    layout: Layout,
    frame_layout: wgpu::BindGroupLayout,
    frame_buffer: wgpu::Buffer,
    frame_group: wgpu::BindGroup,
    /// The frame's tiles' parameters (`TileUniform`s), per-instance vertex attributes.
    tile_params: wgpu::Buffer,
    params_capacity: u64,
    /// Group 1 (the sample arena), with the arena generation it holds.
    tiles_group: Option<(wgpu::BindGroup, u64)>,
    tile_pipeline: wgpu::RenderPipeline,
    /// The same, discarding what lies past the terrain's edge: for tiles that reach past
    /// it (padded ones) and whatever a method marks (see [`FramePass::clip_everything`]).
    /// Kept apart because a `discard` turns the early depth test off.
    clipped_pipeline: wgpu::RenderPipeline,
    depth: Option<(wgpu::Texture, wgpu::TextureView)>,
    /// Whether the depth buffer is kept after a frame, for [`Renderer::read_depth`].
    keep_depth: bool,
    timestamps: Option<Timestamps>,
    /// Frames submitted, and the submission of each of the last [`FRAMES_IN_FLIGHT`].
    frames: u64,
    submissions: std::collections::VecDeque<wgpu::SubmissionIndex>,
    /// GPU time of the latest frame read back, and that frame's number.
    last_gpu: Option<(u64, f64)>,
    /// The resident tiles' GPU resources.
    pub tiles: TileStore,
}

impl Renderer {
    /// A renderer drawing into targets of `format`, for tiles laid out as `layout`.
    pub fn new(gpu: &Gpu, format: wgpu::TextureFormat, layout: Layout) -> Renderer {
        let device = &gpu.device;
        let tiles = TileStore::new(gpu, layout);
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
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("tiles"),
            bind_group_layouts: &[
                Some(&frame_layout),
                Some(&tiles.bindings().samples),
                Some(&tiles.bindings().texture),
            ],
            immediate_size: 0,
        });
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("terrain"),
            source: wgpu::ShaderSource::Wgsl(super::arena::terrain_shader(gpu.samples).into()),
        });
        let tile_pipeline = |vertex: &str, fragment: &str| {
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some("tiles"),
                layout: Some(&pipeline_layout),
                vertex: wgpu::VertexState {
                    module: &shader,
                    entry_point: Some(vertex),
                    compilation_options: Default::default(),
                    buffers: &[Some(wgpu::VertexBufferLayout {
                        array_stride: size_of::<TileUniform>() as u64,
                        step_mode: wgpu::VertexStepMode::Instance,
                        attributes: &TILE_ATTRIBUTES,
                    })],
                },
                primitive: wgpu::PrimitiveState {
                    topology: wgpu::PrimitiveTopology::TriangleStrip,
                    strip_index_format: Some(wgpu::IndexFormat::Uint32),
                    // Terrain is seen from below too (a camera under the surface): two-sided.
                    cull_mode: None,
                    ..Default::default()
                },
                depth_stencil: Some(depth_state()),
                multisample: Default::default(),
                fragment: Some(wgpu::FragmentState {
                    module: &shader,
                    entry_point: Some(fragment),
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
        let (tile_pipeline, clipped_pipeline) = (
            tile_pipeline(
                terrain_shaders::entry::SURFACE,
                terrain_shaders::entry::FRAGMENT,
            ),
            tile_pipeline(
                terrain_shaders::entry::SURFACE_CLIPPED,
                terrain_shaders::entry::FRAGMENT_CLIPPED,
            ),
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
        let tile_params = params_buffer(device, 64);
        let timestamps = gpu.has_timestamps().then(|| Timestamps {
            set: device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("frame time"),
                ty: wgpu::QueryType::Timestamp,
                count: 2 * TIMED_PASSES,
            }),
            resolve: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("timestamps"),
                size: 16 * u64::from(TIMED_PASSES),
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }),
            ring: (0..TIMESTAMP_RING)
                .map(|_| Readback {
                    buffer: device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some("timestamps readback"),
                        size: 16 * u64::from(TIMED_PASSES),
                        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                        mapped_at_creation: false,
                    }),
                    pending: None,
                    mapped: Default::default(),
                })
                .collect(),
            period_ns: gpu.queue.get_timestamp_period(),
        });
        Renderer {
            gpu: gpu.clone(),
            format,
            layout,
            frame_layout,
            frame_buffer,
            frame_group,
            tile_params,
            params_capacity: 64,
            tiles_group: None,
            tile_pipeline,
            clipped_pipeline,
            depth: None,
            keep_depth: false,
            timestamps,
            frames: 0,
            submissions: Default::default(),
            last_gpu: None,
            tiles,
        }
    }

    /// The device and queue.
    pub fn gpu(&self) -> &Gpu {
        &self.gpu
    }

    /// The format of the targets it draws into.
    pub fn format(&self) -> wgpu::TextureFormat {
        self.format
    }

    /// The tiles' layout.
    pub fn layout(&self) -> &Layout {
        &self.layout
    }

    /// The layout of bind group 0, the frame's uniforms (`FrameUniform`), which every pass
    /// has bound: a method's own pipeline puts it first.
    pub fn frame_bind_group_layout(&self) -> &wgpu::BindGroupLayout {
        &self.frame_layout
    }

    /// The depth-stencil state every pass's depth buffer takes (reversed depth).
    pub fn depth_state(&self) -> wgpu::DepthStencilState {
        depth_state()
    }

    /// Keeps the depth buffer of every later frame for [`Renderer::read_depth`] (stored and
    /// copyable, which costs some speed; off by default).
    pub fn keep_depth(&mut self, keep: bool) {
        if keep != self.keep_depth {
            self.keep_depth = keep;
            self.depth = None;
        }
    }

    /// The last frame's depth buffer, row-major from the top left: reversed depth, 0 where
    /// nothing was drawn (the background). Needs [`Renderer::keep_depth`].
    pub fn read_depth(&self) -> Result<Vec<f32>, super::GpuError> {
        let (Some((texture, _)), true) = (&self.depth, self.keep_depth) else {
            return Err(super::GpuError::Readback(
                "no depth kept: call keep_depth(true) before rendering".into(),
            ));
        };
        let bytes = super::offscreen::read_texture(&self.gpu.device, &self.gpu.queue, texture, 4)?;
        Ok(bytemuck::pod_collect_to_vec(&bytes))
    }

    /// Starts a frame seen from `camera` into `target`: the frame's uniforms are written;
    /// the first pass clears the target and the depth buffer.
    pub fn begin_frame<'f>(
        &'f mut self,
        target: &'f wgpu::TextureView,
        camera: &'f Camera,
    ) -> Frame<'f> {
        let started = Instant::now();
        let size = target.texture().size();
        self.ensure_depth(size.width, size.height);
        let aspect = f64::from(size.width) / f64::from(size.height.max(1));
        let light = Camera::to_render(glam::DVec3::new(
            -0.5,
            -0.5,
            std::f64::consts::FRAC_1_SQRT_2,
        ))
        .normalize();
        // The anchor: the sample nearest the camera. Positions are built from sample
        // indices relative to it (see the shader), exact in f32.
        let spacing = self.layout.spacing_m;
        let anchor = [
            (camera.position[0] / spacing[0]).round(),
            (camera.position[1] / spacing[1]).round(),
        ];
        let p = camera.position;
        let frame = FrameUniform {
            view_proj: camera.view_proj_f32(aspect).to_cols_array_2d(),
            light_dir: [light.x as f32, light.y as f32, light.z as f32, 0.0],
            // y: a pixel's height per metre of distance on the view axis.
            params: [
                AMBIENT,
                (2.0 * (camera.fov_y / 2.0).tan() / f64::from(size.height.max(1))) as f32,
                0.0,
                0.0,
            ],
            camera: [
                (p[0] - anchor[0] * spacing[0]) as f32,
                p[2] as f32,
                (p[1] - anchor[1] * spacing[1]) as f32,
                0.0,
            ],
            // The terrain's edge in render space: west, north, east, south.
            clip: [
                -p[0] as f32,
                -p[1] as f32,
                (self.layout.extent_m[0] - p[0]) as f32,
                (self.layout.extent_m[1] - p[1]) as f32,
            ],
        };
        self.gpu
            .queue
            .write_buffer(&self.frame_buffer, 0, bytemuck::bytes_of(&frame));
        let encoder = self
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("frame"),
            });
        Frame {
            renderer: self,
            target,
            camera,
            anchor,
            encoder,
            passes: 0,
            prepared: Prepared::default(),
            stats: RenderStats::default(),
            started,
        }
    }

    fn ensure_depth(&mut self, width: u32, height: u32) {
        if let Some((texture, _)) = &self.depth
            && texture.width() == width
            && texture.height() == height
        {
            return;
        }
        let texture = self.gpu.device.create_texture(&wgpu::TextureDescriptor {
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

    fn ensure_params_capacity(&mut self, slots: u64) {
        if slots <= self.params_capacity {
            return;
        }
        let capacity = slots.next_power_of_two();
        self.tile_params = params_buffer(&self.gpu.device, capacity);
        self.params_capacity = capacity;
        self.tiles_group = None;
    }

    /// Group 1 made again when the parameters' buffer or the sample arena changed.
    fn ensure_tiles_group(&mut self) {
        let generation = self.tiles.arena.generation;
        if matches!(&self.tiles_group, Some((_, g)) if *g == generation) {
            return;
        }
        let group = self
            .gpu
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("tile samples"),
                layout: &self.tiles.bindings().samples,
                entries: &[wgpu::BindGroupEntry {
                    binding: 0,
                    resource: self.tiles.arena.binding(),
                }],
            });
        self.tiles_group = Some((group, generation));
    }

    /// Waits (at most [`GPU_TIMEOUT`]) for every frame submitted to finish, and reads their
    /// timestamps back: the GPU time of the last frame, when the adapter measures it. For a
    /// caller that measures a frame or reads its image; the render loop never calls it.
    pub fn wait_for_gpu(&mut self) -> Result<Option<f64>, super::GpuError> {
        self.gpu
            .device
            .poll(wgpu::PollType::Wait {
                submission_index: None,
                timeout: Some(GPU_TIMEOUT),
            })
            .map_err(|e| super::GpuError::Readback(format!("waiting for the GPU: {e}")))?;
        self.collect_timestamps();
        Ok(self
            .last_gpu
            .filter(|&(frame, _)| frame == self.frames)
            .map(|(_, ms)| ms))
    }

    /// Reads back the timestamps of every frame whose read-back has arrived (no wait).
    fn collect_timestamps(&mut self) {
        let Some(t) = &mut self.timestamps else {
            return;
        };
        for r in &mut t.ring {
            let Some((frame, timed)) = r.pending else {
                continue;
            };
            match r.mapped.load(std::sync::atomic::Ordering::Acquire) {
                MAP_PENDING => continue,
                MAP_DONE => {
                    let slice = r.buffer.slice(..16 * u64::from(timed));
                    if let Ok(data) = slice.get_mapped_range() {
                        let stamps: &[u64] = bytemuck::cast_slice(&data);
                        // From the first pass's start to the last timed pass's end.
                        let ticks = stamps[2 * timed as usize - 1].saturating_sub(stamps[0]);
                        let ms = ticks as f64 * f64::from(t.period_ns) / 1.0e6;
                        if self.last_gpu.is_none_or(|(f, _)| f < frame) {
                            self.last_gpu = Some((frame, ms));
                        }
                    }
                    r.buffer.unmap();
                }
                _ => {}
            }
            r.pending = None;
        }
    }
}

fn depth_state() -> wgpu::DepthStencilState {
    wgpu::DepthStencilState {
        format: DEPTH_FORMAT,
        depth_write_enabled: Some(true),
        depth_compare: Some(wgpu::CompareFunction::Greater),
        stencil: Default::default(),
        bias: Default::default(),
    }
}

/// The tiles a frame prepared, by slot.
#[derive(Debug, Default)]
struct Prepared {
    ids: Vec<TileId>,
    blocks: Vec<Option<[u32; 2]>>,
    /// Whether the tile reaches past the terrain's edge (padded), so is clipped.
    clipped: Vec<bool>,
}

/// One frame being recorded. See the module documentation.
#[derive(Debug)]
pub struct Frame<'f> {
    renderer: &'f mut Renderer,
    target: &'f wgpu::TextureView,
    camera: &'f Camera,
    anchor: [f64; 2],
    encoder: wgpu::CommandEncoder,
    passes: u32,
    prepared: Prepared,
    stats: RenderStats,
    started: Instant,
}

impl<'f> Frame<'f> {
    pub fn camera(&self) -> &Camera {
        self.camera
    }

    /// Width and height of the target, pixels.
    pub fn viewport(&self) -> [u32; 2] {
        let size = self.target.texture().size();
        [size.width, size.height]
    }

    pub fn gpu(&self) -> &Gpu {
        &self.renderer.gpu
    }

    /// The resident tiles.
    pub fn tiles(&self) -> &TileStore {
        &self.renderer.tiles
    }

    /// The frame's command encoder and the resident tiles together, for a method copying
    /// from the tiles before its passes.
    pub fn encoder_and_tiles(&mut self) -> (&mut wgpu::CommandEncoder, &TileStore) {
        (&mut self.encoder, &self.renderer.tiles)
    }

    /// The camera's anchor: the level-0 sample nearest it, whose indices positions are
    /// counted from (the frame uniform's `camera` is the camera relative to it).
    pub fn anchor(&self) -> [f64; 2] {
        self.anchor
    }

    /// The stats so far; a method adds what it alone knows (triangles, fillers).
    pub fn stats_mut(&mut self) -> &mut RenderStats {
        &mut self.stats
    }

    /// Prepares `tiles` (those resident; the others are left out) for the tile pipeline:
    /// a sample buffer each from the pool, their textures (MapBlocks assembled), their
    /// uniforms. Returns each tile's slot for [`FramePass::bind_tile`] (`None`: not
    /// resident, or no room in the sample arena this frame, see [`TileStore::sample_slots`]), and, in [`Frame::draw_order`], the order that binds each block once.
    /// Call it once a frame.
    pub fn prepare_tiles(&mut self, tiles: &[(TileId, TileExtras)]) -> Vec<Option<usize>> {
        let r = &mut *self.renderer;
        let mut slots = Vec::with_capacity(tiles.len());
        let mut ids = Vec::with_capacity(tiles.len());
        let mut extras = Vec::with_capacity(tiles.len());
        for (id, extra) in tiles {
            if r.tiles.contains(*id) {
                slots.push(Some(ids.len()));
                ids.push(*id);
                extras.push(*extra);
            } else {
                slots.push(None);
            }
        }
        let (held, uploads) = r.tiles.pool_samples(&ids);
        // A tile the arena had no room for this frame (the device's buffer limits) is not
        // drawn: the others keep their slots, renumbered.
        if held.iter().any(Option::is_none) {
            let mut renumbered = vec![None; ids.len()];
            let mut next = 0;
            for (old, h) in held.iter().enumerate() {
                if h.is_some() {
                    renumbered[old] = Some(next);
                    next += 1;
                }
            }
            for slot in slots.iter_mut() {
                *slot = slot.and_then(|old| renumbered[old]);
            }
            let keep: Vec<bool> = held.iter().map(Option::is_some).collect();
            let mut k = keep.iter();
            ids.retain(|_| *k.next().expect("one flag a tile"));
            let mut k = keep.iter();
            extras.retain(|_| *k.next().expect("one flag a tile"));
        }
        let samples: Vec<[i32; 3]> = held.into_iter().flatten().collect();
        r.ensure_params_capacity(ids.len() as u64);
        r.ensure_tiles_group();
        let blocks = r.tiles.frame_blocks(&ids);
        self.stats.sample_uploads += uploads;
        let n = r.layout.tile_size;
        let cells = f64::from(n - 1);
        let mut uniforms: Vec<TileUniform> = Vec::with_capacity(ids.len());
        for (slot, (&id, extra)) in ids.iter().zip(&extras).enumerate() {
            let (_, uv) = r.tiles.binding_of(id, blocks[slot]);
            let heights = r.tiles.heights(id).expect("resident");
            // A tile of level k: its samples are 2^k level-0 samples apart, so its origin
            // is counted in its own samples (a division by a power of two: exact) and its
            // spacing is 2^k level 0's. Tiles of one level share their border samples bit
            // for bit, as at level 0.
            let step = Layout::sample_step(id.level);
            let spacing = r.layout.spacing_at(id.level);
            let u = TileUniform {
                origin: [
                    ((f64::from(id.x) * cells * step - self.anchor[0]) / step) as f32,
                    0.0,
                    ((f64::from(id.y) * cells * step - self.anchor[1]) / step) as f32,
                    0.0,
                ],
                spacing: [
                    spacing[0] as f32,
                    spacing[1] as f32,
                    n as f32,
                    extra.floor_m,
                ],
                points: extra.points,
                uv,
                codes: [samples[slot][0], samples[slot][1], samples[slot][2], 0],
                metres: [heights.quantum_m as f32, heights.offset_m as f32, 0.0, 0.0],
            };
            uniforms.push(u);
        }
        if !uniforms.is_empty() {
            r.gpu
                .queue
                .write_buffer(&r.tile_params, 0, bytemuck::cast_slice(&uniforms));
        }
        let clipped = ids
            .iter()
            .map(|&id| {
                let extent = r.layout.tile_extent_m_at(id.level);
                let [x0, y0] = r.layout.tile_origin_m(id);
                // Past the edge by more than rounding: the tile holds padding.
                let slack = 1e-6 * (extent[0] + extent[1]);
                x0 + extent[0] > r.layout.extent_m[0] + slack
                    || y0 + extent[1] > r.layout.extent_m[1] + slack
            })
            .collect();
        self.prepared = Prepared {
            ids,
            blocks,
            clipped,
        };
        slots
    }

    /// The prepared slots in the order that binds each MapBlock's texture once: block by
    /// block, then the tiles drawn with their own textures, in preparation order within each.
    pub fn draw_order(&self) -> Vec<usize> {
        let blocks = &self.prepared.blocks;
        let mut order: Vec<usize> = (0..blocks.len()).collect();
        order.sort_by_key(|&slot| (blocks[slot].is_none(), blocks[slot]));
        order
    }

    /// Opens a render pass on the target and the depth buffer, the frame's uniforms bound
    /// at group 0; the tile pipeline is set by [`FramePass::bind_tile`]. The frame's first
    /// pass clears both; the depth buffer is kept for the passes after it.
    pub fn pass(&mut self) -> FramePass<'_> {
        self.open_pass(true)
    }

    /// [`Frame::pass`] for the frame's last pass: the depth buffer is not kept after it
    /// (unless it is read back, [`Renderer::keep_depth`]), which saves a store.
    pub fn last_pass(&mut self) -> FramePass<'_> {
        self.open_pass(false)
    }

    /// [`Frame::pass`] with a second colour attachment, `extra` (cleared to `clear` when
    /// `clear` is given), for a method's pipeline that writes one more target.
    pub fn pass_with(
        &mut self,
        extra: &wgpu::TextureView,
        clear: Option<wgpu::Color>,
    ) -> FramePass<'_> {
        let attachment = wgpu::RenderPassColorAttachment {
            view: extra,
            depth_slice: None,
            resolve_target: None,
            ops: wgpu::Operations {
                load: clear.map_or(wgpu::LoadOp::Load, wgpu::LoadOp::Clear),
                store: wgpu::StoreOp::Store,
            },
        };
        self.open_pass_with(true, Some(attachment))
    }

    /// The frame's command encoder, for copies a method records between its passes.
    pub fn encoder(&mut self) -> &mut wgpu::CommandEncoder {
        &mut self.encoder
    }

    fn open_pass(&mut self, keep_depth: bool) -> FramePass<'_> {
        self.open_pass_with(keep_depth, None)
    }

    fn open_pass_with(
        &mut self,
        keep_depth: bool,
        extra: Option<wgpu::RenderPassColorAttachment<'_>>,
    ) -> FramePass<'_> {
        let pass = self.passes;
        let attachments = if extra.is_some() { 2 } else { 1 };
        let first = pass == 0;
        self.passes += 1;
        let r = &*self.renderer;
        let depth = &r.depth.as_ref().expect("made in begin_frame").1;
        let mut pass =
            self.encoder
                .begin_render_pass(&wgpu::RenderPassDescriptor {
                    label: Some("terrain"),
                    color_attachments: &[
                        Some(wgpu::RenderPassColorAttachment {
                            view: self.target,
                            depth_slice: None,
                            resolve_target: None,
                            ops: wgpu::Operations {
                                load: if first {
                                    wgpu::LoadOp::Clear(wgpu::Color {
                                        r: SKY[0],
                                        g: SKY[1],
                                        b: SKY[2],
                                        a: 1.0,
                                    })
                                } else {
                                    wgpu::LoadOp::Load
                                },
                                store: wgpu::StoreOp::Store,
                            },
                        }),
                        extra,
                    ][..attachments],
                    depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                        view: depth,
                        depth_ops: Some(wgpu::Operations {
                            load: if first {
                                wgpu::LoadOp::Clear(0.0)
                            } else {
                                wgpu::LoadOp::Load
                            },
                            store: if keep_depth || r.keep_depth {
                                wgpu::StoreOp::Store
                            } else {
                                wgpu::StoreOp::Discard
                            },
                        }),
                        stencil_ops: None,
                    }),
                    timestamp_writes: r.timestamps.as_ref().filter(|_| pass < TIMED_PASSES).map(
                        |t| wgpu::RenderPassTimestampWrites {
                            query_set: &t.set,
                            beginning_of_pass_write_index: Some(2 * pass),
                            end_of_pass_write_index: Some(2 * pass + 1),
                        },
                    ),
                    occlusion_query_set: None,
                    multiview_mask: None,
                })
                .forget_lifetime();
        pass.set_bind_group(0, &r.frame_group, &[]);
        FramePass {
            pass,
            renderer: r,
            prepared: &self.prepared,
            stats: &mut self.stats,
            bound: None,
            tiles_bound: false,
            slot: 0,
            index_buffer: None,
            pipeline: None,
            clip_everything: false,
        }
    }

    /// Submits the frame, then waits (at most [`GPU_TIMEOUT`]) for the frame before it, so
    /// that no more than [`FRAMES_IN_FLIGHT`] are queued; never for this one. Returns what
    /// it drew, with the GPU time of the latest frame read back so far.
    pub fn finish(self) -> RenderStats {
        let Frame {
            renderer: r,
            mut encoder,
            mut stats,
            started,
            passes,
            ..
        } = self;
        r.collect_timestamps();
        r.frames += 1;
        let frame = r.frames;
        let timed = passes.min(TIMED_PASSES);
        // A free read-back buffer of the ring, if any: else this frame is not timed.
        let readback = match &mut r.timestamps {
            Some(t) if timed > 0 => {
                let free = t.ring.iter().position(|b| b.pending.is_none());
                if let Some(i) = free {
                    let bytes = 16 * u64::from(timed);
                    encoder.resolve_query_set(&t.set, 0..2 * timed, &t.resolve, 0);
                    encoder.copy_buffer_to_buffer(&t.resolve, 0, &t.ring[i].buffer, 0, bytes);
                }
                free
            }
            _ => None,
        };
        let submission = r.gpu.queue.submit([encoder.finish()]);
        if let (Some(t), Some(i)) = (&mut r.timestamps, readback) {
            let b = &mut t.ring[i];
            b.pending = Some((frame, timed));
            b.mapped
                .store(MAP_PENDING, std::sync::atomic::Ordering::Release);
            let mapped = b.mapped.clone();
            b.buffer
                .slice(..16 * u64::from(timed))
                .map_async(wgpu::MapMode::Read, move |result| {
                    let state = if result.is_ok() { MAP_DONE } else { MAP_FAILED };
                    mapped.store(state, std::sync::atomic::Ordering::Release);
                });
        }
        r.submissions.push_back(submission);
        while r.submissions.len() as u64 >= FRAMES_IN_FLIGHT {
            let Some(earlier) = r.submissions.pop_front() else {
                break;
            };
            // The frame before this one: the GPU has had this frame's recording time to
            // draw it. A lost device shows as the next frame's error, not a hang.
            let _ = r.gpu.device.poll(wgpu::PollType::Wait {
                submission_index: Some(earlier),
                timeout: Some(GPU_TIMEOUT),
            });
        }
        r.collect_timestamps();
        stats.gpu_ms = r.last_gpu.map(|(_, ms)| ms);
        stats.encode_ms = started.elapsed().as_secs_f64() * 1e3;
        stats
    }
}

/// The tiles' parameters: `slots` `TileUniform`s, per-instance vertex attributes.
fn params_buffer(device: &wgpu::Device, slots: u64) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("tile parameters"),
        size: slots * size_of::<TileUniform>() as u64,
        usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

#[cfg(test)]
mod tests {
    /// Every `.rs` file under `dir`.
    fn sources(dir: &std::path::Path, out: &mut Vec<std::path::PathBuf>) {
        for entry in std::fs::read_dir(dir).expect("the client's sources") {
            let path = entry.expect("a directory entry").path();
            if path.is_dir() {
                sources(&path, out);
            } else if path.extension().is_some_and(|e| e == "rs") {
                out.push(path);
            }
        }
    }

    /// No frame of `fly` or `view` waits for the GPU without a bound: nothing in the client
    /// waits indefinitely (the few waits left, for a measured frame or an image read back,
    /// give up after `GPU_TIMEOUT`), and `Frame::finish` waits only for the frame before.
    #[test]
    fn nothing_in_the_client_waits_for_the_gpu_without_a_bound() {
        let needle = ["wait", "_indefinitely"].concat();
        let mut files = Vec::new();
        sources(
            &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src"),
            &mut files,
        );
        assert!(files.len() > 20, "the sources were found: {files:?}");
        let offenders: Vec<_> = files
            .iter()
            .filter(|f| {
                std::fs::read_to_string(f)
                    .expect("a source file")
                    .contains(&needle)
            })
            .collect();
        assert!(offenders.is_empty(), "{needle} in {offenders:?}");
        let this = std::fs::read_to_string(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src/render/frame/mod.rs"),
        )
        .expect("this file");
        let finish = this
            .split("pub fn finish(self)")
            .nth(1)
            .and_then(|s| s.split("\n    }\n").next())
            .unwrap_or_default();
        assert!(
            finish.contains("submission_index: Some(earlier)"),
            "Frame::finish waits only for an earlier submission"
        );
    }
}
