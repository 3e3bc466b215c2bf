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

use super::Variants;
use super::session::{Measured, Session, median};
use crate::charts::{self, ChartError, XyPanel, XySeries};
use crate::flight::{ErrorCapArgs, FlightError, heading, parse_size};
use crate::lod::budget::BudgetMode;
use crate::lod::plan::LodSettings;
use crate::method::CrackFiller;
use crate::method::MethodKind;
use crate::path::CameraPath;
use crate::render::Camera;
use crate::scene::RenderConfig;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Arguments of `terrain-client bench accuracy`.
#[derive(Debug, Clone, clap::Args)]
pub struct AccuracyArgs {
    /// Base URL of the tile server.
    #[arg(long, env = "TERRAIN_SERVER")]
    pub server: String,
    /// Directory for the CSVs, the summary and the charts; created if missing.
    #[arg(long, default_value = "out/accuracy")]
    pub out: PathBuf,
    /// Fixed global triangle budgets, comma-separated.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "1000,3000,10000,30000,100000,300000,1000000"
    )]
    pub budgets: Vec<u32>,
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
}

impl AccuracyArgs {
    /// The defaults of the command line against `server`, writing to `out`.
    pub fn new(server: impl Into<String>, out: impl Into<PathBuf>) -> AccuracyArgs {
        AccuracyArgs {
            server: server.into(),
            out: out.into(),
            budgets: vec![1000, 3000, 10_000, 30_000, 100_000, 300_000, 1_000_000],
            variants: Variants::default(),
            cameras: 8,
            flight: None,
            size: (640, 360),
            pitch_deg: crate::render::camera::DEFAULT_PITCH_DEG,
            error: ErrorCapArgs::default(),
            repeats: 3,
            label: None,
        }
    }
}

/// One configuration: a method, its filler, its budget.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Config {
    pub method: MethodKind,
    pub filler: CrackFiller,
    pub budget: u32,
}

impl Config {
    /// `method/filler` (or `method` for methods without filler).
    pub fn series(&self) -> String {
        Variants::name(self.method, self.filler)
    }
}

/// One camera drawn with one configuration.
#[derive(Debug, Clone)]
pub struct Row {
    pub camera: u32,
    pub config: Config,
    pub measured: Measured,
}

/// A configuration over all cameras.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    pub config: Config,
    pub triangles: f64,
    pub triangles_needed: f64,
    /// Mean of the per-frame ratios triangles used / triangles needed.
    pub used_over_needed: f64,
    pub filler_triangles: f64,
    pub draw_calls: f64,
    pub mean_error_px: f64,
    pub max_error_px: f64,
    /// Share of terrain pixels above the threshold, percent.
    pub above_threshold_pct: f64,
    pub crack_pixels: f64,
    pub hole_pixels: f64,
    pub silhouette_pixels: f64,
    /// Crack pixels in percent of the reference's terrain pixels.
    pub crack_pct: f64,
    pub psnr_db: f64,
    pub frame_ms: f64,
    pub cpu_ms: f64,
    pub gpu_ms: Option<f64>,
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
        ..RenderConfig::default()
    };
    let mut session = Session::open(&args.server, None, base, args.size).await?;
    let manifest = std::sync::Arc::clone(&session.manifest);
    let path = match &args.flight {
        Some(file) => CameraPath::load(file, &manifest)?,
        None => CameraPath::default_for(&manifest),
    };
    let cameras = cameras_along(&path, args.cameras, args.pitch_deg);
    let bar = progress(
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
    let (mut reference_triangles, mut reference_ms) = (Vec::new(), Vec::new());
    for (i, camera) in cameras.iter().enumerate() {
        let (reference, report) = session.reference(camera)?;
        reference_errors.push(session.own_error(&reference, camera, lod.max_error_px));
        reference_triangles.push(report.stats.triangles as f64);
        reference_ms.push(report.draw_ms);
        for config in configs(args) {
            let render = RenderConfig {
                method: config.method,
                filler: config.filler,
                budget: BudgetMode::Fixed(config.budget),
                ..base
            };
            let measured =
                session.measure(camera, render, &reference, lod.max_error_px, args.repeats)?;
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
            });
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    let stats = session.fetcher.stats();
    let mut report = AccuracyReport {
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
        summaries: summarise(&rows, &configs(args)),
        reference_errors,
        geometry,
        rows,
        files: Vec::new(),
    };
    session.close();
    write(args, &mut report)?;
    Ok(report)
}

fn check(args: &AccuracyArgs) -> Result<(), FlightError> {
    let bad = |m: String| Err(FlightError::BadOption(m));
    if args.budgets.is_empty() || args.budgets.contains(&0) {
        return bad("--budgets must list positive triangle counts".into());
    }
    if args.variants.methods.is_empty() || args.variants.fillers.is_empty() {
        return bad("--methods and --fillers must not be empty".into());
    }
    if args.cameras == 0 {
        return bad("--cameras must be at least 1".into());
    }
    Ok(())
}

/// Every configuration of `args`: per method, per filler when it uses one, per budget.
pub fn configs(args: &AccuracyArgs) -> Vec<Config> {
    let mut out = Vec::new();
    for (method, filler) in args.variants.list() {
        for &budget in &args.budgets {
            out.push(Config {
                method,
                filler,
                budget,
            });
        }
    }
    out
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

/// Means over the cameras, per configuration.
pub fn summarise(rows: &[Row], configs: &[Config]) -> Vec<Summary> {
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
                used_over_needed: mean(&|m| {
                    m.report.stats.triangles as f64 / (m.report.triangles_needed as f64).max(1.0)
                }),
                filler_triangles: mean(&|m| m.report.stats.filler_triangles as f64),
                draw_calls: mean(&|m| f64::from(m.report.stats.draw_calls)),
                mean_error_px: mean(&|m| m.measures.error.mean_px),
                max_error_px: of
                    .iter()
                    .map(|m| m.measures.error.max_px)
                    .fold(0.0, f64::max),
                above_threshold_pct: 100.0 * mean(&|m| m.measures.error.share_above()),
                crack_pixels: mean(&|m| m.measures.crack_pixels as f64),
                hole_pixels: mean(&|m| m.measures.hole_pixels as f64),
                silhouette_pixels: mean(&|m| m.measures.silhouette_pixels as f64),
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
            })
        })
        .collect()
}

/// Columns of `accuracy.csv`.
pub const CSV_HEADER: &str = "camera,method,filler,budget,triangles,triangles_needed,used_over_needed,filler_triangles,draw_calls,terrain_pixels,mean_error_px,max_error_px,above_threshold_pct,crack_pixels,hole_pixels,silhouette_pixels,filler_pixels,reference_terrain_pixels,psnr_db,lod_ms,cpu_ms,gpu_ms,frame_ms";

fn csv_row(r: &Row) -> String {
    let m = &r.measured;
    let e = &m.measures.error;
    format!(
        "{},{},{},{},{},{},{:.4},{},{},{},{:.4},{:.3},{:.3},{},{},{},{},{},{:.2},{:.3},{:.3},{},{:.3}",
        r.camera,
        r.config.method.name(),
        r.config.filler.name(),
        r.config.budget,
        m.report.stats.triangles,
        m.report.triangles_needed,
        m.report.stats.triangles as f64 / (m.report.triangles_needed as f64).max(1.0),
        m.report.stats.filler_triangles,
        m.report.stats.draw_calls,
        e.terrain_pixels,
        e.mean_px,
        e.max_px,
        100.0 * e.share_above(),
        m.measures.crack_pixels,
        m.measures.hole_pixels,
        m.measures.silhouette_pixels,
        m.measures.filler_pixels,
        m.measures.reference_terrain_pixels,
        m.measures.psnr_db,
        m.report.lod_ms,
        m.report.lod_ms + m.report.stats.encode_ms,
        m.gpu_ms.map_or(String::new(), |g| format!("{g:.3}")),
        m.frame_ms,
    )
}

/// What the reference frames themselves get wrong against the true surface, in words.
pub fn reference_floor(report: &AccuracyReport) -> String {
    let worst = report
        .reference_errors
        .iter()
        .map(|e| e.max_px)
        .fold(0.0, f64::max);
    let above: u64 = report
        .reference_errors
        .iter()
        .map(|e| e.above_threshold)
        .sum();
    format!(
        "its own error against the true surface, the measure's floor: at most {worst:.3} px, {above} pixels above {} px over {} cameras",
        report.threshold_px,
        report.reference_errors.len()
    )
}

/// The summary as a Markdown table.
pub fn summary_markdown(report: &AccuracyReport) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| method | budget | triangles | needed | used/needed | mean error (px) | max error (px) | > {} px (%) | crack px | holes px | silhouette px | cracks (% terrain) | PSNR (dB) | frame (ms) | CPU (ms) |",
        report.threshold_px
    );
    let _ = writeln!(
        s,
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    );
    for m in &report.summaries {
        let _ = writeln!(
            s,
            "| {} | {} | {:.0} | {:.0} | {:.2} | {:.3} | {:.2} | {:.2} | {:.0} | {:.0} | {:.0} | {:.2} | {:.1} | {:.1} | {:.2} |",
            m.config.series(),
            m.config.budget,
            m.triangles,
            m.triangles_needed,
            m.used_over_needed,
            m.mean_error_px,
            m.max_error_px,
            m.above_threshold_pct,
            m.crack_pixels,
            m.hole_pixels,
            m.silhouette_pixels,
            m.crack_pct,
            m.psnr_db,
            m.frame_ms,
            m.cpu_ms
        );
    }
    if !report.geometry.is_empty() {
        let _ = writeln!(
            s,
            "\nResident geometry after each method's last frame (heights, error tables, GPU sample buffers, index sets; textures apart):\n"
        );
        for (method, memory) in &report.geometry {
            let _ = writeln!(s, "- {method}: {memory}");
        }
    }
    s
}

impl std::fmt::Display for AccuracyReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "accuracy {}: {} cameras at {}x{}, {} tiles resident ({:.1} MiB, {:.1} MiB downloaded), threshold {} px",
            self.dataset,
            self.cameras,
            self.size.0,
            self.size.1,
            self.tiles,
            self.resident_bytes as f64 / crate::memory::MIB,
            self.downloaded_bytes as f64 / crate::memory::MIB,
            self.threshold_px
        )?;
        writeln!(f, "adapter {}", self.adapter)?;
        writeln!(
            f,
            "reference: {:.0} triangles, {:.1} ms a frame; {}\n",
            self.reference_triangles,
            self.reference_ms,
            reference_floor(self)
        )?;
        write!(f, "{}", summary_markdown(self))?;
        write!(f, "\nwrote")?;
        for file in &self.files {
            write!(f, " {}", file.display())?;
        }
        writeln!(f)
    }
}

fn write(args: &AccuracyArgs, report: &mut AccuracyReport) -> Result<(), FlightError> {
    let out = &args.out;
    let write_err = |path: &Path| {
        let path = path.to_path_buf();
        move |source| FlightError::Write { path, source }
    };
    std::fs::create_dir_all(out).map_err(write_err(out))?;
    let mut csv = String::from(CSV_HEADER);
    csv.push('\n');
    for r in &report.rows {
        csv.push_str(&csv_row(r));
        csv.push('\n');
    }
    let csv_path = out.join("accuracy.csv");
    std::fs::write(&csv_path, csv).map_err(write_err(&csv_path))?;
    let md_path = out.join("summary.md");
    let header = format!(
        "Dataset {}, {} cameras along the flight at {}x{}, adapter {}. Reference: {:.0} triangles, {:.1} ms a frame; {}.\n\n",
        report.dataset,
        report.cameras,
        report.size.0,
        report.size.1,
        report.adapter,
        report.reference_triangles,
        report.reference_ms,
        reference_floor(report)
    );
    std::fs::write(&md_path, header + &summary_markdown(report)).map_err(write_err(&md_path))?;
    report.files = vec![csv_path, md_path];
    report.files.extend(draw_charts(report, out)?);
    Ok(())
}

/// The four charts of the sweep.
fn draw_charts(report: &AccuracyReport, out: &Path) -> Result<Vec<PathBuf>, ChartError> {
    let mut series_names: Vec<String> = Vec::new();
    for s in &report.summaries {
        if !series_names.contains(&s.config.series()) {
            series_names.push(s.config.series());
        }
    }
    let series = |f: &dyn Fn(&Summary) -> (f64, f64)| -> Vec<XySeries> {
        series_names
            .iter()
            .enumerate()
            .map(|(k, name)| XySeries {
                name: name.clone(),
                colour: charts::palette(k),
                points: report
                    .summaries
                    .iter()
                    .filter(|s| &s.config.series() == name)
                    .map(f)
                    .collect(),
                dashed: false,
            })
            .collect()
    };
    let title = &report.dataset;
    let threshold = report.threshold_px;
    let mut files = Vec::new();
    let path = out.join("error-vs-triangles.png");
    charts::xy_chart(
        &[
            XyPanel {
                title: format!("{title}: mean screen-space error against triangles drawn"),
                x_desc: "triangles per frame (log)".into(),
                y_desc: "mean error (px)".into(),
                log_x: true,
                series: series(&|s| (s.triangles, s.mean_error_px)),
            },
            XyPanel {
                title: format!("terrain pixels off by more than {threshold} px"),
                x_desc: "triangles per frame (log)".into(),
                y_desc: "% of terrain pixels".into(),
                log_x: true,
                series: series(&|s| (s.triangles, s.above_threshold_pct)),
            },
        ],
        &path,
    )?;
    files.push(path);
    let path = out.join("error-vs-frame-time.png");
    charts::xy_chart(
        &[XyPanel {
            title: format!(
                "{title}: mean screen-space error against frame time ({})",
                report.adapter
            ),
            x_desc: "frame time, median (ms)".into(),
            y_desc: "mean error (px)".into(),
            log_x: false,
            series: series(&|s| (s.frame_ms, s.mean_error_px)),
        }],
        &path,
    )?;
    files.push(path);
    let path = out.join("cracks-vs-budget.png");
    let mut holes = series(&|s| (f64::from(s.config.budget), s.hole_pixels));
    for h in &mut holes {
        h.name = format!("{} (left as holes)", h.name);
        h.dashed = true;
    }
    let mut cracks = series(&|s| (f64::from(s.config.budget), s.crack_pixels));
    cracks.extend(holes);
    charts::xy_chart(
        &[XyPanel {
            title: format!("{title}: crack pixels per frame against the budget"),
            x_desc: "global triangle budget (log)".into(),
            y_desc: "pixels".into(),
            log_x: true,
            series: cracks,
        }],
        &path,
    )?;
    files.push(path);
    let path = out.join("used-vs-needed.png");
    let mut used = series(&|s| (f64::from(s.config.budget), s.triangles));
    used.truncate(1);
    if let Some(u) = used.first_mut() {
        u.name = format!("used ({})", u.name);
    }
    let mut needed = series(&|s| (f64::from(s.config.budget), s.triangles_needed));
    needed.truncate(1);
    if let Some(n) = needed.first_mut() {
        n.name = format!("needed for {threshold} px");
        n.dashed = true;
        n.colour = charts::palette(5);
    }
    used.extend(needed);
    charts::xy_chart(
        &[
            XyPanel {
                title: format!("{title}: triangles used and needed against the budget"),
                x_desc: "global triangle budget (log)".into(),
                y_desc: "triangles per frame".into(),
                log_x: true,
                series: used,
            },
            XyPanel {
                title: "used / needed (per frame, mean)".into(),
                x_desc: "global triangle budget (log)".into(),
                y_desc: "ratio".into(),
                log_x: true,
                series: series(&|s| (f64::from(s.config.budget), s.used_over_needed)),
            },
        ],
        &path,
    )?;
    files.push(path);
    Ok(files)
}

/// A progress bar of `len` steps (hidden when stderr is not a terminal).
pub fn progress(message: &str, len: u64) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_message(message.to_string());
    bar
}
