//! Every input the fuzz targets kept (`fuzz/corpus/`) and every input that once broke one
//! (`fuzz/regressions/`), replayed through the same functions on stable: none may panic.
//! The fuzzing itself needs nightly and runs in `scripts/fuzz.sh`; this keeps what it found.

use std::path::Path;

#[path = "../../fuzz/src/lib.rs"]
mod targets;

/// A fuzz target's body: any bytes in, a panic on a bug.
type Target = fn(&[u8]);

/// The targets, by the name of their folders under `corpus/` and `regressions/`.
const TARGETS: [(&str, Target); 5] = [
    ("heights_decode", targets::heights_decode),
    ("manifest_parse", targets::manifest_parse),
    ("read_png", targets::read_png),
    ("read_geotiff", targets::read_geotiff),
    ("read_hgt", targets::read_hgt),
];

/// Runs every file of `fuzz/<kind>/<target>/` through the target; returns how many ran.
fn replay(kind: &str, target: &str, run: Target) -> usize {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../fuzz")
        .join(kind)
        .join(target);
    let Ok(entries) = std::fs::read_dir(&dir) else {
        return 0;
    };
    let mut ran = 0;
    for entry in entries {
        let path = entry.expect("readable folder").path();
        let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let outcome = std::panic::catch_unwind(|| run(&bytes));
        assert!(outcome.is_ok(), "{target} panics on {}", path.display());
        ran += 1;
    }
    ran
}

#[test]
fn every_kept_fuzz_input_is_read_without_a_panic() {
    for (target, run) in TARGETS {
        let ran = replay("corpus", target, run);
        // A corpus that went missing must not pass in silence.
        assert!(ran > 0, "fuzz/corpus/{target}/ holds no inputs");
        replay("regressions", target, run);
    }
}
