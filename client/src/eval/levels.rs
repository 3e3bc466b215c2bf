//! `terrain-client bench levels`: the default flight under a memory limit, paged as a
//! pyramid of levels (each policy of sharing the limit between them) and as level 0 alone,
//! each frame's downloaded bytes recorded and frames sampled along the way measured against
//! the whole database at full resolution: the share of the reference's terrain pixels drawn
//! (coverage) and the screen-space error.
//!
//! Each variant flies on its own, one frame after the other as `fly` does; at a sampled
//! frame its colour and depth are kept. The reference frames are drawn afterwards, by a
//! session holding the whole database, so that drawing them (seconds each on a software
//! rasterizer) takes no time from the flights' streaming. Writes `levels.md`, `levels.csv`
//! and `levels.png`.

use super::frame::{Capture, measure};
use super::session::{Session, median};
use crate::charts::{XyPanel, XySeries, palette, xy_chart};
use crate::flight::{FlightError, heading, parse_size};
use crate::memory::MemorySize;
use crate::page::LevelPolicy;
use crate::path::CameraPath;
use crate::render::Camera;
use crate::scene::RenderConfig;
use std::fmt::{self, Write as _};
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// Arguments of `terrain-client bench levels`.
#[derive(Debug, Clone, clap::Args)]
pub struct LevelsArgs {
    /// Base URL of the tile server.
    #[arg(long, env = "TERRAIN_SERVER")]
    pub server: String,
    /// Memory budget of the flights (the limit is 90% of it, as in `fly`).
    #[arg(long, default_value = "16MiB")]
    pub memory: MemorySize,
    /// Directory for levels.md, levels.csv and levels.png; created if missing.
    #[arg(long, default_value = "out/levels")]
    pub out: PathBuf,
    /// Frame size, WIDTHxHEIGHT.
    #[arg(long, default_value = "480x270", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Frames per second of the flight's clock.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// Measure every Nth frame against the reference (and the last one).
    #[arg(long, default_value_t = 15)]
    pub sample_every: u32,
    /// Pixels of error allowed (the methods' threshold, and the share above it).
    #[arg(long, default_value_t = 1.0)]
    pub threshold_px: f64,
}

/// One flight: a way of paging.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Paging {
    /// Every level, the limit shared by `policy`.
    Levels(LevelPolicy),
    /// Level 0 alone: the strip-mask paper's single resolution.
    OneLevel,
}

impl Paging {
    pub fn name(self) -> &'static str {
        match self {
            Paging::Levels(LevelPolicy::Equal) => "levels, equal shares",
            Paging::Levels(LevelPolicy::FinestFirst) => "levels, finest first",
            Paging::OneLevel => "level 0 alone",
        }
    }
}

/// What was measured of one sampled frame.
#[derive(Debug, Clone)]
pub struct Sample {
    pub frame: u32,
    pub time_s: f64,
    /// Bytes downloaded since the flight began, at this frame.
    pub downloaded_bytes: u64,
    pub resident_bytes: u64,
    /// Of `resident_bytes`, the tiles' own (what the byte oracle's held bytes count).
    pub tile_bytes: u64,
    /// Share of the reference's terrain pixels the frame draws, percent.
    pub coverage_pct: f64,
    pub mean_error_px: f64,
    pub max_error_px: f64,
    pub above_threshold_pct: f64,
    /// The byte oracle at this frame ([`OracleFrame`]).
    pub oracle: OracleFrame,
}

/// The byte oracle at a frame of the flight: the fewest bytes of whole tiles that draw the
/// view within the threshold ([`crate::scene::Scene::bytes_needed`]: the coarsest tile of
/// each visible part whose builder-measured deviation from full resolution projects within
/// it), held at that frame, and downloaded by then (each tile the oracle needed at any frame
/// so far, once: its blob and coarsest texture level). Textures are counted at their
/// coarsest level, so the oracle is a floor where the screen resolves finer ones.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct OracleFrame {
    pub tiles: usize,
    pub held_bytes: u64,
    pub downloaded_bytes: u64,
}

/// One flight's samples.
#[derive(Debug, Clone)]
pub struct FlightResult {
    pub paging: Paging,
    pub samples: Vec<Sample>,
    pub frames: u32,
    pub downloaded_bytes: u64,
    pub peak_resident_bytes: u64,
    pub memory_limit: u64,
    /// The byte oracle's downloads over the whole flight, and its largest held bytes at a
    /// frame.
    pub oracle_downloaded_bytes: u64,
    pub oracle_peak_held_bytes: u64,
}

impl FlightResult {
    /// Samples after the first second of flight.
    fn settled(&self) -> impl Iterator<Item = &Sample> {
        self.samples.iter().filter(|s| s.time_s >= 1.0)
    }

    /// Lowest coverage after the first second, percent.
    pub fn min_coverage_pct(&self) -> f64 {
        self.settled()
            .map(|s| s.coverage_pct)
            .fold(f64::INFINITY, f64::min)
    }

    /// Median of the sampled frames' mean error after the first second, pixels.
    pub fn median_mean_error_px(&self) -> f64 {
        let mut errors: Vec<f64> = self.settled().map(|s| s.mean_error_px).collect();
        median(&mut errors)
    }

    /// Median over the sampled frames after the first second of the tiles' bytes held over
    /// the oracle's at the same frame.
    pub fn median_held_over_oracle(&self) -> f64 {
        let mut r: Vec<f64> = self
            .settled()
            .filter(|s| s.oracle.held_bytes > 0)
            .map(|s| s.tile_bytes as f64 / s.oracle.held_bytes as f64)
            .collect();
        median(&mut r)
    }

    /// Median coverage after the first second, percent.
    pub fn median_coverage_pct(&self) -> f64 {
        let mut c: Vec<f64> = self.settled().map(|s| s.coverage_pct).collect();
        median(&mut c)
    }
}

/// The whole comparison.
#[derive(Debug, Clone)]
pub struct LevelsReport {
    pub dataset: String,
    pub adapter: String,
    pub flights: Vec<FlightResult>,
    pub files: Vec<PathBuf>,
}

/// A frame kept for measuring later.
struct Kept {
    frame: u32,
    time_s: f64,
    camera: Camera,
    color: image::RgbaImage,
    depth: Vec<f32>,
    downloaded_bytes: u64,
    resident_bytes: u64,
    tile_bytes: u64,
}

/// Runs the comparison. Must run inside a multi-threaded tokio runtime.
pub async fn run(args: &LevelsArgs) -> Result<LevelsReport, FlightError> {
    if !(args.fps.is_finite() && args.fps > 0.0) || args.sample_every == 0 {
        return Err(FlightError::BadOption(
            "--fps must be positive and --sample-every at least 1".into(),
        ));
    }
    let limit = (args.memory.0 as f64 * crate::memory::DEFAULT_LIMIT_PERCENT / 100.0) as u64;
    let config = RenderConfig::default();
    let variants = [
        Paging::Levels(LevelPolicy::Equal),
        Paging::Levels(LevelPolicy::FinestFirst),
        Paging::OneLevel,
    ];
    let mut kept: Vec<(Paging, Vec<Kept>, u32, u64, u64)> = Vec::new();
    let mut dataset = String::new();
    let mut adapter = String::new();
    // Every frame's camera (the same in each flight), for the byte oracle.
    let mut cameras: Vec<Camera> = Vec::new();
    for (k, paging) in variants.into_iter().enumerate() {
        let mut session = Session::open(&args.server, Some(limit), config, args.size).await?;
        dataset = session.manifest.dataset.clone();
        adapter = session.gpu.description();
        match paging {
            Paging::Levels(policy) => session.scene.set_level_policy(policy),
            Paging::OneLevel => session.scene.use_levels(false),
        }
        let path = CameraPath::default_for(&session.manifest);
        let frames = (path.duration_s() * args.fps).ceil() as u32 + 1;
        let bar = super::progress(paging.name(), u64::from(frames));
        let (mut samples, mut peak) = (Vec::new(), 0u64);
        let start = path.position_at(0.0);
        let centre = [
            session.manifest.extent_m[0] / 2.0,
            session.manifest.extent_m[1] / 2.0,
        ];
        let mut yaw = (centre[1] - start[1]).atan2(centre[0] - start[0]);
        for frame in 0..frames {
            let time_s = f64::from(frame) / args.fps;
            let position = path.position_at(time_s);
            yaw = heading(&path, time_s, yaw);
            let camera = Camera::new(
                position,
                yaw,
                crate::render::camera::DEFAULT_PITCH_DEG.to_radians(),
            );
            if k == 0 {
                cameras.push(camera);
            }
            session.update(position).await?;
            session.draw(&camera);
            peak = peak.max(session.scene.resident_bytes());
            if frame % args.sample_every == 0 || frame + 1 == frames {
                let color = session.target.read(&session.gpu)?;
                let depth = session.scene.read_depth().unwrap_or_else(|| {
                    Err(crate::render::GpuError::Readback("no renderer".into()))
                })?;
                samples.push(Kept {
                    frame,
                    time_s,
                    camera,
                    color,
                    depth,
                    downloaded_bytes: session.fetcher.stats().bytes_downloaded,
                    resident_bytes: session.scene.resident_bytes(),
                    tile_bytes: session.scene.tile_bytes(),
                });
            }
            bar.inc(1);
            // A frame's pace, as `fly` keeps it (streaming goes on meanwhile).
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
        bar.finish_and_clear();
        let downloaded = session.fetcher.stats().bytes_downloaded;
        session.close();
        kept.push((paging, samples, frames, downloaded, peak));
    }

    // The references: the whole database (every level, for the byte oracle), drawn from
    // level 0 at full resolution.
    let mut whole = Session::open(&args.server, None, config, args.size).await?;
    let first = kept
        .first()
        .and_then(|k| k.1.first())
        .map(|s| s.camera)
        .ok_or_else(|| FlightError::BadOption("the flight has no frame".into()))?;
    let centre = whole.centre();
    if !whole
        .settle(centre, &first, Duration::from_secs(900))
        .await?
    {
        return Err(FlightError::BadOption(
            "the whole database did not load within 15 minutes".into(),
        ));
    }
    // The byte oracle at every frame, and its downloads so far.
    let viewport = [args.size.0, args.size.1];
    let mut fetched = std::collections::HashSet::new();
    let mut oracle_downloaded = 0u64;
    let oracle: Vec<OracleFrame> = cameras
        .iter()
        .map(|camera| {
            let needed = whole
                .scene
                .bytes_needed(camera, viewport, args.threshold_px);
            for (id, bytes) in &needed {
                if fetched.insert(*id) {
                    oracle_downloaded += bytes.downloaded;
                }
            }
            OracleFrame {
                tiles: needed.len(),
                held_bytes: needed.iter().map(|(_, b)| b.held).sum(),
                downloaded_bytes: oracle_downloaded,
            }
        })
        .collect();
    let oracle_peak = oracle.iter().map(|o| o.held_bytes).max().unwrap_or(0);
    let count = kept.first().map_or(0, |k| k.1.len());
    let bar = super::progress("references", count as u64);
    let mut results: Vec<FlightResult> = kept
        .iter()
        .map(|(paging, _, frames, downloaded, peak)| FlightResult {
            paging: *paging,
            samples: Vec::new(),
            frames: *frames,
            downloaded_bytes: *downloaded,
            peak_resident_bytes: *peak,
            memory_limit: limit,
            oracle_downloaded_bytes: oracle_downloaded,
            oracle_peak_held_bytes: oracle_peak,
        })
        .collect();
    for i in 0..count {
        let camera = kept[0].1[i].camera;
        let started = Instant::now();
        let (reference, _) = whole.reference(&camera)?;
        tracing::debug!(ms = started.elapsed().as_millis() as u64, "reference frame");
        for (result, (_, samples, ..)) in results.iter_mut().zip(&mut kept) {
            let Some(k) = samples.get_mut(i) else {
                continue;
            };
            let capture = Capture::new(
                std::mem::take(&mut k.color),
                std::mem::take(&mut k.depth),
                &k.camera,
            );
            let m = measure(
                &capture,
                None,
                &reference,
                &k.camera,
                |x, y| whole.scene.surface_height(x, y),
                args.threshold_px,
            );
            result.samples.push(Sample {
                frame: k.frame,
                time_s: k.time_s,
                downloaded_bytes: k.downloaded_bytes,
                resident_bytes: k.resident_bytes,
                tile_bytes: k.tile_bytes,
                coverage_pct: 100.0 * m.coverage(),
                mean_error_px: m.error.mean_px,
                max_error_px: m.error.max_px,
                above_threshold_pct: 100.0 * m.error.share_above(),
                oracle: oracle.get(k.frame as usize).copied().unwrap_or_default(),
            });
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    whole.close();
    let mut report = LevelsReport {
        dataset,
        adapter,
        flights: results,
        files: Vec::new(),
    };
    write(args, &mut report)?;
    Ok(report)
}

fn write(args: &LevelsArgs, report: &mut LevelsReport) -> Result<(), FlightError> {
    let out = &args.out;
    let write_err = |path: &PathBuf| {
        let path = path.clone();
        move |source| FlightError::Write { path, source }
    };
    std::fs::create_dir_all(out).map_err(write_err(out))?;
    let mut csv = String::from(
        "paging,frame,time_s,downloaded_bytes,resident_bytes,coverage_pct,mean_error_px,max_error_px,above_threshold_pct,oracle_tiles,oracle_held_bytes,oracle_downloaded_bytes\n",
    );
    for f in &report.flights {
        for s in &f.samples {
            let _ = writeln!(
                csv,
                "{},{},{:.3},{},{},{:.3},{:.4},{:.3},{:.3},{},{},{}",
                f.paging.name(),
                s.frame,
                s.time_s,
                s.downloaded_bytes,
                s.resident_bytes,
                s.coverage_pct,
                s.mean_error_px,
                s.max_error_px,
                s.above_threshold_pct,
                s.oracle.tiles,
                s.oracle.held_bytes,
                s.oracle.downloaded_bytes
            );
        }
    }
    let csv_path = out.join("levels.csv");
    crate::output::write_file(&csv_path, csv).map_err(write_err(&csv_path))?;
    let md_path = out.join("levels.md");
    crate::output::write_file(&md_path, report.table()).map_err(write_err(&md_path))?;
    let chart = out.join("levels.png");
    let series = |value: fn(&Sample) -> f64| -> Vec<XySeries> {
        report
            .flights
            .iter()
            .enumerate()
            .map(|(k, f)| XySeries {
                name: f.paging.name().to_string(),
                colour: palette(k),
                points: f.samples.iter().map(|s| (s.time_s, value(s))).collect(),
                dashed: false,
            })
            .collect()
    };
    let panel = |title: &str, y: &str, series| XyPanel {
        title: title.to_string(),
        x_desc: "flight time (s)".into(),
        y_desc: y.to_string(),
        log_x: false,
        series,
    };
    xy_chart(
        &[
            panel(
                "Coverage: share of the full-resolution reference's terrain pixels drawn",
                "coverage (%)",
                series(|s| s.coverage_pct),
            ),
            panel(
                "Mean screen-space error against the true surface",
                "mean error (px)",
                series(|s| s.mean_error_px),
            ),
            panel(
                "Downloaded",
                "MiB",
                series(|s| s.downloaded_bytes as f64 / crate::memory::MIB),
            ),
        ],
        &chart,
    )
    .map_err(|e| FlightError::Image {
        path: chart.clone(),
        message: e.to_string(),
    })?;
    report.files = vec![md_path, csv_path, chart];
    Ok(())
}

impl LevelsReport {
    /// The Markdown table: one row per flight.
    pub fn table(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "| paging | downloaded (MiB) | over the byte oracle's | peak counted / limit (MiB) | tiles held over the oracle's, median after 1 s | coverage after 1 s: min / median (%) | mean error after 1 s, median (px) | sampled frames |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|");
        for f in &self.flights {
            let _ = writeln!(
                s,
                "| {} | {:.1} | {:.2}x | {:.1} / {:.1} | {:.2}x | {:.2} / {:.2} | {:.3} | {} of {} |",
                f.paging.name(),
                f.downloaded_bytes as f64 / crate::memory::MIB,
                f.downloaded_bytes as f64 / f.oracle_downloaded_bytes.max(1) as f64,
                f.peak_resident_bytes as f64 / crate::memory::MIB,
                f.memory_limit as f64 / crate::memory::MIB,
                f.median_held_over_oracle(),
                f.min_coverage_pct(),
                f.median_coverage_pct(),
                f.median_mean_error_px(),
                f.samples.len(),
                f.frames
            );
        }
        if let Some(f) = self.flights.first() {
            let _ = writeln!(
                s,
                "\nThe byte oracle over the same flight: {:.1} MiB downloaded, at most {:.1} MiB held at a frame.",
                f.oracle_downloaded_bytes as f64 / crate::memory::MIB,
                f.oracle_peak_held_bytes as f64 / crate::memory::MIB,
            );
        }
        s
    }
}

impl fmt::Display for LevelsReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "levels against one level over {}, adapter {}\n",
            self.dataset, self.adapter
        )?;
        write!(f, "{}", self.table())?;
        let files: Vec<String> = self.files.iter().map(|p| p.display().to_string()).collect();
        write!(f, "\nwrote {}", files.join(" "))
    }
}
