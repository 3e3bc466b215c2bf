//! What a flight says when it ends: how the frame rate held its target, how well the
//! controller predicted, the memory, the network, the process, and the content changes
//! (a database rebuilt under the flight).

use crate::record::{FrameRecord, RenderRecord, windowed_fps};
use std::fmt;
use std::path::PathBuf;

/// How the frame rate held its target, over the frames after the first second.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameRateSummary {
    pub target_fps: Option<f64>,
    /// Frames after the first second of wall-clock time.
    pub frames: u64,
    /// Median over them of the frame rate over the last second ([`windowed_fps`]): with two
    /// frames in flight, one frame's own time is not its cost.
    pub median_fps: f64,
    /// Share of them at which the frame rate over the last second ([`windowed_fps`]) is
    /// within 10% of the target (`None` without a target).
    pub windowed_within_10_percent: Option<f64>,
    /// Lowest and highest frame rate over the last second, after the first second.
    pub windowed_range: (f64, f64),
    /// The frame-rate controller's prediction error ([`prediction_errors`]): median and
    /// 90th percentile, as fractions; `None` without a target.
    pub prediction_error: Option<(f64, f64)>,
    /// Triangles drawn per second of frame time, whole flight.
    pub triangles_per_s: f64,
    pub mean_triangles: f64,
}

impl FrameRateSummary {
    /// From a flight's records; `None` when nothing was rendered after the first second.
    pub fn of(records: &[FrameRecord]) -> Option<FrameRateSummary> {
        let rendered: Vec<&RenderRecord> =
            records.iter().filter_map(|r| r.render.as_ref()).collect();
        let settled: Vec<&RenderRecord> = records
            .iter()
            .filter(|r| r.wall_s >= 1.0)
            .filter_map(|r| r.render.as_ref())
            .collect();
        if settled.is_empty() {
            return None;
        }
        let target = settled[0].target_fps;
        let windows = windowed_fps(records);
        let mut fps: Vec<f64> = windows.iter().map(|&(_, f)| f).collect();
        fps.sort_by(f64::total_cmp);
        let windowed_within = target.map(|t| {
            windows
                .iter()
                .filter(|(_, f)| (f - t).abs() <= 0.1 * t)
                .count() as f64
                / windows.len().max(1) as f64
        });
        let windowed_range = windows.iter().fold((f64::MAX, 0.0f64), |(lo, hi), (_, f)| {
            (lo.min(*f), hi.max(*f))
        });
        let mut errors = prediction_errors(records);
        errors.sort_by(f64::total_cmp);
        let prediction_error = (target.is_some() && !errors.is_empty()).then(|| {
            (
                errors[errors.len() / 2],
                errors[(errors.len() * 9 / 10).min(errors.len() - 1)],
            )
        });
        let triangles: u64 = rendered
            .iter()
            .map(|r| r.triangles + r.filler_triangles)
            .sum();
        let seconds: f64 = rendered.iter().map(|r| r.frame_ms).sum::<f64>() / 1e3;
        Some(FrameRateSummary {
            target_fps: target,
            frames: settled.len() as u64,
            median_fps: fps.get(fps.len() / 2).copied().unwrap_or(0.0),
            windowed_within_10_percent: windowed_within,
            windowed_range,
            prediction_error,
            triangles_per_s: triangles as f64 / seconds.max(1e-9),
            mean_triangles: rendered.iter().map(|r| r.triangles as f64).sum::<f64>()
                / rendered.len() as f64,
        })
    }
}

/// The frame-rate controller's relative error, `|predicted - measured| / measured`, over
/// each run of [`crate::render::frame::FRAMES_IN_FLIGHT`] consecutive frames after the first
/// second that all carry a prediction: the controller measures frames in such runs (a
/// frame's own time with frames in flight is not its cost), so its prediction is judged on
/// them too.
pub fn prediction_errors(records: &[FrameRecord]) -> Vec<f64> {
    let run = crate::render::frame::FRAMES_IN_FLIGHT as usize;
    let pairs: Vec<(f64, f64)> = records
        .iter()
        .filter(|r| r.wall_s >= 1.0)
        .filter_map(|r| r.render.as_ref())
        .filter_map(|r| r.predicted_ms.map(|p| (p, r.frame_ms)))
        .collect();
    pairs
        .chunks_exact(run)
        .filter_map(|c| {
            let predicted: f64 = c.iter().map(|p| p.0).sum();
            let measured: f64 = c.iter().map(|p| p.1).sum();
            (measured > 0.0).then(|| (predicted - measured).abs() / measured)
        })
        .collect()
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
    /// Largest overshoot of the limit at a frame's end, in bytes (0 if never over).
    pub peak_overshoot_bytes: u64,
    /// Frames at whose end the resident bytes were over the limit.
    pub frames_over_limit: u64,
    pub final_complete_belts: u32,
    pub tiles_fetched: u64,
    pub bytes_downloaded: u64,
    pub evicted_unused_bytes: u64,
    /// Request attempts repeated: after transient failures, corrupt bodies, and tiles
    /// asked for again after a failed request.
    pub retries: u64,
    pub failures: u64,
    /// Tiles given up after repeated failures, with the last failure of each.
    pub unavailable: Vec<crate::scene::UnavailableTile>,
    /// Times the server's content changed under the flight (its database was rebuilt), and
    /// what that did to the resident tiles.
    pub content_changes: Vec<ContentChange>,
    /// Peak resident set size of this process (VmHWM), when the OS reports it.
    pub peak_rss_bytes: Option<u64>,
    /// The program's heap at its peak ([`crate::process::peak_heap_bytes`]).
    pub peak_heap_bytes: u64,
    /// wgpu's allocator report at the frame with the most GPU memory allocated; `None`
    /// without rendering or where the backend gives none.
    pub peak_gpu: Option<crate::process::GpuReport>,
    /// Why no target frame rate applies, when one was asked for and the method shares no
    /// triangle budget.
    pub no_target: Option<String>,
    /// The adapter, when the flight rendered.
    pub adapter: Option<String>,
    pub frame_rate: Option<FrameRateSummary>,
    /// Frame PNGs written.
    pub frames_written: Vec<PathBuf>,
    pub csv: PathBuf,
    pub charts: Vec<PathBuf>,
}

impl fmt::Display for FlightSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
        writeln!(
            f,
            "flew {} frames ({:.1} s of flight in {:.1} s) over {}",
            self.frames, self.duration_s, self.wall_s, self.dataset
        )?;
        let over = if self.frames_over_limit == 0 {
            "never over it".to_string()
        } else {
            format!(
                "OVER it at the end of {} of {} frames, by {} bytes at most",
                self.frames_over_limit, self.frames, self.peak_overshoot_bytes
            )
        };
        writeln!(
            f,
            "  memory    peak {:.2} MiB ({} bytes) of terrain against a limit of {:.2} MiB ({} bytes): {over}",
            mib(self.peak_resident_bytes),
            self.peak_resident_bytes,
            mib(self.memory_limit_bytes),
            self.memory_limit_bytes,
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
        for change in &self.content_changes {
            writeln!(f, "  content   {change}")?;
        }
        for tile in &self.unavailable {
            writeln!(
                f,
                "  missing   tile {} given up after {} failed requests: {}",
                tile.id, tile.failures, tile.error
            )?;
        }
        if let Some(adapter) = &self.adapter {
            writeln!(f, "  adapter   {adapter}")?;
        }
        if let Some(r) = &self.frame_rate {
            write!(
                f,
                "  rendering median {:.1} fps after the first second, {:.0} triangles per frame, {:.2} M triangles/s",
                r.median_fps,
                r.mean_triangles,
                r.triangles_per_s / 1e6
            )?;
            match (r.target_fps, r.windowed_within_10_percent) {
                (Some(t), Some(ww)) => {
                    write!(
                        f,
                        "\n            target {t} fps: frame rate over the last second within 10% of it at {:.0}% of frames (range {:.0}-{:.0})",
                        100.0 * ww,
                        r.windowed_range.0,
                        r.windowed_range.1,
                    )?;
                    match r.prediction_error {
                        Some((median, p90)) => writeln!(
                            f,
                            "; predicted frame time off by {:.0}% (median), {:.0}% (90th percentile)",
                            100.0 * median,
                            100.0 * p90
                        )?,
                        None => writeln!(f)?,
                    }
                }
                _ => match &self.no_target {
                    Some(why) => writeln!(f, " ({why})")?,
                    None => writeln!(f, " (fixed budget)")?,
                },
            }
        }
        write!(
            f,
            "  process   heap peak {:.1} MiB",
            mib(self.peak_heap_bytes)
        )?;
        if let Some(gpu) = self.peak_gpu {
            write!(
                f,
                "; GPU {:.1} MiB allocated at most, {:.1} MiB of it the terrain's (the rest: render targets, pipelines and per-frame buffers)",
                mib(gpu.allocated),
                mib(gpu.terrain)
            )?;
        }
        match self.peak_rss_bytes {
            Some(rss) => writeln!(f, "; RSS peak {:.1} MiB", mib(rss))?,
            None => writeln!(f)?,
        }
        write!(f, "  wrote     {}", self.csv.display())?;
        for chart in &self.charts {
            write!(f, ", {}", chart.display())?;
        }
        if let (Some(first), n) = (self.frames_written.first(), self.frames_written.len()) {
            write!(
                f,
                " and {n} frames in {}",
                first.parent().unwrap_or(first).display()
            )?;
        }
        writeln!(f)
    }
}

/// The server's content changed during a flight: a new content version.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ContentChange {
    pub frame: u64,
    pub from: String,
    pub to: String,
    /// Resident tiles kept (same hashes) and dropped; `None` when the grid changed shape
    /// and paging started again from nothing.
    pub kept_dropped: Option<(u64, u64)>,
}

impl fmt::Display for ContentChange {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "frame {}: content version {} replaced {}; ",
            self.frame, self.to, self.from
        )?;
        match self.kept_dropped {
            Some((kept, dropped)) => write!(
                f,
                "{kept} resident tiles kept (unchanged), {dropped} dropped"
            ),
            None => write!(f, "the grid changed shape, paging started again"),
        }
    }
}
