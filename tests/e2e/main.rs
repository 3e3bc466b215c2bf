//! End-to-end tests: one binary, linked once.

mod accuracy;
mod build;
mod fetcher;
mod flight;
mod fuzz_corpora;
mod http;
mod methods;
mod render;
mod round_trip;
