//! Test inputs: the bundled fixture and the data kit outside the repository.
//!
//! The kit is found through one environment variable, [`DATA_DIR_VAR`]. Without it, a test
//! that needs the kit prints that it did not run and returns; with [`REQUIRE_DATA_VAR`] set
//! to 1 (CI sets both) a missing kit fails the test instead. A test never passes because
//! its input is missing without saying so.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Directory of the data kit (`../shared/data` beside the repository in CI).
pub const DATA_DIR_VAR: &str = "TERRAIN_DATA_DIR";
/// Set to 1 to turn a missing data kit into a failure.
pub const REQUIRE_DATA_VAR: &str = "REQUIRE_DATA";

/// The jacksboro DEM bundled in `tests/fixtures/` (with its dataset.json).
pub fn jacksboro() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/jacksboro/jacksboro_fault_dem.png")
}

/// Builds the bundled jacksboro fixture into `dir/db` with the builder's defaults.
pub fn build_jacksboro(dir: &Path) -> terrain_server::build::BuildReport {
    let options = terrain_server::build::BuildOptions::new(jacksboro(), dir.join("db"));
    terrain_server::build::build(
        &options,
        &|_, _| {},
        &std::sync::atomic::AtomicBool::new(false),
    )
    .unwrap_or_else(|e| panic!("the jacksboro fixture must build: {e}"))
}

/// A file of the data kit, or `None` (after saying so on stderr) when the kit is absent.
/// Panics when the kit is required or the variable names a kit that lacks the file.
pub fn kit_file(test: &str, relative: &str) -> Option<PathBuf> {
    let required = std::env::var(REQUIRE_DATA_VAR).is_ok_and(|v| v == "1");
    let Some(dir) = std::env::var_os(DATA_DIR_VAR) else {
        assert!(
            !required,
            "{test}: {REQUIRE_DATA_VAR}=1 but {DATA_DIR_VAR} is not set"
        );
        // Written to the stream itself, not with `eprintln!`: the test harness captures the
        // print macros of passing tests, and this line must be seen.
        let _ = writeln!(
            std::io::stderr(),
            "NOT RUN: {test} needs the data kit: set {DATA_DIR_VAR} to its data/ directory"
        );
        return None;
    };
    let path = Path::new(&dir).join(relative);
    assert!(
        path.exists(),
        "{test}: {} does not exist ({DATA_DIR_VAR}={})",
        path.display(),
        Path::new(&dir).display()
    );
    Some(path)
}

/// A greyscale PNG's samples as codes, row-major.
pub fn png_codes(path: &Path) -> (u32, u32, Vec<i32>) {
    let image = image::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let (w, h) = (image.width(), image.height());
    let codes = match image {
        image::DynamicImage::ImageLuma16(i) => i.into_raw().into_iter().map(i32::from).collect(),
        image::DynamicImage::ImageLuma8(i) => i.into_raw().into_iter().map(i32::from).collect(),
        other => panic!("{}: not grey: {:?}", path.display(), other.color()),
    };
    (w, h, codes)
}

/// An int16 GeoTIFF's samples, read with the `tiff` crate directly (not through the builder).
pub fn geotiff_i16(path: &Path) -> (u32, u32, Vec<i16>) {
    let file = std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut decoder = tiff::decoder::Decoder::new(std::io::BufReader::new(file)).expect("a TIFF");
    let (w, h) = decoder.dimensions().expect("dimensions");
    match decoder.read_image().expect("decodes") {
        tiff::decoder::DecodingResult::I16(v) => (w, h, v),
        _ => panic!("{}: not int16", path.display()),
    }
}

/// A release binary of the workspace, built beside this test binary
/// (`cargo build --release --workspace` builds it; the test command does that first).
pub fn workspace_binary(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("test binary path");
    // target/<profile>/deps/e2e-<hash> -> target/<profile>/<name>
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("target/<profile>");
    let path = dir.join(name);
    assert!(
        path.exists(),
        "{} not built: run `cargo build --release --workspace` first",
        path.display()
    );
    path
}

/// Runs a workspace binary to completion, returning (success, stdout, stderr).
pub fn run_binary(name: &str, args: &[&std::ffi::OsStr]) -> (bool, String, String) {
    let output = Command::new(workspace_binary(name))
        .args(args)
        .output()
        .expect("binary runs");
    (
        output.status.success(),
        String::from_utf8_lossy(&output.stdout).into_owned(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    )
}

/// Bytes the client holds for a resident tile of any level: decoded codes (4 bytes each),
/// its table of mask errors (an `f32` per mask level, from its tile blob) and the coarsest
/// texture level.
pub fn tile_bytes(manifest: &terrain_shared::Manifest, id: terrain_shared::TileId) -> u64 {
    let record = manifest.tile(id).expect("in grid");
    4 * u64::from(manifest.tile_size).pow(2)
        + 4 * u64::from(manifest.mask_levels)
        + record.coarsest_texture_bytes
}

/// A memory budget (`--memory`, before the flight's 10% margin) with room for every tile of
/// the levels above level 0 and for `tiles` tiles of level 0 the size of tile (0, 0): the
/// pager shares the limit out coarsest level first (`page::level_shares`), so each coarser
/// level takes what it needs whole and level 0 gets room for `tiles`.
pub fn budget_for_level_0_tiles(manifest: &terrain_shared::Manifest, tiles: u64) -> u64 {
    let coarser: u64 = manifest
        .tiles()
        .filter(|(id, _)| id.level > 0)
        .map(|(id, _)| tile_bytes(manifest, id))
        .sum();
    (coarser + tiles * tile_bytes(manifest, terrain_shared::TileId::new(0, 0))) * 10 / 9
}
