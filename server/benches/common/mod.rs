//! What the server's bench binaries share: the machine's name, the data kit's place and the
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

/// The CPU's model name from /proc/cpuinfo.
pub fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|text| {
            text.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into())
}

/// The machine in one line: CPU model, cores, memory.
pub fn machine() -> String {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let memory_gib = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| {
            let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
            let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
            Some(kib / (1024.0 * 1024.0))
        });
    match memory_gib {
        Some(gib) => format!("{} ({cores} cores, {gib:.0} GiB)", cpu_model()),
        None => format!("{} ({cores} cores)", cpu_model()),
    }
}
