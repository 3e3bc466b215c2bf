//! `terrain-client bench accuracy`: error against speed over one flight.
//!
//! The whole database is paged in first (every tile, every texture level), so the frames
//! differ only by how they are drawn. Cameras are taken evenly along the flight (the
//! default lap, or `--flight`); at each, the reference is drawn once (every visible tile at
//! full resolution) and then every method, crack filler and fixed triangle budget, each
//! measured against it ([`super::frame::measure`]). Budgets are fixed, not predicted, so
//! that error against triangles does not depend on the machine's speed; frame times are
//! the median of `--repeats` draws.
//!
//! Writes `accuracy.csv` (a row per camera and configuration), `summary.md` (a row per
//! configuration), and the charts: error against triangles, error
//! against frame time, crack pixels against budget, triangles used against needed.

mod blocks;
mod on_screen;
mod report;

pub use self::report::{
    CSV_HEADER, Guarantee, guarantees, pareto_front, reference_floor, summary_markdown,
};
use self::report::{write_images, write_outputs};

use super::Variants;
use super::popping::{Changes, Pair, Popping};
use super::session::{Measured, Session, median};
use crate::flight::{ErrorCapArgs, FlightError, heading, parse_size};
use crate::lod::budget::BudgetMode;
use crate::lod::plan::LodSettings;
use crate::method::CrackFiller;
use crate::method::MethodKind;
use crate::path::CameraPath;
use crate::render::Camera;
use crate::scene::RenderConfig;
use std::path::PathBuf;
use std::time::Duration;

/// Arguments of `terrain-client bench accuracy`.
#[derive(Debug, Clone, clap::Args)]
pub struct AccuracyArgs {
    /// Base URL of the tile server.
    #[arg(long, env = "TERRAIN_SERVER", required_unless_present = "data")]
    pub server: Option<String>,
    /// More databases to sweep, NAME=URL (repeatable): each is swept in turn, into
    /// OUT/NAME, titled NAME.
    #[arg(long = "data", value_parser = super::parse_named)]
    pub data: Vec<(String, String)>,
    /// Directory for the CSVs, the summary and the charts; created if missing.
    #[arg(long, default_value = "out/accuracy")]
    pub out: PathBuf,
    /// The knob of methods with a global triangle budget (strip masks): fixed budgets,
    /// comma-separated.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "1000,3000,10000,30000,100000,300000,1000000"
    )]
    pub budgets: Vec<u32>,
    /// The knob of methods without a budget (GeoMipMaps): the screen-space error each
    /// tile's level is chosen within, pixels, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "0.5,1,2,4,8,16")]
    pub max_errors_px: Vec<f64>,
    /// The knob of the projected grids: grid sizes, COLUMNSxROWS vertices, comma-separated.
    #[arg(
        long,
        value_delimiter = ',',
        value_parser = parse_size,
        default_value = "64x36,128x72,256x144,512x288"
    )]
    pub grids: Vec<(u32, u32)>,
    /// Keep the projective grid uniform (as persistent grid mapping draws it).
    #[arg(long)]
    pub uniform_grid: bool,
    /// Draw the projective grid without ray casting.
    #[arg(long)]
    pub no_ray_casting: bool,
    #[command(flatten)]
    pub variants: Variants,
    /// Cameras taken evenly along the flight.
    #[arg(long, default_value_t = 8)]
    pub cameras: u32,
    /// Camera path (see docs/flight.md). Default: the lap of `fly`.
    #[arg(long)]
    pub flight: Option<PathBuf>,
    /// Frame size, WIDTHxHEIGHT.
    #[arg(long, default_value = "640x360", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Camera pitch, degrees above the horizon.
    #[arg(long, default_value_t = crate::render::camera::DEFAULT_PITCH_DEG, allow_negative_numbers = true)]
    pub pitch_deg: f64,
    /// The error threshold (also of the share of pixels above it) and the strip masks' cap.
    #[command(flatten)]
    pub error: ErrorCapArgs,
    /// Draws per configuration and camera; the frame time is their median.
    #[arg(long, default_value_t = 3)]
    pub repeats: u32,
    /// Name of the dataset in titles (default: the manifest's).
    #[arg(long)]
    pub label: Option<String>,
    /// Frames of the approach popping is measured on (from the first camera towards the
    /// ground it looks at, see `--popping-halvings`); 0 leaves popping out.
    #[arg(long, default_value_t = 40)]
    pub popping_frames: u32,
    /// How many times the distance to the ground the first camera looks at halves over
    /// that approach: each halving doubles every patch's and tile's projected error once,
    /// so each crosses about one level switch; 0 keeps the camera still.
    #[arg(long, default_value_t = 1.0)]
    pub popping_halvings: f64,
    /// Also write every measured frame to OUT/images: `CAMERA-METHOD-SETTING.png`, and for a
    /// frame with a crack filler `...-filler.png`, the frame with the filler's pixels
    /// marked: green where it fills a crack, red where it leaks, blue the holes left.
    #[arg(long)]
    pub images: bool,
    /// Also count, per camera, what regular grids chosen per block of a tile would need
    /// (blocks of 128 down to 4 cells, each at the coarsest GeoMipMap level or strip-mask
    /// step within the threshold at its own nearest point) against the oracle, into
    /// OUT/block-grids.md: how near the oracle a regular-grid method can come by choosing
    /// per block. Slow (every block of every full-resolution tile in view, every step).
    #[arg(long)]
    pub block_grids: bool,
    /// Count the oracle over the samples on screen only: a sample none of whose cells is in
    /// the camera's view is free (by default every sample of every full-resolution tile in
    /// view is held to the threshold, on screen or not). Stricter: a method that culls
    /// inside a tile no longer comes below the oracle for it.
    #[arg(long)]
    pub on_screen_oracle: bool,
}

impl AccuracyArgs {
    /// The defaults of the command line against `server`, writing to `out`.
    pub fn new(server: impl Into<String>, out: impl Into<PathBuf>) -> AccuracyArgs {
        AccuracyArgs {
            server: Some(server.into()),
            data: Vec::new(),
            out: out.into(),
            budgets: vec![1000, 3000, 10_000, 30_000, 100_000, 300_000, 1_000_000],
            max_errors_px: vec![0.5, 1.0, 2.0, 4.0, 8.0, 16.0],
            grids: vec![(64, 36), (128, 72), (256, 144), (512, 288)],
            uniform_grid: false,
            no_ray_casting: false,
            variants: Variants::default(),
            cameras: 8,
            flight: None,
            size: (640, 360),
            pitch_deg: crate::render::camera::DEFAULT_PITCH_DEG,
            error: ErrorCapArgs::default(),
            repeats: 3,
            label: None,
            popping_frames: 40,
            popping_halvings: 1.0,
            images: false,
            block_grids: false,
            on_screen_oracle: false,
        }
    }
}

/// What a method turns to trade error for triangles: each method sweeps its own.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Knob {
    /// A fixed global triangle budget (strip masks).
    Budget(u32),
    /// The screen-space error allowed, pixels (GeoMipMaps, which take no budget).
    MaxErrorPx(f64),
    /// The projected grids' size: vertices per row and per column.
    Grid([u32; 2]),
}

impl Knob {
    /// The knob's setting as a number, for CSV columns and chart axes.
    pub fn value(self) -> f64 {
        match self {
            Knob::Budget(b) => f64::from(b),
            Knob::MaxErrorPx(e) => e,
            Knob::Grid([c, r]) => f64::from(c) * f64::from(r),
        }
    }

    /// Its name, as the CSV's `knob` column gives it.
    pub fn name(self) -> &'static str {
        match self {
            Knob::Budget(_) => "budget",
            Knob::MaxErrorPx(_) => "max_error_px",
            Knob::Grid(_) => "grid_vertices",
        }
    }
}

impl std::fmt::Display for Knob {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Knob::Budget(b) => write!(f, "budget {b}"),
            Knob::MaxErrorPx(e) => write!(f, "{e} px"),
            Knob::Grid([c, r]) => write!(f, "grid {c}x{r}"),
        }
    }
}

/// The knobs `method` is swept over with `args`.
pub fn knobs(method: MethodKind, args: &AccuracyArgs) -> Vec<Knob> {
    match method {
        MethodKind::Geomipmap | MethodKind::QuadtreePatches => args
            .max_errors_px
            .iter()
            .map(|&e| Knob::MaxErrorPx(e))
            .collect(),
        MethodKind::StripMasks | MethodKind::Reference => {
            args.budgets.iter().map(|&b| Knob::Budget(b)).collect()
        }
        MethodKind::Pgm | MethodKind::ProjectiveGrid => args
            .grids
            .iter()
            .map(|&(c, r)| Knob::Grid([c, r]))
            .collect(),
    }
}

/// One configuration: a method, its filler, its knob's setting.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Config {
    pub method: MethodKind,
    pub filler: CrackFiller,
    pub knob: Knob,
}

impl Config {
    /// `method/filler` (or `method` for methods without filler).
    pub fn series(&self) -> String {
        Variants::name(self.method, self.filler)
    }

    /// The screen-space error it is drawn within: its own knob's, or the sweep's
    /// `threshold_px` (the strip masks' error cap).
    pub fn threshold_px(&self, threshold_px: f64) -> f64 {
        match self.knob {
            Knob::Budget(_) | Knob::Grid(_) => threshold_px,
            Knob::MaxErrorPx(e) => e,
        }
    }

    /// How to draw it: `base` with the knob's budget or error threshold.
    pub fn render(&self, base: RenderConfig) -> RenderConfig {
        let mut grid = base.grid;
        let (budget, lod) = match self.knob {
            Knob::Budget(b) => (b, base.lod),
            Knob::Grid(size) => {
                grid.size = size;
                (u32::MAX, base.lod)
            }
            Knob::MaxErrorPx(e) => (
                u32::MAX,
                LodSettings {
                    max_error_px: e,
                    ..base.lod
                },
            ),
        };
        RenderConfig {
            method: self.method,
            filler: self.filler,
            budget: BudgetMode::Fixed(budget),
            lod,
            grid,
            ..base
        }
    }
}

/// One camera drawn with one configuration.
#[derive(Debug, Clone)]
pub struct Row {
    pub camera: u32,
    pub config: Config,
    pub measured: Measured,
    /// Whether the method had every piece of data it asked for before the frame was measured
    /// (the quadtree patches' bodies): `false` when the wait for them ran out, and the frame
    /// was drawn with coarser patches where finer ones had not arrived.
    pub settled: bool,
    /// What was still missing when the wait ran out ([`crate::scene::Scene::unsettled`]).
    pub unsettled: Option<String>,
}

/// A configuration over all cameras.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    pub config: Config,
    pub triangles: f64,
    pub triangles_needed: f64,
    /// The oracle's triangles at this configuration's threshold, mean over the cameras,
    /// and the triangles used over all cameras over the oracle's over all cameras.
    pub oracle_triangles: f64,
    pub used_over_oracle: f64,
    /// Mean of the per-frame ratios triangles used / triangles needed.
    pub used_over_needed: f64,
    pub filler_triangles: f64,
    pub draw_calls: f64,
    pub mean_error_px: f64,
    /// Means over the cameras of each frame's 95th and 99th percentile error.
    pub p95_error_px: f64,
    pub p99_error_px: f64,
    pub max_error_px: f64,
    /// Share of terrain pixels above the threshold, percent.
    pub above_threshold_pct: f64,
    pub crack_pixels: f64,
    pub hole_pixels: f64,
    pub silhouette_pixels: f64,
    /// Pixels showing the crack filler, and of those the ones where the mesh has no crack
    /// (leaks, [`super::frame::FrameMeasures::leak_pixels`]).
    pub filler_pixels: f64,
    pub leak_pixels: f64,
    /// Crack pixels in percent of the reference's terrain pixels.
    pub crack_pct: f64,
    pub psnr_db: f64,
    pub frame_ms: f64,
    pub cpu_ms: f64,
    pub gpu_ms: Option<f64>,
    /// Mean over the cameras of what the scene held after the frame (CPU and GPU bytes).
    pub held_bytes: f64,
    /// Frame-to-frame change on the approach beyond the reference's own, per pixel
    /// ([`super::popping`]); `None` when popping was not measured.
    pub popping: Option<Popping>,
    /// The projective grid's shares of the frame's pixels, percent, mean over the cameras:
    /// those the grid drew with an error past the threshold, and those whose ray was walked
    /// (of those and the ones no grid triangle covered, the rays that enter the terrain's
    /// box). `None` for the other methods.
    pub error_pixels_pct: Option<f64>,
    pub ray_cast_pct: Option<f64>,
}

/// What the sweep measured.
#[derive(Debug, Clone)]
pub struct AccuracyReport {
    pub dataset: String,
    pub adapter: String,
    pub size: (u32, u32),
    pub threshold_px: f64,
    pub cameras: u32,
    pub tiles: usize,
    pub resident_bytes: u64,
    pub downloaded_bytes: u64,
    /// Per camera, the reference frame's own error against the true surface: the floor of
    /// the measure (see [`Session::own_error`]).
    pub reference_errors: Vec<super::metrics::ErrorStats>,
    /// Per camera, the oracle's triangle count ([`oracle_triangles`]) at each threshold the
    /// configurations ask for, as (threshold px, triangles).
    pub oracle: Vec<Vec<(f64, u64)>>,
    /// Whether the oracle counts the samples on screen only (`--on-screen-oracle`).
    pub on_screen_oracle: bool,
    /// Triangles and median time of the reference frames.
    pub reference_triangles: f64,
    pub reference_ms: f64,
    pub rows: Vec<Row>,
    pub summaries: Vec<Summary>,
    /// Per method, the geometry the scene kept right after its last frame (the last
    /// camera, the largest budget).
    pub geometry: Vec<(String, crate::scene::GeometryMemory)>,
    pub files: Vec<PathBuf>,
}

/// Runs the sweep (see the module documentation). Must run inside a multi-threaded tokio
/// runtime.
pub async fn run(args: &AccuracyArgs) -> Result<AccuracyReport, FlightError> {
    check(args)?;
    let defaults = LodSettings::default();
    let lod = args.error.lod(defaults.alpha, defaults.height)?;
    let base = RenderConfig {
        lod,
        grid: crate::method::GridSettings {
            warp: !args.uniform_grid,
            ray_casting: !args.no_ray_casting,
            ..crate::method::GridSettings::default()
        },
        ..RenderConfig::default()
    };
    let server = args
        .server
        .as_deref()
        .ok_or_else(|| FlightError::BadOption("--server (or --data NAME=URL) is needed".into()))?;
    let mut session = Session::open(server, None, base, args.size).await?;
    let manifest = std::sync::Arc::clone(&session.manifest);
    for &method in &args.variants.methods {
        crate::method::check_database(method, &manifest).map_err(FlightError::BadOption)?;
    }
    let path = match &args.flight {
        Some(file) => CameraPath::load(file, &manifest)?,
        None => CameraPath::default_for(&manifest),
    };
    let cameras = cameras_along(&path, args.cameras, args.pitch_deg);
    let bar = super::progress(
        "loading every tile",
        u64::from(args.cameras) * configs(args).len() as u64,
    );
    let centre = session.centre();
    let settled = session
        .settle(centre, &cameras[0], Duration::from_secs(600))
        .await?;
    if !settled || session.scene.resident_tiles() as usize != manifest.tile_count() {
        return Err(FlightError::BadOption(format!(
            "the database did not load whole within 10 minutes ({} of {} tiles resident)",
            session.scene.resident_tiles(),
            manifest.tile_count()
        )));
    }
    bar.set_message("measuring");
    let mut rows = Vec::new();
    let mut geometry: Vec<(String, crate::scene::GeometryMemory)> = Vec::new();
    let mut reference_errors = Vec::new();
    let mut oracle = Vec::new();
    let mut thresholds: Vec<f64> = configs(args)
        .iter()
        .map(|c| c.threshold_px(lod.max_error_px))
        .collect();
    thresholds.sort_by(f64::total_cmp);
    thresholds.dedup();
    let (mut reference_triangles, mut reference_ms) = (Vec::new(), Vec::new());
    let mut block_grids = Vec::new();
    for (i, camera) in cameras.iter().enumerate() {
        let (reference, report) = session.reference(camera)?;
        reference_errors.push(session.own_error(&reference, camera, lod.max_error_px));
        let viewport = [args.size.0, args.size.1];
        if args.block_grids {
            block_grids.push(blocks::block_grid_counts(
                &session.scene,
                camera,
                viewport,
                lod.max_error_px,
            ));
        }
        oracle.push(
            thresholds
                .iter()
                .copied()
                .zip(oracle_triangles(
                    &session.scene,
                    camera,
                    viewport,
                    &thresholds,
                    args.on_screen_oracle,
                ))
                .collect(),
        );
        reference_triangles.push(report.stats.triangles as f64);
        reference_ms.push(report.draw_ms);
        for config in configs(args) {
            let render = config.render(base);
            let settled = session
                .prepare(centre, camera, render, Duration::from_secs(120))
                .await?;
            let unsettled = (!settled).then(|| session.unsettled().unwrap_or_default());
            if let Some(missing) = &unsettled {
                tracing::warn!(
                    camera = i,
                    config = %config.series(),
                    "measured before the scene settled (waited 120 s): {missing}"
                );
            }
            let mut measured =
                session.measure(camera, render, &reference, lod.max_error_px, args.repeats)?;
            let unfilled = measured.unfilled.take();
            if args.images {
                write_images(
                    &args.out.join("images"),
                    &format!(
                        "{i}-{}-{}",
                        config.series().replace('/', "-"),
                        config.knob.value()
                    ),
                    &measured.capture,
                    unfilled.as_ref(),
                    &reference,
                )?;
            }
            if i + 1 == cameras.len() {
                let method = config.method.name().to_string();
                let memory = session.scene.geometry_memory();
                match geometry.iter_mut().find(|(m, _)| *m == method) {
                    Some(entry) => entry.1 = memory,
                    None => geometry.push((method, memory)),
                }
            }
            rows.push(Row {
                camera: i as u32,
                config,
                measured,
                settled,
                unsettled,
            });
            bar.inc(1);
        }
    }
    // Popping, on an approach from the first camera.
    let ground = session
        .scene
        .ground_under(cameras[0].position)
        .unwrap_or(manifest.heights.min_m);
    let approach = approach_flight(
        &cameras[0],
        ground,
        args.popping_frames,
        args.popping_halvings,
    );
    let mut popping = Vec::new();
    if approach.len() >= 2 {
        bar.set_message("popping");
        let references = approach
            .iter()
            .map(|camera| Ok(session.reference(camera)?.0))
            .collect::<Result<Vec<_>, FlightError>>()?;
        for config in configs(args) {
            let render = config.render(base);
            session
                .prepare(centre, &approach[0], render, Duration::from_secs(120))
                .await?;
            let frames = approach
                .iter()
                .map(|camera| Ok(session.capture(camera, render)?.0))
                .collect::<Result<Vec<_>, FlightError>>()?;
            let mut changes = Changes::default();
            for k in 1..approach.len() {
                let at = |j: usize| Pair {
                    method: &frames[j],
                    reference: &references[j],
                    eye: approach[j].position,
                };
                changes.add(at(k - 1), at(k));
            }
            popping.push((config, changes.summary()));
        }
    }
    bar.finish_and_clear();
    let stats = session.fetcher.stats();
    let mut report = AccuracyReport {
        on_screen_oracle: args.on_screen_oracle,
        dataset: args
            .label
            .clone()
            .unwrap_or_else(|| manifest.dataset.clone()),
        adapter: session.gpu.description(),
        size: args.size,
        threshold_px: lod.max_error_px,
        cameras: args.cameras,
        tiles: manifest.tile_count(),
        resident_bytes: session.scene.resident_bytes(),
        downloaded_bytes: stats.bytes_downloaded,
        reference_triangles: reference_triangles.iter().sum::<f64>()
            / reference_triangles.len().max(1) as f64,
        reference_ms: median(&mut reference_ms),
        summaries: summarise(&rows, &configs(args), &popping, &oracle, lod.max_error_px),
        oracle,
        reference_errors,
        geometry,
        rows,
        files: Vec::new(),
    };
    session.close();
    write_outputs(args, &mut report)?;
    if !block_grids.is_empty() {
        let path = args.out.join("block-grids.md");
        let table = blocks::block_grids_markdown(&report, &block_grids);
        println!("{table}");
        std::fs::write(&path, table).map_err(|source| FlightError::Write {
            path: path.clone(),
            source,
        })?;
        report.files.push(path);
    }
    Ok(report)
}

/// The sweep on `--server` (into `--out`) and on every `--data` database (into
/// `OUT/NAME`, titled NAME), one after another.
pub async fn run_each(args: &AccuracyArgs) -> Result<Vec<AccuracyReport>, FlightError> {
    let mut reports = Vec::new();
    if args.server.is_some() {
        reports.push(run(args).await?);
    }
    for (name, url) in &args.data {
        let one = AccuracyArgs {
            server: Some(url.clone()),
            data: Vec::new(),
            out: args.out.join(name),
            label: Some(name.clone()),
            ..args.clone()
        };
        reports.push(run(&one).await?);
    }
    Ok(reports)
}

fn check(args: &AccuracyArgs) -> Result<(), FlightError> {
    let bad = |m: String| Err(FlightError::BadOption(m));
    if args.budgets.is_empty() || args.budgets.contains(&0) {
        return bad("--budgets must list positive triangle counts".into());
    }
    if args.max_errors_px.is_empty()
        || args
            .max_errors_px
            .iter()
            .any(|e| !(e.is_finite() && *e > 0.0))
    {
        return bad("--max-errors-px must list positive pixel errors".into());
    }
    if args.variants.methods.is_empty() || args.variants.fillers.is_empty() {
        return bad("--methods and --fillers must not be empty".into());
    }
    let side = crate::flight::MAX_GRID_SIDE;
    if args.grids.is_empty()
        || args
            .grids
            .iter()
            .any(|&(c, r)| !(2..=side).contains(&c) || !(2..=side).contains(&r))
    {
        return bad(format!(
            "--grids must list sizes of 2 to {side} vertices a side, COLUMNSxROWS"
        ));
    }
    if args.cameras == 0 {
        return bad("--cameras must be at least 1".into());
    }
    Ok(())
}

/// Every configuration of `args`: per method, per filler when it uses one, per setting of
/// the method's knob.
pub fn configs(args: &AccuracyArgs) -> Vec<Config> {
    let mut out = Vec::new();
    for (method, filler) in args.variants.list() {
        for knob in knobs(method, args) {
            out.push(Config {
                method,
                filler,
                knob,
            });
        }
    }
    out
}

/// `frames` cameras from `start` along its view direction towards the point where it meets
/// the plane at height `ground_m`, the distance to that point shrinking by the same factor
/// every frame, `2^halvings` over the flight, with the heading and pitch of `start`. A
/// camera level with or above the horizon, or under the plane, approaches a point a
/// kilometre ahead instead.
pub fn approach_flight(start: &Camera, ground_m: f64, frames: u32, halvings: f64) -> Vec<Camera> {
    let dir = start.direction();
    let height = start.position[2] - ground_m;
    let distance = if dir.z < -1e-3 && height > 0.0 {
        height / -dir.z
    } else {
        1000.0
    };
    let last = f64::from(frames.max(2) - 1);
    (0..frames)
        .map(|i| {
            let travelled = distance * (1.0 - (-halvings * f64::from(i) / last).exp2());
            let p = glam::DVec3::from(start.position) + dir * travelled;
            Camera {
                position: p.to_array(),
                ..*start
            }
        })
        .collect()
}

/// `count` cameras at even times along `path` (its final hold left out), heading along it.
pub fn cameras_along(path: &CameraPath, count: u32, pitch_deg: f64) -> Vec<Camera> {
    let moving = path
        .keyframes()
        .windows(2)
        .rev()
        .find(|k| k[0].x != k[1].x || k[0].y != k[1].y || k[0].z != k[1].z)
        .map_or(path.duration_s(), |k| k[1].t);
    let mut yaw = 0.0;
    (0..count)
        .map(|i| {
            let t = moving * (f64::from(i) + 0.5) / f64::from(count);
            yaw = heading(path, t, yaw);
            Camera::new(path.position_at(t), yaw, pitch_deg.to_radians())
        })
        .collect()
}

/// Per threshold of `thresholds_px`, the fewest triangles a right-triangulated irregular
/// network of the full-resolution data needs for `camera`'s frame to keep every sample
/// within it on screen (the least of that family, not of every mesh): per level-0 tile in view (by its
/// bounding box, as the methods cull), the smallest right-triangulated irregular network
/// within the threshold ([`super::oracle`]), each sample's vertical error projected by the
/// bound the methods use ([`crate::lod::needed::ErrorProjection`]) at that sample. With
/// `on_screen`, a sample none of whose cells is in view ([`on_screen::samples_in_view`]) is free: the
/// oracle culls inside a tile as finely as any method can. Tiles not resident count
/// nothing.
pub fn oracle_triangles(
    scene: &crate::scene::Scene,
    camera: &Camera,
    viewport: [u32; 2],
    thresholds_px: &[f64],
    on_screen: bool,
) -> Vec<u64> {
    let projection = crate::lod::plan::error_projection(camera, viewport);
    let frustum = camera.frustum(f64::from(viewport[0]) / f64::from(viewport[1].max(1)));
    let eye = glam::DVec3::from(camera.position);
    let mut totals = vec![0; thresholds_px.len()];
    for_full_resolution_tiles_in_view(scene, camera, viewport, |[x0, y0], spacing, samples, n| {
        let in_view = on_screen
            .then(|| on_screen::samples_in_view(&frustum, eye, [x0, y0], spacing, samples, n));
        for (total, &threshold_px) in totals.iter_mut().zip(thresholds_px) {
            let ppm = |c: u32, r: u32| {
                if in_view.as_ref().is_some_and(|v| !v[(r * n + c) as usize]) {
                    return 0.0;
                }
                at_sample(
                    &projection,
                    [x0, y0],
                    spacing,
                    samples,
                    n,
                    (c, r),
                    threshold_px,
                )
            };
            *total += super::oracle::rtin_triangles(samples, n, ppm, threshold_px);
        }
    });
    totals
}

/// The oracle's pixels per metre of vertical error at sample `(c, r)` of a level-0 tile of
/// `n x n` `samples` whose corner is at `origin` ([`ErrorProjection::pixels_per_metre`] at
/// the sample itself).
///
/// [`ErrorProjection::pixels_per_metre`]: crate::lod::needed::ErrorProjection::pixels_per_metre
pub(super) fn at_sample(
    projection: &crate::lod::needed::ErrorProjection,
    [x0, y0]: [f64; 2],
    spacing: [f64; 2],
    samples: &[f32],
    n: u32,
    (c, r): (u32, u32),
    threshold_px: f64,
) -> f64 {
    let p = [
        x0 + f64::from(c) * spacing[0],
        y0 + f64::from(r) * spacing[1],
        f64::from(samples[(r * n + c) as usize]),
    ];
    projection.pixels_per_metre(p, p, threshold_px)
}

/// Calls `each(origin_m, spacing_m, samples_m, n)` for every resident level-0 tile in
/// `camera`'s view (by its bounding box, as the methods cull), its heights decoded once.
fn for_full_resolution_tiles_in_view(
    scene: &crate::scene::Scene,
    camera: &Camera,
    viewport: [u32; 2],
    mut each: impl FnMut([f64; 2], [f64; 2], &[f32], u32),
) {
    let manifest = scene.manifest();
    let layout = crate::render::layout::Layout::of(manifest);
    let frustum = camera.frustum(f64::from(viewport[0]) / f64::from(viewport[1].max(1)));
    let eye = glam::DVec3::from(camera.position);
    let extent = layout.tile_extent_m_at(0);
    let spacing = layout.spacing_at(0);
    for (id, record) in manifest.tiles().filter(|(id, _)| id.level == 0) {
        let [x0, y0] = layout.tile_origin_m(id);
        let lo = Camera::to_render(glam::DVec3::new(x0, y0, f64::from(record.min_m)) - eye);
        let hi = Camera::to_render(
            glam::DVec3::new(x0 + extent[0], y0 + extent[1], f64::from(record.max_m)) - eye,
        );
        if !frustum.intersects_box(lo.min(hi), lo.max(hi)) {
            continue;
        }
        let Some(heights) = scene.tile_heights(id) else {
            continue;
        };
        each(
            [x0, y0],
            spacing,
            &heights.to_metres_f32(),
            u32::from(heights.width),
        );
    }
}

/// Means over the cameras, per configuration, with its popping where measured and the
/// oracle's count at its threshold (`threshold_px` for the budgeted methods).
pub fn summarise(
    rows: &[Row],
    configs: &[Config],
    popping: &[(Config, Popping)],
    oracle: &[Vec<(f64, u64)>],
    threshold_px: f64,
) -> Vec<Summary> {
    configs
        .iter()
        .filter_map(|config| {
            let of: Vec<&Measured> = rows
                .iter()
                .filter(|r| r.config == *config)
                .map(|r| &r.measured)
                .collect();
            if of.is_empty() {
                return None;
            }
            let n = of.len() as f64;
            let mean = |f: &dyn Fn(&Measured) -> f64| of.iter().map(|m| f(m)).sum::<f64>() / n;
            let threshold = config.threshold_px(threshold_px);
            let oracle_of = |camera: u32| {
                oracle
                    .get(camera as usize)
                    .and_then(|o| o.iter().find(|(t, _)| *t == threshold))
                    .map(|(_, n)| *n as f64)
            };
            let with_oracle: Vec<(f64, f64)> = rows
                .iter()
                .filter(|r| r.config == *config)
                .filter_map(|r| {
                    oracle_of(r.camera).map(|o| (o, r.measured.report.stats.triangles as f64))
                })
                .collect();
            let k = with_oracle.len().max(1) as f64;
            let oracle_sum = with_oracle.iter().map(|(o, _)| o).sum::<f64>();
            let oracle_triangles = oracle_sum / k;
            // A ratio of sums: a camera over flat sea needs almost nothing, and its ratio
            // alone would swamp a mean of ratios.
            let used_over_oracle =
                with_oracle.iter().map(|(_, used)| used).sum::<f64>() / oracle_sum.max(1.0);
            let mut frame: Vec<f64> = of.iter().map(|m| m.frame_ms).collect();
            let mut gpu: Vec<f64> = of.iter().filter_map(|m| m.gpu_ms).collect();
            let finite_psnr: Vec<f64> = of
                .iter()
                .map(|m| m.measures.psnr_db)
                .filter(|p| p.is_finite())
                .collect();
            Some(Summary {
                config: *config,
                triangles: mean(&|m| m.report.stats.triangles as f64),
                triangles_needed: mean(&|m| m.report.triangles_needed as f64),
                oracle_triangles,
                used_over_oracle,
                used_over_needed: mean(&|m| {
                    m.report.stats.triangles as f64 / (m.report.triangles_needed as f64).max(1.0)
                }),
                filler_triangles: mean(&|m| m.report.stats.filler_triangles as f64),
                draw_calls: mean(&|m| f64::from(m.report.stats.draw_calls)),
                mean_error_px: mean(&|m| m.measures.error.mean_px),
                p95_error_px: mean(&|m| m.measures.error.p95_px),
                p99_error_px: mean(&|m| m.measures.error.p99_px),
                max_error_px: of
                    .iter()
                    .map(|m| m.measures.error.max_px)
                    .fold(0.0, f64::max),
                above_threshold_pct: 100.0 * mean(&|m| m.measures.error.share_above()),
                crack_pixels: mean(&|m| m.measures.crack_pixels as f64),
                hole_pixels: mean(&|m| m.measures.hole_pixels as f64),
                silhouette_pixels: mean(&|m| m.measures.silhouette_pixels as f64),
                filler_pixels: mean(&|m| m.measures.filler_pixels as f64),
                leak_pixels: mean(&|m| m.measures.leak_pixels as f64),
                crack_pct: 100.0
                    * mean(&|m| {
                        m.measures.crack_pixels as f64
                            / (m.measures.reference_terrain_pixels as f64).max(1.0)
                    }),
                psnr_db: if finite_psnr.is_empty() {
                    f64::INFINITY
                } else {
                    finite_psnr.iter().sum::<f64>() / finite_psnr.len() as f64
                },
                frame_ms: median(&mut frame),
                cpu_ms: mean(&|m| m.report.lod_ms + m.report.stats.encode_ms),
                gpu_ms: (!gpu.is_empty()).then(|| median(&mut gpu)),
                held_bytes: mean(&|m| m.held_bytes as f64),
                popping: popping.iter().find(|(c, _)| c == config).map(|(_, p)| *p),
                error_pixels_pct: mean_measure(&of, "error_pixels_pct"),
                ray_cast_pct: mean_measure(&of, "ray_cast_pct"),
            })
        })
        .collect()
}

/// The mean over `of` of method measure `name`, when every frame reported it.
fn mean_measure(of: &[&Measured], name: &str) -> Option<f64> {
    let values: Option<Vec<f64>> = of.iter().map(|m| m.method_measure(name)).collect();
    values
        .filter(|v| !v.is_empty())
        .map(|v| v.iter().sum::<f64>() / v.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pareto_front_keeps_the_points_nothing_beats_on_both_axes() {
        let points = [
            (10.0, 5.0),
            (20.0, 2.0),
            (15.0, 6.0), // beaten by (10, 5)
            (30.0, 2.0), // as good as (20, 2) on error, dearer
            (40.0, 0.5),
            (5.0, f64::NAN),
        ];
        assert_eq!(
            pareto_front(&points),
            [(10.0, 5.0), (20.0, 2.0), (40.0, 0.5)]
        );
        assert!(pareto_front(&[]).is_empty());
    }
}
