//! What a whole-database fetch measured, as values: one [`TileReport`] per tile (a row of
//! `tiles.csv`) and the [`FetchSummary`] printed at the end. Pure formatting; the fetching,
//! timing and file writing are [`crate::cli`]'s.

use std::fmt;
use std::path::PathBuf;
use std::time::Duration;
use terrain_shared::TileId;

/// First line of `tiles.csv`; [`TileReport::csv_row`] writes the columns in this order.
pub const CSV_HEADER: &str =
    "x,y,heights_bytes,texture_bytes,min_m,max_m,roughness_m,decode_ms,fetch_ms";

/// One fetched tile.
#[derive(Debug, Clone, PartialEq)]
pub struct TileReport {
    pub id: TileId,
    pub heights_bytes: u64,
    /// All texture levels together.
    pub texture_bytes: u64,
    /// Lowest and highest decoded sample, metres.
    pub min_m: f64,
    pub max_m: f64,
    /// From the manifest: the client does not recompute it.
    pub roughness_m: f32,
    /// Decoding the heights, on the blocking pool.
    pub decode: Duration,
    /// Every request of the tile (heights and all texture levels), one after the other.
    pub fetch: Duration,
}

impl TileReport {
    /// One `tiles.csv` line without its newline. Metres to the millimetre and times to the
    /// microsecond: finer digits would be noise.
    pub fn csv_row(&self) -> String {
        format!(
            "{},{},{},{},{:.3},{:.3},{:.3},{:.3},{:.3}",
            self.id.x,
            self.id.y,
            self.heights_bytes,
            self.texture_bytes,
            self.min_m,
            self.max_m,
            self.roughness_m,
            millis(self.decode),
            millis(self.fetch),
        )
    }
}

/// The whole `tiles.csv`: header, then one row per report in the order given.
pub fn csv(reports: &[TileReport]) -> String {
    let mut text = String::with_capacity(64 * (reports.len() + 1));
    text.push_str(CSV_HEADER);
    text.push('\n');
    for report in reports {
        text.push_str(&report.csv_row());
        text.push('\n');
    }
    text
}

/// The end of a fetch, printed for a person.
#[derive(Debug, Clone, PartialEq)]
pub struct FetchSummary {
    pub server: String,
    pub dataset: String,
    pub content_version: String,
    pub tiles: usize,
    pub heights_bytes: u64,
    pub texture_bytes: u64,
    /// From the manifest request to the last tile decoded.
    pub elapsed: Duration,
    /// Lowest and highest height over every decoded tile, metres.
    pub decoded_range_m: (f64, f64),
    /// The manifest's `heights.min_m` and `heights.max_m`.
    pub manifest_range_m: (f64, f64),
    /// The manifest's height quantum: ranges closer than half of it agree.
    pub quantum_m: f64,
    pub overview: PathBuf,
    pub overview_size: (u32, u32),
    pub csv: PathBuf,
}

impl FetchSummary {
    /// Whether the decoded heights span what the manifest says, to within half a quantum.
    pub fn ranges_agree(&self) -> bool {
        let tolerance = self.quantum_m / 2.0;
        (self.decoded_range_m.0 - self.manifest_range_m.0).abs() <= tolerance
            && (self.decoded_range_m.1 - self.manifest_range_m.1).abs() <= tolerance
    }
}

impl fmt::Display for FetchSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let total = self.heights_bytes + self.texture_bytes;
        // A zero elapsed time (impossible in practice) reads as "inf", not as a panic.
        let seconds = self.elapsed.as_secs_f64();
        writeln!(
            f,
            "server      {} (dataset {}, content version {})",
            self.server, self.dataset, self.content_version
        )?;
        writeln!(f, "tiles       {}", self.tiles)?;
        writeln!(f, "heights     {}", megabytes(self.heights_bytes))?;
        writeln!(f, "textures    {}", megabytes(self.texture_bytes))?;
        writeln!(
            f,
            "total       {} in {seconds:.2} s: {:.2} MB/s, {:.1} tiles/s",
            megabytes(total),
            total as f64 / 1e6 / seconds,
            self.tiles as f64 / seconds,
        )?;
        writeln!(
            f,
            "heights     decoded {:.2} .. {:.2} m, manifest {:.2} .. {:.2} m ({})",
            self.decoded_range_m.0,
            self.decoded_range_m.1,
            self.manifest_range_m.0,
            self.manifest_range_m.1,
            if self.ranges_agree() {
                "agree"
            } else {
                "DIFFER"
            },
        )?;
        write!(
            f,
            "wrote       {} ({}x{}), {}",
            self.overview.display(),
            self.overview_size.0,
            self.overview_size.1,
            self.csv.display()
        )
    }
}

fn millis(duration: Duration) -> f64 {
    duration.as_secs_f64() * 1e3
}

/// Decimal megabytes, as network throughput is usually counted.
fn megabytes(bytes: u64) -> String {
    format!("{:.3} MB", bytes as f64 / 1e6)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report(x: u32, y: u32) -> TileReport {
        TileReport {
            id: TileId::new(x, y),
            heights_bytes: 1234,
            texture_bytes: 56789,
            min_m: -12.25,
            max_m: 4392.0,
            roughness_m: 3.5,
            decode: Duration::from_micros(1500),
            fetch: Duration::from_millis(20),
        }
    }

    fn summary(decoded_range_m: (f64, f64)) -> FetchSummary {
        FetchSummary {
            server: "http://127.0.0.1:8080".into(),
            dataset: "test".into(),
            content_version: "abc".into(),
            tiles: 4,
            heights_bytes: 1_000_000,
            texture_bytes: 3_000_000,
            elapsed: Duration::from_secs(2),
            decoded_range_m,
            manifest_range_m: (-12.25, 4392.0),
            quantum_m: 0.25,
            overview: "out/overview.png".into(),
            overview_size: (1024, 512),
            csv: "out/tiles.csv".into(),
        }
    }

    #[test]
    fn csv_rows_follow_the_header_columns() {
        assert_eq!(
            report(3, 7).csv_row(),
            "3,7,1234,56789,-12.250,4392.000,3.500,1.500,20.000"
        );
        assert_eq!(
            CSV_HEADER.split(',').count(),
            report(0, 0).csv_row().split(',').count()
        );
        let text = csv(&[report(0, 0), report(1, 0)]);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(
            lines,
            [CSV_HEADER, &report(0, 0).csv_row(), &report(1, 0).csv_row()]
        );
    }

    #[test]
    fn the_summary_gives_throughput_and_compares_height_ranges() {
        let text = summary((-12.25, 4392.1)).to_string();
        assert!(
            text.contains("total       4.000 MB in 2.00 s: 2.00 MB/s, 2.0 tiles/s"),
            "{text}"
        );
        assert!(
            text.contains("decoded -12.25 .. 4392.10 m, manifest -12.25 .. 4392.00 m (agree)"),
            "{text}"
        );
        assert!(!summary((-12.25, 4391.0)).ranges_agree());
    }
}
