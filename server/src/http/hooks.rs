//! Test hooks, compiled only with the `test-hooks` cargo feature (which only the
//! end-to-end tests turn on, as a dev-dependency, so no release build carries them).
//!
//! The tile handlers answer in a single poll, so no real request can be held inside the
//! handler stack: a slow reader holds its *connection*, not a concurrency permit. To test
//! load shedding and the request timeout, this route waits as long as it is asked to,
//! inside the same layers as the tile API.

use axum::extract::Path;
use std::time::Duration;

/// `GET /__test/sleep/{ms}`: answers `slept` after `ms` milliseconds.
pub const SLEEP: &str = "/__test/sleep/{ms}";

pub(super) async fn sleep(Path(ms): Path<u64>) -> &'static str {
    tokio::time::sleep(Duration::from_millis(ms)).await;
    "slept\n"
}
