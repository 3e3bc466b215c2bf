//! Rendering: what every level-of-detail method shares on the GPU. Nothing here knows a
//! method; the methods ([`crate::method`]) record their frames through [`Frame`].
//!
//! - [`gpu`]: the adapter and device (headless or for a window; `REQUIRE_GPU=1` insists on
//!   Vulkan).
//! - [`camera`]: position, orientation, projection (reversed depth) and frustum.
//! - [`layout`]: where the tiles lie and where the terrain ends.
//! - [`frame`]: the [`Renderer`] (frame uniforms, depth and its read-back, timestamps, the
//!   tile pipeline) and one frame's recording ([`Frame`], [`FramePass`]).
//! - [`tiles`]: the resident tiles' sample buffers and textures ([`TileStore`]).
//! - `arena`: where the drawn tiles' samples lie, a storage buffer or (WebGL2) a texture.
//! - [`textures`]: the texture budget, how fine each tile's texture goes.
//! - [`mesh`]: a tile's samples and normals.
//! - [`pool`]: the least-recently-used pool of sample buffers (the GeoMipMaps VBO manager).
//! - [`blocks`]: MapBlocks, textures of `n x m` tiles bound once per block.
//! - [`offscreen`]: a colour target read back into an image (headless flights, tests).

mod arena;
pub mod blocks;
pub mod camera;
pub mod frame;
pub mod gpu;
pub mod layout;
pub mod mesh;
pub mod offscreen;
pub mod pool;
pub mod textures;
pub mod tiles;

pub use camera::Camera;
pub use frame::{Frame, FramePass, IndexSet, RenderStats, Renderer, SKY, TileExtras};
pub use gpu::{Gpu, GpuError, SampleStore};
pub use layout::Layout;
pub use offscreen::Offscreen;
pub use tiles::{GpuResidency, TileStore};
