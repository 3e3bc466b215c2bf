//! `terrain-server`: build a tile database from a DEM, or serve one over HTTP.
//! Thin on purpose: argument parsing, logging set-up and the exit code; the library does the work.

use clap::{Parser, Subcommand};
use std::io::IsTerminal;
use std::process::ExitCode;

/// Build and serve terrain tile databases.
#[derive(Debug, Parser)]
#[command(name = "terrain-server", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Build a tile database from a DEM (16/8-bit PNG, GeoTIFF, SRTM .hgt) and an optional texture.
    Build(terrain_server::build::BuildArgs),
    /// Serve a tile database over HTTP.
    Serve(terrain_server::http::ServeArgs),
    /// Write a database's XYZ pyramid (Terrarium heights by default) as a PMTiles archive.
    Export(terrain_server::export::ExportArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        // Colour codes only where a person reads them, not in log files or CI logs.
        .with_ansi(std::io::stderr().is_terminal())
        .init();
    let result = match cli.command {
        Command::Build(args) => terrain_server::build::run_cli(args),
        Command::Serve(args) => terrain_server::http::run_cli(args),
        Command::Export(args) => terrain_server::export::run_cli(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error:#}");
            ExitCode::FAILURE
        }
    }
}
