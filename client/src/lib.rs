//! The terrain client: everything between a tile server's HTTP API and the screen.
//!
//! The data path runs in steps, one module each, and a tile travels through them in order:
//!
//! 1. **fetch** ([`http_client`], [`requests`]): the manifest, then tiles by URL; every body is
//!    checked against the manifest's content hash before anything else sees it, and
//!    heights are decoded off the async threads. The [`requests`] scheduler carries out the pager's
//!    and the method's requests: bounded concurrency, priority order, cancellation, retries
//!    with backoff.
//! 2. **page** ([`page`]): which belts of tiles around the viewpoint to hold, fetch and
//!    drop within the memory limit ([`memory`]), Algorithm 1 of the strip-mask paper.
//! 3. **choose and draw the level of detail** ([`method`], deciding with [`lod`]): each
//!    method decides what to draw of the resident tiles and records it into a frame.
//! 4. **render** ([`render`]): what every method shares on the GPU: the resident tiles'
//!    samples and textures, the frame's uniforms, depth and read-back, the tile pipeline.
//!
//! [`scene`] runs steps 2 to 4 a frame at a time (with the texture budget), from the one
//! setup path [`scene::Scene::connect`]. [`flight`] drives a scene headless along a camera
//! path ([`path`]) and records each frame ([`record`]); [`viewer`] drives one in a window;
//! [`charts`] draws the records; [`eval`] measures frames against the true surface and a
//! reference.
//!
//! Deciding code (paging, level of detail, camera paths, the [`overview`] mosaic, the
//! [`report`] of a fetch) is pure: values in, values out, no sockets, clocks or GPU, so it
//! is tested with plain data. IO sits at the rim: [`http_client`] and [`requests`] talk HTTP
//! (their tasks and waits in [`tasks`]: a tokio runtime natively, the page's event loop in a
//! browser), [`cli`] and [`flight`] write files and draw progress.
//!
//! **Invariant:** nothing downstream of [`http_client`] sees bytes whose hash was not checked
//! (a method's own data is checked when its hash is given).
//! **Invariant:** the pager never awaits, reads a clock or touches the GPU.

#[cfg(not(target_arch = "wasm32"))]
pub mod charts;
#[cfg(not(target_arch = "wasm32"))]
pub mod cli;
#[cfg(not(target_arch = "wasm32"))]
pub mod eval;
#[cfg(not(target_arch = "wasm32"))]
pub mod flight;
pub mod fly;
pub mod http_client;
pub mod lod;
pub mod memory;
pub mod method;
#[cfg(not(target_arch = "wasm32"))]
pub mod output;
pub mod overview;
pub mod page;
pub mod path;
#[cfg(not(target_arch = "wasm32"))]
pub mod process;
#[cfg(not(target_arch = "wasm32"))]
pub mod record;
pub mod render;
pub mod report;
pub mod requests;
pub mod scene;
pub mod tasks;
#[cfg(test)]
mod testing;
#[cfg(not(target_arch = "wasm32"))]
pub mod viewer;
