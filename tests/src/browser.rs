//! The browser tests' harness: where the repository, Chromium and the viewer are, whether
//! the browser side is set up (`bash viewer/setup.sh`), and a server with the viewer.

use crate::server::TestServer;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Set to 1 to fail, not skip, a browser test without Chromium, node or the viewer.
pub const REQUIRE_BROWSER_VAR: &str = "REQUIRE_BROWSER";

/// The repository's root.
pub fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

pub fn chromium() -> PathBuf {
    std::env::var_os("CHROMIUM").map_or_else(|| PathBuf::from("/usr/bin/chromium"), PathBuf::from)
}

/// Whether the browser side is there; says NOT RUN (or fails under `REQUIRE_BROWSER=1`)
/// when it is not.
pub fn browser_ready(test: &str) -> bool {
    let node = Command::new("node")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    let missing: Vec<String> = [
        (!node).then(|| "node".to_string()),
        (!chromium().exists()).then(|| format!("{}", chromium().display())),
        (!repo().join("viewer/dist/index.html").exists()).then(|| "viewer/dist".to_string()),
        (!repo().join("viewer/node_modules/puppeteer-core").exists())
            .then(|| "viewer/node_modules".to_string()),
    ]
    .into_iter()
    .flatten()
    .collect();
    if missing.is_empty() {
        return true;
    }
    let required = std::env::var(REQUIRE_BROWSER_VAR).is_ok_and(|v| v == "1");
    assert!(
        !required,
        "{test}: {REQUIRE_BROWSER_VAR}=1 but {} missing (run `bash viewer/setup.sh`)",
        missing.join(", ")
    );
    let _ = writeln!(
        std::io::stderr(),
        "NOT RUN: {test} needs {} (run `bash viewer/setup.sh`)",
        missing.join(", ")
    );
    false
}

/// Serves `db` with the viewer and, beside it, `extra` files (the PMTiles archive): the
/// viewer's files are linked into a directory of the test's own.
pub fn serve(db: &Path, tmp: &Path, extra: &[&Path]) -> TestServer {
    let view = tmp.join("view");
    std::fs::create_dir_all(&view).expect("view dir");
    for entry in std::fs::read_dir(repo().join("viewer/dist")).expect("viewer/dist") {
        let entry = entry.expect("entry");
        std::os::unix::fs::symlink(entry.path(), view.join(entry.file_name())).expect("link");
    }
    for file in extra {
        std::fs::copy(file, view.join(file.file_name().expect("name"))).expect("copy");
    }
    TestServer::start_with_viewer(db, &view)
}
