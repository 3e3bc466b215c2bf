//! End-to-end tests: one binary, linked once.

mod build;
mod fetcher;
mod flight;
mod http;
mod round_trip;
