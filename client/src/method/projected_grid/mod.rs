//! The projected grids as methods: persistent grid mapping (Livny et al. 2009) and the
//! error-bounded projective grid (Löffler et al. 2009), over the same streamed tiles.
//!
//! Both keep a regular grid of `columns x rows` vertices on the GPU (an index buffer made
//! once; the vertex shader makes a vertex's place on the screen from its index) and an
//! [`Atlas`] of the resident tiles' height pyramids and colours. Each frame the vertex
//! shader (`grid.wgsl`) casts each vertex's ray from an auxiliary camera
//! ([`geometry::aux_camera`]) onto a plane below the terrain, picks the pyramid
//! level whose samples are as far apart as the vertex's neighbours on the ground, blends it
//! with its parent and displaces the vertex by the height found; the main camera draws it.
//!
//! - **Persistent grid mapping** (`pgm`): a uniform grid; nothing bounds its error.
//! - **Error-bounded projective grid** (`projective-grid`): the grid warped so its cells
//!   come out square on the ground ([`geometry::warp_tables`]); each pixel's error, the
//!   grid's height at the point it draws against the surface's own there (the finest
//!   resident tile's triangles, widened by its distance from full resolution) turned into
//!   pixels, is written with the colour to an error buffer; a second pass casts rays through
//!   the heights in the pixels the buffer marks (past the threshold, or not covered by the
//!   grid), replacing colour and depth. Its counters (pixels ray cast, pixels past the threshold) are read back on
//!   request ([`super::LodMethod::frame_measures`]).
//!
//! Knobs: the grid's size ([`GridSettings::size`]); the error threshold
//! (`--max-error-px`) for the projective grid. No triangle budget plays a part: the grid
//! draws the same triangles every frame.

pub mod atlas;
pub mod geometry;

use self::atlas::{Atlas, slot_order};
use self::geometry::{aux_camera, warp_tables};
use super::{Build, LodMethod, MethodBytes, MethodConfig, MethodInput, MethodKind, MethodOutput};
use crate::lod::plan::{self, LodSettings};
use crate::lod::strips::MaskSet;
use crate::render::{Frame, Gpu};
use terrain_shaders::{
    ERROR_UNCOVERED, GRID, GRID_MAX_LEVELS, GridCounters, GridUniform, WARP_LINES, grid_entry,
    grid_flag,
};
use terrain_shared::{Manifest, TileId, TileRecord};
use web_time::Instant;

/// Default grid: vertices per row and per column.
pub const DEFAULT_GRID: [u32; 2] = [256, 144];
/// Format of the error buffer: one normalised error per pixel.
const ERROR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::R16Float;

/// How a projected grid is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GridSettings {
    /// Vertices per row and per column of the persistent grid.
    pub size: [u32; 2],
    /// Whether the error-bounded grid is warped (Löffler et al.'s non-uniform grid);
    /// `false` keeps it uniform, as persistent grid mapping draws it.
    pub warp: bool,
    /// Whether the error-bounded grid casts rays in the pixels past the threshold.
    pub ray_casting: bool,
}

impl Default for GridSettings {
    fn default() -> GridSettings {
        GridSettings {
            size: DEFAULT_GRID,
            warp: true,
            ray_casting: true,
        }
    }
}

impl GridSettings {
    /// Triangles the grid draws.
    pub fn triangles(&self) -> u64 {
        2 * u64::from(self.size[0].saturating_sub(1)) * u64::from(self.size[1].saturating_sub(1))
    }
}

/// A projected grid. See the module documentation.
#[derive(Debug)]
pub struct ProjectedGrid {
    kind: MethodKind,
    settings: GridSettings,
    lod: LodSettings,
    manifest: Manifest,
    masks: MaskSet,
    atlas: Atlas,
    uniform: wgpu::Buffer,
    resources_layout: wgpu::BindGroupLayout,
    resources: Option<(wgpu::BindGroup, u64)>,
    ray_layout: wgpu::BindGroupLayout,
    sampler: wgpu::Sampler,
    grid_pipeline: wgpu::RenderPipeline,
    ray_pipeline: Option<wgpu::RenderPipeline>,
    indices: Option<(GridIndices, [u32; 2])>,
    error: Option<ErrorBuffer>,
    counters: wgpu::Buffer,
    readback: wgpu::Buffer,
    /// Whether the last frame copied its counters for read-back.
    counted: bool,
    lowest_m: f64,
    highest_m: f64,
}

/// The grid's index buffer: 16-bit indices when the grid has at most 65536 vertices.
#[derive(Debug)]
struct GridIndices {
    buffer: wgpu::Buffer,
    format: wgpu::IndexFormat,
    len: u32,
    triangles: u32,
}

impl GridIndices {
    fn new(gpu: &Gpu, size: [u32; 2], triangles: u32) -> GridIndices {
        let indices = ProjectedGrid::grid_indices(size);
        let (bytes, format): (Vec<u8>, _) = if size[0] * size[1] <= 1 << 16 {
            let short: Vec<u16> = indices.iter().map(|&i| i as u16).collect();
            (
                bytemuck::cast_slice(&short).to_vec(),
                wgpu::IndexFormat::Uint16,
            )
        } else {
            (
                bytemuck::cast_slice(&indices).to_vec(),
                wgpu::IndexFormat::Uint32,
            )
        };
        let buffer = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("terrain/persistent grid"),
            size: (bytes.len() as u64).next_multiple_of(4).max(4),
            usage: wgpu::BufferUsages::INDEX | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut padded = bytes;
        padded.resize(buffer.size() as usize, 0);
        gpu.queue.write_buffer(&buffer, 0, &padded);
        GridIndices {
            buffer,
            format,
            len: indices.len() as u32,
            triangles,
        }
    }
}

#[derive(Debug)]
struct ErrorBuffer {
    texture: wgpu::Texture,
    view: wgpu::TextureView,
    group: wgpu::BindGroup,
}

impl ProjectedGrid {
    pub fn new(config: &MethodConfig, with: &Build<'_>) -> ProjectedGrid {
        let device = &with.gpu.device;
        let manifest = with.manifest.clone();
        let atlas = Atlas::new(with.gpu, &manifest);
        let storage = |binding: u32, read_only: bool, visibility: wgpu::ShaderStages| {
            wgpu::BindGroupLayoutEntry {
                binding,
                visibility,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            }
        };
        let both = wgpu::ShaderStages::VERTEX_FRAGMENT;
        let resources_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("grid resources"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: both,
                    // Storage, not uniform: see `grid` in grid.wgsl (a leak on lavapipe).
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Storage { read_only: true },
                        has_dynamic_offset: false,
                        min_binding_size: wgpu::BufferSize::new(size_of::<GridUniform>() as u64),
                    },
                    count: None,
                },
                storage(1, true, both),
                storage(2, true, both),
                storage(3, true, both),
                wgpu::BindGroupLayoutEntry {
                    binding: 4,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: true },
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 5,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                    count: None,
                },
            ],
        });
        let ray_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("grid ray casting"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: false },
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                    count: None,
                },
                storage(1, false, wgpu::ShaderStages::FRAGMENT),
            ],
        });
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("grid"),
            source: wgpu::ShaderSource::Wgsl(GRID.into()),
        });
        let error_bounded = config.kind == MethodKind::ProjectiveGrid;
        let grid_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("grid"),
            bind_group_layouts: &[Some(with.frame_layout), Some(&resources_layout)],
            immediate_size: 0,
        });
        let colour_target = Some(wgpu::ColorTargetState {
            format: with.format,
            blend: None,
            write_mask: wgpu::ColorWrites::ALL,
        });
        let error_target = Some(wgpu::ColorTargetState {
            format: ERROR_FORMAT,
            blend: None,
            write_mask: wgpu::ColorWrites::ALL,
        });
        let depth = |compare: wgpu::CompareFunction| {
            Some(wgpu::DepthStencilState {
                format: crate::render::frame::DEPTH_FORMAT,
                depth_write_enabled: Some(true),
                depth_compare: Some(compare),
                stencil: Default::default(),
                bias: Default::default(),
            })
        };
        let targets_error = [colour_target.clone(), error_target];
        let targets_colour = [colour_target.clone()];
        let grid_pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("grid"),
            layout: Some(&grid_layout),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some(grid_entry::GRID),
                compilation_options: Default::default(),
                buffers: &[],
            },
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some(if error_bounded {
                    grid_entry::FRAGMENT_ERROR
                } else {
                    grid_entry::FRAGMENT
                }),
                compilation_options: Default::default(),
                targets: if error_bounded {
                    &targets_error
                } else {
                    &targets_colour
                },
            }),
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::TriangleList,
                cull_mode: None,
                ..Default::default()
            },
            depth_stencil: depth(wgpu::CompareFunction::Greater),
            multisample: Default::default(),
            multiview_mask: None,
            cache: None,
        });
        let ray_pipeline = error_bounded.then(|| {
            let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("grid ray casting"),
                bind_group_layouts: &[
                    Some(with.frame_layout),
                    Some(&resources_layout),
                    Some(&ray_layout),
                ],
                immediate_size: 0,
            });
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some("grid ray casting"),
                layout: Some(&layout),
                vertex: wgpu::VertexState {
                    module: &module,
                    entry_point: Some(grid_entry::FULLSCREEN),
                    compilation_options: Default::default(),
                    buffers: &[],
                },
                fragment: Some(wgpu::FragmentState {
                    module: &module,
                    entry_point: Some(grid_entry::RAY),
                    compilation_options: Default::default(),
                    targets: &targets_colour,
                }),
                primitive: Default::default(),
                // The ray's depth replaces the grid's, nearer or not.
                depth_stencil: depth(wgpu::CompareFunction::Always),
                multisample: Default::default(),
                multiview_mask: None,
                cache: None,
            })
        });
        let uniform = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("terrain/grid uniform"),
            size: size_of::<GridUniform>() as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let counters = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("terrain/grid counters"),
            size: size_of::<GridCounters>() as u64,
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_DST
                | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("terrain/grid counters read-back"),
            size: size_of::<GridCounters>() as u64,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("grid colour"),
            address_mode_u: wgpu::AddressMode::ClampToEdge,
            address_mode_v: wgpu::AddressMode::ClampToEdge,
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            mipmap_filter: wgpu::MipmapFilterMode::Linear,
            ..Default::default()
        });
        // The coarsest tile's bounds are the whole terrain's.
        let (lowest_m, highest_m) = manifest
            .levels
            .last()
            .map(|level| {
                level
                    .tiles
                    .iter()
                    .fold((f64::MAX, f64::MIN), |(lo, hi), t| {
                        (lo.min(f64::from(t.min_m)), hi.max(f64::from(t.max_m)))
                    })
            })
            .unwrap_or((0.0, 0.0));
        ProjectedGrid {
            kind: config.kind,
            settings: config.grid,
            lod: config.lod,
            masks: MaskSet::new(manifest.tile_size),
            manifest,
            atlas,
            uniform,
            resources_layout,
            resources: None,
            ray_layout,
            sampler,
            grid_pipeline,
            ray_pipeline,
            indices: None,
            error: None,
            counters,
            readback,
            counted: false,
            lowest_m,
            highest_m,
        }
    }

    fn error_bounded(&self) -> bool {
        self.kind == MethodKind::ProjectiveGrid
    }

    /// The grid's triangles: two per cell, as a list of vertex indices (row-major).
    fn grid_indices(size: [u32; 2]) -> Vec<u32> {
        let [columns, rows] = size;
        let mut out = Vec::with_capacity(6 * (columns as usize - 1) * (rows as usize - 1));
        for j in 0..rows - 1 {
            for i in 0..columns - 1 {
                let a = j * columns + i;
                let (b, c, d) = (a + 1, a + columns, a + columns + 1);
                out.extend_from_slice(&[a, b, c, b, d, c]);
            }
        }
        out
    }

    /// GPU bytes of what it holds besides the atlas.
    fn own_gpu_bytes(&self) -> u64 {
        let error = self.error.as_ref().map_or(0, |e| {
            2 * u64::from(e.texture.width()) * u64::from(e.texture.height())
        });
        self.indices
            .as_ref()
            .map_or(0, |(set, _)| set.buffer.size())
            + self.uniform.size()
            + self.counters.size()
            + self.readback.size()
            + error
    }

    /// Bytes of the atlas's table on the CPU.
    fn atlas_table_cpu_bytes(&self) -> u64 {
        self.atlas.table_cpu_bytes()
    }

    fn ensure_error_buffer(&mut self, gpu: &Gpu, viewport: [u32; 2]) {
        if let Some(e) = &self.error
            && e.texture.width() == viewport[0]
            && e.texture.height() == viewport[1]
        {
            return;
        }
        let texture = gpu.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("terrain/grid error buffer"),
            size: wgpu::Extent3d {
                width: viewport[0].max(1),
                height: viewport[1].max(1),
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: ERROR_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
            view_formats: &[],
        });
        let view = texture.create_view(&Default::default());
        let group = gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("grid ray casting"),
            layout: &self.ray_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(&view),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: self.counters.as_entire_binding(),
                },
            ],
        });
        self.error = Some(ErrorBuffer {
            texture,
            view,
            group,
        });
    }

    fn ensure_resources(&mut self, gpu: &Gpu) {
        if self
            .resources
            .as_ref()
            .is_some_and(|(_, generation)| *generation == self.atlas.generation)
        {
            return;
        }
        let colour = self.atlas.colour_texture().create_view(&Default::default());
        let group = gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("grid resources"),
            layout: &self.resources_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: self.uniform.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: self.atlas.heights_buffer().as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: self.atlas.table_buffer().as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: self.atlas.infos_buffer().as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 4,
                    resource: wgpu::BindingResource::TextureView(&colour),
                },
                wgpu::BindGroupEntry {
                    binding: 5,
                    resource: wgpu::BindingResource::Sampler(&self.sampler),
                },
            ],
        });
        self.resources = Some((group, self.atlas.generation));
    }

    /// The frame's uniform: the auxiliary camera, the plane, the atlas's layout.
    fn uniform(&self, frame: &Frame<'_>) -> GridUniform {
        let camera = frame.camera();
        let viewport = frame.viewport();
        let aspect = f64::from(viewport[0]) / f64::from(viewport[1].max(1));
        let height = camera.position[2];
        // The plane the grid is cast onto: under the lowest point, and under the camera.
        let plane_y = (self.lowest_m - height).min(-1.0);
        let extent = self.manifest.extent_m;
        let far = [0.0, extent[0]]
            .into_iter()
            .flat_map(|x| [0.0, extent[1]].map(|y| (x, y)))
            .map(|(x, y)| (x - camera.position[0]).hypot(y - camera.position[1]))
            .fold(0.0f64, f64::max)
            * 1.5
            + plane_y.abs();
        let aux = aux_camera(camera, aspect, -plane_y, height - self.highest_m);
        let mut flags = 0;
        let mut warp_u = [[0.0f32; 4]; 9];
        let mut warp_v = [[0.0f32; 4]; 9];
        if self.error_bounded() {
            flags |= grid_flag::ERROR_BOUNDED;
            if self.settings.ray_casting {
                flags |= grid_flag::RAY_CASTING;
            }
            if self.settings.warp {
                flags |= grid_flag::WARP;
                let (u, v) = warp_tables(&aux, plane_y, far);
                for k in 0..WARP_LINES {
                    warp_u[k / 4][k % 4] = u[k] as f32;
                    warp_v[k / 4][k % 4] = v[k] as f32;
                }
            }
        }
        let half = camera.fov_y / 2.0;
        let focal_px = f64::from(viewport[1]) / 2.0 / half.tan();
        let spacing = self.manifest.spacing_m;
        let anchor = frame.anchor();
        let mut levels = [[0u32; 4]; GRID_MAX_LEVELS];
        for (slot, level) in levels.iter_mut().zip(&self.atlas.levels) {
            *slot = [level[0], level[1], level[2], 0];
        }
        let mut mips = [[0u32; 4]; terrain_shaders::GRID_MAX_MIPS];
        for (slot, mip) in mips.iter_mut().zip(&self.atlas.layout.mips) {
            *slot = [mip.averaged, mip.blocks, mip.side, mip.per_side];
        }
        let colour = self.atlas.colour_size();
        let v4 = |v: glam::DVec3, w: f64| [v.x as f32, v.y as f32, v.z as f32, w as f32];
        let sky = crate::render::frame::SKY;
        GridUniform {
            forward: v4(aux.forward, plane_y),
            right: v4(aux.right, aux.tan_x),
            up: v4(aux.up, aux.tan_y),
            size: [
                self.settings.size[0] as f32,
                self.settings.size[1] as f32,
                far as f32,
                flags as f32,
            ],
            spacing: [
                spacing[0] as f32,
                spacing[1] as f32,
                self.lod.max_error_px as f32,
                focal_px as f32,
            ],
            anchor: [
                anchor[0] as i32,
                anchor[1] as i32,
                (self.atlas.levels.len().min(GRID_MAX_LEVELS)) as i32,
                (self.manifest.tile_size - 1) as i32,
            ],
            heights: [
                self.lowest_m as f32,
                self.highest_m as f32,
                (half.tan() * aspect) as f32,
                half.tan() as f32,
            ],
            colour: [
                colour[0] as f32,
                colour[1] as f32,
                self.atlas.colour_side as f32,
                self.atlas.layout.floats as f32,
            ],
            screen: [
                viewport[0] as f32,
                viewport[1] as f32,
                self.manifest.raster.width as f32,
                self.manifest.raster.height as f32,
            ],
            sky: [sky[0] as f32, sky[1] as f32, sky[2] as f32, 1.0],
            inverse_view_proj: camera
                .view_proj(aspect)
                .inverse()
                .as_mat4()
                .to_cols_array_2d(),
            levels,
            mips,
            warp_u,
            warp_v,
        }
    }
}

impl LodMethod for ProjectedGrid {
    fn name(&self) -> String {
        let mut name = self.kind.name().to_string();
        if self.error_bounded() {
            if !self.settings.warp {
                name.push_str("/uniform");
            }
            if !self.settings.ray_casting {
                name.push_str("/no-ray-casting");
            }
        }
        name
    }

    fn needs_every_resident_tile(&self) -> bool {
        true
    }

    fn configure(&mut self, config: &MethodConfig) {
        self.lod = config.lod;
        self.settings = config.grid;
    }

    fn draw(&mut self, input: &MethodInput<'_>, frame: &mut Frame<'_>) -> MethodOutput {
        let started = Instant::now();
        let gpu = frame.gpu().clone();
        let viewport = frame.viewport();
        // Importances rank the textures, as for every method; the strip masks' needed
        // levels are the common yardstick of the triangles a frame needs.
        let ranked = plan::rank_visible(
            frame.camera(),
            viewport,
            input.layout,
            input.tiles,
            &self.lod,
        );
        let plan = plan::FramePlan {
            budget: input.budget,
            triangles: self.settings.triangles(),
            triangles_needed: ranked
                .needed_levels
                .iter()
                .map(|&l| u64::from(self.masks.triangle_count(l)))
                .sum(),
            needed_levels: ranked.needed_levels.clone(),
            ..plan::FramePlan::default()
        };
        let importance = ranked
            .visible
            .iter()
            .zip(&ranked.importances)
            .map(|(&i, &w)| (input.tiles[i].id, w))
            .collect();
        // The atlas: the resident tiles nearest first, as clipmaps nest.
        let camera = frame.camera();
        let spacing = self.manifest.spacing_m;
        let viewpoint = [
            camera.position[0] / spacing[0],
            camera.position[1] / spacing[1],
        ];
        let ids: Vec<TileId> = input.resident.iter().map(|&(id, _)| id).collect();
        let deviation: std::collections::HashMap<TileId, f32> =
            input.resident.iter().copied().collect();
        let wanted: Vec<(TileId, f32)> = slot_order(&ids, viewpoint, self.manifest.tile_size - 1)
            .into_iter()
            .map(|id| (id, deviation[&id]))
            .collect();
        {
            let (encoder, tiles) = frame.encoder_and_tiles();
            self.atlas
                .update(&gpu, encoder, tiles, &self.manifest, &wanted);
        }
        // After the update: a resized atlas changes the colour atlas's size.
        let uniform = self.uniform(frame);
        gpu.queue
            .write_buffer(&self.uniform, 0, bytemuck::bytes_of(&uniform));
        self.ensure_resources(&gpu);
        if self.indices.as_ref().map(|(_, s)| *s) != Some(self.settings.size) {
            self.indices = Some((
                GridIndices::new(&gpu, self.settings.size, self.settings.triangles() as u32),
                self.settings.size,
            ));
        }
        if self.error_bounded() {
            self.ensure_error_buffer(&gpu, viewport);
        }
        let lod_ms = started.elapsed().as_secs_f64() * 1e3;
        let resources = &self.resources.as_ref().expect("made above").0;
        let (indices, _) = self.indices.as_ref().expect("made above");
        if self.error_bounded() {
            gpu.queue.write_buffer(
                &self.counters,
                0,
                bytemuck::bytes_of(&GridCounters::default()),
            );
            let error = self.error.as_ref().expect("made above");
            let clear = wgpu::Color {
                r: f64::from(ERROR_UNCOVERED),
                g: 0.0,
                b: 0.0,
                a: 0.0,
            };
            {
                let mut pass = frame.pass_with(&error.view, Some(clear));
                let raw = pass.raw();
                raw.set_pipeline(&self.grid_pipeline);
                raw.set_bind_group(1, resources, &[]);
                raw.set_index_buffer(indices.buffer.slice(..), indices.format);
                raw.draw_indexed(0..indices.len, 0, 0..1);
                let stats = pass.stats_mut();
                stats.draw_calls += 1;
                stats.triangles += u64::from(indices.triangles);
            }
            // With ray casting off the pass still runs, to count the pixels past the
            // threshold (its shader discards every one).
            if let Some(ray) = &self.ray_pipeline {
                let mut pass = frame.last_pass();
                let raw = pass.raw();
                raw.set_pipeline(ray);
                raw.set_bind_group(1, resources, &[]);
                raw.set_bind_group(2, &error.group, &[]);
                raw.draw(0..3, 0..1);
                pass.stats_mut().draw_calls += 1;
            }
            frame.encoder().copy_buffer_to_buffer(
                &self.counters,
                0,
                &self.readback,
                0,
                size_of::<GridCounters>() as u64,
            );
            self.counted = true;
        } else {
            let mut pass = frame.last_pass();
            let raw = pass.raw();
            raw.set_pipeline(&self.grid_pipeline);
            raw.set_bind_group(1, resources, &[]);
            raw.set_index_buffer(indices.buffer.slice(..), indices.format);
            raw.draw_indexed(0..indices.len, 0, 0..1);
            let stats = pass.stats_mut();
            stats.draw_calls += 1;
            stats.triangles += u64::from(indices.triangles);
        }
        MethodOutput {
            plan,
            importance,
            lod_ms,
        }
    }

    fn frame_measures(&mut self, gpu: &Gpu) -> Vec<(&'static str, f64)> {
        if !self.counted {
            return Vec::new();
        }
        self.counted = false;
        let slice = self.readback.slice(..);
        slice.map_async(wgpu::MapMode::Read, |_| {});
        // A measurement of the frame just drawn (evaluation only): it waits, bounded.
        if gpu
            .device
            .poll(wgpu::PollType::Wait {
                submission_index: None,
                timeout: Some(crate::render::gpu::GPU_TIMEOUT),
            })
            .is_err()
        {
            return Vec::new();
        }
        let counters = match slice.get_mapped_range() {
            Ok(data) => *bytemuck::from_bytes::<GridCounters>(&data),
            Err(_) => return Vec::new(),
        };
        self.readback.unmap();
        let pixels = self
            .error
            .as_ref()
            .map_or(1.0, |e| f64::from(e.texture.width() * e.texture.height()));
        vec![
            (
                "error_pixels_pct",
                100.0 * f64::from(counters.errors) / pixels,
            ),
            ("marked_pct", 100.0 * f64::from(counters.marked) / pixels),
            ("ray_cast_pct", 100.0 * f64::from(counters.rays) / pixels),
            ("ray_hit_pct", 100.0 * f64::from(counters.hits) / pixels),
        ]
    }

    fn tile_evicted(&mut self, id: TileId) {
        self.atlas.release(id, &self.manifest);
    }

    /// A slot per resident tile, whether or not it holds one yet: tiles get their slots at
    /// the next frame, after the scene has counted them.
    fn tile_bytes(&self, _id: TileId) -> u64 {
        self.atlas.tile_charge()
    }

    fn expected_tile_bytes(&self, _tile: &TileRecord) -> u64 {
        self.atlas.tile_charge()
    }

    /// The grid, its buffers, the error buffer and what the atlas holds past its tiles'
    /// slots (the table, slots no tile uses).
    fn shared_bytes(&self) -> MethodBytes {
        let gpu = self.own_gpu_bytes()
            + self
                .atlas
                .unused_bytes()
                .saturating_sub(self.atlas_table_cpu_bytes());
        MethodBytes {
            cpu: self.atlas_table_cpu_bytes(),
            gpu,
        }
    }

    /// The buffers it makes whatever it draws (the grid's indices for `--grid`, its
    /// uniform, counters and their read-back, the error buffer of a frame of `viewport`
    /// pixels) and what the atlas holds past its tiles' charges at most.
    fn reserved_bytes(&self, viewport: [u32; 2]) -> u64 {
        let [columns, rows] = self.settings.size;
        let indices = 6 * u64::from(columns.saturating_sub(1)) * u64::from(rows.saturating_sub(1));
        let index_bytes = if columns * rows <= 1 << 16 { 2 } else { 4 };
        let error = if self.error_bounded() {
            2 * u64::from(viewport[0].max(1)) * u64::from(viewport[1].max(1))
        } else {
            0
        };
        (indices * index_bytes).next_multiple_of(4).max(4)
            + self.uniform.size()
            + self.counters.size()
            + self.readback.size()
            + error
            + self.atlas.reserved_bytes()
    }

    fn gpu_bytes(&self) -> u64 {
        self.own_gpu_bytes() + self.atlas.bytes()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_grid_has_two_triangles_a_cell_over_every_vertex() {
        let size = [5, 3];
        let indices = ProjectedGrid::grid_indices(size);
        let settings = GridSettings {
            size,
            ..GridSettings::default()
        };
        assert_eq!(indices.len() as u64, 3 * settings.triangles());
        assert_eq!(settings.triangles(), 16);
        let mut used = [false; 15];
        for &i in &indices {
            used[i as usize] = true;
        }
        assert!(used.iter().all(|&u| u), "every vertex is used");
    }
}
