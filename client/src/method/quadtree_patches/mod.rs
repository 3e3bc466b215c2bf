//! Quadtree progressive patches (Yusov and Turlapov 2007) as a method.
//!
//! The meta quadtree is the tile pyramid: a patch per tile, its triangulation an
//! unbalanced quadtree with a guaranteed world-space error ([`terrain_shared::quadtree`],
//! built by the server's `--patches`). The method asks for the patch index once (each
//! patch's hash, error and height bounds), then for the body of each resident tile whose
//! parent patch it holds: a body is what the parent does not give (split bits and new
//! heights), so patches arrive coarse to fine. Triangulations are built on rayon's pool,
//! off the render thread, and cached on the GPU until their tile leaves.
//!
//! **Traversal** (section 3.7). From the root, a patch is drawn when its error projected
//! to the screen is within `--max-error-px`, or when any of its children is not ready; else
//! its children are visited. The projection is the project's bound
//! ([`crate::lod::needed::ErrorProjection`]: the nearest view depth of the patch's box and
//! its angle off the axis), not the paper's `S / (2 tan(γ/2)) · ε / d` with `d` the distance
//! to the box: that one is exact on the view axis only, and undercounts a vertical error
//! near the screen's corners by up to `sec²` of the angle off the axis.
//!
//! **Geomorphing** (section 3.6). With morphing on, a patch's children are drawn from when
//! its projected error passes half the threshold, and each child's morph parameter falls
//! from 1 (its parent's triangulation: every vertex on its parent's active vertex above it,
//! ring vertices on the parent's surface at the side) to 0 as that error reaches the
//! threshold, so no patch is drawn past the threshold in the middle of a morph. Textures
//! blend from the parent tile's to the patch's own with the same parameter, and towards
//! each neighbour's at the shared side. Without morphing a patch splits at the threshold.
//!
//! **Cracks**: vertical flanges under every side, as deep as the patch's error plus its
//! neighbours' across that side (plus its parent's while it morphs).

mod mesh;

use self::mesh::{Indices, Mesh, build_mesh, data_bytes};
pub use self::mesh::{estimated_bytes, expected_bytes, most_bytes};
use super::{Build, DataWant, LodMethod, MethodBytes, MethodConfig, MethodInput, MethodOutput};
use crate::lod::plan::{self, LodSettings};
use crate::lod::strips::MaskSet;
use crate::render::{Frame, Gpu};
use bytes::Bytes;
use std::collections::{HashMap, HashSet};
use std::sync::{Arc, mpsc};
use terrain_shaders::{PATCHES, PatchUniform, patch_entry};
use terrain_shared::quadtree::{self, PatchData, PatchEntry, Tree};
use terrain_shared::{Manifest, TileId, TileRecord, routes};
use web_time::Instant;

/// The key of the patch index among the method's data (asked for with the root tile).
const INDEX_KEY: u32 = 1;
/// The key of a patch body.
const BODY_KEY: u32 = 0;
/// From which share of the threshold a patch's children are drawn, morphing.
pub const MORPH_START: f64 = 0.5;
/// Bytes of one vertex: own position and height, its target's, the flange flag, its
/// normal (packed).
const VERTEX_BYTES: u64 = 8 * 4;
/// Uniform slots are this far apart (wgpu's minimum dynamic offset alignment).
const UNIFORM_STRIDE: u64 = 256;

/// A patch decoded and meshed.
#[derive(Debug)]
struct Ready {
    data: Arc<PatchData>,
    vertices: wgpu::Buffer,
    indices: wgpu::Buffer,
    index_count: u32,
    format: wgpu::IndexFormat,
    triangles: u32,
    cpu_bytes: u64,
}

impl Ready {
    fn gpu_bytes(&self) -> u64 {
        self.vertices.size() + self.indices.size()
    }
}

/// A body to decode and mesh.
type Job = Box<dyn FnOnce() -> Made + Send>;

/// What a worker made of a body.
struct Made {
    id: TileId,
    result: Result<Mesh, String>,
}

/// Where bodies are decoded and meshed: a worker thread, or, where a program has no threads
/// (the page), the render thread, as each is asked for.
enum Worker {
    Thread(mpsc::Sender<Job>),
    Inline(mpsc::Sender<Made>),
}

impl Worker {
    /// Runs `job`; whether its result will be collected.
    fn run(&self, job: Job) -> bool {
        match self {
            Worker::Thread(jobs) => jobs.send(job).is_ok(),
            Worker::Inline(made) => made.send(job()).is_ok(),
        }
    }
}

/// The quadtree patches method. See the module documentation.
pub struct QuadtreePatches {
    lod: LodSettings,
    manifest: Arc<Manifest>,
    tree: Tree,
    masks: MaskSet,
    index: Option<Vec<PatchEntry>>,
    /// What the pager is told to expect of a patch until the index is in: the most one
    /// can hold ([`most_bytes`]).
    unknown: u64,
    /// Per tile hash, its patch's entry and level (what the pager expects before the tile
    /// is in).
    by_hash: HashMap<String, (PatchEntry, u32)>,
    resident: HashSet<TileId>,
    asked: HashSet<(TileId, u32)>,
    bodies: HashMap<TileId, Bytes>,
    building: HashSet<TileId>,
    ready: HashMap<TileId, Ready>,
    /// What decodes and meshes bodies, and what it made.
    worker: Worker,
    receiver: mpsc::Receiver<Made>,
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    sampler: wgpu::Sampler,
    uniforms: Option<wgpu::Buffer>,
    /// A body that would not decode, said once.
    refused: HashSet<TileId>,
    /// Whether bytes held or expected changed since the scene last asked.
    changed: bool,
}

impl std::fmt::Debug for QuadtreePatches {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("QuadtreePatches")
            .field("ready", &self.ready.len())
            .field("resident", &self.resident.len())
            .finish_non_exhaustive()
    }
}

impl QuadtreePatches {
    pub fn new(config: &MethodConfig, with: &Build<'_>) -> QuadtreePatches {
        let device = &with.gpu.device;
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("terrain/patch"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: true,
                        min_binding_size: wgpu::BufferSize::new(size_of::<PatchUniform>() as u64),
                    },
                    count: None,
                },
                texture_entry(1),
                texture_entry(2),
                wgpu::BindGroupLayoutEntry {
                    binding: 3,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                    count: None,
                },
            ],
        });
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("patches"),
            source: wgpu::ShaderSource::Wgsl(PATCHES.into()),
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("patches"),
            bind_group_layouts: &[Some(with.frame_layout), Some(&layout)],
            immediate_size: 0,
        });
        let attributes = [
            wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Float32x3,
                offset: 0,
                shader_location: 0,
            },
            wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Float32x3,
                offset: 12,
                shader_location: 1,
            },
            wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Float32,
                offset: 24,
                shader_location: 2,
            },
            wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Snorm8x4,
                offset: 28,
                shader_location: 3,
            },
        ];
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("patches"),
            layout: Some(&pipeline_layout),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some(patch_entry::VERTEX),
                compilation_options: Default::default(),
                buffers: &[Some(wgpu::VertexBufferLayout {
                    array_stride: VERTEX_BYTES,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &attributes,
                })],
            },
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some(patch_entry::FRAGMENT),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format: with.format,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::TriangleList,
                cull_mode: None,
                ..Default::default()
            },
            depth_stencil: Some(wgpu::DepthStencilState {
                format: crate::render::frame::DEPTH_FORMAT,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Greater),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            multiview_mask: None,
            cache: None,
        });
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("terrain/patch"),
            address_mode_u: wgpu::AddressMode::ClampToEdge,
            address_mode_v: wgpu::AddressMode::ClampToEdge,
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            mipmap_filter: wgpu::MipmapFilterMode::Linear,
            ..Default::default()
        });
        if let Err(message) = super::check_database(config.kind, with.manifest) {
            tracing::error!("{message}");
        }
        let (jobs, work) = mpsc::channel::<Job>();
        let (sender, receiver) = mpsc::channel();
        let inline = sender.clone();
        // One worker: meshes are built off the render thread, in the order asked.
        let worker = match std::thread::Builder::new()
            .name("quadtree patches".into())
            .spawn(move || {
                while let Ok(job) = work.recv() {
                    if sender.send(job()).is_err() {
                        break;
                    }
                }
            }) {
            Ok(_) => Worker::Thread(jobs),
            Err(_) => Worker::Inline(inline),
        };
        let tree = Tree::for_tile_size(with.manifest.tile_size);
        QuadtreePatches {
            lod: config.lod,
            manifest: Arc::new(with.manifest.clone()),
            tree,
            unknown: most_bytes(tree),
            masks: MaskSet::new(with.manifest.tile_size),
            index: None,
            by_hash: HashMap::new(),
            resident: HashSet::new(),
            asked: HashSet::new(),
            bodies: HashMap::new(),
            building: HashSet::new(),
            ready: HashMap::new(),
            worker,
            receiver,
            pipeline,
            layout,
            sampler,
            uniforms: None,
            refused: HashSet::new(),
            changed: false,
        }
    }

    fn root(&self) -> TileId {
        TileId::at(self.manifest.levels.len() as u32 - 1, 0, 0)
    }

    fn entry(&self, id: TileId) -> Option<&PatchEntry> {
        self.index.as_ref()?.get(self.manifest.index(id)?)
    }

    fn parent_of(&self, id: TileId) -> Option<TileId> {
        (id != self.root()).then(|| TileId::at(id.level + 1, id.x / 2, id.y / 2))
    }

    /// The children of `id` that exist in the pyramid.
    fn children(&self, id: TileId) -> Vec<TileId> {
        if id.level == 0 {
            return Vec::new();
        }
        let grid = &self.manifest.levels[id.level as usize - 1].grid;
        (0..4)
            .map(|q| TileId::at(id.level - 1, 2 * id.x + q % 2, 2 * id.y + q / 2))
            .filter(|c| c.x < grid.columns && c.y < grid.rows)
            .collect()
    }

    fn far(&self, id: TileId) -> [f32; 2] {
        let grid = &self.manifest.levels[id.level as usize].grid;
        quadtree::far_edge(
            self.tree,
            id.level,
            id.x,
            id.y,
            [self.manifest.raster.width, self.manifest.raster.height],
            [grid.columns, grid.rows],
        )
    }

    /// Starts building every body whose parent is ready.
    fn start_builds(&mut self) {
        let startable: Vec<TileId> = self
            .bodies
            .keys()
            .copied()
            .filter(|id| !self.building.contains(id) && !self.ready.contains_key(id))
            .filter(|&id| {
                self.parent_of(id)
                    .is_none_or(|p| self.ready.contains_key(&p))
            })
            .collect();
        for id in startable {
            let Some(body) = self.bodies.get(&id).cloned() else {
                continue;
            };
            let parent = self
                .parent_of(id)
                .and_then(|p| self.ready.get(&p).map(|r| (p, r.data.clone(), self.far(p))));
            let (tree, far, spacing) = (self.tree, self.far(id), self.manifest.spacing_m);
            let heights = (
                self.manifest.heights.offset_m,
                self.manifest.heights.quantum_m / f64::from(quadtree::SUBCODES),
            );
            self.building.insert(id);
            let job: Job = Box::new(move || Made {
                id,
                result: build_mesh(tree, id, far, parent, heights, spacing, &body),
            });
            if !self.worker.run(job) {
                self.building.remove(&id);
            }
        }
    }

    /// Takes what the workers finished.
    fn collect(&mut self, gpu: &Gpu) {
        while let Ok(made) = self.receiver.try_recv() {
            self.building.remove(&made.id);
            if !self.resident.contains(&made.id) {
                continue;
            }
            match made.result {
                Ok((data, vertices, indices, triangles)) => {
                    use wgpu::util::DeviceExt;
                    let v = gpu
                        .device
                        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                            label: Some("terrain/patch vertices"),
                            contents: bytemuck::cast_slice(&vertices),
                            usage: wgpu::BufferUsages::VERTEX,
                        });
                    let (contents, index_count, format): (&[u8], u32, wgpu::IndexFormat) =
                        match &indices {
                            Indices::U16(i) => (
                                bytemuck::cast_slice(i),
                                i.len() as u32,
                                wgpu::IndexFormat::Uint16,
                            ),
                            Indices::U32(i) => (
                                bytemuck::cast_slice(i),
                                i.len() as u32,
                                wgpu::IndexFormat::Uint32,
                            ),
                        };
                    let i = gpu
                        .device
                        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                            label: Some("terrain/patch indices"),
                            contents,
                            usage: wgpu::BufferUsages::INDEX,
                        });
                    // A finest patch has no children to read against it: its heights go.
                    let data = if made.id.level == 0 {
                        Arc::new(PatchData {
                            cut: data.cut.clone(),
                            nodes: Default::default(),
                            border: Default::default(),
                        })
                    } else {
                        data
                    };
                    let cpu_bytes = data_bytes(&data);
                    self.bodies.remove(&made.id);
                    self.changed = true;
                    self.ready.insert(
                        made.id,
                        Ready {
                            data,
                            vertices: v,
                            indices: i,
                            index_count,
                            format,
                            triangles,
                            cpu_bytes,
                        },
                    );
                }
                Err(message) => {
                    if self.refused.insert(made.id) {
                        tracing::warn!(tile = %made.id, "quadtree patch refused: {message}");
                    }
                    self.bodies.remove(&made.id);
                }
            }
        }
    }
}

fn texture_entry(binding: u32) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::FRAGMENT,
        ty: wgpu::BindingType::Texture {
            sample_type: wgpu::TextureSampleType::Float { filterable: true },
            view_dimension: wgpu::TextureViewDimension::D2,
            multisampled: false,
        },
        count: None,
    }
}

/// A drawn patch and what its draw needs.
#[derive(Debug, Clone, Copy)]
struct Drawn {
    id: TileId,
    alpha: f64,
}

impl LodMethod for QuadtreePatches {
    fn name(&self) -> String {
        if self.lod.geomorph {
            "quadtree-patches".into()
        } else {
            "quadtree-patches/no-morph".into()
        }
    }

    fn configure(&mut self, config: &MethodConfig) {
        self.lod = config.lod;
    }

    fn tile_resident(&mut self, _gpu: &Gpu, id: TileId, _heights: &terrain_shared::Heights) {
        self.resident.insert(id);
    }

    fn tile_evicted(&mut self, id: TileId) {
        self.resident.remove(&id);
        self.asked.remove(&(id, BODY_KEY));
        self.asked.remove(&(id, INDEX_KEY));
        self.bodies.remove(&id);
        self.ready.remove(&id);
    }

    fn wants(&mut self) -> Vec<DataWant> {
        let cv = self.manifest.content_version.clone();
        let Some(info) = self.manifest.patches.clone() else {
            return Vec::new();
        };
        let root = self.root();
        let mut out = Vec::new();
        if self.index.is_none() {
            if self.resident.contains(&root) && self.asked.insert((root, INDEX_KEY)) {
                out.push(DataWant {
                    id: root,
                    key: INDEX_KEY,
                    path: routes::patch_index(&cv),
                    hash: Some(info.index.hash.clone()),
                    bytes: Some(info.index.bytes),
                });
            }
            return out;
        }
        let mut ids: Vec<TileId> = self.resident.iter().copied().collect();
        ids.sort_by_key(|id| std::cmp::Reverse(id.level));
        for id in ids {
            if self.ready.contains_key(&id) || self.bodies.contains_key(&id) {
                continue;
            }
            // Coarse to fine: a body is read against its parent's patch.
            let parent_ready = self.parent_of(id).is_none_or(|p| {
                self.ready.contains_key(&p)
                    || self.bodies.contains_key(&p)
                    || self.building.contains(&p)
            });
            if !parent_ready {
                continue;
            }
            let Some(entry) = self.entry(id) else {
                continue;
            };
            let (hash, bytes) = (entry.hash_hex(), u64::from(entry.bytes));
            if self.asked.insert((id, BODY_KEY)) {
                out.push(DataWant {
                    id,
                    key: BODY_KEY,
                    path: routes::patch(&cv, id),
                    hash: Some(hash),
                    bytes: Some(bytes),
                });
            }
        }
        out
    }

    fn bytes_changed(&mut self) -> bool {
        std::mem::take(&mut self.changed)
    }

    fn settled(&self) -> bool {
        if self.manifest.patches.is_none() {
            return true;
        }
        self.index.is_some()
            && self.building.is_empty()
            && self.resident.iter().all(|&id| {
                // A tile whose parent is not resident cannot be read (its body refines
                // its parent's): it waits for the pager, not for the method.
                self.ready.contains_key(&id)
                    || self.refused.contains(&id)
                    || self.entry(id).is_none()
                    || self
                        .parent_of(id)
                        .is_some_and(|p| !self.resident.contains(&p))
            })
    }

    fn data_arrived(&mut self, _gpu: &Gpu, id: TileId, key: u32, bytes: Bytes) {
        if key == INDEX_KEY {
            let count = self.manifest.tiles().count();
            match quadtree::decode_index(&bytes, count) {
                Ok(entries) => {
                    self.by_hash = self
                        .manifest
                        .tiles()
                        .zip(&entries)
                        .map(|((id, t), e)| (t.hash.clone(), (*e, id.level)))
                        .collect();
                    self.index = Some(entries);
                    self.changed = true;
                }
                Err(e) => tracing::warn!("quadtree patch index refused: {e}"),
            }
            return;
        }
        if self.resident.contains(&id) {
            self.bodies.insert(id, bytes);
            self.start_builds();
        }
    }

    fn draw(&mut self, input: &MethodInput<'_>, frame: &mut Frame<'_>) -> MethodOutput {
        let started = Instant::now();
        let gpu = frame.gpu().clone();
        self.collect(&gpu);
        self.start_builds();
        let viewport = frame.viewport();
        let ranked = plan::rank_visible(
            frame.camera(),
            viewport,
            input.layout,
            input.tiles,
            &self.lod,
        );
        let camera = *frame.camera();
        let projection = plan::error_projection(&camera, viewport);
        let aspect = f64::from(viewport[0]) / f64::from(viewport[1].max(1));
        let frustum = camera.frustum(aspect);
        let eye = glam::DVec3::from(camera.position);
        let threshold = self.lod.max_error_px;
        let start = if self.lod.geomorph { MORPH_START } else { 1.0 };
        let layout = *input.layout;
        let tree = self.tree;
        let spacing = self.manifest.spacing_m;

        // The box of a patch, metres, and its projected error, pixels.
        let span = |id: TileId| f64::from(1u32 << (tree.n + id.level));
        let bounds = |id: TileId, e: &PatchEntry| {
            let x0 = (f64::from(id.x) * span(id) - 0.5) * spacing[0];
            let y0 = (f64::from(id.y) * span(id) - 0.5) * spacing[1];
            let lo = [x0, y0, f64::from(e.min_m) - 2.0 * f64::from(e.error_m)];
            let hi = [
                x0 + (span(id) + 1.0) * spacing[0],
                y0 + (span(id) + 1.0) * spacing[1],
                f64::from(e.max_m),
            ];
            (lo, hi)
        };
        let mut drawn: Vec<Drawn> = Vec::new();
        let root = self.root();
        if let (Some(_), true) = (self.entry(root), self.ready.contains_key(&root)) {
            // (patch, its parent's projected error or None)
            let mut stack = vec![(root, None::<f64>)];
            while let Some((id, parent_error)) = stack.pop() {
                let Some(e) = self.entry(id).copied() else {
                    continue;
                };
                let (lo, hi) = bounds(id, &e);
                let lo_r = crate::render::Camera::to_render(glam::DVec3::from(lo) - eye);
                let hi_r = crate::render::Camera::to_render(glam::DVec3::from(hi) - eye);
                if !frustum.intersects_box(lo_r.min(hi_r), hi_r.max(lo_r)) {
                    continue;
                }
                let error_px =
                    f64::from(e.error_m) * projection.pixels_per_metre(lo, hi, threshold);
                let alpha = match parent_error {
                    Some(pe) if self.lod.geomorph => {
                        ((threshold - pe) / ((1.0 - MORPH_START) * threshold)).clamp(0.0, 1.0)
                    }
                    _ => 0.0,
                };
                let children = self.children(id);
                let refine = error_px > start * threshold
                    && !children.is_empty()
                    && children.iter().all(|c| self.ready.contains_key(c));
                if refine {
                    for c in children {
                        stack.push((c, Some(error_px)));
                    }
                } else {
                    drawn.push(Drawn { id, alpha });
                }
            }
        }
        // Importance ranks the textures: the drawn patches' tiles by nearness, and the
        // parents of those morphing, whose textures they blend in, by their morph.
        let mut importance: Vec<(TileId, f64)> = Vec::new();
        for d in &drawn {
            let Some(e) = self.entry(d.id) else { continue };
            let (lo, hi) = bounds(d.id, e);
            let size = (hi[0] - lo[0]).max(hi[1] - lo[1]);
            let distance = crate::lod::needed::distance_to_box(camera.position, lo, hi);
            let w = 1.0 / (1.0 + distance / size).powi(2);
            importance.push((d.id, w));
            if let (true, Some(p)) = (d.alpha > 0.0, self.parent_of(d.id)) {
                importance.push((p, w * d.alpha));
            }
        }
        let total: f64 = importance.iter().map(|(_, w)| w).sum();
        if total > 0.0 {
            importance.iter_mut().for_each(|(_, w)| *w /= total);
        }
        let lod_ms = started.elapsed().as_secs_f64() * 1e3;

        // Uniforms: one slot per drawn patch.
        let needed = (drawn.len().max(1) as u64) * UNIFORM_STRIDE;
        if self.uniforms.as_ref().is_none_or(|b| b.size() < needed) {
            self.uniforms = Some(gpu.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("terrain/patch uniforms"),
                size: needed.next_power_of_two(),
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }));
        }
        let uniforms = self.uniforms.as_ref().expect("made above");
        let levels: HashMap<TileId, (f64, f32)> = drawn
            .iter()
            .map(|d| (d.id, (d.alpha, self.entry(d.id).map_or(0.0, |e| e.error_m))))
            .collect();
        let anchor = frame.anchor();
        let extent = tree.extent() as f32;
        let mut staged = vec![0u8; needed as usize];
        for (k, d) in drawn.iter().enumerate() {
            let id = d.id;
            let unit = span(id) / f64::from(tree.extent());
            let own_error = levels[&id].1;
            // Each side's neighbour in the cut: (level difference, morph, error).
            let mut blend = [0.0f32; 4];
            let mut depth = own_error;
            for (s, (dx, dy)) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)]
                .into_iter()
                .enumerate()
            {
                let (nx, ny) = (i64::from(id.x) + dx, i64::from(id.y) + dy);
                let mut found = None;
                if nx >= 0 && ny >= 0 {
                    let mut n = TileId::at(id.level, nx as u32, ny as u32);
                    let mut d_level = 0;
                    loop {
                        if let Some(&(a, err)) = levels.get(&n) {
                            found = Some((d_level, a, err));
                            break;
                        }
                        if n.level + 1 >= self.manifest.levels.len() as u32 {
                            break;
                        }
                        n = TileId::at(n.level + 1, n.x / 2, n.y / 2);
                        d_level += 1;
                    }
                }
                let (value, neighbour_error) = match found {
                    Some((dl, a, err)) => (((a + f64::from(dl)).max(d.alpha)).min(1.0), err),
                    // Finer neighbours (or none): this side keeps its own morph; a finer
                    // neighbour's flange covers the two errors.
                    None => (d.alpha, own_error),
                };
                blend[s] = value as f32;
                depth = depth.max(own_error + neighbour_error);
            }
            if d.alpha > 0.0
                && let Some(p) = self.parent_of(id).and_then(|p| self.entry(p))
            {
                depth += p.error_m;
            }
            let origin = [
                f64::from(id.x) * span(id) - 0.5 - anchor[0],
                f64::from(id.y) * span(id) - 0.5 - anchor[1],
            ];
            let own_scale = (unit / span(id)) as f32;
            let parent_scale = own_scale / 2.0;
            let (qx, qy) = (f64::from(id.x % 2), f64::from(id.y % 2));
            let uniform = PatchUniform {
                origin: [
                    origin[0] as f32,
                    origin[1] as f32,
                    unit as f32,
                    depth + 1e-3,
                ],
                spacing: [spacing[0] as f32, spacing[1] as f32, d.alpha as f32, 0.0],
                uv: [
                    own_scale,
                    (-0.5 / span(id)) as f32,
                    (-0.5 / span(id)) as f32,
                    parent_scale,
                ],
                parent_uv: [
                    ((qx * span(id) - 0.5) / (2.0 * span(id))) as f32,
                    ((qy * span(id) - 0.5) / (2.0 * span(id))) as f32,
                    extent,
                    0.0,
                ],
                blend,
            };
            let at = k * UNIFORM_STRIDE as usize;
            staged[at..at + size_of::<PatchUniform>()]
                .copy_from_slice(bytemuck::bytes_of(&uniform));
        }
        gpu.queue.write_buffer(uniforms, 0, &staged);

        // Bind groups: the patch's tile texture and its parent's.
        let mut groups = Vec::with_capacity(drawn.len());
        {
            let tiles = frame.tiles();
            for d in &drawn {
                let own = tiles
                    .texture_of(d.id)
                    .map(|(t, _)| t.create_view(&Default::default()));
                let parent = self
                    .parent_of(d.id)
                    .and_then(|p| tiles.texture_of(p))
                    .map(|(t, _)| t.create_view(&Default::default()));
                let Some(own) = own else {
                    groups.push(None);
                    continue;
                };
                let parent = parent.unwrap_or_else(|| own.clone());
                groups.push(Some(gpu.device.create_bind_group(
                    &wgpu::BindGroupDescriptor {
                        label: Some("terrain/patch"),
                        layout: &self.layout,
                        entries: &[
                            wgpu::BindGroupEntry {
                                binding: 0,
                                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                    buffer: uniforms,
                                    offset: 0,
                                    size: wgpu::BufferSize::new(size_of::<PatchUniform>() as u64),
                                }),
                            },
                            wgpu::BindGroupEntry {
                                binding: 1,
                                resource: wgpu::BindingResource::TextureView(&own),
                            },
                            wgpu::BindGroupEntry {
                                binding: 2,
                                resource: wgpu::BindingResource::TextureView(&parent),
                            },
                            wgpu::BindGroupEntry {
                                binding: 3,
                                resource: wgpu::BindingResource::Sampler(&self.sampler),
                            },
                        ],
                    },
                )));
            }
        }
        let mut triangles = 0u64;
        {
            let mut pass = frame.last_pass();
            {
                let raw = pass.raw();
                raw.set_pipeline(&self.pipeline);
            }
            for (k, (d, group)) in drawn.iter().zip(&groups).enumerate() {
                let (Some(group), Some(ready)) = (group, self.ready.get(&d.id)) else {
                    continue;
                };
                let raw = pass.raw();
                raw.set_bind_group(1, group, &[(k as u64 * UNIFORM_STRIDE) as u32]);
                raw.set_vertex_buffer(0, ready.vertices.slice(..));
                raw.set_index_buffer(ready.indices.slice(..), ready.format);
                raw.draw_indexed(0..ready.index_count, 0, 0..1);
                let stats = pass.stats_mut();
                stats.draw_calls += 1;
                stats.triangles += u64::from(ready.triangles);
                triangles += u64::from(ready.triangles);
            }
        }
        let _ = layout;
        let plan = plan::FramePlan {
            budget: input.budget,
            triangles,
            triangles_needed: ranked
                .needed_levels
                .iter()
                .map(|&l| u64::from(self.masks.triangle_count(l)))
                .sum(),
            needed_levels: ranked.needed_levels.clone(),
            ..plan::FramePlan::default()
        };
        MethodOutput {
            plan,
            importance,
            lod_ms,
        }
    }

    fn tile_bytes(&self, id: TileId) -> u64 {
        let held = self
            .ready
            .get(&id)
            .map_or(0, |r| r.cpu_bytes + r.gpu_bytes());
        let body = self.bodies.get(&id).map_or(0, |b| b.len() as u64);
        held + body
    }

    fn expected_tile_bytes(&self, tile: &TileRecord) -> u64 {
        if self.index.is_none() {
            return self.unknown;
        }
        self.by_hash
            .get(&tile.hash)
            .map_or(0, |(e, level)| expected_bytes(e, self.tree, *level))
    }

    fn shared_bytes(&self) -> MethodBytes {
        let pending: u64 = self.bodies.values().map(|b| b.len() as u64).sum::<u64>()
            - self
                .bodies
                .keys()
                .filter(|id| self.resident.contains(id))
                .map(|id| self.bodies[id].len() as u64)
                .sum::<u64>();
        let index = self.index.as_ref().map_or(0, |i| (i.len() * 64) as u64);
        MethodBytes {
            cpu: index + pending,
            gpu: self.uniforms.as_ref().map_or(0, |b| b.size()),
        }
    }

    fn gpu_bytes(&self) -> u64 {
        self.shared_bytes().gpu + self.ready.values().map(Ready::gpu_bytes).sum::<u64>()
    }

    /// The patch index (whether or not it has arrived: the manifest says how many entries
    /// it has) and the uniforms of the last frame's patches.
    fn reserved_bytes(&self, _viewport: [u32; 2]) -> u64 {
        let shared = self.shared_bytes();
        let index = (self.manifest.tile_count() * 64) as u64;
        shared.total()
            + index.saturating_sub(self.index.as_ref().map_or(0, |i| (i.len() * 64) as u64))
    }
}

#[cfg(test)]
mod tests {
    use super::mesh::{placed, surface_at};
    use super::*;
    use terrain_shared::quadtree::Cut;
    use terrain_shared::quadtree::{Parent, Vertex};

    #[test]
    fn a_patch_at_morph_one_lies_on_its_parent() {
        // Vertices of a child at alpha 1 land on the parent's surface: nodes on the
        // parent's active vertex above them, ring vertices on its surface.
        let tree = Tree { n: 3 };
        let height = |v: Vertex| match v {
            Vertex::Node { l, i, j } => 8 * (i32::from(l) * 3 + i32::from(i) - i32::from(j)),
            Vertex::Side { l, k, .. } => 8 * (i32::from(l) + i32::from(k)),
            Vertex::Corner { l, .. } => 8 * i32::from(l),
        };
        let mut parent_cut = Cut::full(tree);
        parent_cut.set_split(2, 0, 0, false);
        let parent_body = quadtree::encode_patch(&parent_cut, None, height, false, 3);
        let parent =
            quadtree::decode_patch(tree, None, false, &parent_body).expect("the parent decodes");
        let link = Parent {
            cut: &parent.cut,
            heights: &parent.nodes,
            quarter: (0, 0),
        };
        let body = quadtree::encode_patch(&Cut::full(tree), Some(&link), height, false, 3);
        let extent = tree.extent() as f32;
        let (_, vertices, _, _) = build_mesh(
            tree,
            TileId::at(0, 0, 0),
            [extent, extent],
            Some((
                TileId::at(1, 0, 0),
                Arc::new(parent.clone()),
                [extent, extent],
            )),
            (0.0, 1.0),
            [1.0, 1.0],
            &body,
        )
        .expect("meshes");
        let surface = placed(tree, [extent, extent], &parent, |c| c as f32);
        for v in vertices.chunks_exact(8) {
            let v: Vec<f32> = v.iter().map(|w| f32::from_bits(*w)).collect();
            let target = [(v[3]) / 2.0, (v[4]) / 2.0];
            let on = surface_at(&surface, target).expect("on the parent");
            assert!(
                (on - v[5]).abs() < 1e-3,
                "target {target:?} at {} off the parent's {on}",
                v[5]
            );
        }
    }

    #[test]
    fn the_index_tells_what_a_patch_will_hold() {
        // Meshes of cuts from full to coarse, at the finest level (heights dropped once
        // meshed) and above: the GPU bytes are what the counts say, and everything held
        // stays within the expectation.
        let tree = Tree { n: 4 };
        let height = |v: Vertex| match v {
            Vertex::Node { l, i, j } => 8 * (i32::from(l) * 5 + i32::from(i) * i32::from(j)),
            Vertex::Side { l, k, .. } => 8 * (i32::from(l) + i32::from(k)),
            Vertex::Corner { l, .. } => 8 * i32::from(l),
        };
        let mut cuts = vec![Cut::full(tree)];
        let mut coarse = Cut::full(tree);
        coarse.set_split(3, 1, 2, false);
        coarse.set_split(2, 0, 0, false);
        cuts.push(coarse);
        let extent = tree.extent() as f32;
        for cut in &cuts {
            for level in [0, 1] {
                let body = quadtree::encode_patch(cut, None, height, level == 0, 3);
                let triangles = quadtree::triangulate(cut);
                let entry = PatchEntry {
                    hash: [0; 16],
                    bytes: body.len() as u32,
                    error_m: 0.0,
                    min_m: 0.0,
                    max_m: 0.0,
                    mesh: quadtree::MeshCounts::of(cut, &triangles),
                };
                let (data, vertices, indices, drawn) = build_mesh(
                    tree,
                    TileId::at(level, 0, 0),
                    [extent, extent],
                    None,
                    (0.0, 1.0),
                    [1.0, 1.0],
                    &body,
                )
                .expect("meshes");
                let index_bytes = match &indices {
                    Indices::U16(i) => i.len() * 2,
                    Indices::U32(i) => i.len() * 4,
                } as u64;
                let gpu = vertices.len() as u64 * 4 + index_bytes;
                let m = entry.mesh;
                assert_eq!(
                    drawn,
                    m.triangles + 2 * m.ring,
                    "surface and flange triangles"
                );
                // A finest patch keeps its cut alone once meshed.
                let cpu = if level == 0 {
                    (tree.nodes() / 8 + 64) as u64
                } else {
                    data_bytes(&data)
                };
                let expected = expected_bytes(&entry, tree, level);
                let mut at_most_cpu = (tree.nodes() / 8 + 64) as u64;
                if level > 0 {
                    at_most_cpu += u64::from(m.vertices) * 32 + u64::from(m.ring) * 24;
                }
                assert_eq!(
                    expected - u64::from(entry.bytes) - at_most_cpu,
                    gpu,
                    "level {level}: the GPU bytes are what the counts say"
                );
                assert!(
                    gpu + cpu <= expected && u64::from(entry.bytes) <= expected,
                    "level {level}: {gpu} + {cpu} held of {expected} expected"
                );
            }
        }
    }
}
