//! The tile database on disk and its read side.
//!
//! A database is a directory of three files:
//!
//! ```text
//! manifest.json   the manifest (shared::Manifest), as served
//! heights.pack    every tile's tile blob (shared::tile_blob), back to back, in manifest
//!                 order (level 0 first, row-major within a level)
//! textures.pack   every tile's texture levels, coarsest first, tiles in manifest order
//! ```
//!
//! Nothing else locates a blob: a tile blob's offset is the sum of the sizes before it in
//! the manifest, and a texture's the sum of the sizes before it in the tile blobs' tables,
//! so the database describes itself and cannot disagree with an index.
//! [`TileDb::open`] checks that the sizes add up to the pack lengths and, by default,
//! that every blob matches its hash, so a damaged database is refused at start-up
//! rather than served.
//!
//! **Invariant:** a database directory is never written after the builder renames it into
//! place, which is what makes memory-mapping its packs sound. Serving a tile is a slice of
//! a map: nothing is decoded, copied or re-encoded per request.

use bytes::Bytes;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use terrain_shared::manifest::{ManifestError, content_hash};
use terrain_shared::{Blob, Manifest, TileBlob, TileId};
use thiserror::Error;

pub const MANIFEST_FILE: &str = "manifest.json";
/// In a database being built, locked by its builder for as long as it runs: a directory
/// holding it is never opened as a database, and one whose lock nobody holds was left by a
/// killed build, which the next build to the same output removes.
pub const BUILDING_LOCK: &str = "building.lock";
pub const HEIGHTS_PACK: &str = "heights.pack";
pub const TEXTURES_PACK: &str = "textures.pack";
/// The quadtree patches' bodies and index, when built ([`terrain_shared::manifest::PatchesInfo`]).
pub const PATCHES_PACK: &str = "patches.pack";
/// The web tiles (`crate::web`): every tile in the index's order, then the index.
pub const WEB_PACK: &str = "web.pack";

/// Why a database could not be opened.
#[derive(Debug, Error)]
pub enum DbError {
    #[error("cannot read {path}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(
        "{0} is a database being built, or one a killed build left (it holds {BUILDING_LOCK}); \
         serve the build's output once it has finished"
    )]
    BeingBuilt(PathBuf),
    #[error("{path} is not a usable manifest")]
    Manifest {
        path: PathBuf,
        source: ManifestError,
    },
    #[error(
        "{pack} is {found} bytes but the manifest lists {expected} bytes of blobs: the database is damaged or incomplete"
    )]
    PackSize {
        pack: PathBuf,
        expected: u64,
        found: u64,
    },
    #[error(
        "{what} of tile {id} in {pack} does not match its hash (expected {expected}, found {found}): the database is damaged"
    )]
    HashMismatch {
        pack: PathBuf,
        id: TileId,
        what: String,
        expected: String,
        found: String,
    },
    #[error("the quadtree patches in {pack} are damaged: {message}")]
    Patches { pack: PathBuf, message: String },
    #[error("the web tiles in {pack} are damaged: {message}")]
    Web { pack: PathBuf, message: String },
    #[error(transparent)]
    Store(#[from] crate::store::StoreError),
    #[error("the tile blob of tile {id} in {pack} is damaged: {source}")]
    TileBlob {
        pack: PathBuf,
        id: TileId,
        source: terrain_shared::tile_blob::TileBlobError,
    },
}

/// Whether [`TileDb::open`] hashes every blob (a full read of the packs) before serving.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verify {
    Hashes,
    SizesOnly,
}

/// One stored object ready to send: its bytes (a slice of the map, for a database opened
/// from a directory), its content hash and that hash as a strong entity tag (`"hash"`),
/// made once here rather than per request.
#[derive(Debug, Clone)]
pub struct StoredBlob {
    /// The mapped bytes of a database opened from a directory; empty for a database in an
    /// object store, whose blobs are only read with [`StoredBlob::fetch`].
    pub bytes: Bytes,
    /// The blob's length, wherever it lies.
    pub len: u64,
    pub hash: String,
    /// `None` when the hash is not a valid tag (only in a damaged manifest).
    pub etag: Option<axum::http::HeaderValue>,
    /// Where the bytes lie: what [`StoredBlob::fetch`] reads.
    place: Place,
}

/// Where a blob's bytes are read from when served.
#[derive(Debug, Clone)]
enum Place {
    /// Held in memory (an index read whole at open).
    Memory,
    /// A local pack file (kept open) and the blob's offset there.
    Local {
        pack: Arc<PackFile>,
        offset: u64,
        /// Whether the bytes read are checked against the hash: when the database was
        /// opened with [`Verify::Hashes`], so that a mismatch means the pack changed since
        /// (opened with [`Verify::SizesOnly`], as `serve --no-verify`, a damaged blob is
        /// served as it is, and the client's hash check catches it).
        check_hash: bool,
    },
    /// An object in a store, read by range through the store's cache, always checked.
    Store {
        source: Arc<crate::store::StoreSource>,
        object: Arc<object_store::path::Path>,
        offset: u64,
    },
}

/// A pack file held open by an opened database, and the cache its blobs are read through.
#[derive(Debug)]
struct PackFile {
    path: PathBuf,
    file: File,
    cache: Arc<crate::store::BlobCache>,
}

/// A pack whose file changed after the database opened (truncated, rewritten in place):
/// what a request for one of its blobs gets instead of the bytes.
#[derive(Debug, Error)]
#[error(
    "{pack} changed after the server opened it ({reason}); the server must be restarted on a finished database"
)]
pub struct PackChanged {
    pub pack: PathBuf,
    pub reason: String,
}

impl StoredBlob {
    /// The blob's bytes as they are in its pack now, read with a positioned read (never
    /// through the memory map, whose pages would raise SIGBUS past the end of a file
    /// truncated behind the server's back) and, when the database was opened checking
    /// hashes, checked against the blob's hash. A pack cut short (or, checked, rewritten)
    /// since the database opened is an error, never a dead process or the wrong bytes under
    /// the right tag.
    fn read_pack(
        &self,
        pack: &PackFile,
        offset: u64,
        check_hash: bool,
    ) -> Result<Bytes, PackChanged> {
        let changed = |reason: String| PackChanged {
            pack: pack.path.clone(),
            reason,
        };
        let mut body = vec![0u8; self.bytes.len()];
        read_exact_at(&pack.file, &mut body, offset).map_err(|e| {
            changed(format!(
                "{} bytes at offset {} could not be read: {e}",
                body.len(),
                offset
            ))
        })?;
        let found = if check_hash {
            content_hash(&body)
        } else {
            self.hash.clone()
        };
        if found != self.hash {
            return Err(changed(format!(
                "the {} bytes at offset {} hash to {found}, not {}",
                body.len(),
                offset,
                self.hash
            )));
        }
        Ok(Bytes::from(body))
    }

    /// The blob's bytes for a response, wherever they lie, through the server's cache of hot
    /// blobs: on a miss, a positioned read of a local pack ([`StoredBlob::read_pack`]) or a
    /// ranged GET of a store's object, checked against the hash before it is kept or sent.
    pub async fn fetch(&self) -> Result<Bytes, crate::store::ReadError> {
        match &self.place {
            Place::Store {
                source,
                object,
                offset,
            } => source.read(object, *offset, self.len, &self.hash).await,
            Place::Local {
                pack,
                offset,
                check_hash,
            } => {
                pack.cache
                    .get_or_load(&self.hash, async {
                        self.read_pack(pack, *offset, *check_hash)
                            .map_err(|e| crate::store::ReadError::PackChanged(Arc::new(e)))
                    })
                    .await
            }
            Place::Memory => Ok(self.bytes.clone()),
        }
    }
}

/// Reads `buf.len()` bytes at `offset`; an end of file first is `UnexpectedEof`.
#[cfg(unix)]
fn read_exact_at(file: &File, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
    std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
}

/// Reads `buf.len()` bytes at `offset`; an end of file first is `UnexpectedEof`.
#[cfg(windows)]
fn read_exact_at(file: &File, mut buf: &mut [u8], mut offset: u64) -> std::io::Result<()> {
    while !buf.is_empty() {
        match std::os::windows::fs::FileExt::seek_read(file, buf, offset)? {
            0 => return Err(std::io::ErrorKind::UnexpectedEof.into()),
            n => {
                buf = &mut buf[n..];
                offset += n as u64;
            }
        }
    }
    Ok(())
}

/// A mapped pack, or a range of one, with the open file it maps.
#[derive(Debug, Clone)]
struct MappedPack {
    map: Bytes,
    file: Arc<PackFile>,
    /// Offset of `map`'s first byte in the file.
    base: u64,
}

impl MappedPack {
    fn len(&self) -> usize {
        self.map.len()
    }

    fn slice(&self, range: impl std::ops::RangeBounds<usize>) -> MappedPack {
        let start = match range.start_bound() {
            std::ops::Bound::Included(&n) => n,
            std::ops::Bound::Excluded(&n) => n + 1,
            std::ops::Bound::Unbounded => 0,
        };
        MappedPack {
            map: self.map.slice(range),
            file: Arc::clone(&self.file),
            base: self.base + start as u64,
        }
    }
}

/// `hash` as a strong entity tag header value.
pub fn strong_etag(hash: &str) -> Option<axum::http::HeaderValue> {
    let tag = format!("\"{hash}\"");
    tag.parse::<headers::ETag>().ok()?;
    axum::http::HeaderValue::from_str(&tag).ok()
}

/// Where an opened database lies.
#[derive(Debug, Clone)]
pub enum Origin {
    Dir(PathBuf),
    Store {
        source: Arc<crate::store::StoreSource>,
        version: String,
    },
}

/// An opened, checked database. Cheap to share behind an `Arc`.
#[derive(Debug)]
pub struct TileDb {
    origin: Origin,
    /// The cache of hot blobs every blob is served through (shared with the next version
    /// opened on a reload).
    cache: Arc<crate::store::BlobCache>,
    manifest: Manifest,
    manifest_json: Bytes,
    /// The manifest gzipped once at open, served to clients that accept gzip.
    manifest_gzip: Bytes,
    manifest_hash: String,
    manifest_etag: Option<axum::http::HeaderValue>,
    heights: Vec<StoredBlob>,
    /// Per tile, its texture levels coarsest first.
    textures: Vec<Vec<StoredBlob>>,
    /// Per tile its quadtree patch, then the index, when the database has them.
    patches: Option<(Vec<StoredBlob>, StoredBlob)>,
    /// The web tiles by kind and coordinates, when the database has them.
    web: Option<std::collections::HashMap<crate::web::index::Entry, StoredBlob>>,
}

impl TileDb {
    /// Opens the database in `dir`, checking pack sizes and, with [`Verify::Hashes`], every hash.
    /// A directory holding [`BUILDING_LOCK`] is refused ([`DbError::BeingBuilt`]).
    pub fn open(dir: &Path, verify: Verify) -> Result<TileDb, DbError> {
        TileDb::open_with_cache(dir, verify, Arc::new(crate::store::BlobCache::new(0)))
    }

    /// [`TileDb::open`], its blobs served through `cache` (the server's cache of hot blobs).
    pub fn open_with_cache(
        dir: &Path,
        verify: Verify,
        cache: Arc<crate::store::BlobCache>,
    ) -> Result<TileDb, DbError> {
        if std::fs::symlink_metadata(dir.join(BUILDING_LOCK)).is_ok() {
            return Err(DbError::BeingBuilt(dir.to_path_buf()));
        }
        TileDb::open_unchecked(dir, verify, cache)
    }

    /// [`TileDb::open`] of the database this build is writing: the builder reads back what
    /// it wrote (for the web tiles) while its lock is still held.
    pub(crate) fn open_being_built(writer_dir: &Path, verify: Verify) -> Result<TileDb, DbError> {
        TileDb::open_unchecked(
            writer_dir,
            verify,
            Arc::new(crate::store::BlobCache::new(0)),
        )
    }

    fn open_unchecked(
        dir: &Path,
        verify: Verify,
        cache: Arc<crate::store::BlobCache>,
    ) -> Result<TileDb, DbError> {
        let manifest_path = dir.join(MANIFEST_FILE);
        let manifest_json = std::fs::read(&manifest_path).map_err(|source| DbError::Io {
            path: manifest_path.clone(),
            source,
        })?;
        let manifest = Manifest::from_json(&manifest_json).map_err(|source| DbError::Manifest {
            path: manifest_path.clone(),
            source,
        })?;

        let heights_path = dir.join(HEIGHTS_PACK);
        let heights_pack = map_file(&heights_path, &cache)?;
        let textures_path = dir.join(TEXTURES_PACK);
        let textures_pack = map_file(&textures_path, &cache)?;

        let heights = slice_pack(
            &heights_pack,
            &heights_path,
            manifest
                .tiles()
                .map(|(id, t)| (id, "tile blob".to_string(), t.blob())),
            verify,
        )?;
        let levels = manifest.texture.levels as usize;
        let mut texture_blobs = Vec::with_capacity(heights.len() * levels);
        for ((id, _), stored) in manifest.tiles().zip(&heights) {
            let head = tile_head(&stored.bytes, &manifest, &heights_path, id)?;
            texture_blobs.extend(
                head.texture
                    .into_iter()
                    .enumerate()
                    .map(|(level, blob)| (id, format!("texture level {level}"), blob)),
            );
        }
        let flat_textures = slice_pack(
            &textures_pack,
            &textures_path,
            texture_blobs.into_iter(),
            verify,
        )?;
        let mut flat = flat_textures.into_iter();
        let textures = (0..heights.len())
            .map(|_| flat.by_ref().take(levels).collect())
            .collect();

        let patches = match &manifest.patches {
            None => None,
            Some(info) => Some(open_patches(dir, &manifest, info, verify, &cache)?),
        };
        let web = match &manifest.web {
            None => None,
            Some(info) => Some(open_web(dir, info, verify, &cache)?),
        };
        TileDb::assemble(
            Origin::Dir(dir.to_path_buf()),
            cache,
            &manifest_path,
            manifest,
            manifest_json,
            heights,
            textures,
            patches,
            web,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn assemble(
        origin: Origin,
        cache: Arc<crate::store::BlobCache>,
        manifest_path: &Path,
        manifest: Manifest,
        manifest_json: Vec<u8>,
        heights: Vec<StoredBlob>,
        textures: Vec<Vec<StoredBlob>>,
        patches: Option<(Vec<StoredBlob>, StoredBlob)>,
        web: Option<std::collections::HashMap<crate::web::index::Entry, StoredBlob>>,
    ) -> Result<TileDb, DbError> {
        let manifest_gzip = gzip(&manifest_json).map_err(|source| DbError::Io {
            path: manifest_path.to_path_buf(),
            source,
        })?;
        Ok(TileDb {
            origin,
            cache,
            manifest_gzip: Bytes::from(manifest_gzip),
            manifest_etag: strong_etag(&content_hash(&manifest_json)),
            manifest_hash: content_hash(&manifest_json),
            manifest,
            manifest_json: Bytes::from(manifest_json),
            heights,
            textures,
            patches,
            web,
        })
    }

    /// Opens content version `version` of the database at `source`'s store location. The
    /// manifest and the patch and web indexes are read whole, the heights pack once as a
    /// stream (its tile blobs locate the textures; with [`Verify::Hashes`] each is checked
    /// on the way), and every pack's size is checked against the manifest. Blobs are then
    /// read per request ([`StoredBlob::fetch`]), each checked against its hash.
    pub async fn open_store(
        source: Arc<crate::store::StoreSource>,
        version: &str,
        verify: Verify,
    ) -> Result<TileDb, DbError> {
        let url = source.url.clone();
        let object = |file: &str| url.object(version, file);
        let shown = |file: &str| PathBuf::from(format!("{url}/v/{version}/{file}"));
        let manifest_path = shown(MANIFEST_FILE);
        let manifest_json = source.whole(&object(MANIFEST_FILE)).await?.to_vec();
        let manifest = Manifest::from_json(&manifest_json).map_err(|source| DbError::Manifest {
            path: manifest_path.clone(),
            source,
        })?;
        if manifest.content_version != version {
            return Err(DbError::Manifest {
                path: manifest_path,
                source: ManifestError::Inconsistent(format!(
                    "it is content version {}, stored as {version}",
                    manifest.content_version
                )),
            });
        }
        let store_blob =
            |object: &Arc<object_store::path::Path>, offset: u64, blob: &Blob| StoredBlob {
                bytes: Bytes::new(),
                len: blob.bytes,
                hash: blob.hash.clone(),
                etag: strong_etag(&blob.hash),
                place: Place::Store {
                    source: Arc::clone(&source),
                    object: Arc::clone(object),
                    offset,
                },
            };
        let check_size = |pack: &str, expected: u64, found: u64| {
            if expected == found {
                Ok(())
            } else {
                Err(DbError::PackSize {
                    pack: shown(pack),
                    expected,
                    found,
                })
            }
        };

        // The heights pack, streamed: each tile blob in turn, its head read for the
        // texture table, then dropped.
        let heights_object = Arc::new(object(HEIGHTS_PACK));
        let listed: Vec<(TileId, Blob)> = manifest.tiles().map(|(id, t)| (id, t.blob())).collect();
        let expected: u64 = listed.iter().map(|(_, b)| b.bytes).sum();
        check_size(HEIGHTS_PACK, expected, source.size(&heights_object).await?)?;
        let levels = manifest.texture.levels as usize;
        let mut heights = Vec::with_capacity(listed.len());
        let mut texture_blobs: Vec<(TileId, Blob)> = Vec::with_capacity(listed.len() * levels);
        let mut pending = Vec::<u8>::new();
        let mut next = 0usize;
        let mut offset = 0u64;
        let heights_path = shown(HEIGHTS_PACK);
        source
            .stream(&heights_object, |chunk| {
                pending.extend_from_slice(&chunk);
                while let Some((id, blob)) = listed.get(next)
                    && pending.len() as u64 >= blob.bytes
                {
                    let bytes: Vec<u8> = pending.drain(..blob.bytes as usize).collect();
                    if verify == Verify::Hashes {
                        let found = content_hash(&bytes);
                        if found != blob.hash {
                            return Err(DbError::HashMismatch {
                                pack: heights_path.clone(),
                                id: *id,
                                what: "tile blob".to_string(),
                                expected: blob.hash.clone(),
                                found,
                            });
                        }
                    }
                    let head = tile_head(&bytes, &manifest, &heights_path, *id)?;
                    texture_blobs.extend(head.texture.into_iter().map(|t| (*id, t)));
                    heights.push(store_blob(&heights_object, offset, blob));
                    offset += blob.bytes;
                    next += 1;
                }
                // More bytes than the manifest lists (a store answering other than its
                // HEAD said): refused at once, never held.
                if next == listed.len() && !pending.is_empty() {
                    return Err(DbError::PackSize {
                        pack: heights_path.clone(),
                        expected,
                        found: offset + pending.len() as u64,
                    });
                }
                Ok(())
            })
            .await?;
        if next != listed.len() || !pending.is_empty() {
            return Err(DbError::PackSize {
                pack: heights_path,
                expected,
                found: offset + pending.len() as u64,
            });
        }

        let textures_object = Arc::new(object(TEXTURES_PACK));
        let expected: u64 = texture_blobs.iter().map(|(_, b)| b.bytes).sum();
        check_size(
            TEXTURES_PACK,
            expected,
            source.size(&textures_object).await?,
        )?;
        let mut offset = 0u64;
        let mut flat = texture_blobs.iter().map(|(_, blob)| {
            let stored = store_blob(&textures_object, offset, blob);
            offset += blob.bytes;
            stored
        });
        let textures = (0..heights.len())
            .map(|_| flat.by_ref().take(levels).collect())
            .collect();

        // An index at the end of a pack, read whole and checked, and the bodies before it.
        let indexed = async |pack: &str, bodies_bytes: u64, index: &Blob| {
            let pack_object = Arc::new(object(pack));
            check_size(
                pack,
                bodies_bytes + index.bytes,
                source.size(&pack_object).await?,
            )?;
            let bytes = source
                .range(&pack_object, bodies_bytes, index.bytes)
                .await?;
            let found = content_hash(&bytes);
            if found != index.hash {
                return Err(DbError::HashMismatch {
                    pack: shown(pack),
                    id: TileId::at(0, 0, 0),
                    what: format!("{pack} index"),
                    expected: index.hash.clone(),
                    found,
                });
            }
            let index_blob = StoredBlob {
                len: bytes.len() as u64,
                bytes,
                hash: index.hash.clone(),
                etag: strong_etag(&index.hash),
                place: Place::Memory,
            };
            Ok::<_, DbError>((pack_object, index_blob))
        };
        let patches =
            match &manifest.patches {
                None => None,
                Some(info) => {
                    let (pack_object, index) =
                        indexed(PATCHES_PACK, info.bodies_bytes, &info.index).await?;
                    let count = manifest.tiles().count();
                    let entries = terrain_shared::quadtree::decode_index(&index.bytes, count)
                        .map_err(|e| DbError::Patches {
                            pack: shown(PATCHES_PACK),
                            message: e.to_string(),
                        })?;
                    let total: u64 = entries.iter().map(|e| u64::from(e.bytes)).sum();
                    check_size(PATCHES_PACK, info.bodies_bytes, total)?;
                    let mut offset = 0u64;
                    let bodies = entries
                        .iter()
                        .map(|e| {
                            let blob = Blob {
                                hash: e.hash_hex(),
                                bytes: u64::from(e.bytes),
                            };
                            let stored = store_blob(&pack_object, offset, &blob);
                            offset += blob.bytes;
                            stored
                        })
                        .collect();
                    Some((bodies, index))
                }
            };
        let web = match &manifest.web {
            None => None,
            Some(info) => {
                let (pack_object, index) = indexed(WEB_PACK, info.tiles_bytes, &info.index).await?;
                let entries =
                    crate::web::index::decode(&index.bytes).map_err(|e| DbError::Web {
                        pack: shown(WEB_PACK),
                        message: e.to_string(),
                    })?;
                let total: u64 = entries.iter().map(|(_, b)| b.bytes).sum();
                check_size(WEB_PACK, info.tiles_bytes, total)?;
                let mut offset = 0u64;
                Some(
                    entries
                        .into_iter()
                        .map(|(entry, blob)| {
                            let stored = store_blob(&pack_object, offset, &blob);
                            offset += blob.bytes;
                            (entry, stored)
                        })
                        .collect(),
                )
            }
        };
        TileDb::assemble(
            Origin::Store {
                source: Arc::clone(&source),
                version: version.to_string(),
            },
            Arc::clone(&source.cache),
            &manifest_path,
            manifest,
            manifest_json,
            heights,
            textures,
            patches,
            web,
        )
    }

    /// Where the database was opened from.
    pub fn origin(&self) -> &Origin {
        &self.origin
    }

    /// The cache of hot blobs it serves through.
    pub fn cache(&self) -> &Arc<crate::store::BlobCache> {
        &self.cache
    }

    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// The manifest exactly as stored, for serving.
    pub fn manifest_json(&self) -> &Bytes {
        &self.manifest_json
    }

    /// The manifest gzipped (once, when the database was opened): a large manifest costs
    /// tens of milliseconds of CPU to compress, too much to spend per request.
    pub fn manifest_gzip(&self) -> &Bytes {
        &self.manifest_gzip
    }

    /// [`Self::manifest_hash`] as a strong entity tag.
    pub fn manifest_etag(&self) -> Option<&axum::http::HeaderValue> {
        self.manifest_etag.as_ref()
    }

    /// Content hash of [`Self::manifest_json`], for its entity tag.
    pub fn manifest_hash(&self) -> &str {
        &self.manifest_hash
    }

    /// The tile blob of tile `id`, if it lies in its level's grid.
    pub fn heights(&self, id: TileId) -> Option<&StoredBlob> {
        self.heights.get(self.index(id)?)
    }

    /// The quadtree patch of tile `id`, if the database has patches and the tile exists.
    pub fn patch(&self, id: TileId) -> Option<&StoredBlob> {
        self.patches.as_ref()?.0.get(self.index(id)?)
    }

    /// The quadtree patches' index, if the database has patches.
    pub fn patch_index(&self) -> Option<&StoredBlob> {
        self.patches.as_ref().map(|p| &p.1)
    }

    /// A web tile (`crate::web`), if the database has web tiles and that one.
    pub fn web_tile(&self, entry: crate::web::index::Entry) -> Option<&StoredBlob> {
        self.web.as_ref()?.get(&entry)
    }

    /// Every web tile, in no particular order (for an export).
    pub fn web_tiles(&self) -> impl Iterator<Item = (&crate::web::index::Entry, &StoredBlob)> + '_ {
        self.web.iter().flat_map(|w| w.iter())
    }

    /// Texture `level` (0 = coarsest) of tile `id`, if both exist.
    pub fn texture(&self, id: TileId, level: u32) -> Option<&StoredBlob> {
        self.textures.get(self.index(id)?)?.get(level as usize)
    }

    fn index(&self, id: TileId) -> Option<usize> {
        self.manifest.index(id)
    }
}

/// The head of tile `id`'s blob, checked to list the manifest's texture and mask levels:
/// where its textures lie in the textures pack.
fn tile_head(
    bytes: &[u8],
    manifest: &Manifest,
    pack: &Path,
    id: TileId,
) -> Result<terrain_shared::tile_blob::TileHead, DbError> {
    let damaged = |source| DbError::TileBlob {
        pack: pack.to_path_buf(),
        id,
        source,
    };
    let head = TileBlob::head(bytes).map_err(damaged)?;
    if head.texture.len() != manifest.texture.levels as usize
        || head.mask_errors_m.len() != manifest.mask_levels as usize
    {
        return Err(damaged(
            terrain_shared::tile_blob::TileBlobError::TooManyLevels {
                mask: head.mask_errors_m.len(),
                texture: head.texture.len(),
            },
        ));
    }
    Ok(head)
}

/// Slices `patches.pack`: the index is checked against the manifest, the bodies against
/// the index's sizes (and hashes, with [`Verify::Hashes`]).
fn open_patches(
    dir: &Path,
    manifest: &Manifest,
    info: &terrain_shared::manifest::PatchesInfo,
    verify: Verify,
    cache: &Arc<crate::store::BlobCache>,
) -> Result<(Vec<StoredBlob>, StoredBlob), DbError> {
    let path = dir.join(PATCHES_PACK);
    let pack = map_file(&path, cache)?;
    let root = TileId::at(0, 0, 0);
    let body_end = info.bodies_bytes as usize;
    if pack.len() as u64 != info.bodies_bytes + info.index.bytes {
        return Err(DbError::PackSize {
            pack: path,
            expected: info.bodies_bytes + info.index.bytes,
            found: pack.len() as u64,
        });
    }
    let index = slice_pack(
        &pack.slice(body_end..),
        &path,
        std::iter::once((root, "patch index".to_string(), info.index.clone())),
        Verify::Hashes,
    )?
    .remove(0);
    let count = manifest.tiles().count();
    let entries = terrain_shared::quadtree::decode_index(&index.bytes, count).map_err(|e| {
        DbError::Patches {
            pack: path.clone(),
            message: e.to_string(),
        }
    })?;
    let bodies = slice_pack(
        &pack.slice(..body_end),
        &path,
        manifest.tiles().zip(&entries).map(|((id, _), e)| {
            (
                id,
                "quadtree patch".to_string(),
                terrain_shared::Blob {
                    hash: e.hash_hex(),
                    bytes: u64::from(e.bytes),
                },
            )
        }),
        verify,
    )?;
    Ok((bodies, index))
}

/// Slices `web.pack`: the index is checked against the manifest, the tiles against the
/// index's sizes (and hashes, with [`Verify::Hashes`]).
fn open_web(
    dir: &Path,
    info: &terrain_shared::manifest::WebInfo,
    verify: Verify,
    cache: &Arc<crate::store::BlobCache>,
) -> Result<std::collections::HashMap<crate::web::index::Entry, StoredBlob>, DbError> {
    let path = dir.join(WEB_PACK);
    let pack = map_file(&path, cache)?;
    let root = TileId::at(0, 0, 0);
    let tiles_end = info.tiles_bytes as usize;
    if pack.len() as u64 != info.tiles_bytes + info.index.bytes {
        return Err(DbError::PackSize {
            pack: path,
            expected: info.tiles_bytes + info.index.bytes,
            found: pack.len() as u64,
        });
    }
    let index = slice_pack(
        &pack.slice(tiles_end..),
        &path,
        std::iter::once((root, "web index".to_string(), info.index.clone())),
        Verify::Hashes,
    )?
    .remove(0);
    let entries = crate::web::index::decode(&index.bytes).map_err(|e| DbError::Web {
        pack: path.clone(),
        message: e.to_string(),
    })?;
    let tiles = slice_pack(
        &pack.slice(..tiles_end),
        &path,
        entries.iter().map(|(e, blob)| {
            (
                TileId::at(e.z, e.x, e.y),
                format!("web tile {:?}", e.kind),
                blob.clone(),
            )
        }),
        verify,
    )?;
    Ok(entries.into_iter().map(|(e, _)| e).zip(tiles).collect())
}

/// Maps a pack read-only, keeping the file open for [`StoredBlob::fetch`]. An empty file
/// cannot be mapped and needs no map.
#[allow(unsafe_code)]
fn map_file(path: &Path, cache: &Arc<crate::store::BlobCache>) -> Result<MappedPack, DbError> {
    let io = |source| DbError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = File::open(path).map_err(io)?;
    let map = if file.metadata().map_err(io)?.len() == 0 {
        Bytes::new()
    } else {
        // SAFETY: the map is read-only and the file belongs to a finished database, which
        // nothing writes after the builder's rename (module invariant). It is read only
        // while the database opens (sizes, hashes, indexes) and by callers in this
        // process; what is served is read with `StoredBlob::fetch`, so a file truncated
        // behind the server's back gives an error response, not a SIGBUS.
        let map = unsafe { memmap2::Mmap::map(&file) }.map_err(io)?;
        Bytes::from_owner(map)
    };
    Ok(MappedPack {
        map,
        file: Arc::new(PackFile {
            path: path.to_path_buf(),
            file,
            cache: Arc::clone(cache),
        }),
        base: 0,
    })
}

/// Cuts a pack into the blobs the manifest lists, in order, checking sizes and hashes.
fn slice_pack(
    pack: &MappedPack,
    path: &Path,
    blobs: impl Iterator<Item = (TileId, String, Blob)>,
    verify: Verify,
) -> Result<Vec<StoredBlob>, DbError> {
    let listed: Vec<_> = blobs.collect();
    let expected: u64 = listed.iter().map(|(_, _, b)| b.bytes).sum();
    if expected != pack.len() as u64 {
        return Err(DbError::PackSize {
            pack: path.to_path_buf(),
            expected,
            found: pack.len() as u64,
        });
    }
    let mut offset = 0usize;
    let mut out = Vec::with_capacity(listed.len());
    for (id, what, blob) in listed {
        let bytes = pack.map.slice(offset..offset + blob.bytes as usize);
        let place = Place::Local {
            pack: Arc::clone(&pack.file),
            offset: pack.base + offset as u64,
            check_hash: verify == Verify::Hashes,
        };
        offset += blob.bytes as usize;
        if verify == Verify::Hashes {
            let found = content_hash(&bytes);
            if found != blob.hash {
                return Err(DbError::HashMismatch {
                    pack: path.to_path_buf(),
                    id,
                    what,
                    expected: blob.hash.clone(),
                    found,
                });
            }
        }
        out.push(StoredBlob {
            bytes,
            len: blob.bytes,
            hash: blob.hash.clone(),
            etag: strong_etag(&blob.hash),
            place,
        });
    }
    Ok(out)
}

/// Removes the directories in `parent` named `prefix…` whose [`BUILDING_LOCK`] nobody
/// holds: builds to the same output that were killed (SIGKILL, a power cut) before they
/// could clean up. A directory whose lock is held (a build running now) or that has no lock
/// is left alone. Returns what was removed.
pub(crate) fn remove_abandoned_builds(parent: &Path, prefix: &str) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(parent) else {
        return Vec::new();
    };
    let mut removed = Vec::new();
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        let is_dir = entry.file_type().is_ok_and(|t| t.is_dir());
        if !name.starts_with(prefix) || !is_dir {
            continue;
        }
        let dir = entry.path();
        let Ok(lock) = File::open(dir.join(BUILDING_LOCK)) else {
            continue;
        };
        if lock.try_lock().is_ok() && std::fs::remove_dir_all(&dir).is_ok() {
            removed.push(dir);
        }
    }
    removed
}

/// Whether a database may be written at `out`: it must not exist, or, with `force`, be a
/// tile database (a real directory holding a manifest and nothing but the database's files)
/// or an empty directory. Anything else (a regular file, a symbolic link, a folder of other
/// files) is refused with what was found, so `--force` can never delete someone's data.
pub fn check_output(out: &Path, force: bool) -> Result<(), WriteError> {
    let meta = match std::fs::symlink_metadata(out) {
        Ok(meta) => meta,
        Err(error) if error.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(source) => {
            return Err(WriteError::Io {
                path: out.to_path_buf(),
                source,
            });
        }
    };
    if !force {
        return Err(WriteError::Exists(out.to_path_buf()));
    }
    let not_a_database = |found: String| WriteError::NotADatabase {
        path: out.to_path_buf(),
        found,
    };
    let kind = meta.file_type();
    if kind.is_symlink() {
        return Err(not_a_database("a symbolic link".into()));
    }
    if !kind.is_dir() {
        return Err(not_a_database(format!("a file of {} bytes", meta.len())));
    }
    let io = |source| WriteError::Io {
        path: out.to_path_buf(),
        source,
    };
    let mut names = Vec::new();
    for entry in std::fs::read_dir(out).map_err(io)? {
        names.push(
            entry
                .map_err(io)?
                .file_name()
                .to_string_lossy()
                .into_owned(),
        );
    }
    if names.is_empty() {
        return Ok(());
    }
    names.sort();
    let ours = [
        MANIFEST_FILE,
        HEIGHTS_PACK,
        TEXTURES_PACK,
        PATCHES_PACK,
        WEB_PACK,
    ];
    let others: Vec<&String> = names
        .iter()
        .filter(|n| !ours.contains(&n.as_str()))
        .collect();
    if !others.is_empty() {
        let shown: Vec<&str> = others.iter().take(3).map(|n| n.as_str()).collect();
        let more = if others.len() > 3 {
            format!(" and {} more", others.len() - 3)
        } else {
            String::new()
        };
        return Err(not_a_database(format!(
            "a directory holding {}{more}",
            shown.join(", ")
        )));
    }
    if !names.iter().any(|n| n == MANIFEST_FILE) {
        return Err(not_a_database(format!(
            "a directory with no {MANIFEST_FILE}"
        )));
    }
    Ok(())
}

/// `bytes` gzipped at the best compression: it is done once per database open.
fn gzip(bytes: &[u8]) -> std::io::Result<Vec<u8>> {
    use std::io::Write;
    let mut encoder = flate2::write::GzEncoder::new(
        Vec::with_capacity(bytes.len() / 4),
        flate2::Compression::best(),
    );
    encoder.write_all(bytes)?;
    encoder.finish()
}

/// Why a database could not be written.
#[derive(Debug, Error)]
pub enum WriteError {
    #[error("{0} already exists: pass --force to replace it")]
    Exists(PathBuf),
    #[error(
        "{0} appeared while this build ran (another build to the same output?); \
         nothing was replaced: pass --force to replace it"
    )]
    AppearedMeanwhile(PathBuf),
    #[error(
        "{path} is not a tile database ({found}); --force replaces only a tile database \
         (a directory of {MANIFEST_FILE}, {HEIGHTS_PACK} and {TEXTURES_PACK}): \
         choose another --out or remove it yourself"
    )]
    NotADatabase { path: PathBuf, found: String },
    #[error("cannot write the database at {path}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("the manifest lists {listed} bytes of {pack} but {written} were written")]
    Mismatch {
        pack: &'static str,
        listed: u64,
        written: u64,
    },
}

/// Writes a database into a hidden temporary directory beside its destination and
/// renames it into place in [`DbWriter::finish`]. Dropped unfinished (an error, a panic),
/// it removes the temporary directory: an interrupted build never leaves a directory
/// that looks like a database, and the manifest, which makes one, is written last.
///
/// Blobs must be added in manifest order (tile by tile, row-major; texture levels
/// coarsest first), the order [`TileDb::open`] reads them back in, with one freedom: the
/// builder finishes coarse tiles while it still makes level 0's, so
/// [`DbWriter::add_level_heights`] and [`DbWriter::add_level_texture`] take the pyramid
/// level. Level 0's blobs (and whatever [`DbWriter::add_heights`] and
/// [`DbWriter::add_texture`] write) go straight to the packs; each coarser level's go to
/// files of its own in the temporary directory, in row-major order, which
/// [`DbWriter::finish`] appends to the packs in level order (`copy_file_range`, no copy
/// through memory) and removes. Level 0 holds three quarters of the bytes, so only a
/// quarter is copied twice.
#[derive(Debug)]
pub struct DbWriter {
    out: PathBuf,
    force: bool,
    tmp: tempfile::TempDir,
    /// [`BUILDING_LOCK`], locked while this writer lives.
    lock: File,
    /// Directories of killed builds to the same output, removed when this one started.
    abandoned: Vec<PathBuf>,
    heights: std::io::BufWriter<File>,
    textures: std::io::BufWriter<File>,
    /// Levels 1, 2, … (index 0 is level 1), opened when first written to.
    coarser: Vec<Option<LevelFiles>>,
    heights_written: u64,
    textures_written: u64,
}

/// A coarse level's blobs until [`DbWriter::finish`] appends them to the packs.
#[derive(Debug)]
struct LevelFiles {
    heights: (PathBuf, std::io::BufWriter<File>),
    textures: (PathBuf, std::io::BufWriter<File>),
}

/// Which pack a blob goes to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pack {
    Heights,
    Textures,
}

impl DbWriter {
    /// Starts a database that will appear at `out`. Refuses an existing `out` unless
    /// `force`, and even then unless it is a tile database (see [`check_output`]).
    pub fn create(out: &Path, force: bool) -> Result<DbWriter, WriteError> {
        check_output(out, force)?;
        let io = |source| WriteError::Io {
            path: out.to_path_buf(),
            source,
        };
        let parent = match out.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&parent).map_err(io)?;
        let name = out
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let prefix = format!(".{name}.building-");
        let abandoned = remove_abandoned_builds(&parent, &prefix);
        let tmp = tempfile::Builder::new()
            .prefix(&prefix)
            .tempdir_in(&parent)
            .map_err(io)?;
        let lock = File::create(tmp.path().join(BUILDING_LOCK)).map_err(io)?;
        lock.try_lock().map_err(|e| {
            io(match e {
                std::fs::TryLockError::Error(e) => e,
                std::fs::TryLockError::WouldBlock => std::io::ErrorKind::WouldBlock.into(),
            })
        })?;
        let heights = File::create(tmp.path().join(HEIGHTS_PACK)).map_err(io)?;
        let textures = File::create(tmp.path().join(TEXTURES_PACK)).map_err(io)?;
        Ok(DbWriter {
            out: out.to_path_buf(),
            force,
            tmp,
            lock,
            abandoned,
            heights: std::io::BufWriter::new(heights),
            textures: std::io::BufWriter::new(textures),
            coarser: Vec::new(),
            heights_written: 0,
            textures_written: 0,
        })
    }

    /// Temporary directories of killed builds to the same output that this one removed
    /// when it started.
    pub fn abandoned_removed(&self) -> &[PathBuf] {
        &self.abandoned
    }

    /// The temporary directory being written (for tests of interrupted builds).
    pub fn temporary_dir(&self) -> &Path {
        self.tmp.path()
    }

    /// Appends the next tile's heights.
    pub fn add_heights(&mut self, bytes: &[u8]) -> Result<Blob, WriteError> {
        self.add(0, Pack::Heights, bytes)
    }

    /// Appends the next texture level (coarsest first within a tile).
    pub fn add_texture(&mut self, bytes: &[u8]) -> Result<Blob, WriteError> {
        self.add(0, Pack::Textures, bytes)
    }

    /// Appends the heights of the next tile of pyramid level `level`.
    pub fn add_level_heights(&mut self, level: u32, bytes: &[u8]) -> Result<Blob, WriteError> {
        self.add(level, Pack::Heights, bytes)
    }

    /// Appends the next texture level of the current tile of pyramid level `level`.
    pub fn add_level_texture(&mut self, level: u32, bytes: &[u8]) -> Result<Blob, WriteError> {
        self.add(level, Pack::Textures, bytes)
    }

    fn add(&mut self, level: u32, pack: Pack, bytes: &[u8]) -> Result<Blob, WriteError> {
        use std::io::Write;
        let io = |source| WriteError::Io {
            path: self.out.clone(),
            source,
        };
        let file = match level.checked_sub(1) {
            None => match pack {
                Pack::Heights => &mut self.heights,
                Pack::Textures => &mut self.textures,
            },
            Some(index) => {
                let index = index as usize;
                if self.coarser.len() <= index {
                    self.coarser.resize_with(index + 1, || None);
                }
                let files = match &mut self.coarser[index] {
                    Some(files) => files,
                    empty => empty.insert(LevelFiles::create(self.tmp.path(), level).map_err(io)?),
                };
                match pack {
                    Pack::Heights => &mut files.heights.1,
                    Pack::Textures => &mut files.textures.1,
                }
            }
        };
        file.write_all(bytes).map_err(io)?;
        match pack {
            Pack::Heights => self.heights_written += bytes.len() as u64,
            Pack::Textures => self.textures_written += bytes.len() as u64,
        }
        Ok(Blob::of(bytes))
    }

    /// Appends the files `heights` and `textures` to pyramid level `level`'s blobs, as if
    /// their blobs had been added one by one (a region job's tiles, [`crate::build::jobs`]);
    /// returns the bytes appended from each.
    pub fn append_level_files(
        &mut self,
        level: u32,
        heights: &Path,
        textures: &Path,
    ) -> Result<(u64, u64), WriteError> {
        use std::io::Write;
        let out = self.out.clone();
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| WriteError::Io { path, source }
        };
        let (to_heights, to_textures) = match level.checked_sub(1) {
            None => (&mut self.heights, &mut self.textures),
            Some(index) => {
                let index = index as usize;
                if self.coarser.len() <= index {
                    self.coarser.resize_with(index + 1, || None);
                }
                let files = match &mut self.coarser[index] {
                    Some(files) => files,
                    empty => {
                        empty.insert(LevelFiles::create(self.tmp.path(), level).map_err(io(&out))?)
                    }
                };
                (&mut files.heights.1, &mut files.textures.1)
            }
        };
        let mut copied = [0; 2];
        for ((from, to), n) in [(heights, to_heights), (textures, to_textures)]
            .into_iter()
            .zip(&mut copied)
        {
            to.flush().map_err(io(&out))?;
            let mut file = File::open(from).map_err(io(from))?;
            // File to file: the standard library copies with copy_file_range where it can.
            *n = std::io::copy(&mut file, to.get_mut()).map_err(io(&out))?;
        }
        self.heights_written += copied[0];
        self.textures_written += copied[1];
        Ok((copied[0], copied[1]))
    }

    /// Writes the quadtree patches' pack: the bodies in tile order, then the index.
    pub fn add_patches(&mut self, bodies: &[Vec<u8>], index: &[u8]) -> Result<(), WriteError> {
        use std::io::Write;
        let path = self.tmp.path().join(PATCHES_PACK);
        let io = |source| WriteError::Io {
            path: path.clone(),
            source,
        };
        let mut file = std::io::BufWriter::new(File::create(&path).map_err(io)?);
        for body in bodies {
            file.write_all(body).map_err(io)?;
        }
        file.write_all(index).map_err(io)?;
        let file = file.into_inner().map_err(|e| io(e.into_error()))?;
        file.sync_all().map_err(io)?;
        Ok(())
    }

    /// Appends the coarser levels to the packs and writes `manifest` into the temporary
    /// directory, which then opens as a database ([`TileDb::open`]) for what is made from
    /// the finished tiles (the web tiles); [`DbWriter::finish`] still has to follow.
    pub fn seal(&mut self, manifest: &Manifest) -> Result<&Path, WriteError> {
        self.append_levels(manifest)?;
        self.write_manifest(manifest)?;
        Ok(self.tmp.path())
    }

    fn append_levels(&mut self, manifest: &Manifest) -> Result<(), WriteError> {
        use std::io::Write;
        let listed_heights: u64 = manifest.tiles().map(|(_, t)| t.bytes).sum();
        if listed_heights != self.heights_written {
            return Err(WriteError::Mismatch {
                pack: HEIGHTS_PACK,
                listed: listed_heights,
                written: self.heights_written,
            });
        }
        let out = self.out.clone();
        let io = |source| WriteError::Io {
            path: out.clone(),
            source,
        };
        for files in std::mem::take(&mut self.coarser).into_iter().flatten() {
            files
                .append_to(&mut self.heights, &mut self.textures)
                .map_err(io)?;
        }
        for pack in [&mut self.heights, &mut self.textures] {
            pack.flush().map_err(io)?;
            pack.get_ref().sync_all().map_err(io)?;
        }
        Ok(())
    }

    fn write_manifest(&self, manifest: &Manifest) -> Result<(), WriteError> {
        use std::io::Write;
        let io = |source| WriteError::Io {
            path: self.out.clone(),
            source,
        };
        let manifest_path = self.tmp.path().join(MANIFEST_FILE);
        let mut file = File::create(&manifest_path).map_err(io)?;
        file.write_all(&manifest.to_json()).map_err(io)?;
        file.sync_all().map_err(io)?;
        Ok(())
    }

    /// Path the web tiles' pack is written to, inside the temporary directory.
    pub fn web_pack_path(&self) -> PathBuf {
        self.tmp.path().join(WEB_PACK)
    }

    /// Writes the manifest, syncs everything and renames the directory to its destination.
    pub fn finish(mut self, manifest: &Manifest) -> Result<PathBuf, WriteError> {
        self.append_levels(manifest)?;
        self.write_manifest(manifest)?;
        let out = self.out.clone();
        let io = |source| WriteError::Io {
            path: out.clone(),
            source,
        };

        // Checked again: the output may have appeared, or changed, while the build ran.
        match check_output(&out, self.force) {
            Err(WriteError::Exists(path)) => return Err(WriteError::AppearedMeanwhile(path)),
            other => other?,
        }
        // No longer being built: the lock goes before the directory takes its name.
        let lock_path = self.tmp.path().join(BUILDING_LOCK);
        let _ = self.lock.unlock();
        std::fs::remove_file(&lock_path).map_err(|source| WriteError::Io {
            path: lock_path.clone(),
            source,
        })?;
        let tmp = self.tmp.keep();
        // An existing database is moved aside first and removed only once the new one is
        // in place, so `out` holds either the old database or the new one, never a mix.
        let mut old = None;
        if self.force && std::fs::symlink_metadata(&out).is_ok() {
            let aside = tmp.with_extension("replaced");
            if let Err(source) = std::fs::rename(&out, &aside) {
                let _ = std::fs::remove_dir_all(&tmp);
                return Err(WriteError::Io { path: out, source });
            }
            old = Some(aside);
        }
        if let Err(source) = std::fs::rename(&tmp, &out) {
            let _ = std::fs::remove_dir_all(&tmp);
            if let Some(aside) = &old {
                let _ = std::fs::rename(aside, &out);
            }
            // Another build finished first: its database stays, this one is dropped.
            if old.is_none() && std::fs::symlink_metadata(&out).is_ok() {
                return Err(WriteError::AppearedMeanwhile(out));
            }
            return Err(WriteError::Io { path: out, source });
        }
        if let Some(aside) = old {
            std::fs::remove_dir_all(&aside).map_err(io)?;
        }
        Ok(out)
    }
}

impl LevelFiles {
    fn create(dir: &Path, level: u32) -> std::io::Result<LevelFiles> {
        let open = |pack: &str| -> std::io::Result<(PathBuf, std::io::BufWriter<File>)> {
            let path = dir.join(format!("{pack}.level-{level}.part"));
            let file = File::create(&path)?;
            Ok((path, std::io::BufWriter::new(file)))
        };
        Ok(LevelFiles {
            heights: open(HEIGHTS_PACK)?,
            textures: open(TEXTURES_PACK)?,
        })
    }

    /// Appends this level's blobs to the packs and removes its files.
    fn append_to(
        self,
        heights: &mut std::io::BufWriter<File>,
        textures: &mut std::io::BufWriter<File>,
    ) -> std::io::Result<()> {
        use std::io::Write;
        for ((path, part), pack) in [(self.heights, heights), (self.textures, textures)] {
            let part = part.into_inner().map_err(|e| e.into_error())?;
            drop(part);
            pack.flush()?;
            // File to file: the standard library copies with copy_file_range where it can.
            std::io::copy(&mut File::open(&path)?, pack.get_mut())?;
            std::fs::remove_file(&path)?;
        }
        Ok(())
    }
}
