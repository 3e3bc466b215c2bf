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
//! mask whose projected error stays within a pixel threshold; [`levels`] chooses which
//! level of the pyramid draws each part of the terrain; [`plan`] culls a frame's tiles,
//! ranks them and makes the strip-mask plan (steps 1 to 3 together). A method's own pure
//! decisions live with it ([`crate::method`]: GeoMipMaps' stitching, the projected grids'
//! geometry).
//!
//! The module owns these decisions and nothing else. The methods ([`crate::method`]) call
//! them; uploading index sets and drawing them is the methods', through the renderer. Nothing here reads a clock, does IO or touches the GPU:
//! time is passed in, so every rule is tested with plain data (benches/lod.rs times a frame).

pub mod budget;
pub mod importance;
pub mod levels;
pub mod needed;
pub mod plan;
pub mod strips;
