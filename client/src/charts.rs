//! Charts of a flight as PNG, in the spirit of the bottom panels of the strip-mask paper's
//! Figures 6 and 7 (memory used over the flight), drawn with plotters from the per-frame
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
}

/// Writes the flight chart: memory, resident tiles, complete belts and download rate over time.
pub fn flight_chart(records: &[FrameRecord], title: &str, path: &Path) -> Result<(), ChartError> {
    register_font();
    let err = |e: String| ChartError {
        path: path.display().to_string(),
        message: e,
    };
    let time = |r: &FrameRecord| r.time_s;
    let rate = download_rate_mbit(records);
    let panels = [
        Panel {
            title: format!("{title}: memory held by resident tiles"),
            y_label: "MiB",
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
            series: vec![("downloaded", BLACK, rate)],
        },
    ];
    let root =
        BitMapBackend::new(path, (WIDTH, PANEL_HEIGHT * panels.len() as u32)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(e.to_string()))?;
    let areas = root.split_evenly((panels.len(), 1));
    let t_max = records.last().map_or(1.0, |r| r.time_s).max(1e-3);
    for (panel, area) in panels.iter().zip(&areas) {
        let y_max = panel
            .series
            .iter()
            .flat_map(|(_, _, s)| s.iter().map(|p| p.1))
            .fold(0.0f64, f64::max)
            .max(1e-9)
            * 1.1;
        let mut chart = ChartBuilder::on(area)
            .caption(&panel.title, ("sans-serif", 18))
            .margin(8)
            .x_label_area_size(32)
            .y_label_area_size(64)
            .build_cartesian_2d(0.0..t_max, 0.0..y_max)
            .map_err(|e| err(e.to_string()))?;
        chart
            .configure_mesh()
            .x_desc("flight time (s)")
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
