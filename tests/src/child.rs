//! A child process watched for memory: the high-water mark of its resident set (`VmHWM` in
//! `/proc/<pid>/status`, Linux) read while it runs, and the child killed as soon as it
//! passes a bound or a deadline, so that a test of a memory bound fails in seconds instead
//! of exhausting the machine.

use std::io::Read;
use std::process::{Command, ExitStatus, Output, Stdio};
use std::time::{Duration, Instant};

/// How often the resident set is read: a body growing at a gigabyte a second passes a bound
/// of tens of megabytes by little more than this allows.
const POLL: Duration = Duration::from_millis(5);

/// What a watched child did.
#[derive(Debug)]
pub struct Watched {
    /// Its exit status and everything it printed.
    pub output: Output,
    /// The highest resident set read, in bytes.
    pub peak_bytes: u64,
    /// Why it was killed, if it was: past the bound or the deadline.
    pub killed: Option<String>,
}

impl Watched {
    pub fn stdout(&self) -> String {
        String::from_utf8_lossy(&self.output.stdout).into_owned()
    }

    pub fn stderr(&self) -> String {
        String::from_utf8_lossy(&self.output.stderr).into_owned()
    }
}

/// Runs `command` to its end, with its stdout and stderr captured, killing it once its
/// resident set passes `kill_above` bytes or it runs past `deadline`.
///
/// # Panics
/// When the command cannot start, or memory cannot be read (not Linux): a test of a memory
/// bound that cannot read memory must not pass. A child that ends before the first read
/// (`peak_bytes` 0) is not a failure: its status no longer holds memory lines.
pub fn run_watched(mut command: Command, kill_above: u64, deadline: Duration) -> Watched {
    let mut child = command
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the command starts");
    let drain = |mut pipe: Box<dyn Read + Send>| {
        std::thread::spawn(move || {
            let mut bytes = Vec::new();
            let _ = pipe.read_to_end(&mut bytes);
            bytes
        })
    };
    let stdout = drain(Box::new(child.stdout.take().expect("piped stdout")));
    let stderr = drain(Box::new(child.stderr.take().expect("piped stderr")));
    let status_path = format!("/proc/{}/status", child.id());
    let started = Instant::now();
    let (mut peak_bytes, mut killed) = (0, None);
    let status: ExitStatus = loop {
        if let Some(kib) = high_water_mark_kib(&status_path) {
            peak_bytes = peak_bytes.max(kib * 1024);
        }
        if let Some(status) = child.try_wait().expect("wait for the child") {
            break status;
        }
        if killed.is_none() {
            if peak_bytes > kill_above {
                killed = Some(format!(
                    "its resident set passed {kill_above} bytes ({peak_bytes})"
                ));
            } else if started.elapsed() > deadline {
                killed = Some(format!("it ran past {deadline:?}"));
            }
            if killed.is_some() {
                let _ = child.kill();
            }
        }
        std::thread::sleep(POLL);
    };
    // This platform reads memory at all: a test of a memory bound must not pass where it
    // cannot (not Linux).
    assert!(
        high_water_mark_kib("/proc/self/status").is_some(),
        "no VmHWM in /proc/self/status: memory cannot be read here"
    );
    // A child never seen with memory (`peak_bytes` 0) ended before its status could show
    // it: before the first read, or between releasing its memory and becoming a zombie,
    // when its status has no memory lines although it has not been reaped yet. The line
    // above shows that this platform reads memory; `a_child_that_runs_has_its_memory_read`
    // that a child living past a read is seen.
    Watched {
        output: Output {
            status,
            stdout: stdout.join().expect("stdout reader"),
            stderr: stderr.join().expect("stderr reader"),
        },
        peak_bytes,
        killed,
    }
}

/// `VmHWM` of a `/proc/<pid>/status`, in KiB; `None` once the process has exited.
fn high_water_mark_kib(status: &str) -> Option<u64> {
    let text = std::fs::read_to_string(status).ok()?;
    let line = text.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_child_that_ends_before_its_memory_is_read_is_no_failure() {
        // `true` often ends before the first read, its status a zombie's: no VmHWM.
        for _ in 0..200 {
            let watched = run_watched(Command::new("true"), 1 << 30, Duration::from_secs(10));
            assert!(watched.output.status.success());
            assert_eq!(watched.killed, None);
        }
    }

    #[test]
    fn a_child_that_runs_has_its_memory_read() {
        let mut sleep = Command::new("sleep");
        sleep.arg("0.2");
        let watched = run_watched(sleep, 1 << 30, Duration::from_secs(10));
        assert!(watched.peak_bytes > 0, "{watched:?}");
    }
}
