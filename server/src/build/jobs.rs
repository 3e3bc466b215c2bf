//! A build split into jobs, for DEMs one machine should not build alone: `build --region
//! I/N` makes the tiles under one region as an independent process (any job runner runs
//! them: a Kubernetes Job array, Slurm, GNU parallel, a shell loop), and `merge` makes the
//! levels above them, the manifest and the web tiles, and puts the database in place. The
//! merged database is the one a single build makes, byte for byte: the same blobs in the
//! same packs, the same manifest, so the same content version (tested).
//!
//! **Regions.** The *split level* `k` is the coarsest level with at least `N` tile rows,
//! and region `I` is the `I`-th of `N` runs of consecutive tile rows of level `k`, as even
//! as they can be. A tile row of level `k` covers two tile rows of level `k - 1`, and so on
//! down to level 0, so a region owns whole tile rows of every level up to `k`, and the tiles
//! it makes need nothing from another region: a tile's decimation error and texture come
//! from its own children, its heights from rows the region reads (level 0's, plus one halo
//! row either side for computed textures).
//!
//! **A job** opens the heights as a build does: the scan, and, with voids, the passes that
//! find and fill them over every row, since a void's fill depends on all of its rim
//! wherever the region edges cut it, and a computed texture's tint on the whole raster's
//! range. Then it reads the rows of its region, makes its tiles of levels `0..=k` on all
//! cores ([`Pyramid::region`]), and writes into a hidden temporary directory in the jobs
//! directory:
//!
//! - `heights.level-J` and `textures.level-J` for each level `J <= k`: its tiles' blobs, in
//!   row-major order, as the packs hold them;
//! - `carries`: what each tile of level `k` hands its parent (its bounds, its distance from
//!   full resolution, its half-resolution errors and its texture halved;
//!   [`super::levels::Carry::write_to`]);
//! - `rows`: the rows of level `k + 1` that its level-`k` rows make, 32-bit little-endian
//!   codes (a region's last row is also the next region's first);
//! - `job.json`, last: the settings every job must share, the split, the tile records, and
//!   every file's size and BLAKE3 hash.
//!
//! The directory is then renamed `job-I-of-N`. A killed job leaves only its temporary
//! directory, removed by the next run of the same job (its lock is free then); a job run
//! again replaces its result, which is the same.
//!
//! **The merge** reads every `job.json`, refuses a missing job, a file whose size or hash
//! differs from its record, and jobs that disagree on a setting, each by name. It appends
//! the jobs' blobs level by level in row order (file to file, nothing decoded), makes the
//! levels above `k` from the rows and the carries ([`Pyramid::above`]), writes the manifest,
//! makes the web tiles from the finished pyramid as a build does, and renames the database
//! into place ([`DbWriter`]).

use super::levels::{Carry, LevelZeroTexture, Parent, Pyramid, TileContext, TileSink};
use super::{
    BuildError, BuildOptions, BuildReport, BuildWarning, ProgressFn, Stage, check_options,
    finish_database, prepare,
};
use crate::db::{DbWriter, WriteError};
use object_store::ObjectStoreExt as _;
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{BufWriter, Read as _, Write as _};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};
use terrain_shared::manifest::{self, Level, RasterSize};
use terrain_shared::{Blob, Manifest, TileRecord, heights};

/// `job.json`'s format.
pub const JOB_FORMAT: &str = "terrain-region-job/1";
/// The file a finished job writes last.
pub const JOB_FILE: &str = "job.json";

/// One region of `count`: `--region I/N`, `I` from 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Region {
    pub index: u32,
    pub count: u32,
}

impl Region {
    /// Parses `I/N` (`0 <= I < N`).
    pub fn parse(text: &str) -> Result<Region, String> {
        let bad = || format!("{text:?} is not I/N with 0 <= I < N, such as 0/4");
        let (i, n) = text.split_once('/').ok_or_else(bad)?;
        let index: u32 = i.trim().parse().map_err(|_| bad())?;
        let count: u32 = n.trim().parse().map_err(|_| bad())?;
        if count == 0 || index >= count {
            return Err(bad());
        }
        Ok(Region { index, count })
    }

    /// The directory a finished job's files are in, inside the jobs directory.
    pub fn dir_name(self) -> String {
        format!("job-{}-of-{}", self.index, self.count)
    }
}

impl std::fmt::Display for Region {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// The split level of `count` jobs over a raster of level 0, and region `index`'s tile rows
/// of it.
pub fn split(
    raster: RasterSize,
    tile_size: u32,
    region: Region,
) -> Result<(u32, std::ops::Range<u32>), BuildError> {
    let rows: Vec<u32> = manifest::level_rasters(raster, tile_size)
        .iter()
        .map(|r| super::tiles::Grid::covering(r.width, r.height, tile_size).rows)
        .collect();
    let Some(k) = rows.iter().rposition(|&r| r >= region.count) else {
        return Err(BuildError::BadOption(format!(
            "--region {region}: this raster has {} tile rows at level 0, so at most {} jobs",
            rows[0], rows[0]
        )));
    };
    let r = u64::from(rows[k]);
    let (i, n) = (u64::from(region.index), u64::from(region.count));
    let start = (i * r / n) as u32;
    let end = ((i + 1) * r / n) as u32;
    Ok((k as u32, start..end))
}

/// What every job of a split must agree on, and all the merge needs besides the tiles.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Plan {
    count: u32,
    split_level: u32,
    /// The manifest without its levels, texture bytes, content version and web tiles.
    manifest: Manifest,
    /// [`heights::Coder`]: `rans`, or `zstd` and its level.
    heights_coder: String,
    jpeg_quality: u8,
    code_range: (i32, i32),
}

/// A file a job wrote.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct FileRecord {
    bytes: u64,
    blake3: String,
}

/// `job.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct JobRecord {
    format: String,
    index: u32,
    plan: Plan,
    /// Tile rows of the split level.
    tile_rows: (u32, u32),
    /// Per level `0..=split`, the region's tiles, row-major.
    levels: Vec<Vec<TileRecord>>,
    /// Per texture level, coarsest first.
    texture_level_bytes: Vec<u64>,
    heights_bytes: u64,
    /// The first row of level `split + 1` in `rows`, and how many.
    up_rows: (u32, u32),
    /// Tiles of the split level in `carries`.
    carries: u64,
    /// Every file but this one, by name.
    files: std::collections::BTreeMap<String, FileRecord>,
    warnings: Vec<String>,
    source_bytes: u64,
    seconds: f64,
}

/// What a finished region job made.
#[derive(Debug, Clone)]
pub struct RegionReport {
    /// The job's directory.
    pub out: PathBuf,
    pub region: Region,
    pub split_level: u32,
    pub tile_rows: std::ops::Range<u32>,
    /// Tiles made, over every level.
    pub tiles: u64,
    /// Level-0 samples under its tiles.
    pub samples: u64,
    pub heights_bytes: u64,
    pub texture_bytes: u64,
    pub warnings: Vec<BuildWarning>,
    pub elapsed: Duration,
}

impl std::fmt::Display for RegionReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
        let s = self.elapsed.as_secs_f64();
        writeln!(
            f,
            "region {} done: {} in {s:.1} s",
            self.region,
            self.out.display()
        )?;
        let levels = match self.split_level {
            0 => "level 0".to_string(),
            k => format!("levels 0-{k}"),
        };
        writeln!(
            f,
            "  tiles     {} tiles of {levels} under tile rows {}..{} of level {}",
            self.tiles, self.tile_rows.start, self.tile_rows.end, self.split_level
        )?;
        writeln!(
            f,
            "  bytes     heights {:.2} MiB, textures {:.2} MiB",
            mib(self.heights_bytes),
            mib(self.texture_bytes)
        )?;
        writeln!(
            f,
            "  speed     {:.2} M samples/s of its region",
            self.samples as f64 / s.max(1e-9) / 1e6
        )?;
        for w in &self.warnings {
            writeln!(f, "  warning   {w}")?;
        }
        Ok(())
    }
}

fn coder_name(coder: heights::Coder) -> String {
    match coder {
        heights::Coder::Rans => "rans".into(),
        heights::Coder::Zstd(level) => format!("zstd:{level}"),
    }
}

fn coder_of(name: &str) -> Option<heights::Coder> {
    match name.split_once(':') {
        None if name == "rans" => Some(heights::Coder::Rans),
        Some(("zstd", level)) => level.parse().ok().map(heights::Coder::Zstd),
        _ => None,
    }
}

/// Runs region job `region` of the build `options` describe, into the jobs directory
/// `options.out`. Checks `cancel` between tiles; a cancelled or failed job leaves nothing
/// in the jobs directory but what was there.
pub fn build_region(
    options: &BuildOptions,
    region: Region,
    progress: ProgressFn<'_>,
    stage: &dyn Fn(Stage),
    cancel: &AtomicBool,
) -> Result<RegionReport, BuildError> {
    let started = Instant::now();
    check_options(options)?;
    if options.patches.is_some() {
        return Err(BuildError::BadOption(
            "--patches holds the whole raster and is not split into region jobs: build them \
             with one `terrain-server build --patches`"
                .into(),
        ));
    }
    let jobs_dir = &options.out;
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| BuildError::Write(WriteError::Io { path, source })
    };
    std::fs::create_dir_all(jobs_dir).map_err(io(jobs_dir))?;
    let mut prepared = prepare(options)?;
    let raster = prepared.manifest.raster;
    let n = prepared.manifest.tile_size;
    let (split_level, tile_rows) = split(raster, n, region)?;
    let mut writer = JobWriter::create(jobs_dir, region, split_level)?;
    if !writer.abandoned.is_empty() {
        prepared
            .warnings
            .push(BuildWarning::AbandonedRemoved(writer.abandoned.clone()));
    }
    stage(Stage::Tiles);
    let mut rows = std::mem::replace(
        &mut prepared.rows,
        super::input::CodeRows::memory(Vec::new(), 0),
    );
    let mut pyramid = Pyramid::region(
        raster,
        prepared.context(),
        split_level,
        tile_rows.clone(),
        progress,
        cancel,
    );
    let first = pyramid.first_row();
    let (mut y, mut up_rows, mut carries) = (0u32, None::<(u32, u32)>, 0u64);
    while !pyramid.is_done() {
        let Some(row) = rows.next_row()? else { break };
        if y >= first {
            pyramid.push_row(row, &mut writer)?;
            let handover = pyramid.take_handover();
            carries += handover.carries.len() as u64;
            writer.hand_over(&handover.carries, &handover.rows)?;
            for (row_y, _) in &handover.rows {
                up_rows = Some(match up_rows {
                    None => (*row_y, 1),
                    Some((first, count)) => (first, count + 1),
                });
            }
        }
        y += 1;
    }
    drop(rows);
    let built = pyramid.finish()?;
    let plan = Plan {
        count: region.count,
        split_level,
        manifest: prepared.manifest.clone(),
        heights_coder: coder_name(prepared.heights_coder),
        jpeg_quality: prepared.jpeg_quality,
        code_range: prepared.code_range,
    };
    let tiles: u64 = built.levels.iter().map(|l| l.tiles.len() as u64).sum();
    let step = u64::from(n - 1);
    let samples = {
        let rows0 = u64::from(tile_rows.end - tile_rows.start) << split_level;
        (rows0 * step).min(u64::from(raster.height)) * u64::from(raster.width)
    };
    let record = JobRecord {
        format: JOB_FORMAT.into(),
        index: region.index,
        plan,
        tile_rows: (tile_rows.start, tile_rows.end),
        levels: built.levels.into_iter().map(|l| l.tiles).collect(),
        texture_level_bytes: built.texture_level_bytes,
        heights_bytes: built.heights_bytes,
        up_rows: up_rows.unwrap_or((0, 0)),
        carries,
        files: Default::default(),
        warnings: prepared.warnings.iter().map(ToString::to_string).collect(),
        source_bytes: prepared.source_bytes,
        seconds: started.elapsed().as_secs_f64(),
    };
    if cancel.load(std::sync::atomic::Ordering::Relaxed) {
        return Err(BuildError::Cancelled);
    }
    let out = writer.finish(record)?;
    Ok(RegionReport {
        out,
        region,
        split_level,
        tile_rows,
        tiles,
        samples,
        heights_bytes: built.heights_bytes,
        texture_bytes: built.texture_bytes,
        warnings: prepared.warnings,
        elapsed: started.elapsed(),
    })
}

/// A file being written, hashed as it goes.
#[derive(Debug)]
struct HashedFile {
    name: String,
    file: BufWriter<File>,
    hasher: blake3::Hasher,
    bytes: u64,
}

impl HashedFile {
    fn create(dir: &Path, name: String) -> Result<HashedFile, WriteError> {
        let path = dir.join(&name);
        let file = File::create(&path).map_err(|source| WriteError::Io { path, source })?;
        Ok(HashedFile {
            name,
            file: BufWriter::new(file),
            hasher: blake3::Hasher::new(),
            bytes: 0,
        })
    }

    fn write(&mut self, dir: &Path, bytes: &[u8]) -> Result<(), WriteError> {
        self.file
            .write_all(bytes)
            .map_err(|source| WriteError::Io {
                path: dir.join(&self.name),
                source,
            })?;
        self.hasher.update(bytes);
        self.bytes += bytes.len() as u64;
        Ok(())
    }

    fn finish(self, dir: &Path) -> Result<(String, FileRecord), WriteError> {
        let io = |source| WriteError::Io {
            path: dir.join(&self.name),
            source,
        };
        let file = self.file.into_inner().map_err(|e| io(e.into_error()))?;
        file.sync_all().map_err(io)?;
        let blake3 = self.hasher.finalize().to_hex().to_string();
        Ok((
            self.name,
            FileRecord {
                bytes: self.bytes,
                blake3,
            },
        ))
    }
}

/// A region job's files, in a hidden temporary directory of the jobs directory until
/// [`JobWriter::finish`] renames it; dropped unfinished, it removes it.
#[derive(Debug)]
struct JobWriter {
    jobs_dir: PathBuf,
    region: Region,
    tmp: tempfile::TempDir,
    lock: File,
    abandoned: Vec<PathBuf>,
    /// Per level, heights then textures.
    levels: Vec<[HashedFile; 2]>,
    carries: HashedFile,
    rows: HashedFile,
}

impl JobWriter {
    fn create(jobs_dir: &Path, region: Region, split_level: u32) -> Result<JobWriter, BuildError> {
        let io = |source| {
            BuildError::Write(WriteError::Io {
                path: jobs_dir.to_path_buf(),
                source,
            })
        };
        let prefix = format!(".{}.building-", region.dir_name());
        let abandoned = crate::db::remove_abandoned_builds(jobs_dir, &prefix);
        let tmp = tempfile::Builder::new()
            .prefix(&prefix)
            .tempdir_in(jobs_dir)
            .map_err(io)?;
        let lock = File::create(tmp.path().join(crate::db::BUILDING_LOCK)).map_err(io)?;
        lock.try_lock().map_err(|e| {
            io(match e {
                std::fs::TryLockError::Error(e) => e,
                std::fs::TryLockError::WouldBlock => std::io::ErrorKind::WouldBlock.into(),
            })
        })?;
        let dir = tmp.path();
        let levels = (0..=split_level)
            .map(|level| {
                Ok([
                    HashedFile::create(dir, format!("heights.level-{level}"))?,
                    HashedFile::create(dir, format!("textures.level-{level}"))?,
                ])
            })
            .collect::<Result<Vec<_>, WriteError>>()?;
        Ok(JobWriter {
            jobs_dir: jobs_dir.to_path_buf(),
            region,
            carries: HashedFile::create(dir, "carries".into())?,
            rows: HashedFile::create(dir, "rows".into())?,
            tmp,
            lock,
            abandoned,
            levels,
        })
    }

    fn add(&mut self, level: u32, which: usize, bytes: &[u8]) -> Result<Blob, WriteError> {
        let dir = self.tmp.path();
        let file = self
            .levels
            .get_mut(level as usize)
            .map(|files| &mut files[which])
            .ok_or_else(|| WriteError::Io {
                path: dir.to_path_buf(),
                source: std::io::Error::other(format!("level {level} is above the split")),
            })?;
        file.write(dir, bytes)?;
        Ok(Blob::of(bytes))
    }

    fn hand_over(&mut self, carries: &[Carry], rows: &[(u32, Vec<i32>)]) -> Result<(), WriteError> {
        let dir = self.tmp.path();
        let mut bytes = Vec::new();
        for carry in carries {
            let start = bytes.len();
            bytes.extend_from_slice(&[0; 4]);
            carry.write_to(&mut bytes);
            let len = (bytes.len() - start - 4) as u32;
            bytes[start..start + 4].copy_from_slice(&len.to_le_bytes());
        }
        self.carries.write(dir, &bytes)?;
        for (_, row) in rows {
            let bytes: Vec<u8> = row.iter().flat_map(|c| c.to_le_bytes()).collect();
            self.rows.write(dir, &bytes)?;
        }
        Ok(())
    }

    /// Syncs every file, writes `job.json` last and renames the directory to
    /// `job-I-of-N`, replacing an earlier run's.
    fn finish(self, mut record: JobRecord) -> Result<PathBuf, BuildError> {
        let dir = self.tmp.path().to_path_buf();
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| BuildError::Write(WriteError::Io { path, source })
        };
        for file in self
            .levels
            .into_iter()
            .flatten()
            .chain([self.carries, self.rows])
        {
            let (name, info) = file.finish(&dir)?;
            record.files.insert(name, info);
        }
        let json = serde_json::to_vec_pretty(&record).map_err(|e| io(&dir)(e.into()))?;
        let path = dir.join(JOB_FILE);
        let mut file = File::create(&path).map_err(io(&path))?;
        file.write_all(&json).map_err(io(&path))?;
        file.sync_all().map_err(io(&path))?;
        let lock_path = dir.join(crate::db::BUILDING_LOCK);
        let _ = self.lock.unlock();
        std::fs::remove_file(&lock_path).map_err(io(&lock_path))?;
        let out = self.jobs_dir.join(self.region.dir_name());
        let tmp = self.tmp.keep();
        // An earlier run's result is moved aside and removed once this one is in place.
        let aside = tmp.with_extension("replaced");
        let had_old = std::fs::rename(&out, &aside).is_ok();
        if let Err(source) = std::fs::rename(&tmp, &out) {
            let _ = std::fs::remove_dir_all(&tmp);
            if had_old {
                let _ = std::fs::rename(&aside, &out);
            }
            return Err(io(&out)(source));
        }
        if had_old {
            std::fs::remove_dir_all(&aside).map_err(io(&aside))?;
        }
        Ok(out)
    }
}

impl TileSink for JobWriter {
    fn add_level_heights(&mut self, level: u32, bytes: &[u8]) -> Result<Blob, WriteError> {
        self.add(level, 0, bytes)
    }
    fn add_level_texture(&mut self, level: u32, bytes: &[u8]) -> Result<Blob, WriteError> {
        self.add(level, 1, bytes)
    }
}

/// What `merge` needs.
#[derive(Debug, Clone)]
pub struct MergeOptions {
    /// Where the region jobs wrote: a jobs directory, or a store location.
    pub jobs: crate::store::Location,
    pub out: PathBuf,
    pub force: bool,
    /// Make the web tiles when the input was georeferenced.
    pub web: bool,
}

/// A finished job's record.
#[derive(Debug)]
struct Job {
    region: Region,
    record: JobRecord,
}

/// Where the merge reads the jobs' files: a jobs directory, or a store location whose
/// files it downloads one at a time into a scratch directory, each removed once used.
enum Source {
    Dir(PathBuf),
    Store {
        url: crate::store::StoreUrl,
        store: std::sync::Arc<dyn object_store::ObjectStore>,
        runtime: tokio::runtime::Runtime,
        scratch: tempfile::TempDir,
    },
}

/// A region found, and its `job.json` when it has one.
type Listed = (Region, Option<Vec<u8>>);

/// A job's file on this machine, checked against its record; a downloaded one is removed
/// when dropped.
struct Fetched {
    path: PathBuf,
    downloaded: bool,
}

impl Drop for Fetched {
    fn drop(&mut self) {
        if self.downloaded {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

impl Source {
    fn open(location: &crate::store::Location) -> Result<Source, BuildError> {
        match location {
            crate::store::Location::Dir(dir) => Ok(Source::Dir(dir.clone())),
            crate::store::Location::Store(url) => {
                let fail = |message: String| BuildError::Jobs {
                    dir: PathBuf::from(url.to_string()),
                    message,
                };
                Ok(Source::Store {
                    store: crate::store::connect(url).map_err(|e| fail(e.to_string()))?,
                    url: url.clone(),
                    runtime: tokio::runtime::Builder::new_current_thread()
                        .enable_all()
                        .build()
                        .map_err(|e| fail(format!("cannot start the async runtime: {e}")))?,
                    scratch: tempfile::Builder::new()
                        .prefix("terrain-merge-jobs-")
                        .tempdir()
                        .map_err(|e| fail(format!("cannot make a scratch directory: {e}")))?,
                })
            }
        }
    }

    fn name(&self) -> PathBuf {
        match self {
            Source::Dir(dir) => dir.clone(),
            Source::Store { url, .. } => PathBuf::from(url.to_string()),
        }
    }

    fn fail(&self, message: String) -> BuildError {
        BuildError::Jobs {
            dir: self.name(),
            message,
        }
    }

    /// The regions present (a directory `job-I-of-N`) and each one's `job.json`, `None`
    /// for a region whose record is missing.
    fn list(&self) -> Result<Vec<Listed>, BuildError> {
        let parse = |name: &str| {
            let (i, n) = name.strip_prefix("job-")?.split_once("-of-")?;
            Region::parse(&format!("{i}/{n}")).ok()
        };
        match self {
            Source::Dir(dir) => {
                let entries = std::fs::read_dir(dir).map_err(|e| self.fail(e.to_string()))?;
                let mut found = Vec::new();
                for entry in entries.flatten() {
                    let name = entry.file_name().to_string_lossy().into_owned();
                    if let Some(region) = parse(&name) {
                        found.push((region, std::fs::read(entry.path().join(JOB_FILE)).ok()));
                    }
                }
                Ok(found)
            }
            Source::Store {
                url,
                store,
                runtime,
                ..
            } => runtime.block_on(async {
                let listed = store
                    .list_with_delimiter(Some(&url.prefix))
                    .await
                    .map_err(|e| self.fail(format!("listing the jobs: {e}")))?;
                let mut found = Vec::new();
                for prefix in listed.common_prefixes {
                    let Some(region) = prefix.filename().and_then(parse) else {
                        continue;
                    };
                    let object = prefix.clone().join(JOB_FILE);
                    let record = match store.get(&object).await {
                        Ok(got) => Some(
                            got.bytes()
                                .await
                                .map_err(|e| self.fail(format!("reading {object}: {e}")))?
                                .to_vec(),
                        ),
                        Err(object_store::Error::NotFound { .. }) => None,
                        Err(e) => return Err(self.fail(format!("reading {object}: {e}"))),
                    };
                    found.push((region, record));
                }
                Ok(found)
            }),
        }
    }

    /// Job `region`'s file `name`, on this machine, its size and hash checked against
    /// `record`.
    fn fetch(&self, job: &Job, name: &str) -> Result<Fetched, BuildError> {
        let region = job.region;
        let expected = job.record.files.get(name).ok_or_else(|| {
            self.fail(format!(
                "region {region}'s record lists no file {name}: run region {region} again"
            ))
        })?;
        let (fetched, shown) = match self {
            Source::Dir(dir) => {
                let path = dir.join(region.dir_name()).join(name);
                let shown = path.display().to_string();
                (
                    Fetched {
                        path,
                        downloaded: false,
                    },
                    shown,
                )
            }
            Source::Store {
                url,
                store,
                runtime,
                scratch,
            } => {
                use futures_util::StreamExt as _;
                let object = url.prefix.clone().join(region.dir_name()).join(name);
                let shown = format!("s3://{}/{object}", url.bucket);
                let fetched = Fetched {
                    path: scratch.path().join(format!("{}-{name}", region.dir_name())),
                    downloaded: true,
                };
                runtime.block_on(async {
                    let got = store
                        .get(&object)
                        .await
                        .map_err(|e| self.fail(format!("reading {shown}: {e}")))?;
                    let mut file = BufWriter::new(
                        File::create(&fetched.path)
                            .map_err(|e| self.fail(format!("{}: {e}", fetched.path.display())))?,
                    );
                    let mut stream = got.into_stream();
                    while let Some(chunk) = stream.next().await {
                        let chunk =
                            chunk.map_err(|e| self.fail(format!("reading {shown}: {e}")))?;
                        file.write_all(&chunk)
                            .map_err(|e| self.fail(format!("{}: {e}", fetched.path.display())))?;
                    }
                    file.flush()
                        .map_err(|e| self.fail(format!("{}: {e}", fetched.path.display())))?;
                    Ok::<(), BuildError>(())
                })?;
                (fetched, shown)
            }
        };
        let mut hasher = blake3::Hasher::new();
        let bytes = File::open(&fetched.path)
            .and_then(|mut f| {
                let mut buf = vec![0; 1 << 16];
                let mut total = 0u64;
                loop {
                    let n = f.read(&mut buf)?;
                    if n == 0 {
                        return Ok(total);
                    }
                    hasher.update(&buf[..n]);
                    total += n as u64;
                }
            })
            .map_err(|e| self.fail(format!("{shown}: {e}")))?;
        let blake3 = hasher.finalize().to_hex().to_string();
        if bytes != expected.bytes || blake3 != expected.blake3 {
            return Err(self.fail(format!(
                "{shown} holds {bytes} bytes of hash {blake3}, but its job recorded {} bytes of \
                 hash {}: run region {region} again",
                expected.bytes, expected.blake3
            )));
        }
        Ok(fetched)
    }
}

/// Reads and checks every job's record: all `N` present and finished, every plan the same,
/// the regions in order.
fn read_jobs(source: &Source) -> Result<Vec<Job>, BuildError> {
    let found = source.list()?;
    let fail = |message: String| source.fail(message);
    let Some(count) = found.iter().map(|(r, _)| r.count).max() else {
        return Err(fail(
            "no region jobs (job-I-of-N): run `terrain-server build DEM --region I/N --out \
             JOBS` for each I first"
                .into(),
        ));
    };
    if let Some((r, _)) = found.iter().find(|(r, _)| r.count != count) {
        return Err(fail(format!(
            "it holds jobs of {} and of {count} regions: remove the other split's",
            r.count
        )));
    }
    let mut records: Vec<(Region, Vec<u8>)> = found
        .into_iter()
        .filter_map(|(region, record)| Some((region, record?)))
        .collect();
    records.sort_by_key(|(r, _)| r.index);
    let missing: Vec<String> = (0..count)
        .filter(|i| !records.iter().any(|(r, _)| r.index == *i))
        .map(|i| format!("{i}/{count}"))
        .collect();
    if !missing.is_empty() {
        return Err(fail(format!(
            "missing region job(s) {}: run `terrain-server build DEM --region I/{count}` for each",
            missing.join(", ")
        )));
    }
    let mut jobs: Vec<Job> = Vec::new();
    for (region, text) in records {
        let record: JobRecord = serde_json::from_slice(&text).map_err(|e| {
            fail(format!(
                "region {region}'s {JOB_FILE} is not a region job's record: {e}"
            ))
        })?;
        if record.format != JOB_FORMAT || record.index != region.index {
            return Err(fail(format!(
                "region {region}'s {JOB_FILE}: format {:?}, region {} (expected {JOB_FORMAT}, \
                 region {region})",
                record.format, record.index
            )));
        }
        if let Some(first) = jobs.first()
            && record.plan != first.record.plan
        {
            return Err(fail(format!(
                "region {region} was built with other settings or another input than region \
                 0/{count} (its {JOB_FILE}'s plan differs): run every region with the same \
                 input and flags"
            )));
        }
        jobs.push(Job { region, record });
    }
    // The regions tile the split level's rows, in order.
    let mut next = 0;
    for job in &jobs {
        if job.record.tile_rows.0 != next {
            return Err(fail(format!(
                "region {} starts at tile row {}, not {next}",
                job.region, job.record.tile_rows.0
            )));
        }
        next = job.record.tile_rows.1;
    }
    Ok(jobs)
}

/// Uploads the finished job in `dir` to the store location `url`, as
/// `PREFIX/job-I-of-N/FILE`: its record removed first and written last, so that a job
/// killed while it uploads is a missing job to the merge, never a mix of two runs.
pub fn upload_job(
    dir: &Path,
    region: Region,
    url: &crate::store::StoreUrl,
) -> Result<u64, crate::store::StoreError> {
    use crate::store::StoreError;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|source| StoreError::Local {
            path: dir.to_path_buf(),
            source,
        })?;
    runtime.block_on(async {
        let store = crate::store::connect(url)?;
        let base = url.prefix.clone().join(region.dir_name());
        let record = base.clone().join(JOB_FILE);
        match store.delete(&record).await {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
            Err(source) => {
                return Err(StoreError::Store {
                    what: format!("removing {record}"),
                    source,
                });
            }
        }
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .map_err(|source| StoreError::Local {
                path: dir.to_path_buf(),
                source,
            })?
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n != JOB_FILE)
            .collect();
        names.sort();
        names.push(JOB_FILE.into());
        let mut sent = 0;
        for name in names {
            let object = base.clone().join(name.as_str());
            sent += crate::store::upload_file(&*store, &dir.join(&name), &object, &|_| {}).await?;
        }
        Ok(sent)
    })
}

/// Merges the region jobs in `options.jobs` into the database at `options.out`.
pub fn merge(
    options: &MergeOptions,
    progress: ProgressFn<'_>,
    stage: &dyn Fn(Stage),
    cancel: &AtomicBool,
) -> Result<BuildReport, BuildError> {
    let started = Instant::now();
    crate::db::check_output(&options.out, options.force)?;
    let source = Source::open(&options.jobs)?;
    let jobs = read_jobs(&source)?;
    let plan = jobs[0].record.plan.clone();
    let base = &plan.manifest;
    let n = base.tile_size;
    let split_level = plan.split_level as usize;
    let all = manifest::level_rasters(base.raster, n);
    let grids: Vec<super::tiles::Grid> = all
        .iter()
        .map(|r| super::tiles::Grid::covering(r.width, r.height, n))
        .collect();
    let fail = |message: String| source.fail(message);
    if jobs.last().map(|j| j.record.tile_rows.1) != Some(grids[split_level].rows) {
        return Err(fail(format!(
            "the regions end before the split level's {} tile rows",
            grids[split_level].rows
        )));
    }
    for job in &jobs {
        let (start, end) = job.record.tile_rows;
        let expected = u64::from(end - start) * u64::from(grids[split_level].columns);
        if job.record.carries != expected {
            return Err(fail(format!(
                "region {} handed over {} carries, not the {expected} of its tiles",
                job.record.index, job.record.carries
            )));
        }
    }
    let heights_coder = coder_of(&plan.heights_coder)
        .ok_or_else(|| fail(format!("unknown heights coder {:?}", plan.heights_coder)))?;
    let mut writer = DbWriter::create(&options.out, options.force)?;
    let mut warnings: Vec<BuildWarning> = Vec::new();
    if !writer.abandoned_removed().is_empty() {
        warnings.push(BuildWarning::AbandonedRemoved(
            writer.abandoned_removed().to_vec(),
        ));
    }
    stage(Stage::Tiles);
    // The jobs' tiles, level by level, region by region: row-major per level.
    let mut levels: Vec<Level> = Vec::new();
    let mut texture_bytes = 0u64;
    let mut texture_level_bytes: Vec<u64> = Vec::new();
    for level in 0..=split_level {
        let mut tiles = Vec::with_capacity(grids[level].len());
        for job in &jobs {
            let heights = source.fetch(job, &format!("heights.level-{level}"))?;
            let textures = source.fetch(job, &format!("textures.level-{level}"))?;
            let (_, t) = writer.append_level_files(level as u32, &heights.path, &textures.path)?;
            texture_bytes += t;
            tiles.extend(job.record.levels.get(level).cloned().unwrap_or_default());
        }
        if tiles.len() != grids[level].len() {
            return Err(fail(format!(
                "level {level} has {} tiles in the jobs' records, not its {}",
                tiles.len(),
                grids[level].len()
            )));
        }
        levels.push(Level {
            raster: all[level],
            grid: manifest::GridSize {
                columns: grids[level].columns,
                rows: grids[level].rows,
            },
            tiles,
        });
    }
    for job in &jobs {
        add_up(&mut texture_level_bytes, &job.record.texture_level_bytes);
    }
    // The levels above the split, from the jobs' rows and carries.
    let mut merged_heights = 0;
    if split_level + 1 < all.len() {
        let context = TileContext {
            tile_size: n,
            quantum_m: base.heights.quantum_m,
            offset_m: base.heights.offset_m,
            code_range: plan.code_range,
            heights_coder,
            texture_format: base.texture.format,
            jpeg_quality: plan.jpeg_quality,
            texture_size: base.texture.size,
            level_zero_texture: LevelZeroTexture::FromChildren,
        };
        let mut carries = CarryReader::new(&jobs, grids[split_level].columns, &source);
        let (columns, child_rows) = (grids[split_level + 1].columns, grids[split_level].rows);
        let children = Box::new(move |y: u32| -> Result<Vec<Parent>, BuildError> {
            let north = carries.next_row()?;
            let south = if 2 * y + 1 < child_rows {
                Some(carries.next_row()?)
            } else {
                None
            };
            let mut parents: Vec<Parent> = (0..columns).map(|_| Parent::default()).collect();
            for (row, slot) in [(Some(north), 0), (south, 2)] {
                for (x, carry) in row.into_iter().flatten().enumerate() {
                    parents[x / 2].children[x % 2 + slot] = Some(carry);
                }
            }
            Ok(parents)
        });
        let mut pyramid = Pyramid::above(
            base.raster,
            context,
            plan.split_level,
            children,
            progress,
            cancel,
        );
        let up = all[split_level + 1];
        let mut next_y = 0u32;
        for job in &jobs {
            let (first, count) = job.record.up_rows;
            let rows = source.fetch(job, "rows")?;
            let path = &rows.path;
            let mut file = std::io::BufReader::new(
                File::open(path).map_err(|e| fail(format!("{}: {e}", path.display())))?,
            );
            let mut bytes = vec![0u8; up.width as usize * 4];
            let mut row = vec![0i32; up.width as usize];
            for y in first..first + count {
                file.read_exact(&mut bytes)
                    .map_err(|e| fail(format!("{}: {e}", path.display())))?;
                if y < next_y {
                    continue;
                }
                if y != next_y {
                    return Err(fail(format!(
                        "region {}'s rows of level {} start at row {y}, not {next_y}",
                        job.region,
                        split_level + 1
                    )));
                }
                for (c, b) in row.iter_mut().zip(bytes.chunks_exact(4)) {
                    *c = i32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                }
                pyramid.push_row(&row, &mut writer)?;
                next_y += 1;
            }
        }
        if next_y != up.height {
            return Err(fail(format!(
                "the jobs' rows of level {} end at row {next_y} of {}",
                split_level + 1,
                up.height
            )));
        }
        let built = pyramid.finish()?;
        merged_heights = built.heights_bytes;
        add_up(&mut texture_level_bytes, &built.texture_level_bytes);
        texture_bytes += built.texture_bytes;
        levels.extend(built.levels);
    }
    let tiles_elapsed = started.elapsed();
    let mut manifest = base.clone();
    manifest.levels = levels;
    manifest.texture.level_bytes = texture_level_bytes;
    let tile_samples = manifest.tile_count() as u64 * u64::from(n) * u64::from(n);
    let (out, web_stats) = finish_database(
        writer,
        &mut manifest,
        options.web,
        &mut warnings,
        progress,
        stage,
        cancel,
    )?;
    Ok(BuildReport {
        out,
        manifest,
        warnings,
        heights_bytes: jobs.iter().map(|j| j.record.heights_bytes).sum::<u64>() + merged_heights,
        texture_bytes,
        tile_samples,
        source_bytes: jobs[0].record.source_bytes,
        patches: None,
        web: web_stats,
        tiles_elapsed,
        elapsed: started.elapsed(),
    })
}

fn add_up(total: &mut Vec<u64>, more: &[u64]) {
    if total.len() < more.len() {
        total.resize(more.len(), 0);
    }
    for (t, m) in total.iter_mut().zip(more) {
        *t += m;
    }
}

/// The split level's carries, a tile row at a time, across the jobs in order.
struct CarryReader<'a> {
    jobs: &'a [Job],
    columns: u32,
    source: &'a Source,
    /// The job being read, its carries file, and the position in it.
    job: usize,
    bytes: Vec<u8>,
    at: usize,
    rows_left: u32,
}

impl<'a> CarryReader<'a> {
    fn new(jobs: &'a [Job], columns: u32, source: &'a Source) -> CarryReader<'a> {
        CarryReader {
            jobs,
            columns,
            source,
            job: 0,
            bytes: Vec::new(),
            at: 0,
            rows_left: 0,
        }
    }

    fn fail(&self, message: String) -> BuildError {
        self.source.fail(message)
    }

    /// The carries of the next tile row of the split level.
    fn next_row(&mut self) -> Result<Vec<Carry>, BuildError> {
        while self.rows_left == 0 {
            let Some(job) = self.jobs.get(self.job) else {
                return Err(self.fail("the jobs' carries end before the split level's".into()));
            };
            if let Some(done) = self.job.checked_sub(1)
                && self.at != self.bytes.len()
            {
                let index = self.jobs[done].region;
                return Err(self.fail(format!(
                    "region {index}'s carries hold more than its tile rows"
                )));
            }
            let carries = self.source.fetch(job, "carries")?;
            let path = &carries.path;
            self.bytes =
                std::fs::read(path).map_err(|e| self.fail(format!("{}: {e}", path.display())))?;
            self.at = 0;
            self.rows_left = job.record.tile_rows.1 - job.record.tile_rows.0;
            self.job += 1;
        }
        self.rows_left -= 1;
        let mut row = Vec::with_capacity(self.columns as usize);
        for _ in 0..self.columns {
            let bad = || {
                let index = self.jobs[self.job - 1].region;
                self.fail(format!(
                    "region {index}'s carries are cut short or malformed"
                ))
            };
            let len = self
                .bytes
                .get(self.at..self.at + 4)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
                .ok_or_else(bad)?;
            let mut body = self
                .bytes
                .get(self.at + 4..self.at + 4 + len)
                .ok_or_else(bad)?;
            let carry = Carry::read_from(&mut body).ok_or_else(bad)?;
            if !body.is_empty() {
                return Err(bad());
            }
            self.at += 4 + len;
            row.push(carry);
        }
        Ok(row)
    }
}

/// `terrain-server merge`: the command-line face of [`merge`].
#[derive(Debug, Clone, clap::Args)]
pub struct MergeArgs {
    /// Where the region jobs (`build --region I/N --out JOBS`) wrote: their jobs directory,
    /// or the store location `s3://bucket/prefix` (files downloaded one at a time).
    #[arg(value_name = "JOBS|s3://BUCKET/PREFIX", value_parser = crate::store::Location::parse)]
    pub jobs: crate::store::Location,
    /// Output: a directory, or an object-store location `s3://bucket/prefix` (as for
    /// `build`). Default: db/NAME, NAME being the dataset's name.
    #[arg(long, short, value_name = "DIR|s3://BUCKET/PREFIX", value_parser = crate::store::Location::parse)]
    pub out: Option<crate::store::Location>,
    /// Replace an existing database at the output path.
    #[arg(long)]
    pub force: bool,
    /// Skip the web tiles (made by default when the input is georeferenced).
    #[arg(long)]
    pub no_web: bool,
    /// No progress bar.
    #[arg(long, short)]
    pub quiet: bool,
}

/// Runs `terrain-server merge`: progress bar, Ctrl-C cancels cleanly, the build's summary.
pub fn run_merge_cli(args: MergeArgs) -> anyhow::Result<()> {
    use anyhow::Context as _;
    let scratch = match &args.out {
        Some(crate::store::Location::Store(_)) => Some(
            tempfile::Builder::new()
                .prefix("terrain-merge-")
                .tempdir()
                .context("cannot make a temporary directory for the merge")?,
        ),
        _ => None,
    };
    let out = match (&args.out, &scratch) {
        (_, Some(dir)) => dir.path().join("db"),
        (Some(crate::store::Location::Dir(dir)), None) => dir.clone(),
        _ => {
            let jobs = read_jobs(&Source::open(&args.jobs)?)?;
            Path::new("db").join(&jobs[0].record.plan.manifest.dataset)
        }
    };
    let options = MergeOptions {
        jobs: args.jobs.clone(),
        out,
        force: args.force,
        web: !args.no_web,
    };
    let report = super::with_progress_bar(args.quiet, "merging", |progress, stage, cancel| {
        merge(&options, progress, stage, cancel)
    })?;
    crate::print_stdout(&super::Summary(&report).to_string()).context("cannot write to stdout")?;
    if let (Some(crate::store::Location::Store(url)), Some(_dir)) = (&args.out, &scratch) {
        super::publish_cli(&report.out, url, args.quiet)?;
    }
    Ok(())
}
