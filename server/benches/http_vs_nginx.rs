//! End-to-end HTTP benchmark: `terrain-server serve` against nginx serving the same heights
//! blobs as static files, under the same load, on the same machine, in one run.
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
//! server goes first, each run after a warm-up.
//!
//! Placement: on a machine with at least `workers + 1` usable CPUs both servers run on the
//! first `workers` of them and wrk on the rest (`taskset`), so the load generator never
//! takes CPU from the server it measures. With fewer CPUs, without `taskset` or with
//! `TERRAIN_BENCH_PIN=0` the run is unpinned and says so on its first lines.
//!
//! It prints, for every run, requests/s, p50 and p99 latency, MiB/s and the server's CPU
//! (per cent of one CPU, and microseconds per request, from `/proc`); then per server the
//! median, minimum, maximum and spread ((max - min) / median) of requests/s and p99; the
//! ratio of the medians ours/nginx, the range of the per-round ratios and the worst and
//! best pairing of any two runs; the CPU model and the load average before and after.
//! A server well below 100% CPU was held back by wrk or by other processes on its CPU
//! (the load average says which), not by its own cost; its CPU per request is then the
//! fairer comparison.
//!
//! Targets: ratio of the medians >= 1.0, our median p99 under 15 ms. Each gets a PASS or
//! FAIL line; the exit status is 0 either way (it is non-zero only when the benchmark
//! cannot run), so a shared machine's noise never fails a build.
//!
//! Both servers get the same number of workers (`TERRAIN_BENCH_WORKERS`, default 1):
//! nginx `worker_processes N`, terrain-server `--worker-threads N`. wrk runs with 2
//! threads. Other settings: `TERRAIN_BENCH_SECONDS` per run (default 10),
//! `TERRAIN_BENCH_CONNECTIONS` (default 64), `TERRAIN_BENCH_ROUNDS` (default 5),
//! `TERRAIN_BENCH_PIN` (default 1; 0 leaves placement to the scheduler),
//! `TERRAIN_BENCH_NICE` (default 0; e.g. -10 runs the servers and wrk at a higher priority
//! than other work on the machine, which needs root or `CAP_SYS_NICE`); the default run
//! takes about 2 minutes 10 s.
//!
//! Priority: with the kernel's autogroup scheduling (`/proc/sys/kernel/sched_autogroup_enabled`,
//! on in most distributions) CPU time is shared between *sessions* first, so `nice` alone
//! does not lift a process above the builds of another terminal. `TERRAIN_BENCH_NICE`
//! therefore also sets the niceness of this benchmark's autogroup (`/proc/self/autogroup`,
//! which the servers and wrk share) and restores it at the end; an interrupted run leaves
//! it raised until the terminal session ends. Needs `nginx` and `wrk` on PATH (Debian:
//! `apt-get install nginx wrk`) and, for pinning, `taskset` (util-linux).
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
/// wrk threads: two load generators, as the reference command `wrk -t2 -c64`. Pinned to one
/// CPU they take turns on it; wrk's event loop is cheap next to a server's work per request.
const WRK_THREADS: u32 = 2;
/// How long a server may take to start answering before the benchmark gives up.
const START_TIMEOUT: Duration = Duration::from_secs(30);
/// Warm-up before each measurement: page cache, nginx's open_file_cache, TCP connections.
const WARM_UP: Duration = Duration::from_secs(2);
/// Targets: at least nginx's requests/s (the ratio of the medians) with every hardening
/// layer on, and a p99 a map client never notices.
const TARGET_RATIO: f64 = 1.0;
const TARGET_P99_MS: f64 = 15.0;

/// A figure of a run: its name, how to read it, and the decimals to print.
type Figure = (&'static str, fn(&Run) -> Option<f64>, usize);

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
    pin: bool,
    /// Niceness of the servers and wrk; 0 leaves their priority alone.
    nice: i64,
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
             TERRAIN_BENCH_ROUNDS (5), TERRAIN_BENCH_PIN (1; 0 = no taskset), TERRAIN_BENCH_NICE (0)."
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
        rounds: number("TERRAIN_BENCH_ROUNDS", 5)?.max(1) as u32,
        pin: number("TERRAIN_BENCH_PIN", 1)? != 0,
        nice: match std::env::var("TERRAIN_BENCH_NICE") {
            Ok(text) => text
                .parse()
                .with_context(|| format!("TERRAIN_BENCH_NICE={text:?} is not a whole number"))?,
            Err(_) => 0,
        },
    })
}

/// Where the servers and wrk run: CPU lists for `taskset -c`, or why there are none.
enum Placement {
    Pinned { servers: String, wrk: String },
    Unpinned { reason: String },
}

/// How the servers and wrk are started: their CPUs and their niceness.
struct Launch<'a> {
    cpus: Option<&'a str>,
    nice: i64,
}

impl Launch<'_> {
    /// `program`, under `nice -n` and `taskset -c` where asked for.
    fn command(&self, program: &str) -> Command {
        let mut wrapper: Vec<String> = Vec::new();
        if self.nice != 0 {
            wrapper.extend(["nice".to_string(), "-n".to_string(), self.nice.to_string()]);
        }
        if let Some(cpus) = self.cpus {
            wrapper.extend(["taskset".to_string(), "-c".to_string(), cpus.to_string()]);
        }
        match wrapper.split_first() {
            Some((first, rest)) => {
                let mut command = Command::new(first);
                command.args(rest).arg(program);
                command
            }
            None => Command::new(program),
        }
    }
}

impl Placement {
    /// The servers take the first `workers` CPUs this process may use, wrk the rest.
    fn choose(settings: &Settings) -> Placement {
        let unpinned = |reason: String| Placement::Unpinned { reason };
        if !settings.pin {
            return unpinned("TERRAIN_BENCH_PIN=0".to_string());
        }
        let cpus = match usable_cpus() {
            Ok(cpus) => cpus,
            Err(error) => return unpinned(format!("cannot read the usable CPUs: {error:#}")),
        };
        if cpus.len() <= settings.workers {
            return unpinned(format!(
                "{} usable CPU(s), {} server worker(s): no CPU left for wrk alone",
                cpus.len(),
                settings.workers
            ));
        }
        if !runs("taskset", "-V") {
            return unpinned("`taskset` is not on PATH (Debian: util-linux)".to_string());
        }
        let list = |cpus: &[usize]| {
            cpus.iter()
                .map(usize::to_string)
                .collect::<Vec<_>>()
                .join(",")
        };
        let (servers, wrk) = cpus.split_at(settings.workers);
        Placement::Pinned {
            servers: list(servers),
            wrk: list(wrk),
        }
    }

    fn servers(&self) -> Option<&str> {
        match self {
            Placement::Pinned { servers, .. } => Some(servers),
            Placement::Unpinned { .. } => None,
        }
    }

    fn wrk(&self) -> Option<&str> {
        match self {
            Placement::Pinned { wrk, .. } => Some(wrk),
            Placement::Unpinned { .. } => None,
        }
    }

    fn describe(&self) -> String {
        match self {
            Placement::Pinned { servers, wrk } => {
                format!("pinned with taskset: both servers on CPU {servers}, wrk on CPU {wrk}")
            }
            Placement::Unpinned { reason } => format!(
                "UNPINNED ({reason}): servers and wrk share the CPUs, so every figure \
                 includes the load generator's competition"
            ),
        }
    }
}

/// The CPUs this process may run on, from `Cpus_allowed_list` in `/proc/self/status`
/// (e.g. `0-1` or `0,2-3`): a container or an outer `taskset` may allow fewer than exist.
fn usable_cpus() -> anyhow::Result<Vec<usize>> {
    let status = std::fs::read_to_string("/proc/self/status")?;
    let list = status
        .lines()
        .find_map(|line| line.strip_prefix("Cpus_allowed_list:"))
        .context("no Cpus_allowed_list in /proc/self/status")?;
    let mut cpus = Vec::new();
    for part in list.trim().split(',') {
        let (first, last) = part.split_once('-').unwrap_or((part, part));
        let (first, last): (usize, usize) = (first.parse()?, last.parse()?);
        cpus.extend(first..=last);
    }
    ensure!(!cpus.is_empty(), "an empty Cpus_allowed_list");
    Ok(cpus)
}

fn runs(program: &str, argument: &str) -> bool {
    Command::new(program)
        .arg(argument)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok()
}

fn run() -> anyhow::Result<()> {
    let settings = settings()?;
    for tool in ["nginx", "wrk"] {
        ensure!(
            runs(tool, "-v"),
            "`{tool}` is not on PATH (Debian: apt-get install nginx wrk)"
        );
    }
    let placement = Placement::choose(&settings);
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
    for (id, _) in manifest.tiles() {
        let path = routes::heights(version, id);
        let blob = db.heights(id).context("a manifest tile without heights")?;
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
    println!("placement: {}", placement.describe());
    let _priority = (settings.nice != 0).then(|| SessionPriority::raise(settings.nice));
    let servers = Launch {
        cpus: placement.servers(),
        nice: settings.nice,
    };
    let load = Launch {
        cpus: placement.wrk(),
        nice: settings.nice,
    };
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
         {} rounds alternating which server goes first, each run after a {}s warm-up",
        settings.connections,
        settings.seconds,
        paths.len(),
        settings.rounds,
        WARM_UP.as_secs()
    );
    println!(
        "servers: nginx worker_processes {w} (sendfile, etag, open_file_cache, access_log off) vs \
         terrain-server --worker-threads {w} (tokio multi-thread runtime, default hardening)\n",
        w = settings.workers
    );

    let (check_path, check_bytes) = &paths[paths.len() / 2];
    let nginx = Nginx::start(work.path(), &root, settings.workers, &servers)?;
    let nginx_name = nginx_version();
    wait_until_serving(nginx.addr, check_path, check_bytes)?;
    let ours = TerrainServer::start(&settings.db, settings.workers, &servers)?;
    wait_until_serving(ours.addr, check_path, check_bytes)?;

    // Rounds alternate which server goes first, so a drift in the machine's load (another
    // build, thermal throttling) falls on both; the medians are what the verdict uses, the
    // spread and the ratio ranges say how far to trust them.
    let (mut nginx_runs, mut our_runs) = (Vec::new(), Vec::new());
    println!(
        "{:<16} {:>6} {:>12} {:>10} {:>10} {:>10} {:>8} {:>12}",
        "server", "round", "requests/s", "p50 ms", "p99 ms", "MiB/s", "cpu %", "cpu us/req"
    );
    for round in 1..=settings.rounds {
        let order = if round % 2 == 1 {
            [true, false]
        } else {
            [false, true]
        };
        for is_nginx in order {
            let (name, addr, pid) = if is_nginx {
                (nginx_name.as_str(), nginx.addr, nginx.pid())
            } else {
                ("terrain-server", ours.addr, ours.pid())
            };
            let result = measure(addr, pid, &script, &settings, &load)?;
            println!(
                "{name:<16} {round:>6} {:>12.0} {:>10.2} {:>10.2} {:>10.1} {:>8} {:>12}",
                result.wrk.requests_per_second,
                result.wrk.p50_ms,
                result.wrk.p99_ms,
                result.wrk.transfer_mib_per_second,
                optional(result.cpu_percent(), 0),
                optional(result.cpu_us_per_request(), 1),
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

    println!(
        "\n{:<16} {:<12} {:>10} {:>10} {:>10} {:>8}",
        "server", "figure", "median", "min", "max", "spread"
    );
    let figures: [Figure; 4] = [
        ("requests/s", |r| Some(r.wrk.requests_per_second), 0),
        ("p99 ms", |r| Some(r.wrk.p99_ms), 2),
        ("cpu %", Run::cpu_percent, 0),
        ("cpu us/req", Run::cpu_us_per_request, 1),
    ];
    for (name, runs) in [
        (nginx_name.as_str(), &nginx_runs),
        ("terrain-server", &our_runs),
    ] {
        for (figure, value, decimals) in figures {
            let Some(summary) = Summary::of(runs.iter().filter_map(value)) else {
                continue;
            };
            println!(
                "{name:<16} {figure:<12} {:>10.decimals$} {:>10.decimals$} {:>10.decimals$} {:>7.0}%",
                summary.median,
                summary.min,
                summary.max,
                summary.spread() * 100.0
            );
        }
    }

    let rate = |runs: &[Run]| Summary::of(runs.iter().map(|r| r.wrk.requests_per_second));
    let (Some(nginx_rate), Some(our_rate)) = (rate(&nginx_runs), rate(&our_runs)) else {
        bail!("no runs were measured");
    };
    let per_round = Summary::of(
        nginx_runs
            .iter()
            .zip(&our_runs)
            .map(|(n, o)| o.wrk.requests_per_second / n.wrk.requests_per_second),
    )
    .context("no rounds were measured")?;
    let ratio = our_rate.median / nginx_rate.median;
    println!(
        "\nratio ours/nginx requests/s: {ratio:.2}x of the medians; per round {:.2}x to {:.2}x; \
         worst to best pairing of any two runs {:.2}x to {:.2}x",
        per_round.min,
        per_round.max,
        our_rate.min / nginx_rate.max,
        our_rate.max / nginx_rate.min
    );
    let cpu = |runs: &[Run]| Summary::of(runs.iter().filter_map(Run::cpu_us_per_request));
    if let (Some(nginx_cpu), Some(our_cpu)) = (cpu(&nginx_runs), cpu(&our_runs)) {
        println!(
            "server CPU per request ours/nginx: {:.2}x of the medians ({:.1} us against {:.1} us)",
            our_cpu.median / nginx_cpu.median,
            our_cpu.median,
            nginx_cpu.median
        );
    }
    let our_p99 = Summary::of(our_runs.iter().map(|r| r.wrk.p99_ms)).context("no runs")?;
    let verdict = |ok: bool| if ok { "PASS" } else { "FAIL" };
    println!(
        "{}: requests/s ratio of the medians {ratio:.2}x, target >= {TARGET_RATIO:.1}x",
        verdict(ratio >= TARGET_RATIO)
    );
    println!(
        "{}: our median p99 {:.2} ms, target < {TARGET_P99_MS} ms",
        verdict(our_p99.median < TARGET_P99_MS),
        our_p99.median
    );
    println!("load average after: {}", load_average());
    if let Placement::Unpinned { .. } = placement {
        println!("note: the numbers above are unpinned");
    }
    Ok(())
}

/// A figure that may be missing (no `/proc`), right-aligned by the caller.
fn optional(value: Option<f64>, decimals: usize) -> String {
    value.map_or_else(|| "-".to_string(), |v| format!("{v:.decimals$}"))
}

/// Median, minimum and maximum of one figure over the rounds.
#[derive(Debug, Clone, Copy)]
struct Summary {
    median: f64,
    min: f64,
    max: f64,
}

impl Summary {
    fn of(values: impl Iterator<Item = f64>) -> Option<Summary> {
        let mut values: Vec<f64> = values.collect();
        values.sort_by(f64::total_cmp);
        let (&min, &max) = (values.first()?, values.last()?);
        let middle = values.len() / 2;
        let median = if values.len() % 2 == 1 {
            values[middle]
        } else {
            (values[middle - 1] + values[middle]) / 2.0
        };
        Some(Summary { median, min, max })
    }

    /// Range over median: 0.2 means the rounds spanned 20% of the typical value.
    fn spread(&self) -> f64 {
        (self.max - self.min) / self.median
    }
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .map(|text| {
            text.split_whitespace()
                .take(3)
                .collect::<Vec<_>>()
                .join(" ")
        })
        .unwrap_or_else(|| "unknown".to_string())
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
        "machine: {cpus} CPUs available, {model}, {} {}; load average before: {}",
        std::env::consts::OS,
        std::env::consts::ARCH,
        load_average()
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

impl Stopped {
    fn pid(&self) -> u32 {
        self.0.id()
    }
}

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
    process: Stopped,
}

impl Nginx {
    /// nginx in the foreground; its workers inherit the master's CPUs and niceness.
    fn start(work: &Path, root: &Path, workers: usize, launch: &Launch) -> anyhow::Result<Nginx> {
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
        let child = launch
            .command("nginx")
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
            process: Stopped(child),
        })
    }

    /// The master's process id; `nice` and `taskset` exec nginx, so it is the child's.
    fn pid(&self) -> u32 {
        self.process.pid()
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
    process: Stopped,
}

impl TerrainServer {
    fn start(db: &Path, workers: usize, launch: &Launch) -> anyhow::Result<TerrainServer> {
        let binary = env!("CARGO_BIN_EXE_terrain-server");
        let mut child = launch
            .command(binary)
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
        Ok(TerrainServer { addr, process })
    }

    fn pid(&self) -> u32 {
        self.process.pid()
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

/// One measured run: what wrk saw and the CPU time the server spent meanwhile.
#[derive(Debug, Clone, Copy)]
struct Run {
    wrk: WrkResult,
    /// Wall-clock seconds of the measured wrk run.
    seconds: f64,
    /// User + system CPU seconds of the server's processes over those seconds, if `/proc`
    /// could tell.
    server_cpu_seconds: Option<f64>,
}

impl Run {
    /// Share of one CPU the server used, in per cent.
    fn cpu_percent(&self) -> Option<f64> {
        Some(self.server_cpu_seconds? / self.seconds * 100.0)
    }

    fn cpu_us_per_request(&self) -> Option<f64> {
        let requests = self.wrk.requests_per_second * self.seconds;
        Some(self.server_cpu_seconds? / requests * 1e6)
    }
}

fn measure(
    addr: SocketAddr,
    server_pid: u32,
    script: &Path,
    settings: &Settings,
    launch: &Launch,
) -> anyhow::Result<Run> {
    wrk(
        addr,
        script,
        settings.connections,
        WARM_UP.as_secs().max(1),
        launch,
    )?;
    let cpu_before = cpu_seconds(server_pid);
    let started = Instant::now();
    let output = wrk(addr, script, settings.connections, settings.seconds, launch)?;
    let seconds = started.elapsed().as_secs_f64();
    let cpu_after = cpu_seconds(server_pid);
    let wrk = parse_wrk(&output).with_context(|| format!("cannot read wrk's output:\n{output}"))?;
    Ok(Run {
        wrk,
        seconds,
        server_cpu_seconds: cpu_before.zip(cpu_after).map(|(b, a)| a - b),
    })
}

/// User + system CPU seconds of process `pid` (all its threads) and of its direct children
/// (nginx's workers), from `/proc/<pid>/stat`; `None` where `/proc` cannot tell.
fn cpu_seconds(pid: u32) -> Option<f64> {
    let ticks_per_second = clock_ticks_per_second()?;
    let mut ticks = 0u64;
    for entry in std::fs::read_dir("/proc").ok()?.flatten() {
        let Some(candidate) = entry
            .file_name()
            .to_str()
            .and_then(|n| n.parse::<u32>().ok())
        else {
            continue;
        };
        let Some(stat) = ProcStat::read(candidate) else {
            continue;
        };
        if candidate == pid || stat.parent == pid {
            ticks += stat.cpu_ticks;
        }
    }
    Some(ticks as f64 / ticks_per_second)
}

/// The fields of `/proc/<pid>/stat` this benchmark needs (proc(5)).
struct ProcStat {
    parent: u32,
    /// utime + stime, in clock ticks.
    cpu_ticks: u64,
}

impl ProcStat {
    fn read(pid: u32) -> Option<ProcStat> {
        let text = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
        // The command name (field 2) is in parentheses and may hold spaces; the fields
        // after the last `)` start with field 3 (state).
        let after_name = &text[text.rfind(')')? + 1..];
        let fields: Vec<&str> = after_name.split_whitespace().collect();
        let field = |number: usize| fields.get(number - 3);
        Some(ProcStat {
            parent: field(4)?.parse().ok()?,
            cpu_ticks: field(14)?.parse::<u64>().ok()? + field(15)?.parse::<u64>().ok()?,
        })
    }
}

/// The niceness of this process's autogroup, raised for the benchmark and put back on drop.
struct SessionPriority {
    previous: Option<i64>,
}

impl SessionPriority {
    const PATH: &str = "/proc/self/autogroup";

    fn raise(nice: i64) -> SessionPriority {
        // The file reads `/autogroup-25 nice 0`.
        let previous = std::fs::read_to_string(Self::PATH).ok().and_then(|text| {
            text.split_whitespace()
                .skip_while(|word| *word != "nice")
                .nth(1)
                .and_then(|value| value.parse().ok())
        });
        match std::fs::write(Self::PATH, nice.to_string()) {
            Ok(()) => println!(
                "priority: servers and wrk at niceness {nice} (nice -n), in a session autogroup at niceness {nice}"
            ),
            Err(error) => println!(
                "priority: servers and wrk at niceness {nice} (nice -n); the session's autogroup \
                 is unchanged ({}: {error}), so other sessions still get an equal share",
                Self::PATH
            ),
        }
        SessionPriority { previous }
    }
}

impl Drop for SessionPriority {
    fn drop(&mut self) {
        if let Some(previous) = self.previous {
            let _ = std::fs::write(Self::PATH, previous.to_string());
        }
    }
}

/// `sysconf(_SC_CLK_TCK)`, through `getconf` to stay free of `libc`; read once.
fn clock_ticks_per_second() -> Option<f64> {
    static TICKS: std::sync::OnceLock<Option<f64>> = std::sync::OnceLock::new();
    *TICKS.get_or_init(|| {
        let output = Command::new("getconf").arg("CLK_TCK").output().ok()?;
        let ticks: f64 = String::from_utf8(output.stdout).ok()?.trim().parse().ok()?;
        (ticks > 0.0).then_some(ticks)
    })
}

/// Runs wrk, killing it if it overruns its duration by a wide margin.
fn wrk(
    addr: SocketAddr,
    script: &Path,
    connections: u32,
    seconds: u64,
    launch: &Launch,
) -> anyhow::Result<String> {
    let mut child = launch
        .command("wrk")
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
