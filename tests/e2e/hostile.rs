//! Hostile use of the release binaries: outputs that are not ours to replace, races, closed
//! pipes, and error messages that must say what happened once.

use std::path::{Path, PathBuf};
use terrain_server::db::{DbWriter, WriteError};
use terrain_shared::Manifest;
use terrain_tests::data::{jacksboro, run_binary};

fn build_args(out: &Path, extra: &[&str]) -> Vec<std::ffi::OsString> {
    let mut args: Vec<std::ffi::OsString> = vec![
        "build".into(),
        jacksboro().into_os_string(),
        "--out".into(),
        out.as_os_str().to_owned(),
        "--tile-size".into(),
        "129".into(),
    ];
    args.extend(extra.iter().map(Into::into));
    args
}

fn run_build(out: &Path, extra: &[&str]) -> (bool, String, String) {
    let args = build_args(out, extra);
    let refs: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
    run_binary("terrain-server", &refs)
}

/// Every entry of `dir`, sorted, hidden ones included.
fn entries(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .expect("readable")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

#[test]
fn force_refuses_a_directory_that_is_not_a_tile_database() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let documents = tmp.path().join("documents");
    std::fs::create_dir(&documents).expect("mkdir");
    std::fs::write(documents.join("thesis.tex"), "years of work").expect("write");
    std::fs::write(documents.join("notes.txt"), "more").expect("write");

    let (ok, _, stderr) = run_build(&documents, &["--force"]);
    assert!(!ok, "a folder of documents was replaced: {stderr}");
    assert!(
        stderr.contains("is not a tile database") && stderr.contains("notes.txt, thesis.tex"),
        "the refusal says what it found: {stderr}"
    );
    assert_eq!(entries(&documents), ["notes.txt", "thesis.tex"]);
    assert_eq!(
        std::fs::read_to_string(documents.join("thesis.tex")).expect("kept"),
        "years of work"
    );
    assert_eq!(entries(tmp.path()), ["documents"], "nothing left beside it");
}

#[test]
fn force_refuses_a_regular_file_and_leaves_it_where_it_was() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let file = tmp.path().join("report.pdf");
    std::fs::write(&file, "%PDF-1.7 precious").expect("write");
    for attempt in 0..2 {
        let (ok, _, stderr) = run_build(&file, &["--force"]);
        assert!(
            !ok,
            "attempt {attempt}: a regular file was replaced: {stderr}"
        );
        assert!(
            stderr.contains("is not a tile database (a file of 17 bytes)"),
            "attempt {attempt}: {stderr}"
        );
        assert_eq!(
            std::fs::read_to_string(&file).expect("kept"),
            "%PDF-1.7 precious"
        );
        assert_eq!(entries(tmp.path()), ["report.pdf"], "attempt {attempt}");
    }
}

#[test]
fn force_replaces_a_database_and_an_empty_directory() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("db");
    std::fs::create_dir(&out).expect("mkdir");
    let (ok, _, stderr) = run_build(&out, &["--force"]);
    assert!(ok, "an empty directory is replaced: {stderr}");
    let (ok, _, stderr) = run_build(&out, &[]);
    assert!(!ok && stderr.contains("pass --force"), "{stderr}");
    let (ok, _, stderr) = run_build(&out, &["--force"]);
    assert!(ok, "a database is replaced: {stderr}");
    assert_eq!(entries(tmp.path()), ["db"]);
    // The fixture is georeferenced: the command line makes its web tiles too.
    assert_eq!(
        entries(&out),
        ["heights.pack", "manifest.json", "textures.pack", "web.pack"]
    );
}

#[test]
fn an_error_cause_is_printed_once() {
    let tmp = tempfile::tempdir().expect("tempdir");
    // A parent that is a file: the output directory cannot be created under it.
    let blocker = tmp.path().join("blocker");
    std::fs::write(&blocker, "x").expect("write");
    let (ok, _, stderr) = run_build(&blocker.join("db"), &[]);
    assert!(!ok);
    let cause = "Not a directory";
    assert_eq!(
        stderr.matches(cause).count(),
        1,
        "the cause appears once: {stderr}"
    );
}

fn empty_manifest() -> Manifest {
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = terrain_tests::data::build_jacksboro(tmp.path());
    let db = terrain_server::db::TileDb::open(&report.out, terrain_server::db::Verify::SizesOnly)
        .expect("opens");
    let mut manifest = db.manifest().clone();
    for level in &mut manifest.levels {
        level.tiles.clear();
    }
    manifest
}

/// Two builds to one output: the first to finish wins, the second says so plainly and
/// leaves nothing behind (no `.building-*`, no half-replaced database).
#[test]
fn the_second_of_two_racing_builds_says_what_happened() {
    let manifest = empty_manifest();
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("db");
    let first = DbWriter::create(&out, false).expect("first");
    let second = DbWriter::create(&out, false).expect("second");
    first.finish(&manifest).expect("the first finishes");
    let error = second.finish(&manifest).expect_err("the second is refused");
    assert!(
        matches!(error, WriteError::AppearedMeanwhile(_)),
        "{error:?}"
    );
    let message = error.to_string();
    assert!(
        message.contains("appeared while this build ran") && !message.contains("os error"),
        "{message}"
    );
    assert_eq!(entries(tmp.path()), ["db"]);
    let kept: PathBuf = out.join("manifest.json");
    assert!(kept.exists(), "the first build's database stays");
}

/// `terrain-server build … | true`: the reader is gone before the summary is printed.
#[test]
fn a_closed_stdout_ends_a_build_quietly() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("db");
    let mut child =
        std::process::Command::new(terrain_tests::data::workspace_binary("terrain-server"))
            .args(build_args(&out, &[]))
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .expect("spawns");
    drop(child.stdout.take());
    let output = child.wait_with_output().expect("waits");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success(),
        "{:?}: {stderr}",
        output.status.code()
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(
        out.join("manifest.json").exists(),
        "the build was completed"
    );
}

/// Logs written to a file (not a terminal) carry no colour escape codes.
#[test]
fn logs_to_a_file_have_no_colour_codes() {
    use std::io::{BufRead, BufReader};
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = terrain_tests::data::build_jacksboro(tmp.path());
    let log = tmp.path().join("server.log");
    let mut child =
        std::process::Command::new(terrain_tests::data::workspace_binary("terrain-server"))
            .arg("serve")
            .arg(&report.out)
            .args(["--addr", "127.0.0.1:0"])
            .stdout(std::process::Stdio::piped())
            .stderr(std::fs::File::create(&log).expect("log file"))
            .spawn()
            .expect("spawns");
    let mut line = String::new();
    BufReader::new(child.stdout.take().expect("stdout"))
        .read_line(&mut line)
        .expect("listening line");
    assert!(line.starts_with("listening on http://"), "{line}");
    let _ = child.kill();
    let _ = child.wait();
    let text = std::fs::read_to_string(&log).expect("log");
    assert!(
        text.contains("database opened"),
        "the log has the start line: {text}"
    );
    assert!(
        !text.contains('\u{1b}'),
        "escape codes in a log file: {text:?}"
    );
}

/// A pack truncated under a running server (`truncate -s 100000 DB/heights.pack`): a tile
/// past the cut gets a 500 naming the pack over HTTP/1 and HTTP/2 alike, with a line in the
/// log; the process lives on and serves what is still whole; `/metrics` counts the 500,
/// not a 200.
#[test]
fn a_pack_truncated_under_the_server_answers_an_error_on_http1_and_http2_and_the_server_lives() {
    use std::io::{BufRead, BufReader};
    use terrain_shared::routes;
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = terrain_tests::data::build_jacksboro(tmp.path());
    let manifest = &report.manifest;
    let log = tmp.path().join("server.log");
    let mut child =
        std::process::Command::new(terrain_tests::data::workspace_binary("terrain-server"))
            .arg("serve")
            .arg(&report.out)
            .args(["--addr", "127.0.0.1:0"])
            .stdout(std::process::Stdio::piped())
            .stderr(std::fs::File::create(&log).expect("log file"))
            .spawn()
            .expect("spawns");
    let mut line = String::new();
    BufReader::new(child.stdout.take().expect("stdout"))
        .read_line(&mut line)
        .expect("listening line");
    let base = line
        .trim()
        .strip_prefix("listening on ")
        .unwrap_or_else(|| panic!("{line}"))
        .trim_end_matches('/')
        .to_string();

    // Tiles lie in the pack in manifest order: one wholly before the cut, one past it.
    const CUT: u64 = 100_000;
    let mut offset = 0u64;
    let (mut before, mut after) = (None, None);
    for (id, tile) in manifest.tiles() {
        let end = offset + tile.blob().bytes;
        if end <= CUT {
            before = Some(id);
        } else if offset >= CUT && after.is_none() {
            after = Some(id);
        }
        offset = end;
    }
    let (before, after) = (
        before.expect("a tile before the cut"),
        after.expect("one past it"),
    );
    std::fs::OpenOptions::new()
        .write(true)
        .open(report.out.join("heights.pack"))
        .expect("pack")
        .set_len(CUT)
        .expect("truncate");

    let v = &manifest.content_version;
    let runtime = tokio::runtime::Runtime::new().expect("runtime");
    runtime.block_on(async {
        let http1 = reqwest::Client::builder()
            .http1_only()
            .build()
            .expect("client");
        let http2 = reqwest::Client::builder()
            .http2_prior_knowledge()
            .build()
            .expect("client");
        for (client, version) in [
            (&http1, reqwest::Version::HTTP_11),
            (&http2, reqwest::Version::HTTP_2),
        ] {
            let url = format!("{base}{}", routes::heights(v, after));
            let response =
                client.get(&url).send().await.unwrap_or_else(|e| {
                    panic!("{version:?}: no answer for a tile past the cut: {e}")
                });
            assert_eq!(response.version(), version);
            assert_eq!(response.status(), 500, "{version:?} {url}");
            let body = response.text().await.expect("error body");
            assert!(
                body.contains("heights.pack changed after the server opened it"),
                "{version:?}: {body}"
            );
            let whole = client
                .get(format!("{base}{}", routes::heights(v, before)))
                .send()
                .await
                .expect("the server lives on");
            assert_eq!(whole.status(), 200, "{version:?}");
            let body = whole.bytes().await.expect("body");
            assert_eq!(
                body.len() as u64,
                manifest.tile(before).expect("in grid").blob().bytes
            );
        }
        let metrics = http1
            .get(format!("{base}/metrics"))
            .send()
            .await
            .expect("metrics")
            .text()
            .await
            .expect("text");
        let count = |status: &str| -> f64 {
            metrics
                .lines()
                .filter(|l| {
                    l.starts_with("http_requests_total{")
                        && l.contains("heights")
                        && l.contains(&format!("status=\"{status}\""))
                })
                .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
                .sum()
        };
        assert_eq!(count("500"), 2.0, "{metrics}");
        assert_eq!(count("200"), 2.0, "{metrics}");
    });
    assert!(
        child.try_wait().expect("status").is_none(),
        "the server exited"
    );
    let _ = child.kill();
    let _ = child.wait();
    let text = std::fs::read_to_string(&log).expect("log");
    assert!(
        text.contains("heights.pack changed after the server opened it"),
        "the log says what happened: {text}"
    );
}

/// Inputs that are not regular files are refused by name before anything is read:
/// `build /dev/zero` read without end before (8 GB in 8 s), a FIFO would block, a
/// directory is no raster.
#[test]
fn a_build_from_a_device_a_fifo_or_a_directory_is_refused_by_name() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let fifo = tmp.path().join("heights.png");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .expect("mkfifo runs");
    assert!(made.success());
    let cases: [(&Path, &str); 3] = [
        (Path::new("/dev/zero"), "a character device"),
        (&fifo, "a FIFO"),
        (tmp.path(), "a directory"),
    ];
    for (input, what) in cases {
        let out = tmp.path().join("db");
        let output =
            std::process::Command::new(terrain_tests::data::workspace_binary("terrain-server"))
                .arg("build")
                .arg(input)
                .arg("--out")
                .arg(&out)
                .output()
                .expect("runs");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(
            output.status.code(),
            Some(1),
            "{}: {stderr}",
            input.display()
        );
        assert!(
            stderr.contains(&format!("is not a regular file ({what})")),
            "{}: {stderr}",
            input.display()
        );
        assert!(!out.exists());
    }
}

/// Options that would make a server that cannot work, or write what is not a web address
/// into the TileJSON documents, are refused before it starts, with the reason.
#[test]
fn serve_options_that_cannot_work_are_refused_with_the_reason() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = terrain_tests::data::build_jacksboro(tmp.path());
    let cases: [(&[&str], &str); 6] = [
        (
            &["--worker-threads", "100000"],
            "more than the 1024 a server starts",
        ),
        (&["--max-concurrent-requests", "0"], "must be at least 1"),
        (&["--max-connections", "0"], "must be at least 1"),
        (
            &["--public-url", "javascript:alert(1)"],
            "the scheme must be http or https",
        ),
        (
            &["--public-url", "https://tiles.example/?x=\"><script>"],
            "without credentials, query or fragment",
        ),
        (&["--public-url", "not a url"], "is not a URL"),
    ];
    for (flags, reason) in cases {
        let output =
            std::process::Command::new(terrain_tests::data::workspace_binary("terrain-server"))
                .arg("serve")
                .arg(&report.out)
                .args(["--addr", "127.0.0.1:0"])
                .args(flags)
                .stdin(std::process::Stdio::null())
                .output()
                .expect("runs");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(2), "{flags:?}: {stderr}");
        assert!(stderr.contains(reason), "{flags:?}: {stderr}");
        assert!(!stderr.contains("panicked"), "{flags:?}: {stderr}");
        assert!(output.stdout.is_empty(), "{flags:?}: it never listened");
    }
}

/// A real deflate stream of `bytes` zero bytes, as zlib wraps it: 1 MiB of zeros deflated
/// once with a full flush (which resets the dictionary, so every such block is the same
/// bytes) and repeated, then the rest, the end and the Adler-32 of the zeros.
fn zlib_of_zeros(bytes: u64) -> Vec<u8> {
    use flate2::{Compress, Compression, FlushCompress};
    const BLOCK: u64 = 1 << 20;
    let deflate = |c: &mut Compress, input: &[u8], flush| {
        let mut out = Vec::with_capacity(64 << 10);
        let before = c.total_in();
        c.compress_vec(input, &mut out, flush).expect("deflates");
        assert_eq!(c.total_in() - before, input.len() as u64, "all input taken");
        out
    };
    let mut c = Compress::new(Compression::best(), false);
    let zeros = vec![0u8; BLOCK as usize];
    let block = deflate(&mut c, &zeros, FlushCompress::Full);
    assert_eq!(
        deflate(&mut c, &zeros, FlushCompress::Full),
        block,
        "a block after a full flush repeats"
    );
    let mut stream = vec![0x78, 0xda];
    for _ in 0..bytes / BLOCK {
        stream.extend_from_slice(&block);
    }
    stream.extend(deflate(
        &mut c,
        &zeros[..(bytes % BLOCK) as usize],
        FlushCompress::Finish,
    ));
    // Adler-32 of zeros: a stays 1, b adds 1 a byte.
    let adler = (((bytes % 65521) as u32) << 16) | 1;
    stream.extend_from_slice(&adler.to_be_bytes());
    stream
}

/// A PNG chunk: length, type, data and the CRC of type and data.
fn png_chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    out.extend_from_slice(&(data.len() as u32).to_be_bytes());
    let mut crc = crc32fast::Hasher::new();
    crc.update(kind);
    crc.update(data);
    out.extend_from_slice(kind);
    out.extend_from_slice(data);
    out.extend_from_slice(&crc.finalize().to_be_bytes());
}

/// A valid 8-bit greyscale PNG of `side` x `side` zero samples, every row filtered "none".
fn png_of_zeros(side: u32) -> Vec<u8> {
    let mut png = vec![137, 80, 78, 71, 13, 10, 26, 10];
    let mut header = Vec::new();
    header.extend_from_slice(&side.to_be_bytes());
    header.extend_from_slice(&side.to_be_bytes());
    header.extend_from_slice(&[8, 0, 0, 0, 0]);
    png_chunk(&mut png, b"IHDR", &header);
    let decoded = u64::from(side) * (u64::from(side) + 1);
    png_chunk(&mut png, b"IDAT", &zlib_of_zeros(decoded));
    png_chunk(&mut png, b"IEND", &[]);
    png
}

/// A PNG of 10 MB that inflates to 10 GB (10^10 samples): refused by its size, before its
/// samples are read, with how large it is and the flag that takes it (it was ground through
/// before, a fraction of a percent of its tiles a minute). A texture image of more pixels
/// than `--max-samples` the same; within the limit both build.
#[test]
fn a_png_that_inflates_to_more_samples_than_the_limit_is_refused_before_it_is_read() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let side = 100_000;
    let bomb = tmp.path().join("bomb.png");
    std::fs::write(&bomb, png_of_zeros(side)).expect("write the PNG");
    let file_bytes = std::fs::metadata(&bomb).expect("metadata").len();
    assert!(
        file_bytes * 4096 > u64::from(side) * u64::from(side),
        "a file its decoded size can come from ({file_bytes} bytes): not the ratio guard"
    );
    let run = |args: &[&std::ffi::OsStr]| {
        let mut command =
            std::process::Command::new(terrain_tests::data::workspace_binary("terrain-server"));
        command.arg("build").args(args);
        terrain_tests::child::run_watched(command, 1 << 30, std::time::Duration::from_secs(60))
    };
    let out = tmp.path().join("db");
    let refused = run(&[bomb.as_os_str(), "--out".as_ref(), out.as_os_str()]);
    let stderr = refused.stderr();
    assert_eq!(refused.killed, None, "{stderr}");
    assert_eq!(refused.output.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains(&format!(
            "heights of 100000 x 100000 = 10000000000 samples, more than the 4294967296 a build \
             takes (--max-samples), from a file of {file_bytes} bytes. Pass --max-samples \
             10000000000 to build it anyway"
        )),
        "{stderr}"
    );
    assert!(!out.exists());

    // A texture the same, and the limit a user sets is the one kept (jacksboro's heights
    // are 403 x 344 = 138,632 samples).
    let texture = tmp.path().join("texture.png");
    image::RgbImage::new(400, 400)
        .save(&texture)
        .expect("write the texture");
    let jacksboro = jacksboro();
    let refused = run(&[
        jacksboro.as_os_str(),
        "--texture".as_ref(),
        texture.as_os_str(),
        "--max-samples".as_ref(),
        "150000".as_ref(),
        "--no-web".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    let stderr = refused.stderr();
    assert_eq!(refused.output.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("a texture of 400 x 400 = 160000 samples, more than the 150000"),
        "{stderr}"
    );
    assert!(!out.exists());
    let built = run(&[
        jacksboro.as_os_str(),
        "--texture".as_ref(),
        texture.as_os_str(),
        "--max-samples".as_ref(),
        "160000".as_ref(),
        "--no-web".as_ref(),
        "--quiet".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert!(built.output.status.success(), "{}", built.stderr());
    assert!(out.join("manifest.json").exists());
}
