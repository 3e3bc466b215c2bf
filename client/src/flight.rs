//! A headless flight: the camera follows a path while the belt pager keeps the largest
//! square of complete belts that fits the memory limit, the fetcher streams tiles, the
//! renderer draws every frame offscreen, and every frame is recorded.
//!
//! Each frame is a [`Scene::update`] (deliveries, paging, texture budget) and a
//! [`Scene::draw`] (culling, importance, triangle budget, masks, render). The path's clock
//! advances `1 / --fps` per frame, whatever the frame took, so every run flies the same
//! frames; how long a frame took is measured and drives the frame-rate controller. Without
//! rendering (`--no-render`) frames are paced at `--fps` in wall-clock time.
//!
//! Outputs (`--out`): `flight.csv` (one row per frame, columns in [`CSV_HEADER`]),
//! `flight.png` (memory, tiles, belts, download rate), `render.png` (target and obtained
//! frame rate, triangles per frame: the top panels of the strip-mask paper's Figures 6 and
//! 7), `frames/frame-NNNNNN.png` every `--frame-every` frames, and a summary on stdout.

use crate::fetch::FetchError;
use crate::fetcher::FetcherConfig;
use crate::lod::budget::{BudgetMode, DEFAULT_TARGET_FPS};
use crate::lod::importance::{DEFAULT_ALPHA, HeightMeasure};
use crate::lod::plan::{DEFAULT_MAX_ERROR_PX, LodSettings};
use crate::memory::{MemoryBudget, MemoryError, MemorySize};
use crate::method::CrackFiller;
use crate::method::MethodKind;
use crate::output::Output;
use crate::path::{CameraPath, PathError};
use crate::render::{Camera, Gpu, GpuError, Offscreen};
use crate::scene::{Reconciled, RenderConfig, Scene, SceneError};
use std::fmt;
use std::io::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use terrain_shared::Manifest;
use thiserror::Error;

pub use crate::scene::expected_tile_bytes;

/// Frames per second of the flight's clock.
pub const DEFAULT_FPS: f64 = 30.0;

/// Where the tiles come from and how much of them to hold: shared by `fly` and `view`.
#[derive(Debug, Clone, clap::Args)]
pub struct StreamArgs {
    /// Base URL of the tile server, e.g. http://127.0.0.1:8080.
    #[arg(long, env = "TERRAIN_SERVER")]
    pub server: String,
    /// Memory budget for tiles (heights, textures, GPU buffers), e.g. 64MiB. Default: the
    /// machine's available memory.
    #[arg(long)]
    pub memory: Option<MemorySize>,
    /// Share of the budget the pager fills, in percent (the rest is the margin for the belt
    /// being fetched).
    #[arg(long, default_value_t = crate::memory::DEFAULT_LIMIT_PERCENT)]
    pub limit_percent: f64,
    /// HTTP requests at once.
    #[arg(long, default_value_t = crate::fetcher::DEFAULT_CONCURRENCY)]
    pub concurrency: usize,
    /// Page and draw level 0 of the pyramid alone: the single-resolution client of the
    /// strip-mask paper (what a database of one level gives anyway).
    #[arg(long)]
    pub single_level: bool,
    /// How the levels of the pyramid share the memory limit.
    #[arg(long, value_enum, default_value_t = crate::page::LevelPolicy::Equal)]
    pub level_policy: crate::page::LevelPolicy,
}

impl StreamArgs {
    /// Options for `server` with the defaults of the command line.
    pub fn new(server: impl Into<String>, memory: Option<MemorySize>) -> StreamArgs {
        StreamArgs {
            server: server.into(),
            memory,
            limit_percent: crate::memory::DEFAULT_LIMIT_PERCENT,
            concurrency: crate::fetcher::DEFAULT_CONCURRENCY,
            single_level: false,
            level_policy: crate::page::LevelPolicy::Equal,
        }
    }

    /// Pages `scene` as these options say: every level or level 0 alone, and the policy
    /// that shares the limit between levels.
    pub fn configure(&self, scene: &mut Scene) {
        scene.use_levels(!self.single_level);
        scene.set_level_policy(self.level_policy);
    }

    /// The memory budget, once the options are checked.
    pub fn budget(&self) -> Result<MemoryBudget, FlightError> {
        if self.concurrency == 0 {
            return Err(FlightError::BadOption(
                "--concurrency must be at least 1".into(),
            ));
        }
        Ok(MemoryBudget::new(self.memory, self.limit_percent)?)
    }

    /// The fetcher's configuration.
    pub fn fetcher_config(&self) -> FetcherConfig {
        FetcherConfig {
            concurrency: self.concurrency,
            ..FetcherConfig::default()
        }
    }
}

/// `terrain-client fly`.
#[derive(Debug, Clone, clap::Args)]
pub struct FlightArgs {
    #[command(flatten)]
    pub stream: StreamArgs,
    /// Camera path: a .json or .csv file of keyframes (see docs/flight.md). Default: a lap
    /// over the whole terrain, then a few seconds still.
    #[arg(long)]
    pub flight: Option<PathBuf>,
    /// Directory for flight.csv, the charts and the frames; created if missing.
    #[arg(long, default_value = "out/flight")]
    pub out: PathBuf,
    /// Frames per second of the flight's clock: each frame advances the path by 1/fps s.
    #[arg(long, default_value_t = DEFAULT_FPS)]
    pub fps: f64,
    /// Do not make the nearest tile current when the viewpoint is off the terrain (for
    /// terrains placed side by side).
    #[arg(long)]
    pub no_nearest_when_outside: bool,
    /// No progress bar.
    #[arg(long, short)]
    pub quiet: bool,
    /// Page and stream only: no GPU, no frames.
    #[arg(long)]
    pub no_render: bool,
    /// Write every Nth frame to OUT/frames as PNG (0: none). The last frame is always written.
    #[arg(long, default_value_t = 30)]
    pub frame_every: u64,
    #[command(flatten)]
    pub render: RenderArgs,
}

impl FlightArgs {
    /// The default flight against `stream`'s server, writing to `out`.
    pub fn new(stream: StreamArgs, out: impl Into<PathBuf>) -> FlightArgs {
        FlightArgs {
            stream,
            flight: None,
            out: out.into(),
            fps: DEFAULT_FPS,
            no_nearest_when_outside: false,
            quiet: true,
            no_render: false,
            frame_every: 30,
            render: RenderArgs::default(),
        }
    }
}

/// How frames are rendered: shared by `fly` and `view`.
#[derive(Debug, Clone, clap::Args)]
pub struct RenderArgs {
    /// Level-of-detail method.
    #[arg(long, value_enum, default_value_t)]
    pub method: MethodKind,
    /// Frame size, WIDTHxHEIGHT.
    #[arg(long, default_value = "960x540", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Frame rate the triangle budget is predicted to hold.
    #[arg(long, default_value_t = DEFAULT_TARGET_FPS)]
    pub target_fps: f64,
    /// A fixed global triangle budget instead of the frame-rate controller (benchmarks).
    #[arg(long)]
    pub fixed_budget: Option<u32>,
    /// How cracks between tiles of different levels are filled.
    #[arg(long, value_enum, default_value_t)]
    pub crack_filler: CrackFiller,
    /// Weight of distance in a tile's importance; its height gets 1 - alpha.
    #[arg(long, default_value_t = DEFAULT_ALPHA)]
    pub alpha: f64,
    /// Height term of the importance: the bounding box's height or the manifest's roughness.
    #[arg(long, value_enum, default_value_t)]
    pub height_measure: HeightMeasure,
    /// Camera pitch, degrees above the horizon (negative looks down).
    #[arg(long, default_value_t = crate::render::camera::DEFAULT_PITCH_DEG, allow_negative_numbers = true)]
    pub pitch_deg: f64,
    /// Draw only the square of complete belts, as the strip-mask paper does. By default
    /// every resident tile is drawn: cached tiles outside the square and those of a belt
    /// still arriving show more of the terrain.
    #[arg(long)]
    pub draw_square_only: bool,
    #[command(flatten)]
    pub error: ErrorCapArgs,
    #[command(flatten)]
    pub grid: GridArgs,
}

/// The projected grids' options (`--method pgm`, `--method projective-grid`): shared by
/// `fly`, `view` and `bench stability`.
#[derive(Debug, Clone, Copy, PartialEq, clap::Args)]
pub struct GridArgs {
    /// The projected grids' size, COLUMNSxROWS vertices: 2 (COLUMNS - 1) (ROWS - 1)
    /// triangles every frame.
    #[arg(long, default_value = "256x144", value_parser = parse_size)]
    pub grid: (u32, u32),
    /// Keep the projective grid uniform instead of warping it to square cells on the ground
    /// (Löffler et al.'s comparison with persistent grid mapping).
    #[arg(long)]
    pub uniform_grid: bool,
    /// Draw the projective grid without casting rays where it passes the error threshold.
    #[arg(long)]
    pub no_ray_casting: bool,
}

impl Default for GridArgs {
    fn default() -> GridArgs {
        let d = crate::method::GridSettings::default();
        GridArgs {
            grid: (d.size[0], d.size[1]),
            uniform_grid: !d.warp,
            no_ray_casting: !d.ray_casting,
        }
    }
}

/// Most vertices a side of a projected grid takes.
pub const MAX_GRID_SIDE: u32 = 4096;

impl GridArgs {
    /// The grid settings, once checked.
    pub fn settings(&self) -> Result<crate::method::GridSettings, FlightError> {
        let (columns, rows) = self.grid;
        if !(2..=MAX_GRID_SIDE).contains(&columns) || !(2..=MAX_GRID_SIDE).contains(&rows) {
            return Err(FlightError::BadOption(format!(
                "--grid {columns}x{rows}: each side must be 2 to {MAX_GRID_SIDE} vertices"
            )));
        }
        Ok(crate::method::GridSettings {
            size: [columns, rows],
            warp: !self.uniform_grid,
            ray_casting: !self.no_ray_casting,
        })
    }
}

/// The screen-space error threshold and the error cap: shared by `fly`, `view` and
/// `bench accuracy`.
#[derive(Debug, Clone, Copy, PartialEq, clap::Args)]
pub struct ErrorCapArgs {
    /// Screen-space error threshold, pixels: no tile is drawn finer than the coarsest mask
    /// whose projected error is within it (GeoMipMaps choose their level by it too), and
    /// `triangles_needed` counts those masks.
    #[arg(long, default_value_t = DEFAULT_MAX_ERROR_PX)]
    pub max_error_px: f64,
    /// Let tiles take finer masks than the error threshold needs when the budget allows
    /// (the paper's plain budget sharing).
    #[arg(long)]
    pub no_error_cap: bool,
    /// Quadtree patches: switch levels at once instead of geomorphing (and blending
    /// textures) between them.
    #[arg(long)]
    pub no_morph: bool,
}

impl Default for ErrorCapArgs {
    fn default() -> ErrorCapArgs {
        ErrorCapArgs {
            max_error_px: DEFAULT_MAX_ERROR_PX,
            no_error_cap: false,
            no_morph: false,
        }
    }
}

impl ErrorCapArgs {
    /// The level-of-detail settings with these options, once checked.
    pub fn lod(&self, alpha: f64, height: HeightMeasure) -> Result<LodSettings, FlightError> {
        if !(self.max_error_px.is_finite() && self.max_error_px > 0.0) {
            return Err(FlightError::BadOption(format!(
                "--max-error-px {} must be positive",
                self.max_error_px
            )));
        }
        Ok(LodSettings {
            alpha,
            height,
            max_error_px: self.max_error_px,
            cap_at_needed: !self.no_error_cap,
            geomorph: !self.no_morph,
        })
    }
}

impl Default for RenderArgs {
    fn default() -> RenderArgs {
        RenderArgs {
            method: MethodKind::default(),
            size: (960, 540),
            target_fps: DEFAULT_TARGET_FPS,
            fixed_budget: None,
            crack_filler: CrackFiller::default(),
            alpha: DEFAULT_ALPHA,
            height_measure: HeightMeasure::default(),
            pitch_deg: crate::render::camera::DEFAULT_PITCH_DEG,
            draw_square_only: false,
            error: ErrorCapArgs::default(),
            grid: GridArgs::default(),
        }
    }
}

impl RenderArgs {
    /// The scene's render configuration.
    pub fn config(&self) -> Result<RenderConfig, FlightError> {
        if !(0.0..=1.0).contains(&self.alpha) {
            return Err(FlightError::BadOption(format!(
                "--alpha {} must be in [0, 1]",
                self.alpha
            )));
        }
        if !(self.target_fps.is_finite() && self.target_fps > 0.0) {
            return Err(FlightError::BadOption(format!(
                "--target-fps {} must be positive",
                self.target_fps
            )));
        }
        let budget = match self.fixed_budget {
            Some(b) => BudgetMode::Fixed(b),
            None => match BudgetMode::default() {
                BudgetMode::Adaptive {
                    initial_budget,
                    min_budget,
                    max_budget,
                    ..
                } => BudgetMode::Adaptive {
                    target_fps: self.target_fps,
                    initial_budget,
                    min_budget,
                    max_budget,
                },
                fixed => fixed,
            },
        };
        Ok(RenderConfig {
            method: self.method,
            lod: self.error.lod(self.alpha, self.height_measure)?,
            filler: self.crack_filler,
            budget,
            square_only: self.draw_square_only,
            grid: self.grid.settings()?,
            ..RenderConfig::default()
        })
    }
}

/// Parses `WIDTHxHEIGHT`.
pub fn parse_size(text: &str) -> Result<(u32, u32), String> {
    let (w, h) = text
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("{text:?}: expected WIDTHxHEIGHT, e.g. 960x540"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .ok()
            .filter(|&n| (16..=8192).contains(&n))
            .ok_or_else(|| format!("{text:?}: each side must be a whole number from 16 to 8192"))
    };
    Ok((parse(w)?, parse(h)?))
}

impl From<crate::output::OutputError> for FlightError {
    fn from(error: crate::output::OutputError) -> FlightError {
        FlightError::Write {
            path: error.path,
            source: error.source,
        }
    }
}

/// The fewest bytes a row of flight.csv takes (a frame without rendering, small numbers):
/// `frames` times this is reserved on disk when the flight starts.
const CSV_ROW_LEAST_BYTES: u64 = 64;
/// At most this much is reserved for flight.csv up front; past it a full disk is found as
/// the rows are written.
const CSV_RESERVE_MAX: u64 = 64 << 20;

/// Why a flight stopped.
#[derive(Debug, Error)]
pub enum FlightError {
    #[error(transparent)]
    Fetch(#[from] FetchError),
    #[error(transparent)]
    Path(#[from] PathError),
    #[error(transparent)]
    Memory(#[from] MemoryError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error(transparent)]
    Scene(#[from] crate::scene::SceneError),
    #[error("cannot write {path}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    /// An output the disk refused while flying: the flight stops there, and what it would
    /// have written is removed, not left cut short.
    #[error(
        "cannot write {path} at frame {frame} of {frames}: the flight stopped there and left no output cut short"
    )]
    WriteWhileFlying {
        path: PathBuf,
        frame: u64,
        frames: u64,
        source: std::io::Error,
    },
    #[error("cannot write {path}: {message}")]
    Image { path: PathBuf, message: String },
    #[error(transparent)]
    Chart(#[from] crate::charts::ChartError),
    #[error("invalid option: {0}")]
    BadOption(String),
    /// Not one tile arrived: a flight of empty frames is no result.
    #[error(
        "no tile arrived in {wall_s:.1} s of flight ({requests} HTTP requests, {failures} failed, \
         {cancelled} cancelled before they landed{last}); flight.csv and the charts in {} \
         show the frames",
        out.display(),
        last = last_failure.as_ref().map(|e| format!("; last failure: {e}")).unwrap_or_default()
    )]
    NothingLoaded {
        wall_s: f64,
        requests: u64,
        failures: u64,
        cancelled: u64,
        last_failure: Option<String>,
        out: PathBuf,
    },
}

pub use crate::record::{CSV_HEADER, FrameRecord, RenderRecord, windowed_fps};

/// How the frame rate held its target, over the frames after the first second.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameRateSummary {
    pub target_fps: Option<f64>,
    /// Frames after the first second of wall-clock time.
    pub frames: u64,
    /// Median over them of the frame rate over the last second ([`windowed_fps`]): with two
    /// frames in flight, one frame's own time is not its cost.
    pub median_fps: f64,
    /// Share of them at which the frame rate over the last second ([`windowed_fps`]) is
    /// within 10% of the target (`None` without a target).
    pub windowed_within_10_percent: Option<f64>,
    /// Lowest and highest frame rate over the last second, after the first second.
    pub windowed_range: (f64, f64),
    /// The frame-rate controller's prediction error ([`prediction_errors`]): median and
    /// 90th percentile, as fractions; `None` without a target.
    pub prediction_error: Option<(f64, f64)>,
    /// Triangles drawn per second of frame time, whole flight.
    pub triangles_per_s: f64,
    pub mean_triangles: f64,
}

impl FrameRateSummary {
    /// From a flight's records; `None` when nothing was rendered after the first second.
    pub fn of(records: &[FrameRecord]) -> Option<FrameRateSummary> {
        let rendered: Vec<&RenderRecord> =
            records.iter().filter_map(|r| r.render.as_ref()).collect();
        let settled: Vec<&RenderRecord> = records
            .iter()
            .filter(|r| r.wall_s >= 1.0)
            .filter_map(|r| r.render.as_ref())
            .collect();
        if settled.is_empty() {
            return None;
        }
        let target = settled[0].target_fps;
        let windows = windowed_fps(records);
        let mut fps: Vec<f64> = windows.iter().map(|&(_, f)| f).collect();
        fps.sort_by(f64::total_cmp);
        let windowed_within = target.map(|t| {
            windows
                .iter()
                .filter(|(_, f)| (f - t).abs() <= 0.1 * t)
                .count() as f64
                / windows.len().max(1) as f64
        });
        let windowed_range = windows.iter().fold((f64::MAX, 0.0f64), |(lo, hi), (_, f)| {
            (lo.min(*f), hi.max(*f))
        });
        let mut errors = prediction_errors(records);
        errors.sort_by(f64::total_cmp);
        let prediction_error = (target.is_some() && !errors.is_empty()).then(|| {
            (
                errors[errors.len() / 2],
                errors[(errors.len() * 9 / 10).min(errors.len() - 1)],
            )
        });
        let triangles: u64 = rendered
            .iter()
            .map(|r| r.triangles + r.filler_triangles)
            .sum();
        let seconds: f64 = rendered.iter().map(|r| r.frame_ms).sum::<f64>() / 1e3;
        Some(FrameRateSummary {
            target_fps: target,
            frames: settled.len() as u64,
            median_fps: fps.get(fps.len() / 2).copied().unwrap_or(0.0),
            windowed_within_10_percent: windowed_within,
            windowed_range,
            prediction_error,
            triangles_per_s: triangles as f64 / seconds.max(1e-9),
            mean_triangles: rendered.iter().map(|r| r.triangles as f64).sum::<f64>()
                / rendered.len() as f64,
        })
    }
}

/// The frame-rate controller's relative error, `|predicted - measured| / measured`, over
/// each run of [`crate::render::frame::FRAMES_IN_FLIGHT`] consecutive frames after the first
/// second that all carry a prediction: the controller measures frames in such runs (a
/// frame's own time with frames in flight is not its cost), so its prediction is judged on
/// them too.
pub fn prediction_errors(records: &[FrameRecord]) -> Vec<f64> {
    let run = crate::render::frame::FRAMES_IN_FLIGHT as usize;
    let pairs: Vec<(f64, f64)> = records
        .iter()
        .filter(|r| r.wall_s >= 1.0)
        .filter_map(|r| r.render.as_ref())
        .filter_map(|r| r.predicted_ms.map(|p| (p, r.frame_ms)))
        .collect();
    pairs
        .chunks_exact(run)
        .filter_map(|c| {
            let predicted: f64 = c.iter().map(|p| p.0).sum();
            let measured: f64 = c.iter().map(|p| p.1).sum();
            (measured > 0.0).then(|| (predicted - measured).abs() / measured)
        })
        .collect()
}

/// What the flight ended with.
#[derive(Debug, Clone)]
pub struct FlightSummary {
    pub dataset: String,
    pub frames: u64,
    pub duration_s: f64,
    pub wall_s: f64,
    pub memory_limit_bytes: u64,
    pub peak_resident_bytes: u64,
    /// Largest overshoot of the limit at a frame's end, in bytes (0 if never over).
    pub peak_overshoot_bytes: u64,
    /// Frames at whose end the resident bytes were over the limit.
    pub frames_over_limit: u64,
    pub final_complete_belts: u32,
    pub tiles_fetched: u64,
    pub bytes_downloaded: u64,
    pub evicted_unused_bytes: u64,
    /// Request attempts repeated: after transient failures, corrupt bodies, and tiles
    /// asked for again after a failed request.
    pub retries: u64,
    pub failures: u64,
    /// Tiles given up after repeated failures, with the last failure of each.
    pub unavailable: Vec<crate::scene::UnavailableTile>,
    /// Times the server's content changed under the flight (its database was rebuilt), and
    /// what that did to the resident tiles.
    pub content_changes: Vec<ContentChange>,
    /// Peak resident set size of this process (VmHWM), when the OS reports it.
    pub peak_rss_bytes: Option<u64>,
    /// The program's heap at its peak ([`crate::process::peak_heap_bytes`]).
    pub peak_heap_bytes: u64,
    /// wgpu's allocator report at the frame with the most GPU memory allocated; `None`
    /// without rendering or where the backend gives none.
    pub peak_gpu: Option<crate::process::GpuReport>,
    /// Why no target frame rate applies, when one was asked for and the method shares no
    /// triangle budget.
    pub no_target: Option<String>,
    /// The adapter, when the flight rendered.
    pub adapter: Option<String>,
    pub frame_rate: Option<FrameRateSummary>,
    /// Frame PNGs written.
    pub frames_written: Vec<PathBuf>,
    pub csv: PathBuf,
    pub charts: Vec<PathBuf>,
}

impl fmt::Display for FlightSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
        writeln!(
            f,
            "flew {} frames ({:.1} s of flight in {:.1} s) over {}",
            self.frames, self.duration_s, self.wall_s, self.dataset
        )?;
        let over = if self.frames_over_limit == 0 {
            "never over it".to_string()
        } else {
            format!(
                "OVER it at the end of {} of {} frames, by {} bytes at most",
                self.frames_over_limit, self.frames, self.peak_overshoot_bytes
            )
        };
        writeln!(
            f,
            "  memory    peak {:.2} MiB ({} bytes) of terrain against a limit of {:.2} MiB ({} bytes): {over}",
            mib(self.peak_resident_bytes),
            self.peak_resident_bytes,
            mib(self.memory_limit_bytes),
            self.memory_limit_bytes,
        )?;
        writeln!(
            f,
            "  square    {} complete belts at the end",
            self.final_complete_belts
        )?;
        writeln!(
            f,
            "  network   {} tiles, {:.2} MiB downloaded ({:.2} MiB evicted before use), {} retries, {} failures",
            self.tiles_fetched,
            mib(self.bytes_downloaded),
            mib(self.evicted_unused_bytes),
            self.retries,
            self.failures
        )?;
        for change in &self.content_changes {
            writeln!(f, "  content   {change}")?;
        }
        for tile in &self.unavailable {
            writeln!(
                f,
                "  missing   tile {} given up after {} failed requests: {}",
                tile.id, tile.failures, tile.error
            )?;
        }
        if let Some(adapter) = &self.adapter {
            writeln!(f, "  adapter   {adapter}")?;
        }
        if let Some(r) = &self.frame_rate {
            write!(
                f,
                "  rendering median {:.1} fps after the first second, {:.0} triangles per frame, {:.2} M triangles/s",
                r.median_fps,
                r.mean_triangles,
                r.triangles_per_s / 1e6
            )?;
            match (r.target_fps, r.windowed_within_10_percent) {
                (Some(t), Some(ww)) => {
                    write!(
                        f,
                        "\n            target {t} fps: frame rate over the last second within 10% of it at {:.0}% of frames (range {:.0}-{:.0})",
                        100.0 * ww,
                        r.windowed_range.0,
                        r.windowed_range.1,
                    )?;
                    match r.prediction_error {
                        Some((median, p90)) => writeln!(
                            f,
                            "; predicted frame time off by {:.0}% (median), {:.0}% (90th percentile)",
                            100.0 * median,
                            100.0 * p90
                        )?,
                        None => writeln!(f)?,
                    }
                }
                _ => match &self.no_target {
                    Some(why) => writeln!(f, " ({why})")?,
                    None => writeln!(f, " (fixed budget)")?,
                },
            }
        }
        write!(
            f,
            "  process   heap peak {:.1} MiB",
            mib(self.peak_heap_bytes)
        )?;
        if let Some(gpu) = self.peak_gpu {
            write!(
                f,
                "; GPU {:.1} MiB allocated at most, {:.1} MiB of it the terrain's (the rest: render targets, pipelines and per-frame buffers)",
                mib(gpu.allocated),
                mib(gpu.terrain)
            )?;
        }
        match self.peak_rss_bytes {
            Some(rss) => writeln!(f, "; RSS peak {:.1} MiB", mib(rss))?,
            None => writeln!(f)?,
        }
        write!(f, "  wrote     {}", self.csv.display())?;
        for chart in &self.charts {
            write!(f, ", {}", chart.display())?;
        }
        if let (Some(first), n) = (self.frames_written.first(), self.frames_written.len()) {
            write!(
                f,
                " and {n} frames in {}",
                first.parent().unwrap_or(first).display()
            )?;
        }
        writeln!(f)
    }
}

/// The server's content changed during a flight: a new content version.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ContentChange {
    pub frame: u64,
    pub from: String,
    pub to: String,
    /// Resident tiles kept (same hashes) and dropped; `None` when the grid changed shape
    /// and paging started again from nothing.
    pub kept_dropped: Option<(u64, u64)>,
}

impl fmt::Display for ContentChange {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "frame {}: content version {} replaced {}; ",
            self.frame, self.to, self.from
        )?;
        match self.kept_dropped {
            Some((kept, dropped)) => write!(
                f,
                "{kept} resident tiles kept (unchanged), {dropped} dropped"
            ),
            None => write!(f, "the grid changed shape, paging started again"),
        }
    }
}

/// The camera's heading along the path: towards where the path is in a second, or the last
/// heading when the path holds still.
pub fn heading(path: &CameraPath, time_s: f64, previous: f64) -> f64 {
    let a = path.position_at(time_s);
    let b = path.position_at(time_s + 1.0);
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    if dx.hypot(dy) < 1e-3 {
        previous
    } else {
        dy.atan2(dx)
    }
}

/// The least manifest cap a flight sets, whatever its budget.
pub const MANIFEST_FLOOR_BYTES: u64 = 1 << 20;

/// The most frames a flight flies: a day at 60 fps, whose records (about 200 bytes a
/// frame) stay near a gigabyte.
pub const MAX_FLIGHT_FRAMES: u64 = 5_184_000;

/// Flies `args`' path against its server. Must run inside a multi-threaded tokio runtime.
pub async fn fly(args: &FlightArgs) -> Result<FlightSummary, FlightError> {
    if !(args.fps.is_finite() && args.fps > 0.0 && args.fps <= 1000.0) {
        return Err(FlightError::BadOption(format!(
            "--fps {} must be in (0, 1000]",
            args.fps
        )));
    }
    let render_config = (!args.no_render)
        .then(|| args.render.config())
        .transpose()?;
    let budget = args.stream.budget()?;
    // A manifest the budget could not hold is refused as it arrives; below 1 MiB the
    // manifest is taken, so that a budget too small for the terrain is refused with the
    // least --memory that would do rather than for its manifest.
    let fetcher_config = crate::fetcher::FetcherConfig {
        max_manifest_bytes: budget
            .budget_bytes
            .clamp(MANIFEST_FLOOR_BYTES, crate::fetch::MAX_MANIFEST_BYTES),
        ..args.stream.fetcher_config()
    };
    let connection = Scene::connect(
        &args.stream.server,
        fetcher_config,
        tokio::runtime::Handle::current(),
    )
    .await?;
    let manifest = Arc::clone(&connection.manifest);
    if let Some(config) = &render_config {
        crate::method::check_database(config.method, &manifest).map_err(FlightError::BadOption)?;
    }
    let path = match &args.flight {
        Some(file) => CameraPath::load(file, &manifest)?,
        None => CameraPath::default_for(&manifest),
    };
    // Each frame keeps a record (flight.csv, the charts): a path whose frames would not fit
    // in memory is refused here, before anything is made or written.
    let frames = (path.duration_s() * args.fps).ceil() + 1.0;
    if frames > MAX_FLIGHT_FRAMES as f64 {
        return Err(FlightError::BadOption(format!(
            "the flight is {:.0} s long, {frames:.0} frames at --fps {}; at most {MAX_FLIGHT_FRAMES} frames are flown (each keeps a row of flight.csv): shorten the path or lower --fps",
            path.duration_s(),
            args.fps
        )));
    }
    let frames = frames as u64;
    let write_err = |path: &std::path::Path| {
        let path = path.to_path_buf();
        move |source| FlightError::Write { path, source }
    };
    let frames_dir = args.out.join("frames");
    let render = match render_config {
        Some(config) => {
            let gpu = Gpu::headless()?;
            let (w, h) = args.render.size;
            let target = Offscreen::new(&gpu, w, h);
            Some((gpu, target, config))
        }
        None => None,
    };

    let bar = if args.quiet {
        indicatif::ProgressBar::hidden()
    } else {
        indicatif::ProgressBar::new(frames)
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} flying [{elapsed_precise}] {wide_bar} {pos}/{len} frames {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );

    let (target, adapter) = match &render {
        Some((gpu, target, _)) => (Some(target), Some(gpu.description())),
        None => (None, None),
    };
    let scene_render = || {
        render.as_ref().map(|(gpu, _, config)| {
            (
                gpu.clone(),
                crate::render::offscreen::OFFSCREEN_FORMAT,
                *config,
            )
        })
    };
    let mut scene = connection.scene(
        budget.limit_bytes(),
        !args.no_nearest_when_outside,
        scene_render(),
    );
    args.stream.configure(&mut scene);
    let mut fetcher = connection.fetcher;
    let (w, h) = args.render.size;
    scene.set_viewport([w, h]);
    budget.check(scene.least_limit(), &what_needs(args))?;
    // Refused or not, nothing is written before here.
    std::fs::create_dir_all(&args.out).map_err(write_err(&args.out))?;
    if render.is_some() && args.frame_every > 0 {
        std::fs::create_dir_all(&frames_dir).map_err(write_err(&frames_dir))?;
    }
    // flight.csv is written as frames are flown, so a disk that fills is found while flying;
    // the least its rows take is reserved now, so a disk already too full is found at once.
    let csv_path = args.out.join("flight.csv");
    let mut csv = Output::create(
        &csv_path,
        (frames * CSV_ROW_LEAST_BYTES).min(CSV_RESERVE_MAX),
    )
    .map_err(|source| FlightError::WriteWhileFlying {
        path: csv_path.clone(),
        frame: 0,
        frames,
        source,
    })?;
    writeln!(csv, "{CSV_HEADER}").map_err(write_err(&csv_path))?;
    let mut content_changes = Vec::new();
    let mut last_failure = None;
    // A failure that stops the flight; the frames flown so far are still written.
    let mut stopped: Option<FlightError> = None;
    let started = Instant::now();
    let mut ticker = tokio::time::interval(Duration::from_secs_f64(1.0 / args.fps));
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // Grown as frames are flown, not reserved for the whole path up front.
    let mut records = Vec::new();
    let mut frames_written = Vec::new();
    let centre = [manifest.extent_m[0] / 2.0, manifest.extent_m[1] / 2.0];
    let start = path.position_at(0.0);
    let mut yaw = (centre[1] - start[1]).atan2(centre[0] - start[0]);
    // Frames follow each other without a pause (no vsync offscreen): a frame's cost, as the
    // frame-rate controller measures it, runs from the end of the one before it's draw, so
    // that the bookkeeping between draws (the CSV row, a frame PNG) is counted too.
    let mut previous_draw_end: Option<Instant> = None;
    for frame in 0..frames {
        if target.is_some() {
            // Rendering sets the pace; let the runtime's tasks run between frames.
            tokio::task::yield_now().await;
        } else {
            ticker.tick().await;
        }
        let update_started = Instant::now();
        let frame_started = previous_draw_end.unwrap_or(update_started);
        let time_s = frame as f64 / args.fps;
        let position = path.position_at(time_s);
        let update = match scene.update(&mut fetcher, frame, position) {
            Ok(update) => update,
            Err(SceneError::TileFailed { id, message }) => {
                // A tile refused (404) is what a client sees when the server's database
                // was rebuilt: its URLs name the old content version. The manifest says
                // whether that is so.
                last_failure = Some(message.clone());
                match reload_content(&mut scene, &mut fetcher, frame).await {
                    Ok(Some((change, reshaped))) => {
                        if let Some(manifest) = reshaped {
                            let pager = crate::page::PagerConfig {
                                columns: manifest.grid(0).columns,
                                rows: manifest.grid(0).rows,
                                memory_limit: budget.limit_bytes(),
                                nearest_when_outside: !args.no_nearest_when_outside,
                                current_over_limit: false,
                            };
                            scene = Scene::new(manifest, pager, scene_render());
                            args.stream.configure(&mut scene);
                            scene.set_viewport([w, h]);
                        }
                        content_changes.push(change);
                        match scene.update(&mut fetcher, frame, position) {
                            Ok(update) => update,
                            Err(error) => {
                                stopped = Some(error.into());
                                break;
                            }
                        }
                    }
                    Ok(None) => {
                        stopped = Some(SceneError::TileFailed { id, message }.into());
                        break;
                    }
                    Err(error) => {
                        stopped = Some(error.into());
                        break;
                    }
                }
            }
        };
        let update_ms = update_started.elapsed().as_secs_f64() * 1e3;
        yaw = heading(&path, time_s, yaw);
        let camera = Camera::new(position, yaw, args.render.pitch_deg.to_radians());
        let drawn = target.and_then(|t| scene.draw(&t.view, &camera, frame_started));
        previous_draw_end = Some(Instant::now());
        let render_record = drawn.map(|d| RenderRecord {
            visible_tiles: d.plan.draws.len() as u32,
            triangles: d.stats.triangles,
            triangles_needed: d.triangles_needed,
            filler_triangles: d.stats.filler_triangles,
            draw_calls: d.stats.draw_calls,
            global_budget: d.plan.budget,
            mask_levels: d.plan.level_histogram(),
            lod_ms: d.lod_ms,
            cpu_ms: update_ms + d.lod_ms + d.stats.encode_ms,
            gpu_ms: d.stats.gpu_ms,
            frame_ms: d.frame_ms,
            predicted_ms: d.predicted_ms,
            target_fps: d.target_fps,
        });
        if let (Some(t), Some((gpu, _, _))) = (target, &render)
            && args.frame_every > 0
            && (frame % args.frame_every == 0 || frame + 1 == frames)
        {
            let file = frames_dir.join(format!("frame-{frame:06}.png"));
            let image = t.read(gpu)?;
            crate::output::write_via(&file, |temp| {
                image.save(temp).map_err(|e| FlightError::Image {
                    path: file.clone(),
                    message: e.to_string(),
                })
            })?;
            frames_written.push(file);
        }
        let stats = fetcher.stats();
        let record = FrameRecord {
            frame,
            time_s,
            wall_s: started.elapsed().as_secs_f64(),
            position_m: position,
            ground_m: scene.ground_under(position),
            current: [update.decision.current.x, update.decision.current.y],
            farthest_complete_belt: update.decision.farthest_complete_belt,
            complete_belts: update.decision.complete_belts,
            resident_tiles: scene.resident_tiles(),
            resident_bytes: scene.resident_bytes(),
            memory_limit_bytes: scene.memory_limit(),
            gpu_bytes: scene.gpu_bytes(),
            heap_bytes: crate::process::heap_bytes(),
            gpu_allocated: scene
                .gpu()
                .and_then(|gpu| crate::process::GpuReport::of(&gpu.device)),
            rss_bytes: crate::process::rss_bytes(),
            bytes_downloaded: stats.bytes_downloaded,
            in_flight: scene.in_flight(),
            retries: retries(&stats, &scene),
            evicted_unused_bytes: scene.evicted_unused_bytes,
            texture_budget_bytes: update.texture_budget,
            render: render_record,
        };
        bar.set_position(frame + 1);
        bar.set_message(match &record.render {
            Some(r) => format!(
                "{} tiles, {:.1}/{:.1} MiB, {:.0} fps, {} triangles",
                record.resident_tiles,
                record.resident_bytes as f64 / crate::memory::MIB,
                record.memory_limit_bytes as f64 / crate::memory::MIB,
                1e3 / r.frame_ms.max(1e-6),
                r.triangles
            ),
            None => format!(
                "{} tiles, {:.1}/{:.1} MiB",
                record.resident_tiles,
                record.resident_bytes as f64 / crate::memory::MIB,
                record.memory_limit_bytes as f64 / crate::memory::MIB
            ),
        });
        if let Err(source) = writeln!(csv, "{}", record.csv_row()) {
            bar.finish_and_clear();
            return Err(FlightError::WriteWhileFlying {
                path: csv_path,
                frame,
                frames,
                source,
            });
        }
        records.push(record);
    }
    bar.finish_and_clear();
    let pending: Vec<_> = fetcher.pending().collect();
    fetcher.cancel(&pending);

    let csv = csv.commit().map_err(write_err(&csv_path))?;
    let mut charts = vec![args.out.join("flight.png")];
    crate::output::write_via(&charts[0], |temp| {
        crate::charts::flight_chart(&records, &manifest.dataset, temp).map_err(FlightError::from)
    })?;
    if records.iter().any(|r| r.render.is_some()) {
        let chart = args.out.join("render.png");
        crate::output::write_via(&chart, |temp| {
            crate::charts::render_chart(&records, &manifest.dataset, temp)
                .map_err(FlightError::from)
        })?;
        charts.push(chart);
    }

    let stats = fetcher.stats();
    if let Some(error) = stopped {
        return Err(error);
    }
    if scene.tiles_fetched == 0 && manifest.tile_count() > 0 {
        return Err(FlightError::NothingLoaded {
            wall_s: started.elapsed().as_secs_f64(),
            requests: stats.requests_started,
            failures: stats.failures,
            cancelled: stats.cancelled,
            last_failure: last_failure
                .or_else(|| scene.unavailable.last().map(|t| t.error.clone())),
            out: args.out.clone(),
        });
    }
    let last = records.last().cloned();
    Ok(FlightSummary {
        dataset: manifest.dataset.clone(),
        frames,
        duration_s: path.duration_s(),
        wall_s: started.elapsed().as_secs_f64(),
        memory_limit_bytes: budget.limit_bytes(),
        peak_resident_bytes: records.iter().map(|r| r.resident_bytes).max().unwrap_or(0),
        peak_overshoot_bytes: records
            .iter()
            .map(|r| r.resident_bytes.saturating_sub(r.memory_limit_bytes))
            .max()
            .unwrap_or(0),
        frames_over_limit: records
            .iter()
            .filter(|r| r.resident_bytes > r.memory_limit_bytes)
            .count() as u64,
        peak_heap_bytes: crate::process::peak_heap_bytes(),
        peak_gpu: records
            .iter()
            .filter_map(|r| r.gpu_allocated)
            .max_by_key(|g| g.allocated),
        no_target: no_target(args),
        final_complete_belts: last.as_ref().map_or(0, |r| r.complete_belts),
        tiles_fetched: scene.tiles_fetched,
        bytes_downloaded: stats.bytes_downloaded,
        evicted_unused_bytes: scene.evicted_unused_bytes,
        retries: retries(&stats, &scene),
        failures: stats.failures,
        unavailable: scene.unavailable.clone(),
        content_changes,
        peak_rss_bytes: crate::process::peak_rss_bytes(),
        adapter,
        frame_rate: FrameRateSummary::of(&records),
        frames_written,
        csv,
        charts,
    })
}

/// Request attempts repeated so far, as `flight.csv`'s `retries` counts them: the
/// fetcher's retries after transient failures and refetches of corrupt bodies, and the
/// scene's requests for tiles whose earlier request failed.
fn retries(stats: &crate::fetcher::FetchStats, scene: &Scene) -> u64 {
    stats.retries + stats.corrupt_refetches + scene.requests_repeated
}

/// After a tile was refused: fetches the manifest again and, when its content version
/// changed, hands it to the fetcher and the scene. `None` when the content is the same
/// (the refusal stands); with the change, the new manifest when the scene cannot take it
/// (its grid changed shape) and a new scene must be made of it.
async fn reload_content(
    scene: &mut Scene,
    fetcher: &mut crate::fetcher::Fetcher,
    frame: u64,
) -> Result<Option<(ContentChange, Option<Arc<Manifest>>)>, FetchError> {
    let manifest = Arc::new(fetcher.fetch_manifest().await?);
    let from = fetcher.manifest().content_version.clone();
    if manifest.content_version == from {
        return Ok(None);
    }
    tracing::warn!(
        "the server's content changed from version {from} to {}: reloading",
        manifest.content_version
    );
    fetcher.replace_manifest(Arc::clone(&manifest));
    let mut change = ContentChange {
        frame,
        from,
        to: manifest.content_version.clone(),
        kept_dropped: None,
    };
    match scene.replace_manifest(Arc::clone(&manifest)) {
        Reconciled::Kept { kept, dropped } => {
            change.kept_dropped = Some((kept, dropped));
            Ok(Some((change, None)))
        }
        Reconciled::Reshaped => Ok(Some((change, Some(manifest)))),
    }
}

/// What a flight's least memory limit is for, for its refusal: the method and frame size,
/// or paging alone.
fn what_needs(args: &FlightArgs) -> String {
    if args.no_render {
        return "paging (--no-render)".to_string();
    }
    let (w, h) = args.render.size;
    format!(
        "--method {} at {w}x{h}{}",
        args.render.method.name(),
        if args.stream.single_level {
            ", one level"
        } else {
            ""
        }
    )
}

/// Why `--target-fps` does not apply to the flight's method, when it does not: only strip
/// masks share a triangle budget out; the other methods draw what their error threshold or
/// grid sets.
fn no_target(args: &FlightArgs) -> Option<String> {
    let method = args.render.method;
    (!args.no_render && args.render.fixed_budget.is_none() && method != MethodKind::StripMasks)
        .then(|| {
            format!(
                "--method {} shares no triangle budget: --target-fps does not apply, what it draws is set by its {}",
                method.name(),
                match method {
                    MethodKind::Pgm | MethodKind::ProjectiveGrid => "grid",
                    MethodKind::Reference => "full resolution of every visible tile",
                    _ => "error threshold",
                }
            )
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_and_bad_ones_say_why() {
        assert_eq!(parse_size("960x540"), Ok((960, 540)));
        assert_eq!(parse_size("64X48"), Ok((64, 48)));
        assert!(parse_size("960").is_err_and(|e| e.contains("WIDTHxHEIGHT")));
        assert!(parse_size("0x10").is_err_and(|e| e.contains("16 to 8192")));
    }

    #[test]
    fn csv_rows_have_one_field_per_column_with_and_without_rendering() {
        let mut record = FrameRecord {
            frame: 1,
            time_s: 0.0,
            wall_s: 0.0,
            position_m: [0.0; 3],
            ground_m: None,
            current: [0, 0],
            farthest_complete_belt: None,
            complete_belts: 0,
            resident_tiles: 0,
            resident_bytes: 0,
            memory_limit_bytes: 0,
            gpu_bytes: 0,
            heap_bytes: 0,
            gpu_allocated: None,
            rss_bytes: None,
            bytes_downloaded: 0,
            in_flight: 0,
            retries: 0,
            evicted_unused_bytes: 0,
            texture_budget_bytes: 0,
            render: None,
        };
        let columns = CSV_HEADER.split(',').count();
        assert_eq!(record.csv_row().split(',').count(), columns);
        record.render = Some(RenderRecord {
            visible_tiles: 3,
            triangles: 10,
            triangles_needed: 4,
            filler_triangles: 6,
            draw_calls: 6,
            global_budget: 12,
            mask_levels: vec![(0, 1), (5, 2)],
            lod_ms: 0.1,
            cpu_ms: 1.0,
            gpu_ms: None,
            frame_ms: 2.0,
            predicted_ms: Some(1.5),
            target_fps: Some(60.0),
        });
        let row = record.csv_row();
        assert_eq!(row.split(',').count(), columns);
        assert!(row.contains(",0:1;5:2,"), "{row}");
    }
}
