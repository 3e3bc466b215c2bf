//! A rebuilt database served by a running server: on SIGHUP, or found by the poll of its
//! manifest, without a restart; the old packs closed (their disk space freed) once served.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use terrain_server::build::{BuildOptions, build};
use terrain_shared::routes;
use terrain_tests::data::{jacksboro, workspace_binary};

/// Builds jacksboro into `out`, replacing what is there, its heights raised by `raise_m`:
/// two raises, two sets of tiles, two content versions.
fn rebuild(out: &Path, raise_m: f64) -> String {
    let options = BuildOptions {
        force: true,
        height_offset: Some(raise_m),
        ..BuildOptions::new(jacksboro(), out)
    };
    build(
        &options,
        &|_, _| {},
        &std::sync::atomic::AtomicBool::new(false),
    )
    .expect("builds")
    .manifest
    .content_version
}

/// A server child killed when dropped, so a failed assertion leaves no server running.
struct Serving(Child);

impl Drop for Serving {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl std::ops::Deref for Serving {
    type Target = Child;
    fn deref(&self) -> &Child {
        &self.0
    }
}

impl std::ops::DerefMut for Serving {
    fn deref_mut(&mut self) -> &mut Child {
        &mut self.0
    }
}

/// `terrain-server serve DB` with `extra` arguments, its log in `log`; the child and its
/// base URL.
fn serve(db: &Path, extra: &[&str], log: &Path) -> (Serving, String) {
    let mut child = Command::new(workspace_binary("terrain-server"))
        .arg("serve")
        .arg(db)
        .args(["--addr", "127.0.0.1:0"])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(log).expect("log file"))
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
        .to_string();
    (Serving(child), base)
}

fn get(base: &str, path: &str) -> (u16, String) {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    runtime.block_on(async {
        let response = reqwest::get(format!("{base}{path}"))
            .await
            .unwrap_or_else(|e| panic!("{path}: {e}"));
        let status = response.status().as_u16();
        (status, response.text().await.expect("body"))
    })
}

fn served_version(base: &str) -> String {
    let (status, body) = get(base, routes::MANIFEST);
    assert_eq!(status, 200, "{body}");
    let manifest: serde_json::Value = serde_json::from_str(&body).expect("manifest JSON");
    manifest["content_version"]
        .as_str()
        .expect("content_version")
        .to_string()
}

/// Polls `check` every 20 ms until it gives `None` (done), failing with the last thing it
/// gave after 30 s: a bound on a broken reload, not a pace.
fn eventually(mut check: impl FnMut() -> Option<String>) {
    let started = Instant::now();
    while let Some(waiting) = check() {
        assert!(started.elapsed() < Duration::from_secs(30), "{waiting}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Waits until the server serves `version`.
fn until_served(base: &str, version: &str, log: &Path) {
    eventually(|| {
        (served_version(base) != version).then(|| {
            format!(
                "{version} never served: {}",
                std::fs::read_to_string(log).unwrap_or_default()
            )
        })
    });
}

/// Files and mappings of `pid` under `dir` that are deleted: what keeps their disk space.
fn deleted_under(pid: u32, dir: &Path) -> Vec<String> {
    let dir = dir.to_string_lossy();
    let mut held = Vec::new();
    for entry in std::fs::read_dir(format!("/proc/{pid}/fd")).expect("fd list") {
        if let Ok(target) = std::fs::read_link(entry.expect("fd").path()) {
            let target = target.to_string_lossy().into_owned();
            if target.contains(&*dir) && target.ends_with("(deleted)") {
                held.push(target);
            }
        }
    }
    let maps = std::fs::read_to_string(format!("/proc/{pid}/maps")).expect("maps");
    held.extend(
        maps.lines()
            .filter(|l| l.contains(&*dir) && l.ends_with("(deleted)"))
            .map(str::to_string),
    );
    held
}

fn signal(child: &Child, name: &str) {
    let sent = Command::new("kill")
        .args([name, &child.id().to_string()])
        .status()
        .expect("kill runs");
    assert!(sent.success());
}

#[test]
fn a_rebuilt_database_is_served_after_sighup_and_its_old_packs_are_closed() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = tmp.path().join("db");
    let first = rebuild(&db, 0.0);
    let log = tmp.path().join("serve.log");
    // No poll: only the signal reloads.
    let (mut child, base) = serve(&db, &["--reload-poll", "0"], &log);
    assert_eq!(served_version(&base), first);
    let second = rebuild(&db, 10.0);
    assert_ne!(first, second, "two builds, two versions");
    assert_eq!(served_version(&base), first, "no reload without SIGHUP");
    let held = deleted_under(child.id(), tmp.path());
    assert!(
        !held.is_empty(),
        "the replaced database's packs are still open before the reload"
    );

    signal(&child, "-HUP");
    until_served(&base, &second, &log);
    assert!(
        child.try_wait().expect("wait").is_none(),
        "SIGHUP reloads, it does not end the server"
    );
    let tile = terrain_shared::TileId::new(0, 0);
    let (status, _) = get(&base, &routes::heights(&second, tile));
    assert_eq!(status, 200, "a tile of the new version");
    let (status, body) = get(&base, &routes::heights(&first, tile));
    assert_eq!(status, 404, "the old version is gone: {body}");
    // The last request with the old database has ended: its files are closed and unmapped
    // (by the reload's own thread, which may still be at it when the new version is seen).
    eventually(|| {
        let held = deleted_under(child.id(), tmp.path());
        (!held.is_empty()).then(|| format!("the replaced packs are never closed: {held:?}"))
    });
    let (_, metrics) = get(&base, routes::METRICS);
    assert!(metrics.contains("database_reloads_total 1"), "{metrics}");

    // A reload that cannot open the directory keeps the database served, and says why.
    let aside = tmp.path().join("aside");
    std::fs::rename(&db, &aside).expect("move the database away");
    signal(&child, "-HUP");
    eventually(|| {
        let text = std::fs::read_to_string(&log).unwrap_or_default();
        (!text.contains("still serving the one before")).then(|| format!("no warning: {text}"))
    });
    assert_eq!(served_version(&base), second);
    let (status, _) = get(&base, &routes::heights(&second, tile));
    assert_eq!(status, 200, "still served from the open files");
    std::fs::rename(&aside, &db).expect("move it back");

    signal(&child, "-TERM");
    assert!(child.wait().expect("exit").success());
}

#[test]
fn a_rebuilt_database_is_found_by_the_poll_without_a_signal() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = tmp.path().join("db");
    let first = rebuild(&db, 0.0);
    let log = tmp.path().join("serve.log");
    let (mut child, base) = serve(&db, &["--reload-poll", "0.05"], &log);
    assert_eq!(served_version(&base), first);
    let second = rebuild(&db, 10.0);
    until_served(&base, &second, &log);
    // The reload logs once it has returned, just after the new version can be seen.
    eventually(|| {
        let text = std::fs::read_to_string(&log).unwrap_or_default();
        (!text.contains("serving the rebuilt database"))
            .then(|| format!("the reload is never logged: {text}"))
    });
    let text = std::fs::read_to_string(&log).unwrap_or_default();
    assert!(text.contains("manifest changed"), "{text}");
    signal(&child, "-TERM");
    assert!(child.wait().expect("exit").success());
}
