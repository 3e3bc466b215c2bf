//! Memory accounting: the budget the pager works within, and the bytes each resident tile
//! really holds.
//!
//! The limit is a percentage of a budget (the strip-mask paper, section 4: "we usually set
//! this parameter to 90% in order to keep a margin for further downloadings", since the
//! pager may overspend by the belt being fetched). The budget is given (`--memory 64MiB`)
//! or, when not, the machine's available memory.

use std::str::FromStr;
use thiserror::Error;

/// Share of the budget the pager may fill, as in the paper.
pub const DEFAULT_LIMIT_PERCENT: f64 = 90.0;

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
