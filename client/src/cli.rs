//! The subcommands of the `terrain-client` binary, so the binary itself stays a parser and
//! an exit code. For now one: `fetch`, which downloads the whole database through
//! [`TileClient`], verifies and decodes every blob, and writes an overview picture and a
//! per-tile CSV. It is the client's end-to-end smoke test and its throughput probe.
//!
//! Owns the IO at the rim: the progress bar, the output files, the task pool. What it
//! prints and writes is formatted by [`crate::report`] and [`crate::overview`].

use crate::fetch::{FetchError, TileClient, decode_heights};
use crate::overview::{OverviewError, mosaic};
use crate::report::{FetchSummary, TileReport, csv};
use bytes::Bytes;
use indicatif::{ProgressBar, ProgressStyle};
use std::io::Cursor;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;
use terrain_shared::{Manifest, TileId, TileRecord, routes};
use thiserror::Error;
use tokio::task::{JoinError, JoinSet};

/// Where `fetch` writes unless told otherwise.
pub const DEFAULT_OUT_DIR: &str = "out/fetch";
/// Requests in flight at once. Eight keeps a local server's workers and a LAN busy without
/// queueing behind its concurrency limit (the server sheds load rather than queue).
pub const DEFAULT_CONCURRENCY: u32 = 8;
/// Longest side of `overview.png`: enough to see the terrain, small enough to open anywhere.
pub const OVERVIEW_MAX_SIDE: u32 = 1024;
pub const OVERVIEW_FILE: &str = "overview.png";
pub const CSV_FILE: &str = "tiles.csv";

/// Arguments of `terrain-client fetch`.
#[derive(Debug, Clone, clap::Args)]
pub struct FetchArgs {
    /// Base URL of the tile server, e.g. http://127.0.0.1:8080 (plain HTTP only).
    #[arg(long, env = "TERRAIN_SERVER")]
    pub server: String,
    /// Directory for overview.png and tiles.csv; created if missing.
    #[arg(long, default_value = DEFAULT_OUT_DIR)]
    pub out: PathBuf,
    /// Tiles fetched at once (each tile's requests run one after the other).
    #[arg(long, default_value_t = DEFAULT_CONCURRENCY, value_parser = clap::value_parser!(u32).range(1..=1024))]
    pub concurrency: u32,
}

/// Why `fetch` stopped.
#[derive(Debug, Error)]
pub enum CliError {
    #[error(transparent)]
    Fetch(#[from] FetchError),
    #[error("could not make the overview picture")]
    Overview(#[from] OverviewError),
    #[error("could not encode {path} as PNG")]
    EncodeOverview {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
    #[error("could not write {path}")]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{task} was cancelled before it finished")]
    Cancelled { task: &'static str },
}

/// Runs `fetch`: the manifest, then every tile's heights and texture levels with
/// `args.concurrency` tiles in flight; then writes the overview and the CSV into `args.out`.
pub async fn run_fetch(args: &FetchArgs) -> Result<FetchSummary, CliError> {
    let client = TileClient::new(&args.server)?;
    let start = Instant::now();
    let manifest = Arc::new(client.manifest().await?);
    tracing::info!(
        server = client.base_url(),
        dataset = manifest.dataset,
        content_version = manifest.content_version,
        tiles = manifest.tiles.len(),
        concurrency = args.concurrency,
        "fetching every tile"
    );

    let total_bytes: u64 = manifest.tiles.iter().map(blob_bytes).sum();
    let bar = progress_bar(total_bytes);
    let fetched = fetch_all(&client, &manifest, args.concurrency as usize, &bar).await;
    bar.finish_and_clear();
    let mut fetched = fetched?;
    let elapsed = start.elapsed();
    fetched.sort_by_key(|tile| (tile.report.id.y, tile.report.id.x));
    tracing::info!(
        tiles = fetched.len(),
        elapsed_ms = elapsed.as_millis() as u64,
        "fetched"
    );

    let reports: Vec<TileReport> = fetched.iter().map(|tile| tile.report.clone()).collect();
    let finest: Vec<(TileId, Bytes)> = fetched
        .into_iter()
        .map(|tile| (tile.report.id, tile.finest_texture))
        .collect();
    let for_mosaic = Arc::clone(&manifest);
    let overview =
        tokio::task::spawn_blocking(move || mosaic(&for_mosaic, &finest, OVERVIEW_MAX_SIDE))
            .await
            .map_err(|error| join_failure(error, "making the overview"))??;

    create_dir(&args.out)?;
    let overview_path = args.out.join(OVERVIEW_FILE);
    let mut png = Vec::new();
    overview
        .write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png)
        .map_err(|source| CliError::EncodeOverview {
            path: overview_path.clone(),
            source,
        })?;
    write(&overview_path, &png)?;
    let csv_path = args.out.join(CSV_FILE);
    write(&csv_path, csv(&reports).as_bytes())?;

    let decoded_range_m = reports
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), r| {
            (lo.min(r.min_m), hi.max(r.max_m))
        });
    Ok(FetchSummary {
        server: client.base_url().to_string(),
        dataset: manifest.dataset.clone(),
        content_version: manifest.content_version.clone(),
        tiles: reports.len(),
        heights_bytes: reports.iter().map(|r| r.heights_bytes).sum(),
        texture_bytes: reports.iter().map(|r| r.texture_bytes).sum(),
        elapsed,
        decoded_range_m,
        manifest_range_m: (manifest.heights.min_m, manifest.heights.max_m),
        quantum_m: manifest.heights.quantum_m,
        overview: overview_path,
        overview_size: overview.dimensions(),
        csv: csv_path,
    })
}

/// One tile, fetched, verified and decoded.
#[derive(Debug)]
struct FetchedTile {
    report: TileReport,
    finest_texture: Bytes,
}

/// Every tile of the manifest with at most `concurrency` in flight. The first error stops
/// the fetch: dropping the [`JoinSet`] aborts the tiles still running.
async fn fetch_all(
    client: &TileClient,
    manifest: &Arc<Manifest>,
    concurrency: usize,
    bar: &ProgressBar,
) -> Result<Vec<FetchedTile>, CliError> {
    let total = manifest.tiles.len();
    let mut pending = manifest.tiles.iter().map(TileRecord::id);
    let mut running = JoinSet::new();
    let mut fetched = Vec::with_capacity(total);
    loop {
        while running.len() < concurrency.max(1) {
            let Some(id) = pending.next() else { break };
            running.spawn(fetch_tile(
                client.clone(),
                Arc::clone(manifest),
                id,
                bar.clone(),
            ));
        }
        let Some(joined) = running.join_next().await else {
            break;
        };
        fetched.push(joined.map_err(|error| join_failure(error, "a tile fetch"))??);
        bar.set_message(format!("{}/{total} tiles", fetched.len()));
    }
    Ok(fetched)
}

/// Heights first (so decoding overlaps the texture requests of other tiles), then the
/// texture levels coarsest first, the order a viewer needs them in.
async fn fetch_tile(
    client: TileClient,
    manifest: Arc<Manifest>,
    id: TileId,
    bar: ProgressBar,
) -> Result<FetchedTile, FetchError> {
    let started = Instant::now();
    let heights_bytes = client.heights_bytes(&manifest, id).await?;
    let mut fetch = started.elapsed();
    bar.inc(heights_bytes.len() as u64);

    let decode_started = Instant::now();
    let url = client.url(&routes::heights(&manifest.content_version, id));
    let heights_len = heights_bytes.len() as u64;
    let heights = decode_heights(url, heights_bytes).await?;
    let decode = decode_started.elapsed();
    let (min_code, max_code) = heights.code_range();
    let to_metres = |code: i32| heights.offset_m + heights.quantum_m * f64::from(code);
    let (min_m, max_m) = (to_metres(min_code), to_metres(max_code));

    let mut texture_bytes = 0;
    let mut finest_texture = Bytes::new();
    for level in 0..manifest.texture.levels {
        let started = Instant::now();
        let texture = client.texture(&manifest, id, level).await?;
        fetch += started.elapsed();
        bar.inc(texture.len() as u64);
        texture_bytes += texture.len() as u64;
        finest_texture = texture;
    }

    let record = manifest.tile(id).ok_or(FetchError::NotInGrid {
        id,
        columns: manifest.grid.columns,
        rows: manifest.grid.rows,
    })?;
    // The manifest's per-tile range is stored as f32; half a quantum plus f32 rounding of
    // the largest heights on Earth (~1 mm at 9 km) covers an honest disagreement.
    let tolerance = heights.quantum_m / 2.0 + 1e-3;
    if (f64::from(record.min_m) - min_m).abs() > tolerance
        || (f64::from(record.max_m) - max_m).abs() > tolerance
    {
        bar.suspend(|| {
            tracing::warn!(
                tile = %id, decoded_min_m = min_m, decoded_max_m = max_m,
                manifest_min_m = record.min_m, manifest_max_m = record.max_m,
                "decoded height range differs from the manifest's"
            );
        });
    }
    Ok(FetchedTile {
        report: TileReport {
            id,
            heights_bytes: heights_len,
            texture_bytes,
            min_m,
            max_m,
            roughness_m: record.roughness_m,
            decode,
            fetch,
        },
        finest_texture,
    })
}

fn blob_bytes(tile: &TileRecord) -> u64 {
    tile.heights.bytes + tile.texture.iter().map(|blob| blob.bytes).sum::<u64>()
}

/// Counts bytes rather than tiles: tiles differ in size by orders of magnitude (a flat sea
/// tile is a few hundred bytes), so bytes give the honest rate and time left. indicatif
/// draws nothing when stderr is not a terminal, so logs and CI output stay clean.
fn progress_bar(total_bytes: u64) -> ProgressBar {
    let bar = ProgressBar::new(total_bytes);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} fetching [{elapsed_precise}] {wide_bar} {bytes}/{total_bytes} ({bytes_per_sec}, {eta} left) {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar
}

/// A task that panicked panics here too (a bug, not an error to report); one that was
/// cancelled (the runtime is shutting down) is an error.
fn join_failure(error: JoinError, task: &'static str) -> CliError {
    match error.try_into_panic() {
        Ok(panic) => std::panic::resume_unwind(panic),
        Err(_) => CliError::Cancelled { task },
    }
}

fn create_dir(path: &std::path::Path) -> Result<(), CliError> {
    std::fs::create_dir_all(path).map_err(|source| CliError::Write {
        path: path.to_path_buf(),
        source,
    })
}

fn write(path: &std::path::Path, bytes: &[u8]) -> Result<(), CliError> {
    std::fs::write(path, bytes).map_err(|source| CliError::Write {
        path: path.to_path_buf(),
        source,
    })
}
