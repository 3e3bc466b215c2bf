//! The manifest: the one JSON document a client fetches first (the strip-mask paper's
//! "main file"). It describes the tile grid and carries, per tile, everything a client
//! needs before it fetches the tile itself: bounds, roughness, per-mask-level errors and
//! the content hash and size of every blob. `docs/manifest.md` documents every field.
//!
//! **Invariant:** tile records are in row-major order (`y * columns + x`); the server's
//! pack files hold the blobs in that same order, which is how it finds them.

use crate::tile::TileId;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Value of the `format` field.
pub const FORMAT: &str = "terrain-tiles";
/// Manifest schema version this crate writes and reads.
pub const VERSION: u32 = 1;

/// The whole description of one tile database.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Always [`FORMAT`].
    pub format: String,
    /// Schema version, [`VERSION`].
    pub version: u32,
    /// Short name of the dataset, e.g. `puget_sound_1k`.
    pub dataset: String,
    /// Hash over every blob hash and the grid: changes whenever any content changes.
    /// Tile URLs carry it, which is what lets caches keep tiles forever.
    pub content_version: String,
    /// Size of the source raster in samples; samples beyond it in edge tiles are padding.
    pub raster: RasterSize,
    /// Samples per tile side, `2^n + 1`; neighbouring tiles share a row or column.
    pub tile_size: u32,
    pub grid: GridSize,
    /// Distance between samples in metres: `[east-west, north-south]`.
    pub spacing_m: [f64; 2],
    /// Width and height of the real samples in metres: `(raster - 1) * spacing`.
    pub extent_m: [f64; 2],
    pub heights: HeightsInfo,
    pub texture: TextureInfo,
    /// Where the raster sits on the Earth, when the source said so.
    pub georeference: Option<Georeference>,
    /// Number of strip-mask levels per tile (`tile_size - 1`); every record has that many errors.
    pub mask_levels: u32,
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

/// Everything about one tile a client may need before it downloads it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileRecord {
    pub x: u32,
    pub y: u32,
    /// Real samples in this tile `[columns, rows]`; the rest repeats the last real one.
    pub valid: [u32; 2],
    pub min_m: f32,
    pub max_m: f32,
    /// Mean terrain ruggedness index (Riley et al. 1999) over the tile's samples, in metres.
    pub roughness_m: f32,
    /// Per strip-mask level, the largest vertical error against the full tile, metres,
    /// rounded up to the centimetre. Index 0 is the full tile (0).
    pub mask_errors_m: Vec<f32>,
    pub heights: Blob,
    /// Texture levels, coarsest first.
    pub texture: Vec<Blob>,
}

impl TileRecord {
    pub fn id(&self) -> TileId {
        TileId::new(self.x, self.y)
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

    /// Pretty JSON, as stored and served.
    pub fn to_json(&self) -> Vec<u8> {
        // Serialising plain data to a Vec cannot fail.
        serde_json::to_vec_pretty(self).unwrap_or_default()
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
        let expected = (self.grid.columns as usize) * (self.grid.rows as usize);
        if self.tiles.len() != expected {
            return bad(format!(
                "{} tile records for a {}x{} grid",
                self.tiles.len(),
                self.grid.columns,
                self.grid.rows
            ));
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
        if self.texture.levels == 0 || self.texture.level_size(0) == 0 {
            return bad("texture has no levels".into());
        }
        for (i, tile) in self.tiles.iter().enumerate() {
            let (x, y) = (
                (i % self.grid.columns as usize) as u32,
                (i / self.grid.columns as usize) as u32,
            );
            if (tile.x, tile.y) != (x, y) {
                return bad(format!(
                    "record {i} is tile {}/{}, expected {x}/{y}",
                    tile.x, tile.y
                ));
            }
            if tile.mask_errors_m.len() != self.mask_levels as usize {
                return bad(format!(
                    "tile {x}/{y} has {} mask errors",
                    tile.mask_errors_m.len()
                ));
            }
            if tile.texture.len() != self.texture.levels as usize {
                return bad(format!(
                    "tile {x}/{y} has {} texture levels",
                    tile.texture.len()
                ));
            }
            if tile.valid[0] == 0 || tile.valid[1] == 0 || tile.valid[0] > n || tile.valid[1] > n {
                return bad(format!("tile {x}/{y} has {:?} valid samples", tile.valid));
            }
        }
        Ok(())
    }

    /// The record of one tile, if it lies inside the grid.
    pub fn tile(&self, id: TileId) -> Option<&TileRecord> {
        if id.x >= self.grid.columns || id.y >= self.grid.rows {
            return None;
        }
        self.tiles
            .get(id.y as usize * self.grid.columns as usize + id.x as usize)
    }

    /// Position of sample `(x, y)` of tile `id` in metres from sample (0, 0) of the raster,
    /// x east, y south.
    pub fn sample_position_m(&self, id: TileId, x: u32, y: u32) -> [f64; 2] {
        let step = f64::from(self.tile_size - 1);
        [
            (f64::from(id.x) * step + f64::from(x)) * self.spacing_m[0],
            (f64::from(id.y) * step + f64::from(y)) * self.spacing_m[1],
        ]
    }

    /// Content version computed from the grid and every blob hash, as the builder sets it.
    pub fn compute_content_version(&self) -> String {
        let mut text = format!(
            "{FORMAT}/{VERSION}/{}/{}x{}",
            self.tile_size, self.grid.columns, self.grid.rows
        );
        for tile in &self.tiles {
            text.push(' ');
            text.push_str(&tile.heights.hash);
            for level in &tile.texture {
                text.push(',');
                text.push_str(&level.hash);
            }
        }
        content_hash(text.as_bytes())[..16].to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texture_levels_past_the_bits_of_the_size_are_empty_not_a_panic() {
        let texture = TextureInfo {
            format: ImageFormat::Png,
            source: TextureSource::Generated,
            size: 128,
            levels: 40,
        };
        let sizes: Vec<u32> = [0, 7, 31, 32, 38, 39].map(|l| texture.level_size(l)).into();
        assert_eq!(sizes, [0, 0, 0, 1, 64, 128]);
    }
}
