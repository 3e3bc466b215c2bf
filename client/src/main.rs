//! `terrain-client`: talk to a terrain tile server. Thin on purpose: argument parsing,
//! logging set-up and the exit code; the library does the work.

use clap::{Parser, Subcommand};
use std::io::{IsTerminal, Write};
use std::process::ExitCode;

/// Stream, inspect and render terrain tiles from a terrain-server.
#[derive(Debug, Parser)]
#[command(name = "terrain-client", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Fetch every tile (heights and all texture levels), verify and decode it, and write
    /// overview.png and tiles.csv.
    Fetch(terrain_client::cli::FetchArgs),
    /// Fly a camera path headless: page tiles in belts around the viewpoint within a memory
    /// budget, render every frame offscreen (strip masks under a triangle budget that holds
    /// a target frame rate, crack filling, textures refined within the budget), and write
    /// frames, flight.csv (one row per frame) and charts (flight.png, render.png).
    Fly(terrain_client::flight::FlightArgs),
    /// Open a window and fly over the streamed terrain with mouse and keyboard (X11 or
    /// Wayland on Linux; Metal on macOS, Direct3D 12 on Windows): the same paging,
    /// streaming and rendering as `fly`.
    View(terrain_client::viewer::ViewArgs),
    /// Measure accuracy against speed: `bench accuracy` sweeps budgets and crack fillers
    /// over a flight against full-resolution reference frames; `bench stability` runs the
    /// scenarios where methods are known to fail.
    #[command(subcommand)]
    Bench(BenchCommand),
}

#[derive(Debug, Subcommand)]
enum BenchCommand {
    /// Error (screen-space pixels, cracks, PSNR) against triangles, frame time and bytes,
    /// each method swept over its own knob (strip masks: fixed budgets; GeoMipMaps: the
    /// error threshold), over cameras along a flight, with popping on an approach to the ground; on
    /// --server and every --data database; writes accuracy.csv, summary.md and charts.
    Accuracy(terrain_client::eval::accuracy::AccuracyArgs),
    /// Named scenarios (grazing views, above the horizon, under the surface, far outside,
    /// memory below one belt, 100 triangles, jumps, special datasets) with every method and
    /// filler; writes stability.md, stability.csv and pictures.
    Stability(terrain_client::eval::stability::StabilityArgs),
    /// The default flight under a memory limit paged as a pyramid of levels (each policy
    /// of sharing the limit) and as level 0 alone: downloaded bytes, and sampled frames'
    /// coverage and screen-space error against the whole database at full resolution;
    /// writes levels.md, levels.csv and levels.png.
    Levels(terrain_client::eval::levels::LevelsArgs),
    /// The projected grids' paper tables on our data: persistent grid mapping's grid sizes
    /// (Livny et al., Table 1) and the error-bounded projective grid uniform and warped,
    /// with and without ray casting (Löffler et al., Tables 1 and 2); writes grids.md.
    Grids(terrain_client::eval::paper_tables::GridsArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        // Colour codes only where a person reads them, not in files or CI logs.
        .with_ansi(std::io::stderr().is_terminal())
        .init();
    // Each command's report is printed once it is done, so that a closed stdout is seen
    // in one place.
    let result: anyhow::Result<String> = match cli.command {
        // The window's event loop needs the main thread, outside any async runtime; the
        // viewer builds the runtime its fetcher runs on.
        Command::View(args) => terrain_client::viewer::run(&args)
            .map(|()| String::new())
            .map_err(anyhow::Error::from),
        Command::Fetch(args) => in_runtime(async move {
            terrain_client::cli::run_fetch(&args)
                .await
                .map(|summary| format!("{summary}\n"))
                .map_err(anyhow::Error::from)
        }),
        Command::Bench(BenchCommand::Accuracy(args)) => in_runtime(async move {
            terrain_client::eval::accuracy::run_each(&args)
                .await
                .map(|reports| {
                    reports
                        .iter()
                        .map(ToString::to_string)
                        .collect::<Vec<_>>()
                        .join("\n")
                })
                .map_err(anyhow::Error::from)
        }),
        Command::Bench(BenchCommand::Stability(args)) if args.list => {
            Ok(terrain_client::eval::stability::list())
        }
        Command::Bench(BenchCommand::Stability(args)) => in_runtime(async move {
            terrain_client::eval::stability::run(&args)
                .await
                .map(|report| report.to_string())
                .map_err(anyhow::Error::from)
        }),
        Command::Bench(BenchCommand::Grids(args)) => in_runtime(async move {
            terrain_client::eval::paper_tables::run(&args)
                .await
                .map(|report| report.markdown)
                .map_err(anyhow::Error::from)
        }),
        Command::Bench(BenchCommand::Levels(args)) => in_runtime(async move {
            terrain_client::eval::levels::run(&args)
                .await
                .map(|report| report.to_string())
                .map_err(anyhow::Error::from)
        }),
        Command::Fly(args) => in_runtime(async move {
            terrain_client::flight::fly(&args)
                .await
                .map(|summary| summary.to_string())
                .map_err(anyhow::Error::from)
        }),
    };
    match result.and_then(|report| print_report(&report)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            // Nobody reads stderr either when it is closed; that is not worth a panic.
            let _ = writeln!(std::io::stderr(), "error: {error:#}");
            ExitCode::FAILURE
        }
    }
}

/// Writes a command's report to stdout. A reader that went away (`terrain-client ... |
/// head`) ends the program quietly and successfully, as ripgrep and the coreutils do:
/// its outputs are written already, and the report was only for the reader.
fn print_report(report: &str) -> anyhow::Result<()> {
    let mut stdout = std::io::stdout().lock();
    match stdout
        .write_all(report.as_bytes())
        .and_then(|()| stdout.flush())
    {
        Err(error) if error.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        Err(error) => Err(anyhow::Error::new(error).context("cannot write to stdout")),
        Ok(()) => Ok(()),
    }
}

/// Runs `work` to completion in a multi-threaded tokio runtime (subcommands without a
/// window).
fn in_runtime(work: impl Future<Output = anyhow::Result<String>>) -> anyhow::Result<String> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?
        .block_on(work)
}
