//! Serving past one machine, run here for real: the database published to a SeaweedFS
//! object store, `serve s3://…` replicas reading it by range through their caches, and
//! nginx with `proxy_cache` in front of them (`terrain_tests::scale`).

use std::ffi::OsStr;
use std::path::Path;
use std::time::{Duration, Instant};
use terrain_client::flight::{FlightArgs, FlightSummary, StreamArgs, fly};
use terrain_client::memory::MemorySize;
use terrain_server::db::{TileDb, Verify};
use terrain_shared::{Manifest, TileId, routes};
use terrain_tests::data::{jacksboro, kit_file};
use terrain_tests::fixtures::{Options, database};
use terrain_tests::scale::{
    BUCKET, Nginx, ObjectStore, Replica, get, metric, server_command, tools,
};

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime")
}

/// `terrain-server publish DB s3://tiles/NAME`: the location's URL.
fn publish(store: &ObjectStore, db: &Path, name: &str) -> String {
    let url = format!("s3://{BUCKET}/{name}");
    let out = server_command(
        store,
        &[
            OsStr::new("publish"),
            db.as_os_str(),
            OsStr::new(&url),
            OsStr::new("--quiet"),
        ],
    );
    assert!(out.contains("the pointer names it"), "{out}");
    url
}

/// Every URL of the database: heights, every texture level, patches and their index, web tiles.
fn every_url(db: &TileDb) -> Vec<String> {
    let manifest = db.manifest();
    let cv = &manifest.content_version;
    let mut urls = Vec::new();
    for (id, _) in manifest.tiles() {
        urls.push(routes::heights(cv, id));
        for level in 0..manifest.texture.levels {
            urls.push(routes::texture(cv, id, level));
        }
        if manifest.patches.is_some() {
            urls.push(routes::patch(cv, id));
        }
    }
    if manifest.patches.is_some() {
        urls.push(routes::patch_index(cv));
    }
    for (entry, _) in db.web_tiles() {
        urls.push(terrain_server::http::web::tile_path(cv, *entry));
    }
    urls
}

/// Publishes `dir` to a store, serves it from the directory and from the store, and checks
/// every URL gives the same status, entity tag and bytes from both.
fn byte_identical(test: &str, dir: &Path, web: bool) {
    let Some(tools) = tools(test) else { return };
    let store = ObjectStore::start(&tools);
    let url = publish(&store, dir, test);
    let local = Replica::start(&store, &dir.to_string_lossy(), &[]);
    let remote = Replica::start(&store, &url, &[]);
    let db = TileDb::open(dir, Verify::SizesOnly).expect("opens");
    let urls = every_url(&db);
    // Puget Sound's PNG says nothing of where it lies: no web tiles.
    assert_eq!(db.web_tiles().next().is_some(), web, "{test}: web tiles");
    let mut bytes = 0usize;
    for path in &urls {
        let (status_a, headers_a, body_a) = get(&format!("{}{path}", local.base));
        let (status_b, headers_b, body_b) = get(&format!("{}{path}", remote.base));
        assert_eq!(status_a, 200, "{path} from the directory");
        assert_eq!(status_b, 200, "{path} from the store: {}", remote.log());
        assert_eq!(headers_a.get("etag"), headers_b.get("etag"), "{path}");
        assert_eq!(
            headers_a.get("content-type"),
            headers_b.get("content-type"),
            "{path}"
        );
        assert!(body_a == body_b, "{path}: the bytes differ");
        bytes += body_b.len();
    }
    let manifest = |base: &str| get(&format!("{base}{}", routes::MANIFEST)).2;
    assert_eq!(manifest(&local.base), manifest(&remote.base));
    let metrics = terrain_tests::scale::get_text(&format!("{}/metrics", remote.base));
    let gets = metric(&metrics, "store_gets_total");
    let asked = metric(&metrics, "blob_cache_requests_total");
    // Every body but the patch index's, which is read whole at open and held.
    let from_store = urls.len() - usize::from(db.manifest().patches.is_some());
    assert_eq!(asked as usize, from_store, "{metrics}");
    assert!(gets >= 1.0 && gets <= asked, "{metrics}");
    println!(
        "{test}: {} URLs, {bytes} bytes, identical from the directory and from the store ({gets} GETs)",
        urls.len()
    );
}

/// `terrain-server build INPUT --out OUT FLAGS…` as a user runs it (web tiles included when
/// the input is georeferenced).
fn cli_build(input: &Path, out: &Path, flags: &[&str]) {
    let mut args: Vec<&OsStr> = vec![OsStr::new("build"), OsStr::new("--quiet")];
    args.extend([input.as_os_str(), OsStr::new("--out"), out.as_os_str()]);
    args.extend(flags.iter().map(OsStr::new));
    let (ok, _, stderr) = terrain_tests::data::run_binary("terrain-server", &args);
    assert!(ok, "build {}: {stderr}", input.display());
}

#[test]
fn every_tile_of_jacksboro_is_byte_identical_from_the_directory_and_from_the_store() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = tmp.path().join("db");
    cli_build(&jacksboro(), &db, &["--patches"]);
    byte_identical("jacksboro", &db, true);
}

#[test]
fn every_tile_of_puget_sound_is_byte_identical_from_the_directory_and_from_the_store() {
    let test = "puget_sound_from_the_store";
    let Some(png) = kit_file(test, "puget_sound_1k/ps_height_1k.png") else {
        return;
    };
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = tmp.path().join("db");
    cli_build(&png, &db, &[]);
    byte_identical(test, &db, false);
}

/// The topology of `docker-compose.yml`, on loopback: a store, the jacksboro database
/// published to it, two replicas and nginx in front.
struct Topology {
    store: ObjectStore,
    replicas: Vec<Replica>,
    nginx: Nginx,
    manifest: Manifest,
}

fn topology(tools: &terrain_tests::scale::Tools, name: &str) -> Topology {
    let store = ObjectStore::start(tools);
    let dir = database(&jacksboro(), Options::Defaults);
    let url = publish(&store, &dir, name);
    let replicas: Vec<Replica> = (0..2)
        .map(|_| Replica::start(&store, &url, &["--reload-poll", "0.2"]))
        .collect();
    let nginx = Nginx::start(tools, &replicas.iter().map(|r| r.addr).collect::<Vec<_>>());
    let manifest = TileDb::open(&dir, Verify::SizesOnly)
        .expect("opens")
        .manifest()
        .clone();
    Topology {
        store,
        replicas,
        nginx,
        manifest,
    }
}

/// A flight that pages jacksboro in room for about three level-0 tiles, so that tiles are
/// evicted and asked for again: paced in wall-clock time, through `base`.
fn tight_flight(base: &str, out: &Path, manifest: &Manifest) -> FlightArgs {
    let budget = terrain_tests::data::budget_for_level_0_tiles(manifest, 3);
    let mut stream = StreamArgs::new(base, Some(MemorySize(budget)));
    stream.concurrency = 2;
    FlightArgs {
        no_render: true,
        ..FlightArgs::new(stream, out)
    }
}

/// No tile given up, the same content throughout, and the square whole at the still end.
fn assert_nothing_lost(summary: &FlightSummary) {
    assert!(summary.unavailable.is_empty(), "{summary}");
    assert!(summary.content_changes.is_empty(), "{summary}");
    assert!(summary.final_complete_belts >= 1, "{summary}");
    assert!(summary.tiles_fetched >= 1, "{summary}");
}

#[test]
fn replicas_behind_nginx_share_the_requests_and_a_replica_killed_mid_flight_loses_nothing() {
    let Some(tools) = tools("replicas behind nginx") else {
        return;
    };
    let mut t = topology(&tools, "replicas");
    let cv = t.manifest.content_version.clone();

    // A MISS, then a HIT, keyed on the URL; the second never reaches a replica.
    let path = routes::heights(&cv, TileId::new(0, 0));
    let (status, first, body) = get(&format!("{}{path}", t.nginx.base));
    assert_eq!(status, 200);
    assert_eq!(first["x-cache-status"], "MISS");
    let (_, second, again) = get(&format!("{}{path}", t.nginx.base));
    assert_eq!(second["x-cache-status"], "HIT");
    assert_eq!(body, again);
    // The manifest (`Cache-Control: no-cache`) is never answered from nginx's cache.
    for _ in 0..2 {
        let (status, headers, _) = get(&format!("{}{}", t.nginx.base, routes::MANIFEST));
        assert_eq!(status, 200);
        assert_ne!(headers["x-cache-status"], "HIT");
    }

    // Misses spread over both replicas (nginx's round robin).
    let cv_tiles: Vec<String> = t
        .manifest
        .tiles()
        .map(|(id, _)| routes::texture(&cv, id, 0))
        .collect();
    let mut upstreams = std::collections::BTreeSet::new();
    for path in &cv_tiles {
        let (status, headers, _) = get(&format!("{}{path}", t.nginx.base));
        assert_eq!(status, 200, "{path}");
        upstreams.insert(headers["x-upstream"].to_str().expect("ascii").to_string());
    }
    assert_eq!(
        upstreams.len(),
        2,
        "every miss went to one replica: {upstreams:?}"
    );
    let served: Vec<f64> = t
        .replicas
        .iter()
        .map(|r| r.metric("blob_cache_requests_total"))
        .collect();
    assert!(served.iter().all(|n| *n >= 1.0), "{served:?}");

    // A flight through nginx; one replica killed once the flight is under way.
    let tmp = tempfile::tempdir().expect("tempdir");
    let flight = tight_flight(&t.nginx.base, &tmp.path().join("flight"), &t.manifest);
    let flying = std::thread::spawn(move || runtime().block_on(fly(&flight)));
    let started = Instant::now();
    let blobs = |t: &Topology| -> f64 {
        t.replicas
            .iter()
            .map(|r| r.metric("blob_cache_requests_total"))
            .sum()
    };
    let before = blobs(&t);
    // Under way: a few tiles through nginx to the replicas.
    while blobs(&t) < before + 3.0 {
        assert!(
            started.elapsed() < Duration::from_secs(30),
            "the flight sent nothing"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(!flying.is_finished(), "the replica must die mid-flight");
    let gets_of_the_killed = t.replicas[0].metric("store_gets_total");
    t.replicas[0].kill();
    let killed_at = started.elapsed();
    let survivor_before = t.replicas[1].metric("blob_cache_requests_total");
    let summary = flying
        .join()
        .expect("flight thread")
        .expect("the flight ends");
    assert_nothing_lost(&summary);
    assert_eq!(
        summary.failures, 0,
        "nginx retried on the live replica: {summary}"
    );
    // Not even a retry: nginx took every request the dead replica would have had to the
    // live one, and answered no error.
    assert_eq!(
        summary.retries, 0,
        "the client saw the dead replica: {summary}"
    );
    let errors: Vec<String> = t
        .nginx
        .access_log()
        .into_iter()
        .filter(|l| l.split(' ').nth(2).is_some_and(|s| s.starts_with('5')))
        .collect();
    assert!(errors.is_empty(), "nginx answered errors: {errors:?}");
    let survivor_after = t.replicas[1].metric("blob_cache_requests_total");
    assert!(
        survivor_after > survivor_before,
        "the live replica answered after the kill"
    );
    // GETs to the store against client requests: nginx's cache and the replicas' own
    // keep the store's share below one GET a request.
    let gets = gets_of_the_killed + t.replicas[1].metric("store_gets_total");
    let log = t.nginx.access_log();
    let hits = log.iter().filter(|l| l.starts_with("HIT ")).count();
    assert!(
        gets >= 1.0 && gets < log.len() as f64,
        "{gets} GETs for {} requests",
        log.len()
    );
    println!(
        "replica killed at {:.2} s of the flight; the client fetched {} tiles, 0 failures, {} retries; \
         {} client requests through nginx ({hits} cache hits), {gets} GETs to the store",
        killed_at.as_secs_f64(),
        summary.tiles_fetched,
        summary.retries,
        log.len()
    );
    drop(t.store);
}

#[test]
fn with_the_store_down_cached_tiles_are_served_and_the_rest_fail_cleanly_until_it_returns() {
    let Some(tools) = tools("store outage") else {
        return;
    };
    let mut t = topology(&tools, "outage");
    let cv = t.manifest.content_version.clone();
    let ids: Vec<TileId> = t.manifest.tiles().map(|(id, _)| id).collect();
    // Half the heights cached by nginx, the other half never asked.
    let (cached, uncached) = ids.split_at(ids.len() / 2);
    for id in cached {
        let (status, _, _) = get(&format!("{}{}", t.nginx.base, routes::heights(&cv, *id)));
        assert_eq!(status, 200);
    }

    t.store.stop();
    for id in cached {
        let (status, headers, _) = get(&format!("{}{}", t.nginx.base, routes::heights(&cv, *id)));
        assert_eq!(status, 200, "cached tile {id} with the store down");
        assert_eq!(headers["x-cache-status"], "HIT");
    }
    let path = routes::heights(&cv, uncached[0]);
    let (status, headers, body) = get(&format!("{}{path}", t.nginx.base));
    let text = String::from_utf8_lossy(&body);
    assert_eq!(status, 503, "{text}");
    assert!(text.contains("store is unavailable"), "{text}");
    assert_eq!(headers["retry-after"], "1");
    assert_eq!(headers["cache-control"], "no-store");
    for replica in &t.replicas {
        let (status, _, _) = get(&format!("{}/healthz", replica.base));
        assert_eq!(status, 200, "a replica stays up while its store is down");
    }
    let errors: f64 = t
        .replicas
        .iter()
        .map(|r| r.metric("store_get_errors_total"))
        .sum();
    assert!(errors >= 1.0);

    // A flight that starts during the outage and goes on after the store returns.
    let tmp = tempfile::tempdir().expect("tempdir");
    let flight = tight_flight(&t.nginx.base, &tmp.path().join("flight"), &t.manifest);
    let flying = std::thread::spawn(move || runtime().block_on(fly(&flight)));
    std::thread::sleep(Duration::from_millis(1500));
    assert!(!flying.is_finished(), "the store must return mid-flight");
    let resuming = Instant::now();
    t.store.resume();
    let resumed_in = resuming.elapsed();
    let summary = flying
        .join()
        .expect("flight thread")
        .expect("the flight ends");
    assert_nothing_lost(&summary);
    // The flight met the outage: some request failed, and was asked again.
    assert!(summary.failures + summary.retries >= 1, "{summary}");
    let (status, headers, _) = get(&format!("{}{path}", t.nginx.base));
    assert_eq!(status, 200, "recovered");
    assert!(headers["x-cache-status"] == "MISS" || headers["x-cache-status"] == "HIT");

    let requests = summary.tiles_fetched;
    let gets: f64 = t
        .replicas
        .iter()
        .map(|r| r.metric("store_gets_total"))
        .sum();
    println!(
        "outage: the store took {:.1} s to return; {} client failures retried, {} tiles fetched, nothing given up; \
         {gets} GETs to the store for the whole test",
        resumed_in.as_secs_f64(),
        summary.failures,
        requests
    );
}

#[test]
fn a_version_published_later_is_served_without_a_restart_and_the_one_before_still_answers() {
    let Some(tools) = tools("store reload") else {
        return;
    };
    let store = ObjectStore::start(&tools);
    let tmp = tempfile::tempdir().expect("tempdir");
    let first_dir = database(&jacksboro(), Options::Defaults);
    let url = publish(&store, &first_dir, "reload");
    let replica = Replica::start(&store, &url, &["--reload-poll", "0.1"]);
    // No poll: this one reads the pointer again on SIGHUP only (`systemctl reload`).
    let on_signal = Replica::start(&store, &url, &["--reload-poll", "0"]);
    let first = TileDb::open(&first_dir, Verify::SizesOnly).expect("opens");
    let first_cv = first.manifest().content_version.clone();
    assert_eq!(served_version(&replica.base), first_cv);

    // A second version whose packs are in the store but whose manifest is not (a publish
    // cut short): not visible.
    let second_dir = tmp.path().join("second");
    let options = terrain_server::build::BuildOptions {
        height_offset: Some(25.0),
        ..terrain_server::build::BuildOptions::new(jacksboro(), &second_dir)
    };
    let second_cv = terrain_server::build::build(
        &options,
        &|_, _| {},
        &std::sync::atomic::AtomicBool::new(false),
    )
    .expect("builds")
    .manifest
    .content_version;
    assert_ne!(first_cv, second_cv);
    let parsed = terrain_server::store::StoreUrl::parse(&url).expect("url");
    let client = terrain_server::store::connect_with(&parsed, &store.env()).expect("client");
    runtime().block_on(async {
        use object_store::ObjectStoreExt as _;
        let pack = std::fs::read(second_dir.join("heights.pack")).expect("pack");
        client
            .put(
                &parsed.object(&second_cv, "heights.pack"),
                object_store::PutPayload::from(pack),
            )
            .await
            .expect("put");
    });
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(
        served_version(&replica.base),
        first_cv,
        "a half-published version"
    );

    // Published whole: served within a few polls, and the first still answers its URLs.
    let out = server_command(
        &store,
        &[
            OsStr::new("publish"),
            second_dir.as_os_str(),
            OsStr::new(&url),
            OsStr::new("--quiet"),
        ],
    );
    assert!(out.contains(&second_cv), "{out}");
    let started = Instant::now();
    while served_version(&replica.base) != second_cv {
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "never served: {}",
            replica.log()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(
        served_version(&on_signal.base),
        first_cv,
        "no poll, no signal"
    );
    on_signal.signal("-HUP");
    let started = Instant::now();
    while served_version(&on_signal.base) != second_cv {
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "never served after SIGHUP: {}",
            on_signal.log()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let tile = TileId::new(0, 0);
    for cv in [&first_cv, &second_cv] {
        let (status, _, _) = get(&format!("{}{}", replica.base, routes::heights(cv, tile)));
        assert_eq!(status, 200, "version {cv}");
    }
    let (status, _, _) = get(&format!(
        "{}{}",
        replica.base,
        routes::heights("0123456789abcdef", tile)
    ));
    assert_eq!(status, 404);
    assert_eq!(replica.metric("database_reloads_total"), 1.0);

    // Publishing a version again writes nothing: a version once complete is never modified.
    let again = server_command(
        &store,
        &[
            OsStr::new("publish"),
            first_dir.as_os_str(),
            OsStr::new(&url),
            OsStr::new("--quiet"),
        ],
    );
    assert!(again.contains("was already there"), "{again}");
}

fn served_version(base: &str) -> String {
    let (status, _, body) = get(&format!("{base}{}", routes::MANIFEST));
    assert_eq!(status, 200);
    let manifest = Manifest::from_json(&body).expect("manifest");
    manifest.content_version
}

#[test]
fn a_pmtiles_export_to_the_store_is_the_archive_written_to_a_file() {
    let Some(tools) = tools("pmtiles export to the store") else {
        return;
    };
    let store = ObjectStore::start(&tools);
    let tmp = tempfile::tempdir().expect("tempdir");
    let db = tmp.path().join("db");
    cli_build(&jacksboro(), &db, &[]);
    let file = tmp.path().join("terrarium.pmtiles");
    let url = format!("s3://{BUCKET}/exports/terrarium.pmtiles");
    for out in [file.as_os_str(), OsStr::new(&url)] {
        let said = server_command(
            &store,
            &[
                OsStr::new("export"),
                db.as_os_str(),
                OsStr::new("--pmtiles"),
                out,
            ],
        );
        assert!(said.starts_with("wrote "), "{said}");
    }
    let parsed = terrain_server::store::StoreUrl::parse(&url).expect("url");
    let client = terrain_server::store::connect_with(&parsed, &store.env()).expect("client");
    let stored = runtime().block_on(async {
        use object_store::ObjectStoreExt as _;
        client
            .get(&parsed.prefix)
            .await
            .expect("get")
            .bytes()
            .await
            .expect("bytes")
    });
    let written = std::fs::read(&file).expect("archive");
    assert!(written.len() > 1000);
    assert!(stored[..] == written[..], "the stored archive differs");
    // An existing object is not replaced without --force.
    let refused =
        std::process::Command::new(terrain_tests::data::workspace_binary("terrain-server"))
            .args(["export", &db.to_string_lossy(), "--pmtiles", &url])
            .envs(store.env())
            .output()
            .expect("runs");
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("exists; give --force"), "{stderr}");
}

#[test]
fn an_object_changed_in_the_store_after_a_replica_opened_it_is_a_500_never_its_bytes() {
    let Some(tools) = tools("a changed object") else {
        return;
    };
    let store = ObjectStore::start(&tools);
    let dir = database(&jacksboro(), Options::Defaults);
    let url = publish(&store, &dir, "changed");
    let replica = Replica::start(&store, &url, &["--cache-bytes", "0"]);
    let db = TileDb::open(&dir, Verify::SizesOnly).expect("opens");
    let cv = db.manifest().content_version.clone();
    let tile = TileId::new(0, 0);
    let texture = format!("{}{}", replica.base, routes::texture(&cv, tile, 0));
    let (status, _, before) = get(&texture);
    assert_eq!(status, 200);

    // Every byte of the textures pack flipped, the size kept: what a store that lost or
    // rewrote an object would return.
    let parsed = terrain_server::store::StoreUrl::parse(&url).expect("url");
    let client = terrain_server::store::connect_with(&parsed, &store.env()).expect("client");
    let flipped: Vec<u8> = std::fs::read(dir.join("textures.pack"))
        .expect("pack")
        .iter()
        .map(|b| !b)
        .collect();
    runtime().block_on(async {
        use object_store::ObjectStoreExt as _;
        client
            .put(
                &parsed.object(&cv, "textures.pack"),
                object_store::PutPayload::from(flipped),
            )
            .await
            .expect("put");
    });
    let (status, _, body) = get(&texture);
    let text = String::from_utf8_lossy(&body);
    assert_eq!(status, 500, "{text}");
    assert!(
        text.contains("textures.pack in the object store changed after the server opened it"),
        "{text}"
    );
    assert_ne!(body, before);
    let (status, _, _) = get(&format!("{}{}", replica.base, routes::heights(&cv, tile)));
    assert_eq!(status, 200, "the heights pack is untouched");
    assert!(replica.log().contains("changed after the server opened it"));
}

#[test]
fn a_build_written_to_the_store_is_served_as_the_same_version_a_local_build_makes() {
    let Some(tools) = tools("build to the store") else {
        return;
    };
    let store = ObjectStore::start(&tools);
    let tmp = tempfile::tempdir().expect("tempdir");
    let url = format!("s3://{BUCKET}/built/jacksboro");
    let said = server_command(
        &store,
        &[
            OsStr::new("build"),
            jacksboro().as_os_str(),
            OsStr::new("--out"),
            OsStr::new(&url),
            OsStr::new("--quiet"),
        ],
    );
    assert!(
        said.contains("published s3://tiles/built/jacksboro"),
        "{said}"
    );
    let local = tmp.path().join("db");
    cli_build(&jacksboro(), &local, &[]);
    let version = TileDb::open(&local, Verify::SizesOnly)
        .expect("opens")
        .manifest()
        .content_version
        .clone();
    assert!(said.contains(&version), "{said}");
    // The build's temporary directory is gone.
    let leftovers: Vec<_> = std::fs::read_dir(std::env::temp_dir())
        .expect("temp dir")
        .flatten()
        .filter(|e| {
            e.file_name()
                .to_string_lossy()
                .starts_with("terrain-build-")
                && e.path().join("db").join("manifest.json").exists()
                && std::fs::read_to_string(e.path().join("db").join("manifest.json"))
                    .is_ok_and(|m| m.contains(&version))
        })
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
    let replica = Replica::start(&store, &url, &[]);
    assert_eq!(served_version(&replica.base), version);

    // A location that holds nothing: serve refuses it by name.
    let output =
        std::process::Command::new(terrain_tests::data::workspace_binary("terrain-server"))
            .args([
                "serve",
                &format!("s3://{BUCKET}/nothing/here"),
                "--addr",
                "127.0.0.1:0",
            ])
            .envs(store.env())
            .output()
            .expect("runs");
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr
            .contains("s3://tiles/nothing/here holds no database: nothing/here/current is missing"),
        "{stderr}"
    );
}

/// Region jobs that upload to the store (`build --region I/N --out s3://…`), merged from
/// the store into the store (`merge s3://… --out s3://…`): the published version is the
/// one a local build makes, and the merge's scratch files are gone. A job whose record is
/// not in the store (killed while uploading) is a missing job to the merge.
#[test]
fn region_jobs_written_to_the_store_merge_into_the_version_one_build_makes() {
    let Some(tools) = tools("region jobs in the store") else {
        return;
    };
    let store = ObjectStore::start(&tools);
    let tmp = tempfile::tempdir().expect("tempdir");
    let jobs = format!("s3://{BUCKET}/jobs/jacksboro");
    let flags = ["--tile-size", "33"];
    for i in 0..3 {
        let region = format!("{i}/3");
        let said = server_command(
            &store,
            &[
                &[
                    OsStr::new("build"),
                    jacksboro().as_os_str(),
                    OsStr::new("--region"),
                    OsStr::new(&region),
                    OsStr::new("--out"),
                    OsStr::new(&jobs),
                    OsStr::new("--quiet"),
                ][..],
                &flags.map(OsStr::new),
            ]
            .concat(),
        );
        assert!(
            said.contains(&format!("region {region} done: {jobs}/job-{i}-of-3"))
                && said.contains("  uploaded "),
            "{said}"
        );
    }
    let local = tmp.path().join("db");
    cli_build(&jacksboro(), &local, &flags);
    let version = TileDb::open(&local, Verify::SizesOnly)
        .expect("opens")
        .manifest()
        .content_version
        .clone();
    let url = format!("s3://{BUCKET}/merged/jacksboro");
    let merge = |out: &str| {
        std::process::Command::new(terrain_tests::data::workspace_binary("terrain-server"))
            .args(["merge", &jobs, "--out", out, "--quiet"])
            .envs(store.env())
            .output()
            .expect("runs")
    };
    let output = merge(&url);
    let said = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{said}{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(
        said.contains("published s3://tiles/merged/jacksboro"),
        "{said}"
    );
    assert!(
        said.contains(&version),
        "one build's version {version}: {said}"
    );
    let replica = Replica::start(&store, &url, &[]);
    assert_eq!(served_version(&replica.base), version);
    let leftovers: Vec<_> = std::fs::read_dir(std::env::temp_dir())
        .expect("temp dir")
        .flatten()
        .filter(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            name.starts_with("terrain-merge-jobs-") || name.starts_with("terrain-region-")
        })
        .filter(|e| std::fs::read_dir(e.path()).is_ok_and(|mut d| d.next().is_some()))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");

    // Region 1's record gone, as a job killed while it uploads leaves it.
    let runtime = runtime();
    runtime.block_on(async {
        use object_store::ObjectStoreExt as _;
        let client = terrain_server::store::connect_with(
            &terrain_server::store::StoreUrl::parse(&jobs).expect("url"),
            &store.env(),
        )
        .expect("connects");
        client
            .delete(&object_store::path::Path::from(
                "jobs/jacksboro/job-1-of-3/job.json",
            ))
            .await
            .expect("deletes");
    });
    let output = merge(tmp.path().join("again").to_str().expect("utf-8"));
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("missing region job(s) 1/3"), "{stderr}");
}
