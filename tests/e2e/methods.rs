//! The method seam carries the shapes of methods still to come, and every byte is counted.
//!
//! Two methods made here (not shipped) stand for them, against a real server streaming
//! jacksboro and a real adapter:
//! - [`OwnMesh`], a projected grid's shape: its own GPU copy of the terrain (one vertex
//!   buffer of every resident tile's coarse grid) drawn as one mesh with a pipeline of its
//!   own, no per-tile draws;
//! - [`OwnData`], progressive patches' shape: data of its own per tile (here the tile's
//!   tile blob again, hash-checked), asked of the scene and fetched by its fetcher.
//!
//! Both rank tiles by importance, so the scene refines their textures, and both hold bytes
//! the scene's resident figure includes. Then a flight with GeoMipMaps and MapBlocks that
//! coarsens and refines: the allocations the GPU allocator reports for the terrain match
//! the scene's ledger and, with the CPU bytes, never pass the memory limit.

use bytes::Bytes;
use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use terrain_client::eval::session::whole_database_bytes;
use terrain_client::lod::plan::{self, Draw, LodSettings};
use terrain_client::lod::strips::MaskSet;
use terrain_client::method::{
    Build, DataWant, LodMethod, MethodBytes, MethodConfig, MethodInput, MethodKind, MethodOutput,
};
use terrain_client::render::offscreen::OFFSCREEN_FORMAT;
use terrain_client::render::tiles::TERRAIN_LABEL;
use terrain_client::render::{Camera, Frame, Gpu, IndexSet, Offscreen, TileExtras};
use terrain_client::requests::FetcherConfig;
use terrain_client::scene::{RenderConfig, Scene};
use terrain_shared::{Heights, TileId, TileRecord, routes};
use terrain_tests::data::build_jacksboro;
use terrain_tests::golden;
use terrain_tests::server::TestServer;

const W: u32 = 320;
const H: u32 = 240;
/// Samples of the coarse grid [`OwnMesh`] keeps per tile side.
const GRID: u32 = 9;
/// The colour [`OwnMesh`] draws with.
const MAGENTA: [u8; 4] = [255, 0, 255, 255];

const MESH_SHADER: &str = r#"
struct Uniforms {
    view_proj: mat4x4<f32>,
    // Camera position in the mesh's space (east, height, south).
    camera: vec4<f32>,
    colour: vec4<f32>,
};
@group(0) @binding(0) var<uniform> u: Uniforms;

@vertex
fn vs(@location(0) p: vec3<f32>) -> @builtin(position) vec4<f32> {
    return u.view_proj * vec4<f32>(p - u.camera.xyz, 1.0);
}

@fragment
fn fs() -> @location(0) vec4<f32> {
    return u.colour;
}
"#;

/// Ranks the resident tiles as every method does: what refines their textures.
fn importance(input: &MethodInput<'_>, frame: &Frame<'_>) -> Vec<(TileId, f64)> {
    let ranked = plan::rank_visible(
        frame.camera(),
        frame.viewport(),
        input.layout,
        input.tiles,
        &LodSettings::default(),
    );
    ranked
        .visible
        .iter()
        .zip(&ranked.importances)
        .map(|(&i, &w)| (input.tiles[i].id, w))
        .collect()
}

/// A projected grid's shape: its own copy of the terrain on the GPU, one mesh, its own
/// pipeline.
#[derive(Debug)]
struct OwnMesh {
    pipeline: wgpu::RenderPipeline,
    uniforms: wgpu::Buffer,
    group: wgpu::BindGroup,
    spacing_m: [f64; 2],
    tile_size: u32,
    /// Per resident tile, its coarse grid (east, height, south), metres.
    grids: HashMap<TileId, Vec<[f32; 3]>>,
    /// The mesh of every grid, rebuilt when the resident tiles change.
    mesh: Option<(wgpu::Buffer, wgpu::Buffer, u32)>,
    dirty: bool,
    draws: u32,
}

impl OwnMesh {
    fn new(with: &Build<'_>) -> OwnMesh {
        let device = &with.gpu.device;
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("own mesh"),
            source: wgpu::ShaderSource::Wgsl(MESH_SHADER.into()),
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("own mesh"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            }],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("own mesh"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("own mesh"),
            layout: Some(&pipeline_layout),
            vertex: wgpu::VertexState {
                module: &shader,
                entry_point: Some("vs"),
                compilation_options: Default::default(),
                buffers: &[Some(wgpu::VertexBufferLayout {
                    array_stride: 12,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &wgpu::vertex_attr_array![0 => Float32x3],
                })],
            },
            primitive: wgpu::PrimitiveState::default(),
            depth_stencil: Some(wgpu::DepthStencilState {
                format: terrain_client::render::frame::DEPTH_FORMAT,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Greater),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &shader,
                entry_point: Some("fs"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format: with.format,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        let uniforms = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("terrain/own mesh uniforms"),
            size: 96,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("own mesh"),
            layout: &layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: uniforms.as_entire_binding(),
            }],
        });
        OwnMesh {
            pipeline,
            uniforms,
            group,
            spacing_m: with.manifest.spacing_m,
            tile_size: with.manifest.tile_size,
            grids: HashMap::new(),
            mesh: None,
            dirty: true,
            draws: 0,
        }
    }

    fn grid_bytes() -> u64 {
        // Vertices, and two triangles a cell.
        u64::from(GRID * GRID) * 12 + u64::from((GRID - 1) * (GRID - 1)) * 6 * 4
    }

    fn rebuild(&mut self, gpu: &Gpu) {
        let mut vertices: Vec<[f32; 3]> = Vec::new();
        let mut indices: Vec<u32> = Vec::new();
        for grid in self.grids.values() {
            let base = vertices.len() as u32;
            vertices.extend_from_slice(grid);
            for r in 0..GRID - 1 {
                for c in 0..GRID - 1 {
                    let i = base + r * GRID + c;
                    indices.extend_from_slice(&[i, i + GRID, i + 1, i + 1, i + GRID, i + GRID + 1]);
                }
            }
        }
        self.mesh = (!indices.is_empty()).then(|| {
            let buffer = |label, usage, bytes: &[u8]| {
                let b = gpu.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size: bytes.len() as u64,
                    usage: usage | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                });
                gpu.queue.write_buffer(&b, 0, bytes);
                b
            };
            (
                buffer(
                    "terrain/own mesh vertices",
                    wgpu::BufferUsages::VERTEX,
                    bytemuck::cast_slice(&vertices),
                ),
                buffer(
                    "terrain/own mesh indices",
                    wgpu::BufferUsages::INDEX,
                    bytemuck::cast_slice(&indices),
                ),
                indices.len() as u32,
            )
        });
        self.dirty = false;
    }
}

impl LodMethod for OwnMesh {
    fn name(&self) -> String {
        "own-mesh".into()
    }

    fn configure(&mut self, _config: &MethodConfig) {}

    fn draw(&mut self, input: &MethodInput<'_>, frame: &mut Frame<'_>) -> MethodOutput {
        if self.dirty {
            let gpu = frame.gpu().clone();
            self.rebuild(&gpu);
        }
        let camera = frame.camera();
        let [w, h] = frame.viewport();
        let p = camera.position;
        let mut uniforms = Vec::with_capacity(24);
        uniforms.extend(
            camera
                .view_proj_f32(f64::from(w) / f64::from(h))
                .to_cols_array(),
        );
        uniforms.extend([p[0] as f32, p[2] as f32, p[1] as f32, 0.0]);
        uniforms.extend([1.0f32, 0.0, 1.0, 1.0]);
        frame
            .gpu()
            .queue
            .write_buffer(&self.uniforms, 0, bytemuck::cast_slice(&uniforms));
        let importance = importance(input, frame);
        let mut pass = frame.pass();
        if let Some((vertices, indices, count)) = &self.mesh {
            let raw = pass.raw();
            raw.set_pipeline(&self.pipeline);
            raw.set_bind_group(0, &self.group, &[]);
            raw.set_vertex_buffer(0, vertices.slice(..));
            raw.set_index_buffer(indices.slice(..), wgpu::IndexFormat::Uint32);
            raw.draw_indexed(0..*count, 0, 0..1);
            pass.stats_mut().draw_calls += 1;
            pass.stats_mut().triangles += u64::from(count / 3);
            self.draws += 1;
        }
        drop(pass);
        MethodOutput {
            importance,
            ..MethodOutput::default()
        }
    }

    fn tile_resident(&mut self, _gpu: &Gpu, id: TileId, heights: &Heights) {
        let cells = self.tile_size - 1;
        let step = cells / (GRID - 1);
        // Resident tiles come from every level of the pyramid: a tile of level k has its
        // samples 2^k level-0 samples apart.
        let spacing = self
            .spacing_m
            .map(|s| s * plan::Layout::sample_step(id.level));
        let mut grid = Vec::with_capacity((GRID * GRID) as usize);
        for r in 0..GRID {
            for c in 0..GRID {
                let (column, row) = ((c * step) as usize, (r * step) as usize);
                grid.push([
                    ((id.x * cells) as f64 + column as f64) as f32 * spacing[0] as f32,
                    heights.metres(column, row) as f32,
                    ((id.y * cells) as f64 + row as f64) as f32 * spacing[1] as f32,
                ]);
            }
        }
        self.grids.insert(id, grid);
        self.dirty = true;
    }

    fn tile_evicted(&mut self, id: TileId) {
        self.grids.remove(&id);
        self.dirty = true;
    }

    fn tile_bytes(&self, id: TileId) -> u64 {
        // Its share of the mesh on the GPU and its grid on the CPU.
        if self.grids.contains_key(&id) {
            2 * Self::grid_bytes()
        } else {
            0
        }
    }

    fn expected_tile_bytes(&self, _tile: &TileRecord) -> u64 {
        2 * Self::grid_bytes()
    }

    fn shared_bytes(&self) -> MethodBytes {
        MethodBytes {
            cpu: 0,
            gpu: self.uniforms.size(),
        }
    }

    fn gpu_bytes(&self) -> u64 {
        self.uniforms.size()
            + self
                .mesh
                .as_ref()
                .map_or(0, |(v, i, _)| v.size() + i.size())
    }
}

/// Progressive patches' shape: data of its own per tile, fetched through the scene.
#[derive(Debug)]
struct OwnData {
    /// Per tile, where its data lives and its hash.
    sources: HashMap<TileId, (String, String)>,
    resident: HashSet<TileId>,
    data: HashMap<TileId, Bytes>,
    strip: Option<IndexSet>,
    masks: MaskSet,
}

impl OwnData {
    fn new(with: &Build<'_>) -> OwnData {
        let version = &with.manifest.content_version;
        OwnData {
            sources: with
                .manifest
                .tiles()
                .map(|(id, t)| (id, (routes::heights(version, id), t.hash.clone())))
                .collect(),
            resident: HashSet::new(),
            data: HashMap::new(),
            strip: None,
            masks: MaskSet::new(with.manifest.tile_size),
        }
    }
}

impl LodMethod for OwnData {
    fn name(&self) -> String {
        "own-data".into()
    }

    fn configure(&mut self, _config: &MethodConfig) {}

    fn draw(&mut self, input: &MethodInput<'_>, frame: &mut Frame<'_>) -> MethodOutput {
        let importance = importance(input, frame);
        // Only tiles whose own data arrived are drawn, at full resolution.
        let draws: Vec<(TileId, TileExtras)> = importance
            .iter()
            .filter(|(id, _)| self.data.contains_key(id))
            .map(|&(id, _)| (id, TileExtras::default()))
            .collect();
        let gpu = frame.gpu().clone();
        let masks = &self.masks;
        let strip = self
            .strip
            .get_or_insert_with(|| IndexSet::new(&gpu, masks.strip(0), masks.triangle_count(0)));
        frame.prepare_tiles(&draws);
        let order = frame.draw_order();
        let mut pass = frame.last_pass();
        for slot in order {
            pass.bind_tile(slot);
            pass.draw(strip);
            pass.stats_mut().triangles += u64::from(strip.triangles);
        }
        drop(pass);
        MethodOutput {
            plan: plan::FramePlan {
                draws: draws.iter().map(|&(id, _)| Draw { id, level: 0 }).collect(),
                ..plan::FramePlan::default()
            },
            importance,
            lod_ms: 0.0,
        }
    }

    fn tile_resident(&mut self, _gpu: &Gpu, id: TileId, _heights: &Heights) {
        self.resident.insert(id);
    }

    fn tile_evicted(&mut self, id: TileId) {
        self.resident.remove(&id);
        self.data.remove(&id);
    }

    fn wants(&mut self) -> Vec<DataWant> {
        self.resident
            .iter()
            .filter(|id| !self.data.contains_key(id))
            .map(|&id| {
                let (path, hash) = self.sources[&id].clone();
                DataWant {
                    id,
                    key: 7,
                    path,
                    hash: Some(hash),
                    bytes: None,
                }
            })
            .collect()
    }

    fn data_arrived(&mut self, _gpu: &Gpu, id: TileId, key: u32, bytes: Bytes) {
        assert_eq!(key, 7, "the key it asked with");
        if self.resident.contains(&id) {
            self.data.insert(id, bytes);
        }
    }

    fn tile_bytes(&self, id: TileId) -> u64 {
        self.data.get(&id).map_or(0, |b| b.len() as u64)
    }

    fn expected_tile_bytes(&self, tile: &TileRecord) -> u64 {
        tile.bytes
    }

    fn shared_bytes(&self) -> MethodBytes {
        MethodBytes {
            cpu: self.masks.bytes(),
            gpu: self.strip.as_ref().map_or(0, IndexSet::bytes),
        }
    }
}

/// Bytes of the allocations the GPU allocator reports for the terrain (labelled
/// [`TERRAIN_LABEL`]); `None` where the backend gives no report.
fn reported_terrain_bytes(gpu: &Gpu) -> Option<u64> {
    let report = gpu.device.generate_allocator_report()?;
    Some(
        report
            .allocations
            .iter()
            .filter(|a| a.name.starts_with(TERRAIN_LABEL))
            .map(|a| a.size)
            .sum(),
    )
}

/// Jacksboro built into a temporary directory (kept while the first value lives), served
/// on a free port, and a runtime for the client.
fn jacksboro() -> (tempfile::TempDir, TestServer, tokio::runtime::Runtime) {
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_jacksboro(tmp.path());
    let server = TestServer::start(&report.out);
    let runtime = tokio::runtime::Runtime::new().expect("runtime");
    (tmp, server, runtime)
}

/// A scene streaming jacksboro from `server` under `limit` bytes, drawn by `config`.
fn scene(
    server: &TestServer,
    gpu: &Gpu,
    limit: u64,
    config: RenderConfig,
) -> (Scene, terrain_client::requests::Fetcher) {
    let connection = tokio::runtime::Handle::current().block_on(Scene::connect(
        server.base_url(),
        FetcherConfig::default(),
        tokio::runtime::Handle::current(),
    ));
    let connection = connection.expect("connects");
    let scene = connection.scene(limit, true, Some((gpu.clone(), OFFSCREEN_FORMAT, config)));
    (scene, connection.fetcher)
}

/// Updates and draws `frames` frames from `camera`, letting deliveries arrive between them;
/// the last frame's image.
fn fly(
    scene: &mut Scene,
    fetcher: &mut terrain_client::requests::Fetcher,
    target: &Offscreen,
    camera: &Camera,
    frames: std::ops::Range<u64>,
    mut each: impl FnMut(&Scene),
) {
    for frame in frames {
        scene
            .update(fetcher, frame, camera.position)
            .expect("update");
        scene
            .draw(&target.view, camera, std::time::Instant::now())
            .expect("rendering");
        each(scene);
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
}

#[test]
fn a_method_with_its_own_pipeline_and_copy_of_the_terrain_draws_one_mesh_and_is_counted() {
    let test = "methods::a_method_with_its_own_pipeline_and_copy_of_the_terrain_draws_one_mesh_and_is_counted";
    let Some(gpu) = golden::gpu(test) else {
        return;
    };
    let (_tmp, server, runtime) = jacksboro();
    let _guard = runtime.enter();
    let limit = competing_limit(&server, 2 * OwnMesh::grid_bytes());
    let (mut scene, mut fetcher) = scene(&server, &gpu, limit, RenderConfig::default());
    scene.use_method(|with| Box::new(OwnMesh::new(with)));
    let target = Offscreen::new(&gpu, W, H);
    let camera = close();
    let mut frame = 0;
    while !scene.settled() || frame < 5 {
        fly(
            &mut scene,
            &mut fetcher,
            &target,
            &camera,
            frame..frame + 1,
            |_| {},
        );
        frame += 1;
        assert!(frame < 2000, "the scene settles");
    }
    let report = scene
        .draw(&target.view, &camera, std::time::Instant::now())
        .expect("rendering");
    assert_eq!(report.method, "own-mesh");
    assert_eq!(report.stats.draw_calls, 1, "one mesh, no per-tile draws");
    assert!(report.plan.draws.is_empty(), "no per-tile draws");
    let image = target.read(&gpu).expect("read back");
    let magenta = image.pixels().filter(|p| p.0 == MAGENTA).count();
    let sky = image.get_pixel(0, 0).0;
    let terrain = image.pixels().filter(|p| p.0 != sky).count();
    eprintln!(
        "own mesh: {magenta} magenta pixels of {} ({terrain} not sky)",
        W * H
    );
    // Its pipeline drew the terrain: a large part of the frame, all of it in its colour.
    assert!(magenta > (W * H / 10) as usize, "{magenta} pixels drawn");
    assert_eq!(magenta, terrain, "every terrain pixel is the mesh's");
    // Textures ranked by its importances, though it drew no tile.
    textures_follow_importance(&scene, &camera);
    assert!(scene.resident_bytes() <= scene.memory_limit());
    // Its bytes are in the resident figure: the mesh on the GPU, counted per tile.
    let tiles = scene.resident_tiles();
    let geometry = scene.geometry_memory();
    assert!(tiles > 0);
    assert_eq!(
        geometry.method_gpu,
        96 + tiles * OwnMesh::grid_bytes(),
        "the mesh of every resident tile and the uniforms"
    );
    assert!(scene.gpu_bytes() >= geometry.method_gpu + geometry.gpu.total());
    assert!(scene.resident_bytes() >= scene.cpu_bytes() + scene.gpu_bytes());
    if let Some(reported) = reported_terrain_bytes(&gpu) {
        assert!(
            reported >= scene.gpu_bytes(),
            "the allocator holds at least the ledger: {reported} < {}",
            scene.gpu_bytes()
        );
    }
}

/// Checks that the method's importances, not per-tile draws, ranked the textures: with a
/// limit that cannot refine every texture, the tiles in view hold finer textures than the
/// resident tiles out of view, and some tile is finer than its coarsest level. Returns the
/// mean levels (in view, out of view).
fn textures_follow_importance(scene: &Scene, camera: &Camera) -> (f64, f64) {
    let manifest = scene.manifest();
    let layout = plan::Layout::of(manifest);
    let candidates: Vec<plan::Candidate> = manifest
        .tiles()
        .map(|(id, t)| plan::Candidate::new(id, t, &[]))
        .collect();
    let visible: HashSet<TileId> =
        plan::visible_tiles(camera, f64::from(W) / f64::from(H), &layout, &candidates)
            .into_iter()
            .map(|i| candidates[i].id)
            .collect();
    let (mut seen, mut unseen) = (Vec::new(), Vec::new());
    for (id, _) in manifest.tiles() {
        if let Some(level) = scene.texture_level(id) {
            let list = if visible.contains(&id) {
                &mut seen
            } else {
                &mut unseen
            };
            list.push(f64::from(level));
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let (seen_mean, unseen_mean) = (mean(&seen), mean(&unseen));
    eprintln!(
        "texture levels: {} tiles in view at {seen_mean:.2} on average, {} out of view at {unseen_mean:.2}",
        seen.len(),
        unseen.len()
    );
    assert!(
        !seen.is_empty() && !unseen.is_empty(),
        "tiles in and out of view"
    );
    assert!(
        seen.iter().any(|&l| l > 0.0),
        "some texture refined past the coarsest"
    );
    assert!(
        seen_mean > unseen_mean,
        "the tiles in view hold finer textures: {seen_mean:.2} against {unseen_mean:.2}"
    );
    (seen_mean, unseen_mean)
}

/// A limit holding every tile of every level at its coarsest texture, what the method
/// expects to hold for each, and a quarter of what their finer levels would take (their
/// sizes are in the tile blobs, fetched here): textures compete.
fn competing_limit(server: &TestServer, per_tile: u64) -> u64 {
    let client = terrain_client::http_client::TileClient::new(server.base_url()).expect("client");
    let handle = tokio::runtime::Handle::current();
    let manifest = handle.block_on(client.manifest()).expect("manifest");
    let (mut base, mut finer) = (0, 0);
    for (id, t) in manifest.tiles() {
        let tile = handle
            .block_on(client.tile(&manifest, id))
            .unwrap_or_else(|e| panic!("tile {id}: {e}"));
        base += terrain_client::scene::expected_tile_bytes(&manifest, t, 1).total() + per_tile;
        finer += terrain_client::render::textures::extra_costs(&manifest, &tile.texture, 1)
            .last()
            .copied()
            .unwrap_or(0);
    }
    // With room for the method's shared bytes (a full-resolution index set at most).
    base + finer / 4 + (512 << 10)
}

/// A camera low over jacksboro looking at its north-west: about half the tiles in view.
fn close() -> Camera {
    Camera::looking_at([15000.0, 8000.0, 1500.0], [5000.0, 2000.0, 300.0])
}

#[test]
fn a_method_fetches_data_of_its_own_through_the_scene_and_is_counted() {
    let test = "methods::a_method_fetches_data_of_its_own_through_the_scene_and_is_counted";
    let Some(gpu) = golden::gpu(test) else {
        return;
    };
    let (_tmp, server, runtime) = jacksboro();
    let _guard = runtime.enter();
    let manifest = tokio::runtime::Handle::current()
        .block_on(
            terrain_client::http_client::TileClient::new(server.base_url())
                .expect("client")
                .manifest(),
        )
        .expect("manifest");
    let largest = manifest.tiles().map(|(_, t)| t.bytes).max().unwrap_or(0);
    let limit = competing_limit(&server, largest);
    let (mut scene, mut fetcher) = scene(&server, &gpu, limit, RenderConfig::default());
    scene.use_method(|with| Box::new(OwnData::new(with)));
    let target = Offscreen::new(&gpu, W, H);
    let camera = close();
    let mut frame = 0;
    let mut drawn = 0;
    while !scene.settled() || frame < 5 || drawn == 0 {
        fly(
            &mut scene,
            &mut fetcher,
            &target,
            &camera,
            frame..frame + 1,
            |_| {},
        );
        drawn = scene
            .draw(&target.view, &camera, std::time::Instant::now())
            .expect("rendering")
            .plan
            .draws
            .len();
        frame += 1;
        assert!(frame < 2000, "the scene settles");
    }
    let tiles = scene.resident_tiles();
    let geometry = scene.geometry_memory();
    // Every resident tile's own data arrived, fetched by the fetcher (a second GET of each
    // tile blob), and is counted on the CPU.
    let stats = fetcher.stats();
    assert!(
        stats.requests_started >= 2 * tiles,
        "{} requests for {tiles} tiles",
        stats.requests_started
    );
    assert!(drawn > 0, "tiles with their data are drawn");
    let manifest = &scene.manifest().clone();
    let own: u64 = manifest
        .tiles()
        .filter(|(id, _)| scene.texture_level(*id).is_some())
        .map(|(_, t)| t.bytes)
        .sum();
    assert!(own > 0);
    assert!(
        geometry.cpu_lod >= own,
        "the method's data is in the CPU figure: {} < {own}",
        geometry.cpu_lod
    );
    assert!(scene.cpu_bytes() >= own);
    textures_follow_importance(&scene, &camera);
    assert!(scene.resident_bytes() <= scene.memory_limit());
}

#[test]
fn geomipmaps_with_map_blocks_never_hold_more_than_the_limit_on_the_gpu_as_the_allocator_reports() {
    let test = "methods::geomipmaps_with_map_blocks_never_hold_more_than_the_limit_on_the_gpu_as_the_allocator_reports";
    let Some(gpu) = golden::gpu(test) else {
        return;
    };
    let (_tmp, server, runtime) = jacksboro();
    let _guard = runtime.enter();
    let config = RenderConfig {
        method: MethodKind::Geomipmap,
        // Blocks of 2 x 2 tiles, so several blocks come and go.
        texture_block_limit: Some(2 * 256),
        ..RenderConfig::default()
    };
    let connection = terrain_tests::connect(&runtime, server.base_url());
    // A third of what the whole database would take: tiles are evicted and textures
    // coarsened and refined as the camera crosses the terrain.
    let whole = whole_database_bytes(&connection.manifest);
    let limit = whole / 3;
    let mut scene = connection.scene(limit, true, Some((gpu.clone(), OFFSCREEN_FORMAT, config)));
    let mut fetcher = connection.fetcher;
    let target = Offscreen::new(&gpu, W, H);
    let extent = scene.manifest().extent_m;
    let mut worst: Option<(u64, u64)> = None;
    let (mut peak_gpu, mut frames) = (0u64, 0u64);
    let mut levels_seen = HashSet::new();
    let mut frame = 0;
    for leg in 0..4 {
        let (from, to) = if leg % 2 == 0 { (0.1, 0.9) } else { (0.9, 0.1) };
        for step in 0..60 {
            let t = from + (to - from) * f64::from(step) / 59.0;
            let position = [extent[0] * t, extent[1] * t, 2500.0];
            let camera = Camera::looking_at(
                position,
                [extent[0] * (1.0 - t), extent[1] * (1.0 - t), 300.0],
            );
            fly(
                &mut scene,
                &mut fetcher,
                &target,
                &camera,
                frame..frame + 1,
                |scene| {
                    let ledger = scene.gpu_bytes();
                    let cpu = scene.cpu_bytes();
                    peak_gpu = peak_gpu.max(ledger);
                    frames += 1;
                    assert!(
                        scene.resident_bytes() <= scene.memory_limit(),
                        "frame {frame}: {} bytes counted, limit {}; {:?}",
                        scene.resident_bytes(),
                        scene.memory_limit(),
                        scene.geometry_memory()
                    );
                    assert!(
                        cpu + ledger <= scene.memory_limit(),
                        "frame {frame}: {cpu} CPU + {ledger} GPU bytes, limit {}",
                        scene.memory_limit()
                    );
                    if let Some(reported) = reported_terrain_bytes(scene.gpu().expect("gpu")) {
                        // Every byte of the ledger is allocated; what the allocator adds is
                        // alignment, within a few percent.
                        assert!(reported >= ledger, "frame {frame}: {reported} < {ledger}");
                        assert!(
                            reported <= ledger + ledger / 20 + (64 << 10),
                            "frame {frame}: the allocator reports {reported}, the ledger {ledger}"
                        );
                        assert!(
                            cpu + reported <= scene.memory_limit(),
                            "frame {frame}: {cpu} CPU + {reported} GPU bytes reported, limit {}",
                            scene.memory_limit()
                        );
                        let w = worst.get_or_insert((0, 0));
                        if cpu + reported > w.0 + w.1 {
                            *w = (cpu, reported);
                        }
                    }
                    for (id, _) in scene.manifest().tiles() {
                        if let Some(level) = scene.texture_level(id) {
                            levels_seen.insert((id, level));
                        }
                    }
                },
            );
            frame += 1;
        }
    }
    eprintln!(
        "{frames} frames, limit {limit} B (a third of the whole database's {whole} B): peak GPU ledger {peak_gpu} B, worst CPU + reported GPU {worst:?}"
    );
    assert!(
        reported_terrain_bytes(&gpu).is_some() || !terrain_client::render::gpu::gpu_required(),
        "the Vulkan backend reports its allocations"
    );
    // The limit binds: the scene held close to it, with tiles at several texture levels.
    let most = worst.map_or(peak_gpu, |(c, g)| c + g);
    assert!(
        most > limit / 2,
        "the flight filled memory: {most} of {limit}"
    );
    // Some tile held two texture levels at different times: refined, or coarsened.
    let tiles_seen: HashSet<TileId> = levels_seen.iter().map(|(id, _)| *id).collect();
    assert!(
        levels_seen.len() > tiles_seen.len(),
        "textures changed level during the flight"
    );
}

#[test]
fn by_default_every_resident_tile_is_drawn_and_with_square_only_the_square_alone() {
    use terrain_tests::proxy::{FaultPlan, FaultyProxy};
    let test =
        "methods::by_default_every_resident_tile_is_drawn_and_with_square_only_the_square_alone";
    let Some(gpu) = golden::gpu(test) else {
        return;
    };
    let (_tmp, server, runtime) = jacksboro();
    // A slow link, so that a belt arrives over many frames.
    let proxy = FaultyProxy::start(
        server.addr(),
        FaultPlan::pass_through().with_bandwidth(300_000),
    );
    let _guard = runtime.enter();
    let connection = terrain_tests::connect(&runtime, proxy.base_url());
    let manifest = Arc::clone(&connection.manifest);
    let limit = 256 << 20;
    let mut scene = connection.scene(
        limit,
        true,
        Some((gpu.clone(), OFFSCREEN_FORMAT, RenderConfig::default())),
    );
    // Level 0 alone, the strip-mask paper's square: with the pyramid, a level-0 tile of the
    // belt still arriving is drawn only where the coarser levels are not fine enough, and
    // from this height (30 km) no such tile was drawn outside the squares in 3000 frames.
    scene.use_levels(false);
    let mut fetcher = connection.fetcher;
    let target = Offscreen::new(&gpu, W, H);
    let extent = manifest.extent_m;
    // Over the north-west corner, high enough to see every tile.
    let camera = Camera::looking_at(
        [extent[0] * 0.05, extent[1] * 0.05, 30000.0],
        [extent[0] * 0.5, extent[1] * 0.5, 300.0],
    );
    let drawn = |scene: &mut Scene| -> HashSet<TileId> {
        scene
            .draw(&target.view, &camera, std::time::Instant::now())
            .expect("rendering")
            .plan
            .draws
            .iter()
            .map(|d| d.id)
            .collect()
    };
    for frame in 0..3000 {
        let update = scene
            .update(&mut fetcher, frame, camera.position)
            .expect("update");
        // Every level used pages its own square: the square is the union of theirs (here
        // level 0's alone), each in its level's numbering.
        let square: HashSet<TileId> = update
            .levels
            .iter()
            .flat_map(|l| {
                terrain_client::page::square_tiles(
                    &l.pager,
                    l.decision.current,
                    l.decision.complete_belts,
                )
                .map(|id| id.with_level(l.level))
            })
            .collect();
        let every = drawn(&mut scene);
        if every.is_subset(&square) {
            // Nothing resident outside the square yet (or the whole grid is the square).
            assert!(frame < 2999, "a belt never arrived in parts");
            std::thread::sleep(std::time::Duration::from_millis(5));
            continue;
        }
        // Tiles of the belt still arriving are drawn by default; with square_only, only
        // the square is.
        scene.reconfigure(RenderConfig {
            square_only: true,
            ..RenderConfig::default()
        });
        let only = drawn(&mut scene);
        eprintln!(
            "frame {frame}: square of {} tiles; {} drawn by default, {} with square_only",
            square.len(),
            every.len(),
            only.len()
        );
        assert!(!only.is_empty(), "the square is drawn");
        assert!(only.is_subset(&square), "{only:?} in {square:?}");
        assert!(only.len() < every.len());
        return;
    }
}
