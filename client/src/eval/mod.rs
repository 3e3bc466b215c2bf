//! Measuring frames against a reference: screen-space geometric error, crack pixels and
//! colour PSNR. Pure functions of per-pixel data, so every rule is tested on constructed
//! frames; producing that data from the renderer is the caller's.

pub mod accuracy;
pub mod frame;
pub mod metrics;
pub mod session;
pub mod stability;
