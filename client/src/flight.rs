//! A headless flight: the viewpoint follows a camera path while the belt pager keeps the
//! largest square of complete belts that fits the memory limit, the fetcher streams tiles,
//! and every frame is recorded.
//!
//! Per frame, in order: deliveries from the fetcher become resident tiles (their bytes
//! counted by kind); the pure pager ([`crate::page::decide`]) sees the viewpoint, the
//! resident bytes and what is in flight, and decides; cancellations and evictions are
//! carried out and new requests queued; the frame is recorded. The pager never waits: a
//! frame takes what has arrived and moves on, as a renderer's frame would.
//!
//! Outputs (`--out`): `flight.csv` (one row per frame, columns in [`CSV_HEADER`]),
//! `flight.png` (the charts), and a summary on stdout.

use crate::fetch::{FetchError, TileClient};
use crate::fetcher::{FailureKind, FetchEvent, Fetcher, FetcherConfig, Want};
use crate::memory::{MemoryBudget, MemoryError, MemorySize, TileBytes};
use crate::page::{self, PagerConfig, PagerView};
use crate::path::{CameraPath, PathError};
use std::fmt;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use terrain_shared::{Manifest, TileId};
use thiserror::Error;

/// Frames per second of the flight's clock: the rate a viewer would page at.
pub const DEFAULT_FPS: f64 = 30.0;

/// `terrain-client fly`.
#[derive(Debug, Clone, clap::Args)]
pub struct FlightArgs {
    /// Base URL of the tile server, e.g. http://127.0.0.1:8080.
    #[arg(long, env = "TERRAIN_SERVER")]
    pub server: String,
    /// Camera path: a .json or .csv file of keyframes (see docs/flight.md). Default: a lap
    /// over the whole terrain, then a few seconds still.
    #[arg(long)]
    pub flight: Option<PathBuf>,
    /// Memory budget for tiles, e.g. 64MiB. Default: the machine's available memory.
    #[arg(long)]
    pub memory: Option<MemorySize>,
    /// Share of the budget the pager fills, in percent (the rest is the margin for the belt
    /// being fetched).
    #[arg(long, default_value_t = crate::memory::DEFAULT_LIMIT_PERCENT)]
    pub limit_percent: f64,
    /// Directory for flight.csv and flight.png; created if missing.
    #[arg(long, default_value = "out/flight")]
    pub out: PathBuf,
    /// Frames per second of the flight.
    #[arg(long, default_value_t = DEFAULT_FPS)]
    pub fps: f64,
    /// HTTP requests at once.
    #[arg(long, default_value_t = 8)]
    pub concurrency: usize,
    /// Do not make the nearest tile current when the viewpoint is off the terrain (for
    /// terrains placed side by side).
    #[arg(long)]
    pub no_nearest_when_outside: bool,
    /// No progress bar.
    #[arg(long, short)]
    pub quiet: bool,
}

/// Why a flight stopped.
#[derive(Debug, Error)]
pub enum FlightError {
    #[error(transparent)]
    Fetch(#[from] FetchError),
    #[error(transparent)]
    Path(#[from] PathError),
    #[error(transparent)]
    Memory(#[from] MemoryError),
    #[error("tile {id} cannot be fetched: {message}")]
    TileFailed { id: TileId, message: String },
    #[error("cannot write {path}: {source}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(transparent)]
    Chart(#[from] crate::charts::ChartError),
    #[error("invalid option: {0}")]
    BadOption(String),
}

/// Columns of `flight.csv`, one row per frame.
pub const CSV_HEADER: &str = "frame,time_s,wall_s,x_m,y_m,z_m,ground_m,current_x,current_y,farthest_complete_belt,complete_belts,resident_tiles,resident_bytes,memory_limit_bytes,bytes_downloaded,in_flight,retries,evicted_unused_bytes";

/// One frame of a flight, as written to `flight.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRecord {
    pub frame: u64,
    /// Flight time: frame / fps.
    pub time_s: f64,
    /// Wall-clock seconds since the flight started.
    pub wall_s: f64,
    pub position_m: [f64; 3],
    /// Terrain height under the viewpoint (nearest sample of the resident current tile);
    /// `None` while that tile is not resident or the viewpoint is off the terrain.
    pub ground_m: Option<f64>,
    pub current: [i64; 2],
    /// Belt index of the farthest complete belt; `None` while the current tile is missing.
    pub farthest_complete_belt: Option<u32>,
    pub complete_belts: u32,
    pub resident_tiles: u64,
    pub resident_bytes: u64,
    pub memory_limit_bytes: u64,
    /// Bytes of response bodies received so far (retries included).
    pub bytes_downloaded: u64,
    pub in_flight: u64,
    pub retries: u64,
    /// Downloaded bytes of tiles evicted before they were ever part of the complete square.
    pub evicted_unused_bytes: u64,
}

impl FrameRecord {
    pub fn csv_row(&self) -> String {
        format!(
            "{},{:.4},{:.4},{:.1},{:.1},{:.1},{},{},{},{},{},{},{},{},{},{},{},{}",
            self.frame,
            self.time_s,
            self.wall_s,
            self.position_m[0],
            self.position_m[1],
            self.position_m[2],
            self.ground_m.map_or(String::new(), |g| format!("{g:.1}")),
            self.current[0],
            self.current[1],
            self.farthest_complete_belt
                .map_or(String::new(), |b| b.to_string()),
            self.complete_belts,
            self.resident_tiles,
            self.resident_bytes,
            self.memory_limit_bytes,
            self.bytes_downloaded,
            self.in_flight,
            self.retries,
            self.evicted_unused_bytes,
        )
    }
}

/// A tile held in memory: its data (what a renderer will upload) and what it costs.
#[derive(Debug, Clone)]
struct ResidentTile {
    heights: terrain_shared::Heights,
    /// Encoded texture levels held, coarsest first.
    textures: Vec<bytes::Bytes>,
    bytes: TileBytes,
    /// Bytes downloaded for it (heights and texture bodies).
    downloaded: u64,
    /// Whether it was ever part of the complete square (what a renderer would draw).
    used: bool,
}

/// What the flight ended with.
#[derive(Debug, Clone)]
pub struct FlightSummary {
    pub dataset: String,
    pub frames: u64,
    pub duration_s: f64,
    pub wall_s: f64,
    pub memory_limit_bytes: u64,
    pub peak_resident_bytes: u64,
    /// Largest overshoot of the limit, in bytes (0 if never over).
    pub peak_overshoot_bytes: u64,
    pub final_complete_belts: u32,
    pub tiles_fetched: u64,
    pub bytes_downloaded: u64,
    pub evicted_unused_bytes: u64,
    pub retries: u64,
    pub failures: u64,
    /// Peak resident set size of this process (VmHWM), when the OS reports it.
    pub peak_rss_bytes: Option<u64>,
    pub csv: PathBuf,
    pub chart: PathBuf,
}

impl fmt::Display for FlightSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
        writeln!(
            f,
            "flew {} frames ({:.1} s of flight in {:.1} s) over {}",
            self.frames, self.duration_s, self.wall_s, self.dataset
        )?;
        writeln!(
            f,
            "  memory    peak {:.2} MiB of tiles against a limit of {:.2} MiB (peak overshoot {:.2} MiB)",
            mib(self.peak_resident_bytes),
            mib(self.memory_limit_bytes),
            mib(self.peak_overshoot_bytes)
        )?;
        writeln!(
            f,
            "  square    {} complete belts at the end",
            self.final_complete_belts
        )?;
        writeln!(
            f,
            "  network   {} tiles, {:.2} MiB downloaded ({:.2} MiB evicted before use), {} retries, {} failures",
            self.tiles_fetched,
            mib(self.bytes_downloaded),
            mib(self.evicted_unused_bytes),
            self.retries,
            self.failures
        )?;
        if let Some(rss) = self.peak_rss_bytes {
            writeln!(f, "  process   peak RSS {:.1} MiB", mib(rss))?;
        }
        writeln!(
            f,
            "  wrote     {} and {}",
            self.csv.display(),
            self.chart.display()
        )
    }
}

/// Flies `args`' path against its server. Must run inside a multi-threaded tokio runtime.
pub async fn fly(args: &FlightArgs) -> Result<FlightSummary, FlightError> {
    if !(args.fps.is_finite() && args.fps > 0.0 && args.fps <= 1000.0) {
        return Err(FlightError::BadOption(format!(
            "--fps {} must be in (0, 1000]",
            args.fps
        )));
    }
    if args.concurrency == 0 {
        return Err(FlightError::BadOption(
            "--concurrency must be at least 1".into(),
        ));
    }
    let budget = MemoryBudget::new(args.memory, args.limit_percent)?;
    let client = TileClient::new(&args.server)?;
    let manifest = Arc::new(client.manifest().await?);
    let path = match &args.flight {
        Some(file) => CameraPath::load(file, &manifest)?,
        None => CameraPath::default_for(&manifest),
    };
    std::fs::create_dir_all(&args.out).map_err(|source| FlightError::Write {
        path: args.out.clone(),
        source,
    })?;

    let config = FetcherConfig {
        concurrency: args.concurrency,
        ..FetcherConfig::default()
    };
    let mut fetcher = Fetcher::new(
        client,
        Arc::clone(&manifest),
        config,
        tokio::runtime::Handle::current(),
    );
    let pager = PagerConfig {
        columns: manifest.grid.columns,
        rows: manifest.grid.rows,
        memory_limit: budget.limit_bytes(),
        nearest_when_outside: !args.no_nearest_when_outside,
    };
    let frames = (path.duration_s() * args.fps).ceil() as u64 + 1;
    let bar = if args.quiet {
        indicatif::ProgressBar::hidden()
    } else {
        indicatif::ProgressBar::new(frames)
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} flying [{elapsed_precise}] {wide_bar} {pos}/{len} frames {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );

    let mut flight = FlightState::new(&manifest, pager);
    let started = Instant::now();
    let mut ticker = tokio::time::interval(Duration::from_secs_f64(1.0 / args.fps));
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut records = Vec::with_capacity(frames as usize);
    for frame in 0..frames {
        ticker.tick().await;
        let time_s = frame as f64 / args.fps;
        let position = path.position_at(time_s);
        let record = flight.frame(
            &mut fetcher,
            frame,
            time_s,
            started.elapsed().as_secs_f64(),
            position,
        )?;
        bar.set_position(frame + 1);
        bar.set_message(format!(
            "{} tiles, {:.1}/{:.1} MiB",
            record.resident_tiles,
            record.resident_bytes as f64 / 1048576.0,
            record.memory_limit_bytes as f64 / 1048576.0
        ));
        records.push(record);
    }
    bar.finish_and_clear();
    fetcher.cancel(&manifest.tiles.iter().map(|t| t.id()).collect::<Vec<_>>());

    let csv = args.out.join("flight.csv");
    let mut text = String::with_capacity(records.len() * 120);
    text.push_str(CSV_HEADER);
    text.push('\n');
    for record in &records {
        text.push_str(&record.csv_row());
        text.push('\n');
    }
    std::fs::write(&csv, text).map_err(|source| FlightError::Write {
        path: csv.clone(),
        source,
    })?;
    let chart = args.out.join("flight.png");
    crate::charts::flight_chart(&records, &manifest.dataset, &chart)?;

    let stats = fetcher.stats();
    let last = records.last().cloned();
    Ok(FlightSummary {
        dataset: manifest.dataset.clone(),
        frames,
        duration_s: path.duration_s(),
        wall_s: started.elapsed().as_secs_f64(),
        memory_limit_bytes: budget.limit_bytes(),
        peak_resident_bytes: records.iter().map(|r| r.resident_bytes).max().unwrap_or(0),
        peak_overshoot_bytes: records
            .iter()
            .map(|r| r.resident_bytes.saturating_sub(r.memory_limit_bytes))
            .max()
            .unwrap_or(0),
        final_complete_belts: last.as_ref().map_or(0, |r| r.complete_belts),
        tiles_fetched: flight.tiles_fetched,
        bytes_downloaded: stats.bytes_downloaded,
        evicted_unused_bytes: flight.evicted_unused_bytes,
        retries: stats.retries,
        failures: stats.failures,
        peak_rss_bytes: peak_rss_bytes(),
        csv,
        chart,
    })
}

/// The flight's memory: what is resident, and the counters of the CSV.
#[derive(Debug)]
struct FlightState {
    columns: u32,
    tile_size: u32,
    tile_extent_m: [f64; 2],
    pager: PagerConfig,
    tiles: Vec<Option<ResidentTile>>,
    resident_bytes: Vec<u64>,
    /// What each tile will hold once resident, from the manifest's sizes: the pager admits a
    /// belt only if it fits.
    expected_bytes: Vec<u64>,
    in_flight: Vec<bool>,
    tiles_fetched: u64,
    evicted_unused_bytes: u64,
}

impl FlightState {
    fn new(manifest: &Manifest, pager: PagerConfig) -> FlightState {
        let count = manifest.tiles.len();
        let cells = f64::from(manifest.tile_size - 1);
        FlightState {
            columns: manifest.grid.columns,
            tile_size: manifest.tile_size,
            tile_extent_m: [cells * manifest.spacing_m[0], cells * manifest.spacing_m[1]],
            pager,
            tiles: vec![None; count],
            resident_bytes: vec![0; count],
            expected_bytes: manifest
                .tiles
                .iter()
                .map(|t| expected_tile_bytes(manifest, t).total())
                .collect(),
            in_flight: vec![false; count],
            tiles_fetched: 0,
            evicted_unused_bytes: 0,
        }
    }

    fn index(&self, id: TileId) -> usize {
        id.y as usize * self.columns as usize + id.x as usize
    }

    /// One frame: deliveries, decision, actions, record.
    fn frame(
        &mut self,
        fetcher: &mut Fetcher,
        frame: u64,
        time_s: f64,
        wall_s: f64,
        position: [f64; 3],
    ) -> Result<FrameRecord, FlightError> {
        for event in fetcher.poll() {
            match event {
                FetchEvent::Tile {
                    id,
                    heights,
                    heights_bytes,
                    coarsest_texture,
                    ..
                } => {
                    let bytes = TileBytes {
                        decoded_heights: std::mem::size_of_val(heights.codes.as_slice()) as u64,
                        textures: coarsest_texture.len() as u64,
                        ..TileBytes::default()
                    };
                    let i = self.index(id);
                    self.resident_bytes[i] = bytes.total();
                    self.tiles[i] = Some(ResidentTile {
                        heights,
                        downloaded: heights_bytes + coarsest_texture.len() as u64,
                        textures: vec![coarsest_texture],
                        bytes,
                        used: false,
                    });
                    self.tiles_fetched += 1;
                }
                FetchEvent::TextureLevel { id, bytes, .. } => {
                    let i = self.index(id);
                    if let Some(tile) = &mut self.tiles[i] {
                        tile.bytes.textures += bytes.len() as u64;
                        tile.downloaded += bytes.len() as u64;
                        tile.textures.push(bytes);
                        self.resident_bytes[i] = tile.bytes.total();
                    }
                }
                FetchEvent::Failed { id, error, .. } => {
                    // A tile the server refuses (4xx) will never arrive: the flight cannot
                    // complete its square, so it stops with the server's reason. Corrupt or
                    // unreachable tiles are asked for again by the pager on a later frame.
                    if FailureKind::of(&error) == FailureKind::Permanent {
                        return Err(FlightError::TileFailed {
                            id,
                            message: error.to_string(),
                        });
                    }
                    tracing::warn!(tile = %id, error = %error, "tile failed after retries; it will be requested again");
                }
            }
        }
        fetcher.mark_pending(&mut self.in_flight, self.columns);
        let viewpoint = [
            position[0] / self.tile_extent_m[0],
            position[1] / self.tile_extent_m[1],
        ];
        let view = PagerView {
            viewpoint,
            resident_bytes: &self.resident_bytes,
            in_flight: &self.in_flight,
            expected_bytes: Some(&self.expected_bytes),
        };
        let decision = page::decide(&self.pager, &view);

        fetcher.cancel(&decision.cancel);
        for &id in &decision.evict {
            let i = self.index(id);
            if let Some(tile) = self.tiles[i].take()
                && !tile.used
            {
                self.evicted_unused_bytes += tile.downloaded;
            }
            self.resident_bytes[i] = 0;
        }
        for (rank, &id) in decision.fetch.iter().enumerate() {
            // Earlier frames' requests go first; within a frame, the pager's order (nearest first).
            fetcher.request(id, Want::Tile, (frame << 20) | rank as u64);
        }
        for id in page::square_tiles(&self.pager, decision.current, decision.complete_belts) {
            let i = self.index(id);
            if let Some(tile) = &mut self.tiles[i] {
                tile.used = true;
            }
        }

        let stats = fetcher.stats();
        Ok(FrameRecord {
            frame,
            time_s,
            wall_s,
            position_m: position,
            ground_m: self.ground_under(position),
            current: [decision.current.x, decision.current.y],
            farthest_complete_belt: decision.farthest_complete_belt,
            complete_belts: decision.complete_belts,
            resident_tiles: self.tiles.iter().filter(|t| t.is_some()).count() as u64,
            resident_bytes: self.resident_bytes.iter().sum(),
            memory_limit_bytes: self.pager.memory_limit,
            bytes_downloaded: stats.bytes_downloaded,
            in_flight: fetcher.pending_count() as u64,
            retries: stats.retries,
            evicted_unused_bytes: self.evicted_unused_bytes,
        })
    }
}

impl FlightState {
    /// Height of the nearest sample under `position`, if its tile is resident.
    fn ground_under(&self, position: [f64; 3]) -> Option<f64> {
        let cells = f64::from(self.tile_size - 1);
        let (tx, ty) = (
            position[0] / self.tile_extent_m[0],
            position[1] / self.tile_extent_m[1],
        );
        if tx < 0.0
            || ty < 0.0
            || tx >= f64::from(self.columns)
            || ty >= (self.tiles.len() / self.columns as usize) as f64
        {
            return None;
        }
        let tile = self.tiles[self.index(TileId::new(tx as u32, ty as u32))].as_ref()?;
        let x = ((tx - tx.floor()) * cells).round() as usize;
        let y = ((ty - ty.floor()) * cells).round() as usize;
        Some(tile.heights.metres(x, y))
    }
}

/// What a tile holds once resident, known from the manifest before it is fetched: the same
/// accounting as a delivered tile's (decoded codes, coarsest texture level).
pub fn expected_tile_bytes(manifest: &Manifest, tile: &terrain_shared::TileRecord) -> TileBytes {
    TileBytes {
        decoded_heights: u64::from(manifest.tile_size).pow(2) * std::mem::size_of::<i32>() as u64,
        textures: tile.texture.first().map_or(0, |level| level.bytes),
        ..TileBytes::default()
    }
}

/// Peak resident set size of this process, from /proc/self/status (Linux).
pub fn peak_rss_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    Some(line.split_whitespace().nth(1)?.parse::<u64>().ok()? * 1024)
}
