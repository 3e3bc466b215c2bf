//! End-to-end tests: one binary, linked once.

mod http;
mod build;
mod round_trip;
mod fetcher;
mod flight;
