//! The suite's two tiers. The default tier (`bash scripts/test.sh`) runs every test but the
//! longest flights, which only the full tier runs (`TERRAIN_TEST_TIER=full`, set by
//! `.ci/run`). A full-tier test in the default tier says so on stderr, with the way to run
//! it, and returns: never skipped without a word.

use std::io::Write;

/// Set to `full` to run the full tier.
pub const TIER_VAR: &str = "TERRAIN_TEST_TIER";

/// Whether the full tier runs (`TERRAIN_TEST_TIER=full`).
pub fn is_full() -> bool {
    std::env::var(TIER_VAR).is_ok_and(|v| v == "full")
}

/// `true` in the full tier; otherwise says that `test` did not run and why, and `false`.
pub fn full(test: &str) -> bool {
    if is_full() {
        return true;
    }
    // Written to the stream itself: the harness captures `eprintln!` of passing tests.
    let _ = writeln!(
        std::io::stderr(),
        "NOT RUN: {test} is in the full tier: set {TIER_VAR}=full (as .ci/run does) to run it"
    );
    false
}
