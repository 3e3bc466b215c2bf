//! Databases built once per test process and shared by the tests that only read them: the
//! same input with the same options is built once, however many tests ask for it (a test
//! that asks while the build runs waits for it). A test that changes a database (corrupts a
//! file, reloads one) builds its own.
//!
//! They live under the system's temporary directory in `terrain-test-fixtures-<pid>`;
//! those of processes that have exited are removed when the next process starts.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};
use terrain_server::build::{BuildOptions, build};

/// What a shared database is built with: the builder's defaults, or with the quadtree
/// patches too (tolerance 0, as `--patches` builds them).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Options {
    Defaults,
    WithPatches,
}

type Slot = Arc<OnceLock<PathBuf>>;

fn slots() -> &'static Mutex<HashMap<(PathBuf, Options), Slot>> {
    static SLOTS: OnceLock<Mutex<HashMap<(PathBuf, Options), Slot>>> = OnceLock::new();
    SLOTS.get_or_init(Default::default)
}

const PREFIX: &str = "terrain-test-fixtures-";

/// Databases built so far in this process: each one's folder has its own number.
static BUILT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// This process's directory of shared databases, made on first use after removing those of
/// processes that no longer run.
fn root() -> &'static Path {
    static ROOT: OnceLock<PathBuf> = OnceLock::new();
    ROOT.get_or_init(|| {
        let tmp = std::env::temp_dir();
        if let Ok(entries) = std::fs::read_dir(&tmp) {
            for entry in entries.flatten() {
                let name = entry.file_name();
                let Some(pid) = name.to_str().and_then(|n| n.strip_prefix(PREFIX)) else {
                    continue;
                };
                if pid.parse::<u32>().is_ok() && !Path::new("/proc").join(pid).exists() {
                    let _ = std::fs::remove_dir_all(entry.path());
                }
            }
        }
        let dir = tmp.join(format!("{PREFIX}{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("the fixtures' directory");
        dir
    })
}

/// The database of `input` built with `options`, built on the first call of the process
/// and shared by every later one. Panics when it does not build (the fixtures must).
pub fn database(input: &Path, options: Options) -> PathBuf {
    let slot = Arc::clone(
        slots()
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .entry((input.to_path_buf(), options))
            .or_default(),
    );
    slot.get_or_init(|| {
        let name = format!(
            "{}-{}-{}",
            input.file_stem().unwrap_or_default().to_string_lossy(),
            match options {
                Options::Defaults => "defaults",
                Options::WithPatches => "patches",
            },
            // Two inputs of the same name in different folders stay apart.
            BUILT.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
        );
        let mut build_options = BuildOptions::new(input, root().join(name).join("db"));
        if options == Options::WithPatches {
            build_options.patches = Some(0.0);
        }
        build(
            &build_options,
            &|_, _| {},
            &std::sync::atomic::AtomicBool::new(false),
        )
        .unwrap_or_else(|e| panic!("the fixture {} must build: {e}", input.display()))
        .out
    })
    .clone()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_database_is_built_once_and_shared() {
        let input = crate::data::jacksboro();
        let first = database(&input, Options::Defaults);
        let modified = std::fs::metadata(first.join("manifest.json"))
            .and_then(|m| m.modified())
            .expect("a manifest");
        let threads: Vec<_> = (0..3)
            .map(|_| {
                let input = input.clone();
                std::thread::spawn(move || database(&input, Options::Defaults))
            })
            .collect();
        for t in threads {
            assert_eq!(t.join().expect("no panic"), first);
        }
        assert_eq!(
            std::fs::metadata(first.join("manifest.json"))
                .and_then(|m| m.modified())
                .expect("a manifest"),
            modified,
            "not built again"
        );
        let patches = database(&input, Options::WithPatches);
        assert_ne!(patches, first);
        assert!(patches.join("manifest.json").is_file());
        assert!(first.starts_with(root()));
    }
}
