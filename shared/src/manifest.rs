//! The manifest: the one JSON document a client fetches first (the strip-mask paper's
//! "main file"). It describes the pyramid of tile grids and carries, per tile, only what a
//! client needs before it fetches the tile: bounds, roughness and the hash and size of the
//! tile blob, which brings the rest (`crate::tile_blob`). `docs/api.md` documents every
//! field.
//!
//! **Invariant:** levels are listed finest first and tile records are row-major within a
//! level (`y * columns + x`); the server's pack files hold the blobs in that same order,
//! which is how it finds them.

use crate::tile::TileId;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Value of the `format` field.
pub const FORMAT: &str = "terrain-tiles";
/// Manifest schema version this crate writes and reads.
pub const VERSION: u32 = 2;

/// The whole description of one tile database.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Always [`FORMAT`].
    pub format: String,
    /// Schema version, [`VERSION`].
    pub version: u32,
    /// Short name of the dataset, e.g. `puget_sound_1k`.
    pub dataset: String,
    /// Hash over every tile hash and the grids: changes whenever any content changes.
    /// Tile URLs carry it, which is what lets caches keep tiles forever.
    pub content_version: String,
    /// Size of the source raster (level 0) in samples; samples beyond it in edge tiles are
    /// padding.
    pub raster: RasterSize,
    /// Samples per tile side, `2^n + 1`, at every level; neighbouring tiles share a row or
    /// column.
    pub tile_size: u32,
    /// Distance between level-0 samples in metres: `[east-west, north-south]`.
    pub spacing_m: [f64; 2],
    /// Width and height of the real samples in metres: `(raster - 1) * spacing`.
    pub extent_m: [f64; 2],
    pub heights: HeightsInfo,
    pub texture: TextureInfo,
    /// Where the raster sits on the Earth, when the source said so.
    pub georeference: Option<Georeference>,
    /// Number of strip-mask levels per tile (`tile_size - 1`); every tile blob has that
    /// many errors.
    pub mask_levels: u32,
    /// The pyramid, level 0 (full resolution) first; the last level is one tile.
    pub levels: Vec<Level>,
    /// The quadtree progressive patches ([`crate::quadtree`]), when the database was built
    /// with them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub patches: Option<PatchesInfo>,
    /// The tiles the web's own clients read (MapLibre's XYZ tiles, Cesium's
    /// quantized-mesh), when the source was georeferenced.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub web: Option<WebInfo>,
}

/// Value of [`WebInfo::format`].
pub const WEB_FORMAT: &str = "terrain-web/1";

/// Where a database's web tiles are (`web.pack`: every tile in the index's order, then the
/// index) and what pyramids they make. `docs/api.md` documents the routes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WebInfo {
    /// Always [`WEB_FORMAT`].
    pub format: String,
    /// The source's coordinate reference system, e.g. `EPSG:4326`.
    pub crs: String,
    /// Longitude and latitude bounds of the samples, degrees: `[west, south, east, north]`.
    pub bounds_deg: [f64; 4],
    /// Pixels per side of an XYZ (Web Mercator) tile.
    pub xyz_tile_size: u32,
    /// The finest XYZ zoom: the last whose pixels are no finer than level 0's samples.
    pub xyz_max_zoom: u32,
    /// Format of the XYZ texture tiles.
    pub xyz_texture: ImageFormat,
    /// The finest level of the quantized-mesh pyramid (geographic tiling scheme).
    pub cesium_max_level: u32,
    /// Per quantized-mesh level, the largest vertical distance of any of its meshes from
    /// the full-resolution surface under it, metres.
    pub cesium_max_error_m: Vec<f64>,
    /// The index: per tile its kind, coordinates, hash and size.
    pub index: Blob,
    /// Bytes of every tile together (the index follows them in the pack).
    pub tiles_bytes: u64,
}

/// Where a database's quadtree patches are: one body per tile (a patch of the meta
/// quadtree is a tile of the pyramid), in the manifest's tile order, then the index
/// ([`crate::quadtree::encode_index`]), all in `patches.pack`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PatchesInfo {
    /// Always [`crate::quadtree::FORMAT`].
    pub format: String,
    /// The world-space tolerance of the finest patches, metres.
    pub tolerance_m: f64,
    /// The index: per patch its hash, size, error and height bounds.
    pub index: Blob,
    /// Bytes of every body together (the index follows them in the pack).
    pub bodies_bytes: u64,
}

/// One level of the pyramid: level `k` keeps every `2^k`-th sample of level 0.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Level {
    /// Samples of this level ([`level_rasters`]).
    pub raster: RasterSize,
    pub grid: GridSize,
    /// One entry per tile, row-major (`y * columns + x`).
    pub tiles: Vec<TileRecord>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct RasterSize {
    pub width: u32,
    pub height: u32,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct GridSize {
    pub columns: u32,
    pub rows: u32,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HeightsInfo {
    /// Name and version of the tile codec, [`crate::heights::CODEC_NAME`].
    pub codec: String,
    /// Metres per height code step: the source's own precision.
    pub quantum_m: f64,
    /// Metres at code 0.
    pub offset_m: f64,
    pub min_m: f64,
    pub max_m: f64,
    /// Source samples that were no-data and got filled from their neighbours.
    pub filled_voids: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ImageFormat {
    Jpeg,
    Png,
}

impl ImageFormat {
    pub fn content_type(self) -> &'static str {
        match self {
            ImageFormat::Jpeg => "image/jpeg",
            ImageFormat::Png => "image/png",
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TextureSource {
    /// Resampled from the image given to the builder.
    Image,
    /// Computed from the heights: hypsometric tint with hill shading.
    Generated,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TextureInfo {
    pub format: ImageFormat,
    pub source: TextureSource,
    /// Texels per side of the finest level. The texture of a tile covers exactly the square
    /// from its first to its last sample, edge to edge: texel `i` of `size` spans
    /// `[i, i + 1] * (tile_size - 1) / size` in sample units, so its centre sits at
    /// `(i + 0.5) * (tile_size - 1) / size`, the usual GPU convention.
    pub size: u32,
    /// Number of levels; level 0 is the coarsest, each next level doubles the side.
    pub levels: u32,
    /// Encoded bytes of each texture level (coarsest first) over every tile of every level
    /// of the pyramid: what holding them all costs, before the tile blobs say it per tile.
    #[serde(default)]
    pub level_bytes: Vec<u64>,
}

impl TextureInfo {
    /// Texels per side of `level` (0 = coarsest).
    pub fn level_size(&self, level: u32) -> u32 {
        // 0 when the levels outnumber the bits of the size: a shift of 32 or more is no
        // halving at all for `>>`.
        self.size
            .checked_shr(self.levels.saturating_sub(1).saturating_sub(level))
            .unwrap_or(0)
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Georeference {
    /// Coordinate reference system, e.g. `EPSG:4326`, when known.
    pub crs: Option<String>,
    /// Coordinates of sample (0, 0), the north-west one, in CRS units.
    pub origin: [f64; 2],
    /// Step between samples in CRS units: `[x, y]`, y usually negative.
    pub sample_step: [f64; 2],
}

/// Everything about one tile a client needs before it downloads it: what paging and culling
/// need, and the hash that verifies the tile blob (`crate::tile_blob`), which carries the
/// rest (mask errors, texture hashes). Serialised as a six-element array
/// `[hash, bytes, coarsest_texture_bytes, min_m, max_m, roughness_m]` to keep the manifest
/// small.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(from = "RecordRow", into = "RecordRow")]
pub struct TileRecord {
    /// BLAKE3 of the tile blob, first 16 bytes in hex: also its entity tag.
    pub hash: String,
    /// Size of the tile blob.
    pub bytes: u64,
    /// Size of the coarsest texture level, fetched with the tile: with `bytes`, what a
    /// client will hold for the tile before it asks for it.
    pub coarsest_texture_bytes: u64,
    /// Height bounds of the full-resolution surface under the tile, metres.
    pub min_m: f32,
    pub max_m: f32,
    /// Mean terrain ruggedness index (Riley et al. 1999) over the tile's samples, metres.
    pub roughness_m: f32,
}

type RecordRow = (String, u64, u64, f32, f32, f32);

impl From<RecordRow> for TileRecord {
    fn from(
        (hash, bytes, coarsest_texture_bytes, min_m, max_m, roughness_m): RecordRow,
    ) -> TileRecord {
        TileRecord {
            hash,
            bytes,
            coarsest_texture_bytes,
            min_m,
            max_m,
            roughness_m,
        }
    }
}

impl From<TileRecord> for RecordRow {
    fn from(r: TileRecord) -> RecordRow {
        (
            r.hash,
            r.bytes,
            r.coarsest_texture_bytes,
            r.min_m,
            r.max_m,
            r.roughness_m,
        )
    }
}

impl TileRecord {
    /// A record of nothing yet (zero hash and sizes, flat at 0 m): what a manifest is
    /// shaped with ([`Manifest::with_geometry`]) before its tiles are written.
    pub fn empty() -> TileRecord {
        TileRecord {
            hash: "0".repeat(32),
            bytes: 0,
            coarsest_texture_bytes: 0,
            min_m: 0.0,
            max_m: 0.0,
            roughness_m: 0.0,
        }
    }

    /// The blob this record verifies.
    pub fn blob(&self) -> Blob {
        Blob {
            hash: self.hash.clone(),
            bytes: self.bytes,
        }
    }
}

/// The raster of every level of the pyramid over a `width x height` level 0: level `k + 1`
/// keeps every other sample of level `k` (`ceil((w - 1) / 2) + 1` samples; its last sample
/// stands on level `k`'s last one when `w - 1` is even, and one sample past it, repeating
/// it, when odd), until a level fits in one tile of `tile_size`.
pub fn level_rasters(raster: RasterSize, tile_size: u32) -> Vec<RasterSize> {
    let mut levels = vec![raster];
    let mut r = raster;
    while (r.width > tile_size || r.height > tile_size) && levels.len() < 32 {
        r = RasterSize {
            width: (r.width.saturating_sub(1)).div_ceil(2) + 1,
            height: (r.height.saturating_sub(1)).div_ceil(2) + 1,
        };
        levels.push(r);
    }
    levels
}

/// The fewest tiles of `tile_size` that cover `raster`; edge tiles are padded.
pub fn grid_covering(raster: RasterSize, tile_size: u32) -> GridSize {
    let step = tile_size.saturating_sub(1).max(1);
    GridSize {
        columns: raster.width.saturating_sub(1).div_ceil(step).max(1),
        rows: raster.height.saturating_sub(1).div_ceil(step).max(1),
    }
}

/// One stored object: its content hash and its size.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Blob {
    /// BLAKE3 of the bytes, first 16 bytes in hex: also the HTTP entity tag.
    pub hash: String,
    pub bytes: u64,
}

impl Blob {
    pub fn of(bytes: &[u8]) -> Blob {
        Blob {
            hash: content_hash(bytes),
            bytes: bytes.len() as u64,
        }
    }
}

/// The content hash used everywhere: BLAKE3, first 128 bits, lowercase hex.
pub fn content_hash(bytes: &[u8]) -> String {
    let digest = blake3::hash(bytes);
    digest.as_bytes()[..16]
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Why a manifest was refused.
#[derive(Debug, Error)]
pub enum ManifestError {
    #[error("manifest is not valid JSON for this schema: {0}")]
    // Not a `#[source]`: the message carries it, so a cause chain prints it once.
    Json(serde_json::Error),
    #[error("not a tile manifest: format {0:?}")]
    WrongFormat(String),
    #[error("manifest version {found} is not supported (this build reads {VERSION})")]
    UnsupportedVersion { found: u32 },
    #[error("inconsistent manifest: {0}")]
    Inconsistent(String),
}

impl Manifest {
    /// Parses and checks a manifest: schema, version and internal consistency.
    pub fn from_json(bytes: &[u8]) -> Result<Manifest, ManifestError> {
        let manifest: Manifest = serde_json::from_slice(bytes).map_err(ManifestError::Json)?;
        manifest.validate()?;
        Ok(manifest)
    }

    /// Compact JSON, as stored and served (a tile record is one short array).
    pub fn to_json(&self) -> Vec<u8> {
        // Serialising plain data to a Vec cannot fail.
        serde_json::to_vec(self).unwrap_or_default()
    }

    /// Checks what the types cannot: counts, order and sizes agree.
    pub fn validate(&self) -> Result<(), ManifestError> {
        let bad = |m: String| Err(ManifestError::Inconsistent(m));
        if self.format != FORMAT {
            return Err(ManifestError::WrongFormat(self.format.clone()));
        }
        if self.version != VERSION {
            return Err(ManifestError::UnsupportedVersion {
                found: self.version,
            });
        }
        let n = self.tile_size;
        if n < 3 || !(n - 1).is_power_of_two() || n > u32::from(crate::heights::MAX_SIDE) {
            return bad(format!(
                "tile size {n} is not 2^k + 1 up to {}",
                crate::heights::MAX_SIDE
            ));
        }
        if self.raster.width < 2 || self.raster.height < 2 {
            return bad(format!(
                "raster of {}x{} samples",
                self.raster.width, self.raster.height
            ));
        }
        let rasters = level_rasters(self.raster, n);
        if self.levels.len() != rasters.len() {
            return bad(format!(
                "{} levels where a {}x{} raster in tiles of {n} has {}",
                self.levels.len(),
                self.raster.width,
                self.raster.height,
                rasters.len()
            ));
        }
        for (k, (level, raster)) in self.levels.iter().zip(&rasters).enumerate() {
            if level.raster != *raster {
                return bad(format!(
                    "level {k} has {}x{} samples, expected {}x{}",
                    level.raster.width, level.raster.height, raster.width, raster.height
                ));
            }
            let grid = grid_covering(*raster, n);
            if level.grid != grid {
                return bad(format!(
                    "level {k} has a {}x{} grid, expected {}x{}",
                    level.grid.columns, level.grid.rows, grid.columns, grid.rows
                ));
            }
            let expected = (grid.columns as usize) * (grid.rows as usize);
            if level.tiles.len() != expected {
                return bad(format!(
                    "level {k}: {} tile records for a {}x{} grid",
                    level.tiles.len(),
                    grid.columns,
                    grid.rows
                ));
            }
            if let Some(i) = level
                .tiles
                .iter()
                .position(|t| t.hash.len() != 32 || !t.hash.bytes().all(|b| b.is_ascii_hexdigit()))
            {
                return bad(format!("level {k}: tile record {i} has no 32-digit hash"));
            }
        }
        if self.mask_levels != crate::mask::level_count(n) {
            return bad(format!("{} mask levels for tiles of {n}", self.mask_levels));
        }
        let extent = [
            f64::from(self.raster.width.saturating_sub(1)) * self.spacing_m[0],
            f64::from(self.raster.height.saturating_sub(1)) * self.spacing_m[1],
        ];
        if extent
            .iter()
            .zip(self.extent_m)
            .any(|(derived, stated)| (derived - stated).abs() > 1e-6 * derived.abs().max(1.0))
        {
            return bad(format!(
                "extent {:?} m does not match (raster - 1) * spacing = {extent:?} m",
                self.extent_m
            ));
        }
        if self.texture.levels == 0 || self.texture.levels > 16 || self.texture.level_size(0) == 0 {
            return bad("texture has no levels, or more than 16".into());
        }
        if self.texture.level_bytes.len() != self.texture.levels as usize {
            return bad(format!(
                "{} texture level sizes for {} levels",
                self.texture.level_bytes.len(),
                self.texture.levels
            ));
        }
        Ok(())
    }

    /// A manifest of the pyramid over a `raster` cut into tiles of `tile_size`, every tile's
    /// record made by `record`, its content version computed: for tests and tools that need
    /// the geometry (a database's is written by the builder).
    pub fn with_geometry(
        dataset: &str,
        raster: RasterSize,
        tile_size: u32,
        spacing_m: [f64; 2],
        texture: TextureInfo,
        record: impl Fn(TileId) -> TileRecord,
    ) -> Manifest {
        let levels = level_rasters(raster, tile_size)
            .into_iter()
            .enumerate()
            .map(|(k, raster)| {
                let grid = grid_covering(raster, tile_size);
                let tiles = (0..grid.rows)
                    .flat_map(|y| (0..grid.columns).map(move |x| (x, y)))
                    .map(|(x, y)| record(TileId::at(k as u32, x, y)))
                    .collect();
                Level {
                    raster,
                    grid,
                    tiles,
                }
            })
            .collect();
        let mut manifest = Manifest {
            format: FORMAT.into(),
            version: VERSION,
            dataset: dataset.into(),
            content_version: String::new(),
            raster,
            tile_size,
            spacing_m,
            extent_m: [
                f64::from(raster.width.saturating_sub(1)) * spacing_m[0],
                f64::from(raster.height.saturating_sub(1)) * spacing_m[1],
            ],
            heights: HeightsInfo {
                codec: crate::heights::CODEC_NAME.into(),
                quantum_m: 1.0,
                offset_m: 0.0,
                min_m: 0.0,
                max_m: 0.0,
                filled_voids: 0,
            },
            texture,
            georeference: None,
            patches: None,
            web: None,
            mask_levels: crate::mask::level_count(tile_size),
            levels,
        };
        manifest
            .texture
            .level_bytes
            .resize(manifest.texture.levels as usize, 0);
        manifest.content_version = manifest.compute_content_version();
        manifest
    }

    /// Number of levels of the pyramid (at least 1).
    pub fn level_count(&self) -> u32 {
        self.levels.len() as u32
    }

    /// The coarsest level, which one tile covers.
    pub fn coarsest_level(&self) -> u32 {
        self.level_count().saturating_sub(1)
    }

    /// The tile grid of `level` (an empty grid past the last level).
    pub fn grid(&self, level: u32) -> GridSize {
        self.levels.get(level as usize).map_or(
            GridSize {
                columns: 0,
                rows: 0,
            },
            |l| l.grid,
        )
    }

    /// Metres between the samples of `level`: level 0's spacing times `2^level`.
    pub fn level_spacing_m(&self, level: u32) -> [f64; 2] {
        let scale = f64::from(1u32 << level.min(31));
        [self.spacing_m[0] * scale, self.spacing_m[1] * scale]
    }

    /// The record of one tile, if it lies inside its level's grid.
    pub fn tile(&self, id: TileId) -> Option<&TileRecord> {
        self.index(id).map(|i| self.record_at(i))
    }

    /// Tiles of every level together: the length of the client's dense per-tile slices.
    pub fn tile_count(&self) -> usize {
        self.levels.iter().map(|l| l.tiles.len()).sum()
    }

    /// Where the tiles of `level` start in the dense order of every level (level 0 first,
    /// each level row-major).
    pub fn level_offset(&self, level: u32) -> usize {
        self.levels
            .iter()
            .take(level as usize)
            .map(|l| l.tiles.len())
            .sum()
    }

    /// Position of `id` in the dense order of every level, if it lies inside its grid.
    pub fn index(&self, id: TileId) -> Option<usize> {
        let level = self.levels.get(id.level as usize)?;
        if id.x >= level.grid.columns || id.y >= level.grid.rows {
            return None;
        }
        Some(
            self.level_offset(id.level)
                + id.y as usize * level.grid.columns as usize
                + id.x as usize,
        )
    }

    /// The tile at position `index` of the dense order.
    ///
    /// # Panics
    ///
    /// When `index >= tile_count()`.
    pub fn id_at(&self, index: usize) -> TileId {
        let mut rest = index;
        for (k, level) in self.levels.iter().enumerate() {
            if rest < level.tiles.len() {
                let columns = level.grid.columns as usize;
                return TileId::at(k as u32, (rest % columns) as u32, (rest / columns) as u32);
            }
            rest -= level.tiles.len();
        }
        panic!("tile index {index} past the {} tiles", self.tile_count())
    }

    fn record_at(&self, index: usize) -> &TileRecord {
        let id = self.id_at(index);
        let level = &self.levels[id.level as usize];
        &level.tiles[id.y as usize * level.grid.columns as usize + id.x as usize]
    }

    /// Every tile of every level with its record, in the dense order.
    pub fn tiles(&self) -> impl Iterator<Item = (TileId, &TileRecord)> + '_ {
        self.levels.iter().enumerate().flat_map(|(k, level)| {
            let columns = level.grid.columns as usize;
            level.tiles.iter().enumerate().map(move |(i, record)| {
                (
                    TileId::at(k as u32, (i % columns) as u32, (i / columns) as u32),
                    record,
                )
            })
        })
    }

    /// Real samples `[columns, rows]` of tile `id`; the rest of its `tile_size` repeats the
    /// last real one. Zero for a tile outside its grid.
    pub fn valid(&self, id: TileId) -> [u32; 2] {
        let Some(level) = self.levels.get(id.level as usize) else {
            return [0, 0];
        };
        let step = self.tile_size - 1;
        let real = |first: u32, count: u32| count.saturating_sub(first).min(self.tile_size);
        [
            real(id.x.saturating_mul(step), level.raster.width),
            real(id.y.saturating_mul(step), level.raster.height),
        ]
    }

    /// The existing tiles of the next finer level that `id` covers.
    pub fn children(&self, id: TileId) -> Vec<TileId> {
        id.children()
            .map(|c| c.into_iter().filter(|c| self.index(*c).is_some()).collect())
            .unwrap_or_default()
    }

    /// Position of sample `(x, y)` of tile `id` in metres from sample (0, 0) of the raster,
    /// x east, y south.
    pub fn sample_position_m(&self, id: TileId, x: u32, y: u32) -> [f64; 2] {
        let step = f64::from(self.tile_size - 1);
        let spacing = self.level_spacing_m(id.level);
        [
            (f64::from(id.x) * step + f64::from(x)) * spacing[0],
            (f64::from(id.y) * step + f64::from(y)) * spacing[1],
        ]
    }

    /// Content version computed from the grids and every tile hash, as the builder sets it.
    pub fn compute_content_version(&self) -> String {
        let mut text = format!("{FORMAT}/{VERSION}/{}", self.tile_size);
        for level in &self.levels {
            text.push_str(&format!(" {}x{}:", level.grid.columns, level.grid.rows));
            for tile in &level.tiles {
                text.push(' ');
                text.push_str(&tile.hash);
            }
        }
        if let Some(p) = &self.patches {
            text.push_str(&format!(" patches {}", p.index.hash));
        }
        if let Some(w) = &self.web {
            text.push_str(&format!(" web {}", w.index.hash));
        }
        content_hash(text.as_bytes())[..16].to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_halve_until_one_tile_holds_a_level() {
        let r = |width, height| RasterSize { width, height };
        assert_eq!(
            level_rasters(r(4097, 4097), 129),
            [
                r(4097, 4097),
                r(2049, 2049),
                r(1025, 1025),
                r(513, 513),
                r(257, 257),
                r(129, 129)
            ]
        );
        // 344 - 1 = 343 cells, odd: 172 at level 1 (its last sample one past, padded), 86
        // at level 2.
        assert_eq!(
            level_rasters(r(403, 344), 129),
            [r(403, 344), r(202, 173), r(102, 87)]
        );
        assert_eq!(level_rasters(r(100, 50), 129), [r(100, 50)]);
        // A level's grid is its parent level's halved, rounded up.
        for raster in [r(4097, 4097), r(403, 344), r(10801, 6001), r(130, 2000)] {
            let rasters = level_rasters(raster, 65);
            for pair in rasters.windows(2) {
                let (fine, coarse) = (grid_covering(pair[0], 65), grid_covering(pair[1], 65));
                assert_eq!(coarse.columns, fine.columns.div_ceil(2), "{raster:?}");
                assert_eq!(coarse.rows, fine.rows.div_ceil(2), "{raster:?}");
            }
            let last = grid_covering(*rasters.last().expect("one level at least"), 65);
            assert_eq!((last.columns, last.rows), (1, 1), "{raster:?}");
        }
    }

    #[test]
    fn texture_levels_past_the_bits_of_the_size_are_empty_not_a_panic() {
        let texture = TextureInfo {
            format: ImageFormat::Png,
            source: TextureSource::Generated,
            size: 128,
            levels: 40,
            level_bytes: Vec::new(),
        };
        let sizes: Vec<u32> = [0, 7, 31, 32, 38, 39].map(|l| texture.level_size(l)).into();
        assert_eq!(sizes, [0, 0, 0, 1, 64, 128]);
    }
}
