//! Charts of a flight as PNG, in the spirit of the strip-mask paper's Figures 6 and 7:
//! memory used over the flight (their bottom panels) and frame rate and triangles per frame
//! (their top panels), drawn with plotters from the per-frame
//! records. Pure apart from writing the file: records in, picture out.
//!
//! plotters' bitmap backend draws text with a font it is given; the project ships DejaVu
//! Sans (`assets/fonts`, its licence beside it) so charts look the same on every machine.

use crate::flight::FrameRecord;
use plotters::prelude::*;
use std::path::Path;
use thiserror::Error;

const FONT: &[u8] = include_bytes!("../assets/fonts/DejaVuSans.ttf");
const WIDTH: u32 = 1200;
const PANEL_HEIGHT: u32 = 260;
const MIB: f64 = 1024.0 * 1024.0;

#[derive(Debug, Error)]
#[error("cannot draw chart {path}: {message}")]
pub struct ChartError {
    pub path: String,
    pub message: String,
}

fn register_font() {
    // Registering twice is harmless; plotters keeps the last one.
    let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
}

/// One line of a panel: its legend, colour and points (flight time, value).
type Series<'a> = (&'a str, RGBColor, Vec<(f64, f64)>);

/// One panel: named series over flight time.
struct Panel<'a> {
    title: String,
    y_label: &'a str,
    series: Vec<Series<'a>>,
    /// Top of the y axis; default: 10% above the largest value.
    y_max: Option<f64>,
}

/// Writes the flight chart: memory, resident tiles, complete belts and download rate over time.
pub fn flight_chart(records: &[FrameRecord], title: &str, path: &Path) -> Result<(), ChartError> {
    let time = |r: &FrameRecord| r.time_s;
    let rate = download_rate_mbit(records);
    let panels = [
        Panel {
            title: format!("{title}: memory held by resident tiles"),
            y_label: "MiB",
            y_max: None,
            series: vec![
                (
                    "resident",
                    BLUE,
                    records
                        .iter()
                        .map(|r| (time(r), r.resident_bytes as f64 / MIB))
                        .collect(),
                ),
                (
                    "limit",
                    RED,
                    records
                        .iter()
                        .map(|r| (time(r), r.memory_limit_bytes as f64 / MIB))
                        .collect(),
                ),
            ],
        },
        Panel {
            title: "tiles".into(),
            y_label: "tiles",
            y_max: None,
            series: vec![
                (
                    "resident",
                    BLUE,
                    records
                        .iter()
                        .map(|r| (time(r), r.resident_tiles as f64))
                        .collect(),
                ),
                (
                    "in flight",
                    MAGENTA,
                    records
                        .iter()
                        .map(|r| (time(r), r.in_flight as f64))
                        .collect(),
                ),
            ],
        },
        Panel {
            title: "complete belts around the current tile".into(),
            y_label: "belts",
            y_max: None,
            series: vec![(
                "complete belts",
                GREEN,
                records
                    .iter()
                    .map(|r| (time(r), f64::from(r.complete_belts)))
                    .collect(),
            )],
        },
        Panel {
            title: "download rate (1 s window)".into(),
            y_label: "Mbit/s",
            y_max: None,
            series: vec![("downloaded", BLACK, rate)],
        },
    ];
    let t_max = records.last().map_or(1.0, |r| r.time_s);
    draw_panels(&panels, path, "flight time (s)", t_max)
}

/// Writes the rendering chart, the top panels of the strip-mask paper's Figures 6 and 7:
/// target and obtained frame rate, and triangles per frame with the global budget, over
/// wall-clock time. Frames without rendering are left out.
pub fn render_chart(records: &[FrameRecord], title: &str, path: &Path) -> Result<(), ChartError> {
    let rendered: Vec<(f64, &crate::flight::RenderRecord)> = records
        .iter()
        .filter_map(|r| r.render.as_ref().map(|x| (r.wall_s, x)))
        .collect();
    let mut rate = vec![(
        "obtained (1 / frame time)",
        RGBColor(150, 170, 230),
        rendered
            .iter()
            .map(|(t, r)| (*t, 1e3 / r.frame_ms.max(1e-6)))
            .collect::<Vec<_>>(),
    )];
    rate.push((
        "obtained (frames in the last second)",
        BLUE,
        crate::flight::windowed_fps(records),
    ));
    if rendered.iter().any(|(_, r)| r.target_fps.is_some()) {
        rate.push((
            "target",
            RED,
            rendered
                .iter()
                .filter_map(|(t, r)| r.target_fps.map(|f| (*t, f)))
                .collect(),
        ));
    }
    let target_max = rendered
        .iter()
        .filter_map(|(_, r)| r.target_fps)
        .reduce(f64::max);
    let panels = [
        Panel {
            title: format!("{title}: frame rate"),
            y_label: "frames/s",
            // The first frames, with nothing to draw yet, run at hundreds of frames per
            // second: the axis stops at three times the target so the steady state shows.
            y_max: target_max.map(|t| 3.0 * t),
            series: rate,
        },
        Panel {
            title: "triangles per frame".into(),
            y_label: "triangles",
            y_max: None,
            series: vec![
                (
                    "drawn (masks)",
                    BLUE,
                    rendered
                        .iter()
                        .map(|(t, r)| (*t, r.triangles as f64))
                        .collect(),
                ),
                (
                    "global budget",
                    RED,
                    rendered
                        .iter()
                        .map(|(t, r)| (*t, f64::from(r.global_budget)))
                        .collect(),
                ),
            ],
        },
        Panel {
            title: "visible tiles".into(),
            y_label: "tiles",
            y_max: None,
            series: vec![(
                "visible",
                GREEN,
                rendered
                    .iter()
                    .map(|(t, r)| (*t, f64::from(r.visible_tiles)))
                    .collect(),
            )],
        },
    ];
    let t_max = rendered.last().map_or(1.0, |(t, _)| *t);
    draw_panels(&panels, path, "wall-clock time (s)", t_max)
}

/// Draws `panels` one above the other into `path`, sharing an x axis from 0 to `x_max`.
fn draw_panels(panels: &[Panel], path: &Path, x_desc: &str, x_max: f64) -> Result<(), ChartError> {
    register_font();
    let err = |e: String| ChartError {
        path: path.display().to_string(),
        message: e,
    };
    let root =
        BitMapBackend::new(path, (WIDTH, PANEL_HEIGHT * panels.len() as u32)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(e.to_string()))?;
    let areas = root.split_evenly((panels.len(), 1));
    let t_max = x_max.max(1e-3);
    for (panel, area) in panels.iter().zip(&areas) {
        let y_max = panel.y_max.unwrap_or_else(|| {
            panel
                .series
                .iter()
                .flat_map(|(_, _, s)| s.iter().map(|p| p.1))
                .fold(0.0f64, f64::max)
                .max(1e-9)
                * 1.1
        });
        let mut chart = ChartBuilder::on(area)
            .caption(&panel.title, ("sans-serif", 18))
            .margin(8)
            .x_label_area_size(32)
            .y_label_area_size(64)
            .build_cartesian_2d(0.0..t_max, 0.0..y_max)
            .map_err(|e| err(e.to_string()))?;
        chart
            .configure_mesh()
            .x_desc(x_desc)
            .y_desc(panel.y_label)
            .label_style(("sans-serif", 13))
            .draw()
            .map_err(|e| err(e.to_string()))?;
        for (name, colour, points) in &panel.series {
            let colour = *colour;
            chart
                .draw_series(LineSeries::new(
                    points.iter().copied(),
                    colour.stroke_width(2),
                ))
                .map_err(|e| err(e.to_string()))?
                .label(*name)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2))
                });
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 13))
            .draw()
            .map_err(|e| err(e.to_string()))?;
    }
    root.present().map_err(|e| err(e.to_string()))?;
    Ok(())
}

/// Download rate over a trailing one-second window of wall-clock time, in Mbit/s.
fn download_rate_mbit(records: &[FrameRecord]) -> Vec<(f64, f64)> {
    let mut start = 0;
    records
        .iter()
        .enumerate()
        .map(|(i, r)| {
            while records[start].wall_s < r.wall_s - 1.0 {
                start += 1;
            }
            let (first, span) = (&records[start], r.wall_s - records[start].wall_s);
            let bits = (r.bytes_downloaded - first.bytes_downloaded) as f64 * 8.0;
            let rate = if span > 0.0 && i > start {
                bits / span / 1e6
            } else {
                0.0
            };
            (r.time_s, rate)
        })
        .collect()
}
