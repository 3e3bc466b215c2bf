//! What the server's bench binaries share: the machine's name and a run's stamp, the data
//! kit's place and the
//! mosaic that makes a larger input from a smaller one. A bench includes it with
//! `mod common;`.

#![allow(dead_code)] // each bench uses part of it

pub mod mosaic;

use std::path::PathBuf;

/// The variable naming the data kit's `data/` directory.
pub const DATA_DIR_VAR: &str = "TERRAIN_DATA_DIR";

/// The data kit: `$TERRAIN_DATA_DIR`, else `../shared/data` beside the repository, if it
/// exists.
pub fn data_dir() -> Option<PathBuf> {
    let dir = match std::env::var_os(DATA_DIR_VAR) {
        Some(dir) => PathBuf::from(dir),
        None => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"),
    };
    dir.is_dir().then_some(dir)
}

/// The stamp of a generated figure (commit, machine, date): the one the tests' benches
/// use, `tests/src/stamp.rs`, included here rather than written twice.
#[path = "../../../tests/src/stamp.rs"]
pub mod stamp;

/// The machine in one line: CPU model, cores, memory.
pub fn machine() -> String {
    stamp::machine()
}
