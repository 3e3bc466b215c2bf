//! Serving a rebuilt database without a restart.
//!
//! `terrain-server build --force` replaces a database directory by renaming a complete new
//! one into its place ([`crate::db`]), so the directory's `manifest.json` becomes another
//! file. The server notices that two ways, and either way opens the directory again with
//! [`AppState::reload`]:
//!
//! - **SIGHUP**, the usual "read your files again" signal: reloads at once;
//! - **a poll** of the manifest's identity (device, inode, size, modification time) every
//!   `--reload-poll` seconds: a `stat`, nothing read.
//!
//! A request takes the database once ([`AppState::db`]), so requests already running end
//! with the old one; when the last of them ends the old packs are closed and unmapped, and
//! the disk space of the deleted files is freed. A reload that fails (a directory missing
//! for the moment, a build's lock, a damaged pack) keeps the database served and logs why.

use super::{AppState, Reloaded};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, SystemTime};

/// What identifies the file at a path: a renamed-in replacement differs in inode at least.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Identity {
    device: u64,
    inode: u64,
    bytes: u64,
    modified: Option<SystemTime>,
}

fn identity(path: &Path) -> Option<Identity> {
    let meta = std::fs::metadata(path).ok()?;
    #[cfg(unix)]
    let (device, inode) = {
        use std::os::unix::fs::MetadataExt as _;
        (meta.dev(), meta.ino())
    };
    #[cfg(not(unix))]
    let (device, inode) = (0, 0);
    Some(Identity {
        device,
        inode,
        bytes: meta.len(),
        modified: meta.modified().ok(),
    })
}

/// Reloads `state`'s database on SIGHUP and, with `poll`, whenever its manifest file
/// changes. Runs until the runtime ends.
pub async fn watch(state: Arc<AppState>, poll: Option<Duration>) {
    let manifest: PathBuf = state.db().dir().join("manifest.json");
    let mut seen = identity(&manifest);
    #[cfg(unix)]
    let mut hangup = match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup()) {
        Ok(signal) => Some(signal),
        Err(error) => {
            tracing::error!(%error, "cannot listen for SIGHUP: reloads only by the poll");
            None
        }
    };
    loop {
        let hangup_received = async {
            #[cfg(unix)]
            if let Some(signal) = &mut hangup {
                signal.recv().await;
                return;
            }
            std::future::pending::<()>().await;
        };
        let why = tokio::select! {
            () = hangup_received => "SIGHUP received",
            () = sleep_or_forever(poll) => {
                let now = identity(&manifest);
                // Missing for the moment (a build renaming its directory into place), or
                // the file already served: nothing to do.
                if now.is_none() || now == seen {
                    continue;
                }
                "the database's manifest changed"
            }
        };
        // Seen whatever the outcome: a damaged rebuild is tried once, not every poll.
        seen = identity(&manifest);
        let reloading = Arc::clone(&state);
        match tokio::task::spawn_blocking(move || reloading.reload()).await {
            Ok(Ok(Reloaded::Replaced { from, to })) => {
                tracing::info!(why, from = %from, to = %to, "serving the rebuilt database");
            }
            Ok(Ok(Reloaded::Unchanged)) => {
                tracing::info!(why, "the database is the one served; nothing reloaded");
            }
            Ok(Err(error)) => tracing::warn!(
                why,
                error = %format!("{:#}", anyhow::Error::new(error)),
                "cannot open the database again; still serving the one before"
            ),
            Err(error) => tracing::error!(%error, "the reload task failed"),
        }
    }
}

async fn sleep_or_forever(poll: Option<Duration>) {
    match poll {
        Some(every) => tokio::time::sleep(every).await,
        None => std::future::pending().await,
    }
}
