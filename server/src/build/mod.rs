//! The tile-database builder: DEM (and texture) in, database out.
//!
//! Steps, one module each: [`input`] reads the raster and its metadata, [`voids`] fills
//! no-data, [`tiles`] cuts tiles and computes their metadata, [`texture`] makes each
//! tile's mip chain, [`levels`] builds the pyramid of levels a band of tile rows at a time,
//! and [`crate::db::DbWriter`] writes everything atomically. This module merges flags with
//! what the files say, chooses how the heights are read, runs the steps and reports.
//!
//! **Memory.** A build holds a band of tile rows per level, never a whole level, so its
//! memory grows with the raster's width and not with its height ([`levels`]). The heights
//! are read row by row ([`input::rows`]): a scan first, for what the first tile already
//! depends on (a float raster's quantum, the heights' range that computed textures are
//! tinted over, whether there are voids), then, with voids, two passes that find and solve
//! them region by region ([`voids`]: what they hold grows with the largest void, not with
//! the raster), then the build, which puts the filled codes in place. One thing is held
//! whole: a texture image (decoded once and resampled per tile; its size is the user's
//! choice). Formats the row reader does not handle (an interlaced PNG, say) are read whole,
//! and filled by the same passes over their rows.
//!
//! Precedence of metadata: command-line flags, then the file itself (GeoTIFF tags, `.hgt`
//! name), then a `dataset.json` beside the input, then defaults (with a warning).

pub mod input;
pub mod jobs;
pub mod levels;
pub mod patches;
pub mod texture;
pub mod tiles;
pub mod voids;

use crate::db::{DbWriter, WriteError};
use anyhow::Context as _;
use clap::Args;
use input::CodeRows;
use levels::{LevelZeroTexture, Pyramid, TileContext};
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use terrain_shared::manifest::{
    self, Georeference, HeightsInfo, ImageFormat, RasterSize, TextureInfo, TextureSource,
};
use terrain_shared::{EncodeError, Manifest, heights, mask};
use thiserror::Error;

pub use input::{InputError, OutOfRange, Raster};
pub use texture::Registration;

/// Default samples per tile side: 2^7 + 1, as in the strip-mask paper's experiments.
pub const DEFAULT_TILE_SIZE: u32 = 129;
/// Precision kept for floating-point heights that are not whole numbers.
pub const DEFAULT_FLOAT_QUANTUM_M: f64 = 0.01;

/// `terrain-server build`: the command-line face of [`BuildOptions`].
#[derive(Debug, Clone, Args)]
pub struct BuildArgs {
    /// Height raster: 16- or 8-bit greyscale PNG, GeoTIFF (int16, uint16, float32) or SRTM .hgt.
    /// A dataset.json beside it supplies spacing, height scale, no-data and texture.
    pub heights: PathBuf,
    /// Texture image (RGB) covering the raster. Default: the texture named by dataset.json,
    /// else one computed from the heights (hypsometric tint with hill shading).
    #[arg(long)]
    pub texture: Option<PathBuf>,
    /// Compute the texture from the heights even when an image is available.
    #[arg(long, conflicts_with = "texture")]
    pub generated_texture: bool,
    /// How the texture image sits on the raster (default: dataset.json's, else edge-aligned).
    #[arg(long, value_enum)]
    pub texture_registration: Option<Registration>,
    /// Output: a directory, or an object-store location `s3://bucket/prefix` (the database is
    /// built in a temporary directory, uploaded as its content version, packs first and
    /// manifest last, then the location's pointer is moved to it; credentials and endpoint
    /// from the AWS_* environment variables). Default: db/NAME, NAME being the dataset name.
    #[arg(long, short, value_name = "DIR|s3://BUCKET/PREFIX", value_parser = crate::store::Location::parse)]
    pub out: Option<crate::store::Location>,
    /// Replace an existing database at the output path.
    #[arg(long)]
    pub force: bool,
    /// Dataset name in the manifest. Default: the folder name when a dataset.json is beside
    /// the input, else the file name.
    #[arg(long)]
    pub name: Option<String>,
    /// Samples per tile side, 2^n + 1 (tiles share their border samples).
    #[arg(long, default_value_t = DEFAULT_TILE_SIZE)]
    pub tile_size: u32,
    /// Sample spacing in metres: one value, or east-west,north-south.
    #[arg(long, value_delimiter = ',', num_args = 1..=2)]
    pub spacing: Option<Vec<f64>>,
    /// Metres per height unit of the raster.
    #[arg(long)]
    pub height_scale: Option<f64>,
    /// Metres added to every height after scaling.
    #[arg(long)]
    pub height_offset: Option<f64>,
    /// Raster value meaning "no data" (GeoTIFF: read from the file; .hgt: -32768).
    #[arg(long, allow_hyphen_values = true)]
    pub nodata: Option<f64>,
    /// Precision in metres kept for float heights that are not whole numbers. Heights are
    /// stored as 32-bit multiples of it, so it also bounds them: 0.01 m holds ±21,474 km; a
    /// quantum too fine for the raster's heights is refused.
    #[arg(long, default_value_t = DEFAULT_FLOAT_QUANTUM_M, allow_hyphen_values = true)]
    pub float_quantum: f64,
    /// What to do with float samples no height code holds at the quantum (such as -3.4e38 or
    /// 1e30 marking no-data without a no-data tag, or infinities): refuse the build and name
    /// them, or take them as no-data and fill them like any void. NaN is always no-data.
    #[arg(long, value_enum, default_value_t = OutOfRange::Refuse)]
    pub out_of_range: OutOfRange,
    /// Texture image format: jpeg for photographs and tints, png for lossless.
    #[arg(long, value_enum, default_value_t = TextureFormatArg::Jpeg)]
    pub texture_format: TextureFormatArg,
    /// Finest texture side per tile in texels, a power of two. Default: the source image's
    /// density, or one texel per cell for computed textures.
    #[arg(long)]
    pub texture_size: Option<u32>,
    /// JPEG quality, 1-100.
    #[arg(long, default_value_t = texture::DEFAULT_JPEG_QUALITY, value_parser = clap::value_parser!(u8).range(1..=100))]
    pub jpeg_quality: u8,
    /// Entropy coder of the heights: rans (codec 2: context-modelled rANS, within a few
    /// percent of the residuals' entropy, fast to encode) or zstd (codec 1: byte planes and
    /// zstd at --zstd-level, what older databases hold; slower to build, faster to decode).
    #[arg(long, value_enum, default_value_t = HeightsCodecArg::Rans)]
    pub heights_codec: HeightsCodecArg,
    /// zstd level (1-22) of the quadtree patches, and of the heights with
    /// `--heights-codec zstd`; decoding speed does not depend on it.
    #[arg(long, default_value_t = heights::DEFAULT_ZSTD_LEVEL, value_parser = clap::value_parser!(i32).range(1..=22))]
    pub zstd_level: i32,
    /// Also build the quadtree progressive patches (`--method quadtree-patches`): an
    /// adaptive triangulation per tile with a guaranteed error, stored beside the tiles.
    /// Holds the whole raster in memory while it runs.
    #[arg(long)]
    pub patches: bool,
    /// World-space tolerance of the finest patches, metres (0 keeps every sample that is
    /// not on a plane with its neighbours).
    #[arg(long, default_value_t = 0.0, requires = "patches")]
    pub patch_tolerance: f64,
    /// Skip the web tiles (MapLibre's Terrarium and Terrain-RGB XYZ tiles, Cesium's
    /// quantized-mesh). They are made by default when the input is georeferenced
    /// (GeoTIFF tags, an .hgt name, dataset.json bounds), from the finished pyramid.
    #[arg(long)]
    pub no_web: bool,
    /// Largest raster a build takes, in samples (width x height), for the heights and for a
    /// texture image alike. A larger one is refused before its samples are read, with its
    /// size: a small file can decode to a huge raster (a PNG inflates up to about 1000-fold),
    /// and a build passes over every sample several times before its first tile is done.
    /// Raise it for a DEM that large.
    #[arg(long, default_value_t = DEFAULT_MAX_SAMPLES, value_name = "SAMPLES")]
    pub max_samples: u64,
    /// Make only the tiles of region I of N, as one of N independent jobs, into the jobs
    /// directory --out (default db/NAME.jobs), or uploaded to the store location --out
    /// s3://BUCKET/PREFIX; `terrain-server merge` then makes the database, the same as one
    /// build's. Regions are runs of tile rows of the coarsest
    /// level with at least N of them. Every job reads the whole heights file (a scan, and
    /// the voids' passes), and makes its region's tiles.
    #[arg(long, value_name = "I/N", value_parser = jobs::Region::parse, conflicts_with = "patches")]
    pub region: Option<jobs::Region>,
    /// No progress bar.
    #[arg(long, short)]
    pub quiet: bool,
}

/// The default of `--max-samples`: 65,536 x 65,536, 8 GiB of 16-bit heights.
pub const DEFAULT_MAX_SAMPLES: u64 = 1 << 32;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum HeightsCodecArg {
    Rans,
    Zstd,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum TextureFormatArg {
    Jpeg,
    Png,
}

/// Everything a build needs, resolved. [`BuildOptions::from_args`] fills it from flags.
#[derive(Debug, Clone)]
pub struct BuildOptions {
    pub heights: PathBuf,
    pub texture: TextureChoice,
    pub texture_registration: Option<Registration>,
    pub out: PathBuf,
    pub force: bool,
    pub name: Option<String>,
    pub tile_size: u32,
    pub spacing_m: Option<[f64; 2]>,
    pub height_scale: Option<f64>,
    pub height_offset: Option<f64>,
    pub nodata: Option<f64>,
    pub float_quantum_m: f64,
    pub out_of_range: OutOfRange,
    pub texture_format: ImageFormat,
    pub texture_size: Option<u32>,
    pub jpeg_quality: u8,
    /// The heights' entropy coder.
    pub heights_coder: heights::Coder,
    /// zstd level of the quadtree patches.
    pub zstd_level: i32,
    /// The quadtree patches' tolerance (metres), when they are built.
    pub patches: Option<f64>,
    /// Make the web tiles when the input is georeferenced (the command line's default;
    /// off in [`BuildOptions::new`]).
    pub web: bool,
    /// Largest raster taken, heights or texture, in samples (`--max-samples`).
    pub max_samples: u64,
}

/// Where the texture comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TextureChoice {
    /// The given image, or dataset.json's, or computed when there is none.
    Auto,
    Image(PathBuf),
    Generated,
}

impl BuildOptions {
    /// Options with defaults for `heights` written to `out`.
    pub fn new(heights: impl Into<PathBuf>, out: impl Into<PathBuf>) -> BuildOptions {
        BuildOptions {
            heights: heights.into(),
            texture: TextureChoice::Auto,
            texture_registration: None,
            out: out.into(),
            force: false,
            name: None,
            tile_size: DEFAULT_TILE_SIZE,
            spacing_m: None,
            height_scale: None,
            height_offset: None,
            nodata: None,
            float_quantum_m: DEFAULT_FLOAT_QUANTUM_M,
            out_of_range: OutOfRange::Refuse,
            texture_format: ImageFormat::Jpeg,
            texture_size: None,
            jpeg_quality: texture::DEFAULT_JPEG_QUALITY,
            heights_coder: heights::Coder::Rans,
            zstd_level: heights::DEFAULT_ZSTD_LEVEL,
            patches: None,
            web: false,
            max_samples: DEFAULT_MAX_SAMPLES,
        }
    }

    pub fn from_args(args: &BuildArgs) -> Result<BuildOptions, BuildError> {
        let spacing_m = match args.spacing.as_deref() {
            None => None,
            Some([s]) => Some([*s, *s]),
            Some([x, y]) => Some([*x, *y]),
            Some(_) => {
                return Err(BuildError::BadOption(
                    "--spacing takes one or two values".into(),
                ));
            }
        };
        let name = args.name.clone();
        let out = match &args.out {
            Some(crate::store::Location::Dir(out)) => out.clone(),
            // Built in a temporary directory, then published (`run_cli`).
            Some(crate::store::Location::Store(_)) => std::env::temp_dir().join("terrain-build"),
            None => {
                Path::new("db").join(name.clone().unwrap_or_else(|| default_name(&args.heights)))
            }
        };
        Ok(BuildOptions {
            texture: match (&args.texture, args.generated_texture) {
                (Some(path), _) => TextureChoice::Image(path.clone()),
                (None, true) => TextureChoice::Generated,
                (None, false) => TextureChoice::Auto,
            },
            texture_registration: args.texture_registration,
            force: args.force,
            name,
            tile_size: args.tile_size,
            spacing_m,
            height_scale: args.height_scale,
            height_offset: args.height_offset,
            nodata: args.nodata,
            float_quantum_m: args.float_quantum,
            out_of_range: args.out_of_range,
            texture_format: match args.texture_format {
                TextureFormatArg::Jpeg => ImageFormat::Jpeg,
                TextureFormatArg::Png => ImageFormat::Png,
            },
            texture_size: args.texture_size,
            jpeg_quality: args.jpeg_quality,
            heights_coder: match args.heights_codec {
                HeightsCodecArg::Rans => heights::Coder::Rans,
                HeightsCodecArg::Zstd => heights::Coder::Zstd(args.zstd_level),
            },
            zstd_level: args.zstd_level,
            patches: args.patches.then_some(args.patch_tolerance),
            web: !args.no_web,
            max_samples: args.max_samples,
            ..BuildOptions::new(&args.heights, out)
        })
    }
}

/// The dataset name: the folder's when a dataset.json describes it, else the file stem.
fn default_name(heights: &Path) -> String {
    let folder = heights
        .parent()
        .filter(|p| p.join("dataset.json").exists())
        .and_then(|p| p.file_name());
    folder
        .or_else(|| heights.file_stem())
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "terrain".into())
}

/// Why a build failed. Nothing is left at the output path in any of these cases.
#[derive(Debug, Error)]
pub enum BuildError {
    #[error(transparent)]
    Input(#[from] InputError),
    #[error(transparent)]
    Write(#[from] WriteError),
    #[error("texture {path}: {message}")]
    Texture { path: PathBuf, message: String },
    #[error("cannot encode tile {tile}")]
    Encode {
        tile: terrain_shared::TileId,
        source: EncodeError,
    },
    #[error("cannot encode a texture level: {0}")]
    TextureEncode(String),
    #[error("tile size {0} is not 2^n + 1 between 3 and 4097")]
    BadTileSize(u32),
    #[error("invalid option: {0}")]
    BadOption(String),
    #[error(
        "{path}: {what} of {width} x {height} = {samples} samples, more than the {max} a build \
         takes (--max-samples), from a file of {file_bytes} bytes. Pass --max-samples {samples} \
         to build it anyway"
    )]
    TooLarge {
        path: PathBuf,
        what: &'static str,
        width: u32,
        height: u32,
        samples: u64,
        max: u64,
        file_bytes: u64,
    },
    #[error("build cancelled; nothing was written to the output")]
    Cancelled,
    #[error("level {level} stopped after {made} of its {rows} tile rows: the heights ended early")]
    Unfinished { level: u32, made: u32, rows: u32 },
    #[error("the web tiles: {0}")]
    Web(#[from] crate::web::build::WebError),
    #[error("region jobs in {dir}: {message}")]
    Jobs { dir: PathBuf, message: String },
    #[error("reading the new tiles back for the web tiles: {0}")]
    ReadBack(#[from] crate::db::DbError),
}

/// Something a user should know about a finished build; the database is still complete.
#[derive(Debug, Clone, PartialEq)]
pub enum BuildWarning {
    FilledVoids(voids::FillReport),
    /// Float samples no height code holds, taken as no-data ([`OutOfRange::Nodata`]).
    OutOfRangeAsNodata {
        samples: usize,
    },
    SpacingUnknown,
    /// No web tiles: the input does not say where it lies on the Earth in a way this build
    /// can place (the reason); the native routes work as ever.
    NoWeb(String),
    TextureAspect {
        texture: [u32; 2],
        raster: [u32; 2],
    },
    /// Temporary directories of killed builds to the same output, removed.
    AbandonedRemoved(Vec<PathBuf>),
}

impl fmt::Display for BuildWarning {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            BuildWarning::AbandonedRemoved(dirs) => {
                let names: Vec<String> = dirs.iter().map(|d| d.display().to_string()).collect();
                write!(
                    f,
                    "removed what {} killed build(s) to this output left: {}",
                    dirs.len(),
                    names.join(", ")
                )
            }
            BuildWarning::FilledVoids(r) => {
                write!(
                    f,
                    "filled {} no-data samples in {} voids (largest: {} samples) with the thin-plate membrane of their rims",
                    r.samples, r.regions, r.largest_region
                )?;
                if r.unconverged > 0 {
                    write!(
                        f,
                        "; {} of them stopped at the iteration cap short of {} code steps",
                        r.unconverged,
                        voids::TOLERANCE
                    )?;
                }
                Ok(())
            }
            BuildWarning::OutOfRangeAsNodata { samples } => write!(
                f,
                "{samples} float samples no height code holds were taken as no-data (--out-of-range nodata)"
            ),
            BuildWarning::NoWeb(reason) => write!(
                f,
                "no web tiles (MapLibre and Cesium routes off for this database): {reason}"
            ),
            BuildWarning::SpacingUnknown => {
                write!(
                    f,
                    "sample spacing unknown: assumed 1 m (give --spacing or a dataset.json)"
                )
            }
            BuildWarning::TextureAspect { texture, raster } => write!(
                f,
                "texture is {}x{} but the raster {}x{}: its aspect differs, it is stretched to fit",
                texture[0], texture[1], raster[0], raster[1]
            ),
        }
    }
}

/// What a finished build made.
#[derive(Debug, Clone)]
pub struct BuildReport {
    pub out: PathBuf,
    pub manifest: Manifest,
    pub warnings: Vec<BuildWarning>,
    pub heights_bytes: u64,
    pub texture_bytes: u64,
    /// Samples stored in tiles (shared borders and padding included).
    pub tile_samples: u64,
    pub source_bytes: u64,
    /// The quadtree patches, when built.
    pub patches: Option<patches::Stats>,
    /// The web tiles, when made.
    pub web: Option<crate::web::build::Stats>,
    /// Reading the heights and making every level's tiles, heights and textures.
    pub tiles_elapsed: Duration,
    pub elapsed: Duration,
}

/// Progress of a build, for a bar: items of the current [`Stage`] done out of its total.
pub type ProgressFn<'a> = &'a (dyn Fn(usize, usize) + Sync);

/// The stages of a build, in order, each with its own progress count.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Reading the heights and making every level's tiles: heights, errors, textures.
    Tiles,
    /// The quadtree patches (`--patches`), from the raster.
    Patches,
    /// The web tiles, from the finished pyramid.
    WebTiles,
}

impl fmt::Display for Stage {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Stage::Tiles => "tiles",
            Stage::Patches => "patches",
            Stage::WebTiles => "web tiles",
        })
    }
}

/// Builds the database described by `options`. Checks `cancel` between tiles; a cancelled
/// or failed build leaves nothing at `options.out`.
pub fn build(
    options: &BuildOptions,
    progress: ProgressFn<'_>,
    cancel: &AtomicBool,
) -> Result<BuildReport, BuildError> {
    build_in_stages(options, progress, &|_| {}, cancel)
}

/// [`build`], calling `stage` as each stage starts (the progress counts start again).
pub fn build_in_stages(
    options: &BuildOptions,
    progress: ProgressFn<'_>,
    stage: &dyn Fn(Stage),
    cancel: &AtomicBool,
) -> Result<BuildReport, BuildError> {
    let started = Instant::now();
    check_options(options)?;
    // Before reading anything: a refused output should not cost a read of the whole input.
    crate::db::check_output(&options.out, options.force)?;
    let mut prepared = prepare(options)?;
    let mut writer = DbWriter::create(&options.out, options.force)?;
    if !writer.abandoned_removed().is_empty() {
        prepared.warnings.push(BuildWarning::AbandonedRemoved(
            writer.abandoned_removed().to_vec(),
        ));
    }
    stage(Stage::Tiles);
    let mut rows = std::mem::replace(&mut prepared.rows, CodeRows::memory(Vec::new(), 0));
    let mut pyramid = Pyramid::new(
        prepared.manifest.raster,
        prepared.context(),
        progress,
        cancel,
    );
    let mut whole: Vec<i32> = Vec::new();
    while let Some(row) = rows.next_row()? {
        if options.patches.is_some() {
            whole.extend_from_slice(row);
        }
        pyramid.push_row(row, &mut writer)?;
    }
    drop(rows);
    let built = pyramid.finish()?;
    let tiles_elapsed = started.elapsed();
    let mut manifest = prepared.manifest.clone();
    manifest.levels = built.levels;
    manifest.texture.level_bytes = built.texture_level_bytes;
    let mut patch_stats = None;
    if let Some(tolerance_m) = options.patches {
        if !(tolerance_m.is_finite() && tolerance_m >= 0.0) {
            return Err(BuildError::BadOption(format!(
                "--patch-tolerance {tolerance_m} must be a finite number of metres, 0 or more"
            )));
        }
        let started = Instant::now();
        stage(Stage::Patches);
        let made = patches::build(
            &whole,
            &manifest,
            tolerance_m,
            options.zstd_level,
            progress,
            cancel,
        )?;
        drop(whole);
        let index = terrain_shared::quadtree::encode_index(&made.entries);
        patch_stats = Some(patches::Stats::of(
            &made,
            index.len() as u64,
            started.elapsed(),
        ));
        writer.add_patches(&made.bodies, &index)?;
        manifest.patches = Some(manifest::PatchesInfo {
            format: terrain_shared::quadtree::FORMAT.into(),
            tolerance_m,
            index: terrain_shared::Blob::of(&index),
            bodies_bytes: made.bodies.iter().map(|b| b.len() as u64).sum(),
        });
    }
    let (out, web_stats) = finish_database(
        writer,
        &mut manifest,
        options.web,
        &mut prepared.warnings,
        progress,
        stage,
        cancel,
    )?;
    Ok(BuildReport {
        out,
        tile_samples: built.tile_samples,
        manifest,
        warnings: prepared.warnings,
        heights_bytes: built.heights_bytes,
        texture_bytes: built.texture_bytes,
        source_bytes: prepared.source_bytes,
        patches: patch_stats,
        web: web_stats,
        tiles_elapsed,
        elapsed: started.elapsed(),
    })
}

/// Refuses options no build takes, before anything is read.
fn check_options(options: &BuildOptions) -> Result<(), BuildError> {
    let n = options.tile_size;
    if !(3..=4097).contains(&n) || !(n - 1).is_power_of_two() {
        return Err(BuildError::BadTileSize(n));
    }
    if let Some(size) = options.texture_size
        && (!size.is_power_of_two() || size > 4096)
    {
        return Err(BuildError::BadOption(format!(
            "--texture-size {size} is not a power of two up to 4096"
        )));
    }
    Ok(())
}

/// Writes the manifest's content version, makes the web tiles when asked and the input
/// allows (from the sealed database), and puts the database in place.
fn finish_database(
    mut writer: DbWriter,
    manifest: &mut Manifest,
    web: bool,
    warnings: &mut Vec<BuildWarning>,
    progress: ProgressFn<'_>,
    stage: &dyn Fn(Stage),
    cancel: &AtomicBool,
) -> Result<(PathBuf, Option<crate::web::build::Stats>), BuildError> {
    manifest.content_version = manifest.compute_content_version();
    if cancel.load(Ordering::Relaxed) {
        return Err(BuildError::Cancelled);
    }
    let mut web_stats = None;
    if web {
        match crate::web::crs::Placement::new(manifest.georeference.as_ref()) {
            Err(reason) => warnings.push(BuildWarning::NoWeb(reason.to_string())),
            Ok(placement) => {
                let dir = writer.seal(manifest)?.to_path_buf();
                let db = crate::db::TileDb::open_being_built(&dir, crate::db::Verify::SizesOnly)?;
                stage(Stage::WebTiles);
                let (info, stats) = crate::web::build::build(
                    &db,
                    placement,
                    &writer.web_pack_path(),
                    progress,
                    cancel,
                )
                .map_err(|e| match e {
                    crate::web::build::WebError::Cancelled => BuildError::Cancelled,
                    e => BuildError::Web(e),
                })?;
                drop(db);
                manifest.web = Some(info);
                manifest.content_version = manifest.compute_content_version();
                web_stats = Some(stats);
            }
        }
    }
    let out = writer.finish(manifest)?;
    Ok((out, web_stats))
}

/// What a build knows before its first tile (see [`prepare`]).
#[derive(Debug)]
struct Prepared {
    /// The heights, filled, row by row.
    rows: CodeRows,
    /// The manifest without its levels, texture bytes, content version, patches and web
    /// tiles.
    manifest: Manifest,
    warnings: Vec<BuildWarning>,
    source_bytes: u64,
    /// Smallest and largest code, voids filled.
    code_range: (i32, i32),
    source_image: Option<image::RgbImage>,
    registration: Registration,
    heights_coder: heights::Coder,
    jpeg_quality: u8,
}

impl Prepared {
    /// What every tile shares.
    fn context(&self) -> TileContext<'_> {
        TileContext {
            tile_size: self.manifest.tile_size,
            quantum_m: self.manifest.heights.quantum_m,
            offset_m: self.manifest.heights.offset_m,
            code_range: self.code_range,
            heights_coder: self.heights_coder,
            texture_format: self.manifest.texture.format,
            jpeg_quality: self.jpeg_quality,
            texture_size: self.manifest.texture.size,
            level_zero_texture: match &self.source_image {
                Some(image) => LevelZeroTexture::Image {
                    image,
                    registration: self.registration,
                    raster: (self.manifest.raster.width, self.manifest.raster.height),
                },
                None => LevelZeroTexture::Generated {
                    spacing_m: self.manifest.spacing_m,
                    min_m: self.manifest.heights.min_m,
                    max_m: self.manifest.heights.max_m,
                },
            },
        }
    }
}

/// Opens the heights (a scan of every row, and the voids' passes when there are any), the
/// texture, and resolves every setting of the manifest from flags, the files and the
/// dataset.json, in that order.
fn prepare(options: &BuildOptions) -> Result<Prepared, BuildError> {
    let n = options.tile_size;
    // Only regular files: a device (`/dev/zero`), a FIFO or a directory has no size to
    // check a header against and would be read without end.
    input::check_regular_file(&options.heights)?;
    if let TextureChoice::Image(path) = &options.texture {
        input::check_regular_file(path)?;
    }
    let mut warnings = Vec::new();
    let dataset = input::DatasetInfo::beside(&options.heights)?;
    let (dataset_dir, info) = match dataset {
        Some((path, info)) => (path.parent().map(Path::to_path_buf), info),
        None => (None, input::DatasetInfo::default()),
    };
    let heights_input = open_heights(
        &options.heights,
        options.max_samples,
        &input::ReadOptions {
            nodata: options.nodata.or(info.nodata),
            float_quantum_m: options.float_quantum_m,
            out_of_range: options.out_of_range,
        },
    )?;
    if heights_input.out_of_range_voids > 0 {
        warnings.push(BuildWarning::OutOfRangeAsNodata {
            samples: heights_input.out_of_range_voids,
        });
    }
    let source_bytes = std::fs::metadata(&options.heights)
        .map(|m| m.len())
        .unwrap_or(0);

    let scale = options.height_scale.or(info.height_scale_m).unwrap_or(1.0);
    let offset = options
        .height_offset
        .or(info.height_offset_m)
        .unwrap_or(0.0);
    if !(scale.is_finite() && scale > 0.0 && offset.is_finite()) {
        return Err(BuildError::BadOption(format!(
            "height scale {scale} and offset {offset} must be finite, scale positive"
        )));
    }
    let quantum_m = heights_input.quantum_m * scale;
    let offset_m = heights_input.offset_m * scale + offset;
    let (width, height) = (heights_input.width, heights_input.height);
    let spacing_m = match options
        .spacing_m
        .or(heights_input.spacing_m)
        .or_else(|| info.spacing(height))
    {
        Some(s) if s.iter().all(|v| v.is_finite() && *v > 0.0) => s,
        Some(s) => {
            return Err(BuildError::BadOption(format!(
                "spacing {s:?} must be positive"
            )));
        }
        None => {
            warnings.push(BuildWarning::SpacingUnknown);
            [1.0, 1.0]
        }
    };
    let georeference: Option<Georeference> = heights_input
        .georeference
        .clone()
        .or_else(|| info.georeference());

    let filled_voids = heights_input
        .filled
        .as_ref()
        .map_or(0, |r| r.samples as u64);
    warnings.extend(heights_input.filled.clone().map(BuildWarning::FilledVoids));
    let (min_code, max_code) = heights_input.code_range;
    let (min_m, max_m) = (
        offset_m + quantum_m * f64::from(min_code),
        offset_m + quantum_m * f64::from(max_code),
    );

    // The texture source.
    let texture_path = match &options.texture {
        TextureChoice::Image(path) => Some(path.clone()),
        TextureChoice::Generated => None,
        TextureChoice::Auto => info
            .texture
            .as_ref()
            .zip(dataset_dir.as_ref())
            .map(|(t, dir)| dir.join(t)),
    };
    let source_image = match &texture_path {
        Some(path) => {
            let image = read_texture(path, options.max_samples)?;
            let (tw, th) = (f64::from(image.width()), f64::from(image.height()));
            let (rw, rh) = (f64::from(width - 1), f64::from(height - 1));
            if ((tw / th) / (rw / rh) - 1.0).abs() > 0.02 {
                warnings.push(BuildWarning::TextureAspect {
                    texture: [image.width(), image.height()],
                    raster: [width, height],
                });
            }
            Some(image)
        }
        None => None,
    };
    let registration = options
        .texture_registration
        .or_else(|| {
            info.texture_registration
                .as_deref()
                .and_then(Registration::from_dataset)
        })
        .unwrap_or(Registration::EdgeAligned);
    let texture_size = options.texture_size.unwrap_or_else(|| match &source_image {
        Some(image) => texture::size_for_source(image.width(), width, n),
        None => n - 1,
    });
    let texture_levels = texture::level_count(texture_size);
    let name = options
        .name
        .clone()
        .unwrap_or_else(|| default_name(&options.heights));
    let manifest = Manifest {
        format: manifest::FORMAT.into(),
        version: manifest::VERSION,
        dataset: name,
        content_version: String::new(),
        raster: RasterSize { width, height },
        tile_size: n,
        spacing_m,
        extent_m: [
            f64::from(width - 1) * spacing_m[0],
            f64::from(height - 1) * spacing_m[1],
        ],
        heights: HeightsInfo {
            codec: options.heights_coder.name().into(),
            quantum_m,
            offset_m,
            min_m,
            max_m,
            filled_voids,
        },
        texture: TextureInfo {
            format: options.texture_format,
            source: if source_image.is_some() {
                TextureSource::Image
            } else {
                TextureSource::Generated
            },
            size: texture_size,
            levels: texture_levels,
            level_bytes: Vec::new(),
        },
        georeference,
        mask_levels: mask::level_count(n),
        levels: Vec::new(),
        patches: None,
        web: None,
    };
    Ok(Prepared {
        rows: heights_input.rows,
        manifest,
        warnings,
        source_bytes,
        code_range: heights_input.code_range,
        source_image,
        registration,
        heights_coder: options.heights_coder,
        jpeg_quality: options.jpeg_quality,
    })
}

/// The heights a build reads, with what it must know before the first tile.
#[derive(Debug)]
struct HeightsInput {
    width: u32,
    height: u32,
    /// Metres per code step and metres at code 0, as far as the file knows.
    quantum_m: f64,
    offset_m: f64,
    georeference: Option<Georeference>,
    spacing_m: Option<[f64; 2]>,
    out_of_range_voids: usize,
    /// Smallest and largest code, voids filled.
    code_range: (i32, i32),
    filled: Option<voids::FillReport>,
    rows: CodeRows,
}

/// Opens the heights: streamed when the file allows it and has no voids, else read whole
/// and its voids filled (see the module docs).
fn open_heights(
    path: &Path,
    max_samples: u64,
    options: &input::ReadOptions,
) -> Result<HeightsInput, BuildError> {
    if let Some(reader) = input::rows::open(path, options)? {
        let header = reader.header();
        check_size(path, "heights", (header.width, header.height), max_samples)?;
        let scan = reader.scan()?;
        let (width, height) = (scan.header.width, scan.header.height);
        let mut rows = CodeRows::stream(&scan)?;
        let mut code_range = scan.code_range;
        let mut filled = None;
        if scan.voids > 0 {
            // Voids are found in one more pass over the rows, solved region by region in
            // another, and put in place as the build reads them (`voids`): the raster is
            // never held whole.
            let mut labeler = voids::Labeler::new();
            let mut find = CodeRows::stream(&scan)?;
            while let Some((_, v)) = find.next_row_with_voids()? {
                labeler.push(v);
            }
            let mut solving = CodeRows::stream(&scan)?;
            // The filled codes wait in an anonymous file of the system's temporary
            // directory: its errors name that directory.
            let spill = |source| input::InputError::Io {
                path: std::env::temp_dir(),
                source,
            };
            let store = voids::Store::file().map_err(spill)?;
            let fills = voids::solve(labeler.finish(), width, height, store, spill, || {
                solving
                    .next_row_with_voids()
                    .map(|row| row.map(|(c, v)| (c.to_vec(), v.to_vec())))
            })?;
            if let Some((low, high)) = fills.code_range() {
                code_range = (code_range.0.min(low), code_range.1.max(high));
            }
            filled = fills.report();
            rows = rows.with_fills(fills.stream());
        }
        return Ok(HeightsInput {
            width,
            height,
            quantum_m: scan.quantum_m,
            offset_m: 0.0,
            georeference: scan.header.georeference.clone(),
            spacing_m: scan.header.spacing_m,
            out_of_range_voids: scan.out_of_range_voids,
            code_range,
            rows,
            filled,
        });
    }
    // Only PNGs the row reader does not take (colour, interlaced) come here.
    let size = image_size(path).map_err(|message| input::InputError::Image {
        path: path.into(),
        message,
    })?;
    check_size(path, "heights", size, max_samples)?;
    let mut raster = input::read_heights(path, options)?;
    let (width, height) = (raster.width, raster.height);
    let voids = std::mem::take(&mut raster.voids);
    let filled = voids::fill(&mut raster.codes, &voids, width as usize, height as usize);
    drop(voids);
    let code_range = raster
        .codes
        .iter()
        .fold((i32::MAX, i32::MIN), |(lo, hi), &c| (lo.min(c), hi.max(c)));
    Ok(HeightsInput {
        width,
        height,
        quantum_m: raster.quantum_m,
        offset_m: raster.offset_m,
        georeference: raster.georeference,
        spacing_m: raster.spacing_m,
        out_of_range_voids: raster.out_of_range_voids,
        code_range,
        filled,
        rows: CodeRows::memory(raster.codes, width),
    })
}

/// Refuses a raster of more than `max_samples` samples, before its samples are read.
fn check_size(
    path: &Path,
    what: &'static str,
    (width, height): (u32, u32),
    max_samples: u64,
) -> Result<(), BuildError> {
    let samples = u64::from(width) * u64::from(height);
    if samples <= max_samples {
        return Ok(());
    }
    Err(BuildError::TooLarge {
        path: path.into(),
        what,
        width,
        height,
        samples,
        max: max_samples,
        file_bytes: std::fs::metadata(path).map_or(0, |m| m.len()),
    })
}

/// An image's width and height, from its header alone.
fn image_size(path: &Path) -> Result<(u32, u32), String> {
    use image::ImageDecoder as _;
    let decoder = image::ImageReader::open(path)
        .map_err(|e| e.to_string())?
        .with_guessed_format()
        .map_err(|e| e.to_string())?
        .into_decoder()
        .map_err(|e| e.to_string())?;
    Ok(decoder.dimensions())
}

/// Decodes a texture image whole, as RGB, when it holds at most `max_samples` pixels.
fn read_texture(path: &Path, max_samples: u64) -> Result<image::RgbImage, BuildError> {
    let texture_error = |message: String| BuildError::Texture {
        path: path.into(),
        message,
    };
    let size = image_size(path).map_err(texture_error)?;
    check_size(path, "a texture", size, max_samples)?;
    Ok(image::ImageReader::open(path)
        .map_err(|e| texture_error(e.to_string()))?
        .with_guessed_format()
        .map_err(|e| texture_error(e.to_string()))?
        .decode()
        .map_err(|e| texture_error(e.to_string()))?
        .into_rgb8())
}

/// Runs `terrain-server build`: progress bar, Ctrl-C cancels cleanly, summary at the end.
pub fn run_cli(args: BuildArgs) -> anyhow::Result<()> {
    let mut options = BuildOptions::from_args(&args)?;
    if let Some(region) = args.region {
        // A job for a store is written to a temporary jobs directory, then uploaded.
        let scratch = match &args.out {
            Some(crate::store::Location::Store(_)) => {
                let dir = tempfile::Builder::new()
                    .prefix("terrain-region-")
                    .tempdir()
                    .context("cannot make a temporary directory for the job")?;
                options.out = dir.path().join("jobs");
                Some(dir)
            }
            Some(crate::store::Location::Dir(_)) => None,
            None => {
                let name = args
                    .name
                    .clone()
                    .unwrap_or_else(|| default_name(&args.heights));
                options.out = Path::new("db").join(format!("{name}.jobs"));
                None
            }
        };
        let report = with_progress_bar(args.quiet, "building", |progress, stage, cancel| {
            jobs::build_region(&options, region, progress, stage, cancel)
        })
        .with_context(|| format!("building region {region} of {}", options.heights.display()))?;
        let mut report = report;
        let mut uploaded = None;
        if let (Some(crate::store::Location::Store(url)), Some(_dir)) = (&args.out, &scratch) {
            let started = Instant::now();
            let sent = jobs::upload_job(&report.out, region, url)
                .with_context(|| format!("uploading region {region} to {url}"))?;
            report.out = PathBuf::from(format!("{url}/{}", region.dir_name()));
            uploaded = Some(format!(
                "  uploaded  {:.1} MiB in {:.1} s\n",
                sent as f64 / (1024.0 * 1024.0),
                started.elapsed().as_secs_f64()
            ));
        }
        let text = report.to_string() + uploaded.as_deref().unwrap_or("");
        crate::print_stdout(&text).context("cannot write to stdout")?;
        return Ok(());
    }
    // A build for a store is written to a temporary directory first, removed at the end.
    let scratch = match &args.out {
        Some(crate::store::Location::Store(_)) => {
            let dir = tempfile::Builder::new()
                .prefix("terrain-build-")
                .tempdir()
                .context("cannot make a temporary directory for the build")?;
            options.out = dir.path().join("db");
            Some(dir)
        }
        _ => None,
    };
    let report = with_progress_bar(args.quiet, "building", |progress, stage, cancel| {
        build_in_stages(&options, progress, stage, cancel)
    })
    .with_context(|| format!("building {}", options.heights.display()))?;
    crate::print_stdout(&Summary(&report).to_string()).context("cannot write to stdout")?;
    if let (Some(crate::store::Location::Store(url)), Some(_dir)) = (&args.out, &scratch) {
        publish_cli(&report.out, url, args.quiet)?;
    }
    Ok(())
}

/// Runs `work` with a progress bar per stage (`verb` and the stage's name, its count, rate
/// and time left) and Ctrl-C wired to its cancel flag.
fn with_progress_bar<T>(
    quiet: bool,
    verb: &str,
    work: impl FnOnce(ProgressFn<'_>, &dyn Fn(Stage), &AtomicBool) -> Result<T, BuildError>,
) -> Result<T, BuildError> {
    let cancel = std::sync::Arc::new(AtomicBool::new(false));
    {
        let cancel = cancel.clone();
        // A second Ctrl-C while the build winds down still kills the process: the temporary
        // directory then stays behind under a hidden name, never at the output path.
        let _ = ctrlc::set_handler(move || {
            if cancel.swap(true, Ordering::Relaxed) {
                std::process::exit(130);
            }
        });
    }
    let bar = if quiet {
        indicatif::ProgressBar::hidden()
    } else {
        indicatif::ProgressBar::new(0)
    };
    let template = format!(
        "{{spinner}} {verb} {{msg}} [{{elapsed_precise}}] {{wide_bar}} {{pos}}/{{len}} ({{per_sec}}, {{eta}} left)"
    );
    bar.set_style(
        indicatif::ProgressStyle::with_template(&template)
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let on_progress = |done: usize, total: usize| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    };
    // One bar per stage: its count, elapsed time and rate start again.
    let on_stage = |stage: Stage| {
        bar.reset();
        bar.set_length(0);
        bar.set_message(stage.to_string());
    };
    let result = work(&on_progress, &on_stage, &cancel);
    bar.finish_and_clear();
    result
}

/// Uploads the database built in `dir` to `url` with a progress bar, and says what it did.
pub fn publish_cli(dir: &Path, url: &crate::store::StoreUrl, quiet: bool) -> anyhow::Result<()> {
    let total: u64 = std::fs::read_dir(dir)
        .with_context(|| format!("cannot read {}", dir.display()))?
        .flatten()
        .filter_map(|e| e.metadata().ok())
        .map(|m| m.len())
        .sum();
    let bar = if quiet {
        indicatif::ProgressBar::hidden()
    } else {
        indicatif::ProgressBar::new(total)
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} uploading [{elapsed_precise}] {wide_bar} {bytes}/{total_bytes} ({bytes_per_sec}, {eta} left)",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let started = std::time::Instant::now();
    let published = runtime.block_on(async {
        let store = crate::store::connect(url)?;
        crate::store::publish(&*store, dir, url, &|n| bar.set_position(n)).await
    });
    bar.finish_and_clear();
    let published = published.with_context(|| format!("publishing to {url}"))?;
    let text = if published.already_there {
        format!(
            "published {url}: content version {} was already there; the pointer names it\n",
            published.version
        )
    } else {
        format!(
            "published {url}: content version {}, {:.1} MiB uploaded in {:.1} s; the pointer names it\n",
            published.version,
            published.uploaded_bytes as f64 / (1024.0 * 1024.0),
            started.elapsed().as_secs_f64()
        )
    };
    crate::print_stdout(&text).context("cannot write to stdout")?;
    Ok(())
}

/// The end-of-build summary.
#[derive(Debug)]
pub struct Summary<'a>(pub &'a BuildReport);

impl fmt::Display for Summary<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let r = self.0;
        let m = &r.manifest;
        let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
        let samples = f64::from(m.raster.width) * f64::from(m.raster.height);
        writeln!(
            f,
            "built {} ({}) in {:.1} s",
            r.out.display(),
            m.dataset,
            r.elapsed.as_secs_f64()
        )?;
        writeln!(
            f,
            "  raster    {} x {} samples, spacing {:.1} x {:.1} m, heights {:.1} .. {:.1} m in steps of {} m",
            m.raster.width,
            m.raster.height,
            m.spacing_m[0],
            m.spacing_m[1],
            m.heights.min_m,
            m.heights.max_m,
            m.heights.quantum_m
        )?;
        writeln!(
            f,
            "  tiles     {} x {} = {} tiles of {}^2 samples at level 0; {} levels, {} tiles in all",
            m.grid(0).columns,
            m.grid(0).rows,
            m.levels[0].tiles.len(),
            m.tile_size,
            m.level_count(),
            m.tile_count(),
        )?;
        writeln!(
            f,
            "  heights   {:.2} MiB, {:.3} bytes/sample: {:.2}x smaller than 16-bit samples, {:.2}x smaller than the source file",
            mib(r.heights_bytes),
            r.heights_bytes as f64 / r.tile_samples as f64,
            (2 * r.tile_samples) as f64 / r.heights_bytes as f64,
            r.source_bytes as f64 / r.heights_bytes as f64,
        )?;
        writeln!(
            f,
            "  textures  {:.2} MiB, {} levels of {:?} per tile up to {}^2 texels, {}",
            mib(r.texture_bytes),
            m.texture.levels,
            m.texture.format,
            m.texture.size,
            match m.texture.source {
                TextureSource::Image => "from the texture image",
                TextureSource::Generated => "computed from the heights",
            }
        )?;
        if let Some(p) = &r.patches {
            writeln!(
                f,
                "  patches   {:.2} MiB in {:.1} s for {} patches: split bits {:.4} bytes/sample (1 bit a node, the paper's 0.06), heights {:.3} bytes/sample, index {:.1} KiB; {:.1}% of the samples active in the finest patches",
                mib(p.bodies_bytes + p.index_bytes),
                p.elapsed.as_secs_f64(),
                m.tile_count(),
                p.split_bytes as f64 / samples,
                p.height_bytes as f64 / samples,
                p.index_bytes as f64 / 1024.0,
                100.0 * p.active_vertices as f64 / samples,
            )?;
        }
        if let (Some(w), Some(info)) = (&r.web, &m.web) {
            writeln!(
                f,
                "  web       {:.2} MiB in {:.1} s: {} XYZ tiles (zoom 0-{}; Terrarium {:.2} MiB, Terrain-RGB {:.2} MiB, texture {:.2} MiB) and {} quantized-mesh tiles (level 0-{}, {:.2} MiB, {:.0} vertices a tile); bounds {:.5}, {:.5} .. {:.5}, {:.5} ({})",
                mib(info.tiles_bytes + info.index.bytes),
                w.seconds,
                w.xyz_tiles,
                info.xyz_max_zoom,
                mib(w.terrarium_bytes),
                mib(w.terrain_rgb_bytes),
                mib(w.texture_bytes),
                w.mesh_tiles,
                info.cesium_max_level,
                mib(w.mesh_bytes),
                w.mesh_vertices as f64 / w.mesh_tiles.max(1) as f64,
                info.bounds_deg[0],
                info.bounds_deg[1],
                info.bounds_deg[2],
                info.bounds_deg[3],
                info.crs,
            )?;
        }
        // Each product's seconds and source samples a second (the patches and the web tiles
        // are made after the tiles, from them).
        let rate = |seconds: f64| samples / seconds.max(1e-9) / 1e6;
        let tiles_s = r.tiles_elapsed.as_secs_f64();
        write!(
            f,
            "  speed     tiles, heights and textures {tiles_s:.1} s ({:.2} M samples/s)",
            rate(tiles_s)
        )?;
        if let Some(p) = &r.patches {
            let s = p.elapsed.as_secs_f64();
            write!(f, "; patches {s:.1} s ({:.2} M samples/s)", rate(s))?;
        }
        if let Some(w) = &r.web {
            write!(
                f,
                "; web {:.1} s ({:.2} M samples/s)",
                w.seconds,
                rate(w.seconds)
            )?;
        }
        writeln!(f)?;
        if r.warnings.is_empty() {
            writeln!(f, "  warnings  none")?;
        }
        for w in &r.warnings {
            writeln!(f, "  warning   {w}")?;
        }
        Ok(())
    }
}
