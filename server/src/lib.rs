//! The tile server: a builder that turns a DEM (and an optional texture) into a tile
//! database, and an HTTP server that serves it.
//!
//! - [`build`] reads rasters, tiles them, computes per-tile metadata and textures, and
//!   writes a database through [`db::DbWriter`].
//! - [`db`] is the database on disk: its layout, the atomic writer and the read side.
//! - [`http`] serves an opened [`db::TileDb`] over HTTP.
//! - [`store`] keeps a database in an object store (S3): publishing, the pointer, the cache.
//! - [`web`] makes the tiles MapLibre and Cesium read; [`export`] writes them as PMTiles.
//!
//! The binary (`src/main.rs`) only parses arguments and maps errors to exit codes.

pub mod build;
pub mod db;
pub mod export;
pub mod http;
pub mod store;
pub mod web;

/// Writes `text` to stdout and flushes it. A closed stdout (`terrain-server build … | head
/// -0`) is not an error: whoever reads the output has gone, and the work is done, so the
/// text is dropped quietly, as other command-line tools do.
pub fn print_stdout(text: &str) -> std::io::Result<()> {
    use std::io::Write;
    let mut stdout = std::io::stdout().lock();
    match stdout
        .write_all(text.as_bytes())
        .and_then(|()| stdout.flush())
    {
        Err(error) if error.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        other => other,
    }
}
