//! The memory limit, exactly: every method and filler, at limits that bind, never holds a
//! byte more than the limit at the end of a frame (as counted, and with the GPU as wgpu's
//! allocator reports it), or refuses at start with the budget that would do; and no
//! method makes the process grow frame after frame.

use std::path::{Path, PathBuf};
use terrain_client::eval::Variants;
use terrain_client::eval::session::whole_database_bytes;
use terrain_client::eval::stability::{self, StabilityArgs};
use terrain_client::flight::{FlightArgs, FlightError, StreamArgs, fly};
use terrain_client::memory::{MemoryError, MemorySize};
use terrain_client::method::{CrackFiller, MethodKind};
use terrain_tests::data::jacksboro;
use terrain_tests::golden;
use terrain_tests::server::TestServer;

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime")
}

/// Every method, the strip masks with every filler a user can choose.
fn every_variant() -> Vec<(MethodKind, CrackFiller)> {
    let mut variants: Vec<(MethodKind, CrackFiller)> = [
        CrackFiller::None,
        CrackFiller::Skirts,
        CrackFiller::PlanarShadow,
        CrackFiller::PlanarShadowPaper,
    ]
    .into_iter()
    .map(|f| (MethodKind::StripMasks, f))
    .collect();
    for method in [
        MethodKind::Reference,
        MethodKind::Geomipmap,
        MethodKind::Pgm,
        MethodKind::ProjectiveGrid,
        MethodKind::QuadtreePatches,
    ] {
        variants.push((method, CrackFiller::default()));
    }
    variants
}

/// A random walk over and around the terrain: a new place every half second, anywhere
/// from a fifth of the extent off its west and north edges to a fifth past the others,
/// from 150 m to 4 km up, for 8 s (a linear congruential generator, so every run flies
/// the same).
fn random_walk(dir: &Path, extent: [f64; 2]) -> PathBuf {
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut next = || {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut text = String::from("t,x,y,z\n");
    for k in 0..=16 {
        let (x, y) = (-0.2 + 1.4 * next(), -0.2 + 1.4 * next());
        let z = 150.0 + 3850.0 * next();
        text.push_str(&format!(
            "{},{:.1},{:.1},{z:.1}\n",
            0.5 * f64::from(k),
            x * extent[0],
            y * extent[1]
        ));
    }
    let path = dir.join("walk.csv");
    std::fs::write(&path, text).expect("flight file");
    path
}

fn flight(
    server: &str,
    out: &Path,
    walk: &Path,
    variant: (MethodKind, CrackFiller),
    memory: u64,
) -> FlightArgs {
    let mut stream = StreamArgs::new(server, Some(MemorySize(memory)));
    stream.concurrency = 4;
    let mut args = FlightArgs::new(stream, out);
    args.flight = Some(walk.to_path_buf());
    args.fps = 10.0;
    args.quiet = true;
    args.frame_every = 0;
    args.render.method = variant.0;
    args.render.crack_filler = variant.1;
    args.render.size = (320, 180);
    args
}

/// `flight.csv` as rows of named columns.
fn read_csv(path: &Path) -> Vec<std::collections::HashMap<String, String>> {
    let text = std::fs::read_to_string(path).expect("flight.csv");
    let mut lines = text.lines();
    let header: Vec<String> = lines
        .next()
        .expect("header")
        .split(',')
        .map(str::to_string)
        .collect();
    lines
        .map(|l| {
            header
                .iter()
                .cloned()
                .zip(l.split(',').map(str::to_string))
                .collect()
        })
        .collect()
}

fn number(row: &std::collections::HashMap<String, String>, column: &str) -> u64 {
    row[column]
        .parse()
        .unwrap_or_else(|e| panic!("{column} = {:?}: {e}", row[column]))
}

#[test]
fn every_method_keeps_the_limit_on_every_frame_of_a_random_walk_or_refuses_below_what_it_needs() {
    let test = "memory::every_method_keeps_the_limit_on_every_frame_of_a_random_walk";
    if !terrain_tests::tier::full(test) {
        return;
    }
    let Some(_) = golden::gpu(test) else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(&terrain_tests::fixtures::database(
        &jacksboro(),
        terrain_tests::fixtures::Options::WithPatches,
    ));
    let manifest = server.state().db().manifest().clone();
    let walk = random_walk(tmp.path(), manifest.extent_m);
    let whole = whole_database_bytes(&manifest);
    let runtime = runtime();
    for variant in every_variant() {
        let name = Variants::name(variant.0, variant.1);
        let out = tmp.path().join(name.replace('/', "-"));
        // Far below what it needs: refused before anything is fetched or written, with the
        // budget that would do.
        let refused = runtime.block_on(fly(&flight(server.base_url(), &out, &walk, variant, 1024)));
        let Err(FlightError::Memory(MemoryError::TooSmall(too_small))) = refused else {
            panic!("{name} at 1 KiB: {refused:?}");
        };
        assert!(
            !out.exists(),
            "{name}: refused, yet it wrote {}",
            out.display()
        );
        let least = too_small.least_budget_bytes();
        // A fifth of the way from the least it needs to the whole database: the pager must
        // choose, and the method's index sets come and go.
        let memory = least + (whole.saturating_sub(least)) / 5;
        let summary = runtime
            .block_on(fly(&flight(
                server.base_url(),
                &out,
                &walk,
                variant,
                memory,
            )))
            .unwrap_or_else(|e| panic!("{name} at {memory} bytes: {e}"));
        eprintln!("{name}: least --memory {least} bytes; at {memory}:\n{summary}");
        assert_eq!(summary.frames_over_limit, 0, "{name}: {summary}");
        assert_eq!(summary.peak_overshoot_bytes, 0, "{name}");
        let rows = read_csv(&summary.csv);
        assert_eq!(rows.len() as u64, summary.frames);
        let mut evicted = false;
        let mut previous = 0;
        let mut worst_padding = 0;
        for row in &rows {
            let (resident, limit, ledger) = (
                number(row, "resident_bytes"),
                number(row, "memory_limit_bytes"),
                number(row, "gpu_bytes"),
            );
            assert!(
                resident <= limit,
                "{name}, frame {}: {resident} > {limit}",
                row["frame"]
            );
            // The GPU as wgpu's allocator reports it: every terrain allocation it has is in
            // the ledger (which charges some ahead: a sample slot per resident tile), at the
            // size the client asked for; the allocator's padding of each (lavapipe: up to
            // 64 bytes a buffer, a few dozen a mip) is the driver's, reported beside.
            let reported = number(row, "gpu_allocated_terrain_bytes");
            assert!(
                reported <= ledger + ledger / 100 + (64 << 10),
                "{name}, frame {}: the allocator reports {reported} terrain bytes, the ledger {ledger}",
                row["frame"]
            );
            worst_padding = worst_padding.max(reported.saturating_sub(ledger));
            evicted |= resident < previous;
            previous = resident;
        }
        assert!(
            evicted,
            "{name}: the limit never made the pager drop a tile"
        );
        eprintln!(
            "{name}: the allocator's padding of the terrain's GPU bytes: {worst_padding} bytes at most"
        );
    }
}

#[test]
fn every_method_and_filler_below_one_belt_keeps_the_limit_or_refuses_at_start() {
    let test = "memory::every_method_and_filler_below_one_belt";
    let Some(_) = golden::gpu(test) else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(&terrain_tests::fixtures::database(
        &jacksboro(),
        terrain_tests::fixtures::Options::WithPatches,
    ));
    let mut args = StabilityArgs {
        frames: 8,
        scenarios: vec!["memory-below-one-belt".into()],
        ..StabilityArgs::new(server.base_url(), tmp.path().join("stability"))
    };
    args.variants.methods = vec![
        MethodKind::StripMasks,
        MethodKind::Reference,
        MethodKind::Geomipmap,
        MethodKind::Pgm,
        MethodKind::ProjectiveGrid,
        MethodKind::QuadtreePatches,
    ];
    args.variants.fillers = vec![
        CrackFiller::None,
        CrackFiller::Skirts,
        CrackFiller::PlanarShadow,
        CrackFiller::PlanarShadowPaper,
    ];
    let report = runtime().block_on(stability::run(&args)).expect("matrix");
    eprintln!("{report}");
    assert_eq!(report.runs.len(), args.variants.list().len());
    let mut ran = 0;
    for r in &report.runs {
        assert_eq!(r.failure, None, "{}", r.method);
        if let Some(why) = &r.refused {
            assert!(why.contains("give --memory"), "{}: {why}", r.method);
            continue;
        }
        ran += 1;
        assert!(
            r.within_memory(),
            "{}: {} bytes counted, {} held, limit {}",
            r.method,
            r.peak_resident_bytes,
            r.peak_held_bytes,
            r.memory_limit_bytes
        );
    }
    assert!(
        ran >= 5,
        "the strip masks with every filler and the reference run below one belt, coarser: {ran}"
    );
}

/// A still camera over jacksboro for 20 s of flight: frame after frame of the same work.
fn still(dir: &Path) -> PathBuf {
    let path = dir.join("still.json");
    std::fs::write(
        &path,
        r#"{"units": "extent", "keyframes": [
            {"t": 0, "x": 0.45, "y": 0.55, "z": 2500},
            {"t": 20, "x": 0.45, "y": 0.55, "z": 2500}]}"#,
    )
    .expect("flight file");
    path
}

#[test]
fn no_method_makes_the_process_grow_frame_after_frame() {
    let test = "memory::no_method_makes_the_process_grow_frame_after_frame";
    if !terrain_tests::tier::full(test) {
        return;
    }
    let Some(_) = golden::gpu(test) else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(&terrain_tests::fixtures::database(
        &jacksboro(),
        terrain_tests::fixtures::Options::WithPatches,
    ));
    let path = still(tmp.path());
    for method in [
        MethodKind::StripMasks,
        MethodKind::Geomipmap,
        MethodKind::Pgm,
        MethodKind::ProjectiveGrid,
        MethodKind::QuadtreePatches,
    ] {
        let out = tmp.path().join(method.name());
        // Its own process: the resident set is the process's, and the other tests share
        // this one.
        let (ok, stdout, stderr) = terrain_tests::data::run_binary(
            "terrain-client",
            &[
                "fly",
                "--server",
                server.base_url(),
                "--method",
                method.name(),
                "--flight",
            ]
            .map(std::ffi::OsStr::new)
            .into_iter()
            .chain([path.as_os_str()])
            .chain(
                [
                    "--fps",
                    // Frames enough after everything has arrived: the grids draw a few
                    // frames a second here, the others a hundred or more.
                    if method.is_projected_grid() {
                        "4"
                    } else {
                        "20"
                    },
                    "--size",
                    "320x180",
                    "--quiet",
                    "--frame-every",
                    "0",
                    "--out",
                ]
                .map(std::ffi::OsStr::new),
            )
            .chain([out.as_os_str()])
            .collect::<Vec<_>>(),
        );
        assert!(ok, "{}: {stderr}", method.name());
        let rows = read_csv(&out.join("flight.csv"));
        let rss = |k: usize| number(&rows[k], "rss_bytes");
        // Once every tile is in (nothing in flight, the tiles as at the end, and every byte
        // downloaded: the textures' finer levels arrive after their tiles, and a loaded
        // machine draws many frames before they are all in) and two seconds have passed (the method's own
        // data meshed), what grows grows with the frames, as
        // lavapipe's memory did with the grids while their parameters were a uniform
        // buffer rewritten every frame (1.8 to 4.3 MB a frame, heap and GPU flat).
        let last = rows.last().expect("frames");
        let settled = rows
            .iter()
            .rposition(|r| {
                number(r, "in_flight") != 0
                    || number(r, "resident_tiles") != number(last, "resident_tiles")
                    || number(r, "bytes_downloaded") != number(last, "bytes_downloaded")
                    || r["wall_s"].parse::<f64>().unwrap_or(0.0) < 2.0
            })
            .map_or(0, |k| k + 1);
        let (from, to) = (settled + 10, rows.len() - 1);
        assert!(
            to >= from + 40,
            "{}: settled at frame {settled} of {}: the last frame at {} s of wall time with \
             {} tile(s) in flight and {} resident\n{stdout}",
            method.name(),
            rows.len(),
            last["wall_s"],
            last["in_flight"],
            last["resident_tiles"]
        );
        let growth = rss(to).saturating_sub(rss(from));
        eprintln!(
            "{}: resident set {:.1} MiB at frame {from}, {:.1} MiB at frame {to}\n{stdout}",
            method.name(),
            rss(from) as f64 / 1048576.0,
            rss(to) as f64 / 1048576.0
        );
        assert!(
            growth <= 16 << 20,
            "{}: the process grew by {:.1} MiB over {} frames of a still view",
            method.name(),
            growth as f64 / 1048576.0,
            to - from
        );
    }
}
