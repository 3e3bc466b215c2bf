//! Charts of a flight as PNG, in the spirit of the strip-mask paper's Figures 6 and 7:
//! memory used over the flight (their bottom panels) and frame rate and triangles per frame
//! (their top panels), drawn with plotters from the per-frame
//! records. Pure apart from writing the file: records in, picture out.
//!
//! plotters' bitmap backend draws text with a font it is given; the project ships DejaVu
//! Sans (`assets/fonts`, its licence beside it) so charts look the same on every machine.

use crate::record::FrameRecord;
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
    let rendered: Vec<(f64, &crate::record::RenderRecord)> = records
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
        crate::record::windowed_fps(records),
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

/// A line of an [`XyPanel`]: points joined in x order, with markers.
#[derive(Debug, Clone)]
pub struct XySeries {
    pub name: String,
    pub colour: RGBColor,
    pub points: Vec<(f64, f64)>,
    pub dashed: bool,
}

/// A panel of named series over a shared x axis (linear or logarithmic).
#[derive(Debug, Clone)]
pub struct XyPanel {
    pub title: String,
    pub x_desc: String,
    pub y_desc: String,
    pub log_x: bool,
    pub series: Vec<XySeries>,
}

/// `1500` as `1.5k`, `2000000` as `2M`, others with one decimal (two below 1, three
/// below 0.1, four below 0.01), trailing zeros left out.
fn short_number(x: f64) -> String {
    let trim = |v: f64| {
        let s = if v.abs() < 0.01 {
            format!("{v:.4}")
        } else if v.abs() < 0.1 {
            format!("{v:.3}")
        } else if v.abs() < 1.0 {
            format!("{v:.2}")
        } else {
            format!("{v:.1}")
        };
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s
        }
    };
    if x.abs() >= 1e6 {
        format!("{}M", trim(x / 1e6))
    } else if x.abs() >= 1e3 {
        format!("{}k", trim(x / 1e3))
    } else {
        trim(x)
    }
}

/// The `k`-th of a few colours that stay apart on white.
pub fn palette(k: usize) -> RGBColor {
    const COLOURS: [RGBColor; 8] = [
        RGBColor(31, 119, 180),
        RGBColor(255, 127, 14),
        RGBColor(44, 160, 44),
        RGBColor(214, 39, 40),
        RGBColor(148, 103, 189),
        RGBColor(80, 80, 80),
        RGBColor(23, 190, 207),
        RGBColor(188, 189, 34),
    ];
    COLOURS[k % COLOURS.len()]
}

/// Draws `panels` one above the other into `path`: each series as a line through its
/// points (sorted by x) with a dot at each.
pub fn xy_chart(panels: &[XyPanel], path: &Path) -> Result<(), ChartError> {
    register_font();
    let err = |e: String| ChartError {
        path: path.display().to_string(),
        message: e,
    };
    let root = BitMapBackend::new(path, (WIDTH, (PANEL_HEIGHT + 90) * panels.len() as u32))
        .into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(e.to_string()))?;
    let areas = root.split_evenly((panels.len(), 1));
    for (panel, area) in panels.iter().zip(&areas) {
        let points = || panel.series.iter().flat_map(|s| s.points.iter().copied());
        let finite = |v: f64| v.is_finite();
        let x_lo = points()
            .map(|p| p.0)
            .filter(|&x| finite(x) && (!panel.log_x || x > 0.0))
            .fold(f64::INFINITY, f64::min);
        let x_hi = points()
            .map(|p| p.0)
            .filter(|&x| finite(x))
            .fold(f64::NEG_INFINITY, f64::max);
        let y_hi = points()
            .map(|p| p.1)
            .filter(|&y| finite(y))
            .fold(0.0f64, f64::max)
            .max(1e-9)
            * 1.1;
        let (x_lo, x_hi) = if x_lo.is_finite() && x_hi > x_lo {
            (x_lo, x_hi)
        } else if x_lo.is_finite() {
            (x_lo * 0.5, x_lo * 2.0 + 1.0)
        } else {
            (1.0, 10.0)
        };
        let mut builder = ChartBuilder::on(area);
        builder
            .caption(&panel.title, ("sans-serif", 18))
            .margin(10)
            .x_label_area_size(36)
            .y_label_area_size(70);
        macro_rules! body {
            ($chart:expr) => {{
                let mut chart = $chart;
                chart
                    .configure_mesh()
                    .x_desc(panel.x_desc.as_str())
                    .y_desc(panel.y_desc.as_str())
                    .x_label_formatter(&|x: &f64| short_number(*x))
                    .y_label_formatter(&|y: &f64| short_number(*y))
                    .label_style(("sans-serif", 13))
                    .draw()
                    .map_err(|e| err(e.to_string()))?;
                for s in &panel.series {
                    let mut pts: Vec<(f64, f64)> = s
                        .points
                        .iter()
                        .copied()
                        .filter(|p| finite(p.0) && finite(p.1) && (!panel.log_x || p.0 > 0.0))
                        .collect();
                    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
                    let colour = s.colour;
                    let style = colour.stroke_width(2);
                    if s.dashed {
                        chart
                            .draw_series(DashedLineSeries::new(pts.iter().copied(), 8, 5, style))
                            .map_err(|e| err(e.to_string()))?
                            .label(s.name.as_str())
                            .legend(move |(x, y)| {
                                PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(1))
                            });
                    } else {
                        chart
                            .draw_series(LineSeries::new(pts.iter().copied(), style))
                            .map_err(|e| err(e.to_string()))?
                            .label(s.name.as_str())
                            .legend(move |(x, y)| {
                                PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2))
                            });
                    }
                    chart
                        .draw_series(pts.iter().map(|&p| Circle::new(p, 3, colour.filled())))
                        .map_err(|e| err(e.to_string()))?;
                }
                chart
                    .configure_series_labels()
                    .background_style(WHITE.mix(0.85))
                    .border_style(BLACK)
                    .label_font(("sans-serif", 13))
                    .position(SeriesLabelPosition::UpperRight)
                    .draw()
                    .map_err(|e| err(e.to_string()))?;
            }};
        }
        if panel.log_x {
            body!(
                builder
                    .build_cartesian_2d((x_lo * 0.8..x_hi * 1.25).log_scale(), 0.0..y_hi)
                    .map_err(|e| err(e.to_string()))?
            );
        } else {
            let pad = (x_hi - x_lo) * 0.05;
            body!(
                builder
                    .build_cartesian_2d((x_lo - pad).max(0.0)..x_hi + pad, 0.0..y_hi)
                    .map_err(|e| err(e.to_string()))?
            );
        }
    }
    root.present().map_err(|e| err(e.to_string()))?;
    Ok(())
}
