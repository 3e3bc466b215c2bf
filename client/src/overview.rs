//! The overview: one picture of the whole terrain, pasted together from every tile's
//! finest texture level and cropped to the real extent of the raster.
//!
//! Pure: encoded images and the manifest in, one [`RgbImage`] out. Fetching the textures
//! and writing the picture are the caller's ([`crate::cli`]).
//!
//! Geometry: tile `(x, y)` covers texels `[x * size, (x + 1) * size)` of the full-resolution
//! mosaic (`size` = the manifest's finest texture side). Neighbouring tiles share a row of
//! samples but not texels, because a tile's texture spans its `tile_size - 1` cells edge to
//! edge. An edge tile holds `valid` real samples, `valid - 1` real cells, so only
//! `(valid - 1) / (tile_size - 1)` of its texture is terrain; the rest is padding, cut off.

use image::{RgbImage, imageops};
use terrain_shared::manifest::ImageFormat;
use terrain_shared::{Manifest, TileId};
use thiserror::Error;

/// Why no overview could be made.
#[derive(Debug, Error)]
pub enum OverviewError {
    #[error("the manifest's grid has no tiles")]
    EmptyGrid,
    #[error("tile {id} is not in the {columns}x{rows} grid")]
    NotInGrid { id: TileId, columns: u32, rows: u32 },
    #[error("texture of tile {id} does not decode as {format:?}")]
    Decode {
        id: TileId,
        format: ImageFormat,
        #[source]
        source: image::ImageError,
    },
    #[error("texture of tile {id} is {width}x{height} texels; the finest level is {size}x{size}")]
    WrongSize {
        id: TileId,
        width: u32,
        height: u32,
        size: u32,
    },
}

/// Size in pixels of the overview [`mosaic`] makes for `manifest`: the real extent at the
/// finest texture level, scaled down (never up) so the longer side is at most `max_side`.
pub fn overview_size(manifest: &Manifest, max_side: u32) -> Result<(u32, u32), OverviewError> {
    let full = real_extent(manifest)?;
    Ok(scaled(full, max_side))
}

/// Decodes each tile's finest texture level (`finest_levels`: tile and encoded image, in
/// the manifest's texture format) and pastes them into one picture of the whole terrain,
/// at most `max_side` pixels on its longer side. Tiles missing from the list stay black.
///
/// Each tile is scaled down before it is pasted, so memory stays at one tile plus the
/// output however large the terrain is.
pub fn mosaic<B: AsRef<[u8]>>(
    manifest: &Manifest,
    finest_levels: &[(TileId, B)],
    max_side: u32,
) -> Result<RgbImage, OverviewError> {
    let full = real_extent(manifest)?;
    let out = scaled(full, max_side);
    let size = manifest.texture.size;
    let format = manifest.texture.format;
    let mut canvas = RgbImage::new(out.0, out.1);
    for (id, bytes) in finest_levels {
        let id = *id;
        if id.level != 0 || manifest.tile(id).is_none() {
            return Err(OverviewError::NotInGrid {
                id,
                columns: manifest.grid(0).columns,
                rows: manifest.grid(0).rows,
            });
        }
        let decoded = image::load_from_memory_with_format(bytes.as_ref(), image_format(format))
            .map_err(|source| OverviewError::Decode { id, format, source })?;
        if (decoded.width(), decoded.height()) != (size, size) {
            return Err(OverviewError::WrongSize {
                id,
                width: decoded.width(),
                height: decoded.height(),
                size,
            });
        }
        let (x0, x1) = (
            scale_position(id.x, size, full.0, out.0),
            scale_position(id.x + 1, size, full.0, out.0),
        );
        let (y0, y1) = (
            scale_position(id.y, size, full.1, out.1),
            scale_position(id.y + 1, size, full.1, out.1),
        );
        if x1 == x0 || y1 == y0 || x0 >= out.0 || y0 >= out.1 {
            continue; // Smaller than a pixel, or all padding.
        }
        let rgb = decoded.to_rgb8();
        let tile = if (x1 - x0, y1 - y0) == (size, size) {
            rgb
        } else {
            // Area averaging: every texel counts, which is what a downscaled picture of
            // detailed terrain needs (a point filter would alias ridges into noise).
            imageops::thumbnail(&rgb, x1 - x0, y1 - y0)
        };
        // `replace` clips at the canvas edge, which is the crop to the real extent.
        imageops::replace(&mut canvas, &tile, i64::from(x0), i64::from(y0));
    }
    Ok(canvas)
}

/// The `image` crate's name for a manifest texture format.
pub fn image_format(format: ImageFormat) -> image::ImageFormat {
    match format {
        ImageFormat::Jpeg => image::ImageFormat::Jpeg,
        ImageFormat::Png => image::ImageFormat::Png,
    }
}

/// The most bytes [`mosaic`]'s picture takes as a PNG, known before a tile is fetched: its
/// RGB rows with their filter bytes, stored uncompressed at worst (deflate's stored blocks
/// and the chunk headers add well under 1%), and the PNG's own headers.
pub fn png_bound(manifest: &Manifest, max_side: u32) -> Result<u64, OverviewError> {
    let (width, height) = scaled(real_extent(manifest)?, max_side);
    let rows = u64::from(height) * (3 * u64::from(width) + 1);
    Ok(rows + rows / 64 + 4096)
}

/// Texels of real terrain in the full-resolution mosaic, `(width, height)`.
fn real_extent(manifest: &Manifest) -> Result<(u32, u32), OverviewError> {
    let grid = manifest.grid(0);
    let (columns, rows) = (grid.columns, grid.rows);
    if columns == 0 || rows == 0 {
        return Err(OverviewError::EmptyGrid);
    }
    let last = manifest.valid(TileId::new(columns - 1, rows - 1));
    let (last_column, last_row) = (std::iter::once(last[0]), std::iter::once(last[1]));
    let axis = |count: u32, last_valid: u32| {
        let size = u64::from(manifest.texture.size);
        let cells = u64::from(manifest.tile_size.saturating_sub(1).max(1));
        // Partly covered texels count: the picture keeps every real sample.
        let last = (u64::from(last_valid.saturating_sub(1)) * size).div_ceil(cells);
        let texels = u64::from(count - 1) * size + last;
        u32::try_from(texels).unwrap_or(u32::MAX).max(1)
    };
    Ok((
        axis(columns, last_column.max().unwrap_or(1)),
        axis(rows, last_row.max().unwrap_or(1)),
    ))
}

/// `full` scaled down so its longer side is at most `max_side`; never scaled up.
fn scaled(full: (u32, u32), max_side: u32) -> (u32, u32) {
    let longest = full.0.max(full.1);
    let max_side = max_side.max(1);
    if longest <= max_side {
        return full;
    }
    let side = |n: u32| {
        let n = (u64::from(n) * u64::from(max_side) + u64::from(longest) / 2) / u64::from(longest);
        (n as u32).max(1)
    };
    (side(full.0), side(full.1))
}

/// Output pixel of the edge before tile `index` along an axis: rounding the edges rather
/// than the tile widths makes neighbouring tiles meet without gaps or overlaps.
fn scale_position(index: u32, size: u32, full: u32, out: u32) -> u32 {
    let texel = u64::from(index) * u64::from(size);
    let pixel = (texel * u64::from(out) * 2 + u64::from(full)) / (2 * u64::from(full));
    u32::try_from(pixel).unwrap_or(u32::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::Rgb;
    use std::io::Cursor;
    use terrain_shared::TileRecord;
    use terrain_shared::manifest::{RasterSize, TextureInfo, TextureSource};

    /// 3-sample tiles over a `raster` of samples, textures of `size` texels.
    fn manifest(raster: (u32, u32), size: u32) -> Manifest {
        Manifest::with_geometry(
            "test",
            RasterSize {
                width: raster.0,
                height: raster.1,
            },
            3,
            [1.0, 1.0],
            TextureInfo {
                format: ImageFormat::Png,
                source: TextureSource::Generated,
                size,
                levels: 1,
                level_bytes: Vec::new(),
            },
            |_| TileRecord::empty(),
        )
    }

    /// A solid `size`-square PNG whose colour names the tile: red = 60 x + 10, green = 60 y + 10.
    fn texture(id: TileId, size: u32) -> Vec<u8> {
        let image = RgbImage::from_pixel(size, size, colour(id));
        let mut png = Vec::new();
        image
            .write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png)
            .expect("encodes");
        png
    }

    fn colour(id: TileId) -> Rgb<u8> {
        Rgb([60 * id.x as u8 + 10, 60 * id.y as u8 + 10, 200])
    }

    fn all_textures(manifest: &Manifest) -> Vec<(TileId, Vec<u8>)> {
        manifest
            .tiles()
            .filter(|(id, _)| id.level == 0)
            .map(|(id, _)| (id, texture(id, manifest.texture.size)))
            .collect()
    }

    /// Checks the mosaic's size and, at each `(x, y)` pixel given, which tile's colour it shows.
    fn check(
        manifest: &Manifest,
        max_side: u32,
        size: (u32, u32),
        pixels: &[((u32, u32), TileId)],
    ) {
        let image = mosaic(manifest, &all_textures(manifest), max_side).expect("mosaic");
        assert_eq!(image.dimensions(), size);
        assert_eq!(overview_size(manifest, max_side).expect("size"), size);
        for &((x, y), id) in pixels {
            assert_eq!(
                *image.get_pixel(x, y),
                colour(id),
                "pixel {x},{y} should be tile {id}"
            );
        }
    }

    #[test]
    fn full_tiles_are_placed_side_by_side_at_the_texture_size() {
        // 5 samples = 2 tiles of 2 cells each, exactly: no padding.
        let (a, b, c, d) = (
            TileId::new(0, 0),
            TileId::new(1, 0),
            TileId::new(0, 1),
            TileId::new(1, 1),
        );
        check(
            &manifest((5, 5), 4),
            1024,
            (8, 8),
            &[
                ((0, 0), a),
                ((3, 3), a),
                ((4, 0), b),
                ((7, 3), b),
                ((0, 4), c),
                ((4, 4), d),
                ((7, 7), d),
            ],
        );
    }

    #[test]
    fn edge_tiles_are_cropped_to_their_real_cells() {
        // 4 samples wide: the second column holds 2 valid samples, 1 of its 2 cells, so half
        // of its texture (2 of 4 texels) is terrain. 5 samples high fill 2 rows exactly.
        let m = manifest((4, 5), 4);
        assert_eq!(m.valid(TileId::new(1, 0)), [2, 3]);
        check(
            &m,
            1024,
            (6, 8),
            &[
                ((3, 0), TileId::new(0, 0)),
                ((4, 0), TileId::new(1, 0)),
                ((5, 7), TileId::new(1, 1)),
            ],
        );
    }

    #[test]
    fn partly_covered_texels_are_kept() {
        // Textures of 5 texels over 2 cells: the one real cell of the edge tile is 2.5 texels.
        check(
            &manifest((4, 5), 5),
            1024,
            (8, 10),
            &[((7, 0), TileId::new(1, 0))],
        );
    }

    #[test]
    fn large_mosaics_are_scaled_down_to_the_longest_side() {
        // 8x6 texels at full size (the last row is half padding), scaled to 4x3.
        let m = manifest((5, 4), 4);
        check(
            &m,
            4,
            (4, 3),
            &[
                ((0, 0), TileId::new(0, 0)),
                ((3, 0), TileId::new(1, 0)),
                ((0, 2), TileId::new(0, 1)),
            ],
        );
    }

    #[test]
    fn small_mosaics_are_not_scaled_up() {
        check(&manifest((5, 5), 4), 4096, (8, 8), &[]);
    }

    #[test]
    fn missing_tiles_stay_black() {
        let m = manifest((5, 5), 4);
        let image = mosaic(&m, &all_textures(&m)[..1], 1024).expect("mosaic");
        assert_eq!(*image.get_pixel(7, 7), Rgb([0, 0, 0]));
        assert_eq!(*image.get_pixel(0, 0), colour(TileId::new(0, 0)));
    }

    #[test]
    fn bad_textures_and_ids_are_errors_that_name_the_tile() {
        let m = manifest((5, 5), 4);
        let id = TileId::new(1, 1);
        let error = mosaic(&m, &[(id, b"not a png".to_vec())], 64).expect_err("undecodable");
        assert!(
            matches!(error, OverviewError::Decode { id: i, .. } if i == id),
            "{error}"
        );
        let error = mosaic(&m, &[(id, texture(id, 8))], 64).expect_err("wrong size");
        assert_eq!(
            error.to_string(),
            "texture of tile 1/1 is 8x8 texels; the finest level is 4x4"
        );
        let outside = TileId::new(2, 0);
        let error = mosaic(&m, &[(outside, texture(outside, 4))], 64).expect_err("outside");
        assert!(matches!(error, OverviewError::NotInGrid { .. }), "{error}");
    }
}
