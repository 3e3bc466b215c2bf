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
    /// Make the database from the region jobs of a build split into jobs (`build --region
    /// I/N`), the same database one build makes.
    Merge(terrain_server::build::jobs::MergeArgs),
    /// Serve a tile database over HTTP.
    Serve(terrain_server::http::ServeArgs),
    /// Upload a finished database to an object store (s3://bucket/prefix) and point the
    /// location at it; `serve s3://bucket/prefix` then serves it, and picks up later ones.
    Publish(terrain_server::store::PublishArgs),
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
        Command::Merge(args) => terrain_server::build::jobs::run_merge_cli(args),
        Command::Serve(args) => terrain_server::http::run_cli(args),
        Command::Export(args) => terrain_server::export::run_cli(args),
        Command::Publish(args) => terrain_server::store::run_publish_cli(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {}", cause_chain(&error));
            ExitCode::FAILURE
        }
    }
}

/// `error` and every cause under it, joined by `: `, each once: a cause whose text the
/// line so far already holds (an error that prints its source, then is given it as its
/// cause) is left out.
fn cause_chain(error: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in error.chain() {
        let line = cause.to_string();
        if line.is_empty() || text.contains(&line) {
            continue;
        }
        if !text.is_empty() {
            text.push_str(": ");
        }
        text.push_str(&line);
    }
    text
}

#[cfg(test)]
mod tests {
    use super::cause_chain;

    #[derive(Debug, thiserror::Error)]
    #[error("disk full")]
    struct Full;

    #[derive(Debug, thiserror::Error)]
    #[error("cannot write web.pack: {0}")]
    struct Write(#[source] Full);

    #[derive(Debug, thiserror::Error)]
    #[error("the web tiles: {0}")]
    struct Web(#[from] Write);

    #[test]
    fn each_cause_is_printed_once_even_when_an_error_prints_its_source_too() {
        let error = anyhow::Error::new(Web(Write(Full))).context("building dem.tif");
        assert_eq!(
            cause_chain(&error),
            "building dem.tif: the web tiles: cannot write web.pack: disk full"
        );
    }
}
