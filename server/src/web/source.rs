//! Heights and colours of a tile database at any point, read from its own tiles: what the
//! web tiles are resampled from, one pyramid level at a time, with a small cache of
//! decoded tiles (the web tiles are made in an order that keeps it warm).

use crate::db::TileDb;
use image::RgbImage;
use std::collections::HashMap;
use std::sync::Arc;
use terrain_shared::TileId;
use terrain_shared::heights::Heights;
use terrain_shared::tile_blob::TileBlob;
use thiserror::Error;

/// Decoded tiles a [`Sampler`] keeps before it starts again.
const CACHE_TILES: usize = 64;

/// A tile of the database that could not be read back while making the web tiles.
#[derive(Debug, Error)]
pub enum SourceError {
    #[error("tile {id:?} is missing from the database")]
    Missing { id: TileId },
    #[error("tile {id:?} does not decode: {message}")]
    Decode { id: TileId, message: String },
}

/// Reads heights and colours of one database, decoding tiles as needed.
#[derive(Debug)]
pub struct Sampler<'a> {
    db: &'a TileDb,
    heights: HashMap<TileId, Arc<Vec<f32>>>,
    textures: HashMap<TileId, Arc<RgbImage>>,
    errors: HashMap<TileId, f64>,
    /// The tile the last height came from: consecutive samples are mostly in one tile, and
    /// this answers them without a lookup.
    last_heights: Option<(TileId, Arc<Vec<f32>>)>,
}

impl<'a> Sampler<'a> {
    pub fn new(db: &'a TileDb) -> Sampler<'a> {
        Sampler {
            db,
            heights: HashMap::new(),
            textures: HashMap::new(),
            errors: HashMap::new(),
            last_heights: None,
        }
    }

    /// The tile of `level` holding level-`level` sample `(c, r)` (fractional, clamped to the
    /// level's raster), with the position inside it.
    fn locate(&self, level: u32, c: f64, r: f64) -> (TileId, f64, f64) {
        let manifest = self.db.manifest();
        let raster = manifest.levels[level as usize].raster;
        let step = f64::from(manifest.tile_size - 1);
        let c = c.clamp(0.0, f64::from(raster.width - 1));
        let r = r.clamp(0.0, f64::from(raster.height - 1));
        let grid = manifest.grid(level);
        let x = ((c / step).floor() as u32).min(grid.columns - 1);
        let y = ((r / step).floor() as u32).min(grid.rows - 1);
        let id = TileId { level, x, y };
        (id, c - f64::from(x) * step, r - f64::from(y) * step)
    }

    fn tile_heights(&mut self, id: TileId) -> Result<&[f32], SourceError> {
        if self
            .last_heights
            .as_ref()
            .is_none_or(|(last, _)| *last != id)
        {
            let h = self.load_heights(id)?;
            self.last_heights = Some((id, h));
        }
        Ok(self
            .last_heights
            .as_ref()
            .map_or(&[], |(_, h)| h.as_slice()))
    }

    fn load_heights(&mut self, id: TileId) -> Result<Arc<Vec<f32>>, SourceError> {
        if let Some(h) = self.heights.get(&id) {
            return Ok(h.clone());
        }
        let blob = self.db.heights(id).ok_or(SourceError::Missing { id })?;
        let decode = |message: String| SourceError::Decode { id, message };
        let tile = TileBlob::decode(&blob.bytes).map_err(|e| decode(e.to_string()))?;
        let heights = Heights::decode(&tile.heights).map_err(|e| decode(e.to_string()))?;
        if self.heights.len() >= CACHE_TILES {
            self.heights.clear();
        }
        let h = Arc::new(heights.to_metres_f32());
        self.heights.insert(id, h.clone());
        Ok(h)
    }

    /// Height in metres at level-0 sample `(col, row)` (fractional), bilinear between the
    /// samples of pyramid `level`.
    pub fn height(&mut self, level: u32, col: f64, row: f64) -> Result<f64, SourceError> {
        let scale = f64::from(1u32 << level);
        let (id, u, v) = self.locate(level, col / scale, row / scale);
        let n = self.db.manifest().tile_size as usize;
        let h = self.tile_heights(id)?;
        let (c0, r0) = (
            (u.floor() as usize).min(n - 1),
            (v.floor() as usize).min(n - 1),
        );
        let (c1, r1) = ((c0 + 1).min(n - 1), (r0 + 1).min(n - 1));
        let (fu, fv) = (u - c0 as f64, v - r0 as f64);
        let at = |c: usize, r: usize| f64::from(h[r * n + c]);
        let top = at(c0, r0) * (1.0 - fu) + at(c1, r0) * fu;
        let bottom = at(c0, r1) * (1.0 - fu) + at(c1, r1) * fu;
        Ok(top * (1.0 - fv) + bottom * fv)
    }

    /// The distance from the full-resolution surface of pyramid `level`'s tile holding
    /// level-0 sample `(col, row)`, metres, from its tile blob's error table.
    pub fn level_error(&mut self, level: u32, col: f64, row: f64) -> Result<f64, SourceError> {
        let scale = f64::from(1u32 << level);
        let (id, _, _) = self.locate(level, col / scale, row / scale);
        if let Some(&e) = self.errors.get(&id) {
            return Ok(e);
        }
        let blob = self.db.heights(id).ok_or(SourceError::Missing { id })?;
        let head = TileBlob::head(&blob.bytes).map_err(|e| SourceError::Decode {
            id,
            message: e.to_string(),
        })?;
        let e = f64::from(head.mask_errors_m.first().copied().unwrap_or(0.0));
        if self.errors.len() >= 16 * CACHE_TILES {
            self.errors.clear();
        }
        self.errors.insert(id, e);
        Ok(e)
    }

    fn tile_texture(&mut self, id: TileId) -> Result<Arc<RgbImage>, SourceError> {
        if let Some(t) = self.textures.get(&id) {
            return Ok(t.clone());
        }
        let finest = self.db.manifest().texture.levels.saturating_sub(1);
        let blob = self
            .db
            .texture(id, finest)
            .ok_or(SourceError::Missing { id })?;
        let image = image::load_from_memory(&blob.bytes)
            .map_err(|e| SourceError::Decode {
                id,
                message: e.to_string(),
            })?
            .to_rgb8();
        if self.textures.len() >= CACHE_TILES {
            self.textures.clear();
        }
        let t = Arc::new(image);
        self.textures.insert(id, t.clone());
        Ok(t)
    }

    /// Colour at level-0 sample `(col, row)`, bilinear between the texels of the finest
    /// texture of pyramid `level`'s tile there.
    pub fn colour(&mut self, level: u32, col: f64, row: f64) -> Result<[u8; 3], SourceError> {
        let scale = f64::from(1u32 << level);
        let (id, u, v) = self.locate(level, col / scale, row / scale);
        let step = f64::from(self.db.manifest().tile_size - 1);
        let t = self.tile_texture(id)?;
        let (w, h) = (t.width().max(1), t.height().max(1));
        // Texel i spans [i, i + 1] * step / size in sample units (`TextureInfo::size`).
        let tx = (u * f64::from(w) / step - 0.5).clamp(0.0, f64::from(w - 1));
        let ty = (v * f64::from(h) / step - 0.5).clamp(0.0, f64::from(h - 1));
        let (x0, y0) = (tx.floor() as u32, ty.floor() as u32);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (fx, fy) = (tx - f64::from(x0), ty - f64::from(y0));
        let mut out = [0u8; 3];
        for (k, o) in out.iter_mut().enumerate() {
            let at = |x: u32, y: u32| f64::from(t.get_pixel(x, y).0[k]);
            let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
            let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
            *o = (top * (1.0 - fy) + bottom * fy).round().clamp(0.0, 255.0) as u8;
        }
        Ok(out)
    }
}
