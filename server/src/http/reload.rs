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
//! A database in an object store ([`crate::store`]) is polled by reading its pointer
//! object every `--reload-poll` seconds (a GET of a few bytes); the version it served
//! before stays answered to requests that name it.
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
    // A directory's manifest file, watched by its identity; a store's pointer is read at
    // every poll instead (the reload compares the version it names with the one served).
    let manifest: Option<PathBuf> = match state.db().origin() {
        crate::db::Origin::Dir(dir) => Some(dir.join("manifest.json")),
        crate::db::Origin::Store { .. } => None,
    };
    let mut seen = manifest.as_deref().and_then(identity);
    // Whether the last poll of a store's pointer failed: an outage is logged once.
    let mut store_failing = false;
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
                let Some(manifest) = &manifest else {
                    // A store: the pointer is read by the reload itself.
                    poll_store(&state, &mut store_failing).await;
                    continue;
                };
                let now = identity(manifest);
                // Missing for the moment (a build renaming its directory into place), or
                // the file already served: nothing to do.
                if now.is_none() || now == seen {
                    continue;
                }
                "the database's manifest changed"
            }
        };
        // Seen whatever the outcome: a damaged rebuild is tried once, not every poll.
        seen = manifest.as_deref().and_then(identity);
        match state.reload().await {
            Ok(Reloaded::Replaced { from, to }) => {
                tracing::info!(why, from = %from, to = %to, "serving the rebuilt database");
            }
            Ok(Reloaded::Unchanged) => {
                tracing::info!(why, "the database is the one served; nothing reloaded");
            }
            Err(error) => tracing::warn!(
                why,
                error = %format!("{:#}", anyhow::Error::new(error)),
                "cannot open the database again; still serving the one before"
            ),
        }
    }
}

/// One poll of a store's pointer: a new version is opened and served; a store that does
/// not answer is logged once per outage, not once per poll.
async fn poll_store(state: &AppState, failing: &mut bool) {
    match state.reload().await {
        Ok(Reloaded::Replaced { from, to }) => {
            tracing::info!(from = %from, to = %to, "the store's pointer names a new version: serving it");
            *failing = false;
        }
        Ok(Reloaded::Unchanged) => {
            if std::mem::replace(failing, false) {
                tracing::info!("the object store answers again");
            }
        }
        Err(error) => {
            if !std::mem::replace(failing, true) {
                tracing::warn!(
                    error = %format!("{:#}", anyhow::Error::new(error)),
                    "cannot read the store's pointer; still serving the version before"
                );
            }
        }
    }
}

async fn sleep_or_forever(poll: Option<Duration>) {
    match poll {
        Some(every) => tokio::time::sleep(every).await,
        None => std::future::pending().await,
    }
}
