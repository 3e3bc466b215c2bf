//! What a generated figure is stamped with: the commit, the machine and the date of the
//! run that printed it.

use std::process::Command;

/// The commit the workspace is at (short hash), `-dirty` when it has changes; or
/// `STAMP_COMMIT`, which a script that writes tracked files as it runs reads before its
/// first write (`scripts/stamp.sh`).
pub fn commit() -> String {
    if let Some(commit) = std::env::var("STAMP_COMMIT").ok().filter(|c| !c.is_empty()) {
        return commit;
    }
    let git = |args: &[&str]| {
        Command::new("git")
            .args(args)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
    };
    let hash = git(&["rev-parse", "--short=7", "HEAD"]).unwrap_or_else(|| "unknown".into());
    let dirty =
        git(&["status", "--porcelain", "--untracked-files=no"]).is_some_and(|s| !s.is_empty());
    if dirty { format!("{hash}-dirty") } else { hash }
}

/// Today's date, UTC, `YYYY-MM-DD`.
pub fn date() -> String {
    Command::new("date")
        .args(["-u", "+%Y-%m-%d"])
        .output()
        .ok()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        .unwrap_or_else(|| "unknown date".into())
}

/// The machine in one line: CPU model, cores, memory.
pub fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|text| {
            text.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let memory_gib = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| {
            let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
            let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
            Some(kib / (1024.0 * 1024.0))
        });
    match memory_gib {
        Some(gib) => format!("{cpu} ({cores} cores, {gib:.0} GiB)"),
        None => format!("{cpu} ({cores} cores)"),
    }
}

/// The stamp line of a generated table: `commit C, machine, date`.
pub fn line() -> String {
    format!("commit {}, {}, {}", commit(), machine(), date())
}
