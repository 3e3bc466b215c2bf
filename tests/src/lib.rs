//! Test harness shared by the end-to-end tests.

pub mod data;
pub mod golden;
pub mod proxy;
pub mod server;
pub mod synthetic;
