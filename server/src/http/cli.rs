//! `terrain-server serve`: arguments, the tokio runtime, the one stdout line, the signals.
//!
//! Standard output carries exactly one line, `listening on http://ADDR`, flushed at once:
//! scripts and the benchmark start the server on port 0 and read the port from it.
//! Everything else (logs) goes to standard error.

use super::{AppState, ServeOptions, serve, shutdown_signal};
use crate::db::{TileDb, Verify};
use anyhow::Context;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

/// Where the server listens unless told otherwise: loopback only, so exposing it is a
/// deliberate `--addr 0.0.0.0:8080`.
pub const DEFAULT_ADDR: &str = "127.0.0.1:8080";

/// How often the server looks for a rebuilt database by default: a `stat` of one file.
pub const DEFAULT_RELOAD_POLL: Duration = Duration::from_secs(2);

/// Arguments of `terrain-server serve`.
#[derive(clap::Args, Debug)]
pub struct ServeArgs {
    /// Tile database: a directory written by `terrain-server build`, or an object-store
    /// location `s3://bucket/prefix` that `build --out s3://…` published to (credentials,
    /// region and endpoint from the AWS_* environment variables: AWS_ACCESS_KEY_ID,
    /// AWS_SECRET_ACCESS_KEY, AWS_REGION, AWS_ENDPOINT, AWS_ALLOW_HTTP=true for plain HTTP).
    #[arg(value_name = "DB", value_parser = crate::store::Location::parse)]
    pub db: crate::store::Location,
    /// Bytes of blobs kept in memory for the next requests (the hot tiles), whether read
    /// from an object store or from the directory's packs: a hit costs neither a read nor a
    /// hash check. 0 keeps none. Counted and reported in /metrics.
    #[arg(long, value_name = "SIZE", default_value = "256MiB", value_parser = byte_size)]
    pub cache_bytes: u64,
    /// Address to listen on. Port 0 picks a free port; the line on stdout names it.
    #[arg(long, default_value = DEFAULT_ADDR)]
    pub addr: SocketAddr,
    /// Skip hashing every blob at start-up and only check pack sizes (faster start on large
    /// databases, but a damaged blob would be served).
    #[arg(long)]
    pub no_verify: bool,
    /// Seconds a connection may go without a request in progress: to send its request head
    /// after connecting, and between requests (the keep-alive idle timeout).
    #[arg(long, value_name = "SECONDS", default_value_t = super::serve::DEFAULT_HEADER_READ_TIMEOUT.as_secs_f64(), value_parser = seconds)]
    pub header_read_timeout: f64,
    /// Seconds a response may make no progress (the client not reading) before its
    /// connection is closed.
    #[arg(long, value_name = "SECONDS", default_value_t = super::serve::DEFAULT_WRITE_TIMEOUT.as_secs_f64(), value_parser = seconds)]
    pub write_timeout: f64,
    /// Seconds from routing a request to its response head before it is answered 503.
    #[arg(long, value_name = "SECONDS", default_value_t = super::serve::DEFAULT_REQUEST_TIMEOUT.as_secs_f64(), value_parser = seconds)]
    pub request_timeout: f64,
    /// Requests handled at once; more are refused with 503 instead of queued.
    #[arg(long, default_value_t = super::serve::DEFAULT_MAX_CONCURRENT_REQUESTS, value_parser = at_least_one)]
    pub max_concurrent_requests: usize,
    /// Connections open at once. When all are taken, the oldest with no request in progress
    /// is closed to make room; when every one is busy, new ones wait in the accept backlog.
    #[arg(long, default_value_t = super::serve::DEFAULT_MAX_CONNECTIONS, value_parser = at_least_one)]
    pub max_connections: usize,
    /// Seconds shutdown waits for responses in flight after SIGINT or SIGTERM.
    #[arg(long, value_name = "SECONDS", default_value_t = super::serve::DEFAULT_SHUTDOWN_DEADLINE.as_secs_f64(), value_parser = seconds)]
    pub shutdown_deadline: f64,
    /// `scheme://host[:port]` of the server as browsers reach it, for the absolute tile
    /// URLs of the TileJSON documents (default: the request's Host, over http).
    #[arg(long, value_name = "URL", value_parser = public_url)]
    pub public_url: Option<String>,
    /// Serve the viewer page (MapLibre and Cesium, `bash viewer/setup.sh` makes it) from
    /// this directory under `/view/`; `/` then redirects to it.
    #[arg(long, value_name = "DIR")]
    pub viewer: Option<PathBuf>,
    /// Seconds between two looks at the database's manifest file (for a store, a GET of its
    /// pointer object): when a build with `--force` has replaced the database, or a build
    /// published a new version to the store, the new one is served from then on, without a
    /// restart (SIGHUP does the same at once). 0: only on SIGHUP.
    #[arg(long, value_name = "SECONDS", default_value_t = DEFAULT_RELOAD_POLL.as_secs_f64(), value_parser = seconds)]
    pub reload_poll: f64,
    /// Runtime worker threads, up to 1024; 0 means one per CPU core.
    #[arg(long, default_value_t = 0, value_parser = worker_threads)]
    pub worker_threads: usize,
}

/// A count that 0 would make meaningless (a server answering nothing, or everything).
fn at_least_one(text: &str) -> Result<usize, String> {
    let n: usize = text
        .parse()
        .map_err(|_| format!("{text:?} is not a whole number"))?;
    if n == 0 {
        return Err("must be at least 1".into());
    }
    Ok(n)
}

/// The most runtime threads a server starts: beyond it the threads' stacks, not the
/// requests, would be what the machine spends its memory on.
pub const MAX_WORKER_THREADS: usize = 1024;

fn worker_threads(text: &str) -> Result<usize, String> {
    let n: usize = text
        .parse()
        .map_err(|_| format!("{text:?} is not a whole number"))?;
    if n > MAX_WORKER_THREADS {
        return Err(format!(
            "{n} threads is more than the {MAX_WORKER_THREADS} a server starts (0: one per CPU core)"
        ));
    }
    Ok(n)
}

/// `--public-url`: an `http` or `https` URL of a host, nothing after it but a path, so
/// that what goes into the TileJSON documents' tile URLs is a web address and nothing else
/// (`javascript:`, `data:`, a query or a fragment are refused).
fn public_url(text: &str) -> Result<String, String> {
    let url = url::Url::parse(text).map_err(|e| format!("{text:?} is not a URL: {e}"))?;
    if !matches!(url.scheme(), "http" | "https") {
        return Err(format!(
            "{text:?}: the scheme must be http or https, not {:?}",
            url.scheme()
        ));
    }
    if url.host_str().is_none_or(str::is_empty)
        || url.query().is_some()
        || url.fragment().is_some()
        || !url.username().is_empty()
        || url.password().is_some()
    {
        return Err(format!(
            "{text:?}: give scheme://host[:port][/path], without credentials, query or fragment"
        ));
    }
    Ok(text.trim_end_matches('/').to_string())
}

impl ServeArgs {
    pub fn options(&self) -> ServeOptions {
        ServeOptions {
            header_read_timeout: Duration::from_secs_f64(self.header_read_timeout),
            write_timeout: Duration::from_secs_f64(self.write_timeout),
            request_timeout: Duration::from_secs_f64(self.request_timeout),
            max_concurrent_requests: self.max_concurrent_requests,
            max_connections: self.max_connections,
            shutdown_deadline: Duration::from_secs_f64(self.shutdown_deadline),
        }
    }
}

/// Opens the database, binds, prints the address and serves until SIGINT or SIGTERM; a
/// rebuilt database is served without a restart ([`super::reload`]).
pub fn run_cli(args: ServeArgs) -> anyhow::Result<()> {
    let verify = if args.no_verify {
        Verify::SizesOnly
    } else {
        Verify::Hashes
    };
    let mut runtime = tokio::runtime::Builder::new_multi_thread();
    runtime.enable_all();
    if args.worker_threads > 0 {
        runtime.worker_threads(args.worker_threads);
    }
    let runtime = runtime.build().context("cannot start the async runtime")?;

    let started = std::time::Instant::now();
    let cache = Arc::new(crate::store::BlobCache::new(args.cache_bytes));
    let opened = match &args.db {
        crate::store::Location::Dir(dir) => {
            TileDb::open_with_cache(dir, verify, Arc::clone(&cache)).map_err(anyhow::Error::from)
        }
        crate::store::Location::Store(url) => {
            let store = crate::store::connect(url)?;
            let source = Arc::new(crate::store::StoreSource {
                store,
                url: url.clone(),
                cache: Arc::clone(&cache),
            });
            runtime.block_on(async {
                let version = crate::store::current_version(&*source.store, url).await?;
                anyhow::Ok(TileDb::open_store(source, &version, verify).await?)
            })
        }
    };
    let db = opened.with_context(|| format!("cannot serve {}", args.db))?;
    let manifest = db.manifest();
    tracing::info!(
        db = %args.db,
        dataset = %manifest.dataset,
        content_version = %manifest.content_version,
        tiles = manifest.tile_count(),
        levels = manifest.level_count(),
        ?verify,
        elapsed_ms = started.elapsed().as_millis() as u64,
        "database opened"
    );
    if let Some(dir) = &args.viewer
        && !dir.join("index.html").is_file()
    {
        anyhow::bail!(
            "--viewer {}: no index.html there (run `bash viewer/setup.sh` to make viewer/dist)",
            dir.display()
        );
    }
    if manifest.web.is_none() {
        tracing::info!("no web tiles in this database: the MapLibre and Cesium routes answer 404");
    }
    let mut state = AppState::with_verify(db, verify);
    let from_store = matches!(args.db, crate::store::Location::Store(_));
    state.metrics.register_cache(cache, from_store);
    state.public_url = args.public_url.clone();
    state.viewer = args.viewer.clone();
    let state = Arc::new(state);
    let options = args.options();
    runtime.block_on(async move {
        let listener = tokio::net::TcpListener::bind(args.addr)
            .await
            .with_context(|| format!("cannot listen on {}", args.addr))?;
        let local = listener
            .local_addr()
            .context("cannot read the bound address")?;
        crate::print_stdout(&format!("listening on http://{local}\n"))
            .context("cannot write to stdout")?;
        tracing::info!(addr = %local, ?options, "serving");
        let poll = (args.reload_poll > 0.0).then(|| Duration::from_secs_f64(args.reload_poll));
        tokio::spawn(super::reload::watch(Arc::clone(&state), poll));
        serve(listener, state, options, shutdown_signal())
            .await
            .context("server failed")
    })?;
    tracing::info!("stopped");
    Ok(())
}

/// A size in bytes: a whole number, optionally followed by KiB, MiB or GiB.
fn byte_size(text: &str) -> Result<u64, String> {
    let trimmed = text.trim();
    let (number, unit) = match trimmed.find(|c: char| !c.is_ascii_digit()) {
        Some(at) => trimmed.split_at(at),
        None => (trimmed, ""),
    };
    let scale: u64 = match unit.trim() {
        "" | "B" => 1,
        "KiB" => 1 << 10,
        "MiB" => 1 << 20,
        "GiB" => 1 << 30,
        other => {
            return Err(format!(
                "{text:?}: unknown unit {other:?} (a number of bytes, or with KiB, MiB or GiB)"
            ));
        }
    };
    number
        .parse::<u64>()
        .ok()
        .and_then(|n| n.checked_mul(scale))
        .ok_or_else(|| {
            format!("{text:?} is not a size (a number of bytes, or with KiB, MiB or GiB)")
        })
}

/// A non-negative, finite number of seconds.
fn seconds(text: &str) -> Result<f64, String> {
    let value: f64 = text
        .parse()
        .map_err(|_| format!("{text:?} is not a number of seconds"))?;
    if value.is_finite() && value >= 0.0 && Duration::try_from_secs_f64(value).is_ok() {
        Ok(value)
    } else {
        Err(format!(
            "{text:?} is not a non-negative, finite number of seconds"
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::byte_size;

    #[test]
    fn cache_sizes_take_bytes_or_binary_units() {
        assert_eq!(byte_size("0"), Ok(0));
        assert_eq!(byte_size("4096"), Ok(4096));
        assert_eq!(byte_size("256MiB"), Ok(256 << 20));
        assert_eq!(byte_size("2 GiB"), Ok(2 << 30));
        for bad in ["", "MiB", "1.5MiB", "12MB", "-1", "99999999999999GiB"] {
            let error = byte_size(bad).expect_err(bad);
            assert!(error.contains(bad), "{bad}: {error}");
        }
    }
}
