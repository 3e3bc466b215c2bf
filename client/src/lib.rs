//! The terrain client: everything between a tile server's HTTP API and the screen.
//!
//! The data path runs in steps, one module each, and a tile travels through them in order:
//!
//! 1. **fetch** ([`fetch`]): the manifest, then tiles by URL; every body is checked against
//!    the manifest's content hash before anything else sees it, and heights are decoded off
//!    the async threads.
//! 2. **page** (later): which belts of tiles around the viewpoint to hold, fetch and drop.
//! 3. **choose LOD** (later): the mask level and texture level each held tile draws with.
//! 4. **render** (later): upload and draw.
//!
//! Deciding code (paging, LOD choice, the [`overview`] mosaic, the [`report`] of a fetch) is
//! pure: values in, values out, no sockets, clocks or GPU, so it is tested with plain data.
//! IO sits at the rim: [`fetch`] talks HTTP, [`cli`] writes files and draws progress.
//!
//! **Invariant:** nothing downstream of [`fetch`] sees bytes whose hash was not checked.

pub mod charts;
pub mod cli;
pub mod fetch;
pub mod fetcher;
pub mod flight;
pub mod memory;
pub mod overview;
pub mod page;
pub mod path;
pub mod report;
