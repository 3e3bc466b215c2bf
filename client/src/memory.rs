//! Memory accounting: the budget the pager works within, and the bytes each resident tile
//! really holds.
//!
//! The limit is a percentage of a budget (the strip-mask paper, section 4: "we usually set
//! this parameter to 90% in order to keep a margin for further downloadings", since its
//! pager could overspend by the belt being fetched; this one never does, and keeps the 90%
//! as room for the program beside the terrain). The budget is given (`--memory 64MiB`) or,
//! when not, the machine's available memory. [`MEMORY_INVARIANT`] says what the limit
//! covers and that it holds.

use std::str::FromStr;
use thiserror::Error;

/// Share of the budget the pager may fill, as in the paper.
pub const DEFAULT_LIMIT_PERCENT: f64 = 90.0;

/// The memory invariant, stated word for word in README.md, ARCHITECTURE.md,
/// docs/flight.md, docs/reliability.md and `crate::scene` (the client's test
/// `the_memory_invariant_is_stated_word_for_word_everywhere` holds them to it). The scene
/// keeps it: the method's reservation ([`crate::method::LodMethod::reserved_bytes`]) comes
/// off the limit first, the pager admits a belt (the current tile's too) only if its bytes,
/// known from the manifest, fit, finer textures are paid from what is left, and what a
/// frame's draw made past the reservation comes off at its end
/// (`crate::scene::Scene::draw`); [`MemoryBudget::check`] refuses a limit below
/// [`LeastLimit`].
pub const MEMORY_INVARIANT: &str = "At the end of every frame, the bytes the client holds for the terrain (every resident tile's heights, textures and GPU copies, and all the drawing method holds, CPU and GPU) are at most the memory limit, `--limit-percent` (90 by default) of `--memory`. There is no exception: a limit too small for what the method reserves plus the coarsest level of the pyramid held whole (with one level, its largest tile) is refused at start with the least `--memory` that would do. The limit does not cover the program, its render targets and pipelines, or the graphics driver's own memory; a flight reports them beside it (heap, GPU allocations, resident set).";

/// Why a budget could not be worked out.
#[derive(Debug, Error, PartialEq)]
pub enum MemoryError {
    #[error(
        "cannot read a memory size from {0:?}: use a number with a unit, e.g. 64MiB, 1.5GiB or 500MB"
    )]
    BadSize(String),
    #[error("the limit percentage {0} is not in (0, 100]")]
    BadPercent(f64),
    #[error(
        "cannot read the available memory from /proc/meminfo ({0}); give a budget with --memory"
    )]
    Unavailable(String),
    #[error("{0}")]
    TooSmall(LimitTooSmall),
}

/// The least memory limit a scene needs to draw anything and keep its limit
/// (`crate::scene::Scene::least_limit`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LeastLimit {
    /// What the drawing method reserves for no tile in particular (its index sets, grid,
    /// error buffer, atlas slack: `crate::method::LodMethod::reserved_bytes`).
    pub method_bytes: u64,
    /// The coarsest level of the pyramid, held whole (or, paging one level, its largest
    /// tile: the current tile must fit).
    pub tiles_bytes: u64,
    /// Whether `tiles_bytes` is a whole level (a pyramid), not one tile.
    pub whole_level: bool,
}

impl LeastLimit {
    pub fn total(&self) -> u64 {
        self.method_bytes + self.tiles_bytes
    }
}

/// A limit below [`LeastLimit`], as [`MemoryBudget::check`] refuses it.
#[derive(Debug, Clone, PartialEq)]
pub struct LimitTooSmall {
    pub budget: MemoryBudget,
    pub least: LeastLimit,
    /// What needs it, e.g. `--method pgm at 480x270`.
    pub what: String,
}

impl LimitTooSmall {
    /// The least budget (`--memory`) whose limit holds [`LeastLimit`], rounded up to a
    /// hundredth of a MiB.
    pub fn least_budget_bytes(&self) -> u64 {
        let bytes = (self.least.total() as f64 * 100.0 / self.budget.limit_percent).ceil();
        let hundredth = MIB / 100.0;
        ((bytes / hundredth).ceil() * hundredth).ceil() as u64
    }
}

impl std::fmt::Display for LimitTooSmall {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let mib = |b: u64| b as f64 / MIB;
        write!(
            f,
            "the memory limit of {:.2} MiB ({} bytes, {}% of {:.2} MiB) cannot hold what {} needs: \
             {:.2} MiB ({} bytes) {}, and {:.2} MiB ({} bytes) for the method's own buffers; \
             give --memory {:.2}MiB or more",
            mib(self.budget.limit_bytes()),
            self.budget.limit_bytes(),
            self.budget.limit_percent,
            mib(self.budget.budget_bytes),
            self.what,
            mib(self.least.tiles_bytes),
            self.least.tiles_bytes,
            if self.least.whole_level {
                "for the coarsest level of the pyramid, which it holds whole"
            } else {
                "for the largest tile, which must fit when it is current"
            },
            mib(self.least.method_bytes),
            self.least.method_bytes,
            self.least_budget_bytes() as f64 / MIB,
        )
    }
}

/// Bytes in a mebibyte, for printing sizes in MiB.
pub const MIB: f64 = 1048576.0;

/// A memory size parsed from text such as `64MiB`, `1.5 GiB`, `500MB` or `1048576`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MemorySize(pub u64);

impl FromStr for MemorySize {
    type Err = MemoryError;
    fn from_str(text: &str) -> Result<MemorySize, MemoryError> {
        let size: bytesize::ByteSize = text
            .trim()
            .parse()
            .map_err(|_| MemoryError::BadSize(text.into()))?;
        if size.as_u64() == 0 {
            return Err(MemoryError::BadSize(text.into()));
        }
        Ok(MemorySize(size.as_u64()))
    }
}

/// The budget and the limit derived from it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MemoryBudget {
    pub budget_bytes: u64,
    pub limit_percent: f64,
    /// Where the budget came from, for reports.
    pub source: BudgetSource,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BudgetSource {
    Given,
    Available,
}

impl MemoryBudget {
    /// `percent` of `budget`, or of the available memory when `budget` is `None`.
    pub fn new(budget: Option<MemorySize>, percent: f64) -> Result<MemoryBudget, MemoryError> {
        if !(percent > 0.0 && percent <= 100.0) {
            return Err(MemoryError::BadPercent(percent));
        }
        let (budget_bytes, source) = match budget {
            Some(MemorySize(bytes)) => (bytes, BudgetSource::Given),
            None => (available_memory()?, BudgetSource::Available),
        };
        Ok(MemoryBudget {
            budget_bytes,
            limit_percent: percent,
            source,
        })
    }

    /// Bytes the pager may fill.
    pub fn limit_bytes(&self) -> u64 {
        (self.budget_bytes as f64 * self.limit_percent / 100.0) as u64
    }

    /// Refuses a limit below `least`, naming the budget that would do; `what` says what
    /// needs it (e.g. `--method pgm at 480x270`).
    pub fn check(&self, least: LeastLimit, what: &str) -> Result<(), MemoryError> {
        if self.limit_bytes() >= least.total() {
            return Ok(());
        }
        Err(MemoryError::TooSmall(LimitTooSmall {
            budget: *self,
            least,
            what: what.to_string(),
        }))
    }
}

/// `MemAvailable` of /proc/meminfo: what can be allocated without swapping.
pub fn available_memory() -> Result<u64, MemoryError> {
    let text = std::fs::read_to_string("/proc/meminfo")
        .map_err(|e| MemoryError::Unavailable(e.to_string()))?;
    parse_meminfo_available(&text)
        .ok_or_else(|| MemoryError::Unavailable("no MemAvailable line".into()))
}

fn parse_meminfo_available(text: &str) -> Option<u64> {
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Bytes one resident tile holds, by kind: everything kept per tile, and only what is kept.
/// The compressed heights body is dropped once decoded (the decoded codes are what is
/// used), so it is not here; the encoded texture levels are kept (a renderer decodes them
/// on upload). A renderer adds its vertex data and GPU buffers here when it uploads a tile.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TileBytes {
    pub decoded_heights: u64,
    pub textures: u64,
    /// What the level-of-detail method holds for it, CPU and GPU (its own tables, its own
    /// copy of the terrain, data of its own).
    pub method: u64,
    /// The renderer's GPU bytes for it: sample buffer and texture copies.
    pub gpu: u64,
}

impl TileBytes {
    pub fn total(&self) -> u64 {
        self.decoded_heights + self.textures + self.method + self.gpu
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_read_binary_and_decimal_units() {
        let check = |text: &str, bytes: u64| {
            assert_eq!(text.parse::<MemorySize>(), Ok(MemorySize(bytes)), "{text}")
        };
        check("64MiB", 64 << 20);
        check("32 MiB", 32 << 20);
        check("1GiB", 1 << 30);
        check("500MB", 500_000_000);
        check("4096", 4096);
        assert!("lots".parse::<MemorySize>().is_err());
        assert!("0MiB".parse::<MemorySize>().is_err());
    }

    #[test]
    fn the_limit_is_the_percentage_of_the_budget() {
        let budget =
            MemoryBudget::new(Some(MemorySize(100 << 20)), DEFAULT_LIMIT_PERCENT).expect("valid");
        assert_eq!(budget.limit_bytes(), 94_371_840); // 90% of 100 MiB
        assert_eq!(
            MemoryBudget::new(None, 0.0),
            Err(MemoryError::BadPercent(0.0))
        );
        assert_eq!(
            MemoryBudget::new(None, 120.0),
            Err(MemoryError::BadPercent(120.0))
        );
    }

    #[test]
    fn a_limit_below_the_least_is_refused_with_the_budget_that_would_do() {
        let budget = MemoryBudget::new(Some(MemorySize(1 << 20)), 90.0).expect("valid");
        let least = LeastLimit {
            method_bytes: 600_000,
            tiles_bytes: 400_000,
            whole_level: true,
        };
        let Err(MemoryError::TooSmall(refusal)) = budget.check(least, "--method pgm at 480x270")
        else {
            panic!("943,718 bytes cannot hold 1,000,000");
        };
        // 1,000,000 / 0.9 = 1,111,112 bytes, 1.0597 MiB: 1.06 MiB.
        assert_eq!(refusal.least_budget_bytes(), (1.06 * MIB).ceil() as u64);
        let text = refusal.to_string();
        for part in [
            "943718 bytes",
            "--method pgm at 480x270",
            "400000 bytes) for the coarsest level",
            "600000 bytes) for the method",
            "--memory 1.06MiB",
        ] {
            assert!(text.contains(part), "{part:?} in {text}");
        }
        let enough =
            MemoryBudget::new(Some(MemorySize(refusal.least_budget_bytes())), 90.0).expect("valid");
        assert_eq!(enough.check(least, "it"), Ok(()));
    }

    #[test]
    fn available_memory_comes_from_meminfo() {
        let text = "MemTotal:       24000000 kB\nMemFree:  100 kB\nMemAvailable:   2000 kB\n";
        assert_eq!(parse_meminfo_available(text), Some(2000 * 1024));
        assert_eq!(parse_meminfo_available("MemTotal: 1 kB\n"), None);
        assert!(available_memory().is_ok_and(|b| b > 0));
    }

    #[test]
    fn tile_bytes_add_up_every_kind() {
        let bytes = TileBytes {
            decoded_heights: 2,
            textures: 4,
            method: 8,
            gpu: 16,
        };
        assert_eq!(bytes.total(), 30);
    }
}
