//! `terrain-client bench grids`: the projected grids' paper tables, in shape, on our data.
//!
//! - Livny et al.'s Table 1 (persistent grid mapping): grid size, triangles, frame rate.
//! - Löffler et al.'s Tables 1 and 2 (the error-bounded projective grid): per grid size, the
//!   frame rate of the uniform and the warped grid without and with ray casting, and the
//!   errors of the visible pixels without ray casting (the share past the threshold, which
//!   ray casting must redraw, the mean and the maximum).
//!
//! Each table is the accuracy sweep ([`super::accuracy`]) run over the papers' grid sizes on
//! one flight, at Löffler et al.'s screen size by default, with the numbers the papers print
//! beside ours. Writes `grids.md` and the sweeps' own files under `OUT/*`.

use super::accuracy::{self, AccuracyArgs, AccuracyReport, Summary};
use crate::flight::{FlightError, parse_size};
use crate::method::MethodKind;
use std::fmt::Write as _;
use std::path::PathBuf;

/// Arguments of `terrain-client bench grids`.
#[derive(Debug, Clone, clap::Args)]
pub struct GridsArgs {
    /// Base URL of the tile server (the papers fly over Puget Sound).
    #[arg(long, env = "TERRAIN_SERVER")]
    pub server: String,
    /// Directory for grids.md and the sweeps; created if missing.
    #[arg(long, default_value = "out/grids")]
    pub out: PathBuf,
    /// Frame size, WIDTHxHEIGHT (Löffler et al. measured at 1024x800).
    #[arg(long, default_value = "1024x800", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Cameras taken evenly along the flight.
    #[arg(long, default_value_t = 4)]
    pub cameras: u32,
    /// Draws per configuration and camera; the frame time is their median.
    #[arg(long, default_value_t = 3)]
    pub repeats: u32,
    /// The projective grid's error threshold, pixels.
    #[arg(long, default_value_t = 1.0)]
    pub max_error_px: f64,
}

/// Livny et al.'s Table 1: grid (columns x rows as printed), thousands of triangles, and
/// frames per second with two fragment fetches, on an NVIDIA GeForce 7800 GTX (AMD Athlon
/// 3500+, 16K x 16K Puget Sound).
pub const LIVNY_TABLE_1: [((u32, u32), u32, u32); 6] = [
    ((150, 600), 180, 177),
    ((200, 800), 320, 119),
    ((430, 430), 370, 112),
    ((300, 900), 540, 78),
    ((600, 600), 720, 59),
    ((400, 1600), 1280, 35),
];

/// A row of Löffler et al.'s Tables 1 and 2 (NVIDIA GeForce 8800 GTX, Core 2 Duo 2.0 GHz,
/// 4K Puget Sound, 1024 x 800): grid; frames per second uniform, non-uniform, ray casting
/// uniform, ray casting non-uniform; error pixels (%), mean and maximum error (px), each
/// uniform then non-uniform.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoefflerRow {
    pub grid: (u32, u32),
    pub fps: [f64; 4],
    pub error_pixels_pct: [f64; 2],
    pub mean_px: [f64; 2],
    pub max_px: [f64; 2],
}

pub const LOEFFLER_TABLES: [LoefflerRow; 5] = [
    LoefflerRow {
        grid: (1024, 512),
        fps: [68.72, 61.48, 33.43, 36.42],
        error_pixels_pct: [10.7, 7.5],
        mean_px: [1.60, 1.42],
        max_px: [18.0, 6.77],
    },
    LoefflerRow {
        grid: (512, 256),
        fps: [251.34, 217.82, 64.26, 70.17],
        error_pixels_pct: [15.6, 12.1],
        mean_px: [1.70, 1.40],
        max_px: [23.1, 6.9],
    },
    LoefflerRow {
        grid: (600, 600),
        fps: [98.14, 90.69, 41.05, 43.64],
        error_pixels_pct: [11.9, 8.5],
        mean_px: [1.83, 1.53],
        max_px: [22.0, 8.3],
    },
    LoefflerRow {
        grid: (300, 900),
        fps: [131.47, 119.53, 43.27, 45.81],
        error_pixels_pct: [13.0, 9.0],
        mean_px: [1.68, 1.44],
        max_px: [19.3, 6.7],
    },
    LoefflerRow {
        grid: (400, 1900),
        fps: [48.61, 45.80, 23.52, 25.34],
        error_pixels_pct: [11.0, 7.4],
        mean_px: [1.67, 1.51],
        max_px: [14.9, 6.7],
    },
];

/// What the tables measured.
#[derive(Debug, Clone)]
pub struct GridsReport {
    pub markdown: String,
    pub files: Vec<PathBuf>,
}

/// One sweep: `method` over `grids`, warped or not, with or without ray casting.
async fn sweep(
    args: &GridsArgs,
    name: &str,
    method: MethodKind,
    grids: Vec<(u32, u32)>,
    warp: bool,
    ray_casting: bool,
) -> Result<AccuracyReport, FlightError> {
    let mut one = AccuracyArgs {
        grids,
        size: args.size,
        cameras: args.cameras,
        repeats: args.repeats,
        popping_frames: 0,
        uniform_grid: !warp,
        no_ray_casting: !ray_casting,
        ..AccuracyArgs::new(args.server.clone(), args.out.join(name))
    };
    one.error.max_error_px = args.max_error_px;
    one.variants.methods = vec![method];
    accuracy::run(&one).await
}

fn row_of(report: &AccuracyReport, grid: (u32, u32)) -> Option<&Summary> {
    report
        .summaries
        .iter()
        .find(|s| s.config.knob == accuracy::Knob::Grid([grid.0, grid.1]))
}

fn fps(s: Option<&Summary>) -> String {
    s.map_or("-".into(), |s| {
        format!("{:.1}", 1000.0 / s.frame_ms.max(1e-9))
    })
}

/// Runs the sweeps and writes `grids.md`. Must run inside a multi-threaded tokio runtime.
pub async fn run(args: &GridsArgs) -> Result<GridsReport, FlightError> {
    std::fs::create_dir_all(&args.out).map_err(|e| FlightError::Write {
        path: args.out.clone(),
        source: e,
    })?;
    let livny_grids: Vec<(u32, u32)> = LIVNY_TABLE_1.iter().map(|r| r.0).collect();
    let pgm = sweep(args, "pgm", MethodKind::Pgm, livny_grids, false, false).await?;
    let loeffler_grids: Vec<(u32, u32)> = LOEFFLER_TABLES.iter().map(|r| r.grid).collect();
    let mut runs = Vec::new();
    for (name, warp, ray) in [
        ("uniform", false, false),
        ("non-uniform", true, false),
        ("uniform-ray-casting", false, true),
        ("non-uniform-ray-casting", true, true),
    ] {
        let report = sweep(
            args,
            name,
            MethodKind::ProjectiveGrid,
            loeffler_grids.clone(),
            warp,
            ray,
        )
        .await?;
        runs.push(report);
    }
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Measured on {} at {}x{}, {} cameras along the flight over {}, the error threshold {} px; the papers' figures in parentheses (Livny et al.: GeForce 7800 GTX, 16K x 16K Puget Sound; Löffler et al.: GeForce 8800 GTX, 4K Puget Sound at 1024x800).\n",
        pgm.adapter, args.size.0, args.size.1, args.cameras, pgm.dataset, args.max_error_px
    );
    let _ = writeln!(
        s,
        "**Persistent grid mapping** (Livny et al., Table 1):\n\n| grid | triangles (K) | frames/s | mean / p99 / max error (px) | > {} px (%) |\n|---|---:|---:|---:|---:|",
        args.max_error_px
    );
    for &(grid, triangles, paper_fps) in &LIVNY_TABLE_1 {
        let ours = row_of(&pgm, grid);
        let _ = writeln!(
            s,
            "| {}x{} | {} ({triangles}) | {} ({paper_fps}) | {} | {} |",
            grid.0,
            grid.1,
            ours.map_or("-".into(), |m| format!("{:.0}", m.triangles / 1000.0)),
            fps(ours),
            ours.map_or("-".into(), |m| format!(
                "{:.3} / {:.2} / {:.2}",
                m.mean_error_px, m.p99_error_px, m.max_error_px
            )),
            ours.map_or("-".into(), |m| format!("{:.2}", m.above_threshold_pct)),
        );
    }
    let _ = writeln!(
        s,
        "\n**The error-bounded projective grid** (Löffler et al., Table 1: frames per second):\n\n| grid | uniform | non-uniform | ray casting, uniform | ray casting, non-uniform |\n|---|---:|---:|---:|---:|"
    );
    for row in &LOEFFLER_TABLES {
        let _ = write!(s, "| {}x{} |", row.grid.0, row.grid.1);
        for (k, run) in runs.iter().enumerate() {
            let _ = write!(s, " {} ({}) |", fps(row_of(run, row.grid)), row.fps[k]);
        }
        let _ = writeln!(s);
    }
    let _ = writeln!(
        s,
        "\n(Löffler et al., Table 2: the visible pixels without ray casting; error pixels are those the grid draws with an error past the threshold, which ray casting redraws; ray cast: the pixels whose ray is walked, those and the uncovered ones whose ray enters the terrain's box.)\n\n| grid | error pixels (%) uniform | non-uniform | mean error (px) uniform | non-uniform | max error (px) uniform | non-uniform | with ray casting: p99 / max (px), ray cast (%) |\n|---|---:|---:|---:|---:|---:|---:|---:|"
    );
    for row in &LOEFFLER_TABLES {
        let (u, n) = (row_of(&runs[0], row.grid), row_of(&runs[1], row.grid));
        let cell = |m: Option<&Summary>, f: &dyn Fn(&Summary) -> f64, paper: f64| {
            format!(
                "{} ({paper})",
                m.map_or("-".into(), |m| format!("{:.2}", f(m)))
            )
        };
        let ray = row_of(&runs[3], row.grid);
        let _ = writeln!(
            s,
            "| {}x{} | {} | {} | {} | {} | {} | {} | {} |",
            row.grid.0,
            row.grid.1,
            cell(
                u,
                &|m| m.error_pixels_pct.unwrap_or(f64::NAN),
                row.error_pixels_pct[0]
            ),
            cell(
                n,
                &|m| m.error_pixels_pct.unwrap_or(f64::NAN),
                row.error_pixels_pct[1]
            ),
            cell(u, &|m| m.mean_error_px, row.mean_px[0]),
            cell(n, &|m| m.mean_error_px, row.mean_px[1]),
            cell(u, &|m| m.max_error_px, row.max_px[0]),
            cell(n, &|m| m.max_error_px, row.max_px[1]),
            ray.map_or("-".into(), |m| format!(
                "{:.2} / {:.2}, {:.1}",
                m.p99_error_px,
                m.max_error_px,
                m.ray_cast_pct.unwrap_or(f64::NAN)
            )),
        );
    }
    let path = args.out.join("grids.md");
    crate::output::write_file(&path, &s).map_err(|e| FlightError::Write {
        path: path.clone(),
        source: e,
    })?;
    Ok(GridsReport {
        markdown: s,
        files: vec![path],
    })
}
