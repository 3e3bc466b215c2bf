//! `terrain-client view`: a window onto the streamed terrain, flown with mouse and keyboard.
//!
//! The viewer drives the same [`Scene`] as the headless flight ([`crate::flight`]): each
//! frame is a [`Scene::update`] (deliveries, paging, texture budget) at the camera's
//! position and a [`Scene::draw`] into the window's surface. Only where the camera goes
//! differs: the user steers it ([`FlyCamera`], pure and tested) instead of a path.
//!
//! Threads: winit's event loop owns the main thread; the fetcher's requests run on a tokio
//! multi-thread runtime built here, which the loop never blocks on. Nothing waits on the
//! network: a frame draws what has arrived.
//!
//! Controls (also printed at start, [`CONTROLS`]): W/S forward and back along the view,
//! A/D strafe, E or Space up, Q or Ctrl down, Shift five times faster, left mouse drag
//! looks around, the mouse wheel changes the speed, Escape quits.

use crate::flight::{FlightError, RenderArgs, StreamArgs};
use crate::http_client::FetchError;
use crate::memory::{MemoryBudget, MemoryError};
use crate::render::{Gpu, GpuError};
use crate::scene::{Connection, DrawReport, RenderConfig, Scene, SceneError};
use std::f64::consts::FRAC_PI_2;
use std::sync::Arc;
use std::time::{Duration, Instant};
use terrain_shared::Manifest;
use thiserror::Error;
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, EventLoop};
use winit::keyboard::{KeyCode, PhysicalKey};
use winit::window::{Window, WindowId};

pub use crate::fly::*;

/// How often the window title is updated.
pub const TITLE_INTERVAL: Duration = Duration::from_millis(250);
/// How often `--print-stats` prints the title to stderr.
pub const PRINT_INTERVAL: Duration = Duration::from_secs(2);
/// The controls, as printed at start.
pub const CONTROLS: &str = "controls:
  W / S            forward / back (along the view)
  A / D            strafe left / right
  E or Space       up
  Q or Ctrl        down
  Shift            5x speed while held
  left mouse drag  look around
  mouse wheel      faster / slower
  Escape           quit";

/// `terrain-client view`.
#[derive(Debug, Clone, clap::Args)]
pub struct ViewArgs {
    #[command(flatten)]
    pub stream: StreamArgs,
    /// Where the camera starts, X,Y,Z metres (x east and y south from the north-west
    /// corner, z up), e.g. --start=1000,2000,800. Default: above the terrain's centre, 5% of
    /// its larger extent above its highest point, looking north.
    #[arg(long, value_parser = parse_point, allow_hyphen_values = true, value_name = "X,Y,Z")]
    pub start: Option<[f64; 3]>,
    /// Flying speed, metres per second (Shift: 5x; the mouse wheel changes it). Default: a
    /// tenth of the terrain's larger extent per second.
    #[arg(long)]
    pub speed: Option<f64>,
    /// Print the window title's statistics to stderr every 2 s (they are also logged at
    /// debug level: RUST_LOG=terrain_client=debug).
    #[arg(long)]
    pub print_stats: bool,
    /// Rendering, as for `fly`: --size is the window's initial size and --pitch-deg the
    /// initial pitch.
    #[command(
        flatten,
        next_help_heading = "Rendering (as for `fly`; --size: initial window size, --pitch-deg: \
                             initial pitch)"
    )]
    pub render: RenderArgs,
}

/// Why the viewer could not start or stopped.
#[derive(Debug, Error)]
pub enum ViewError {
    #[error(
        "a window needs a display ({0}); set DISPLAY (X11) or WAYLAND_DISPLAY, or for headless use run \
         `terrain-client fly`, which renders offscreen and writes frames and flight.csv"
    )]
    NoDisplay(String),
    #[error("cannot open the window: {0}")]
    Window(String),
    #[error("cannot start the async runtime for the fetcher: {0}")]
    Runtime(std::io::Error),
    #[error("invalid option: {0}")]
    BadOption(String),
    #[error(transparent)]
    Fetch(#[from] FetchError),
    #[error(transparent)]
    Memory(#[from] MemoryError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error(transparent)]
    Flight(#[from] FlightError),
    #[error(transparent)]
    Scene(#[from] SceneError),
}

/// Keys and buttons held, and what happened since the last frame.
#[derive(Debug, Clone, Default)]
struct InputState {
    forward: bool,
    back: bool,
    left: bool,
    right: bool,
    up: bool,
    down: bool,
    /// Left and right Shift separately, so releasing one keeps the other's effect.
    shift: [bool; 2],
    dragging: bool,
    cursor: Option<[f64; 2]>,
    look: [f64; 2],
    wheel: f64,
}

impl InputState {
    /// Records a key; returns true when it is one of the controls.
    fn key(&mut self, code: KeyCode, pressed: bool) -> bool {
        let slot = match code {
            KeyCode::KeyW | KeyCode::ArrowUp => &mut self.forward,
            KeyCode::KeyS | KeyCode::ArrowDown => &mut self.back,
            KeyCode::KeyA | KeyCode::ArrowLeft => &mut self.left,
            KeyCode::KeyD | KeyCode::ArrowRight => &mut self.right,
            KeyCode::KeyE | KeyCode::Space | KeyCode::PageUp => &mut self.up,
            KeyCode::KeyQ | KeyCode::ControlLeft | KeyCode::ControlRight | KeyCode::PageDown => {
                &mut self.down
            }
            KeyCode::ShiftLeft => &mut self.shift[0],
            KeyCode::ShiftRight => &mut self.shift[1],
            _ => return false,
        };
        *slot = pressed;
        true
    }

    fn cursor_moved(&mut self, x: f64, y: f64) {
        if self.dragging
            && let Some([px, py]) = self.cursor
        {
            self.look[0] += x - px;
            self.look[1] += y - py;
        }
        self.cursor = Some([x, y]);
    }

    /// Releases everything held (the window lost focus: its key-ups will not come).
    fn release_all(&mut self) {
        *self = InputState {
            cursor: self.cursor,
            ..InputState::default()
        };
    }

    /// This frame's input; the drag and the wheel are consumed.
    fn take(&mut self) -> FlyInput {
        let axis = |plus: bool, minus: bool| f64::from(u8::from(plus)) - f64::from(u8::from(minus));
        let input = FlyInput {
            forward: axis(self.forward, self.back),
            right: axis(self.right, self.left),
            up: axis(self.up, self.down),
            fast: self.shift[0] || self.shift[1],
            look: self.look,
            wheel: self.wheel,
        };
        self.look = [0.0; 2];
        self.wheel = 0.0;
        input
    }
}

/// What the title shows.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ViewStats {
    pub fps: f64,
    pub triangles: u64,
    pub visible_tiles: usize,
    pub resident_tiles: u64,
    pub total_tiles: usize,
    pub resident_bytes: u64,
    pub memory_limit: u64,
}

/// The window title: dataset and frame statistics.
pub fn title(dataset: &str, s: &ViewStats) -> String {
    let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
    format!(
        "terrain-client view — {dataset} — {:.0} fps, {} triangles, {} tiles visible, {}/{} tiles resident, {:.1}/{:.1} MiB",
        s.fps,
        s.triangles,
        s.visible_tiles,
        s.resident_tiles,
        s.total_tiles,
        mib(s.resident_bytes),
        mib(s.memory_limit)
    )
}

/// Opens the window and flies until it is closed or Escape is pressed. Runs the event loop
/// on the calling thread, which must be the main thread and not inside a tokio runtime.
pub fn run(args: &ViewArgs) -> Result<(), ViewError> {
    if let Some(speed) = args.speed
        && !(speed.is_finite() && speed > 0.0)
    {
        return Err(ViewError::BadOption(format!(
            "--speed {speed} must be a positive number of metres per second"
        )));
    }
    let render_config = args.render.config()?;
    let budget = args.stream.budget()?;
    // Before any network traffic: without a display there is nothing to show it on.
    let display_set = |name: &str| std::env::var_os(name).is_some_and(|v| !v.is_empty());
    // On Linux and the BSDs winit needs X11 or Wayland; macOS and Windows always have one.
    if cfg!(all(
        unix,
        not(any(
            target_os = "macos",
            target_os = "ios",
            target_os = "android"
        ))
    )) && !display_set("DISPLAY")
        && !display_set("WAYLAND_DISPLAY")
    {
        return Err(ViewError::NoDisplay(
            "neither DISPLAY nor WAYLAND_DISPLAY is set".into(),
        ));
    }
    let event_loop = EventLoop::new().map_err(|e| {
        // winit says "os error at FILE:LINE: WHY"; the user needs WHY and the display.
        let text = e.to_string();
        let why = match text.strip_prefix("os error at ") {
            Some(rest) => rest.split_once(": ").map_or(rest, |(_, why)| why),
            None => &text,
        };
        let display = std::env::var("DISPLAY").unwrap_or_default();
        let wayland = std::env::var("WAYLAND_DISPLAY").unwrap_or_default();
        ViewError::NoDisplay(format!(
            "DISPLAY={display} WAYLAND_DISPLAY={wayland}: {why}"
        ))
    })?;

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("terrain-fetch")
        .build()
        .map_err(ViewError::Runtime)?;
    let connection = runtime.block_on(Scene::connect(
        &args.stream.server,
        args.stream.fetcher_config(),
        runtime.handle().clone(),
    ))?;
    let manifest = Arc::clone(&connection.manifest);
    let start = args.start.unwrap_or_else(|| default_start(&manifest));
    let speed = args.speed.unwrap_or_else(|| default_speed(&manifest));
    // Looking north by default.
    let camera = FlyCamera::new(start, -FRAC_PI_2, args.render.pitch_deg.to_radians(), speed);
    println!(
        "viewing {} ({} tiles, {:.0} x {:.0} m) from {}; memory limit {:.1} MiB; start at \
         {:.0},{:.0},{:.0} m, {:.0} m/s",
        manifest.dataset,
        manifest.levels[0].tiles.len(),
        manifest.extent_m[0],
        manifest.extent_m[1],
        args.stream.server,
        budget.limit_bytes() as f64 / crate::memory::MIB,
        start[0],
        start[1],
        start[2],
        camera.speed
    );
    println!("{CONTROLS}");

    let mut app = App {
        manifest,
        connection,
        budget,
        stream: args.stream.clone(),
        render_config,
        window_size: args.render.size,
        print_stats: args.print_stats,
        camera,
        input: InputState::default(),
        view: None,
        error: None,
        frame: 0,
        last_frame: None,
        window_stats: WindowStats::new(Instant::now()),
    };
    let run = event_loop.run_app(&mut app);
    // Stop the downloads (dropping the fetcher aborts them) before the runtime goes.
    let error = app.error.take();
    drop(app);
    runtime.shutdown_timeout(Duration::from_secs(1));
    match (error, run) {
        (Some(error), _) => Err(error),
        (None, run) => run.map_err(|e| ViewError::Window(e.to_string())),
    }
}

/// The window, its surface and the scene drawn into it.
#[derive(Debug)]
struct View {
    window: Arc<Window>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    /// Format views of the surface's textures take (the sRGB form of `config.format`).
    view_format: wgpu::TextureFormat,
    gpu: Gpu,
    scene: Scene,
}

impl View {
    fn open(
        event_loop: &ActiveEventLoop,
        connection: &Connection,
        budget: MemoryBudget,
        stream: &crate::flight::StreamArgs,
        render: RenderConfig,
        size: (u32, u32),
    ) -> Result<View, ViewError> {
        let attributes = Window::default_attributes()
            .with_title(format!(
                "terrain-client view — {}",
                connection.manifest.dataset
            ))
            .with_inner_size(PhysicalSize::new(size.0, size.1));
        let window = Arc::new(
            event_loop
                .create_window(attributes)
                .map_err(|e| ViewError::Window(e.to_string()))?,
        );
        let instance = Gpu::instance();
        let surface = instance
            .create_surface(Arc::clone(&window))
            .map_err(|e| GpuError::Surface(e.to_string()))?;
        let gpu = Gpu::with_instance(instance, Some(&surface))?;
        let inner = window.inner_size();
        let (mut config, view_format) = gpu
            .surface_config(&surface, inner.width, inner.height)
            .ok_or_else(|| {
                GpuError::Surface(format!(
                    "the adapter {} cannot present to this window",
                    gpu.description()
                ))
            })?;
        crate::method::check_gpu(render.method, gpu.downlevel()).map_err(ViewError::BadOption)?;
        config.present_mode = wgpu::PresentMode::AutoVsync;
        surface.configure(&gpu.device, &config);
        tracing::info!(
            adapter = %gpu.description(),
            format = ?config.format,
            width = config.width,
            height = config.height,
            "window open"
        );
        let mut scene = connection.scene(
            budget.limit_bytes(),
            true,
            Some((gpu.clone(), view_format, render)),
        );
        stream.configure(&mut scene);
        scene.set_viewport([config.width, config.height]);
        budget.check(
            scene.least_limit(),
            &format!(
                "--method {} in a window of {}x{}",
                render.method.name(),
                config.width,
                config.height
            ),
        )?;
        Ok(View {
            window,
            surface,
            config,
            view_format,
            gpu,
            scene,
        })
    }

    fn resize(&mut self, size: PhysicalSize<u32>) {
        if size.width == 0 || size.height == 0 {
            return;
        }
        self.config.width = size.width;
        self.config.height = size.height;
        self.surface.configure(&self.gpu.device, &self.config);
    }

    /// The next texture to draw into, and whether the surface should be reconfigured
    /// once it is presented (suboptimal); `None` when this frame cannot be drawn (the
    /// surface timed out, is hidden, or was reconfigured or recreated).
    fn acquire(&mut self) -> Result<Option<(wgpu::SurfaceTexture, bool)>, ViewError> {
        use wgpu::CurrentSurfaceTexture as Current;
        Ok(match self.surface.get_current_texture() {
            Current::Success(texture) => Some((texture, false)),
            Current::Suboptimal(texture) => Some((texture, true)),
            Current::Timeout | Current::Occluded => None,
            Current::Outdated => {
                self.resize(self.window.inner_size());
                None
            }
            Current::Lost => {
                tracing::warn!("the window's surface was lost; creating it again");
                self.surface = self
                    .gpu
                    .instance
                    .create_surface(Arc::clone(&self.window))
                    .map_err(|e| GpuError::Surface(e.to_string()))?;
                self.surface.configure(&self.gpu.device, &self.config);
                None
            }
            Current::Validation => {
                tracing::warn!("acquiring the window's next texture raised a validation error");
                None
            }
        })
    }
}

/// Frame counts and the last draw, between title updates.
#[derive(Debug, Clone)]
struct WindowStats {
    since: Instant,
    frames: u64,
    last_print: Instant,
    last: Option<(u64, usize)>,
}

impl WindowStats {
    fn new(now: Instant) -> WindowStats {
        WindowStats {
            since: now,
            frames: 0,
            last_print: now,
            last: None,
        }
    }
}

#[derive(Debug)]
struct App {
    manifest: Arc<Manifest>,
    /// The manifest and the fetcher streaming its tiles.
    connection: Connection,
    budget: MemoryBudget,
    /// How the scene pages the levels (`--single-level`, `--level-policy`).
    stream: crate::flight::StreamArgs,
    render_config: RenderConfig,
    window_size: (u32, u32),
    print_stats: bool,
    camera: FlyCamera,
    input: InputState,
    view: Option<View>,
    /// Why the loop was stopped, reported once it returns.
    error: Option<ViewError>,
    frame: u64,
    last_frame: Option<Instant>,
    window_stats: WindowStats,
}

impl App {
    fn fail(&mut self, event_loop: &ActiveEventLoop, error: ViewError) {
        if self.error.is_none() {
            self.error = Some(error);
        }
        event_loop.exit();
    }

    /// One frame: move the camera, page and stream, draw, present.
    fn redraw(&mut self) -> Result<(), ViewError> {
        let Some(view) = &mut self.view else {
            return Ok(());
        };
        // Acquire first: a vsync wait there is not the frame's work, and the frame-rate
        // controller should see only the work.
        let texture = view.acquire()?;
        let now = Instant::now();
        let dt = self
            .last_frame
            .map_or(0.0, |t| now.duration_since(t).as_secs_f64());
        self.last_frame = Some(now);
        self.camera.apply(&self.input.take(), dt);
        // Off the terrain, or over a tile not yet resident, the lowest point is the floor.
        let ground = view.scene.ground_under(self.camera.position);
        self.camera
            .keep_above(Some(ground.unwrap_or(self.manifest.heights.min_m)));
        view.scene.update(
            &mut self.connection.fetcher,
            self.frame,
            self.camera.position,
        )?;
        self.frame += 1;
        if let Some((texture, suboptimal)) = texture {
            let target = texture.texture.create_view(&wgpu::TextureViewDescriptor {
                format: Some(view.view_format),
                ..Default::default()
            });
            let report: Option<DrawReport> = view.scene.draw(&target, &self.camera.camera(), now);
            // Nothing may hold the surface's texture when it is reconfigured.
            drop(target);
            view.window.pre_present_notify();
            view.gpu.queue.present(texture);
            if suboptimal {
                view.resize(view.window.inner_size());
            }
            if let Some(report) = report {
                self.window_stats.last = Some((report.stats.triangles, report.plan.draws.len()));
            }
            self.window_stats.frames += 1;
        } else {
            // Hidden or reconfigured: page on, but do not spin.
            std::thread::sleep(Duration::from_millis(10));
        }
        self.update_title();
        Ok(())
    }

    fn update_title(&mut self) {
        let Some(view) = &self.view else {
            return;
        };
        let now = Instant::now();
        let s = &mut self.window_stats;
        let elapsed = now.duration_since(s.since);
        if elapsed < TITLE_INTERVAL {
            return;
        }
        let (triangles, visible_tiles) = s.last.unwrap_or((0, 0));
        let stats = ViewStats {
            fps: s.frames as f64 / elapsed.as_secs_f64(),
            triangles,
            visible_tiles,
            resident_tiles: view.scene.resident_tiles(),
            total_tiles: self.manifest.tile_count(),
            resident_bytes: view.scene.resident_bytes(),
            memory_limit: view.scene.memory_limit(),
        };
        s.since = now;
        s.frames = 0;
        let text = title(&self.manifest.dataset, &stats);
        view.window.set_title(&text);
        if now.duration_since(s.last_print) >= PRINT_INTERVAL {
            s.last_print = now;
            let [x, y, z] = self.camera.position;
            tracing::debug!(x, y, z, speed = self.camera.speed, "{text}");
            if self.print_stats {
                eprintln!(
                    "{text} — camera at {x:.0},{y:.0},{z:.0} m, yaw {:.0}°, pitch {:.0}°, {:.0} m/s",
                    self.camera.yaw.to_degrees(),
                    self.camera.pitch.to_degrees(),
                    self.camera.speed
                );
            }
        }
    }
}

impl ApplicationHandler for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.view.is_some() {
            return;
        }
        match View::open(
            event_loop,
            &self.connection,
            self.budget,
            &self.stream,
            self.render_config,
            self.window_size,
        ) {
            Ok(view) => {
                view.window.request_redraw();
                self.view = Some(view);
            }
            Err(error) => self.fail(event_loop, error),
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) => {
                if let Some(view) = &mut self.view {
                    view.resize(size);
                }
            }
            WindowEvent::Focused(false) => self.input.release_all(),
            WindowEvent::KeyboardInput { event, .. } => {
                let pressed = event.state == ElementState::Pressed;
                if let PhysicalKey::Code(code) = event.physical_key {
                    if code == KeyCode::Escape && pressed {
                        event_loop.exit();
                    } else {
                        self.input.key(code, pressed);
                    }
                }
            }
            WindowEvent::MouseInput {
                state,
                button: MouseButton::Left,
                ..
            } => self.input.dragging = state == ElementState::Pressed,
            WindowEvent::CursorMoved { position, .. } => {
                self.input.cursor_moved(position.x, position.y);
            }
            WindowEvent::CursorLeft { .. } => self.input.cursor = None,
            WindowEvent::MouseWheel { delta, .. } => {
                self.input.wheel += match delta {
                    MouseScrollDelta::LineDelta(_, y) => f64::from(y),
                    // Touchpads: about 40 pixels a notch.
                    MouseScrollDelta::PixelDelta(p) => p.y / 40.0,
                };
            }
            WindowEvent::RedrawRequested => {
                if let Err(error) = self.redraw() {
                    self.fail(event_loop, error);
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, _event_loop: &ActiveEventLoop) {
        if let Some(view) = &self.view {
            view.window.request_redraw();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::TAU;

    fn close(a: [f64; 3], b: [f64; 3]) -> bool {
        a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-9)
    }

    #[test]
    fn forward_moves_along_the_heading_at_the_speed() {
        // Looking south (y grows southwards), level.
        let mut camera = FlyCamera::new([100.0, 200.0, 50.0], FRAC_PI_2, 0.0, 10.0);
        let input = FlyInput {
            forward: 1.0,
            ..FlyInput::default()
        };
        camera.apply(&input, 0.1);
        assert!(
            close(camera.position, [100.0, 201.0, 50.0]),
            "{:?}",
            camera.position
        );
        // Back undoes it.
        camera.apply(
            &FlyInput {
                forward: -1.0,
                ..FlyInput::default()
            },
            0.1,
        );
        assert!(
            close(camera.position, [100.0, 200.0, 50.0]),
            "{:?}",
            camera.position
        );
    }

    #[test]
    fn forward_follows_the_pitch_and_strafe_and_up_do_not() {
        let mut camera = FlyCamera::new([0.0; 3], 0.0, (-45.0f64).to_radians(), 10.0);
        camera.apply(
            &FlyInput {
                forward: 1.0,
                ..FlyInput::default()
            },
            0.1,
        );
        let h = 0.5f64.sqrt();
        assert!(
            close(camera.position, [h, 0.0, -h]),
            "{:?}",
            camera.position
        );
        // Looking east, right is south; up is world up whatever the pitch.
        let mut camera = FlyCamera::new([0.0; 3], 0.0, (-45.0f64).to_radians(), 10.0);
        camera.apply(
            &FlyInput {
                right: 1.0,
                up: 1.0,
                ..FlyInput::default()
            },
            0.1,
        );
        assert!(
            close(camera.position, [0.0, 1.0, 1.0]),
            "{:?}",
            camera.position
        );
    }

    #[test]
    fn shift_and_the_wheel_scale_the_speed() {
        let forward = FlyInput {
            forward: 1.0,
            ..FlyInput::default()
        };
        let mut slow = FlyCamera::new([0.0; 3], 0.0, 0.0, 10.0);
        let mut fast = slow;
        slow.apply(&forward, 0.1);
        fast.apply(
            &FlyInput {
                fast: true,
                ..forward
            },
            0.1,
        );
        assert!((fast.position[0] - FAST_FACTOR * slow.position[0]).abs() < 1e-9);
        let mut camera = FlyCamera::new([0.0; 3], 0.0, 0.0, 10.0);
        camera.apply(
            &FlyInput {
                wheel: 2.0,
                ..FlyInput::default()
            },
            0.0,
        );
        assert!((camera.speed - 10.0 * WHEEL_FACTOR * WHEEL_FACTOR).abs() < 1e-9);
        assert_eq!(camera.position, [0.0; 3], "no time, no movement");
        camera.apply(
            &FlyInput {
                wheel: -1e6,
                ..FlyInput::default()
            },
            0.0,
        );
        assert_eq!(
            camera.speed, SPEED_RANGE.0,
            "the wheel cannot stop the camera"
        );
    }

    #[test]
    fn pitch_is_clamped_and_yaw_wraps() {
        let mut camera = FlyCamera::new([0.0; 3], 0.0, 0.0, 10.0);
        camera.apply(
            &FlyInput {
                look: [0.0, -1e6],
                ..FlyInput::default()
            },
            0.0,
        );
        assert!((camera.pitch - MAX_PITCH_DEG.to_radians()).abs() < 1e-12);
        camera.apply(
            &FlyInput {
                look: [0.0, 1e6],
                ..FlyInput::default()
            },
            0.0,
        );
        assert!((camera.pitch + MAX_PITCH_DEG.to_radians()).abs() < 1e-12);
        // Dragging right turns right: from east towards south.
        let mut camera = FlyCamera::new([0.0; 3], 0.0, 0.0, 10.0);
        camera.apply(
            &FlyInput {
                look: [100.0, 0.0],
                ..FlyInput::default()
            },
            0.0,
        );
        assert!(camera.yaw > 0.0 && camera.yaw < FRAC_PI_2, "{}", camera.yaw);
        camera.apply(
            &FlyInput {
                look: [-200.0, 0.0],
                ..FlyInput::default()
            },
            0.0,
        );
        assert!((0.0..TAU).contains(&camera.yaw), "{}", camera.yaw);
    }

    #[test]
    fn the_position_stays_finite_and_long_stalls_do_not_jump() {
        let mut camera = FlyCamera::new([1.0, 2.0, 3.0], 0.0, 0.0, 10.0);
        let forward = FlyInput {
            forward: 1.0,
            ..FlyInput::default()
        };
        camera.apply(&forward, f64::NAN);
        camera.apply(
            &FlyInput {
                look: [f64::INFINITY, f64::NAN],
                wheel: f64::NAN,
                ..forward
            },
            0.0,
        );
        assert_eq!(camera.position, [1.0, 2.0, 3.0]);
        assert!(camera.yaw.is_finite() && camera.pitch.is_finite() && camera.speed == 10.0);
        camera.apply(&forward, 100.0);
        assert!((camera.position[0] - (1.0 + 10.0 * MAX_STEP_S)).abs() < 1e-9);
        let mut huge = FlyCamera::new([0.0; 3], 0.0, 0.0, f64::MAX);
        huge.apply(&forward, MAX_STEP_S);
        assert!(huge.position.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn the_camera_keeps_clear_of_the_ground() {
        let mut camera = FlyCamera::new([0.0, 0.0, 100.0], 0.0, 0.0, 10.0);
        camera.keep_above(Some(99.0));
        assert_eq!(camera.position[2], 99.0 + GROUND_CLEARANCE_M);
        camera.keep_above(Some(10.0));
        camera.keep_above(None);
        assert_eq!(camera.position[2], 99.0 + GROUND_CLEARANCE_M);
    }

    #[test]
    fn keys_make_axes_and_drags_only_count_while_the_button_is_held() {
        let mut input = InputState::default();
        assert!(input.key(KeyCode::KeyW, true));
        assert!(input.key(KeyCode::KeyA, true));
        assert!(input.key(KeyCode::Space, true));
        assert!(input.key(KeyCode::ShiftRight, true));
        assert!(!input.key(KeyCode::KeyZ, true));
        input.cursor_moved(10.0, 10.0);
        input.cursor_moved(20.0, 30.0);
        let i = input.take();
        assert_eq!((i.forward, i.right, i.up, i.fast), (1.0, -1.0, 1.0, true));
        assert_eq!(i.look, [0.0, 0.0], "not dragging");
        input.dragging = true;
        input.cursor_moved(25.0, 28.0);
        assert_eq!(input.take().look, [5.0, -2.0]);
        assert_eq!(input.take().look, [0.0, 0.0], "a drag is consumed once");
        input.release_all();
        assert_eq!(input.take(), FlyInput::default());
    }

    #[test]
    fn points_parse_and_bad_ones_say_why() {
        assert_eq!(parse_point("1,-2.5, 3e2"), Ok([1.0, -2.5, 300.0]));
        assert!(parse_point("1,2").is_err_and(|e| e.contains("X,Y,Z")));
        assert!(parse_point("1,x,3").is_err_and(|e| e.contains("finite")));
        assert!(parse_point("1,inf,3").is_err_and(|e| e.contains("finite")));
    }

    #[test]
    fn the_title_names_dataset_and_counts() {
        let text = title(
            "jacksboro",
            &ViewStats {
                fps: 59.6,
                triangles: 12345,
                visible_tiles: 7,
                resident_tiles: 9,
                total_tiles: 16,
                resident_bytes: 3 * 1048576,
                memory_limit: 64 * 1048576,
            },
        );
        assert_eq!(
            text,
            "terrain-client view — jacksboro — 60 fps, 12345 triangles, 7 tiles visible, \
             9/16 tiles resident, 3.0/64.0 MiB"
        );
    }
}
