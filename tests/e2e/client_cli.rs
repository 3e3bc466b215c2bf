//! The `terrain-client` release binary as a person or a script runs it, against a real
//! server: what it prints on stdout and stderr, and its exit status, when its reader goes
//! away, when a file cannot be read or written, when a tile keeps failing, when a body has
//! no end and when the memory limit cannot hold what the client needs.

use std::ffi::OsString;
use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::Duration;
use terrain_client::http_client::MAX_MANIFEST_BYTES;
use terrain_tests::child::{Watched, run_watched};
use terrain_tests::data::{build_jacksboro, workspace_binary};
use terrain_tests::proxy::{Fault, FaultPlan, FaultyProxy};
use terrain_tests::server::TestServer;

/// A 2 s flight held still over tile (1, 1) of jacksboro's 4 x 3 grid.
fn still_flight(dir: &Path) -> std::path::PathBuf {
    let path = dir.join("still.json");
    std::fs::write(
        &path,
        r#"{"units": "extent", "keyframes": [
            {"t": 0, "x": 0.4, "y": 0.5, "z": 3000},
            {"t": 2, "x": 0.4, "y": 0.5, "z": 3000}]}"#,
    )
    .expect("flight file");
    path
}

/// `terrain-client fly --no-render --quiet` against `server` with `extra` arguments.
fn fly_command(server: &str, out: &Path, flight: &Path, extra: &[&str]) -> Command {
    let mut command = Command::new(workspace_binary("terrain-client"));
    let mut args: Vec<OsString> = vec![
        "fly".into(),
        "--server".into(),
        server.into(),
        "--no-render".into(),
        "--quiet".into(),
        "--flight".into(),
        flight.into(),
        "--out".into(),
        out.into(),
    ];
    args.extend(extra.iter().map(OsString::from));
    command.args(args).env("RUST_LOG", "warn");
    command
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

fn run(mut command: Command) -> Output {
    command.output().expect("terrain-client runs")
}

#[test]
fn a_reader_that_goes_away_ends_the_client_quietly_and_successfully() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(&build_jacksboro(tmp.path()).out);
    let mut command = fly_command(
        server.base_url(),
        &tmp.path().join("flight"),
        &still_flight(tmp.path()),
        &[],
    );
    let mut child = command
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("terrain-client starts");
    // `terrain-client fly ... | true`: the reader is gone before anything is printed.
    drop(child.stdout.take());
    let output = child.wait_with_output().expect("terrain-client ends");
    let stderr = text(&output.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(output.status.code(), Some(0), "{stderr}");
    assert!(tmp.path().join("flight/flight.csv").exists());
}

#[test]
fn an_error_prints_each_cause_once() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(&build_jacksboro(tmp.path()).out);
    let flight = still_flight(tmp.path());
    let a_file = tmp.path().join("a-file");
    std::fs::write(&a_file, b"not a directory").expect("file");
    let cases = [
        (
            fly_command(
                server.base_url(),
                &tmp.path().join("out"),
                &tmp.path().join("no-such-flight.json"),
                &[],
            ),
            "cannot read flight path",
            "No such file or directory",
        ),
        (
            fly_command(server.base_url(), &a_file.join("out"), &flight, &[]),
            "cannot write",
            "Not a directory",
        ),
    ];
    for (command, context, cause) in cases {
        let output = run(command);
        let stderr = text(&output.stderr);
        assert_eq!(output.status.code(), Some(1), "{stderr}");
        let line = stderr
            .lines()
            .find(|line| line.starts_with("error: "))
            .unwrap_or_else(|| panic!("no error line: {stderr}"));
        assert!(line.contains(context), "{line}");
        assert_eq!(line.matches(cause).count(), 1, "{line}");
    }
}

#[test]
fn a_failing_tile_is_warned_about_with_the_cause_of_its_failure() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(&build_jacksboro(tmp.path()).out);
    // Every request for tile (1, 1)'s heights (its tile blob, level 0) is reset.
    const BAD: &str = "/levels/0/tiles/1/1/heights";
    let proxy = FaultyProxy::start(
        server.addr(),
        FaultPlan::rotation(&[Fault::Reset]).only_paths_containing(BAD),
    );
    let output = run(fly_command(
        proxy.base_url(),
        &tmp.path().join("flight"),
        &still_flight(tmp.path()),
        &[],
    ));
    let stderr = text(&output.stderr);
    let warning = stderr
        .lines()
        .find(|line| line.contains("tile request failed"))
        .unwrap_or_else(|| panic!("no warning for the failing tile: {stderr}"));
    // "GET <url> failed" and, after it, what failed underneath (reqwest's error and the
    // connection's).
    let (_, cause) = warning
        .split_once(&format!("{BAD} failed: "))
        .unwrap_or_else(|| panic!("no cause after the URL: {warning}"));
    assert!(cause.len() > 10, "{warning}");
    assert_eq!(warning.matches(BAD).count(), 1 + cause.matches(BAD).count());
}

#[test]
fn a_memory_limit_below_what_the_client_needs_is_refused_at_start_with_the_budget_that_would_do() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(&build_jacksboro(tmp.path()).out);
    let flight = still_flight(tmp.path());
    let output = run(fly_command(
        server.base_url(),
        &tmp.path().join("refused"),
        &flight,
        &["--memory", "1KiB"],
    ));
    let stderr = text(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    // The limit (90% of 1 KiB), what it cannot hold and why, and the budget that would do.
    for part in [
        "921 bytes",
        "cannot hold what paging (--no-render) needs",
        "for the coarsest level of the pyramid, which it holds whole",
        "give --memory ",
    ] {
        assert!(stderr.contains(part), "{part:?} in {stderr}");
    }
    assert!(!tmp.path().join("refused").exists(), "nothing written");
    let least = stderr
        .split("give --memory ")
        .nth(1)
        .and_then(|rest| rest.split_whitespace().next())
        .expect("a budget");
    let output = run(fly_command(
        server.base_url(),
        &tmp.path().join("flown"),
        &flight,
        &["--memory", least],
    ));
    let (stdout, stderr) = (text(&output.stdout), text(&output.stderr));
    assert_eq!(output.status.code(), Some(0), "--memory {least}: {stderr}");
    assert!(stdout.contains("never over it"), "{stdout}");
}

/// `terrain-client fetch` of `server` into `out`.
fn fetch_command(server: &str, out: &Path) -> Command {
    let mut command = Command::new(workspace_binary("terrain-client"));
    command
        .args(["fetch", "--server", server, "--out"])
        .arg(out)
        .env("RUST_LOG", "warn");
    command
}

const MIB: u64 = 1 << 20;

/// A server (or a proxy in front of one) that sends a tile or the manifest as a body
/// without end, or says it will send a gigabyte: `fetch` and `fly --memory 64MiB` cut each
/// off at the size it can be (the tile's from the manifest; the manifest's a cap, the
/// memory budget for a flight) and end with a clear error, holding no more than the limit
/// beyond what the same command holds against an honest server.
#[test]
fn an_endless_or_oversized_body_is_cut_off_within_the_memory_limit_with_a_clear_error() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(&build_jacksboro(tmp.path()).out);
    let flight = still_flight(tmp.path());
    const LIMIT: u64 = 64 * MIB;
    const TILE: &str = "/levels/0/tiles/1/1/heights";
    const MANIFEST: &str = "/v1/manifest.json";
    let deadline = Duration::from_secs(120);
    let fly = |server: &str, out: &str| {
        fly_command(
            server,
            &tmp.path().join(out),
            &flight,
            &["--memory", "64MiB"],
        )
    };
    let fetch = |server: &str, out: &str| fetch_command(server, &tmp.path().join(out));
    // The fixed cost: each command against the honest server, through a proxy that passes
    // everything (the same path for the bytes).
    let honest = FaultyProxy::start(server.addr(), FaultPlan::pass_through());
    let succeeded = |what: &str, run: &Watched| {
        assert!(run.killed.is_none(), "{what}: killed, {:?}", run.killed);
        assert_eq!(
            run.output.status.code(),
            Some(0),
            "{what}: {}",
            run.stderr()
        );
        run.peak_bytes
    };
    let fly_fixed = succeeded(
        "fly",
        &run_watched(fly(honest.base_url(), "honest-fly"), 4 * LIMIT, deadline),
    );
    let fetch_fixed = succeeded(
        "fetch",
        &run_watched(
            fetch(honest.base_url(), "honest-fetch"),
            4 * LIMIT,
            deadline,
        ),
    );
    for (fault, path) in [
        (Fault::Endless, TILE),
        (Fault::Oversized, TILE),
        (Fault::Endless, MANIFEST),
        (Fault::Oversized, MANIFEST),
    ] {
        let proxy = FaultyProxy::start(
            server.addr(),
            FaultPlan::rotation(&[fault]).only_paths_containing(path),
        );
        let what = format!("{fault:?} {path}");
        // fly: within its limit beyond the fixed cost.
        let bound = fly_fixed + LIMIT;
        let run = run_watched(fly(proxy.base_url(), "fly"), bound, deadline);
        let stderr = run.stderr();
        assert!(
            run.killed.is_none(),
            "fly, {what}: killed, {:?}: {stderr}",
            run.killed
        );
        assert!(
            run.peak_bytes <= bound,
            "fly, {what}: {} > {bound} bytes",
            run.peak_bytes
        );
        assert!(
            stderr.contains("the body is longer than"),
            "fly, {what}: {stderr}"
        );
        // Without the manifest there is no flight; without a tile there is one, warned about.
        let code = if path == MANIFEST { 1 } else { 0 };
        assert_eq!(
            run.output.status.code(),
            Some(code),
            "fly, {what}: {stderr}"
        );
        // fetch: no memory option; a body holds no more than its size or the manifest's cap.
        let bound = fetch_fixed + MAX_MANIFEST_BYTES.max(LIMIT);
        let run = run_watched(fetch(proxy.base_url(), "fetch"), bound, deadline);
        let stderr = run.stderr();
        assert!(
            run.killed.is_none(),
            "fetch, {what}: killed, {:?}: {stderr}",
            run.killed
        );
        assert_eq!(run.output.status.code(), Some(1), "fetch, {what}: {stderr}");
        assert!(
            stderr.contains("the body is longer than"),
            "fetch, {what}: {stderr}"
        );
        if path == TILE {
            // A tile's body is cut off at the tile's size, a few kilobytes.
            assert!(
                run.peak_bytes <= fetch_fixed + 16 * MIB,
                "fetch, {what}: {} bytes against {fetch_fixed} without the fault",
                run.peak_bytes
            );
        }
        assert!(proxy.stats().endless > 0, "{what}: the fault was served");
    }
}

/// Flight paths that would cost memory without end are refused at start, with a reason,
/// in bounded memory: a path a hundred days long (each frame keeps a record), and a path
/// that is not a regular file (`/dev/zero`, read without end before).
#[test]
fn a_path_too_long_to_fly_or_not_a_file_is_refused_at_start_in_bounded_memory() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(&build_jacksboro(tmp.path()).out);
    let long = tmp.path().join("long.csv");
    std::fs::write(&long, "t,x,y,z\n0,1000,1000,3000\n1e7,2000,1000,3000\n").expect("path");
    let big = tmp.path().join("big.json");
    let file = std::fs::File::create(&big).expect("file");
    file.set_len(terrain_client::path::MAX_PATH_FILE_BYTES + 1)
        .expect("sparse file");
    let cases: [(&Path, &str); 3] = [
        (&long, "at most 5184000 frames are flown"),
        (Path::new("/dev/zero"), "not a regular file"),
        (&big, "more than the 67108864 a camera path may have"),
    ];
    for (flight, reason) in cases {
        let out = tmp.path().join("out");
        let Watched {
            output,
            peak_bytes,
            killed,
        } = run_watched(
            fly_command(server.base_url(), &out, flight, &[]),
            512 << 20,
            Duration::from_secs(60),
        );
        let stderr = text(&output.stderr);
        assert!(
            killed.is_none(),
            "{}: {killed:?} {stderr}",
            flight.display()
        );
        assert_eq!(
            output.status.code(),
            Some(1),
            "{}: {stderr}",
            flight.display()
        );
        assert!(stderr.contains(reason), "{}: {stderr}", flight.display());
        assert!(!stderr.contains("panicked"), "{stderr}");
        assert!(
            peak_bytes < 512 << 20,
            "{}: {peak_bytes} bytes",
            flight.display()
        );
        assert!(!out.exists(), "nothing written for {}", flight.display());
    }
}

/// `command` with the files it writes limited to `kib` KiB (bash's `ulimit -f`, with
/// SIGXFSZ ignored so the limit is an error, not a kill): a write or a reservation past it
/// fails with EFBIG ("File too large") at the moment it is made, as one on a full disk fails
/// with ENOSPC, without filling a disk this machine shares.
fn with_files_limited_to(command: &Command, kib: u64) -> Command {
    let mut limited = Command::new("bash");
    limited
        .arg("-c")
        .arg(format!("trap '' XFSZ; ulimit -f {kib}; exec \"$0\" \"$@\""))
        .arg(command.get_program())
        .args(command.get_args());
    for (key, value) in command.get_envs() {
        match value {
            Some(value) => limited.env(key, value),
            None => limited.env_remove(key),
        };
    }
    limited
}

/// Every file under `dir`, with its size.
fn files_under(dir: &Path) -> Vec<(String, u64)> {
    let mut files = Vec::new();
    if let Ok(entries) = std::fs::read_dir(dir) {
        for entry in entries {
            let entry = entry.expect("entry");
            let meta = entry.metadata().expect("metadata");
            if meta.is_dir() {
                files.extend(files_under(&entry.path()));
            } else {
                files.push((entry.path().display().to_string(), meta.len()));
            }
        }
    }
    files
}

/// Heights requests the server has answered, from its `/metrics`.
fn heights_requests(server: &TestServer) -> f64 {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let text = runtime.block_on(async {
        reqwest::get(server.url("/metrics"))
            .await
            .expect("metrics")
            .text()
            .await
            .expect("text")
    });
    text.lines()
        .filter(|l| l.starts_with("http_requests_total{") && l.contains("heights"))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum()
}

/// A disk that fills during `fetch` or `fly` (here a file size limit, which refuses a write
/// the way a full disk does): `fetch` finds it before a tile is asked for (its outputs'
/// space is reserved first), `fly` at the frame whose row does not fit (flight.csv is
/// written as frames fly), or at start when even the rows' least size does not fit; each
/// exits 1 naming the file and the cause, and leaves no file cut short or of 0 bytes.
#[test]
fn a_disk_that_fills_is_reported_while_fetching_or_flying_and_leaves_no_output_cut_short() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(&build_jacksboro(tmp.path()).out);
    let no_output_cut_short = |out: &Path| {
        let files = files_under(out);
        assert!(files.is_empty(), "left behind: {files:?}");
    };

    // fetch: 8 KiB of file, far less than the overview can take.
    let out = tmp.path().join("fetch");
    let output = run(with_files_limited_to(
        &fetch_command(server.base_url(), &out),
        8,
    ));
    let stderr = text(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("overview.png") && stderr.contains("File too large"),
        "{stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(heights_requests(&server), 0.0, "reported before the fetch");
    no_output_cut_short(&out);
    // The same fetch with room succeeds: the limit was the only thing in the way.
    let room = run(fetch_command(server.base_url(), &out));
    assert_eq!(room.status.code(), Some(0), "{}", text(&room.stderr));
    let written = files_under(&out);
    assert!(
        written.len() == 2 && written.iter().all(|(_, bytes)| *bytes > 0),
        "{written:?}"
    );

    // fly, 401 frames of a 2 s path at 200 fps; its rows take more than 64 bytes each, so
    // 32 KiB holds the least reserved at start (401 x 64) and not every row.
    let flight = still_flight(tmp.path());
    let out = tmp.path().join("fly");
    let fly = fly_command(server.base_url(), &out, &flight, &["--fps", "200"]);
    let output = run(with_files_limited_to(&fly, 32));
    let stderr = text(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    let frame: u64 = stderr
        .split("flight.csv at frame ")
        .nth(1)
        .and_then(|rest| rest.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no frame named: {stderr}"));
    assert!(
        frame > 0 && frame < 400 && stderr.contains("of 401") && stderr.contains("File too large"),
        "stopped at the frame that did not fit, not after the flight: {stderr}"
    );
    no_output_cut_short(&out);

    // fly with 4 KiB: not even the rows' least size fits, found before the first frame.
    let output = run(with_files_limited_to(&fly, 4));
    let stderr = text(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("flight.csv at frame 0 of 401"), "{stderr}");
    no_output_cut_short(&out);
}
