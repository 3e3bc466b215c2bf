//! The subcommands of the `terrain-client` binary, so the binary itself stays a parser and
//! an exit code. For now one: `fetch`, which downloads the whole database through the
//! client's [`Fetcher`] (retries, backoff, hash checks, decoding off the async threads, as
//! the flights have them), and writes an overview picture and a per-tile CSV. It is the
//! client's end-to-end smoke test and its throughput probe.
//!
//! Owns the IO at the rim: the progress bar, the output files. What it
//! prints and writes is formatted by [`crate::report`] and [`crate::overview`].

use crate::http_client::FetchError;
use crate::output::Output;
use crate::overview::{OverviewError, mosaic};
use crate::report::{FetchSummary, TileReport, csv};
use crate::requests::{FetchEvent, Fetcher, FetcherConfig, Want};
use crate::scene::Scene;
use bytes::Bytes;
use indicatif::{ProgressBar, ProgressStyle};
use std::collections::HashMap;
use std::io::{Cursor, Write as _};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use terrain_shared::{Heights, Manifest, TileId, TileRecord};
use thiserror::Error;
use tokio::task::JoinError;

/// Where `fetch` writes unless told otherwise.
pub const DEFAULT_OUT_DIR: &str = "out/fetch";
/// Requests in flight at once: the fetcher's default, [`crate::requests::DEFAULT_CONCURRENCY`].
pub const DEFAULT_CONCURRENCY: u32 = crate::requests::DEFAULT_CONCURRENCY as u32;
/// Longest side of `overview.png`: enough to see the terrain, small enough to open anywhere.
pub const OVERVIEW_MAX_SIDE: u32 = 1024;
pub const OVERVIEW_FILE: &str = "overview.png";
pub const CSV_FILE: &str = "tiles.csv";
/// Reserved on disk per row of tiles.csv when a fetch starts: more than a row of real
/// heights and sizes takes.
const CSV_ROW_MOST_BYTES: u64 = 128;

/// Arguments of `terrain-client fetch`.
#[derive(Debug, Clone, clap::Args)]
pub struct FetchArgs {
    /// Base URL of the tile server, e.g. http://127.0.0.1:8080 (plain HTTP only).
    #[arg(long, env = "TERRAIN_SERVER")]
    pub server: String,
    /// Directory for overview.png and tiles.csv; created if missing.
    #[arg(long, default_value = DEFAULT_OUT_DIR)]
    pub out: PathBuf,
    /// Requests at once (each retried on transient errors).
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
/// `args.concurrency` requests at once; then writes the overview and the CSV into `args.out`.
pub async fn run_fetch(args: &FetchArgs) -> Result<FetchSummary, CliError> {
    let start = Instant::now();
    let connection = Scene::connect(
        &args.server,
        FetcherConfig {
            concurrency: args.concurrency as usize,
            ..FetcherConfig::default()
        },
        tokio::runtime::Handle::current(),
    )
    .await?;
    let (manifest, mut fetcher) = (connection.manifest, connection.fetcher);
    let server = fetcher.base_url().to_string();
    tracing::info!(
        server,
        dataset = manifest.dataset,
        content_version = manifest.content_version,
        tiles = manifest.levels[0].tiles.len(),
        concurrency = args.concurrency,
        "fetching every tile"
    );

    // The outputs' disk space is reserved before a tile is fetched: a disk too full for
    // them is found now, not after the whole fetch.
    create_dir(&args.out)?;
    let overview_path = args.out.join(OVERVIEW_FILE);
    let csv_path = args.out.join(CSV_FILE);
    let reserve = |path: &std::path::Path, bytes: u64| {
        Output::create(path, bytes).map_err(|source| CliError::Write {
            path: path.to_path_buf(),
            source,
        })
    };
    let mut overview_file = reserve(
        &overview_path,
        crate::overview::png_bound(&manifest, OVERVIEW_MAX_SIDE)?,
    )?;
    let mut csv_file = reserve(
        &csv_path,
        (manifest.levels[0].tiles.len() as u64 + 1) * CSV_ROW_MOST_BYTES,
    )?;

    // Finer texture levels add to the bar as their sizes become known (in the tile blobs).
    let total_bytes: u64 = manifest.levels[0].tiles.iter().map(blob_bytes).sum();
    let bar = progress_bar(total_bytes);
    let fetched = fetch_all(&mut fetcher, &manifest, &bar).await;
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

    let written = |path: &std::path::Path| {
        let path = path.to_path_buf();
        move |source| CliError::Write { path, source }
    };
    let mut png = Vec::new();
    overview
        .write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png)
        .map_err(|source| CliError::EncodeOverview {
            path: overview_path.clone(),
            source,
        })?;
    overview_file
        .write_all(&png)
        .map_err(written(&overview_path))?;
    csv_file
        .write_all(csv(&reports).as_bytes())
        .map_err(written(&csv_path))?;
    overview_file.commit().map_err(written(&overview_path))?;
    csv_file.commit().map_err(written(&csv_path))?;

    let decoded_range_m = reports
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), r| {
            (lo.min(r.min_m), hi.max(r.max_m))
        });
    Ok(FetchSummary {
        server,
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

/// A tile on its way: what has arrived of it.
#[derive(Debug)]
struct Arriving {
    heights: Option<(Heights, u64)>,
    /// Texture levels by level (0 = coarsest).
    textures: Vec<Option<Bytes>>,
    fetch: Duration,
    decode: Duration,
}

/// Every tile of the manifest through the client's [`Fetcher`] (the one the flights use:
/// priority order, at most its concurrency in requests at once, retries with backoff on
/// transient errors, a corrupt body fetched again): each tile's heights with its coarsest
/// texture level, then its finer levels, tiles in the manifest's order. The first request
/// that fails after its retries stops the fetch (dropping the fetcher aborts the rest).
async fn fetch_all(
    fetcher: &mut Fetcher,
    manifest: &Manifest,
    bar: &ProgressBar,
) -> Result<Vec<FetchedTile>, CliError> {
    let level0 = &manifest.levels[0];
    let total = level0.tiles.len();
    let levels = manifest.texture.levels as usize;
    let mut arriving: HashMap<TileId, Arriving> = HashMap::with_capacity(total);
    let mut rank: HashMap<TileId, u64> = HashMap::with_capacity(total);
    for i in 0..total {
        let columns = level0.grid.columns as usize;
        let id = TileId::new((i % columns) as u32, (i / columns) as u32);
        // A tile's finer levels come right after it: priority (tile, level).
        fetcher.request(id, Want::Tile, (i as u64) << 8);
        rank.insert(id, i as u64);
    }
    let mut fetched = Vec::with_capacity(total);
    while fetched.len() < total {
        let events = fetcher.poll();
        if events.is_empty() {
            tokio::time::sleep(Duration::from_millis(2)).await;
            continue;
        }
        for event in events {
            let id = event.id();
            let tile = arriving.entry(id).or_insert_with(|| Arriving {
                heights: None,
                textures: vec![None; levels],
                fetch: Duration::ZERO,
                decode: Duration::ZERO,
            });
            match event {
                FetchEvent::Tile {
                    heights,
                    heights_bytes,
                    coarsest_texture,
                    texture,
                    elapsed,
                    decode,
                    ..
                } => {
                    bar.inc_length(texture.iter().skip(1).map(|b| b.bytes).sum());
                    bar.inc(heights_bytes + coarsest_texture.len() as u64);
                    tile.heights = Some((heights, heights_bytes));
                    if let Some(slot) = tile.textures.first_mut() {
                        *slot = Some(coarsest_texture);
                    }
                    tile.fetch += elapsed.saturating_sub(decode);
                    tile.decode = decode;
                    for (level, blob) in texture.into_iter().enumerate().skip(1) {
                        let priority = (rank[&id] << 8) | level as u64;
                        fetcher.request_texture(id, level as u32, blob, priority);
                    }
                }
                FetchEvent::TextureLevel {
                    level,
                    bytes,
                    elapsed,
                    ..
                } => {
                    bar.inc(bytes.len() as u64);
                    tile.fetch += elapsed;
                    if let Some(slot) = tile.textures.get_mut(level as usize) {
                        *slot = Some(bytes);
                    }
                }
                FetchEvent::Failed { error, .. } => return Err(error.into()),
                // Nothing here asks for other data.
                FetchEvent::Data { .. } => {}
            }
            if !tile.textures.iter().all(Option::is_some) {
                continue;
            }
            if let Some(mut tile) = arriving.remove(&id) {
                match tile.heights.take() {
                    Some(heights) => {
                        fetched.push(finish_tile(manifest, id, heights, tile, bar)?);
                        bar.set_message(format!("{}/{total} tiles", fetched.len()));
                    }
                    // Finer levels before the tile itself: it is still on its way.
                    None => {
                        arriving.insert(id, tile);
                    }
                }
            }
        }
    }
    Ok(fetched)
}

/// The report of a tile whose heights and every texture level arrived.
fn finish_tile(
    manifest: &Manifest,
    id: TileId,
    (heights, heights_len): (Heights, u64),
    tile: Arriving,
    bar: &ProgressBar,
) -> Result<FetchedTile, FetchError> {
    let record = manifest.tile(id).ok_or(FetchError::NotInGrid {
        id,
        columns: manifest.grid(0).columns,
        rows: manifest.grid(0).rows,
    })?;
    let (min_code, max_code) = heights.code_range();
    let to_metres = |code: i32| heights.offset_m + heights.quantum_m * f64::from(code);
    let (min_m, max_m) = (to_metres(min_code), to_metres(max_code));
    let textures: Vec<Bytes> = tile.textures.into_iter().flatten().collect();
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
            texture_bytes: textures.iter().map(|t| t.len() as u64).sum(),
            min_m,
            max_m,
            roughness_m: record.roughness_m,
            decode: tile.decode,
            fetch: tile.fetch,
        },
        finest_texture: textures.last().cloned().unwrap_or_default(),
    })
}

fn blob_bytes(tile: &TileRecord) -> u64 {
    tile.bytes + tile.coarsest_texture_bytes
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
