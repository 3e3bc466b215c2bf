//! The vocabulary that crosses the wire between the tile server and its clients:
//! tile ids, the manifest, the URL routes, the heights codec and the strip-mask
//! geometry that the builder's error tables and the renderer must agree on.
//!
//! Invariant: this crate does no IO, spawns nothing and knows nothing of HTTP
//! servers, sockets or GPUs. It turns bytes into values and back.

pub mod heights;
pub mod manifest;
pub mod mask;
pub mod quadtree;
mod rans;
pub mod routes;
pub mod tile;
pub mod tile_blob;
#[cfg(any(target_arch = "wasm32", test))]
mod zstd_frames;

pub use heights::{DecodeError, EncodeError, Heights};
pub use manifest::{Blob, Manifest, TileRecord};
pub use tile::TileId;
pub use tile_blob::TileBlob;
