//! A tile database in an object store (S3 and the stores that speak its API), read and
//! written through the `object_store` crate.
//!
//! A location `s3://bucket/prefix` holds any number of content versions and one pointer:
//!
//! ```text
//! prefix/current                              the content version served (its text, one line)
//! prefix/v/<content_version>/manifest.json    a version's files, as in a directory (crate::db)
//! prefix/v/<content_version>/heights.pack
//! prefix/v/<content_version>/textures.pack    (and patches.pack, web.pack when built)
//! ```
//!
//! **Invariants.**
//! - A version is written packs first, manifest last, pointer after: a reader that follows
//!   the pointer (or finds a manifest) finds every pack of that version complete. S3 makes
//!   each PUT atomic, so the pointer is either the old version or the new one.
//! - A version is never written again once its manifest exists ([`publish`] skips it), and
//!   nothing deletes one: a server still serving an old version, and every cache holding
//!   its URLs, keeps finding its bytes.
//! - Credentials, region and endpoint come from the usual `AWS_*` environment variables
//!   (`AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_REGION`, `AWS_ENDPOINT`,
//!   `AWS_ALLOW_HTTP` for a store on plain HTTP), read by `object_store`, which also retries
//!   failed requests with backoff.
//!
//! A server on a store reads the manifest and the pack indexes once at open, the heights
//! pack once as a stream to learn where each texture lies, and then every blob by a ranged
//! GET ([`crate::db::StoredBlob::fetch`]) through a bounded cache of hot blobs ([`BlobCache`]).

use bytes::Bytes;
use futures_util::StreamExt as _;
use object_store::ClientConfigKey;
use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey};
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt as _, PutPayload, RetryConfig, WriteMultipart};
use prometheus_client::metrics::counter::Counter;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;
use thiserror::Error;

/// The pointer object's name under a location's prefix.
pub const POINTER: &str = "current";
/// Parts of a multipart upload: S3's minimum part is 5 MiB.
const PART_BYTES: usize = 8 * 1024 * 1024;

/// Where a database is: a local directory or a location in an object store.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Location {
    Dir(PathBuf),
    Store(StoreUrl),
}

impl Location {
    /// `s3://bucket[/prefix]` is a store; anything else is a directory.
    pub fn parse(text: &str) -> Result<Location, String> {
        if text.contains("://") {
            StoreUrl::parse(text).map(Location::Store)
        } else {
            Ok(Location::Dir(PathBuf::from(text)))
        }
    }
}

impl std::fmt::Display for Location {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Location::Dir(dir) => write!(f, "{}", dir.display()),
            Location::Store(url) => write!(f, "{url}"),
        }
    }
}

/// `s3://bucket/prefix`, checked: a bucket name, and a prefix of plain path segments.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StoreUrl {
    pub bucket: String,
    /// The prefix under the bucket (empty for the bucket's root).
    pub prefix: ObjectPath,
}

impl StoreUrl {
    pub fn parse(text: &str) -> Result<StoreUrl, String> {
        // Checked on the text: URL parsing would quietly resolve them away.
        if text.split('/').any(|s| s == "." || s == "..") {
            return Err(format!(
                "{text:?}: the prefix may not hold . or .. segments"
            ));
        }
        let url = url::Url::parse(text).map_err(|e| format!("{text:?} is not a URL: {e}"))?;
        if url.scheme() != "s3" {
            return Err(format!(
                "{text:?}: only s3://bucket/prefix object-store locations are supported (or a directory path)"
            ));
        }
        let bucket = url
            .host_str()
            .filter(|b| !b.is_empty())
            .ok_or_else(|| format!("{text:?} names no bucket: expected s3://bucket/prefix"))?
            .to_string();
        if url.query().is_some() || url.fragment().is_some() {
            return Err(format!("{text:?}: a location takes no query or fragment"));
        }
        let segments: Vec<&str> = url.path().split('/').filter(|s| !s.is_empty()).collect();
        let prefix = ObjectPath::parse(segments.join("/"))
            .map_err(|e| format!("{text:?}: not a usable prefix: {e}"))?;
        Ok(StoreUrl { bucket, prefix })
    }

    /// The pointer object naming the version served.
    pub fn pointer(&self) -> ObjectPath {
        self.prefix.clone().join(POINTER)
    }

    /// The object of one file (`manifest.json`, a pack) of one version.
    pub fn object(&self, version: &str, file: &str) -> ObjectPath {
        self.prefix.clone().join("v").join(version).join(file)
    }
}

impl std::fmt::Display for StoreUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.prefix.as_ref().is_empty() {
            write!(f, "s3://{}", self.bucket)
        } else {
            write!(f, "s3://{}/{}", self.bucket, self.prefix)
        }
    }
}

/// Why a store could not be reached, read or written.
#[derive(Debug, Error)]
pub enum StoreError {
    #[error("cannot configure the object store for {url}: {source}")]
    Configure {
        url: String,
        source: object_store::Error,
    },
    #[error(
        "{url} holds no database: {pointer} is missing (publish one with `terrain-server build --out {url}`)"
    )]
    NoPointer { url: String, pointer: String },
    #[error("{what} in the object store: {source}")]
    Store {
        what: String,
        source: object_store::Error,
    },
    #[error("{pointer} is not a content version: {text:?}")]
    BadPointer { pointer: String, text: String },
    #[error("cannot read {path}: {source}")]
    Local {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// A client of the store at `url`'s bucket, configured from the `AWS_*` environment, with
/// retries bounded so that a store that is down fails a request in seconds, not minutes.
pub fn connect(url: &StoreUrl) -> Result<Arc<dyn ObjectStore>, StoreError> {
    connect_with(url, &[])
}

/// [`connect`], with `AWS_*` settings given here taking the place of the environment's
/// (as `("AWS_ENDPOINT", "http://…")`); an unknown name is an error.
pub fn connect_with(
    url: &StoreUrl,
    settings: &[(&str, String)],
) -> Result<Arc<dyn ObjectStore>, StoreError> {
    let retry = RetryConfig {
        max_retries: 3,
        retry_timeout: Duration::from_secs(10),
        ..RetryConfig::default()
    };
    let mut builder = AmazonS3Builder::from_env()
        .with_bucket_name(&url.bucket)
        .with_retry(retry);
    for (name, value) in settings {
        let key: AmazonS3ConfigKey =
            name.to_ascii_lowercase()
                .parse()
                .map_err(|source| StoreError::Configure {
                    url: url.to_string(),
                    source,
                })?;
        builder = builder.with_config(key, value);
    }
    // Timeouts short enough that a store that is down is noticed in seconds, unless the
    // environment sets them (AWS_CONNECT_TIMEOUT, AWS_TIMEOUT).
    for (variable, key, value) in [
        ("AWS_CONNECT_TIMEOUT", ClientConfigKey::ConnectTimeout, "2s"),
        ("AWS_TIMEOUT", ClientConfigKey::Timeout, "30s"),
    ] {
        if std::env::var_os(variable).is_none() && !settings.iter().any(|(n, _)| n == &variable) {
            builder = builder.with_config(AmazonS3ConfigKey::Client(key), value);
        }
    }
    let store = builder.build().map_err(|source| StoreError::Configure {
        url: url.to_string(),
        source,
    })?;
    Ok(Arc::new(store))
}

/// The content version `url`'s pointer names.
pub async fn current_version(
    store: &dyn ObjectStore,
    url: &StoreUrl,
) -> Result<String, StoreError> {
    let pointer = url.pointer();
    let bytes = match store.get(&pointer).await {
        Ok(got) => got.bytes().await,
        Err(e) => Err(e),
    };
    let bytes = match bytes {
        Ok(bytes) => bytes,
        Err(object_store::Error::NotFound { .. }) => {
            return Err(StoreError::NoPointer {
                url: url.to_string(),
                pointer: pointer.to_string(),
            });
        }
        Err(source) => {
            return Err(StoreError::Store {
                what: format!("reading {pointer}"),
                source,
            });
        }
    };
    let text = String::from_utf8_lossy(&bytes).trim().to_string();
    let valid = !text.is_empty()
        && text.len() <= 128
        && text
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
    if !valid {
        return Err(StoreError::BadPointer {
            pointer: pointer.to_string(),
            text: text.chars().take(80).collect(),
        });
    }
    Ok(text)
}

/// Arguments of `terrain-server publish`.
#[derive(clap::Args, Debug)]
pub struct PublishArgs {
    /// A finished database directory (it is opened and every hash checked first).
    pub db: PathBuf,
    /// Where to publish it: `s3://bucket/prefix`.
    #[arg(value_name = "s3://BUCKET/PREFIX", value_parser = StoreUrl::parse)]
    pub to: StoreUrl,
    /// No progress bar.
    #[arg(long, short)]
    pub quiet: bool,
}

/// `terrain-server publish`: checks the database, uploads it, moves the pointer.
pub fn run_publish_cli(args: PublishArgs) -> anyhow::Result<()> {
    use anyhow::Context as _;
    crate::db::TileDb::open(&args.db, crate::db::Verify::Hashes)
        .with_context(|| format!("cannot publish {}", args.db.display()))?;
    crate::build::publish_cli(&args.db, &args.to, args.quiet)
}

/// What [`publish`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Published {
    pub version: String,
    /// Bytes uploaded (0 when the version was already in the store).
    pub uploaded_bytes: u64,
    /// Whether the version was in the store already (its manifest present).
    pub already_there: bool,
}

/// Uploads the finished database in `dir` to `url` as its content version, then points
/// `url`'s pointer at it: packs first, the manifest last, the pointer after (module
/// invariants). A version whose manifest is already in the store is not written again.
pub async fn publish(
    store: &dyn ObjectStore,
    dir: &Path,
    url: &StoreUrl,
    progress: &dyn Fn(u64),
) -> Result<Published, StoreError> {
    let manifest_path = dir.join(crate::db::MANIFEST_FILE);
    let manifest_json = std::fs::read(&manifest_path).map_err(|source| StoreError::Local {
        path: manifest_path.clone(),
        source,
    })?;
    let manifest =
        terrain_shared::Manifest::from_json(&manifest_json).map_err(|e| StoreError::Local {
            path: manifest_path.clone(),
            source: std::io::Error::new(std::io::ErrorKind::InvalidData, e.to_string()),
        })?;
    let version = manifest.content_version.clone();
    let manifest_object = url.object(&version, crate::db::MANIFEST_FILE);
    let already_there = match store.head(&manifest_object).await {
        Ok(_) => true,
        Err(object_store::Error::NotFound { .. }) => false,
        Err(source) => {
            return Err(StoreError::Store {
                what: format!("looking for {manifest_object}"),
                source,
            });
        }
    };
    let mut uploaded = 0u64;
    if !already_there {
        for pack in [
            crate::db::HEIGHTS_PACK,
            crate::db::TEXTURES_PACK,
            crate::db::PATCHES_PACK,
            crate::db::WEB_PACK,
        ] {
            let path = dir.join(pack);
            if !path.exists() {
                continue;
            }
            uploaded += upload_file(store, &path, &url.object(&version, pack), &|n| {
                progress(uploaded + n)
            })
            .await?;
        }
        store
            .put(&manifest_object, PutPayload::from(manifest_json.clone()))
            .await
            .map_err(|source| StoreError::Store {
                what: format!("writing {manifest_object}"),
                source,
            })?;
        uploaded += manifest_json.len() as u64;
        progress(uploaded);
    }
    let pointer = url.pointer();
    store
        .put(
            &pointer,
            PutPayload::from(format!("{version}\n").into_bytes()),
        )
        .await
        .map_err(|source| StoreError::Store {
            what: format!("writing {pointer}"),
            source,
        })?;
    Ok(Published {
        version,
        uploaded_bytes: uploaded,
        already_there,
    })
}

/// Uploads one file in parts (a multipart upload, aborted on error so no part is left
/// billed), reading it a part at a time: the object appears, whole, when it completes.
pub async fn upload_file(
    store: &dyn ObjectStore,
    path: &Path,
    object: &ObjectPath,
    progress: &dyn Fn(u64),
) -> Result<u64, StoreError> {
    use std::io::Read as _;
    let local = |source| StoreError::Local {
        path: path.to_path_buf(),
        source,
    };
    let remote = |source| StoreError::Store {
        what: format!("writing {object}"),
        source,
    };
    let mut file = std::fs::File::open(path).map_err(local)?;
    let upload = store.put_multipart(object).await.map_err(remote)?;
    let mut writer = WriteMultipart::new_with_chunk_size(upload, PART_BYTES);
    let mut buf = vec![0u8; PART_BYTES];
    let mut sent = 0u64;
    loop {
        let n = match file.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) => {
                let _ = writer.abort().await;
                return Err(local(e));
            }
        };
        // At most a few parts in flight: memory stays a few parts whatever the file's size.
        if let Err(e) = writer.wait_for_capacity(4).await {
            return Err(remote(e));
        }
        writer.write(&buf[..n]);
        sent += n as u64;
        progress(sent);
    }
    writer.finish().await.map_err(remote)?;
    Ok(sent)
}

/// The server's cache of hot blobs, bounded in bytes, and its counters (reported in
/// `/metrics`): in front of a store, every blob read by a ranged GET; in front of a local
/// directory, every blob read from its pack (so a hot tile costs neither a read nor a hash).
/// Keyed by a blob's content hash: identical bytes in two versions are held once, and a key
/// can never name other bytes (what is loaded is checked against it first).
pub struct BlobCache {
    cache: quick_cache::sync::Cache<String, Bytes, ByteWeight>,
    capacity: u64,
    /// Blob bodies asked for (each response body).
    pub requests: Counter,
    /// Loads on a miss: ranged GETs to a store, or reads of a local pack (a load shared by
    /// concurrent requests of the same blob counts once).
    pub loads: Counter,
    /// Loads that failed: unreachable (for a store, after its client's retries), or bytes
    /// other than their hash names.
    pub load_errors: Counter,
    /// Bytes loaded that matched their hash.
    pub loaded_bytes: Counter,
}

impl std::fmt::Debug for BlobCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BlobCache")
            .field("capacity", &self.capacity)
            .field("held", &self.cache.weight())
            .finish()
    }
}

#[derive(Clone)]
struct ByteWeight;

impl quick_cache::Weighter<String, Bytes> for ByteWeight {
    fn weight(&self, key: &String, value: &Bytes) -> u64 {
        // The key and the entry's bookkeeping count too, so small blobs cannot overrun.
        (value.len() + key.len() + 64) as u64
    }
}

impl BlobCache {
    /// A cache of at most `capacity` bytes (0 keeps nothing).
    pub fn new(capacity: u64) -> BlobCache {
        let items = (capacity / (16 * 1024)).clamp(16, 1 << 20) as usize;
        BlobCache {
            cache: quick_cache::sync::Cache::with_weighter(items, capacity.max(1), ByteWeight),
            capacity,
            requests: Counter::default(),
            loads: Counter::default(),
            load_errors: Counter::default(),
            loaded_bytes: Counter::default(),
        }
    }

    pub fn capacity(&self) -> u64 {
        self.capacity
    }

    /// Bytes held now (blobs, keys and bookkeeping).
    pub fn held(&self) -> u64 {
        self.cache.weight()
    }

    /// The blob `hash`, from the cache or, on a miss, from `load` (once for concurrent
    /// requests of the same blob), counted here for every kind of load. Only what `load`
    /// returns `Ok` is kept.
    pub async fn get_or_load<E>(
        &self,
        hash: &str,
        load: impl Future<Output = Result<Bytes, E>>,
    ) -> Result<Bytes, E> {
        self.requests.inc();
        let counted = async {
            self.loads.inc();
            let loaded = load.await;
            match &loaded {
                Ok(bytes) => self.loaded_bytes.inc_by(bytes.len() as u64),
                Err(_) => self.load_errors.inc(),
            };
            loaded
        };
        if self.capacity == 0 {
            return counted.await;
        }
        self.cache.get_or_insert_async(hash, counted).await
    }
}

/// A database's store, its cache and where its version lies: what a blob read from a
/// store needs ([`crate::db::StoredBlob::fetch`]).
#[derive(Debug)]
pub struct StoreSource {
    pub store: Arc<dyn ObjectStore>,
    pub url: StoreUrl,
    pub cache: Arc<BlobCache>,
}

impl StoreSource {
    /// Reads `len` bytes at `offset` of `object`, checked against `hash`, through the cache.
    pub async fn read(
        &self,
        object: &ObjectPath,
        offset: u64,
        len: u64,
        hash: &str,
    ) -> Result<Bytes, ReadError> {
        if len == 0 {
            // An empty range is not a valid S3 range request; an empty blob needs no GET.
            let found = terrain_shared::manifest::content_hash(&[]);
            return if found == hash {
                Ok(Bytes::new())
            } else {
                Err(ReadError::Changed {
                    object: object.to_string(),
                    reason: format!("an empty blob hashes to {found}, not {hash}"),
                })
            };
        }
        self.cache
            .get_or_load(hash, async {
                let got = self.store.get_range(object, offset..offset + len).await;
                let bytes = got.map_err(|source| ReadError::Unavailable {
                    object: object.to_string(),
                    source: Arc::new(source),
                })?;
                let found = terrain_shared::manifest::content_hash(&bytes);
                if bytes.len() as u64 != len || found != hash {
                    return Err(ReadError::Changed {
                        object: object.to_string(),
                        reason: format!(
                            "{} bytes at offset {offset} (of {len} asked) hash to {found}, not {hash}",
                            bytes.len()
                        ),
                    });
                }
                Ok(bytes)
            })
            .await
    }

    /// A whole object, streamed: `each` sees its chunks in order; an error from `each` ends
    /// the read there.
    pub async fn stream(
        &self,
        object: &ObjectPath,
        mut each: impl FnMut(Bytes) -> Result<(), crate::db::DbError>,
    ) -> Result<(), crate::db::DbError> {
        let unavailable = |source| {
            crate::db::DbError::Store(StoreError::Store {
                what: format!("reading {object}"),
                source,
            })
        };
        let got = self.store.get(object).await.map_err(unavailable)?;
        let mut stream = got.into_stream();
        while let Some(chunk) = stream.next().await {
            each(chunk.map_err(unavailable)?)?;
        }
        Ok(())
    }

    /// All of `object`, in one GET, not cached (the manifest read at open).
    pub async fn whole(&self, object: &ObjectPath) -> Result<Bytes, crate::db::DbError> {
        let unavailable = |source| {
            crate::db::DbError::Store(StoreError::Store {
                what: format!("reading {object}"),
                source,
            })
        };
        let got = self.store.get(object).await.map_err(unavailable)?;
        got.bytes().await.map_err(unavailable)
    }

    /// `len` bytes at `offset` of `object`, not cached (the indexes read at open).
    pub async fn range(
        &self,
        object: &ObjectPath,
        offset: u64,
        len: u64,
    ) -> Result<Bytes, crate::db::DbError> {
        self.store
            .get_range(object, offset..offset + len)
            .await
            .map_err(|source| {
                crate::db::DbError::Store(StoreError::Store {
                    what: format!("reading {len} bytes at {offset} of {object}"),
                    source,
                })
            })
    }

    /// The size of `object`.
    pub async fn size(&self, object: &ObjectPath) -> Result<u64, crate::db::DbError> {
        match self.store.head(object).await {
            Ok(meta) => Ok(meta.size),
            Err(source) => Err(crate::db::DbError::Store(StoreError::Store {
                what: format!("looking for {object}"),
                source,
            })),
        }
    }
}

/// Why a blob's bytes could not be read for a response.
#[derive(Debug, Clone, Error)]
pub enum ReadError {
    /// A pack of a local database changed after it was opened.
    #[error(transparent)]
    PackChanged(Arc<crate::db::PackChanged>),
    /// The store did not answer (down, unreachable, refusing): worth retrying later.
    #[error("the object store did not return {object}: {source}")]
    Unavailable {
        object: String,
        source: Arc<object_store::Error>,
    },
    /// The store returned other bytes than the database's hash names.
    #[error("{object} in the object store changed after the server opened it ({reason})")]
    Changed { object: String, reason: String },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn locations_are_directories_unless_they_are_s3_urls() {
        assert_eq!(
            Location::parse("db/jacksboro").expect("a directory"),
            Location::Dir(PathBuf::from("db/jacksboro"))
        );
        let Location::Store(url) =
            Location::parse("s3://tiles/terrain/jacksboro/").expect("a store")
        else {
            panic!("not a store");
        };
        assert_eq!(url.bucket, "tiles");
        assert_eq!(url.prefix.as_ref(), "terrain/jacksboro");
        assert_eq!(url.to_string(), "s3://tiles/terrain/jacksboro");
        assert_eq!(url.pointer().as_ref(), "terrain/jacksboro/current");
        assert_eq!(
            url.object("abc", "heights.pack").as_ref(),
            "terrain/jacksboro/v/abc/heights.pack"
        );
        let root = StoreUrl::parse("s3://tiles").expect("a bucket");
        assert_eq!(root.pointer().as_ref(), "current");
        for bad in [
            "s3://",
            "gs://tiles/x",
            "s3://tiles/a/../b",
            "s3://tiles/x?versionId=1",
        ] {
            let error = Location::parse(bad).expect_err("refused");
            assert!(error.contains(bad), "{bad}: {error}");
        }
    }
}
