//! Makes a database's web tiles from its own pyramid, before the database is renamed into
//! place: XYZ Web Mercator tiles of the heights (Terrarium and Mapbox Terrain-RGB PNGs) and
//! of the texture (RGBA PNGs, transparent off the terrain), and quantized-mesh tiles on the
//! geographic scheme, each mesh a strip mask of a 65-sample grid chosen within Cesium's
//! error for its level. Every tile is resampled from the nearest finer level of the
//! pyramid; nothing finer than level 0 is made.

use super::crs::Placement;
use super::index::{Entry, Kind};
use super::quantized_mesh::{self, GeoRect};
use super::source::{Sampler, SourceError};
use super::tiling::{self, TileXyz};
use crate::db::TileDb;
use rayon::prelude::*;
use std::io::Write;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use terrain_shared::manifest::{Blob, ImageFormat, WEB_FORMAT, WebInfo};
use terrain_shared::mask;
use thiserror::Error;

/// Pixels per side of the XYZ tiles.
pub const XYZ_TILE_SIZE: u32 = 256;

#[derive(Debug, Error)]
pub enum WebError {
    #[error(transparent)]
    Source(#[from] SourceError),
    #[error("cannot place the raster on the globe: {0}")]
    Crs(#[from] super::crs::CrsError),
    #[error("cannot encode a web tile: {0}")]
    Encode(String),
    #[error("cannot write {path}: {source}")]
    Io {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
    #[error("build cancelled")]
    Cancelled,
}

/// What the web tiles cost, for the build report.
#[derive(Debug, Clone, Default)]
pub struct Stats {
    pub xyz_tiles: usize,
    pub terrarium_bytes: u64,
    pub terrain_rgb_bytes: u64,
    pub texture_bytes: u64,
    pub mesh_tiles: usize,
    pub mesh_bytes: u64,
    pub mesh_vertices: u64,
    pub seconds: f64,
}

/// One made tile, before it is written.
struct Made {
    entries: Vec<(Entry, Vec<u8>)>,
}

/// Terrarium: `h + 32768 = R * 256 + G + B / 256`, a 1/256 m quantum.
pub fn terrarium(h: f64) -> [u8; 3] {
    let v = ((h + 32768.0) * 256.0)
        .round()
        .clamp(0.0, f64::from(0xff_ffff)) as u32;
    [(v >> 16) as u8, (v >> 8) as u8, v as u8]
}

/// Mapbox Terrain-RGB: `h = -10000 + (R * 65536 + G * 256 + B) / 10`, a 0.1 m quantum.
pub fn terrain_rgb(h: f64) -> [u8; 3] {
    let v = ((h + 10000.0) * 10.0)
        .round()
        .clamp(0.0, f64::from(0xff_ffff)) as u32;
    [(v >> 16) as u8, (v >> 8) as u8, v as u8]
}

fn png(data: &[u8], size: u32, colour: png::ColorType) -> Result<Vec<u8>, WebError> {
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, size, size);
    encoder.set_color(colour);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Balanced);
    let encode = |e: png::EncodingError| WebError::Encode(e.to_string());
    let mut writer = encoder.write_header().map_err(encode)?;
    writer.write_image_data(data).map_err(encode)?;
    writer.finish().map_err(encode)?;
    Ok(out)
}

fn gzip(bytes: &[u8]) -> Result<Vec<u8>, WebError> {
    let mut encoder = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    let io = |source| WebError::Io {
        path: "gzip".into(),
        source,
    };
    encoder.write_all(bytes).map_err(io)?;
    encoder.finish().map_err(io)
}

/// The pyramid's terms: where the raster lies, its finer sample spacing, its coarsest level.
struct Frame {
    placement: Placement,
    width: f64,
    height: f64,
    sample_m: f64,
    coarsest: u32,
    centre_lat: f64,
    bounds: [f64; 4],
    /// Degrees of latitude between samples (at most), for margins.
    sample_deg: f64,
}

impl Frame {
    /// Level-0 sample coordinates of `(lon, lat)` if it lies on the raster.
    fn sample(&self, lon: f64, lat: f64) -> Result<Option<(f64, f64)>, WebError> {
        self.sample_near(lon, lat, 1e-6)
    }

    /// Level-0 sample coordinates of the point of the raster nearest `(lon, lat)`, on it or
    /// off it: where a web tile off the terrain takes its height, so that the surface ends
    /// level with the DEM's edge instead of falling to 0 m (a wall kilometres high at a
    /// high edge in MapLibre, a floating slab in Cesium).
    fn sample_clamped(&self, lon: f64, lat: f64) -> Result<(f64, f64), WebError> {
        let [w, s, e, n] = self.bounds;
        let (c, r) = self.placement.to_sample(lon.clamp(w, e), lat.clamp(s, n))?;
        Ok((
            c.clamp(0.0, self.width - 1.0),
            r.clamp(0.0, self.height - 1.0),
        ))
    }

    /// Level-0 sample coordinates of `(lon, lat)` if it lies on the raster or within
    /// `reach` samples of it, clamped onto the raster.
    fn sample_near(&self, lon: f64, lat: f64, reach: f64) -> Result<Option<(f64, f64)>, WebError> {
        // Far off the raster a projection may not even be defined.
        let [w, s, e, n] = self.bounds;
        let margin = 1e-3 * (e - w).max(n - s) + reach * self.sample_deg;
        if lon < w - margin || lon > e + margin || lat < s - margin || lat > n + margin {
            return Ok(None);
        }
        let (c, r) = self.placement.to_sample(lon, lat)?;
        let (wc, hr) = (self.width - 1.0, self.height - 1.0);
        Ok(
            (c >= -reach && r >= -reach && c <= wc + reach && r <= hr + reach)
                .then_some((c.clamp(0.0, wc), r.clamp(0.0, hr))),
        )
    }
}

fn xyz_tile(frame: &Frame, t: TileXyz, sampler: &mut Sampler) -> Result<Made, WebError> {
    let size = XYZ_TILE_SIZE;
    let pixel_m = tiling::mercator_pixel_m(frame.centre_lat, t.z, size);
    let level = tiling::nearest_finer_level(pixel_m, frame.sample_m, frame.coarsest);
    let n = (size * size) as usize;
    let (mut terr, mut rgb, mut tex) = (vec![0u8; n * 3], vec![0u8; n * 3], vec![0u8; n * 4]);
    // A pixel's longitude depends on its column alone and its latitude on its row alone: each
    // is worked out once per column or row, by the same function.
    let pixel = |k: u32| f64::from(k) + 0.5;
    let lons: Vec<f64> = (0..size)
        .map(|i| tiling::mercator_lon_lat(pixel(t.x * size + i), pixel(t.y * size), t.z, size).0)
        .collect();
    let lats: Vec<f64> = (0..size)
        .map(|j| tiling::mercator_lon_lat(pixel(t.x * size), pixel(t.y * size + j), t.z, size).1)
        .collect();
    for (j, &lat) in (0..size).zip(&lats) {
        for (i, &lon) in (0..size).zip(&lons) {
            let k = (j * size + i) as usize;
            let (h, colour) = match frame.sample(lon, lat)? {
                Some((c, r)) => (
                    sampler.height(level, c, r)?,
                    Some(sampler.colour(level, c, r)?),
                ),
                // Off the terrain: the nearest edge's height, no colour (transparent).
                None => {
                    let (c, r) = frame.sample_clamped(lon, lat)?;
                    (sampler.height(level, c, r)?, None)
                }
            };
            terr[k * 3..k * 3 + 3].copy_from_slice(&terrarium(h));
            rgb[k * 3..k * 3 + 3].copy_from_slice(&terrain_rgb(h));
            if let Some(c) = colour {
                tex[k * 4..k * 4 + 3].copy_from_slice(&c);
                tex[k * 4 + 3] = 255;
            }
        }
    }
    let entry = |kind| Entry {
        kind,
        z: t.z,
        x: t.x,
        y: t.y,
    };
    Ok(Made {
        entries: vec![
            (
                entry(Kind::Terrarium),
                png(&terr, size, png::ColorType::Rgb)?,
            ),
            (
                entry(Kind::TerrainRgb),
                png(&rgb, size, png::ColorType::Rgb)?,
            ),
            (entry(Kind::Texture), png(&tex, size, png::ColorType::Rgba)?),
        ],
    })
}

/// Height of the mesh of mask `level` over `grid` at grid position `(gx, gy)` (fractional,
/// row 0 north), by the triangle of the mask's cell there.
fn mesh_height(grid: &[f64], side: u32, kept: &[u32], gx: f64, gy: f64) -> f64 {
    let n = side as usize;
    // The kept indices are the multiples of a step, then the last: how many are at most `g`
    // is counted, not searched for (this runs for every sample under every mesh tile).
    let step = kept.get(1).copied().unwrap_or(1).max(1);
    let last = kept.last().copied().unwrap_or(0);
    let find = |g: f64| {
        let count = if g.is_nan() || g < 0.0 {
            0
        } else if g >= f64::from(last) {
            kept.len()
        } else {
            // The multiples of `step` up to `g`, all below the last; the quotient's rounding
            // corrected against the exact comparison.
            let mut k = (g / f64::from(step)) as u32;
            while k > 0 && f64::from(k * step) > g {
                k -= 1;
            }
            while f64::from((k + 1) * step) <= g {
                k += 1;
            }
            k as usize + 1
        };
        let i = count.clamp(1, kept.len() - 1);
        (kept[i - 1], kept[i])
    };
    let (c0, c1) = find(gx);
    let (r0, r1) = find(gy);
    let at = |c: u32, r: u32| grid[r as usize * n + c as usize];
    let u = ((gx - f64::from(c0)) / f64::from(c1 - c0)).clamp(0.0, 1.0);
    let v = ((gy - f64::from(r0)) / f64::from(r1 - r0)).clamp(0.0, 1.0);
    mask::cell_height(at(c0, r0), at(c1, r0), at(c0, r1), at(c1, r1), u, v)
}

/// A quantized-mesh tile and the largest distance of its mesh from the full-resolution
/// surface under it (at the samples of the pyramid level it was made from, plus that
/// level's own distance from level 0, from the tile blobs' error tables).
fn mesh_tile(
    frame: &Frame,
    t: TileXyz,
    finest: bool,
    sampler: &mut Sampler,
) -> Result<(Made, f64, u64), WebError> {
    let side = tiling::MESH_GRID;
    let [west, south, east, north] = tiling::geographic_rect(t);
    let d = east - west;
    let step_m = tiling::geographic_step_m(frame.centre_lat, t.z);
    let level = tiling::nearest_finer_level(step_m, frame.sample_m, frame.coarsest);
    // Grid points off the raster by less than a grid step take the nearest edge sample, so
    // every triangle over the raster is made of its heights; farther ones are at 0 m.
    let reach = (d / f64::from(side - 1)).to_radians() * tiling::EARTH_RADIUS_M / frame.sample_m;
    let mut grid = vec![0.0f64; (side * side) as usize];
    let mut any = false;
    for r in 0..side {
        for c in 0..side {
            let lon = west + d * f64::from(c) / f64::from(side - 1);
            let lat = north - d * f64::from(r) / f64::from(side - 1);
            match frame.sample_near(lon, lat, reach)? {
                Some((col, row)) => {
                    grid[(r * side + c) as usize] = sampler.height(level, col, row)?;
                    any = true;
                }
                // Off the terrain: the nearest edge's height (see `sample_clamped`).
                None => {
                    let (col, row) = frame.sample_clamped(lon, lat)?;
                    grid[(r * side + c) as usize] = sampler.height(level, col, row)?;
                }
            }
        }
    }
    // The pyramid level's samples inside the tile: where the mesh is measured.
    let mut checks: Vec<(f64, f64, f64)> = Vec::new();
    let mut level_error = 0.0f64;
    if any || t.z > 0 {
        let scale = f64::from(1u32 << level);
        let corners = [(west, north), (east, north), (west, south), (east, south)];
        let mut lo = (f64::MAX, f64::MAX);
        let mut hi = (f64::MIN, f64::MIN);
        for (lon, lat) in corners {
            let (c, r) = frame.placement.to_sample(lon, lat)?;
            lo = (lo.0.min(c), lo.1.min(r));
            hi = (hi.0.max(c), hi.1.max(r));
        }
        let last_c = ((frame.width - 1.0) / scale).floor();
        let last_r = ((frame.height - 1.0) / scale).floor();
        let c0 = (lo.0 / scale).floor().clamp(0.0, last_c) as u32;
        let c1 = (hi.0 / scale).ceil().clamp(0.0, last_c) as u32;
        let r0 = (lo.1 / scale).floor().clamp(0.0, last_r) as u32;
        let r1 = (hi.1 / scale).ceil().clamp(0.0, last_r) as u32;
        for r in r0..=r1 {
            for c in c0..=c1 {
                let (col, row) = (f64::from(c) * scale, f64::from(r) * scale);
                let (lon, lat) = frame.placement.to_lon_lat(col, row)?;
                if lon < west || lon > east || lat < south || lat > north {
                    continue;
                }
                let gx = (lon - west) / d * f64::from(side - 1);
                let gy = (north - lat) / d * f64::from(side - 1);
                let (h, error) = sampler.sample(level, c, r)?;
                checks.push((gx, gy, h));
                level_error = level_error.max(error);
            }
        }
    }
    let measure = |kept: &[u32]| {
        checks
            .iter()
            .map(|&(gx, gy, h)| (mesh_height(&grid, side, kept, gx, gy) - h).abs())
            .fold(0.0f64, f64::max)
    };
    let full = measure(&mask::kept_indices(side, 0));
    let grid_f32: Vec<f32> = grid.iter().map(|&h| h as f32).collect();
    let target = tiling::cesium_level_error_m(t.z);
    // The coarsest mask whose bound (its distance from the grid, plus the grid's from the
    // level's samples and the level's from level 0) is within Cesium's error of the level;
    // the finest level keeps the whole grid, the closest the meshes come to level 0.
    let mut chosen = 0;
    for m in (1..mask::level_count(side)).rev().filter(|_| !finest) {
        let bound = f64::from(mask::max_vertical_error(&grid_f32, side, m)) + full + level_error;
        if bound <= target {
            chosen = m;
            break;
        }
    }
    let (lo, hi) = grid
        .iter()
        .fold((f64::MAX, f64::MIN), |(lo, hi), &h| (lo.min(h), hi.max(h)));
    let quantum = (hi - lo) / 32767.0;
    // The finest mask is the grid itself, measured already.
    let mesh_error = if chosen == 0 {
        full
    } else {
        measure(&mask::kept_indices(side, chosen))
    };
    let error = mesh_error + level_error + quantum;
    let mesh = quantized_mesh::mesh_from_grid(&grid, side, chosen);
    let vertices = mesh.u.len() as u64;
    let rect = GeoRect {
        west,
        south,
        east,
        north,
    };
    let bytes = gzip(&quantized_mesh::encode(&rect, &mesh))?;
    Ok((
        Made {
            entries: vec![(
                Entry {
                    kind: Kind::QuantizedMesh,
                    z: t.z,
                    x: t.x,
                    y: t.y,
                },
                bytes,
            )],
        },
        error,
        vertices,
    ))
}

/// Tiles handed to rayon at once: enough that both halves of a split have work to steal
/// whatever the tiles cost, few enough that what they make is small (at most a few MiB).
const BATCH_PER_THREAD: usize = 16;

/// `make` over `tiles`, each tile a task of rayon's, each task with a cache of decoded tiles
/// of its own (rayon's `map_init`, reused across the tiles a thread takes in a row); results
/// in the tiles' order.
fn in_parallel<T: Send>(
    db: &TileDb,
    tiles: &[TileXyz],
    make: impl Fn(TileXyz, &mut Sampler) -> Result<T, WebError> + Sync,
    tick: &(dyn Fn() + Sync),
) -> Result<Vec<T>, WebError> {
    tiles
        .par_iter()
        .map_init(
            || Sampler::new(db),
            |sampler, &t| {
                let m = make(t, sampler);
                tick();
                m
            },
        )
        .collect()
}

/// Whether the database can have web tiles, and if not why (for the build's warning).
pub fn placement(db: &TileDb) -> Result<Placement, WebError> {
    Ok(Placement::new(db.manifest().georeference.as_ref())?)
}

/// Makes every web tile of `db` into `pack` (tiles, then the index), returning what the
/// manifest says of them.
pub fn build(
    db: &TileDb,
    placement: Placement,
    pack: &Path,
    progress: &(dyn Fn(usize, usize) + Sync),
    cancel: &AtomicBool,
) -> Result<(WebInfo, Stats), WebError> {
    let started = std::time::Instant::now();
    let manifest = db.manifest();
    let raster = manifest.raster;
    let bounds = placement.bounds(raster.width, raster.height)?;
    let sample_m = manifest.spacing_m[0].min(manifest.spacing_m[1]);
    let centre_lat = (bounds[1] + bounds[3]) / 2.0;
    let frame = Frame {
        placement,
        width: f64::from(raster.width),
        height: f64::from(raster.height),
        sample_m,
        coarsest: manifest.coarsest_level(),
        centre_lat,
        bounds,
        sample_deg: (sample_m.max(manifest.spacing_m[0].max(manifest.spacing_m[1]))
            / tiling::EARTH_RADIUS_M)
            .to_degrees()
            / centre_lat.to_radians().cos().max(0.01),
    };
    let max_zoom = tiling::mercator_max_zoom(centre_lat, sample_m, XYZ_TILE_SIZE);
    let max_level = tiling::geographic_max_level(centre_lat, sample_m);
    let xyz: Vec<TileXyz> = (0..=max_zoom)
        .flat_map(|z| tiling::mercator_tiles(bounds, z, XYZ_TILE_SIZE))
        .collect();
    let meshes: Vec<TileXyz> = (0..=max_level)
        .flat_map(|z| tiling::geographic_tiles(bounds, z))
        .collect();
    let total = xyz.len() + meshes.len();
    let done = AtomicUsize::new(0);
    let tick = || progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);

    let io = |source| WebError::Io {
        path: pack.to_path_buf(),
        source,
    };
    let mut file = std::io::BufWriter::new(std::fs::File::create(pack).map_err(io)?);
    let mut entries: Vec<(Entry, Blob)> = Vec::with_capacity(xyz.len() * 3 + meshes.len());
    let mut stats = Stats {
        xyz_tiles: xyz.len(),
        mesh_tiles: meshes.len(),
        ..Stats::default()
    };
    // Batches of tiles in row order, the tiles of each made in parallel; written in order.
    let batch = BATCH_PER_THREAD * rayon::current_num_threads();
    let mut write = |made: Made, stats: &mut Stats| -> Result<(), WebError> {
        for (entry, bytes) in made.entries {
            file.write_all(&bytes).map_err(io)?;
            let n = bytes.len() as u64;
            match entry.kind {
                Kind::Terrarium => stats.terrarium_bytes += n,
                Kind::TerrainRgb => stats.terrain_rgb_bytes += n,
                Kind::Texture => stats.texture_bytes += n,
                Kind::QuantizedMesh => stats.mesh_bytes += n,
            }
            entries.push((entry, Blob::of(&bytes)));
        }
        Ok(())
    };
    for tiles in xyz.chunks(batch) {
        if cancel.load(Ordering::Relaxed) {
            return Err(WebError::Cancelled);
        }
        let made = in_parallel(db, tiles, |t, sampler| xyz_tile(&frame, t, sampler), &tick)?;
        for m in made {
            write(m, &mut stats)?;
        }
    }
    let mut max_error = vec![0.0f64; max_level as usize + 1];
    for tiles in meshes.chunks(batch) {
        if cancel.load(Ordering::Relaxed) {
            return Err(WebError::Cancelled);
        }
        let made = in_parallel(
            db,
            tiles,
            |t, sampler| mesh_tile(&frame, t, t.z == max_level, sampler),
            &tick,
        )?;
        for (m, error, vertices) in made {
            let z = m.entries[0].0.z as usize;
            max_error[z] = max_error[z].max(error);
            stats.mesh_vertices += vertices;
            write(m, &mut stats)?;
        }
    }
    let tiles_bytes: u64 = entries.iter().map(|(_, b)| b.bytes).sum();
    let index = super::index::encode(&entries);
    file.write_all(&index).map_err(io)?;
    let file = file.into_inner().map_err(|e| io(e.into_error()))?;
    file.sync_all().map_err(io)?;
    stats.seconds = started.elapsed().as_secs_f64();
    Ok((
        WebInfo {
            format: WEB_FORMAT.into(),
            crs: frame.placement.crs().to_string(),
            bounds_deg: bounds,
            xyz_tile_size: XYZ_TILE_SIZE,
            xyz_max_zoom: max_zoom,
            xyz_texture: ImageFormat::Png,
            cesium_max_level: max_level,
            cesium_max_error_m: max_error,
            index: Blob::of(&index),
            tiles_bytes,
        },
        stats,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_encodings_decode_to_the_height_within_their_quantum() {
        for h in [-432.1, 0.0, 0.004, 1234.567, 8848.86] {
            let [r, g, b] = terrarium(h);
            let back = f64::from(r) * 256.0 + f64::from(g) + f64::from(b) / 256.0 - 32768.0;
            assert!(
                (back - h).abs() <= 0.5 / 256.0 + 1e-9,
                "terrarium {h}: {back}"
            );
            let [r, g, b] = terrain_rgb(h);
            let back =
                -10000.0 + (f64::from(r) * 65536.0 + f64::from(g) * 256.0 + f64::from(b)) * 0.1;
            assert!((back - h).abs() <= 0.05 + 1e-9, "terrain-rgb {h}: {back}");
        }
    }

    #[test]
    fn the_mesh_height_finds_the_cell_a_search_of_the_kept_indices_finds() {
        // The counted cell against a search, for every mask of a 65-sample grid, at points
        // on and between the kept indices and just off the grid.
        let side = 65u32;
        let grid: Vec<f64> = (0..side * side)
            .map(|i| f64::from((i * 7919) % 101) - 50.0)
            .collect();
        let searched = |kept: &[u32], gx: f64, gy: f64| {
            let find = |g: f64| {
                let i = kept
                    .partition_point(|&k| f64::from(k) <= g)
                    .clamp(1, kept.len() - 1);
                (kept[i - 1], kept[i])
            };
            let ((c0, c1), (r0, r1)) = (find(gx), find(gy));
            let at = |c: u32, r: u32| grid[(r * side + c) as usize];
            let u = ((gx - f64::from(c0)) / f64::from(c1 - c0)).clamp(0.0, 1.0);
            let v = ((gy - f64::from(r0)) / f64::from(r1 - r0)).clamp(0.0, 1.0);
            mask::cell_height(at(c0, r0), at(c1, r0), at(c0, r1), at(c1, r1), u, v)
        };
        let mut points = vec![-1.0, -1e-12, 64.0, 64.5, 1e9, f64::NAN];
        for k in 0..=640 {
            let g = f64::from(k) / 10.0;
            points.extend([g, g - 1e-12, g + 1e-12]);
        }
        for level in 0..mask::level_count(side) {
            let kept = mask::kept_indices(side, level);
            for (i, &gx) in points.iter().enumerate() {
                let gy = points[(i * 31) % points.len()];
                let (a, b) = (
                    mesh_height(&grid, side, &kept, gx, gy),
                    searched(&kept, gx, gy),
                );
                assert!(
                    a == b || (a.is_nan() && b.is_nan()),
                    "level {level} at ({gx}, {gy}): {a} against {b}"
                );
            }
        }
    }

    #[test]
    fn the_mesh_height_follows_the_masks_triangles() {
        // A 5x5 grid with one bump that mask level 1 drops: at the bump the level-0 mesh
        // has it, the level-1 mesh does not.
        let mut grid = vec![0.0; 25];
        grid[2 * 5 + 1] = 10.0;
        let k0 = mask::kept_indices(5, 0);
        let k1 = mask::kept_indices(5, 1);
        assert_eq!(mesh_height(&grid, 5, &k0, 1.0, 2.0), 10.0);
        assert_eq!(mesh_height(&grid, 5, &k0, 1.5, 2.0), 5.0);
        assert_eq!(mesh_height(&grid, 5, &k1, 1.0, 2.0), 0.0);
    }
}
