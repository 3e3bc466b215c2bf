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
    /// this answers them without a lookup. The same for colours and error tables.
    last_heights: Option<(TileId, Arc<Vec<f32>>)>,
    last_texture: Option<(TileId, Arc<RgbImage>)>,
    last_error: Option<(TileId, f64)>,
    /// Per pyramid level, what [`Sampler::locate`] reads of the manifest: the last sample's
    /// column and row, the last tile's column and row.
    levels: Vec<LevelBounds>,
    /// Samples per tile side, and cells (`tile_size - 1`).
    tile_size: usize,
    step: f64,
    /// `1 / step` where `step` is a power of two (as tiles of `2^n + 1` samples make it):
    /// multiplying by it is then exactly dividing by the step, and faster.
    per_step: Option<f64>,
}

/// The extent of one pyramid level, in samples and in tiles.
#[derive(Debug, Clone, Copy)]
struct LevelBounds {
    last_c: f64,
    last_r: f64,
    last_x: u32,
    last_y: u32,
}

impl<'a> Sampler<'a> {
    pub fn new(db: &'a TileDb) -> Sampler<'a> {
        let manifest = db.manifest();
        let levels = manifest
            .levels
            .iter()
            .map(|l| LevelBounds {
                last_c: f64::from(l.raster.width.saturating_sub(1)),
                last_r: f64::from(l.raster.height.saturating_sub(1)),
                last_x: l.grid.columns.saturating_sub(1),
                last_y: l.grid.rows.saturating_sub(1),
            })
            .collect();
        Sampler {
            db,
            heights: HashMap::new(),
            textures: HashMap::new(),
            errors: HashMap::new(),
            last_heights: None,
            last_texture: None,
            last_error: None,
            levels,
            tile_size: manifest.tile_size as usize,
            step: f64::from(manifest.tile_size - 1),
            per_step: (manifest.tile_size - 1)
                .is_power_of_two()
                .then(|| 1.0 / f64::from(manifest.tile_size - 1)),
        }
    }

    /// The tile of `level` holding level-`level` sample `(c, r)` (fractional, clamped to the
    /// level's raster), with the position inside it.
    ///
    /// Called for every pixel of every web tile: the level's bounds are read from
    /// [`Sampler::levels`], and the floors are casts (the values are clamped non-negative,
    /// where a cast truncates as `floor` does).
    #[inline]
    fn locate(&self, level: u32, c: f64, r: f64) -> (TileId, f64, f64) {
        let bounds = self.levels[level as usize];
        let step = self.step;
        let c = c.clamp(0.0, bounds.last_c);
        let r = r.clamp(0.0, bounds.last_r);
        let (cx, ry) = match self.per_step {
            Some(per_step) => (c * per_step, r * per_step),
            None => (c / step, r / step),
        };
        let x = (cx as u32).min(bounds.last_x);
        let y = (ry as u32).min(bounds.last_y);
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
        // Dividing by a power of two is multiplying by its inverse, exactly.
        let per_scale = 1.0 / f64::from(1u32 << level);
        let (id, u, v) = self.locate(level, col * per_scale, row * per_scale);
        let n = self.tile_size;
        let h = self.tile_heights(id)?;
        // Casts as floors: a negative `u` (rounding at a tile's first column) saturates to 0,
        // as its floor would.
        let (c0, r0) = ((u as usize).min(n - 1), (v as usize).min(n - 1));
        let (c1, r1) = ((c0 + 1).min(n - 1), (r0 + 1).min(n - 1));
        let (fu, fv) = (u - c0 as f64, v - r0 as f64);
        let at = |c: usize, r: usize| f64::from(h[r * n + c]);
        let top = at(c0, r0) * (1.0 - fu) + at(c1, r0) * fu;
        let bottom = at(c0, r1) * (1.0 - fu) + at(c1, r1) * fu;
        Ok(top * (1.0 - fv) + bottom * fv)
    }

    /// Height in metres of sample `(c, r)` of pyramid `level` itself (what [`Sampler::height`]
    /// gives at level-0 sample `(c, r) * 2^level`), with the distance of the level's tile
    /// there from the full-resolution surface, from its tile blob's error table.
    pub fn sample(&mut self, level: u32, c: u32, r: u32) -> Result<(f64, f64), SourceError> {
        let (id, u, v) = self.locate(level, f64::from(c), f64::from(r));
        let n = self.tile_size;
        let error = self.tile_error(id)?;
        let h = self.tile_heights(id)?;
        let (c0, r0) = ((u as usize).min(n - 1), (v as usize).min(n - 1));
        Ok((f64::from(h[r0 * n + c0]), error))
    }

    /// The first entry of tile `id`'s error table, metres: its distance from the
    /// full-resolution surface.
    fn tile_error(&mut self, id: TileId) -> Result<f64, SourceError> {
        if let Some((last, e)) = self.last_error
            && last == id
        {
            return Ok(e);
        }
        if let Some(&e) = self.errors.get(&id) {
            self.last_error = Some((id, e));
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
        self.last_error = Some((id, e));
        Ok(e)
    }

    fn tile_texture(&mut self, id: TileId) -> Result<&RgbImage, SourceError> {
        if self
            .last_texture
            .as_ref()
            .is_none_or(|(last, _)| *last != id)
        {
            let t = self.load_texture(id)?;
            self.last_texture = Some((id, t));
        }
        Ok(self
            .last_texture
            .as_ref()
            .map(|(_, t)| &**t)
            .expect("set above"))
    }

    fn load_texture(&mut self, id: TileId) -> Result<Arc<RgbImage>, SourceError> {
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
        let per_scale = 1.0 / f64::from(1u32 << level);
        let (id, u, v) = self.locate(level, col * per_scale, row * per_scale);
        let step = self.step;
        let t = self.tile_texture(id)?;
        let (w, h) = (t.width().max(1), t.height().max(1));
        // Texel i spans [i, i + 1] * step / size in sample units (`TextureInfo::size`).
        let tx = (u * f64::from(w) / step - 0.5).clamp(0.0, f64::from(w - 1));
        let ty = (v * f64::from(h) / step - 0.5).clamp(0.0, f64::from(h - 1));
        // Clamped non-negative: the casts are floors.
        let (x0, y0) = (tx as u32, ty as u32);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (fx, fy) = (tx - f64::from(x0), ty - f64::from(y0));
        let texels = t.as_raw();
        let row = w as usize * 3;
        let mut out = [0u8; 3];
        for (k, o) in out.iter_mut().enumerate() {
            let at = |x: u32, y: u32| f64::from(texels[y as usize * row + x as usize * 3 + k]);
            let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
            let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
            *o = (top * (1.0 - fy) + bottom * fy).round().clamp(0.0, 255.0) as u8;
        }
        Ok(out)
    }
}
