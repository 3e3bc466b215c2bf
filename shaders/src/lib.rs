//! WGSL shader sources and the `#[repr(C)]` Rust types that mirror each uniform and vertex
//! struct they declare, with the constants both sides share named once here.
//!
//! Empty until the renderer lands: the client draws nothing yet, so there is no shader to
//! keep in step with Rust.
