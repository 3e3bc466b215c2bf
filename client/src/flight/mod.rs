//! A headless flight: the camera follows a path while the belt pager keeps the largest
//! square of complete belts that fits the memory limit, the fetcher streams tiles, the
//! renderer draws every frame offscreen, and every frame is recorded.
//!
//! Each frame is a [`Scene::update`] (deliveries, paging, texture budget) and a
//! [`Scene::draw`] (culling, importance, triangle budget, masks, render). The path's clock
//! advances `1 / --fps` per frame, whatever the frame took, so every run flies the same
//! frames; how long a frame took is measured and drives the frame-rate controller. Without
//! rendering (`--no-render`) frames are paced at `--fps` in wall-clock time, or with
//! `--no-wait` each as soon as a request finishes (at the latest at that pace).
//!
//! Outputs (`--out`): `flight.csv` (one row per frame, columns in [`CSV_HEADER`]),
//! `flight.png` (memory, tiles, belts, download rate), `render.png` (target and obtained
//! frame rate, triangles per frame: the top panels of the strip-mask paper's Figures 6 and
//! 7), `frames/frame-NNNNNN.png` every `--frame-every` frames, and a summary on stdout.

mod args;
mod summary;

pub use self::args::{
    DEFAULT_FPS, ErrorCapArgs, FlightArgs, GridArgs, MAX_GRID_SIDE, RenderArgs, StreamArgs,
    parse_size,
};
pub use self::summary::{ContentChange, FlightSummary, FrameRateSummary, prediction_errors};

use crate::http_client::FetchError;
use crate::memory::MemoryError;
use crate::method::MethodKind;
use crate::output::Output;
use crate::path::{CameraPath, PathError};
use crate::render::{Camera, Gpu, GpuError, Offscreen};
use crate::scene::{Reconciled, Scene, SceneError};
use std::io::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use terrain_shared::Manifest;
use thiserror::Error;

pub use crate::scene::expected_tile_bytes;

impl From<crate::output::OutputError> for FlightError {
    fn from(error: crate::output::OutputError) -> FlightError {
        FlightError::Write {
            path: error.path,
            source: error.source,
        }
    }
}

/// The fewest bytes a row of flight.csv takes (a frame without rendering, small numbers):
/// `frames` times this is reserved on disk when the flight starts.
const CSV_ROW_LEAST_BYTES: u64 = 64;
/// At most this much is reserved for flight.csv up front; past it a full disk is found as
/// the rows are written.
const CSV_RESERVE_MAX: u64 = 64 << 20;

/// Why a flight stopped.
#[derive(Debug, Error)]
pub enum FlightError {
    #[error(transparent)]
    Fetch(#[from] FetchError),
    #[error(transparent)]
    Path(#[from] PathError),
    #[error(transparent)]
    Memory(#[from] MemoryError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error(transparent)]
    Scene(#[from] crate::scene::SceneError),
    #[error("cannot write {path}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    /// An output the disk refused while flying: the flight stops there, and what it would
    /// have written is removed, not left cut short.
    #[error(
        "cannot write {path} at frame {frame} of {frames}: the flight stopped there and left no output cut short"
    )]
    WriteWhileFlying {
        path: PathBuf,
        frame: u64,
        frames: u64,
        source: std::io::Error,
    },
    #[error("cannot write {path}: {message}")]
    Image { path: PathBuf, message: String },
    #[error(transparent)]
    Chart(#[from] crate::charts::ChartError),
    #[error("invalid option: {0}")]
    BadOption(String),
    /// Not one tile arrived: a flight of empty frames is no result.
    #[error(
        "no tile arrived in {wall_s:.1} s of flight ({requests} HTTP requests, {failures} failed, \
         {cancelled} cancelled before they landed{last}); flight.csv and the charts in {} \
         show the frames",
        out.display(),
        last = last_failure.as_ref().map(|e| format!("; last failure: {e}")).unwrap_or_default()
    )]
    NothingLoaded {
        wall_s: f64,
        requests: u64,
        failures: u64,
        cancelled: u64,
        last_failure: Option<String>,
        out: PathBuf,
    },
}

pub use crate::record::{CSV_HEADER, FrameRecord, RenderRecord, windowed_fps};

pub use crate::path::heading;

/// The least manifest cap a flight sets, whatever its budget.
pub const MANIFEST_FLOOR_BYTES: u64 = 1 << 20;

/// The most frames a flight flies: a day at 60 fps, whose records (about 200 bytes a
/// frame) stay near a gigabyte.
pub const MAX_FLIGHT_FRAMES: u64 = 5_184_000;

/// Flies `args`' path against its server. Must run inside a multi-threaded tokio runtime.
pub async fn fly(args: &FlightArgs) -> Result<FlightSummary, FlightError> {
    if !(args.fps.is_finite() && args.fps > 0.0 && args.fps <= 1000.0) {
        return Err(FlightError::BadOption(format!(
            "--fps {} must be in (0, 1000]",
            args.fps
        )));
    }
    let render_config = (!args.no_render)
        .then(|| args.render.config())
        .transpose()?;
    let budget = args.stream.budget()?;
    // A manifest the budget could not hold is refused as it arrives; below 1 MiB the
    // manifest is taken, so that a budget too small for the terrain is refused with the
    // least --memory that would do rather than for its manifest.
    let fetcher_config = crate::requests::FetcherConfig {
        max_manifest_bytes: budget
            .budget_bytes
            .clamp(MANIFEST_FLOOR_BYTES, crate::http_client::MAX_MANIFEST_BYTES),
        ..args.stream.fetcher_config()
    };
    let connection = Scene::connect(
        &args.stream.server,
        fetcher_config,
        tokio::runtime::Handle::current(),
    )
    .await?;
    let manifest = Arc::clone(&connection.manifest);
    if let Some(config) = &render_config {
        crate::method::check_database(config.method, &manifest).map_err(FlightError::BadOption)?;
    }
    let path = match &args.flight {
        Some(file) => CameraPath::load(file, &manifest)?,
        None => CameraPath::default_for(&manifest),
    };
    // Each frame keeps a record (flight.csv, the charts): a path whose frames would not fit
    // in memory is refused here, before anything is made or written.
    let frames = (path.duration_s() * args.fps).ceil() + 1.0;
    if frames > MAX_FLIGHT_FRAMES as f64 {
        return Err(FlightError::BadOption(format!(
            "the flight is {:.0} s long, {frames:.0} frames at --fps {}; at most {MAX_FLIGHT_FRAMES} frames are flown (each keeps a row of flight.csv): shorten the path or lower --fps",
            path.duration_s(),
            args.fps
        )));
    }
    let frames = frames as u64;
    let write_err = |path: &std::path::Path| {
        let path = path.to_path_buf();
        move |source| FlightError::Write { path, source }
    };
    let frames_dir = args.out.join("frames");
    let render = match render_config {
        Some(config) => {
            let gpu = Gpu::headless()?;
            crate::method::check_gpu(config.method, gpu.downlevel())
                .map_err(FlightError::BadOption)?;
            let (w, h) = args.render.size;
            let target = Offscreen::new(&gpu, w, h);
            Some((gpu, target, config))
        }
        None => None,
    };

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

    let (target, adapter) = match &render {
        Some((gpu, target, _)) => (Some(target), Some(gpu.description())),
        None => (None, None),
    };
    let scene_render = || {
        render.as_ref().map(|(gpu, _, config)| {
            (
                gpu.clone(),
                crate::render::offscreen::OFFSCREEN_FORMAT,
                *config,
            )
        })
    };
    let mut scene = connection.scene(
        budget.limit_bytes(),
        !args.no_nearest_when_outside,
        scene_render(),
    );
    args.stream.configure(&mut scene);
    let mut fetcher = connection.fetcher;
    let (w, h) = args.render.size;
    scene.set_viewport([w, h]);
    budget.check(scene.least_limit(), &what_needs(args))?;
    // Refused or not, nothing is written before here.
    std::fs::create_dir_all(&args.out).map_err(write_err(&args.out))?;
    if render.is_some() && args.frame_every > 0 {
        std::fs::create_dir_all(&frames_dir).map_err(write_err(&frames_dir))?;
    }
    // flight.csv is written as frames are flown, so a disk that fills is found while flying;
    // the least its rows take is reserved now, so a disk already too full is found at once.
    let csv_path = args.out.join("flight.csv");
    let mut csv = Output::create(
        &csv_path,
        (frames * CSV_ROW_LEAST_BYTES).min(CSV_RESERVE_MAX),
    )
    .map_err(|source| FlightError::WriteWhileFlying {
        path: csv_path.clone(),
        frame: 0,
        frames,
        source,
    })?;
    writeln!(csv, "{CSV_HEADER}").map_err(write_err(&csv_path))?;
    let mut content_changes = Vec::new();
    let mut last_failure = None;
    // A failure that stops the flight; the frames flown so far are still written.
    let mut stopped: Option<FlightError> = None;
    let started = Instant::now();
    let period = Duration::from_secs_f64(1.0 / args.fps);
    let mut ticker = tokio::time::interval(period);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // Grown as frames are flown, not reserved for the whole path up front.
    let mut records = Vec::new();
    let mut frames_written = Vec::new();
    let centre = [manifest.extent_m[0] / 2.0, manifest.extent_m[1] / 2.0];
    let start = path.position_at(0.0);
    let mut yaw = (centre[1] - start[1]).atan2(centre[0] - start[0]);
    // Frames follow each other without a pause (no vsync offscreen): a frame's cost, as the
    // frame-rate controller measures it, runs from the end of the one before it's draw, so
    // that the bookkeeping between draws (the CSV row, a frame PNG) is counted too.
    let mut previous_draw_end: Option<Instant> = None;
    for frame in 0..frames {
        if target.is_some() {
            // Rendering sets the pace; let the runtime's tasks run between frames.
            tokio::task::yield_now().await;
        } else if args.no_wait {
            if frame > 0 {
                fetcher.next_finished(period).await;
            }
            tokio::task::yield_now().await;
        } else {
            ticker.tick().await;
        }
        let update_started = Instant::now();
        let frame_started = previous_draw_end.unwrap_or(update_started);
        let time_s = frame as f64 / args.fps;
        let position = path.position_at(time_s);
        let update = match scene.update(&mut fetcher, frame, position) {
            Ok(update) => update,
            Err(SceneError::TileFailed { id, message }) => {
                // A tile refused (404) is what a client sees when the server's database
                // was rebuilt: its URLs name the old content version. The manifest says
                // whether that is so.
                last_failure = Some(message.clone());
                match reload_content(&mut scene, &mut fetcher, frame).await {
                    Ok(Some((change, reshaped))) => {
                        if let Some(manifest) = reshaped {
                            let pager = crate::page::PagerConfig {
                                columns: manifest.grid(0).columns,
                                rows: manifest.grid(0).rows,
                                memory_limit: budget.limit_bytes(),
                                nearest_when_outside: !args.no_nearest_when_outside,
                                current_over_limit: false,
                            };
                            scene = Scene::new(manifest, pager, scene_render());
                            args.stream.configure(&mut scene);
                            scene.set_viewport([w, h]);
                        }
                        content_changes.push(change);
                        match scene.update(&mut fetcher, frame, position) {
                            Ok(update) => update,
                            Err(error) => {
                                stopped = Some(error.into());
                                break;
                            }
                        }
                    }
                    Ok(None) => {
                        stopped = Some(SceneError::TileFailed { id, message }.into());
                        break;
                    }
                    Err(error) => {
                        stopped = Some(error.into());
                        break;
                    }
                }
            }
        };
        let update_ms = update_started.elapsed().as_secs_f64() * 1e3;
        yaw = heading(&path, time_s, yaw);
        let camera = Camera::new(position, yaw, args.render.pitch_deg.to_radians());
        let drawn = target.and_then(|t| scene.draw(&t.view, &camera, frame_started));
        previous_draw_end = Some(Instant::now());
        let render_record = drawn.map(|d| RenderRecord {
            visible_tiles: d.plan.draws.len() as u32,
            triangles: d.stats.triangles,
            triangles_needed: d.triangles_needed,
            filler_triangles: d.stats.filler_triangles,
            draw_calls: d.stats.draw_calls,
            global_budget: d.plan.budget,
            mask_levels: d.plan.level_histogram(),
            lod_ms: d.lod_ms,
            cpu_ms: update_ms + d.lod_ms + d.stats.encode_ms,
            gpu_ms: d.stats.gpu_ms,
            frame_ms: d.frame_ms,
            predicted_ms: d.predicted_ms,
            target_fps: d.target_fps,
        });
        if let (Some(t), Some((gpu, _, _))) = (target, &render)
            && args.frame_every > 0
            && (frame % args.frame_every == 0 || frame + 1 == frames)
        {
            let file = frames_dir.join(format!("frame-{frame:06}.png"));
            let image = t.read(gpu)?;
            crate::output::write_via(&file, |temp| {
                image.save(temp).map_err(|e| FlightError::Image {
                    path: file.clone(),
                    message: e.to_string(),
                })
            })?;
            frames_written.push(file);
        }
        let stats = fetcher.stats();
        let record = FrameRecord {
            frame,
            time_s,
            wall_s: started.elapsed().as_secs_f64(),
            position_m: position,
            ground_m: scene.ground_under(position),
            current: [update.decision.current.x, update.decision.current.y],
            farthest_complete_belt: update.decision.farthest_complete_belt,
            complete_belts: update.decision.complete_belts,
            resident_tiles: scene.resident_tiles(),
            resident_bytes: scene.resident_bytes(),
            memory_limit_bytes: scene.memory_limit(),
            gpu_bytes: scene.gpu_bytes(),
            heap_bytes: crate::process::heap_bytes(),
            gpu_allocated: scene
                .gpu()
                .and_then(|gpu| crate::process::GpuReport::of(&gpu.device)),
            rss_bytes: crate::process::rss_bytes(),
            bytes_downloaded: stats.bytes_downloaded,
            in_flight: scene.in_flight(),
            retries: retries(&stats, &scene),
            evicted_unused_bytes: scene.evicted_unused_bytes,
            texture_budget_bytes: update.texture_budget,
            render: render_record,
        };
        bar.set_position(frame + 1);
        bar.set_message(match &record.render {
            Some(r) => format!(
                "{} tiles, {:.1}/{:.1} MiB, {:.0} fps, {} triangles",
                record.resident_tiles,
                record.resident_bytes as f64 / crate::memory::MIB,
                record.memory_limit_bytes as f64 / crate::memory::MIB,
                1e3 / r.frame_ms.max(1e-6),
                r.triangles
            ),
            None => format!(
                "{} tiles, {:.1}/{:.1} MiB",
                record.resident_tiles,
                record.resident_bytes as f64 / crate::memory::MIB,
                record.memory_limit_bytes as f64 / crate::memory::MIB
            ),
        });
        if let Err(source) = writeln!(csv, "{}", record.csv_row()) {
            bar.finish_and_clear();
            return Err(FlightError::WriteWhileFlying {
                path: csv_path,
                frame,
                frames,
                source,
            });
        }
        records.push(record);
    }
    bar.finish_and_clear();
    let pending: Vec<_> = fetcher.pending().collect();
    fetcher.cancel(&pending);

    let csv = csv.commit().map_err(write_err(&csv_path))?;
    let mut charts = vec![args.out.join("flight.png")];
    crate::output::write_via(&charts[0], |temp| {
        crate::charts::flight_chart(&records, &manifest.dataset, temp).map_err(FlightError::from)
    })?;
    if records.iter().any(|r| r.render.is_some()) {
        let chart = args.out.join("render.png");
        crate::output::write_via(&chart, |temp| {
            crate::charts::render_chart(&records, &manifest.dataset, temp)
                .map_err(FlightError::from)
        })?;
        charts.push(chart);
    }

    let stats = fetcher.stats();
    if let Some(error) = stopped {
        return Err(error);
    }
    if scene.tiles_fetched == 0 && manifest.tile_count() > 0 {
        return Err(FlightError::NothingLoaded {
            wall_s: started.elapsed().as_secs_f64(),
            requests: stats.requests_started,
            failures: stats.failures,
            cancelled: stats.cancelled,
            last_failure: last_failure
                .or_else(|| scene.unavailable.last().map(|t| t.error.clone())),
            out: args.out.clone(),
        });
    }
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
        frames_over_limit: records
            .iter()
            .filter(|r| r.resident_bytes > r.memory_limit_bytes)
            .count() as u64,
        peak_heap_bytes: crate::process::peak_heap_bytes(),
        peak_gpu: records
            .iter()
            .filter_map(|r| r.gpu_allocated)
            .max_by_key(|g| g.allocated),
        no_target: no_target(args),
        final_complete_belts: last.as_ref().map_or(0, |r| r.complete_belts),
        tiles_fetched: scene.tiles_fetched,
        bytes_downloaded: stats.bytes_downloaded,
        evicted_unused_bytes: scene.evicted_unused_bytes,
        retries: retries(&stats, &scene),
        failures: stats.failures,
        unavailable: scene.unavailable.clone(),
        content_changes,
        peak_rss_bytes: crate::process::peak_rss_bytes(),
        adapter,
        frame_rate: FrameRateSummary::of(&records),
        frames_written,
        csv,
        charts,
    })
}

/// Request attempts repeated so far, as `flight.csv`'s `retries` counts them: the
/// fetcher's retries after transient failures and refetches of corrupt bodies, and the
/// scene's requests for tiles whose earlier request failed.
fn retries(stats: &crate::requests::FetchStats, scene: &Scene) -> u64 {
    stats.retries + stats.corrupt_refetches + scene.requests_repeated
}

/// After a tile was refused: fetches the manifest again and, when its content version
/// changed, hands it to the fetcher and the scene. `None` when the content is the same
/// (the refusal stands); with the change, the new manifest when the scene cannot take it
/// (its grid changed shape) and a new scene must be made of it.
async fn reload_content(
    scene: &mut Scene,
    fetcher: &mut crate::requests::Fetcher,
    frame: u64,
) -> Result<Option<(ContentChange, Option<Arc<Manifest>>)>, FetchError> {
    let manifest = Arc::new(fetcher.fetch_manifest().await?);
    let from = fetcher.manifest().content_version.clone();
    if manifest.content_version == from {
        return Ok(None);
    }
    tracing::warn!(
        "the server's content changed from version {from} to {}: reloading",
        manifest.content_version
    );
    fetcher.replace_manifest(Arc::clone(&manifest));
    let mut change = ContentChange {
        frame,
        from,
        to: manifest.content_version.clone(),
        kept_dropped: None,
    };
    match scene.replace_manifest(Arc::clone(&manifest)) {
        Reconciled::Kept { kept, dropped } => {
            change.kept_dropped = Some((kept, dropped));
            Ok(Some((change, None)))
        }
        Reconciled::Reshaped => Ok(Some((change, Some(manifest)))),
    }
}

/// What a flight's least memory limit is for, for its refusal: the method and frame size,
/// or paging alone.
fn what_needs(args: &FlightArgs) -> String {
    if args.no_render {
        return "paging (--no-render)".to_string();
    }
    let (w, h) = args.render.size;
    format!(
        "--method {} at {w}x{h}{}",
        args.render.method.name(),
        if args.stream.single_level {
            ", one level"
        } else {
            ""
        }
    )
}

/// Why `--target-fps` does not apply to the flight's method, when it does not: only strip
/// masks share a triangle budget out; the other methods draw what their error threshold or
/// grid sets.
fn no_target(args: &FlightArgs) -> Option<String> {
    let method = args.render.method;
    (!args.no_render && args.render.fixed_budget.is_none() && method != MethodKind::StripMasks)
        .then(|| {
            format!(
                "--method {} shares no triangle budget: --target-fps does not apply, what it draws is set by its {}",
                method.name(),
                match method {
                    MethodKind::Pgm | MethodKind::ProjectiveGrid => "grid",
                    MethodKind::Reference => "full resolution of every visible tile",
                    _ => "error threshold",
                }
            )
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_and_bad_ones_say_why() {
        assert_eq!(parse_size("960x540"), Ok((960, 540)));
        assert_eq!(parse_size("64X48"), Ok((64, 48)));
        assert!(parse_size("960").is_err_and(|e| e.contains("WIDTHxHEIGHT")));
        assert!(parse_size("0x10").is_err_and(|e| e.contains("16 to 8192")));
    }

    #[test]
    fn csv_rows_have_one_field_per_column_with_and_without_rendering() {
        let mut record = FrameRecord {
            frame: 1,
            time_s: 0.0,
            wall_s: 0.0,
            position_m: [0.0; 3],
            ground_m: None,
            current: [0, 0],
            farthest_complete_belt: None,
            complete_belts: 0,
            resident_tiles: 0,
            resident_bytes: 0,
            memory_limit_bytes: 0,
            gpu_bytes: 0,
            heap_bytes: 0,
            gpu_allocated: None,
            rss_bytes: None,
            bytes_downloaded: 0,
            in_flight: 0,
            retries: 0,
            evicted_unused_bytes: 0,
            texture_budget_bytes: 0,
            render: None,
        };
        let columns = CSV_HEADER.split(',').count();
        assert_eq!(record.csv_row().split(',').count(), columns);
        record.render = Some(RenderRecord {
            visible_tiles: 3,
            triangles: 10,
            triangles_needed: 4,
            filler_triangles: 6,
            draw_calls: 6,
            global_budget: 12,
            mask_levels: vec![(0, 1), (5, 2)],
            lod_ms: 0.1,
            cpu_ms: 1.0,
            gpu_ms: None,
            frame_ms: 2.0,
            predicted_ms: Some(1.5),
            target_fps: Some(60.0),
        });
        let row = record.csv_row();
        assert_eq!(row.split(',').count(), columns);
        assert!(row.contains(",0:1;5:2,"), "{row}");
    }
}
