//! The tile server: a builder that turns a DEM (and an optional texture) into a tile
//! database, and an HTTP server that serves it.
//!
//! - [`build`] reads rasters, tiles them, computes per-tile metadata and textures, and
//!   writes a database through [`db::DbWriter`].
//! - [`db`] is the database on disk: its layout, the atomic writer and the read side.
//! - [`http`] serves an opened [`db::TileDb`] over HTTP.
//!
//! The binary (`src/main.rs`) only parses arguments and maps errors to exit codes.

pub mod build;
pub mod db;
pub mod http;
