//! A small hand-made tile database, written through the server's own [`DbWriter`], for
//! tests that need a real database but not the builder.
//!
//! A 2x2 grid of 17x17-sample tiles whose height codes follow a known formula
//! ([`SyntheticDb::codes`]) over the whole raster, so neighbouring tiles agree on their
//! shared edge, and two tiny PNG texture levels per tile (4 and 8 texels a side); above it,
//! level 1 of the pyramid, one tile of every other sample.
//! [`SyntheticDb::write_with_large_texture`] additionally replaces the finest texture of
//! one tile by many pseudo-random bytes: not a decodable image, only a body large enough
//! that sending it takes a client's cooperation (transport tests).

use anyhow::Context;
use std::io::Cursor;
use std::path::{Path, PathBuf};
use terrain_server::db::DbWriter;
use terrain_shared::manifest::{GridSize, ImageFormat, RasterSize, TextureInfo, TextureSource};
use terrain_shared::{Blob, Heights, Manifest, TileBlob, TileId, TileRecord};

/// Samples per tile side (`2^4 + 1`).
pub const TILE_SIZE: u32 = 17;
pub const GRID: GridSize = GridSize {
    columns: 2,
    rows: 2,
};
/// Texture levels per tile; level `l` is `4 << l` texels a side.
pub const TEXTURE_LEVELS: u32 = 2;
/// Metres per height code.
pub const QUANTUM_M: f64 = 0.25;
/// Metres at code 0.
pub const OFFSET_M: f64 = -100.0;
/// The tile and level [`SyntheticDb::write_with_large_texture`] makes large.
pub const LARGE_TEXTURE: (TileId, u32) = (TileId::new(1, 1), TEXTURE_LEVELS - 1);

/// A database written to a temporary directory, removed on drop, with the bytes of every
/// blob kept for comparison.
#[derive(Debug)]
pub struct SyntheticDb {
    _root: tempfile::TempDir,
    dir: PathBuf,
    manifest: Manifest,
    /// Per tile in manifest order (every level), the tile blob.
    heights: Vec<Vec<u8>>,
    /// Per tile in manifest order, the texture levels coarsest first.
    textures: Vec<Vec<Vec<u8>>>,
}

impl SyntheticDb {
    /// The plain synthetic database.
    pub fn write() -> anyhow::Result<SyntheticDb> {
        Self::write_inner(None)
    }

    /// The synthetic database with the texture at [`LARGE_TEXTURE`] replaced by `bytes`
    /// pseudo-random bytes.
    pub fn write_with_large_texture(bytes: usize) -> anyhow::Result<SyntheticDb> {
        Self::write_inner(Some(bytes))
    }

    /// The database directory, for `TileDb::open` or `terrain-server serve`.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// Every tile of level 0, row-major.
    pub fn tile_ids(&self) -> Vec<TileId> {
        self.manifest
            .tiles()
            .filter(|(id, _)| id.level == 0)
            .map(|(id, _)| id)
            .collect()
    }

    /// Every tile of every level, in manifest order.
    pub fn all_tile_ids(&self) -> Vec<TileId> {
        self.manifest.tiles().map(|(id, _)| id).collect()
    }

    /// The tile blob of `id` as written (what its heights route serves).
    pub fn heights(&self, id: TileId) -> &[u8] {
        &self.heights[self.index(id)]
    }

    /// Texture `level` of `id` as written.
    pub fn texture(&self, id: TileId, level: u32) -> &[u8] {
        &self.textures[self.index(id)][level as usize]
    }

    fn index(&self, id: TileId) -> usize {
        self.manifest
            .index(id)
            .expect("a tile of the synthetic grid")
    }

    /// The height codes of tile `id`: `1000 + 3 gx + 5 gy + (gx gy mod 7)` at level-0
    /// sample `(gx, gy)` (a tile of level `k` keeps every `2^k`-th), a tilted plane with some
    /// texture so the codec's residuals are not all zero.
    pub fn codes(id: TileId) -> Heights {
        let step = TILE_SIZE - 1;
        let mut codes = Vec::with_capacity((TILE_SIZE * TILE_SIZE) as usize);
        for y in 0..TILE_SIZE {
            for x in 0..TILE_SIZE {
                let (gx, gy) = (
                    ((id.x * step + x) << id.level) as i32,
                    ((id.y * step + y) << id.level) as i32,
                );
                codes.push(1000 + 3 * gx + 5 * gy + (gx * gy) % 7);
            }
        }
        Heights {
            width: TILE_SIZE as u16,
            height: TILE_SIZE as u16,
            quantum_m: QUANTUM_M,
            offset_m: OFFSET_M,
            codes,
        }
    }

    fn write_inner(large_texture: Option<usize>) -> anyhow::Result<SyntheticDb> {
        let root = tempfile::tempdir().context("cannot create a temporary directory")?;
        let dir = root.path().join("synthetic");
        let mut writer = DbWriter::create(&dir, false)?;
        let mask_levels = terrain_shared::mask::level_count(TILE_SIZE);
        let raster = RasterSize {
            width: (TILE_SIZE - 1) * GRID.columns + 1,
            height: (TILE_SIZE - 1) * GRID.rows + 1,
        };
        let texture = TextureInfo {
            format: ImageFormat::Png,
            source: TextureSource::Generated,
            size: 4 << (TEXTURE_LEVELS - 1),
            levels: TEXTURE_LEVELS,
            level_bytes: Vec::new(),
        };
        let placeholder = |_| TileRecord::empty();
        let mut manifest = Manifest::with_geometry(
            "synthetic",
            raster,
            TILE_SIZE,
            [10.0, 10.0],
            texture,
            placeholder,
        );
        let (mut heights, mut textures) = (Vec::new(), Vec::new());
        let (mut min_code, mut max_code) = (i32::MAX, i32::MIN);
        let ids: Vec<TileId> = manifest.tiles().map(|(id, _)| id).collect();
        for id in ids {
            let tile = Self::codes(id);
            let (low, high) = tile.code_range();
            min_code = min_code.min(low);
            max_code = max_code.max(high);
            let mut levels = Vec::new();
            for level in 0..TEXTURE_LEVELS {
                levels.push(match large_texture {
                    Some(size) if (id, level) == LARGE_TEXTURE => pseudo_random_bytes(size),
                    _ => texture_png(id, 4 << level)?,
                });
            }
            let blob = TileBlob {
                // Level 0 is the full tile; the others are plausible, not computed.
                mask_errors_m: (0..mask_levels).map(|level| level as f32 * 0.25).collect(),
                texture: levels.iter().map(|l| Blob::of(l)).collect(),
                heights: tile.encode()?,
            }
            .encode();
            let stored = writer.add_heights(&blob)?;
            for (l, level) in levels.iter().enumerate() {
                manifest.texture.level_bytes[l] += writer.add_texture(level)?.bytes;
            }
            let metres = |code: i32| (OFFSET_M + QUANTUM_M * f64::from(code)) as f32;
            let level = &mut manifest.levels[id.level as usize];
            level.tiles[(id.y * level.grid.columns + id.x) as usize] = TileRecord {
                hash: stored.hash,
                bytes: stored.bytes,
                coarsest_texture_bytes: levels[0].len() as u64,
                min_m: metres(low),
                max_m: metres(high),
                roughness_m: 1.0,
            };
            heights.push(blob);
            textures.push(levels);
        }
        manifest.heights.quantum_m = QUANTUM_M;
        manifest.heights.offset_m = OFFSET_M;
        manifest.heights.min_m = OFFSET_M + QUANTUM_M * f64::from(min_code);
        manifest.heights.max_m = OFFSET_M + QUANTUM_M * f64::from(max_code);
        manifest.content_version = manifest.compute_content_version();
        manifest.validate()?;
        writer.finish(&manifest)?;
        Ok(SyntheticDb {
            _root: root,
            dir,
            manifest,
            heights,
            textures,
        })
    }
}

/// A `size`-texel PNG whose colour encodes the tile, so levels and tiles all differ.
fn texture_png(id: TileId, size: u32) -> anyhow::Result<Vec<u8>> {
    let image = image::RgbImage::from_fn(size, size, |x, y| {
        image::Rgb([
            (id.x * 100 + x * 10) as u8,
            (id.y * 100 + y * 10) as u8,
            (size + 40 * id.level) as u8,
        ])
    });
    let mut png = Cursor::new(Vec::new());
    image
        .write_to(&mut png, image::ImageFormat::Png)
        .context("cannot encode a synthetic texture")?;
    Ok(png.into_inner())
}

/// xorshift64: incompressible, reproducible bytes without a random-number crate.
fn pseudo_random_bytes(size: usize) -> Vec<u8> {
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut bytes = Vec::with_capacity(size + 8);
    while bytes.len() < size {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        bytes.extend_from_slice(&state.to_le_bytes());
    }
    bytes.truncate(size);
    bytes
}
