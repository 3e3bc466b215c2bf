//! The terrain client in a browser tab.
//!
//! The page (`web/page/`, built by `bash scripts/build-web.sh` into `viewer/dist/client/` and
//! served by `terrain-server serve --viewer viewer/dist` under `/view/client/`) makes one
//! [`Client`] on its canvas and calls [`Client::frame`] from `requestAnimationFrame`. The
//! client is the native one ([`terrain_client::scene::Scene`]: belt paging under the memory
//! limit, importance, the frame-rate controller's triangle budget, strip masks and the
//! planar shadow, the other methods), with three things of the page's at its rim: requests
//! go through the browser's `fetch` as the page's own tasks
//! ([`terrain_client::requests::Spawner::page`]), the clock is the page's, and frames are
//! drawn into the canvas with WebGPU, or with WebGL2 where the browser has no WebGPU. On
//! WebGL2 the tiles' samples are read from a texture ([`terrain_client::render::SampleStore`]),
//! and the methods that need what WebGL2 lacks (GeoMipMaps' base vertex, the projected grids'
//! storage buffers) say so when chosen ([`terrain_client::method::check_gpu`]): the strip
//! masks with every crack filler, and the reference, draw on both.
//!
//! **Memory.** The limit covers what it covers natively
//! ([`terrain_client::memory::MEMORY_INVARIANT`]): tiles, textures, GPU copies and what the
//! method holds. The page shows the wasm heap beside it (`WebAssembly.Memory`'s size), which
//! holds the CPU side of that and the program.
//!
//! Empty on every target but `wasm32`.
#![cfg(target_arch = "wasm32")]

use std::sync::Arc;
use terrain_client::fly::{FlyCamera, FlyInput};
use terrain_client::lod::budget::BudgetMode;
use terrain_client::memory::{MemoryBudget, MemorySize};
use terrain_client::method::{CrackFiller, MethodKind};
use terrain_client::path::{CameraPath, heading};
use terrain_client::render::{Camera, Gpu};
use terrain_client::requests::{Fetcher, FetcherConfig, Spawner};
use terrain_client::scene::{RenderConfig, Scene};
use terrain_shared::Manifest;
use wasm_bindgen::prelude::*;
use web_time::Instant;

/// What the page says when the browser has neither WebGPU nor WebGL2.
const NO_GPU: &str = "this page draws with WebGPU or WebGL2, and this browser offers neither \
     here (is hardware acceleration turned off?). Open it in a browser with either, or use \
     the native client (terrain-client view).";

/// What the page asks for (a JSON object; every field optional).
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Options {
    /// The memory budget, e.g. "64MiB"; the limit is `limit_percent` of it.
    pub memory: String,
    pub limit_percent: f64,
    /// Frames per second the triangle budget is predicted to hold.
    pub target_fps: f64,
    /// A fixed triangle budget instead (for comparisons and golden images).
    pub fixed_budget: Option<u32>,
    /// `strip-masks`, `geomipmaps`, `projected-grid`, ... as `terrain-client fly --method`.
    pub method: String,
    /// `planar-shadow`, ... as `terrain-client fly --crack-filler`.
    pub filler: String,
    /// `flight`: the default flight (`terrain-client fly`'s, frame by frame at
    /// `flight_fps`); `fly`: the user steers.
    pub mode: String,
    pub flight_fps: f64,
    /// Flight mode: the flight's clock is the page's (a second of flight a second of wall
    /// time, as a user would see it) instead of `flight_fps` a frame.
    pub wall_clock: bool,
    /// Flight mode: the flight starts again at its end (for long runs).
    pub loop_flight: bool,
    pub pitch_deg: f64,
}

impl Default for Options {
    fn default() -> Options {
        Options {
            memory: "64MiB".into(),
            limit_percent: terrain_client::memory::DEFAULT_LIMIT_PERCENT,
            target_fps: terrain_client::lod::budget::DEFAULT_TARGET_FPS,
            fixed_budget: None,
            method: MethodKind::default().name().into(),
            filler: CrackFiller::default().name().into(),
            mode: "flight".into(),
            flight_fps: 30.0,
            wall_clock: false,
            loop_flight: false,
            pitch_deg: terrain_client::render::camera::DEFAULT_PITCH_DEG,
        }
    }
}

/// Where the camera goes.
#[derive(Debug)]
enum Mode {
    /// The default flight, one frame of `fps` per drawn frame (so frame `k` is the native
    /// flight's frame `k`, whatever the page's frame rate), or by the page's clock from
    /// `wall_clock` on; from its start again at its end with `looped`.
    Flight {
        path: CameraPath,
        fps: f64,
        yaw: f64,
        pitch: f64,
        wall_clock: Option<Instant>,
        looped: bool,
    },
    /// The user steers.
    Fly { camera: FlyCamera, input: FlyInput },
}

/// One frame's figures, for the page's overlay (and its tests).
#[derive(Debug, Default, Clone, serde::Serialize)]
pub struct FrameStats {
    pub frame: u64,
    /// Bytes the limit covers, at the end of the frame.
    pub resident_bytes: u64,
    pub limit_bytes: u64,
    /// The most `resident_bytes` was at any frame's end.
    pub peak_resident_bytes: u64,
    pub gpu_bytes: u64,
    pub complete_belts: u32,
    pub belt_count: u32,
    pub resident_tiles: u64,
    pub in_flight: u64,
    pub triangles: u64,
    pub filler_triangles: u64,
    pub budget: Option<u32>,
    pub target_fps: Option<f64>,
    /// This frame's wall time as the frame-rate controller measured it.
    pub frame_ms: f64,
    pub bytes_downloaded: u64,
    pub requests: u64,
    pub failures: u64,
    pub method: String,
    /// The flight has reached its end (flight mode).
    pub flight_done: bool,
    /// Every tile is resident with its textures, nothing in flight.
    pub settled: bool,
    pub camera: [f64; 5],
}

#[wasm_bindgen(start)]
pub fn start() {
    console_error_panic_hook::set_once();
}

/// The client in the page: a scene drawn into a canvas.
#[wasm_bindgen]
#[derive(Debug)]
pub struct Client {
    scene: Scene,
    fetcher: Fetcher,
    manifest: Arc<Manifest>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    view_format: wgpu::TextureFormat,
    gpu: Gpu,
    render: RenderConfig,
    mode: Mode,
    frame: u64,
    last_frame: Option<Instant>,
    peak_resident: u64,
    backend: String,
}

fn js_error(message: impl std::fmt::Display) -> JsError {
    JsError::new(&message.to_string())
}

fn parse_enum<T: clap::ValueEnum>(what: &str, text: &str) -> Result<T, JsError> {
    T::from_str(text, true).map_err(|_| {
        let names: Vec<String> = T::value_variants()
            .iter()
            .filter_map(|v| v.to_possible_value().map(|p| p.get_name().to_string()))
            .collect();
        js_error(format!("{what} {text:?}: one of {}", names.join(", ")))
    })
}

fn render_config(options: &Options) -> Result<RenderConfig, JsError> {
    if !(options.target_fps.is_finite() && options.target_fps > 0.0) {
        return Err(js_error(format!(
            "target fps {} must be positive",
            options.target_fps
        )));
    }
    let budget = match (options.fixed_budget, BudgetMode::default()) {
        (Some(b), _) => BudgetMode::Fixed(b),
        (
            None,
            BudgetMode::Adaptive {
                initial_budget,
                min_budget,
                max_budget,
                ..
            },
        ) => BudgetMode::Adaptive {
            target_fps: options.target_fps,
            initial_budget,
            min_budget,
            max_budget,
        },
        (None, fixed) => fixed,
    };
    Ok(RenderConfig {
        method: parse_enum("method", &options.method)?,
        filler: parse_enum("crack filler", &options.filler)?,
        budget,
        ..RenderConfig::default()
    })
}

/// Methods the page draws, or why not: the database must have what the method reads
/// ([`terrain_client::method::check_database`]), and on WebGL2 some methods lack what they
/// draw with ([`terrain_client::method::check_gpu`]).
fn check_method(kind: MethodKind, manifest: &Manifest, gpu: &Gpu) -> Result<(), JsError> {
    terrain_client::method::check_gpu(kind, gpu.downlevel()).map_err(js_error)?;
    terrain_client::method::check_database(kind, manifest).map_err(js_error)
}

fn budget(options: &Options) -> Result<MemoryBudget, JsError> {
    let size: MemorySize = options.memory.parse().map_err(js_error)?;
    MemoryBudget::new(Some(size), options.limit_percent).map_err(js_error)
}

#[wasm_bindgen]
impl Client {
    /// Connects to the tile server at `server` (its manifest, checked) and opens the page's
    /// GPU on `canvas`; `options` is a JSON object of [`Options`].
    pub async fn connect(
        canvas: web_sys::HtmlCanvasElement,
        server: String,
        options: String,
    ) -> Result<Client, JsError> {
        let options: Options = serde_json::from_str(if options.trim().is_empty() {
            "{}"
        } else {
            &options
        })
        .map_err(|e| js_error(format!("options: {e}")))?;
        let render = render_config(&options)?;
        let budget = budget(&options)?;
        let (width, height) = (canvas.width().max(1), canvas.height().max(1));

        // WebGPU where the browser has it, else WebGL2 (a canvas takes one context only, so
        // the choice is made before the surface).
        let mut descriptor = wgpu::InstanceDescriptor::new_without_display_handle();
        descriptor.backends = if wgpu::util::is_browser_webgpu_supported().await {
            wgpu::Backends::BROWSER_WEBGPU
        } else {
            wgpu::Backends::GL
        };
        let instance = wgpu::Instance::new(descriptor);
        let surface = instance
            .create_surface(wgpu::SurfaceTarget::Canvas(canvas))
            .map_err(|e| js_error(format!("{NO_GPU} ({e})")))?;
        let gpu = Gpu::for_page(instance, &surface)
            .await
            .map_err(|e| js_error(format!("{NO_GPU} ({e})")))?;
        let backend = format!("{:?}", gpu.adapter.get_info().backend);
        let (config, view_format) =
            gpu.surface_config(&surface, width, height).ok_or_else(|| {
                js_error(format!(
                    "{} cannot draw into this canvas",
                    gpu.description()
                ))
            })?;
        surface.configure(&gpu.device, &config);

        let connection = Scene::connect(&server, FetcherConfig::default(), Spawner::page())
            .await
            .map_err(|e| js_error(terrain_client::http_client::cause_chain(&e)))?;
        let manifest = Arc::clone(&connection.manifest);
        check_method(render.method, &manifest, &gpu)?;
        let mut scene = connection.scene(
            budget.limit_bytes(),
            true,
            Some((gpu.clone(), view_format, render)),
        );
        scene.set_viewport([config.width, config.height]);
        budget
            .check(
                scene.least_limit(),
                &format!("{} in a canvas of {width}x{height}", render.method.name()),
            )
            .map_err(js_error)?;
        let pitch = options.pitch_deg.to_radians();
        let mode = match options.mode.as_str() {
            "flight" => {
                if !(options.flight_fps.is_finite() && options.flight_fps > 0.0) {
                    return Err(js_error("flight fps must be positive"));
                }
                let path = CameraPath::default_for(&manifest);
                let start = path.position_at(0.0);
                let centre = [manifest.extent_m[0] / 2.0, manifest.extent_m[1] / 2.0];
                Mode::Flight {
                    yaw: (centre[1] - start[1]).atan2(centre[0] - start[0]),
                    path,
                    fps: options.flight_fps,
                    pitch,
                    wall_clock: options.wall_clock.then(Instant::now),
                    looped: options.loop_flight,
                }
            }
            "fly" => Mode::Fly {
                camera: FlyCamera::new(
                    terrain_client::fly::default_start(&manifest),
                    -std::f64::consts::FRAC_PI_2,
                    pitch,
                    terrain_client::fly::default_speed(&manifest),
                ),
                input: FlyInput::default(),
            },
            other => return Err(js_error(format!("mode {other:?}: flight or fly"))),
        };
        Ok(Client {
            scene,
            fetcher: connection.fetcher,
            manifest,
            surface,
            config,
            view_format,
            gpu,
            render,
            mode,
            frame: 0,
            last_frame: None,
            peak_resident: 0,
            backend,
        })
    }

    /// The graphics API drawing (`BrowserWebGpu`).
    pub fn backend(&self) -> String {
        self.backend.clone()
    }

    /// The adapter, in words.
    pub fn adapter(&self) -> String {
        self.gpu.description()
    }

    /// The dataset's name.
    pub fn dataset(&self) -> String {
        self.manifest.dataset.clone()
    }

    /// One frame: moves the camera, pages and streams, draws and presents. Returns the
    /// frame's [`FrameStats`] as JSON.
    pub fn frame(&mut self) -> Result<String, JsError> {
        let now = Instant::now();
        let dt = self
            .last_frame
            .map_or(0.0, |t| now.duration_since(t).as_secs_f64());
        // The frame-rate controller measures from the start of the frame before: in a page
        // the GPU's work is asynchronous (nothing in the frame waits for it), and the
        // browser paces animation frames by it, so the time between frames is what a frame
        // costs, and what the user sees.
        let frame_started = self.last_frame.unwrap_or(now);
        self.last_frame = Some(now);
        let pitch = self.pitch();
        let (camera, flight_done) = match &mut self.mode {
            Mode::Flight {
                path,
                fps,
                yaw,
                wall_clock,
                looped,
                ..
            } => {
                let t = match wall_clock {
                    Some(started) => now.duration_since(*started).as_secs_f64(),
                    None => self.frame as f64 / *fps,
                };
                let t = if *looped && path.duration_s() > 0.0 {
                    t % path.duration_s()
                } else {
                    t
                };
                let position = path.position_at(t);
                *yaw = heading(path, t, *yaw);
                (
                    Camera::new(position, *yaw, pitch),
                    !*looped && t >= path.duration_s(),
                )
            }
            Mode::Fly { camera, input } => {
                camera.apply(input, dt);
                input.look = [0.0, 0.0];
                input.wheel = 0.0;
                let ground = self.scene.ground_under(camera.position);
                camera.keep_above(Some(ground.unwrap_or(self.manifest.heights.min_m)));
                (camera.camera(), false)
            }
        };
        let update = self
            .scene
            .update(&mut self.fetcher, self.frame, camera.position)
            .map_err(js_error)?;
        let texture = match self.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(t)
            | wgpu::CurrentSurfaceTexture::Suboptimal(t) => Some(t),
            _ => {
                self.surface.configure(&self.gpu.device, &self.config);
                None
            }
        };
        let report = texture.and_then(|texture| {
            let target = texture.texture.create_view(&wgpu::TextureViewDescriptor {
                format: Some(self.view_format),
                ..Default::default()
            });
            let report = self.scene.draw(&target, &camera, frame_started);
            drop(target);
            self.gpu.queue.present(texture);
            report
        });
        let resident = self.scene.resident_bytes();
        self.peak_resident = self.peak_resident.max(resident);
        let fetch = self.fetcher.stats();
        let stats = FrameStats {
            frame: self.frame,
            resident_bytes: resident,
            limit_bytes: self.scene.memory_limit(),
            peak_resident_bytes: self.peak_resident,
            gpu_bytes: self.scene.gpu_bytes(),
            complete_belts: update.decision.complete_belts,
            belt_count: update.decision.belt_count,
            resident_tiles: self.scene.resident_tiles(),
            in_flight: self.scene.in_flight(),
            triangles: report.as_ref().map_or(0, |r| r.stats.triangles),
            filler_triangles: report.as_ref().map_or(0, |r| r.stats.filler_triangles),
            budget: self.scene.budget(),
            target_fps: report.as_ref().and_then(|r| r.target_fps),
            frame_ms: report.as_ref().map_or(0.0, |r| r.frame_ms),
            bytes_downloaded: fetch.bytes_downloaded,
            requests: fetch.requests_started,
            failures: fetch.failures,
            method: report.map(|r| r.method).unwrap_or_default(),
            flight_done,
            settled: self.scene.settled(),
            camera: [
                camera.position[0],
                camera.position[1],
                camera.position[2],
                camera.yaw,
                camera.pitch,
            ],
        };
        self.frame += 1;
        serde_json::to_string(&stats).map_err(js_error)
    }

    /// The canvas was resized to `width` x `height` pixels.
    pub fn resize(&mut self, width: u32, height: u32) {
        self.config.width = width.max(1);
        self.config.height = height.max(1);
        self.surface.configure(&self.gpu.device, &self.config);
        self.scene
            .set_viewport([self.config.width, self.config.height]);
    }

    /// Keys held (fly mode): each axis -1, 0 or 1; `fast`: Shift.
    pub fn steer(&mut self, forward: f64, right: f64, up: f64, fast: bool) {
        if let Mode::Fly { input, .. } = &mut self.mode {
            input.forward = forward;
            input.right = right;
            input.up = up;
            input.fast = fast;
        }
    }

    /// A mouse drag of `dx`, `dy` pixels and `wheel` notches since the last frame (fly mode).
    pub fn look(&mut self, dx: f64, dy: f64, wheel: f64) {
        if let Mode::Fly { input, .. } = &mut self.mode {
            input.look[0] += dx;
            input.look[1] += dy;
            input.wheel += wheel;
        }
    }

    /// A new memory budget ("64MiB"), the limit being the same share of it. Refused (the
    /// old one stays) when below what the scene needs to draw anything.
    pub fn set_memory(&mut self, memory: String, limit_percent: f64) -> Result<(), JsError> {
        let budget = budget(&Options {
            memory,
            limit_percent,
            ..Options::default()
        })?;
        budget
            .check(self.scene.least_limit(), "this page")
            .map_err(js_error)?;
        self.scene.set_memory_limit(budget.limit_bytes());
        Ok(())
    }

    /// A new target frame rate for the triangle budget.
    pub fn set_target_fps(&mut self, fps: f64) -> Result<(), JsError> {
        let render = render_config(&Options {
            target_fps: fps,
            method: self.render.method.name().into(),
            filler: self.render.filler.name().into(),
            ..Options::default()
        })?;
        self.render.budget = render.budget;
        self.scene.reconfigure(self.render);
        Ok(())
    }

    /// Another method and crack filler, as `terrain-client fly --method --crack-filler`.
    pub fn set_method(&mut self, method: String, filler: String) -> Result<(), JsError> {
        let kind: MethodKind = parse_enum("method", &method)?;
        check_method(kind, &self.manifest, &self.gpu)?;
        self.render.method = kind;
        self.render.filler = parse_enum("crack filler", &filler)?;
        self.scene.reconfigure(self.render);
        Ok(())
    }
}

impl Client {
    fn pitch(&self) -> f64 {
        match &self.mode {
            Mode::Fly { camera, .. } => camera.pitch,
            Mode::Flight { pitch, .. } => *pitch,
        }
    }
}
