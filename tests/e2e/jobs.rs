//! A build split into region jobs and a merge (`build --region I/N`, `merge`): run as
//! separate processes of the real binary, the merged database is byte for byte the one a
//! single build makes; a killed job rerun gives the same; a damaged or missing job is
//! refused by name and leaves nothing at the output.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use terrain_server::build::jobs::{Region, split};
use terrain_shared::manifest::RasterSize;
use terrain_tests::data::{jacksboro, png_codes, run_binary, workspace_binary};

const NODATA: u16 = 65535;

/// Writes `codes` (`width x height`, each below [`NODATA`]) as a 16-bit PNG, with the
/// samples of `voids` (row range, column range) set to [`NODATA`].
fn write_dem(
    path: &Path,
    width: u32,
    height: u32,
    codes: &[i32],
    voids: &[(std::ops::Range<u32>, std::ops::Range<u32>)],
) {
    let mut image = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::new(width, height);
    for (x, y, pixel) in image.enumerate_pixels_mut() {
        let code = codes[(y * width + x) as usize].clamp(0, i32::from(NODATA) - 1) as u16;
        let void = voids
            .iter()
            .any(|(rows, columns)| rows.contains(&y) && columns.contains(&x));
        *pixel = image::Luma([if void { NODATA } else { code }]);
    }
    image.save(path).expect("writes the DEM");
}

/// Hills and ridges with a deterministic roughness, `width x height` codes.
fn synthetic_codes(width: u32, height: u32) -> Vec<i32> {
    (0..height)
        .flat_map(|y| (0..width).map(move |x| (x, y)))
        .map(|(x, y)| {
            let (fx, fy) = (f64::from(x) / 37.0, f64::from(y) / 53.0);
            let hills = 900.0 * (fx.sin() * fy.cos() + 1.2) + 300.0 * ((fx + fy) / 3.0).sin();
            let grain = (x.wrapping_mul(7919) ^ y.wrapping_mul(104_729)) % 23;
            (hills + f64::from(grain)) as i32
        })
        .collect()
}

fn run(args: &[&str]) -> (bool, String, String) {
    let args: Vec<&std::ffi::OsStr> = args.iter().map(std::ffi::OsStr::new).collect();
    run_binary("terrain-server", &args)
}

/// The four region jobs of `dem` (`flags` added), run at once as separate processes.
fn run_jobs_at_once(dem: &Path, jobs: &Path, count: u32, flags: &[&str]) {
    let children: Vec<_> = (0..count)
        .map(|i| {
            Command::new(workspace_binary("terrain-server"))
                .args(["build", "--quiet"])
                .arg(dem)
                .args(["--region", &format!("{i}/{count}"), "--out"])
                .arg(jobs)
                .args(flags)
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .expect("job starts")
        })
        .collect();
    for (i, child) in children.into_iter().enumerate() {
        let output = child.wait_with_output().expect("job runs");
        let stdout = String::from_utf8_lossy(&output.stdout);
        assert!(
            output.status.success(),
            "job {i}/{count}: {}",
            String::from_utf8_lossy(&output.stderr)
        );
        assert!(
            stdout.starts_with(&format!("region {i}/{count} done")),
            "{stdout}"
        );
    }
}

/// Every file of database `a` equals `b`'s, and both hold the same files.
fn assert_same_database(a: &Path, b: &Path) {
    let names = |dir: &Path| -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .expect("database")
            .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    };
    assert_eq!(names(a), names(b));
    for name in names(a) {
        let (x, y) = (
            std::fs::read(a.join(&name)).expect("reads"),
            std::fs::read(b.join(&name)).expect("reads"),
        );
        assert!(x == y, "{name} differs: {} and {} bytes", x.len(), y.len());
    }
}

fn content_version(db: &Path) -> String {
    terrain_server::db::TileDb::open(db, terrain_server::db::Verify::Hashes)
        .expect("opens, every blob's hash checked")
        .manifest()
        .content_version
        .clone()
}

/// Jacksboro with voids across the region edges, cut into 33^2 tiles: four jobs run at once
/// and a merge make the database one build makes, web tiles and computed texture included.
#[test]
fn four_region_jobs_and_a_merge_make_the_database_one_build_makes() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (width, height, codes) = png_codes(&jacksboro());
    let raster = RasterSize { width, height };
    // Where the regions meet, in level-0 rows: each void straddles one such edge.
    let edges: Vec<u32> = (1..4)
        .map(|i| {
            let (k, rows) = split(raster, 33, Region { index: i, count: 4 }).expect("splits");
            (rows.start * 32) << k
        })
        .collect();
    assert!(
        edges.windows(2).all(|w| w[0] < w[1]) && edges[0] > 0,
        "{edges:?}"
    );
    let voids: Vec<_> = edges
        .iter()
        .zip([40, 180, 300])
        .map(|(&edge, x)| (edge - 6..edge + 5, x..x + 30))
        .collect();
    let dem = tmp.path().join("dem.png");
    write_dem(&dem, width, height, &codes, &voids);
    // A dataset.json beside it: spacing and georeference (so web tiles are made), no-data.
    let mut info: serde_json::Value = serde_json::from_slice(
        &std::fs::read(jacksboro().with_file_name("dataset.json")).expect("dataset.json"),
    )
    .expect("json");
    info["nodata"] = NODATA.into();
    std::fs::write(
        tmp.path().join("dataset.json"),
        serde_json::to_vec(&info).expect("json"),
    )
    .expect("writes");
    let flags = ["--tile-size", "33"];
    let one = tmp.path().join("one");
    let (ok, stdout, stderr) = run(&[
        &["build", "--quiet", utf8(&dem), "--out", utf8(&one)][..],
        &flags,
    ]
    .concat());
    assert!(ok, "{stderr}");
    assert!(
        stdout.contains("filled 990 no-data samples in 3 voids"),
        "{stdout}"
    );
    assert!(stdout.contains("  web "), "web tiles made: {stdout}");

    let jobs = tmp.path().join("jobs");
    run_jobs_at_once(&dem, &jobs, 4, &flags);
    let merged = tmp.path().join("merged");
    let (ok, stdout, stderr) = run(&["merge", "--quiet", utf8(&jobs), "--out", utf8(&merged)]);
    assert!(ok, "{stderr}");
    assert!(
        stdout.starts_with("built "),
        "the build's summary: {stdout}"
    );
    assert_eq!(content_version(&merged), content_version(&one));
    assert_same_database(&merged, &one);
}

/// A region job killed while it writes leaves only its hidden temporary directory: the merge
/// refuses the jobs directory (naming the missing region) and writes nothing; the job run
/// again removes what the killed one left and the merge then gives one build's database.
/// A damaged job file is refused by name; a finished job run again changes nothing.
#[test]
fn a_killed_region_job_rerun_gives_the_same_database_and_a_damaged_one_is_refused() {
    let tmp = tempfile::tempdir().expect("tempdir");
    // Large enough, in small tiles, that a job writes for a good while.
    let (width, height) = (1025, 1025);
    let dem = tmp.path().join("dem.png");
    write_dem(&dem, width, height, &synthetic_codes(width, height), &[]);
    let texture = tmp.path().join("texture.png");
    image::RgbImage::from_fn(512, 512, |x, y| {
        image::Rgb([(x / 2) as u8, (y / 2) as u8, ((x ^ y) % 256) as u8])
    })
    .save(&texture)
    .expect("writes the texture");
    let flags = [
        "--tile-size",
        "17",
        "--texture",
        utf8(&texture),
        "--spacing",
        "30",
    ];
    let one = tmp.path().join("one");
    let (ok, _, stderr) = run(&[
        &["build", "--quiet", utf8(&dem), "--out", utf8(&one)][..],
        &flags,
    ]
    .concat());
    assert!(ok, "{stderr}");

    let jobs = tmp.path().join("jobs");
    for i in [0, 2, 3] {
        let (ok, _, stderr) = run(&[
            &[
                "build",
                "--quiet",
                utf8(&dem),
                "--region",
                &format!("{i}/4"),
                "--out",
                utf8(&jobs),
            ][..],
            &flags,
        ]
        .concat());
        assert!(ok, "{stderr}");
    }
    // Job 1, killed (SIGKILL) once its temporary directory holds tiles.
    let mut child = Command::new(workspace_binary("terrain-server"))
        .args(["build", "--quiet"])
        .arg(&dem)
        .args(["--region", "1/4", "--out"])
        .arg(&jobs)
        .args(flags)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("job starts");
    let temporary = || -> Option<PathBuf> {
        std::fs::read_dir(&jobs)
            .ok()?
            .flatten()
            .map(|e| e.path())
            .find(|p| {
                p.file_name()
                    .is_some_and(|n| n.to_string_lossy().starts_with(".job-1-of-4.building-"))
            })
    };
    let started = std::time::Instant::now();
    let partial = loop {
        let written = temporary().and_then(|dir| {
            let level0 = std::fs::metadata(dir.join("heights.level-0")).ok()?;
            (level0.len() > 0).then_some(dir)
        });
        if let Some(dir) = written {
            break dir;
        }
        assert!(
            child.try_wait().expect("waits").is_none(),
            "job 1 ended before it wrote a tile that could be seen"
        );
        assert!(started.elapsed().as_secs() < 120, "job 1 wrote nothing");
        std::thread::sleep(std::time::Duration::from_millis(1));
    };
    child.kill().expect("kills");
    child.wait().expect("reaped");
    assert!(
        !jobs.join("job-1-of-4").exists(),
        "job 1 finished before it was killed: the test needs a larger input"
    );
    assert!(
        partial.exists(),
        "the killed job's temporary directory stays"
    );

    let merged = tmp.path().join("merged");
    let merge = || {
        run(&[
            "merge",
            "--quiet",
            "--no-web",
            utf8(&jobs),
            "--out",
            utf8(&merged),
        ])
    };
    let (ok, _, stderr) = merge();
    assert!(!ok, "a merge without job 1 must fail");
    assert!(stderr.contains("missing region job(s) 1/4"), "{stderr}");
    assert!(!merged.exists(), "nothing at the output");

    // Rerun: the killed job's leftovers go, the result is one build's.
    let rerun = |i: u32| {
        run(&[
            &[
                "build",
                "--quiet",
                utf8(&dem),
                "--region",
                &format!("{i}/4"),
                "--out",
                utf8(&jobs),
            ][..],
            &flags,
        ]
        .concat())
    };
    let (ok, stdout, stderr) = rerun(1);
    assert!(ok, "{stderr}");
    assert!(
        stdout.contains("removed what 1 killed build(s)"),
        "{stdout}"
    );
    assert!(!partial.exists());
    let job2 = std::fs::read(jobs.join("job-2-of-4/carries")).expect("carries");
    let (ok, _, stderr) = rerun(2);
    assert!(ok, "{stderr}");
    assert_eq!(
        std::fs::read(jobs.join("job-2-of-4/carries")).expect("carries"),
        job2,
        "a job run again makes the same"
    );
    let (ok, _, stderr) = merge();
    assert!(ok, "{stderr}");
    assert_eq!(content_version(&merged), content_version(&one));
    assert_same_database(&merged, &one);
    std::fs::remove_dir_all(&merged).expect("removes");

    // Damage: a flipped byte in a carry, then a level file cut short.
    let carries = jobs.join("job-3-of-4/carries");
    let mut bytes = std::fs::read(&carries).expect("reads");
    bytes[40] ^= 0x10;
    std::fs::write(&carries, &bytes).expect("writes");
    let (ok, _, stderr) = merge();
    assert!(!ok);
    assert!(
        stderr.contains("job-3-of-4/carries holds") && stderr.contains("run region 3/4 again"),
        "{stderr}"
    );
    assert!(!merged.exists());
    bytes[40] ^= 0x10;
    std::fs::write(&carries, &bytes).expect("writes");
    let level0 = jobs.join("job-0-of-4/heights.level-0");
    let len = std::fs::metadata(&level0).expect("exists").len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&level0)
        .and_then(|f| f.set_len(len - 1))
        .expect("truncates");
    let (ok, _, stderr) = merge();
    assert!(!ok);
    assert!(
        stderr.contains("job-0-of-4/heights.level-0 holds") && stderr.contains("run region 0/4"),
        "{stderr}"
    );
    assert!(!merged.exists());
    let (ok, _, stderr) = rerun(0);
    assert!(ok, "{stderr}");

    // A job built with another setting than the others.
    let (ok, _, stderr) = run(&[
        &[
            "build",
            "--quiet",
            utf8(&dem),
            "--region",
            "3/4",
            "--out",
            utf8(&jobs),
            "--jpeg-quality",
            "50",
        ][..],
        &flags,
    ]
    .concat());
    assert!(ok, "{stderr}");
    let (ok, _, stderr) = merge();
    assert!(!ok);
    assert!(
        stderr.contains("region 3/4 was built with other settings or another input"),
        "{stderr}"
    );
    assert!(!merged.exists());
}

/// Regions tile the split level's rows in order, the split level is the coarsest with a row
/// for every job, and more jobs than level 0's tile rows are refused.
#[test]
fn regions_cover_the_split_levels_rows_once_and_too_many_jobs_are_refused() {
    let raster = RasterSize {
        width: 4097,
        height: 3000,
    };
    for count in 1..=24 {
        let mut next = 0;
        let mut level = None;
        for index in 0..count {
            let (k, rows) = split(raster, 129, Region { index, count }).expect("splits");
            assert!(level.is_none_or(|l| l == k));
            level = Some(k);
            assert_eq!(rows.start, next);
            assert!(!rows.is_empty(), "{count} jobs: region {index} is empty");
            next = rows.end;
        }
        let k = level.expect("a level") as usize;
        let grids = terrain_shared::manifest::level_rasters(raster, 129);
        let rows_at = |k: usize| (grids[k].height - 1).div_ceil(128).max(1);
        assert_eq!(next, rows_at(k), "{count} jobs cover level {k}");
        assert!(k + 1 == grids.len() || rows_at(k + 1) < count);
    }
    let error = split(
        raster,
        129,
        Region {
            index: 0,
            count: 25,
        },
    )
    .expect_err("24 rows");
    assert!(error.to_string().contains("at most 24 jobs"), "{error}");
    assert!(Region::parse("4/4").is_err() && Region::parse("a/4").is_err());
    assert_eq!(Region::parse("3/4"), Ok(Region { index: 3, count: 4 }));
}

fn utf8(path: &Path) -> &str {
    path.to_str().expect("a UTF-8 temporary path")
}
