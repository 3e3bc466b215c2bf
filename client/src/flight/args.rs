//! What `fly` and `view` are asked to do: the command line's arguments (where the tiles
//! come from and how much of them to hold, the path, the rendering and its method's knobs),
//! checked as they are parsed.

use super::FlightError;
use crate::lod::budget::{BudgetMode, DEFAULT_TARGET_FPS};
use crate::lod::importance::{DEFAULT_ALPHA, HeightMeasure};
use crate::lod::plan::{DEFAULT_MAX_ERROR_PX, LodSettings};
use crate::memory::{MemoryBudget, MemorySize};
use crate::method::{CrackFiller, MethodKind};
use crate::requests::FetcherConfig;
use crate::scene::{RenderConfig, Scene};
use std::path::PathBuf;

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
    #[arg(long, default_value_t = crate::requests::DEFAULT_CONCURRENCY)]
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
            concurrency: crate::requests::DEFAULT_CONCURRENCY,
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
    /// With --no-render, do not pace frames in wall-clock time: a frame follows the one
    /// before as soon as a request finishes (at once when none is running, at the latest
    /// 1/fps later). The path's clock still advances 1/fps a frame, so the flight flies the
    /// same frames in the time the server takes to answer; its download rate is then not
    /// a viewer's, and a tile that failed, asked for again after a wait in wall-clock
    /// time, may not be before the flight ends. For tests and quick checks of paging.
    #[arg(long, requires = "no_render")]
    pub no_wait: bool,
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
            no_wait: false,
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
