//! What `bench stability` writes: the Markdown matrix of scenarios against methods, the
//! CSV of every run, and each scenario's frames side by side with the failing pixels
//! marked.

use super::{
    ALTITUDE_COVERAGE_PCT, ALTITUDE_HOLES_SHARE, RunResult, StabilityArgs, StabilityReport,
};
use crate::eval::frame::{Capture, Unfilled};
use crate::flight::FlightError;
use std::fmt::Write as _;
use std::path::Path;

/// `frame` with the pixels it lost to the background (where the reference has terrain:
/// cracks, and silhouettes a coarser surface lowered) painted red; with a crack filler
/// (`unfilled`, the frame without it and with the crack probe), its pixels green where they
/// fill a crack and magenta where they leak.
pub(super) fn marked(
    frame: &Capture,
    reference: &Capture,
    unfilled: Option<&Unfilled>,
) -> image::RgbaImage {
    let mut image = frame.color.clone();
    let width = image.width();
    for (i, (f, r)) in frame.points.iter().zip(&reference.points).enumerate() {
        let at = (i as u32 % width, i as u32 / width);
        if f.is_none() && r.is_some() {
            image.put_pixel(at.0, at.1, image::Rgba([255, 0, 0, 255]));
        } else if let Some(u) = unfilled
            && frame.depth[i] != u.depth[i]
        {
            let colour = if u.probe[i] != u.depth[i] {
                [0, 220, 0, 255]
            } else {
                [255, 0, 255, 255]
            };
            image.put_pixel(at.0, at.1, image::Rgba(colour));
        }
    }
    image
}

pub(super) fn mib(b: u64) -> f64 {
    b as f64 / 1048576.0
}

/// The table as Markdown, images linked from `images/`.
pub fn markdown(report: &StabilityReport) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| scenario | method | crack px (% of terrain) | holes px | filler / leaks px | coverage (%) | mean / p99 / max error (px) | without the filler: p99 / max (px) | > 1 px (%) | frame ms median / p95 / max | peak counted / held / limit of database (MiB) | flat tiles at coarsest | triangles used / needed | result |"
    );
    let _ = writeln!(
        s,
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"
    );
    for r in &report.runs {
        if let Some(why) = &r.failure {
            let _ = writeln!(
                s,
                "| {} | {} | | | | | | | | | | | | **failed**: {} |",
                r.scenario,
                r.method,
                why.replace('|', "/")
            );
            continue;
        }
        if let Some(why) = &r.refused {
            let _ = writeln!(
                s,
                "| {} | {} | | | | | | | | | | | | refused at start: {} |",
                r.scenario,
                r.method,
                why.replace('|', "/")
            );
            continue;
        }
        let pct = 100.0 * r.crack_pixels as f64 / (r.reference_terrain_pixels as f64).max(1.0);
        let _ = writeln!(
            s,
            "| {} | {} | {} ({:.2}%) | {} | {} | {:.2}{} | {:.2} / {:.1} / {:.1} | {} | {:.2} | {:.1} / {:.1} / {:.1} | {:.1} / {:.1} / {:.1} of {:.1} {} | {} | {} / {} | {} |",
            r.scenario,
            r.method,
            r.crack_pixels,
            pct,
            r.hole_pixels,
            if r.method.contains('/') && !r.method.ends_with("/none") {
                format!("{} / {}", r.filler_pixels, r.leak_pixels)
            } else {
                "-".to_string()
            },
            r.coverage_pct,
            if r.whole_reference { "*" } else { "" },
            r.mean_error_px,
            r.p99_error_px,
            r.max_error_px,
            r.unfilled_error_px
                .map_or("-".to_string(), |(p99, max)| format!("{p99:.1} / {max:.1}")),
            r.above_threshold_pct,
            r.frame_ms_median,
            r.frame_ms_p95,
            r.frame_ms_max,
            mib(r.peak_resident_bytes),
            mib(r.peak_held_bytes),
            mib(r.memory_limit_bytes),
            mib(r.database_bytes),
            if r.within_memory() {
                "(within)"
            } else {
                "(**over**)"
            },
            if r.flat_tiles.0 == 0 {
                "-".to_string()
            } else {
                format!("{} of {}", r.flat_tiles.1, r.flat_tiles.0)
            },
            r.triangles.0,
            r.triangles.1,
            r.altitude_shortfall()
                .map_or("ok".to_string(), |why| format!("**short**: {why}")),
        );
    }
    for (name, why) in &report.skipped {
        let _ = writeln!(s, "| {name} | all | | | | | | | | | | not run: {why} |");
    }
    if report.runs.iter().any(|r| r.whole_reference) {
        let _ = writeln!(
            s,
            "\n\\* against a reference holding the whole database at full resolution (the other rows: every tile the scenario's own limit let in). Such a row is ok when it draws at least {ALTITUDE_COVERAGE_PCT}% of the reference's terrain pixels with a mean error within 1 px and, when the method closes cracks, holes on at most {}% of them.",
            100.0 * ALTITUDE_HOLES_SHARE
        );
    }
    s
}

pub(super) fn write_outputs(
    args: &StabilityArgs,
    report: &mut StabilityReport,
) -> Result<(), FlightError> {
    let out = &args.out;
    let images = out.join("images");
    let write_err = |path: &Path| {
        let path = path.to_path_buf();
        move |source| FlightError::Write { path, source }
    };
    std::fs::create_dir_all(&images).map_err(write_err(&images))?;
    let mut md = markdown(report);
    md.push_str(
        "\nPictures: the reference (left), then each method's measured frame; in red, pixels showing the background where the reference shows terrain (cracks, and silhouettes lowered by a coarser surface); with a crack filler, its pixels in green where they fill a crack and in magenta where they leak (show where the mesh has no crack).\n\n",
    );
    let mut scenarios: Vec<&str> = report.runs.iter().map(|r| r.scenario.as_str()).collect();
    scenarios.dedup();
    for name in scenarios {
        let runs: Vec<&RunResult> = report.runs.iter().filter(|r| r.scenario == name).collect();
        let Some(reference) = runs.iter().find_map(|r| r.reference.as_ref()) else {
            continue;
        };
        let mut tiles = vec![reference.clone()];
        tiles.extend(runs.iter().filter_map(|r| r.picture.clone()));
        let (w, h) = reference.dimensions();
        let mut strip = image::RgbaImage::from_pixel(
            w * tiles.len() as u32 + 4 * (tiles.len() as u32 - 1),
            h,
            image::Rgba([255, 255, 255, 255]),
        );
        for (k, t) in tiles.iter().enumerate() {
            image::imageops::overlay(&mut strip, t, i64::from(k as u32 * (w + 4)), 0);
        }
        let file = images.join(format!("{name}.png"));
        strip.save(&file).map_err(|e| FlightError::Image {
            path: file.clone(),
            message: e.to_string(),
        })?;
        let labels: Vec<String> = std::iter::once("reference".to_string())
            .chain(
                runs.iter()
                    .filter(|r| r.picture.is_some())
                    .map(|r| r.method.clone()),
            )
            .collect();
        let _ = writeln!(
            md,
            "**{name}** ({}): ![{name}](images/{name}.png)\n",
            labels.join(", ")
        );
        report.files.push(file);
    }
    let md_path = out.join("stability.md");
    crate::output::write_file(&md_path, &md).map_err(write_err(&md_path))?;
    let mut csv = String::from(
        "scenario,method,failure,crack_pixels,hole_pixels,reference_terrain_pixels,max_error_px,above_threshold_pct,frame_ms_median,frame_ms_p95,frame_ms_max,peak_resident_bytes,peak_held_bytes,memory_limit_bytes,database_bytes,flat_tiles,flat_tiles_coarsest,triangles,triangles_needed,coverage_pct,mean_error_px,whole_reference,p99_error_px,filler_pixels,leak_pixels\n",
    );
    for r in &report.runs {
        let _ = writeln!(
            csv,
            "{},{},{},{},{},{},{:.3},{:.3},{:.3},{:.3},{:.3},{},{},{},{},{},{},{},{},{:.3},{:.3},{},{:.3},{},{}",
            r.scenario,
            r.method,
            r.failure
                .clone()
                .or_else(|| r.refused.as_ref().map(|why| format!("refused: {why}")))
                .unwrap_or_default()
                .replace([',', '\n'], ";"),
            r.crack_pixels,
            r.hole_pixels,
            r.reference_terrain_pixels,
            r.max_error_px,
            r.above_threshold_pct,
            r.frame_ms_median,
            r.frame_ms_p95,
            r.frame_ms_max,
            r.peak_resident_bytes,
            r.peak_held_bytes,
            r.memory_limit_bytes,
            r.database_bytes,
            r.flat_tiles.0,
            r.flat_tiles.1,
            r.triangles.0,
            r.triangles.1,
            r.coverage_pct,
            r.mean_error_px,
            r.whole_reference,
            r.p99_error_px,
            r.filler_pixels,
            r.leak_pixels
        );
    }
    let csv_path = out.join("stability.csv");
    crate::output::write_file(&csv_path, csv).map_err(write_err(&csv_path))?;
    report.files.insert(0, csv_path);
    report.files.insert(0, md_path);
    Ok(())
}

impl std::fmt::Display for StabilityReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(f, "stability matrix, adapter {}\n", self.adapter)?;
        write!(f, "{}", markdown(self))?;
        write!(f, "\nwrote")?;
        for file in &self.files {
            write!(f, " {}", file.display())?;
        }
        writeln!(f)
    }
}
