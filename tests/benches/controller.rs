//! The frame-rate controller holding a target: rendered flights over jacksboro (and, with
//! `$TERRAIN_DATA_DIR`, Puget Sound) at 30 and 60 fps.
//!
//! ```text
//! cargo bench -p terrain-tests --bench controller -- OUT_DIR
//! ```
//!
//! Each flight is the default lap at 960x540 with strip masks, a process of its own
//! (`terrain-client fly`), on whatever adapter the machine has (lavapipe without a GPU). Per
//! flight, from its `flight.csv`, over the frames after the first second of wall-clock
//! time: the median frame rate over the last second, the share of frames at which it is
//! within 10% of the target, its range, the controller's prediction error (median and 90th
//! percentile, two frames at a time: `terrain_client::flight::prediction_errors`), the mean
//! triangles a frame and the peak resident set. Writes `controller.md` (stamped with the
//! commit, machine, adapter and date) and `controller.csv` to OUT_DIR (default
//! `out/bench/controller`).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;
use terrain_server::build::{BuildOptions, build};
use terrain_tests::data::workspace_binary;
use terrain_tests::server::TestServer;

/// (target fps, --memory, crack filler) of each flight.
const FLIGHTS: [(u32, &str, &str); 5] = [
    (60, "16MiB", "planar-shadow"),
    (60, "3MiB", "planar-shadow"),
    (30, "16MiB", "planar-shadow"),
    (30, "16MiB", "skirts"),
    (30, "16MiB", "none"),
];

fn main() {
    let out = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with("--"))
        .map_or_else(|| PathBuf::from("out/bench/controller"), PathBuf::from);
    std::fs::create_dir_all(&out).expect("output directory");
    let out = out.canonicalize().expect("output directory");
    let mut inputs = vec![(
        "jacksboro".to_string(),
        Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/jacksboro/jacksboro_fault_dem.png"),
    )];
    match std::env::var_os("TERRAIN_DATA_DIR") {
        Some(kit) => inputs.push((
            "puget_sound_1k".to_string(),
            PathBuf::from(kit).join("puget_sound_1k/ps_height_1k.png"),
        )),
        None => {
            eprintln!("note: TERRAIN_DATA_DIR is not set: jacksboro only (Puget Sound NOT RUN)")
        }
    }
    let mut adapter = String::new();
    let mut md = String::new();
    let mut csv = String::from(
        "dataset,target_fps,memory,filler,frames,median_fps,held_within_10_percent,min_fps,max_fps,prediction_error_median,prediction_error_p90,mean_triangles,peak_rss_bytes\n",
    );
    let mut rows = String::new();
    for (name, input) in &inputs {
        let options = BuildOptions {
            force: true,
            web: false,
            ..BuildOptions::new(input, out.join("db").join(name))
        };
        let report = build(
            &options,
            &|_, _| {},
            &std::sync::atomic::AtomicBool::new(false),
        )
        .unwrap_or_else(|e| panic!("{name}: {e}"));
        let server = TestServer::start(&report.out);
        for (target, memory, filler) in FLIGHTS {
            let dir = out.join(format!("{name}-{target}fps-{memory}-{filler}"));
            let _ = std::fs::remove_dir_all(&dir);
            let output = Command::new(workspace_binary("terrain-client"))
                .args(["fly", "--server", server.base_url(), "--memory", memory])
                .args([
                    "--target-fps",
                    &target.to_string(),
                    "--crack-filler",
                    filler,
                ])
                .args(["--frame-every", "0", "--quiet", "--out"])
                .arg(&dir)
                .env("RUST_LOG", "warn")
                .output()
                .expect("terrain-client runs");
            let stdout = String::from_utf8_lossy(&output.stdout);
            assert!(
                output.status.success(),
                "{name} {target} fps: {}",
                String::from_utf8_lossy(&output.stderr)
            );
            if let Some(a) = stdout
                .lines()
                .find_map(|l| l.trim().strip_prefix("adapter"))
            {
                adapter = a.trim().to_string();
            }
            let f = measure(&dir.join("flight.csv"), f64::from(target));
            eprintln!(
                "{name}, {target} fps, {memory}, {filler}: median {:.1} fps, held {:.0}%",
                f.median,
                100.0 * f.held
            );
            let _ = writeln!(
                csv,
                "{name},{target},{memory},{filler},{},{:.2},{:.4},{:.1},{:.1},{:.4},{:.4},{:.0},{}",
                f.frames,
                f.median,
                f.held,
                f.range.0,
                f.range.1,
                f.error.0,
                f.error.1,
                f.triangles,
                f.rss
            );
            let _ = writeln!(
                rows,
                "| {name} | {target} fps | {memory} | {filler} | {:.1} | **{:.0}%** | {:.0}-{:.0} | {:.0}% / {:.0}% | {:.0} | {:.1} MiB |",
                f.median,
                100.0 * f.held,
                f.range.0,
                f.range.1,
                100.0 * f.error.0,
                100.0 * f.error.1,
                f.triangles,
                f.rss as f64 / 1048576.0
            );
        }
    }
    let _ = write!(
        md,
        "<!-- written by `cargo bench -p terrain-tests --bench controller`; do not edit -->\n\
         Run: {}; adapter {adapter}.\n\n\
         | dataset | target | --memory | crack filler | median fps over 1 s | held within 10% | range over 1 s windows | prediction error, median / 90th percentile | mean triangles a frame | peak RSS |\n\
         |---|---|---|---|---:|---:|---|---:|---:|---:|\n{rows}",
        terrain_tests::stamp::line()
    );
    std::fs::write(out.join("controller.csv"), csv).expect("controller.csv");
    std::fs::write(out.join("controller.md"), &md).expect("controller.md");
    println!("{md}");
    println!("wrote {}", out.join("controller.md").display());
}

/// What a flight's frames say about its frame rate.
struct FrameRate {
    frames: usize,
    median: f64,
    held: f64,
    range: (f64, f64),
    error: (f64, f64),
    triangles: f64,
    rss: u64,
}

fn measure(csv: &Path, target: f64) -> FrameRate {
    let text = std::fs::read_to_string(csv).expect("flight.csv");
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or("").split(',').collect();
    let column = |name: &str| header.iter().position(|h| *h == name).expect(name);
    let (wall, frame_ms, predicted, triangles, rss) = (
        column("wall_s"),
        column("frame_ms"),
        column("predicted_ms"),
        column("triangles"),
        column("rss_bytes"),
    );
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    let number = |r: &Vec<&str>, c: usize| r.get(c).and_then(|v| v.parse::<f64>().ok());
    let walls: Vec<f64> = rows.iter().filter_map(|r| number(r, wall)).collect();
    // Frames drawn in the last second, at each frame from the first full second on.
    let mut start = 0;
    let mut windows = Vec::new();
    for (i, &t) in walls.iter().enumerate() {
        while walls[start] <= t - 1.0 {
            start += 1;
        }
        if t >= 1.0 {
            windows.push((i + 1 - start) as f64);
        }
    }
    let mut sorted = windows.clone();
    sorted.sort_by(f64::total_cmp);
    let held = windows
        .iter()
        .filter(|&&f| (f - target).abs() <= 0.1 * target)
        .count() as f64
        / windows.len().max(1) as f64;
    // Prediction error two frames at a time, after the first second.
    let pairs: Vec<(f64, f64)> = rows
        .iter()
        .filter(|r| number(r, wall).is_some_and(|w| w >= 1.0))
        .filter_map(|r| Some((number(r, predicted)?, number(r, frame_ms)?)))
        .collect();
    let mut errors: Vec<f64> = pairs
        .chunks_exact(2)
        .map(|c| ((c[0].0 + c[1].0) - (c[0].1 + c[1].1)).abs() / (c[0].1 + c[1].1).max(1e-9))
        .collect();
    errors.sort_by(f64::total_cmp);
    let at = |v: &[f64], q: f64| {
        v.get(((v.len() as f64 * q) as usize).min(v.len().saturating_sub(1)))
            .copied()
            .unwrap_or(0.0)
    };
    FrameRate {
        frames: rows.len(),
        median: at(&sorted, 0.5),
        held,
        range: (
            sorted.first().copied().unwrap_or(0.0),
            sorted.last().copied().unwrap_or(0.0),
        ),
        error: (at(&errors, 0.5), at(&errors, 0.9)),
        triangles: rows
            .iter()
            .filter_map(|r| number(r, triangles))
            .sum::<f64>()
            / rows.len().max(1) as f64,
        rss: rows
            .iter()
            .filter_map(|r| number(r, rss))
            .fold(0.0f64, f64::max) as u64,
    }
}
