//! A real adapter for render tests, and golden-image comparison.
//!
//! **Adapter.** [`gpu`] returns a headless device, or `None` after saying on stderr that
//! the test did not run; with `REQUIRE_GPU=1` (CI) a missing adapter, or one that is not
//! Vulkan, fails the test instead.
//!
//! **Golden images** live in `tests/golden/`, made with lavapipe (the render tests; its
//! name in `tests/golden/ADAPTER`) and headless Chromium (the browser tests). [`compare`]
//! asks for every pixel equal ([`Match::Exact`]) on that lavapipe running on the processor
//! recorded beside it, where it renders bit for bit the same on every run. The same lavapipe
//! on another processor compiles its shaders for other vector instructions (AVX-512, FMA)
//! and rounds differently: there every channel of every pixel may differ by one level and
//! no more ([`Match::Rounding`]; an AMD EPYC and an Intel Xeon with AVX-512 differ on up to
//! 2% of the pixels, each by one level). On any other adapter, and for the browsers, at
//! most [`MAX_DIFFERING_SHARE`] of the pixels may differ by more than [`CHANNEL_TOLERANCE`]
//! in some channel ([`Match::Tolerant`]): room for other rasterisation and filtering (a
//! pixel along an edge, a texel's rounding). On failure it writes
//! `target/golden/NAME-actual.png` and `NAME-diff.png` (differing pixels in red over a
//! faded copy of the golden image) and says where. `UPDATE_GOLDEN=1` rewrites the golden
//! images instead of comparing; look at them before committing.

use std::io::Write;
use std::path::{Path, PathBuf};
use terrain_client::render::Gpu;
use terrain_client::render::gpu::gpu_required;

/// Largest per-channel difference (0-255) for a pixel to count as equal.
pub const CHANNEL_TOLERANCE: u8 = 12;
/// Largest per-channel difference on the golden images' adapter run on another processor.
pub const ROUNDING_TOLERANCE: u8 = 1;
/// Largest share of pixels allowed to differ.
pub const MAX_DIFFERING_SHARE: f64 = 0.005;

/// How close a frame must be to its golden image.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Match {
    /// Every channel of every pixel equal.
    Exact,
    /// Every channel of every pixel within [`ROUNDING_TOLERANCE`].
    Rounding,
    /// At most [`MAX_DIFFERING_SHARE`] of the pixels differ by more than
    /// [`CHANNEL_TOLERANCE`].
    Tolerant,
}

/// The adapter the render tests' golden images were made with (its name, as wgpu gives it:
/// lavapipe's carries its LLVM version and vector width, which change its rounding), and on
/// its second line the processor it ran on ([`processor`]).
const ADAPTER_FILE: &str = "ADAPTER";

/// What of this machine's processor decides how lavapipe rounds: its vendor and model, and
/// the vector instructions LLVM compiles shaders for.
pub fn processor() -> String {
    let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let field = |key: &str| {
        info.lines()
            .find(|l| l.split(':').next().is_some_and(|k| k.trim() == key))
            .and_then(|l| l.split_once(':'))
            .map_or(String::new(), |(_, v)| v.trim().to_string())
    };
    let flags = field("flags");
    let vector: Vec<&str> = ["avx", "avx2", "fma", "avx512f"]
        .into_iter()
        .filter(|f| flags.split_whitespace().any(|x| x == *f))
        .collect();
    format!(
        "{} {} [{}] on {}",
        field("vendor_id"),
        field("model name"),
        vector.join(" "),
        std::env::consts::ARCH
    )
}

impl Match {
    /// Exact on the adapter and processor the golden images were made with
    /// (`tests/golden/ADAPTER`, a lavapipe), within rounding on that adapter elsewhere,
    /// tolerant on any other adapter; said on stderr unless exact. With `UPDATE_GOLDEN=1`
    /// on lavapipe, records this adapter and processor as the ones.
    pub fn on(gpu: &Gpu) -> Match {
        let name = gpu.adapter.get_info().name;
        let cpu = processor();
        let path = golden_dir().join(ADAPTER_FILE);
        if std::env::var("UPDATE_GOLDEN").is_ok_and(|v| v == "1") && name.starts_with("llvmpipe") {
            std::fs::write(&path, format!("{name}\n{cpu}\n"))
                .expect("tests/golden/ADAPTER written");
        }
        let recorded = std::fs::read_to_string(&path).unwrap_or_default();
        let mut lines = recorded.lines().map(str::trim);
        let (made_with, made_on) = (lines.next().unwrap_or(""), lines.next().unwrap_or(""));
        let how = Match::between(made_with, made_on, &name, &cpu);
        if how != Match::Exact {
            let _ = writeln!(
                std::io::stderr(),
                "golden images compared {how:?}: made with {made_with:?} on {made_on:?}, rendered with {name:?} on {cpu:?}"
            );
        }
        how
    }

    /// How close a frame rendered by `adapter` on `cpu` must be to images made by
    /// `made_with` on `made_on`.
    pub fn between(made_with: &str, made_on: &str, adapter: &str, cpu: &str) -> Match {
        match (made_with == adapter, made_on == cpu) {
            (true, true) => Match::Exact,
            (true, false) => Match::Rounding,
            (false, _) => Match::Tolerant,
        }
    }

    fn tolerance(self) -> (u8, f64) {
        match self {
            Match::Exact => (0, 0.0),
            Match::Rounding => (ROUNDING_TOLERANCE, 0.0),
            Match::Tolerant => (CHANNEL_TOLERANCE, MAX_DIFFERING_SHARE),
        }
    }
}

/// A headless device, or `None` (said on stderr) when there is none and none is required.
pub fn gpu(test: &str) -> Option<Gpu> {
    match Gpu::headless() {
        Ok(gpu) => Some(gpu),
        Err(e) => {
            assert!(!gpu_required(), "{test}: REQUIRE_GPU=1 but {e}");
            let _ = writeln!(
                std::io::stderr(),
                "NOT RUN: {test} needs a graphics adapter: {e}"
            );
            None
        }
    }
}

fn golden_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("golden")
}

fn failure_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/golden")
}

fn differs(p: &image::Rgba<u8>, q: &image::Rgba<u8>, tolerance: u8) -> bool {
    p.0.iter()
        .zip(q.0.iter())
        .any(|(x, y)| x.abs_diff(*y) > tolerance)
}

/// Pixels whose channels differ by more than [`CHANNEL_TOLERANCE`].
pub fn differing_pixels(a: &image::RgbaImage, b: &image::RgbaImage) -> u64 {
    differing_pixels_by(a, b, CHANNEL_TOLERANCE)
}

/// Pixels whose channels differ by more than `tolerance`.
pub fn differing_pixels_by(a: &image::RgbaImage, b: &image::RgbaImage, tolerance: u8) -> u64 {
    a.pixels()
        .zip(b.pixels())
        .filter(|(p, q)| differs(p, q, tolerance))
        .count() as u64
}

/// The share of `actual`'s pixels that differ from `tests/golden/NAME.png` (as [`compare`]
/// counts them), or `None` when there is no golden image of that size: for a frame that
/// may legitimately differ from it, to say by how much.
pub fn differing_share(name: &str, actual: &image::RgbaImage) -> Option<f64> {
    let golden = image::open(golden_dir().join(format!("{name}.png")))
        .ok()?
        .into_rgba8();
    (golden.dimensions() == actual.dimensions()).then(|| {
        let total = u64::from(actual.width()) * u64::from(actual.height());
        differing_pixels(&golden, actual) as f64 / total as f64
    })
}

/// Compares `actual` with `tests/golden/NAME.png` (see the module docs).
pub fn compare(name: &str, actual: &image::RgbaImage, how: Match) {
    let golden_path = golden_dir().join(format!("{name}.png"));
    if std::env::var("UPDATE_GOLDEN").is_ok_and(|v| v == "1") {
        std::fs::create_dir_all(golden_dir()).expect("tests/golden");
        actual.save(&golden_path).expect("golden image written");
        let _ = writeln!(std::io::stderr(), "updated {}", golden_path.display());
        return;
    }
    let golden = match image::open(&golden_path) {
        Ok(image) => image.into_rgba8(),
        Err(e) => {
            let out = write_failure(name, actual, None, 0);
            panic!(
                "{name}: no golden image at {} ({e}); the frame is at {}. Look at it, then run with UPDATE_GOLDEN=1 to make it the golden image",
                golden_path.display(),
                out.display()
            );
        }
    };
    assert_eq!(
        golden.dimensions(),
        actual.dimensions(),
        "{name}: size differs from {}",
        golden_path.display()
    );
    let (tolerance, allowed) = how.tolerance();
    let differing = differing_pixels_by(&golden, actual, tolerance);
    let total = u64::from(actual.width()) * u64::from(actual.height());
    let share = differing as f64 / total as f64;
    if share > allowed {
        write_failure(name, actual, Some(&golden), tolerance);
        panic!(
            "{name}: {differing} of {total} pixels ({:.3}%) differ from {} by more than {tolerance} (allowed {:.2}%, {how:?}); see {}-actual.png and -diff.png",
            100.0 * share,
            golden_path.display(),
            100.0 * allowed,
            failure_dir().join(name).display()
        );
    }
}

/// Writes NAME-actual.png (and NAME-diff.png against `golden`); returns the actual's path.
fn write_failure(
    name: &str,
    actual: &image::RgbaImage,
    golden: Option<&image::RgbaImage>,
    tolerance: u8,
) -> PathBuf {
    let dir = failure_dir();
    let _ = std::fs::create_dir_all(&dir);
    let actual_path = dir.join(format!("{name}-actual.png"));
    let _ = actual.save(&actual_path);
    if let Some(golden) = golden {
        let diff = image::RgbaImage::from_fn(actual.width(), actual.height(), |x, y| {
            let (p, q) = (actual.get_pixel(x, y), golden.get_pixel(x, y));
            if differs(p, q, tolerance) {
                image::Rgba([255, 0, 0, 255])
            } else {
                let grey = (u16::from(q.0[0]) + u16::from(q.0[1]) + u16::from(q.0[2])) / 6 + 128;
                image::Rgba([grey as u8, grey as u8, grey as u8, 255])
            }
        });
        let _ = diff.save(dir.join(format!("{name}-diff.png")));
    }
    actual_path
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_same_adapter_on_another_processor_is_held_to_rounding_and_no_more() {
        let lvp = "llvmpipe (LLVM 15.0.6, 256 bits)";
        let amd = "AuthenticAMD AMD EPYC [avx avx2 fma] on x86_64";
        let intel = "GenuineIntel Intel(R) Xeon(R) Processor [avx avx2 fma avx512f] on x86_64";
        assert_eq!(Match::between(lvp, amd, lvp, amd), Match::Exact);
        assert_eq!(Match::between(lvp, amd, lvp, intel), Match::Rounding);
        assert_eq!(
            Match::between(lvp, amd, "NVIDIA H100", amd),
            Match::Tolerant
        );

        let golden = image::RgbaImage::from_pixel(8, 8, image::Rgba([100, 150, 200, 255]));
        let mut rounded = golden.clone();
        for p in rounded.pixels_mut() {
            p.0[1] += 1;
        }
        let mut wrong = golden.clone();
        wrong.get_pixel_mut(3, 3).0[0] += 2;
        let fails = |how: Match, actual: &image::RgbaImage| {
            let (tolerance, allowed) = how.tolerance();
            differing_pixels_by(&golden, actual, tolerance) as f64 / 64.0 > allowed
        };
        assert!(fails(Match::Exact, &rounded), "exact allows no rounding");
        assert!(
            !fails(Match::Rounding, &rounded),
            "one level on every pixel is rounding"
        );
        assert!(
            fails(Match::Rounding, &wrong),
            "two levels on one pixel is not"
        );
        assert!(!processor().is_empty());
    }
}
