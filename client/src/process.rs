//! What the whole process holds, beside what the memory limit counts: the heap the program
//! allocated (a counting allocator, this crate's global allocator), the GPU memory wgpu's
//! allocator reports, and the resident set the operating system reports.
//!
//! The memory limit ([`crate::memory`]) covers the terrain: every resident tile's bytes,
//! CPU and GPU, and what the drawing method holds. These figures show the rest, so that a
//! user can tell what a limit buys: the program and its runtime, the HTTP client, render
//! targets and pipelines, and (without a GPU) the software rasteriser, whose memory is
//! neither Rust heap nor a wgpu allocation but shows in the resident set.

use peak_alloc::PeakAlloc;

/// Counts every byte the program allocates through Rust's allocator: two relaxed atomic
/// additions per allocation, on top of the system allocator.
#[global_allocator]
static HEAP: PeakAlloc = PeakAlloc;

/// Bytes the program holds on its heap now (Rust allocations; the C libraries' own, such
/// as the Vulkan driver's, are not seen here but are in [`rss_bytes`]).
pub fn heap_bytes() -> u64 {
    HEAP.current_usage() as u64
}

/// The most [`heap_bytes`] has been since the process started.
pub fn peak_heap_bytes() -> u64 {
    HEAP.peak_usage() as u64
}

/// Resident set size of this process now (`VmRSS`), when the OS reports it (Linux).
pub fn rss_bytes() -> Option<u64> {
    status_kib("VmRSS:").map(|k| k * 1024)
}

/// Peak resident set size of this process (`VmHWM`), when the OS reports it (Linux).
pub fn peak_rss_bytes() -> Option<u64> {
    status_kib("VmHWM:").map(|k| k * 1024)
}

fn status_kib(key: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    parse_status_kib(&status, key)
}

fn parse_status_kib(status: &str, key: &str) -> Option<u64> {
    let line = status.lines().find(|l| l.starts_with(key))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// GPU memory as wgpu's allocator reports it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct GpuReport {
    /// Bytes of every live allocation.
    pub allocated: u64,
    /// Of them, those labelled as the terrain's ([`crate::render::tiles::TERRAIN_LABEL`]):
    /// what the memory limit counts on the GPU.
    pub terrain: u64,
    /// Bytes the allocator holds from the driver (allocations and the free space in its
    /// blocks).
    pub reserved: u64,
}

impl GpuReport {
    /// The device's report; `None` where the backend gives none.
    pub fn of(device: &wgpu::Device) -> Option<GpuReport> {
        let report = device.generate_allocator_report()?;
        Some(GpuReport {
            allocated: report.total_allocated_bytes,
            terrain: report
                .allocations
                .iter()
                .filter(|a| a.name.starts_with(crate::render::tiles::TERRAIN_LABEL))
                .map(|a| a.size)
                .sum(),
            reserved: report.total_reserved_bytes,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_heap_count_follows_an_allocation() {
        let before = heap_bytes();
        let block = vec![1u8; 8 << 20];
        // Other test threads allocate too; 8 MiB stands out of their noise.
        assert!(
            heap_bytes() >= before + (7 << 20),
            "{} then {}",
            before,
            heap_bytes()
        );
        assert!(peak_heap_bytes() >= heap_bytes());
        drop(block);
    }

    #[test]
    fn status_lines_give_kibibytes() {
        let status = "Name:\tx\nVmHWM:\t  182720 kB\nVmRSS:\t  100 kB\n";
        assert_eq!(parse_status_kib(status, "VmHWM:"), Some(182_720));
        assert_eq!(parse_status_kib(status, "VmRSS:"), Some(100));
        assert_eq!(parse_status_kib(status, "VmSwap:"), None);
        assert!(rss_bytes().is_some_and(|r| r > 0));
    }
}
