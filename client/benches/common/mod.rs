//! What the client's bench binaries share: timing statistics, a reproducible random source
//! and the machine's name. Each bench includes it with `mod common;`.

#![allow(dead_code)] // each bench uses part of it

/// Mean, median, p99 and max of nanosecond samples, in microseconds.
pub struct Stats {
    pub mean: f64,
    pub median: f64,
    pub p99: f64,
    pub max: f64,
}

impl Stats {
    pub fn of(samples_ns: &mut [u64]) -> Stats {
        samples_ns.sort_unstable();
        let us = |ns: u64| ns as f64 / 1000.0;
        let at = |q: f64| us(samples_ns[((samples_ns.len() - 1) as f64 * q).round() as usize]);
        Stats {
            mean: samples_ns.iter().sum::<u64>() as f64 / samples_ns.len() as f64 / 1000.0,
            median: at(0.5),
            p99: at(0.99),
            max: at(1.0),
        }
    }

    /// One Markdown table row.
    pub fn row(&self, name: &str) -> String {
        format!(
            "| {name} | {:.2} | {:.2} | {:.2} | {:.2} |",
            self.mean, self.median, self.p99, self.max
        )
    }
}

/// splitmix64: every run draws the same numbers, without a dependency.
pub struct Random(pub u64);

impl Random {
    pub fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `0..n`.
    pub fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }

    /// Uniform in `[0, 1)`.
    pub fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
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
