//! Rendering: the wgpu terrain renderer and what feeds it.
//!
//! - [`gpu`]: the adapter and device (headless or for a window; `REQUIRE_GPU=1` insists on
//!   Vulkan).
//! - [`camera`]: position, orientation, projection (reversed depth) and frustum.
//! - [`plan`]: per frame, which resident tiles are visible and which strip mask each draws
//!   (culling, then [`crate::lod`]'s importance and budget sharing).
//! - [`textures`]: the texture budget, how fine each tile's texture goes.
//! - [`mesh`]: a tile's samples and normals, and the skirt strips.
//! - [`terrain`]: GPU resources and the render pass, with the crack fillers.
//! - [`pool`]: the least-recently-used pool of sample buffers (the GeoMipMaps VBO manager).
//! - [`blocks`]: MapBlocks, textures of `n x m` tiles bound once per block.
//! - [`offscreen`]: a colour target read back into an image (headless flights, tests).

pub mod blocks;
pub mod camera;
pub mod gpu;
pub mod mesh;
pub mod offscreen;
pub mod plan;
pub mod pool;
pub mod terrain;
pub mod textures;

pub use camera::Camera;
pub use gpu::{Gpu, GpuError};
pub use offscreen::Offscreen;
pub use plan::{Draw, FramePlan, Layout, LodSettings};
pub use terrain::{CrackFiller, GpuResidency, RenderStats, TerrainRenderer};
