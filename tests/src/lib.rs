//! Test harness shared by the end-to-end tests.

pub mod browser;
pub mod child;
pub mod data;
pub mod fixtures;
pub mod golden;
pub mod proxy;
pub mod scale;
pub mod server;
pub mod stamp;
pub mod synthetic;
pub mod tier;

/// A scene's connection to the server at `base_url` with the default fetcher, made on
/// `runtime`; panics with the reason when the server cannot be reached.
pub fn connect(
    runtime: &tokio::runtime::Runtime,
    base_url: &str,
) -> terrain_client::scene::Connection {
    runtime
        .block_on(terrain_client::scene::Scene::connect(
            base_url,
            terrain_client::requests::FetcherConfig::default(),
            runtime.handle().clone(),
        ))
        .unwrap_or_else(|e| panic!("cannot connect to {base_url}: {e}"))
}
