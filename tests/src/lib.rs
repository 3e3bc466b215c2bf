//! Test harness shared by the end-to-end tests.

pub mod server;
pub mod synthetic;
pub mod data;
pub mod proxy;
