//! Choosing the level of detail: which strip mask each visible tile draws this frame.
//!
//! Section 5 of the strip-mask paper (Pouderoux and Marvie 2005) in three pure steps, each
//! its own module, called once per frame in this order:
//!
//! 1. [`importance`]: a visual importance per visible tile from its distance to the
//!    viewpoint and its height (bounding box or roughness), summing to 1 (section 5.2).
//! 2. [`budget`]: the frame's global triangle budget, predicted from previous frames to hold
//!    a target frame rate ([`budget::FrameRateController`]), shared greedily among the tiles
//!    in decreasing importance ([`budget::share`], section 5.3).
//! 3. [`strips`]: the mask set every tile shares, one triangle strip per mask level, built
//!    lazily, and the choice of the finest mask that fits a tile's budget (section 5.1).
//!
//! Beside them, [`needed`] measures a frame against what it needs: per tile, the coarsest
//! mask whose projected error stays within a pixel threshold.
//!
//! The module owns these decisions and nothing else. Which tiles are visible, their
//! distances and the measured frame times come from the caller; uploading the strips and
//! drawing them is the renderer's. Nothing here reads a clock, does IO or touches the GPU:
//! time is passed in, so every rule is tested with plain data (benches/lod.rs times a frame).

pub mod budget;
pub mod geomipmap;
pub mod importance;
pub mod needed;
pub mod strips;
