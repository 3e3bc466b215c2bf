//! End-to-end tests: one binary, linked once.

mod accuracy;
mod browser;
mod build;
mod client_cli;
mod docs;
mod fetcher;
mod flight;
mod fuzz_corpora;
mod grids;
mod hostile;
mod http;
mod jobs;
mod levels;
mod memory;
mod methods;
mod patches;
mod reload;
mod render;
mod round_trip;
mod scale;
mod web;
