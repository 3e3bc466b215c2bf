//! `terrain-client bench stability`: named scenarios where level-of-detail methods are
//! known to fail, run with every method and crack filler.
//!
//! Each run streams its own scene from the server (paging, fetching, textures, the
//! frame-rate controller: everything a flight does) along the scenario's cameras, then
//! lets the last view settle and measures it against the reference at that camera (every
//! resident tile at full resolution). A run that returns an error or panics is reported as
//! failed, and the others go on. Writes `stability.md` (the table), `stability.csv`, and per
//! scenario a picture: the reference, then each method's frame with the pixels it lost to
//! the background in red.

mod report;

pub use self::report::markdown;
use self::report::{marked, write_outputs};

use super::Variants;
use super::session::{Session, median, whole_database_bytes};
use crate::flight::{FlightError, parse_size};
use crate::lod::budget::BudgetMode;
use crate::memory::MemorySize;
use crate::method::CrackFiller;
use crate::method::MethodKind;
use crate::render::Camera;
use crate::scene::{RenderConfig, expected_tile_bytes};
use std::path::PathBuf;
use std::time::{Duration, Instant};
use terrain_shared::Manifest;

/// Arguments of `terrain-client bench stability`.
#[derive(Debug, Clone, clap::Args)]
pub struct StabilityArgs {
    /// Base URL of the server for the scenarios of any terrain.
    #[arg(long, env = "TERRAIN_SERVER", required_unless_present = "list")]
    pub server: Option<String>,
    /// Servers of named datasets for the scenarios that need them, NAME=URL (repeatable):
    /// grand_canyon_hoppe, srtm_geotiff, himalaya_4097. Scenarios without theirs are listed
    /// as not run. A database under any other name is your own: the altitude scenarios
    /// run on it too, as SCENARIO@NAME, with the same checks.
    #[arg(long = "data", value_parser = super::parse_named)]
    pub data: Vec<(String, String)>,
    /// Directory for stability.md, stability.csv and the pictures; created if missing.
    #[arg(long, default_value = "out/stability")]
    pub out: PathBuf,
    /// Scenarios to run, comma-separated (default: all; see --list).
    #[arg(long, value_delimiter = ',')]
    pub scenarios: Vec<String>,
    /// List the scenarios and exit.
    #[arg(long)]
    pub list: bool,
    #[command(flatten)]
    pub variants: Variants,
    /// Frames streamed and drawn per run before the measured one.
    #[arg(long, default_value_t = 40)]
    pub frames: u32,
    /// Memory budget of the scenarios that do not set their own.
    #[arg(long, default_value = "64MiB")]
    pub memory: MemorySize,
    /// Frame size, WIDTHxHEIGHT.
    #[arg(long, default_value = "480x270", value_parser = parse_size)]
    pub size: (u32, u32),
}

impl StabilityArgs {
    /// The defaults of the command line against `server`, writing to `out`.
    pub fn new(server: impl Into<String>, out: impl Into<PathBuf>) -> StabilityArgs {
        StabilityArgs {
            server: Some(server.into()),
            data: Vec::new(),
            out: out.into(),
            scenarios: Vec::new(),
            list: false,
            variants: Variants::default(),
            frames: 40,
            memory: MemorySize(64 << 20),
            size: (480, 270),
        }
    }
}

/// What a scenario does to the camera, the memory or the budget.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Kind {
    /// Low over the terrain, looking this many degrees below the horizon.
    Grazing(f64),
    /// Looking 15 degrees above the horizon.
    AboveHorizon,
    /// Low over the ground a tile and a half west of the highest tile, below its top,
    /// looking level at it: a peak rising into the view from ground the view's bottom
    /// edge does not reach (the projected grids' auxiliary camera).
    LowNearPeak,
    /// 50 m below the lowest point under the camera.
    BelowSurface,
    /// Two terrain widths west of the terrain, looking at it.
    FarOutside,
    /// A memory budget of a third of one belt (three tiles' worth).
    MemoryBelowOneBelt,
    /// A fixed budget of 100 triangles.
    Budget100,
    /// Jumps between opposite corners every quarter of the frames.
    Jump,
    /// The default lap at a bird's eye (for datasets of their own).
    Overview,
    /// Looking down at the highest tile from a third of a tile south of it.
    Relief,
    /// Over the flat (zero-error) tile nearest the terrain's centre, from 1.5 tiles west.
    FlatSea,
    /// High over the terrain (this many metres above its highest sample), looking north
    /// this many degrees down, with [`ALTITUDE_MEMORY`]: what only a pyramid of levels
    /// draws whole. Measured against the whole database at full resolution, and held to
    /// [`RunResult::altitude_shortfall`]. Run on himalaya_4097 and on every database of
    /// your own given with `--data` ([`targets`]).
    Altitude { above_m: f64, pitch_deg: f64 },
}

/// Memory budget of the [`Kind::Altitude`] scenarios.
pub const ALTITUDE_MEMORY: u64 = 16 << 20;

/// Least share of the reference's terrain pixels an altitude frame draws, percent.
pub const ALTITUDE_COVERAGE_PCT: f64 = 99.5;

/// Most holes (cracks left showing the background) a filler that closes cracks may leave in
/// an altitude frame, as a share of the reference's terrain pixels: the planar shadow is
/// known to leave a few where a crack near the terrain's border meets a shadow clipped at
/// the edge (`docs/evaluation.md`). Without a filler every crack is a hole.
pub const ALTITUDE_HOLES_SHARE: f64 = 0.0005;

/// A named scenario.
#[derive(Debug, Clone, Copy)]
pub struct Scenario {
    pub name: &'static str,
    /// Dataset it needs (`--data NAME=URL`); `None` runs on `--server`.
    pub dataset: Option<&'static str>,
    pub what: &'static str,
    pub kind: Kind,
}

/// Every scenario, in table order.
pub const SCENARIOS: &[Scenario] = &[
    Scenario {
        name: "grazing-1deg",
        dataset: None,
        what: "low over the terrain, looking 1 degree down",
        kind: Kind::Grazing(1.0),
    },
    Scenario {
        name: "grazing-3deg",
        dataset: None,
        what: "low over the terrain, looking 3 degrees down",
        kind: Kind::Grazing(3.0),
    },
    Scenario {
        name: "grazing-5deg",
        dataset: None,
        what: "low over the terrain, looking 5 degrees down",
        kind: Kind::Grazing(5.0),
    },
    Scenario {
        name: "above-horizon",
        dataset: None,
        what: "looking 15 degrees above the horizon",
        kind: Kind::AboveHorizon,
    },
    Scenario {
        name: "low-near-peak",
        dataset: None,
        what: "30 m over the ground a tile and a half from the highest tile, looking level at it",
        kind: Kind::LowNearPeak,
    },
    Scenario {
        name: "below-surface",
        dataset: None,
        what: "camera 50 m under the terrain",
        kind: Kind::BelowSurface,
    },
    Scenario {
        name: "far-outside",
        dataset: None,
        what: "two terrain widths outside, looking at it",
        kind: Kind::FarOutside,
    },
    Scenario {
        name: "memory-below-one-belt",
        dataset: None,
        what: "memory for three tiles, less than one belt",
        kind: Kind::MemoryBelowOneBelt,
    },
    Scenario {
        name: "budget-100",
        dataset: None,
        what: "a fixed budget of 100 triangles",
        kind: Kind::Budget100,
    },
    Scenario {
        name: "jump",
        dataset: None,
        what: "jumps between opposite corners",
        kind: Kind::Jump,
    },
    Scenario {
        name: "altitude-30km-20deg",
        dataset: Some("himalaya_4097"),
        what: "30 km above the highest point, 20 degrees down, 16 MiB",
        kind: Kind::Altitude {
            above_m: 30_000.0,
            pitch_deg: 20.0,
        },
    },
    Scenario {
        name: "altitude-30km-45deg",
        dataset: Some("himalaya_4097"),
        what: "30 km above the highest point, 45 degrees down, 16 MiB",
        kind: Kind::Altitude {
            above_m: 30_000.0,
            pitch_deg: 45.0,
        },
    },
    Scenario {
        name: "altitude-100km-20deg",
        dataset: Some("himalaya_4097"),
        what: "100 km above the highest point, 20 degrees down, 16 MiB",
        kind: Kind::Altitude {
            above_m: 100_000.0,
            pitch_deg: 20.0,
        },
    },
    Scenario {
        name: "altitude-100km-45deg",
        dataset: Some("himalaya_4097"),
        what: "100 km above the highest point, 45 degrees down, 16 MiB",
        kind: Kind::Altitude {
            above_m: 100_000.0,
            pitch_deg: 45.0,
        },
    },
    Scenario {
        name: "altitude-3km-horizon",
        dataset: Some("himalaya_4097"),
        what: "3 km above the highest point, looking at the horizon, 16 MiB",
        kind: Kind::Altitude {
            above_m: 3_000.0,
            pitch_deg: 0.0,
        },
    },
    Scenario {
        name: "terraced-8bit",
        dataset: Some("grand_canyon_hoppe"),
        what: "8-bit heights in 10 m terraces",
        kind: Kind::Overview,
    },
    Scenario {
        name: "voids",
        dataset: Some("srtm_geotiff"),
        what: "SRTM with filled voids",
        kind: Kind::Overview,
    },
    Scenario {
        name: "extreme-relief",
        dataset: Some("himalaya_4097"),
        what: "the highest tile (Everest) from a third of a tile away",
        kind: Kind::Relief,
    },
    Scenario {
        name: "flat-sea",
        dataset: Some("himalaya_4097"),
        what: "over the zero (sea) areas",
        kind: Kind::FlatSea,
    },
];

/// One run: a scenario with one method and filler.
#[derive(Debug, Clone)]
pub struct RunResult {
    /// The scenario's name, with `@NAME` when it ran on a database of the user's own.
    pub scenario: String,
    pub method: String,
    pub frames: u32,
    pub crack_pixels: u64,
    pub hole_pixels: u64,
    pub reference_terrain_pixels: u64,
    pub max_error_px: f64,
    /// 99th percentile screen-space error of the measured frame, pixels.
    pub p99_error_px: f64,
    /// With a crack filler, the 99th percentile and maximum error of the same frame drawn
    /// without it (the same masks: the frame-rate controller gives each run its own).
    pub unfilled_error_px: Option<(f64, f64)>,
    /// Pixels showing the crack filler, and of those the ones where the mesh has no crack
    /// ([`crate::eval::frame::FrameMeasures::leak_pixels`]).
    pub filler_pixels: u64,
    pub leak_pixels: u64,
    pub above_threshold_pct: f64,
    pub frame_ms_median: f64,
    pub frame_ms_p95: f64,
    pub frame_ms_max: f64,
    /// The most the scene counted against the limit in any frame
    /// ([`crate::scene::Scene::resident_bytes`]).
    pub peak_resident_bytes: u64,
    /// The most it really held in any frame: CPU bytes plus the GPU allocations made for
    /// the terrain ([`crate::scene::Scene::cpu_bytes`] + [`crate::scene::Scene::gpu_bytes`]).
    pub peak_held_bytes: u64,
    pub memory_limit_bytes: u64,
    /// What the whole database would take with every texture level: a limit below it
    /// binds (the scene cannot hold everything).
    pub database_bytes: u64,
    /// Flat (zero-error) tiles drawn in the measured frame, and how many at the coarsest mask.
    pub flat_tiles: (u32, u32),
    /// Triangles used and needed in the measured frame.
    pub triangles: (u64, u64),
    /// Of the pixels where the reference shows terrain, the share the frame draws (terrain
    /// or filler), percent.
    pub coverage_pct: f64,
    /// Mean screen-space error of the measured frame, pixels.
    pub mean_error_px: f64,
    /// Whether the reference held the whole database ([`Kind::Altitude`]) rather than what
    /// the scenario's own limit let in.
    pub whole_reference: bool,
    /// Whether the method closes cracks (a filler, or stitching and skirts).
    pub closes_cracks: bool,
    /// Why it failed: an error or a panic.
    pub failure: Option<String>,
    /// Why the run was refused at start: its memory limit cannot hold what the method needs
    /// to draw anything and keep the limit ([`crate::memory::LimitTooSmall`]). Not a
    /// failure: the limit is kept by not starting.
    pub refused: Option<String>,
    pub picture: Option<image::RgbaImage>,
    pub reference: Option<image::RgbaImage>,
}

impl RunResult {
    /// Whether the scene kept within the limit in every frame, as counted and as held.
    pub fn within_memory(&self) -> bool {
        self.peak_resident_bytes <= self.memory_limit_bytes
            && self.peak_held_bytes <= self.memory_limit_bytes
    }

    /// Whether the limit kept the scene from holding the whole database.
    pub fn limit_binds(&self) -> bool {
        self.memory_limit_bytes < self.database_bytes
    }

    /// For a run measured against the whole database (an altitude scenario), what it falls
    /// short of: coverage of at least [`ALTITUDE_COVERAGE_PCT`] of the reference's terrain,
    /// a mean screen-space error within 1 px, and no more holes than
    /// [`ALTITUDE_HOLES_SHARE`] when the method closes cracks. `None` when it meets all
    /// three, or is not such a run.
    pub fn altitude_shortfall(&self) -> Option<String> {
        if !self.whole_reference || self.failure.is_some() || self.refused.is_some() {
            return None;
        }
        let mut short = Vec::new();
        if self.coverage_pct < ALTITUDE_COVERAGE_PCT {
            short.push(format!(
                "coverage {:.2}% < {ALTITUDE_COVERAGE_PCT}%",
                self.coverage_pct
            ));
        }
        if self.mean_error_px > 1.0 {
            short.push(format!("mean error {:.2} px > 1 px", self.mean_error_px));
        }
        let allowed = (ALTITUDE_HOLES_SHARE * self.reference_terrain_pixels as f64).floor();
        if self.closes_cracks && self.hole_pixels as f64 > allowed {
            short.push(format!(
                "{} holes > {allowed} ({}% of terrain)",
                self.hole_pixels,
                100.0 * ALTITUDE_HOLES_SHARE
            ));
        }
        (!short.is_empty()).then(|| short.join(", "))
    }
}

/// What the matrix found.
#[derive(Debug, Clone, Default)]
pub struct StabilityReport {
    pub runs: Vec<RunResult>,
    /// Scenarios not run, with why.
    pub skipped: Vec<(String, String)>,
    pub adapter: String,
    pub files: Vec<PathBuf>,
}

/// Runs the matrix. Must run inside a multi-threaded tokio runtime.
pub async fn run(args: &StabilityArgs) -> Result<StabilityReport, FlightError> {
    for name in &args.scenarios {
        if !SCENARIOS.iter().any(|s| s.name == name) {
            return Err(FlightError::BadOption(format!(
                "unknown scenario {name:?}; --list shows them"
            )));
        }
    }
    if args.frames == 0 || args.variants.methods.is_empty() || args.variants.fillers.is_empty() {
        return Err(FlightError::BadOption(
            "--frames, --methods and --fillers must not be empty".into(),
        ));
    }
    let chosen: Vec<&Scenario> = SCENARIOS
        .iter()
        .filter(|s| args.scenarios.is_empty() || args.scenarios.iter().any(|n| n == s.name))
        .collect();
    let variants = args.variants.list();
    let mut report = StabilityReport::default();
    let bar = super::progress("stability", (chosen.len() * variants.len()) as u64);
    let whole = WholeCache::default();
    let mut runs: Vec<(&Scenario, Vec<(String, String)>)> = chosen
        .into_iter()
        .map(|s| targets(s, args).map(|t| (s, t)))
        .collect::<Result<_, _>>()?;
    // The runs on databases of the user's own go last, one database after another, so that
    // the whole-database reference of each is loaded once.
    let own: Vec<(&Scenario, Vec<(String, String)>)> = args
        .data
        .iter()
        .flat_map(|(name, _)| {
            let suffix = format!("@{name}");
            runs.iter()
                .map(|(s, t)| {
                    let mine = t.iter().filter(|(l, _)| l.ends_with(&suffix)).cloned();
                    (*s, mine.collect::<Vec<_>>())
                })
                .filter(|(_, t)| !t.is_empty())
                .collect::<Vec<_>>()
        })
        .collect();
    for (_, t) in &mut runs {
        t.retain(|(label, _)| !label.contains('@'));
    }
    // A scenario that ran on databases of the user's own alone is not "not run".
    runs.retain(|(s, t)| !t.is_empty() || !own.iter().any(|(o, _)| o.name == s.name));
    runs.extend(own);
    bar.set_length(
        runs.iter()
            .map(|(_, t)| t.len().max(1) * variants.len())
            .sum::<usize>() as u64,
    );
    for (scenario, targets) in runs {
        if targets.is_empty() {
            let why = match (scenario.dataset, scenario.kind) {
                (Some(name), Kind::Altitude { .. }) => {
                    format!("no --data {name}=URL, nor a database of your own, given")
                }
                (Some(name), _) => format!("no --data {name}=URL given"),
                (None, _) => "no server".into(),
            };
            report.skipped.push((scenario.name.to_string(), why));
            bar.inc(variants.len() as u64);
            continue;
        }
        for (label, server) in targets {
            for &(method, filler) in &variants {
                bar.set_message(format!("{label} {}", filler.name()));
                let (one, server, args2) = (*scenario, server.clone(), args.clone());
                let label2 = label.clone();
                let whole = std::sync::Arc::clone(&whole);
                // Its own task: a panic is caught and reported as the run's failure.
                let joined = tokio::spawn(async move {
                    run_one(&one, &label2, &server, &args2, method, filler, whole).await
                })
                .await;
                let result = match joined {
                    Ok(Ok((r, adapter))) => {
                        report.adapter = adapter;
                        r
                    }
                    Ok(Err(FlightError::Memory(crate::memory::MemoryError::TooSmall(why)))) => {
                        RunResult {
                            refused: Some(why.to_string()),
                            failure: None,
                            ..failed(&label, method, filler, String::new())
                        }
                    }
                    Ok(Err(e)) => failed(&label, method, filler, format!("error: {e}")),
                    Err(e) if e.is_panic() => {
                        let panic = e.into_panic();
                        let message = panic
                            .downcast_ref::<String>()
                            .cloned()
                            .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                            .unwrap_or_default();
                        failed(&label, method, filler, format!("panic: {message}"))
                    }
                    Err(e) => failed(&label, method, filler, format!("cancelled: {e}")),
                };
                report.runs.push(result);
                bar.inc(1);
            }
        }
    }
    bar.finish_and_clear();
    write_outputs(args, &mut report)?;
    Ok(report)
}

/// The databases `scenario` runs on, as (label, URL): `--server` for a scenario of any
/// terrain; its dataset's `--data` server for one that needs a dataset; and for an altitude
/// scenario also every `--data` database no scenario names (the user's own), labelled
/// `SCENARIO@NAME`. Empty when its dataset was not given.
pub fn targets(
    scenario: &Scenario,
    args: &StabilityArgs,
) -> Result<Vec<(String, String)>, FlightError> {
    let Some(dataset) = scenario.dataset else {
        let server = args.server.clone().ok_or_else(|| {
            FlightError::BadOption("--server is needed to run the scenarios".into())
        })?;
        return Ok(vec![(scenario.name.to_string(), server)]);
    };
    let known = |name: &str| SCENARIOS.iter().any(|s| s.dataset == Some(name));
    let altitude = matches!(scenario.kind, Kind::Altitude { .. });
    Ok(args
        .data
        .iter()
        .filter_map(|(name, url)| {
            if name == dataset {
                Some((scenario.name.to_string(), url.clone()))
            } else if altitude && !known(name) {
                Some((format!("{}@{name}", scenario.name), url.clone()))
            } else {
                None
            }
        })
        .collect())
}

fn failed(label: &str, method: MethodKind, filler: CrackFiller, why: String) -> RunResult {
    RunResult {
        scenario: label.to_string(),
        method: Variants::name(method, filler),
        frames: 0,
        crack_pixels: 0,
        hole_pixels: 0,
        reference_terrain_pixels: 0,
        max_error_px: 0.0,
        above_threshold_pct: 0.0,
        frame_ms_median: 0.0,
        frame_ms_p95: 0.0,
        frame_ms_max: 0.0,
        peak_resident_bytes: 0,
        peak_held_bytes: 0,
        memory_limit_bytes: 0,
        database_bytes: 0,
        p99_error_px: 0.0,
        unfilled_error_px: None,
        filler_pixels: 0,
        leak_pixels: 0,
        flat_tiles: (0, 0),
        triangles: (0, 0),
        coverage_pct: 0.0,
        mean_error_px: 0.0,
        whole_reference: false,
        closes_cracks: false,
        failure: Some(why),
        refused: None,
        picture: None,
        reference: None,
    }
}

/// The cameras of `kind` over `manifest`, `frames` of them.
pub fn cameras(kind: Kind, manifest: &Manifest, frames: u32) -> Vec<Camera> {
    let [w, h] = manifest.extent_m;
    let cells = f64::from(manifest.tile_size - 1);
    let (tile_x, tile_y) = (cells * manifest.spacing_m[0], cells * manifest.spacing_m[1]);
    let tile_m = tile_x.min(tile_y);
    let grid = manifest.grid(0);
    let centre_of = |(t, _): (terrain_shared::TileId, &terrain_shared::TileRecord)| {
        [
            (f64::from(t.x) + 0.5) * tile_x,
            (f64::from(t.y) + 0.5) * tile_y,
        ]
    };
    let under = |x: f64, y: f64| {
        let tx = ((x / tile_x) as u32).min(grid.columns - 1);
        let ty = ((y / tile_y) as u32).min(grid.rows - 1);
        manifest.tile(terrain_shared::TileId::new(tx, ty))
    };
    let f = |i: u32| f64::from(i) / f64::from(frames.max(2) - 1);
    let top = manifest.heights.max_m;
    (0..frames)
        .map(|i| match kind {
            Kind::Grazing(deg) => {
                // Eastwards over a tile, 30 m above the highest point beneath.
                let (x, y) = (0.3 * w + f(i) * tile_m, 0.5 * h);
                let z = under(x, y).map_or(top, |t| f64::from(t.max_m)) + 30.0;
                Camera::new([x, y, z], 0.0, -deg.to_radians())
            }
            Kind::AboveHorizon => {
                let (x, y) = (0.3 * w + f(i) * tile_m, 0.5 * h);
                let z = under(x, y).map_or(top, |t| f64::from(t.max_m)) + 200.0;
                Camera::new([x, y, z], 0.0, 15f64.to_radians())
            }
            Kind::LowNearPeak => {
                let peak = manifest
                    .tiles()
                    .filter(|(id, _)| id.level == 0)
                    .max_by(|(_, a), (_, b)| a.max_m.total_cmp(&b.max_m))
                    .map_or([0.5 * w, 0.5 * h], centre_of);
                // Drifting a third of a tile towards it over the frames.
                let x = (peak[0] - (1.5 - f(i) / 3.0) * tile_m).max(0.0);
                let y = peak[1];
                let z = under(x, y).map_or(top, |t| f64::from(t.max_m)) + 30.0;
                let yaw = (peak[1] - y).atan2(peak[0] - x);
                Camera::new([x, y, z], yaw, 0.0)
            }
            Kind::BelowSurface => {
                let (x, y) = (0.5 * w, 0.5 * h);
                let z = under(x, y).map_or(0.0, |t| f64::from(t.min_m)) - 50.0;
                Camera::new([x, y, z], f(i) * std::f64::consts::TAU, -10f64.to_radians())
            }
            Kind::FarOutside => Camera::looking_at(
                [-2.0 * w.max(h), 0.5 * h, top + 0.2 * w.max(h)],
                [0.5 * w, 0.5 * h, manifest.heights.min_m],
            ),
            Kind::Jump => {
                let corner = (i * 4 / frames.max(1)).is_multiple_of(2);
                let (x, y) = if corner {
                    (0.1 * w, 0.1 * h)
                } else {
                    (0.9 * w, 0.9 * h)
                };
                Camera::looking_at(
                    [x, y, top + 0.05 * w],
                    [0.5 * w, 0.5 * h, manifest.heights.min_m],
                )
            }
            Kind::MemoryBelowOneBelt | Kind::Budget100 | Kind::Overview => {
                let (x, y) = (0.2 * w + 0.6 * f(i) * w, 0.2 * h + 0.6 * f(i) * h);
                Camera::new(
                    [x, y, top + 0.05 * w.max(h)],
                    std::f64::consts::FRAC_PI_4,
                    -25f64.to_radians(),
                )
            }
            Kind::Relief => {
                let peak = manifest
                    .tiles()
                    .filter(|(id, _)| id.level == 0)
                    .max_by(|(_, a), (_, b)| a.max_m.total_cmp(&b.max_m))
                    .map_or([0.5 * w, 0.5 * h], centre_of);
                // A third of a tile south of the highest tile's centre, 500 m above the
                // highest point, sweeping a fifth of a tile west to east.
                let from = [
                    peak[0] + (f(i) - 0.5) * 0.2 * tile_m,
                    peak[1] + tile_m / 3.0,
                ];
                Camera::looking_at(
                    [from[0], from[1], top + 500.0],
                    [peak[0], peak[1], top - 3000.0],
                )
            }
            Kind::FlatSea => {
                // A flat tile: its bounds are one height, so every mask's error is 0.
                let flat = manifest
                    .tiles()
                    .filter(|(id, t)| id.level == 0 && t.min_m == t.max_m)
                    .min_by_key(|(id, _)| {
                        let (cx, cy) = (grid.columns / 2, grid.rows / 2);
                        id.x.abs_diff(cx) + id.y.abs_diff(cy)
                    })
                    .map_or([0.5 * w, 0.5 * h], centre_of);
                Camera::looking_at(
                    [
                        flat[0] - 1.5 * tile_m,
                        flat[1] + f(i) * tile_m,
                        0.4 * tile_m,
                    ],
                    [flat[0], flat[1], 0.0],
                )
            }
            Kind::Altitude { above_m, pitch_deg } => {
                // Over the south third of the terrain, looking north across it, drifting a
                // tenth of its width east over the frames so that the levels page.
                Camera::new(
                    [(0.45 + 0.1 * f(i)) * w, 0.7 * h, top + above_m],
                    -std::f64::consts::FRAC_PI_2,
                    -pitch_deg.to_radians(),
                )
            }
        })
        .collect()
}

/// A session holding the whole database of one server, kept between the runs that measure
/// against it ([`Kind::Altitude`]): loading it takes longer than a run.
type WholeCache = std::sync::Arc<tokio::sync::Mutex<Option<(String, Session)>>>;

async fn run_one(
    scenario: &Scenario,
    label: &str,
    server: &str,
    args: &StabilityArgs,
    method: MethodKind,
    filler: CrackFiller,
    whole: WholeCache,
) -> Result<(RunResult, String), FlightError> {
    let config = RenderConfig {
        method,
        filler,
        budget: if scenario.kind == Kind::Budget100 {
            BudgetMode::Fixed(100)
        } else {
            BudgetMode::default()
        },
        ..RenderConfig::default()
    };
    let client = crate::http_client::TileClient::new(server)?;
    let manifest = client.manifest().await?;
    let database = whole_database_bytes(&manifest);
    let altitude = matches!(scenario.kind, Kind::Altitude { .. });
    let limit = if altitude {
        ALTITUDE_MEMORY
    } else if scenario.kind == Kind::MemoryBelowOneBelt {
        let one = manifest
            .tiles()
            .map(|(_, t)| {
                expected_tile_bytes(&manifest, t, config.method_config().texture_copies()).total()
            })
            .max()
            .unwrap_or(0);
        3 * one
    } else {
        // Three quarters of the whole database at most, so that the limit binds in every
        // scenario: the pager has to choose what to hold.
        args.memory.0.min(database / 4 * 3)
    };
    let mut session = Session::open(server, Some(limit), config, args.size).await?;
    crate::method::check_database(method, &session.manifest).map_err(FlightError::BadOption)?;
    let cams = cameras(scenario.kind, &session.manifest, args.frames);
    let mut times = Vec::new();
    let (mut peak, mut held) = (0, 0);
    let held_now = |scene: &crate::scene::Scene| scene.cpu_bytes() + scene.gpu_bytes();
    for camera in &cams {
        let started = Instant::now();
        session.update(camera.position).await?;
        session.scene.draw(&session.target.view, camera, started);
        times.push(started.elapsed().as_secs_f64() * 1e3);
        peak = peak.max(session.scene.resident_bytes());
        held = held.max(held_now(&session.scene));
    }
    let last = *cams.last().expect("at least one frame");
    session
        .settle(last.position, &last, Duration::from_secs(20))
        .await?;
    peak = peak.max(session.scene.resident_bytes());
    held = held.max(held_now(&session.scene));
    // The measured frame keeps the budget the controller had reached (the reference's
    // drawing must not reset it).
    let frozen = RenderConfig {
        budget: BudgetMode::Fixed(session.scene.budget().unwrap_or(u32::MAX)),
        ..config
    };
    let (reference, measured) = if altitude {
        // The reference holds the whole database; the scene's own limit holds too little of
        // level 0 to draw it, or to give the true surface the errors are measured against.
        let mut cache = whole.lock().await;
        if cache.as_ref().is_none_or(|(url, _)| url != server) {
            // Its frames while it loads are the strip masks' (cheap, and with no data of
            // their own to wait for: with levels off, the quadtree patches' index, which
            // comes with the top level, would never arrive); it draws the reference.
            let loading = RenderConfig {
                method: MethodKind::StripMasks,
                ..config
            };
            let mut opened = Session::open(server, None, loading, args.size).await?;
            opened.scene.use_levels(false);
            *cache = Some((server.to_string(), opened));
        }
        let (_, whole) = cache.as_mut().expect("just set");
        let centre = whole.centre();
        if !whole
            .settle(centre, &last, Duration::from_secs(600))
            .await?
        {
            return Err(FlightError::BadOption(
                "the whole database did not load within 10 minutes".into(),
            ));
        }
        let (reference, _) = whole.reference(&last)?;
        let measured = session.measure_against(&last, frozen, &reference, &whole.scene, 1.0)?;
        (reference, measured)
    } else {
        let (reference, _) = session.reference(&last)?;
        // A method with data of its own asks for it again after the reference's frame.
        session
            .prepare(last.position, &last, frozen, Duration::from_secs(20))
            .await?;
        let measured = session.measure(&last, frozen, &reference, 1.0, 1)?;
        (reference, measured)
    };
    peak = peak.max(session.scene.resident_bytes());
    held = held.max(held_now(&session.scene));
    let plan = &measured.report.plan;
    let n = session.manifest.tile_size;
    let coarsest = |_: &crate::lod::plan::Draw| method.coarsest_level(n);
    let mut flat = (0, 0);
    for d in &plan.draws {
        if let Some(t) = session.manifest.tile(d.id)
            && t.min_m == t.max_m
        {
            flat.0 += 1;
            flat.1 += u32::from(d.level == coarsest(d));
        }
    }
    session.close();
    let mut sorted = times.clone();
    let p95 = {
        sorted.sort_by(f64::total_cmp);
        sorted[(sorted.len() * 95 / 100).min(sorted.len() - 1)]
    };
    let m = &measured.measures;
    Ok((
        RunResult {
            scenario: label.to_string(),
            method: Variants::name(method, filler),
            frames: cams.len() as u32 + 1,
            crack_pixels: m.crack_pixels,
            hole_pixels: m.hole_pixels,
            reference_terrain_pixels: m.reference_terrain_pixels,
            max_error_px: m.error.max_px,
            p99_error_px: m.error.p99_px,
            unfilled_error_px: m.unfilled_error.map(|e| (e.p99_px, e.max_px)),
            filler_pixels: m.filler_pixels,
            leak_pixels: m.leak_pixels,
            above_threshold_pct: 100.0 * m.error.share_above(),
            frame_ms_median: median(&mut times),
            frame_ms_p95: p95,
            frame_ms_max: sorted.last().copied().unwrap_or(0.0),
            peak_resident_bytes: peak,
            peak_held_bytes: held,
            memory_limit_bytes: limit,
            database_bytes: database,
            flat_tiles: flat,
            triangles: (
                measured.report.stats.triangles,
                measured.report.triangles_needed,
            ),
            coverage_pct: 100.0 * m.coverage(),
            mean_error_px: m.error.mean_px,
            whole_reference: altitude,
            closes_cracks: !method.uses_filler() || filler != CrackFiller::None,
            failure: None,
            refused: None,
            picture: Some(marked(
                &measured.capture,
                &reference,
                measured.unfilled.as_ref(),
            )),
            reference: Some(reference.color.clone()),
        },
        session.gpu.description(),
    ))
}

/// Names and descriptions of the scenarios, one a line.
pub fn list() -> String {
    SCENARIOS
        .iter()
        .map(|s| {
            format!(
                "{:<22} {}{}\n",
                s.name,
                s.what,
                match (s.dataset, s.kind) {
                    (Some(d), Kind::Altitude { .. }) =>
                        format!(" (on --data {d}=URL and any database of your own)"),
                    (Some(d), _) => format!(" (needs --data {d}=URL)"),
                    (None, _) => String::new(),
                }
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scenario(name: &str) -> &'static Scenario {
        SCENARIOS
            .iter()
            .find(|s| s.name == name)
            .expect("a scenario")
    }

    #[test]
    fn altitude_scenarios_run_on_himalaya_and_on_every_database_of_the_users_own() {
        let args = StabilityArgs {
            data: [
                ("himalaya_4097", "http://h"),
                ("srtm_geotiff", "http://s"),
                ("alps", "http://a"),
            ]
            .map(|(n, u)| (n.to_string(), u.to_string()))
            .to_vec(),
            ..StabilityArgs::new("http://any", "out")
        };
        let of = |name: &str| targets(scenario(name), &args).expect("targets");
        let pair = |l: &str, u: &str| (l.to_string(), u.to_string());
        assert_eq!(
            of("altitude-30km-20deg"),
            [
                pair("altitude-30km-20deg", "http://h"),
                pair("altitude-30km-20deg@alps", "http://a")
            ]
        );
        // Other dataset scenarios run on their dataset alone, the generic ones on --server.
        assert_eq!(of("voids"), [pair("voids", "http://s")]);
        assert_eq!(of("extreme-relief"), [pair("extreme-relief", "http://h")]);
        assert_eq!(of("grazing-1deg"), [pair("grazing-1deg", "http://any")]);
        // Without himalaya_4097, a database of one's own still gets the altitude scenarios.
        let own = StabilityArgs {
            data: vec![("alps".into(), "http://a".into())],
            ..args.clone()
        };
        assert_eq!(
            targets(scenario("altitude-3km-horizon"), &own).expect("targets"),
            [pair("altitude-3km-horizon@alps", "http://a")]
        );
        assert!(
            targets(scenario("terraced-8bit"), &own)
                .expect("targets")
                .is_empty()
        );
    }

    #[test]
    fn an_altitude_run_falls_short_on_coverage_error_or_holes_a_filler_should_close() {
        let run = RunResult {
            coverage_pct: 99.7,
            mean_error_px: 0.4,
            hole_pixels: 5,
            reference_terrain_pixels: 100_000,
            whole_reference: true,
            closes_cracks: true,
            ..failed(
                "altitude-30km-20deg",
                MethodKind::StripMasks,
                CrackFiller::Skirts,
                String::new(),
            )
        };
        let run = RunResult {
            failure: None,
            ..run
        };
        assert_eq!(run.altitude_shortfall(), None);
        let short = |r: RunResult| r.altitude_shortfall().unwrap_or_default();
        assert!(
            short(RunResult {
                coverage_pct: 99.4,
                ..run.clone()
            })
            .contains("coverage 99.40%")
        );
        assert!(
            short(RunResult {
                mean_error_px: 1.2,
                ..run.clone()
            })
            .contains("mean error")
        );
        assert!(
            short(RunResult {
                hole_pixels: 51,
                ..run.clone()
            })
            .contains("51 holes > 50")
        );
        // Without a filler every crack is a hole, which the check allows.
        let bare = RunResult {
            hole_pixels: 900,
            closes_cracks: false,
            ..run.clone()
        };
        assert_eq!(bare.altitude_shortfall(), None);
        // A run against its own limit's tiles is not held to it.
        let own = RunResult {
            coverage_pct: 50.0,
            whole_reference: false,
            ..run
        };
        assert_eq!(own.altitude_shortfall(), None);
    }
}
