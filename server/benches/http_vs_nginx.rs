//! End-to-end HTTP benchmark: `terrain-server serve` against nginx serving the same
//! heights blobs as static files, under the same load, on the same machine, in one run.
//!
//! ```text
//! TERRAIN_BENCH_DB=db/puget_sound_1k cargo bench -p terrain-server --bench http_vs_nginx
//! cargo bench -p terrain-server --bench http_vs_nginx -- db/puget_sound_1k
//! ```
//!
//! It writes every heights blob of the database to a file at its URL path under a
//! temporary directory, starts nginx on it (sendfile, etag, open_file_cache, no access
//! log: nginx at its best for static files) and the release `terrain-server` on the
//! database, checks both answer a tile with the right bytes, then runs `wrk` against each
//! with a Lua script that cycles over every heights URL, in rounds that alternate which
//! server goes first. It prints requests/s, p50 and p99 latency of every run, the medians,
//! the ratio of the medians ours/nginx and the machine. Targets: ratio >= 0.7, our median
//! p99 under 15 ms.
//!
//! Both servers get the same number of workers (`TERRAIN_BENCH_WORKERS`, default 1):
//! nginx `worker_processes N`, terrain-server `--worker-threads N`. wrk runs on the same
//! machine with 2 threads, so on a 2-core machine one core serves and one loads.
//! Other settings: `TERRAIN_BENCH_SECONDS` per run (default 10), `TERRAIN_BENCH_CONNECTIONS`
//! (default 64), `TERRAIN_BENCH_ROUNDS` (default 3); the default run takes about 75 s. Needs `nginx` and `wrk` on PATH (Debian: `apt-get install nginx wrk`).
//! Every child process is stopped when the benchmark ends, also on error.

use anyhow::{Context, bail, ensure};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use terrain_server::db::{TileDb, Verify};
use terrain_shared::routes;

const HEIGHTS_CONTENT_TYPE: &str = terrain_server::http::routes::HEIGHTS_CONTENT_TYPE;
const TILE_CACHE_CONTROL: &str = terrain_server::http::routes::TILE_CACHE_CONTROL;
/// wrk threads: two load generators, as the issue's reference command (`wrk -t2 -c64`).
const WRK_THREADS: u32 = 2;
/// How long a server may take to start answering before the benchmark gives up.
const START_TIMEOUT: Duration = Duration::from_secs(30);
/// Warm-up before each measurement: page cache, nginx's open_file_cache, TCP connections.
const WARM_UP: Duration = Duration::from_secs(2);
/// Targets from the issue.
const TARGET_RATIO: f64 = 0.7;
const TARGET_P99_MS: f64 = 15.0;

fn main() {
    match run() {
        Ok(()) => {}
        Err(error) => {
            eprintln!("http_vs_nginx: {error:#}");
            std::process::exit(1);
        }
    }
}

struct Settings {
    db: PathBuf,
    workers: usize,
    seconds: u64,
    connections: u32,
    rounds: u32,
}

fn settings() -> anyhow::Result<Settings> {
    // `cargo bench` passes `--bench`; the first other argument is the database.
    let argument = std::env::args().skip(1).find(|a| !a.starts_with("--"));
    let Some(db) = argument.or_else(|| std::env::var("TERRAIN_BENCH_DB").ok()) else {
        bail!(
            "no database given.\n\n\
             usage: TERRAIN_BENCH_DB=<database dir> cargo bench -p terrain-server --bench http_vs_nginx\n   \
             or: cargo bench -p terrain-server --bench http_vs_nginx -- <database dir>\n\n\
             A database is what `terrain-server build` writes, e.g.\n   \
             cargo run --release -p terrain-server -- build tests/fixtures/jacksboro/jacksboro_fault_dem.png --out db/jacksboro\n\n\
             Optional: TERRAIN_BENCH_WORKERS (default 1), TERRAIN_BENCH_SECONDS (10), TERRAIN_BENCH_CONNECTIONS (64),\n\
             TERRAIN_BENCH_ROUNDS (3)."
        );
    };
    let number = |name: &str, default: u64| -> anyhow::Result<u64> {
        match std::env::var(name) {
            Ok(text) => text
                .parse()
                .with_context(|| format!("{name}={text:?} is not a whole number")),
            Err(_) => Ok(default),
        }
    };
    Ok(Settings {
        db: PathBuf::from(db),
        workers: number("TERRAIN_BENCH_WORKERS", 1)?.max(1) as usize,
        seconds: number("TERRAIN_BENCH_SECONDS", 10)?.max(1),
        connections: number("TERRAIN_BENCH_CONNECTIONS", 64)?.max(1) as u32,
        rounds: number("TERRAIN_BENCH_ROUNDS", 3)?.max(1) as u32,
    })
}

fn run() -> anyhow::Result<()> {
    let settings = settings()?;
    for tool in ["nginx", "wrk"] {
        ensure!(
            Command::new(tool)
                .arg("-v")
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .status()
                .is_ok(),
            "`{tool}` is not on PATH (Debian: apt-get install nginx wrk)"
        );
    }
    let db = TileDb::open(&settings.db, Verify::SizesOnly)
        .with_context(|| format!("cannot open the database {}", settings.db.display()))?;
    let manifest = db.manifest();
    let version = &manifest.content_version;

    let work = tempfile::Builder::new()
        .prefix("http-vs-nginx-")
        .tempdir()
        .context("cannot create a temporary directory")?;
    let root = work.path().join("www");
    let mut paths = Vec::new();
    let mut total_bytes = 0u64;
    for tile in &manifest.tiles {
        let path = routes::heights(version, tile.id());
        let blob = db
            .heights(tile.id())
            .context("a manifest tile without heights")?;
        let file = root.join(path.trim_start_matches('/'));
        if let Some(parent) = file.parent() {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("cannot create {}", parent.display()))?;
        }
        std::fs::write(&file, &blob.bytes)
            .with_context(|| format!("cannot write {}", file.display()))?;
        total_bytes += blob.bytes.len() as u64;
        paths.push((path, blob.bytes.clone()));
    }
    ensure!(!paths.is_empty(), "the database has no tiles");
    // nginx's workers may run as `nobody`; the temporary directory is private by default.
    make_world_readable(work.path())?;

    let script = work.path().join("cycle.lua");
    std::fs::write(&script, wrk_script(paths.iter().map(|(p, _)| p.as_str())))
        .context("cannot write the wrk script")?;

    print_machine();
    println!(
        "database: {} ({}, {} tiles, heights {:.2} MiB, mean {:.1} KiB per tile)",
        settings.db.display(),
        manifest.dataset,
        paths.len(),
        total_bytes as f64 / (1 << 20) as f64,
        total_bytes as f64 / paths.len() as f64 / 1024.0
    );
    println!(
        "load: wrk -t{WRK_THREADS} -c{} -d{}s --latency, cycling over all {} heights URLs, on the same machine; \
         {} rounds alternating which server goes first, each after a {}s warm-up",
        settings.connections,
        settings.seconds,
        paths.len(),
        settings.rounds,
        WARM_UP.as_secs()
    );
    println!(
        "servers: nginx worker_processes {w} (sendfile, etag, open_file_cache, access_log off) vs \
         terrain-server --worker-threads {w} (tokio multi-thread runtime)\n",
        w = settings.workers
    );

    let (check_path, check_bytes) = &paths[paths.len() / 2];
    let nginx = Nginx::start(work.path(), &root, settings.workers)?;
    let nginx_name = nginx_version();
    wait_until_serving(nginx.addr, check_path, check_bytes)?;
    let ours = TerrainServer::start(&settings.db, settings.workers)?;
    wait_until_serving(ours.addr, check_path, check_bytes)?;

    // Rounds alternate which server goes first, so a drift in the machine's load (another
    // build, thermal throttling) falls on both; the medians are what the verdict uses.
    let (mut nginx_runs, mut our_runs) = (Vec::new(), Vec::new());
    println!(
        "{:<16} {:>6} {:>12} {:>10} {:>10} {:>10}",
        "server", "round", "requests/s", "p50 ms", "p99 ms", "MiB/s"
    );
    for round in 1..=settings.rounds {
        let order = if round % 2 == 1 {
            [true, false]
        } else {
            [false, true]
        };
        for is_nginx in order {
            let (name, addr) = if is_nginx {
                (nginx_name.as_str(), nginx.addr)
            } else {
                ("terrain-server", ours.addr)
            };
            let result = measure(addr, &script, &settings)?;
            println!(
                "{name:<16} {round:>6} {:>12.0} {:>10.2} {:>10.2} {:>10.1}",
                result.requests_per_second,
                result.p50_ms,
                result.p99_ms,
                result.transfer_mib_per_second
            );
            if is_nginx {
                nginx_runs.push(result)
            } else {
                our_runs.push(result)
            }
        }
    }
    drop(ours);
    drop(nginx);

    let nginx_median = WrkResult::median(&nginx_runs);
    let our_median = WrkResult::median(&our_runs);
    println!();
    for (name, result) in [
        (nginx_name.as_str(), &nginx_median),
        ("terrain-server", &our_median),
    ] {
        println!(
            "{name:<16} {:>6} {:>12.0} {:>10.2} {:>10.2} {:>10.1}",
            "median",
            result.requests_per_second,
            result.p50_ms,
            result.p99_ms,
            result.transfer_mib_per_second
        );
    }
    let ratio = our_median.requests_per_second / nginx_median.requests_per_second;
    let verdict = |ok: bool| if ok { "met" } else { "MISSED" };
    println!(
        "\nratio ours/nginx: {ratio:.2}x requests/s (target >= {TARGET_RATIO}: {}); our p99 {:.2} ms (target < {TARGET_P99_MS} ms: {})",
        verdict(ratio >= TARGET_RATIO),
        our_median.p99_ms,
        verdict(our_median.p99_ms < TARGET_P99_MS)
    );
    Ok(())
}

fn print_machine() {
    let cpus = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(0);
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|info| {
            info.lines()
                .find(|line| line.starts_with("model name"))
                .and_then(|line| line.split_once(':'))
                .map(|(_, model)| model.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".to_string());
    println!(
        "machine: {cpus} CPUs available, {model}, {} {}",
        std::env::consts::OS,
        std::env::consts::ARCH
    );
}

/// A Lua script for wrk whose `request` walks the paths in a cycle (per wrk thread).
fn wrk_script<'a>(paths: impl Iterator<Item = &'a str>) -> String {
    let mut lua = String::from("local paths = {\n");
    for path in paths {
        lua.push_str(&format!("  {path:?},\n"));
    }
    lua.push_str(
        "}\nlocal i = 0\nrequest = function()\n  i = i % #paths + 1\n  return wrk.format(\"GET\", paths[i])\nend\n",
    );
    lua
}

fn make_world_readable(dir: &Path) -> anyhow::Result<()> {
    use std::os::unix::fs::PermissionsExt;
    let mode = if dir.is_dir() { 0o755 } else { 0o644 };
    std::fs::set_permissions(dir, std::fs::Permissions::from_mode(mode))
        .with_context(|| format!("cannot chmod {}", dir.display()))?;
    if dir.is_dir() {
        for entry in
            std::fs::read_dir(dir).with_context(|| format!("cannot list {}", dir.display()))?
        {
            make_world_readable(&entry.context("cannot list a directory")?.path())?;
        }
    }
    Ok(())
}

fn free_port() -> anyhow::Result<u16> {
    // Bound and released at once; the small race with another process is acceptable here.
    let listener = std::net::TcpListener::bind("127.0.0.1:0").context("cannot find a free port")?;
    Ok(listener.local_addr()?.port())
}

/// A child process that is stopped (SIGTERM, then SIGKILL after 5 s) when dropped.
struct Stopped(Child);

impl Drop for Stopped {
    fn drop(&mut self) {
        // SIGTERM lets nginx's master stop its workers; a SIGKILLed master would orphan them.
        let _ = Command::new("kill")
            .arg("-TERM")
            .arg(self.0.id().to_string())
            .status();
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.0.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

struct Nginx {
    addr: SocketAddr,
    _process: Stopped,
}

impl Nginx {
    fn start(work: &Path, root: &Path, workers: usize) -> anyhow::Result<Nginx> {
        let port = free_port()?;
        let prefix = work.join("nginx");
        std::fs::create_dir_all(prefix.join("temp"))
            .context("cannot create nginx's directories")?;
        let conf = prefix.join("nginx.conf");
        let p = prefix.display();
        let config = format!(
            r#"worker_processes {workers};
pid {p}/nginx.pid;
error_log {p}/error.log warn;
events {{ worker_connections 4096; }}
http {{
    access_log off;
    sendfile on;
    tcp_nopush on;
    tcp_nodelay on;
    etag on;
    # wrk keeps its connections; nginx's default would close each after 1000 requests.
    keepalive_requests 1000000;
    open_file_cache max=100000 inactive=60s;
    open_file_cache_valid 60s;
    client_body_temp_path {p}/temp/body;
    proxy_temp_path {p}/temp/proxy;
    fastcgi_temp_path {p}/temp/fastcgi;
    uwsgi_temp_path {p}/temp/uwsgi;
    scgi_temp_path {p}/temp/scgi;
    types {{ }}
    default_type {HEIGHTS_CONTENT_TYPE};
    server {{
        listen 127.0.0.1:{port};
        root {root};
        location / {{
            add_header Cache-Control "{TILE_CACHE_CONTROL}";
        }}
    }}
}}
"#,
            root = root.display()
        );
        std::fs::write(&conf, config).context("cannot write nginx.conf")?;
        let child = Command::new("nginx")
            .arg("-p")
            .arg(&prefix)
            .arg("-e")
            .arg(prefix.join("error.log"))
            .arg("-c")
            .arg(&conf)
            .args(["-g", "daemon off;"])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .spawn()
            .context("cannot start nginx")?;
        Ok(Nginx {
            addr: SocketAddr::from(([127, 0, 0, 1], port)),
            _process: Stopped(child),
        })
    }
}

fn nginx_version() -> String {
    // `nginx -v` writes "nginx version: nginx/1.22.1" to stderr.
    Command::new("nginx")
        .arg("-v")
        .output()
        .ok()
        .and_then(|out| String::from_utf8(out.stderr).ok())
        .and_then(|text| text.trim().rsplit(' ').next().map(str::to_string))
        .unwrap_or_else(|| "nginx".to_string())
}

struct TerrainServer {
    addr: SocketAddr,
    _process: Stopped,
}

impl TerrainServer {
    fn start(db: &Path, workers: usize) -> anyhow::Result<TerrainServer> {
        let binary = env!("CARGO_BIN_EXE_terrain-server");
        let mut child = Command::new(binary)
            .arg("serve")
            .arg(db)
            .args([
                "--addr",
                "127.0.0.1:0",
                "--worker-threads",
                &workers.to_string(),
            ])
            .env("RUST_LOG", "warn")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .spawn()
            .with_context(|| format!("cannot start {binary}"))?;
        let stdout = child
            .stdout
            .take()
            .context("no stdout from terrain-server")?;
        let process = Stopped(child);
        // The one stdout line names the port; read it on a thread so a silent server
        // cannot hang the benchmark.
        let (sender, receiver) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut line = String::new();
            let _ = std::io::BufRead::read_line(&mut std::io::BufReader::new(stdout), &mut line);
            let _ = sender.send(line);
        });
        let line = receiver
            .recv_timeout(START_TIMEOUT)
            .context("terrain-server printed no address")?;
        let addr = line
            .trim()
            .strip_prefix("listening on http://")
            .and_then(|addr| addr.parse().ok())
            .with_context(|| format!("unexpected first line from terrain-server: {line:?}"))?;
        Ok(TerrainServer {
            addr,
            _process: process,
        })
    }
}

/// Polls `path` until the server answers it with `expected` bytes (or fails after a while):
/// both servers must serve the same tiles before their numbers mean anything.
fn wait_until_serving(addr: SocketAddr, path: &str, expected: &[u8]) -> anyhow::Result<()> {
    let deadline = Instant::now() + START_TIMEOUT;
    loop {
        match fetch_once(addr, path) {
            Ok(body) => {
                ensure!(
                    body == expected,
                    "{addr}{path} answers {} bytes that are not the stored tile",
                    body.len()
                );
                return Ok(());
            }
            Err(error) if Instant::now() > deadline => {
                return Err(error.context(format!("{addr} never served {path}")));
            }
            Err(_) => std::thread::sleep(Duration::from_millis(50)),
        }
    }
}

/// One `Connection: close` GET; the body of a 200.
fn fetch_once(addr: SocketAddr, path: &str) -> anyhow::Result<Vec<u8>> {
    let mut stream = TcpStream::connect_timeout(&addr, Duration::from_secs(2))?;
    stream.set_read_timeout(Some(Duration::from_secs(5)))?;
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: bench\r\nConnection: close\r\n\r\n"
    )?;
    let mut response = Vec::new();
    stream.read_to_end(&mut response)?;
    let end = response
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .context("no response head")?;
    let head = String::from_utf8_lossy(&response[..end]);
    ensure!(
        head.starts_with("HTTP/1.1 200"),
        "answer: {}",
        head.lines().next().unwrap_or("")
    );
    Ok(response[end + 4..].to_vec())
}

#[derive(Debug, Clone, Copy)]
struct WrkResult {
    requests_per_second: f64,
    p50_ms: f64,
    p99_ms: f64,
    transfer_mib_per_second: f64,
}

impl WrkResult {
    /// Median of each figure separately, over the rounds.
    fn median(runs: &[WrkResult]) -> WrkResult {
        let median = |figure: fn(&WrkResult) -> f64| {
            let mut values: Vec<f64> = runs.iter().map(figure).collect();
            values.sort_by(f64::total_cmp);
            values.get(values.len() / 2).copied().unwrap_or(f64::NAN)
        };
        WrkResult {
            requests_per_second: median(|r| r.requests_per_second),
            p50_ms: median(|r| r.p50_ms),
            p99_ms: median(|r| r.p99_ms),
            transfer_mib_per_second: median(|r| r.transfer_mib_per_second),
        }
    }
}

fn measure(addr: SocketAddr, script: &Path, settings: &Settings) -> anyhow::Result<WrkResult> {
    wrk(addr, script, settings.connections, WARM_UP.as_secs().max(1))?;
    let output = wrk(addr, script, settings.connections, settings.seconds)?;
    parse_wrk(&output).with_context(|| format!("cannot read wrk's output:\n{output}"))
}

/// Runs wrk, killing it if it overruns its duration by a wide margin.
fn wrk(addr: SocketAddr, script: &Path, connections: u32, seconds: u64) -> anyhow::Result<String> {
    let mut child = Command::new("wrk")
        .arg(format!("-t{WRK_THREADS}"))
        .arg(format!("-c{connections}"))
        .arg(format!("-d{seconds}s"))
        .arg("--latency")
        .arg("-s")
        .arg(script)
        .arg(format!("http://{addr}"))
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .context("cannot start wrk")?;
    let deadline = Instant::now() + Duration::from_secs(seconds + 30);
    loop {
        if child.try_wait()?.is_some() {
            break;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            bail!("wrk ran past its deadline");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let output = child.wait_with_output()?;
    let text = String::from_utf8_lossy(&output.stdout).into_owned();
    ensure!(
        output.status.success(),
        "wrk failed: {}{}",
        text,
        String::from_utf8_lossy(&output.stderr)
    );
    ensure!(
        !text.contains("Non-2xx"),
        "wrk saw error answers from {addr}:\n{text}"
    );
    Ok(text)
}

fn parse_wrk(output: &str) -> anyhow::Result<WrkResult> {
    let field = |prefix: &str| -> Option<&str> {
        output
            .lines()
            .find_map(|line| line.trim_start().strip_prefix(prefix))
            .map(str::trim)
    };
    let requests_per_second = field("Requests/sec:").context("no Requests/sec")?.parse()?;
    let transfer_mib_per_second = field("Transfer/sec:")
        .map(size_mib)
        .transpose()?
        .unwrap_or(0.0);
    let p50_ms = duration_ms(field("50%").context("no 50% latency (wrk --latency)")?)?;
    let p99_ms = duration_ms(field("99%").context("no 99% latency (wrk --latency)")?)?;
    Ok(WrkResult {
        requests_per_second,
        p50_ms,
        p99_ms,
        transfer_mib_per_second,
    })
}

/// wrk durations: `812.00us`, `1.23ms`, `1.01s`, `2.00m`.
fn duration_ms(text: &str) -> anyhow::Result<f64> {
    let split = text
        .find(|c: char| c.is_ascii_alphabetic())
        .context("a duration without unit")?;
    let value: f64 = text[..split].parse()?;
    Ok(match &text[split..] {
        "us" => value / 1000.0,
        "ms" => value,
        "s" => value * 1000.0,
        "m" => value * 60_000.0,
        unit => bail!("unknown duration unit {unit:?}"),
    })
}

/// wrk sizes: `1.23KB`, `45.6MB`, `1.0GB` (binary multiples).
fn size_mib(text: &str) -> anyhow::Result<f64> {
    let split = text
        .find(|c: char| c.is_ascii_alphabetic())
        .context("a size without unit")?;
    let value: f64 = text[..split].parse()?;
    Ok(match &text[split..] {
        "B" => value / (1 << 20) as f64,
        "KB" => value / 1024.0,
        "MB" => value,
        "GB" => value * 1024.0,
        unit => bail!("unknown size unit {unit:?}"),
    })
}
