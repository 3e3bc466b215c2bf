//! What `bench accuracy` writes: the CSV of every frame measured, the Markdown summary
//! (and the reference's own floor), the frames as images, and the charts of triangles
//! against error with each method's Pareto front.

use super::{AccuracyArgs, AccuracyReport, Knob, Row, Summary};
use crate::charts::{self, ChartError, XyPanel, XySeries};
use crate::eval::frame::{Capture, Unfilled};
use crate::eval::popping::Popping;
use crate::flight::FlightError;
use crate::method::CrackFiller;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Columns of `accuracy.csv`.
pub const CSV_HEADER: &str = "camera,method,filler,knob,setting,triangles,triangles_needed,used_over_needed,filler_triangles,draw_calls,terrain_pixels,mean_error_px,max_error_px,above_threshold_pct,crack_pixels,hole_pixels,silhouette_pixels,filler_pixels,reference_terrain_pixels,psnr_db,lod_ms,cpu_ms,gpu_ms,frame_ms,oracle_triangles,error_pixels_pct,ray_cast_pct,p99_error_px,leak_pixels";

/// Writes `frame` as `DIR/NAME.png` and, with `unfilled`, `DIR/NAME-filler.png`: the frame
/// with its filler's pixels marked ([`crate::eval::frame::filler_picture`]).
pub(super) fn write_images(
    dir: &Path,
    name: &str,
    frame: &Capture,
    unfilled: Option<&Unfilled>,
    reference: &Capture,
) -> Result<(), FlightError> {
    std::fs::create_dir_all(dir).map_err(|source| FlightError::Write {
        path: dir.to_path_buf(),
        source,
    })?;
    let save = |image: &image::RgbaImage, path: PathBuf| {
        image.save(&path).map_err(|e| FlightError::Image {
            message: e.to_string(),
            path,
        })
    };
    save(&frame.color, dir.join(format!("{name}.png")))?;
    if let Some(unfilled) = unfilled {
        let picture = crate::eval::frame::filler_picture(frame, unfilled, reference);
        save(&picture, dir.join(format!("{name}-filler.png")))?;
    }
    Ok(())
}

pub(super) fn csv_row(r: &Row, oracle: Option<u64>) -> String {
    let m = &r.measured;
    let e = &m.measures.error;
    format!(
        "{},{},{},{},{},{},{},{:.4},{},{},{},{:.4},{:.3},{:.3},{},{},{},{},{},{:.2},{:.3},{:.3},{},{:.3},{},{},{},{:.3},{}",
        r.camera,
        r.config.method.name(),
        r.config.filler.name(),
        r.config.knob.name(),
        r.config.knob.value(),
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
        oracle.map_or(String::new(), |o| o.to_string()),
        m.method_measure("error_pixels_pct")
            .map_or(String::new(), |v| format!("{v:.3}")),
        m.method_measure("ray_cast_pct")
            .map_or(String::new(), |v| format!("{v:.3}")),
        e.p99_px,
        m.measures.leak_pixels,
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
        "| method | setting | triangles | oracle | used/oracle | needed | used/needed | mean / p95 / p99 error (px) | max error (px) | > {} px (%) | crack px | holes px | filler px / leaks | silhouette px | cracks (% terrain) | PSNR (dB) | frame (ms) | CPU (ms) | held (MiB) | popping: colour mean / depth p99 (%) / jump colour / jump depth (%) | error px / ray cast (%) |",
        report.threshold_px
    );
    let _ = writeln!(
        s,
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    );
    for m in &report.summaries {
        let _ = writeln!(
            s,
            "| {} | {} | {:.0} | {:.0} | {:.2} | {:.0} | {:.2} | {:.3} / {:.2} / {:.2} | {:.2} | {:.2} | {:.0} | {:.0} | {} | {:.0} | {:.2} | {:.1} | {:.1} | {:.2} | {:.1} | {} | {} |",
            m.config.series(),
            m.config.knob,
            m.triangles,
            m.oracle_triangles,
            m.used_over_oracle,
            m.triangles_needed,
            m.used_over_needed,
            m.mean_error_px,
            m.p95_error_px,
            m.p99_error_px,
            m.max_error_px,
            m.above_threshold_pct,
            m.crack_pixels,
            m.hole_pixels,
            if m.config.method.uses_filler() && m.config.filler != CrackFiller::None {
                format!("{:.0} / {:.0}", m.filler_pixels, m.leak_pixels)
            } else {
                "-".to_string()
            },
            m.silhouette_pixels,
            m.crack_pct,
            m.psnr_db,
            m.frame_ms,
            m.cpu_ms,
            m.held_bytes / crate::memory::MIB,
            m.popping.map_or("-".to_string(), |p| format!(
                "{:.2} / {:.2} / {:.2} / {:.3}",
                p.colour_mean, p.depth_p99_pct, p.colour_jump, p.depth_jump_pct
            )),
            match (m.error_pixels_pct, m.ray_cast_pct) {
                (Some(e), Some(r)) => format!("{e:.2} / {r:.2}"),
                _ => "-".to_string(),
            },
        );
    }
    if let Some(first) = report.oracle.first() {
        let _ = writeln!(
            s,
            "\nThe oracle per camera: the fewest triangles of a right-triangulated irregular network over the full-resolution tiles in view that keeps every sample {} within the threshold on screen.\n",
            if report.on_screen_oracle {
                "of a cell in view (`--on-screen-oracle`: samples off screen are free)"
            } else {
                "of those tiles, on screen or not,"
            }
        );
        let _ = write!(s, "| threshold (px) |");
        for k in 0..report.oracle.len() {
            let _ = write!(s, " camera {k} |");
        }
        let _ = writeln!(s, "\n|---:|{}", "---:|".repeat(report.oracle.len()));
        for (j, (threshold, _)) in first.iter().enumerate() {
            let _ = write!(s, "| {threshold} |");
            for camera in &report.oracle {
                let _ = write!(s, " {} |", camera.get(j).map_or(0, |(_, n)| *n));
            }
            let _ = writeln!(s);
        }
    }
    oracle_per_camera(&mut s, report);
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

/// Each guaranteed method at its setting of the sweep's threshold, with its rows, one per
/// camera: the error knob's row at that threshold, the largest budget of a budgeted method
/// (within its error cap), and the projective grid at every grid size (it is drawn within
/// the sweep's threshold whatever its grid). Persistent grid mapping has no threshold and
/// is left out.
fn at_threshold(report: &AccuracyReport) -> Vec<(String, Vec<&Row>)> {
    let threshold = report.threshold_px;
    let largest_budget = |series: &str| {
        report
            .rows
            .iter()
            .filter(|r| r.config.series() == series)
            .filter_map(|r| match r.config.knob {
                Knob::Budget(b) => Some(b),
                _ => None,
            })
            .max()
    };
    let at_setting = |row: &Row| match row.config.knob {
        Knob::MaxErrorPx(e) => e == threshold,
        Knob::Budget(b) => Some(b) == largest_budget(&row.config.series()),
        Knob::Grid(_) => row.config.method == crate::method::MethodKind::ProjectiveGrid,
    };
    let mut lines: Vec<(String, Vec<&Row>)> = Vec::new();
    for row in report.rows.iter().filter(|r| at_setting(r)) {
        let name = format!("{} ({})", row.config.series(), row.config.knob);
        match lines.iter_mut().find(|(n, _)| *n == name) {
            Some((_, rows)) => rows.push(row),
            None => lines.push((name, vec![row])),
        }
    }
    lines
}

/// The oracle's triangles for `camera` at the sweep's threshold.
fn oracle_of(report: &AccuracyReport, camera: u32) -> Option<u64> {
    report
        .oracle
        .get(camera as usize)
        .and_then(|c| c.iter().find(|(t, _)| *t == report.threshold_px))
        .map(|(_, n)| *n)
}

/// How a guaranteed method at its setting of the sweep's threshold kept its guarantee over
/// the cameras ([`guarantees`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Guarantee {
    /// `series (setting)`.
    pub name: String,
    pub cameras: usize,
    /// Cameras whose 99th percentile is within the threshold and whose maximum is within
    /// the larger of the threshold and the reference's own maximum on that camera (the
    /// measure's floor).
    pub cameras_held: usize,
    pub worst_p99_px: f64,
    /// The largest maximum error past the larger of the threshold and the floor (0 when
    /// every camera keeps it).
    pub worst_excess_px: f64,
    /// Triangles over the oracle's, summed over the cameras (the summary's
    /// `used_over_oracle`).
    pub over_oracle: f64,
}

/// The guarantee of each method at its setting of the sweep's threshold, held against the
/// measure on every camera: p99 within the threshold, the maximum within the larger of the
/// threshold and the reference's own maximum on that camera, and the triangles against
/// the oracle's.
pub fn guarantees(report: &AccuracyReport) -> Vec<Guarantee> {
    let threshold = report.threshold_px;
    at_threshold(report)
        .into_iter()
        .map(|(name, rows)| {
            let (mut held, mut worst_p99, mut worst_excess) = (0, 0.0f64, 0.0f64);
            for row in &rows {
                let e = &row.measured.measures.error;
                let floor = report
                    .reference_errors
                    .get(row.camera as usize)
                    .map_or(0.0, |r| r.max_px);
                let allowed = threshold.max(floor);
                if e.p99_px <= threshold && e.max_px <= allowed {
                    held += 1;
                }
                worst_p99 = worst_p99.max(e.p99_px);
                worst_excess = worst_excess.max(e.max_px - allowed);
            }
            // The summary's ratio over the same rows.
            let over_oracle = rows.first().map_or(0.0, |row| {
                report
                    .summaries
                    .iter()
                    .find(|s| s.config == row.config)
                    .map_or(0.0, |s| s.used_over_oracle)
            });
            Guarantee {
                name,
                cameras: rows.len(),
                cameras_held: held,
                worst_p99_px: worst_p99,
                worst_excess_px: worst_excess,
                over_oracle,
            }
        })
        .collect()
}

/// The table of triangles over the oracle per camera, for each method at its setting of
/// the sweep's threshold ([`at_threshold`]), then the guarantee of each ([`guarantees`]).
fn oracle_per_camera(s: &mut String, report: &AccuracyReport) {
    let threshold = report.threshold_px;
    let lines: Vec<(String, Vec<(u64, u64)>)> = at_threshold(report)
        .into_iter()
        .map(|(name, rows)| {
            let per_camera = rows
                .iter()
                .filter_map(|r| {
                    oracle_of(report, r.camera).map(|o| (r.measured.report.stats.triangles, o))
                })
                .collect();
            (name, per_camera)
        })
        .filter(|(_, per_camera): &(String, Vec<(u64, u64)>)| !per_camera.is_empty())
        .collect();
    if lines.is_empty() {
        return;
    }
    let cameras = lines.iter().map(|(_, c)| c.len()).max().unwrap_or(0);
    let _ = writeln!(
        s,
        "\nTriangles over the oracle per camera, each method at its setting of the {threshold} px threshold:\n"
    );
    let _ = write!(s, "| method (setting) |");
    for k in 0..cameras {
        let _ = write!(s, " camera {k} |");
    }
    let _ = writeln!(s, " all cameras |\n|---|{}---:|", "---:|".repeat(cameras));
    for (name, per_camera) in &lines {
        let _ = write!(s, "| {name} |");
        for &(triangles, oracle) in per_camera {
            let _ = write!(s, " {:.2} |", triangles as f64 / oracle.max(1) as f64);
        }
        let (used, needed) = per_camera
            .iter()
            .fold((0, 0), |(u, n), &(t, o)| (u + t, n + o));
        let _ = writeln!(s, " {:.2} |", used as f64 / needed.max(1) as f64);
    }
    guarantee_table(s, report);
}

/// The guarantees as a Markdown table ([`guarantees`]).
fn guarantee_table(s: &mut String, report: &AccuracyReport) {
    let rows = guarantees(report);
    if rows.is_empty() {
        return;
    }
    let threshold = report.threshold_px;
    let _ = writeln!(
        s,
        "\nThe guarantee at the {threshold} px threshold, each method at its setting: a camera holds it when its 99th percentile is within {threshold} px and its maximum within the larger of {threshold} px and the reference's own maximum there; triangles over the oracle's over all cameras, against twice.\n"
    );
    let _ = writeln!(
        s,
        "| method (setting) | cameras holding the error | worst p99 (px) | worst max past its allowance (px) | triangles over the oracle | within 2x |\n|---|---:|---:|---:|---:|---|"
    );
    for g in rows {
        let _ = writeln!(
            s,
            "| {} | {} of {} | {:.3} | {:.3} | {:.2} | {} |",
            g.name,
            g.cameras_held,
            g.cameras,
            g.worst_p99_px,
            g.worst_excess_px.max(0.0),
            g.over_oracle,
            if g.over_oracle <= 2.0 { "yes" } else { "no" }
        );
    }
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

pub(super) fn write_outputs(
    args: &AccuracyArgs,
    report: &mut AccuracyReport,
) -> Result<(), FlightError> {
    let out = &args.out;
    let write_err = |path: &Path| {
        let path = path.to_path_buf();
        move |source| FlightError::Write { path, source }
    };
    std::fs::create_dir_all(out).map_err(write_err(out))?;
    let mut csv = String::from(CSV_HEADER);
    csv.push('\n');
    for r in &report.rows {
        let threshold = r.config.threshold_px(report.threshold_px);
        let oracle = report
            .oracle
            .get(r.camera as usize)
            .and_then(|o| o.iter().find(|(t, _)| *t == threshold))
            .map(|(_, n)| *n);
        csv.push_str(&csv_row(r, oracle));
        csv.push('\n');
    }
    let csv_path = out.join("accuracy.csv");
    crate::output::write_file(&csv_path, csv).map_err(write_err(&csv_path))?;
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
    crate::output::write_file(&md_path, header + &summary_markdown(report))
        .map_err(write_err(&md_path))?;
    report.files = vec![csv_path, md_path];
    report.files.extend(draw_charts(report, out)?);
    Ok(())
}

/// The four charts of the sweep.
pub(super) fn draw_charts(report: &AccuracyReport, out: &Path) -> Result<Vec<PathBuf>, ChartError> {
    let mut series_names: Vec<String> = Vec::new();
    for s in &report.summaries {
        if !series_names.contains(&s.config.series()) {
            series_names.push(s.config.series());
        }
    }
    // One line per method and filler, through its knob's settings; `f` leaves out the
    // settings a chart has no place for.
    let series_of = |f: &dyn Fn(&Summary) -> Option<(f64, f64)>| -> Vec<XySeries> {
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
                    .filter_map(f)
                    .collect(),
                dashed: false,
            })
            .filter(|s| !s.points.is_empty())
            .collect()
    };
    let series = |f: &dyn Fn(&Summary) -> (f64, f64)| series_of(&|s| Some(f(s)));
    let budget = |s: &Summary| match s.config.knob {
        Knob::Budget(b) => Some(f64::from(b)),
        Knob::MaxErrorPx(_) | Knob::Grid(_) => None,
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
                series: with_front(series(&|s| (s.triangles, s.mean_error_px))),
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
            series: with_front(series(&|s| (s.frame_ms, s.mean_error_px))),
        }],
        &path,
    )?;
    files.push(path);
    let path = out.join("error-vs-bytes.png");
    charts::xy_chart(
        &[XyPanel {
            title: format!(
                "{title}: mean screen-space error against bytes held (CPU and GPU, whole database resident)"
            ),
            x_desc: "bytes held after the frame (MiB)".into(),
            y_desc: "mean error (px)".into(),
            log_x: false,
            series: with_front(series(&|s| {
                (s.held_bytes / crate::memory::MIB, s.mean_error_px)
            })),
        }],
        &path,
    )?;
    files.push(path);
    if report.summaries.iter().any(|s| s.popping.is_some()) {
        let path = out.join("popping.png");
        let popping = |f: &dyn Fn(&Popping) -> f64| {
            series_of(&|s| s.popping.as_ref().map(|p| (s.triangles, f(p))))
        };
        charts::xy_chart(
            &[
                XyPanel {
                    title: format!(
                        "{title}: popping, colour change between frames beyond the reference's"
                    ),
                    x_desc: "triangles per frame (log)".into(),
                    y_desc: "mean colour change (0-255)".into(),
                    log_x: true,
                    series: popping(&|p| p.colour_mean),
                },
                XyPanel {
                    title: "depth change between frames beyond the reference's, 99th percentile"
                        .into(),
                    x_desc: "triangles per frame (log)".into(),
                    y_desc: "depth change (% of distance)".into(),
                    log_x: true,
                    series: popping(&|p| p.depth_p99_pct),
                },
                XyPanel {
                    title: "the jump: the largest step's mean colour change beyond its neighbours'"
                        .into(),
                    x_desc: "triangles per frame (log)".into(),
                    y_desc: "mean colour change (0-255)".into(),
                    log_x: true,
                    series: popping(&|p| p.colour_jump),
                },
                XyPanel {
                    title: "the jump in depth: the largest step's beyond its neighbours'".into(),
                    x_desc: "triangles per frame (log)".into(),
                    y_desc: "mean depth change (% of distance)".into(),
                    log_x: true,
                    series: popping(&|p| p.depth_jump_pct),
                },
            ],
            &path,
        )?;
        files.push(path);
    }
    let path = out.join("cracks-vs-budget.png");
    let mut holes = series_of(&|s| budget(s).map(|b| (b, s.hole_pixels)));
    for h in &mut holes {
        h.name = format!("{} (left as holes)", h.name);
        h.dashed = true;
    }
    let mut cracks = series_of(&|s| budget(s).map(|b| (b, s.crack_pixels)));
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
    // The fillers side by side: where each shows without a crack, and what it does to the
    // largest errors.
    let filled = |s: &Summary| s.config.method.uses_filler();
    let fillers = |f: &dyn Fn(&Summary) -> f64| {
        series_of(&|s| budget(s).filter(|_| filled(s)).map(|b| (b, f(s))))
    };
    if !fillers(&|s| s.leak_pixels).is_empty() {
        let path = out.join("fillers-vs-budget.png");
        charts::xy_chart(
            &[
                XyPanel {
                    title: format!("{title}: filler pixels where the mesh has no crack (leaks)"),
                    x_desc: "global triangle budget (log)".into(),
                    y_desc: "pixels per frame".into(),
                    log_x: true,
                    series: fillers(&|s| s.leak_pixels),
                },
                XyPanel {
                    title: "largest error over the cameras".into(),
                    x_desc: "global triangle budget (log)".into(),
                    y_desc: "max error (px)".into(),
                    log_x: true,
                    series: fillers(&|s| s.max_error_px),
                },
                XyPanel {
                    title: "99th percentile error (per frame, mean)".into(),
                    x_desc: "global triangle budget (log)".into(),
                    y_desc: "p99 error (px)".into(),
                    log_x: true,
                    series: fillers(&|s| s.p99_error_px),
                },
            ],
            &path,
        )?;
        files.push(path);
    }
    let path = out.join("used-vs-needed.png");
    let mut used = series_of(&|s| budget(s).map(|b| (b, s.triangles)));
    used.truncate(1);
    if let Some(u) = used.first_mut() {
        u.name = format!("used ({})", u.name);
    }
    let mut needed = series_of(&|s| budget(s).map(|b| (b, s.triangles_needed)));
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
                series: series_of(&|s| budget(s).map(|b| (b, s.used_over_needed))),
            },
        ],
        &path,
    )?;
    files.push(path);
    Ok(files)
}

/// The points of `points` no other point beats on both axes (smaller x and smaller y),
/// by increasing x: the Pareto front of error against a cost.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let mut sorted: Vec<(f64, f64)> = points
        .iter()
        .copied()
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .collect();
    sorted.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let mut front: Vec<(f64, f64)> = Vec::new();
    for p in sorted {
        if front.last().is_none_or(|last| p.1 < last.1) {
            front.push(p);
        }
    }
    front
}

/// `series` and, dashed in black, the Pareto front over all their points.
pub(super) fn with_front(mut series: Vec<XySeries>) -> Vec<XySeries> {
    let all: Vec<(f64, f64)> = series.iter().flat_map(|s| s.points.clone()).collect();
    series.push(XySeries {
        name: "Pareto front (all methods)".into(),
        colour: plotters::style::RGBColor(0, 0, 0),
        points: pareto_front(&all),
        dashed: true,
    });
    series
}
