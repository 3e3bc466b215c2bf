//! Memory per method: what the limit covers and what the process holds beside it.
//!
//! ```text
//! cargo bench -p terrain-tests --bench memory -- OUT_DIR
//! ```
//!
//! Builds jacksboro (the bundled fixture) and, with `$TERRAIN_DATA_DIR`, every DEM of the
//! data kit (Puget Sound, himalaya_4097, the Grand Canyon, Mt Rainier's SRTM tile), each
//! with the quadtree patches, serves each, and flies the default lap over it with every
//! method at `--memory` 4, 16 and 64 MiB (480x270, 5 frames a second of flight time, each
//! flight a process of its own so that its resident set is its own). Per flight: refused at
//! start (and the least `--memory` it named), or the peak terrain bytes against the limit,
//! the frames over it and by how much, and the peaks over the frames of the program's heap,
//! wgpu's allocations (all, and the terrain's) and the resident set. Writes `memory.csv`
//! and `memory.md` (the table, stamped with the commit, machine, adapter and date) to
//! OUT_DIR (default `out/bench/memory`), and prints the table.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;
use terrain_server::build::{BuildOptions, build};
use terrain_tests::data::workspace_binary;
use terrain_tests::server::TestServer;

const MIB: f64 = 1048576.0;
const MEMORY_MIB: [u64; 3] = [4, 16, 64];
const METHODS: [&str; 6] = [
    "strip-masks",
    "reference",
    "geomipmap",
    "pgm",
    "projective-grid",
    "quadtree-patches",
];

/// One flight's outcome.
enum Outcome {
    Refused { least_memory: String },
    Flown(Peaks),
    Failed(String),
}

/// Peaks over a flight's frames, from its `flight.csv`.
#[derive(Default)]
struct Peaks {
    frames: u64,
    limit: u64,
    terrain: u64,
    frames_over: u64,
    overshoot: u64,
    heap: u64,
    gpu_allocated: u64,
    gpu_terrain: u64,
    rss: u64,
    fps: f64,
}

fn main() {
    let out = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with("--"))
        .map_or_else(|| PathBuf::from("out/bench/memory"), PathBuf::from);
    std::fs::create_dir_all(&out).expect("output directory");
    let out = out.canonicalize().expect("output directory");
    let fixture =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/jacksboro/jacksboro_fault_dem.png");
    let mut inputs = vec![("jacksboro".to_string(), fixture)];
    match std::env::var_os("TERRAIN_DATA_DIR") {
        Some(kit) => {
            let kit = PathBuf::from(kit);
            for (name, file) in [
                ("puget_sound_1k", "puget_sound_1k/ps_height_1k.png"),
                ("himalaya_4097", "himalaya_4097/g10g_himalaya_4097.png"),
                (
                    "grand_canyon_hoppe",
                    "grand_canyon_hoppe/gcanyon_elev_crop.bw.png",
                ),
                ("mt_rainier_90m", "srtm_geotiff/mt_rainier_90m.tif"),
            ] {
                inputs.push((name.to_string(), kit.join(file)));
            }
        }
        None => eprintln!(
            "note: TERRAIN_DATA_DIR is not set: jacksboro only (the data kit's DEMs NOT RUN)"
        ),
    }
    let dbs = out.join("db");
    let mut rows = Vec::new();
    let mut adapter = String::new();
    for (name, input) in &inputs {
        eprintln!("building {name} with the quadtree patches");
        let options = BuildOptions {
            patches: Some(0.0),
            force: true,
            ..BuildOptions::new(input, dbs.join(name))
        };
        let report = build(
            &options,
            &|_, _| {},
            &std::sync::atomic::AtomicBool::new(false),
        )
        .unwrap_or_else(|e| panic!("{name}: {e}"));
        let server = TestServer::start(&report.out);
        for memory in MEMORY_MIB {
            for method in METHODS {
                let dir = out.join(format!("{name}-{method}-{memory}MiB"));
                let _ = std::fs::remove_dir_all(&dir);
                eprint!("{name}, {method}, {memory} MiB: ");
                let output = Command::new(workspace_binary("terrain-client"))
                    .args(["fly", "--server", server.base_url(), "--method", method])
                    .args(["--memory", &format!("{memory}MiB")])
                    .args([
                        "--fps",
                        "5",
                        "--size",
                        "480x270",
                        "--frame-every",
                        "0",
                        "--quiet",
                    ])
                    .arg("--out")
                    .arg(&dir)
                    .env("RUST_LOG", "warn")
                    .output()
                    .expect("terrain-client runs");
                let stdout = String::from_utf8_lossy(&output.stdout);
                let stderr = String::from_utf8_lossy(&output.stderr);
                if let Some(a) = stdout
                    .lines()
                    .find_map(|l| l.trim().strip_prefix("adapter"))
                {
                    adapter = a.trim().to_string();
                }
                let outcome = if output.status.success() {
                    Outcome::Flown(peaks(&dir.join("flight.csv")))
                } else if let Some(least) = stderr.split("give --memory ").nth(1) {
                    Outcome::Refused {
                        least_memory: least.split_whitespace().next().unwrap_or("?").to_string(),
                    }
                } else {
                    Outcome::Failed(stderr.lines().last().unwrap_or("").to_string())
                };
                eprintln!(
                    "{}",
                    match &outcome {
                        Outcome::Refused { least_memory } =>
                            format!("refused (least {least_memory})"),
                        Outcome::Flown(p) => format!(
                            "{} frames, {} over, RSS {:.1} MiB",
                            p.frames,
                            p.frames_over,
                            p.rss as f64 / MIB
                        ),
                        Outcome::Failed(why) => format!("FAILED: {why}"),
                    }
                );
                rows.push((name.clone(), method, memory, outcome));
            }
        }
    }
    let stamp = terrain_tests::stamp::line();
    let mut csv = String::from(
        "dataset,method,memory_mib,result,least_memory,frames,limit_bytes,peak_terrain_bytes,frames_over,peak_overshoot_bytes,peak_heap_bytes,peak_gpu_allocated_bytes,peak_gpu_terrain_bytes,peak_rss_bytes,fps\n",
    );
    let mut md = format!(
        "<!-- written by `cargo bench -p terrain-tests --bench memory`; do not edit -->\n\
         Run: {stamp}; adapter {adapter}.\n\n\
         | dataset | method | --memory | limit (MiB) | peak terrain (MiB) | over the limit | heap peak (MiB) | GPU allocated peak (MiB), terrain | RSS peak (MiB) | RSS / limit | frames a second |\n\
         |---|---|---:|---:|---:|---|---:|---:|---:|---:|---:|\n"
    );
    let mut failures = 0;
    for (dataset, method, memory, outcome) in &rows {
        match outcome {
            Outcome::Refused { least_memory } => {
                let _ = writeln!(
                    csv,
                    "{dataset},{method},{memory},refused,{least_memory},,,,,,,,,,"
                );
                let _ = writeln!(
                    md,
                    "| {dataset} | {method} | {memory} MiB | | | refused at start: needs --memory {least_memory} | | | | | |"
                );
            }
            Outcome::Flown(p) => {
                let _ = writeln!(
                    csv,
                    "{dataset},{method},{memory},flown,,{},{},{},{},{},{},{},{},{},{:.1}",
                    p.frames,
                    p.limit,
                    p.terrain,
                    p.frames_over,
                    p.overshoot,
                    p.heap,
                    p.gpu_allocated,
                    p.gpu_terrain,
                    p.rss,
                    p.fps
                );
                let over = if p.frames_over == 0 {
                    "never".to_string()
                } else {
                    format!(
                        "**{} frames, by {} bytes at most**",
                        p.frames_over, p.overshoot
                    )
                };
                let _ = writeln!(
                    md,
                    "| {dataset} | {method} | {memory} MiB | {:.2} | {:.2} | {over} | {:.1} | {:.1}, {:.1} | {:.1} | {:.1}x | {:.1} |",
                    p.limit as f64 / MIB,
                    p.terrain as f64 / MIB,
                    p.heap as f64 / MIB,
                    p.gpu_allocated as f64 / MIB,
                    p.gpu_terrain as f64 / MIB,
                    p.rss as f64 / MIB,
                    p.rss as f64 / p.limit.max(1) as f64,
                    p.fps
                );
                failures += u32::from(p.frames_over > 0);
            }
            Outcome::Failed(why) => {
                failures += 1;
                let _ = writeln!(csv, "{dataset},{method},{memory},failed,,,,,,,,,,,");
                let _ = writeln!(
                    md,
                    "| {dataset} | {method} | {memory} MiB | | | **failed**: {} | | | | | |",
                    why.replace('|', "/")
                );
            }
        }
    }
    std::fs::write(out.join("memory.csv"), csv).expect("memory.csv");
    std::fs::write(out.join("memory.md"), &md).expect("memory.md");
    println!("{md}");
    println!("wrote {} and memory.csv", out.join("memory.md").display());
    assert_eq!(
        failures, 0,
        "flights over the limit or failed: see the table"
    );
}

/// The peaks of a flight's `flight.csv`.
fn peaks(csv: &Path) -> Peaks {
    let text = std::fs::read_to_string(csv).unwrap_or_default();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or("").split(',').collect();
    let column = |name: &str| header.iter().position(|h| *h == name);
    let (resident, limit, heap, allocated, terrain, rss, wall) = (
        column("resident_bytes"),
        column("memory_limit_bytes"),
        column("heap_bytes"),
        column("gpu_allocated_bytes"),
        column("gpu_allocated_terrain_bytes"),
        column("rss_bytes"),
        column("wall_s"),
    );
    let mut p = Peaks::default();
    let mut walls = Vec::new();
    for line in lines {
        let fields: Vec<&str> = line.split(',').collect();
        let get = |c: Option<usize>| -> u64 {
            c.and_then(|c| fields.get(c))
                .and_then(|v| v.parse().ok())
                .unwrap_or(0)
        };
        p.frames += 1;
        p.limit = get(limit);
        let r = get(resident);
        p.terrain = p.terrain.max(r);
        if r > p.limit {
            p.frames_over += 1;
            p.overshoot = p.overshoot.max(r - p.limit);
        }
        p.heap = p.heap.max(get(heap));
        p.gpu_allocated = p.gpu_allocated.max(get(allocated));
        p.gpu_terrain = p.gpu_terrain.max(get(terrain));
        p.rss = p.rss.max(get(rss));
        if let Some(w) = wall
            .and_then(|c| fields.get(c))
            .and_then(|v| v.parse::<f64>().ok())
        {
            walls.push(w);
        }
    }
    // Frames per second of wall-clock time over the whole flight.
    if let (Some(first), Some(last)) = (walls.first(), walls.last())
        && last > first
    {
        p.fps = (walls.len() - 1) as f64 / (last - first);
    }
    p
}
