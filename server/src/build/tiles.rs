//! Cutting the raster into tiles of `(2^n + 1)^2` samples that share their border rows
//! and columns, and the per-tile metadata a client needs before the heights: bounds,
//! roughness and the error of every strip-mask level.

use terrain_shared::manifest::RasterSize;
use terrain_shared::{Heights, TileId, mask};

/// The tile grid over a raster.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Grid {
    pub tile_size: u32,
    pub columns: u32,
    pub rows: u32,
}

impl Grid {
    /// The fewest tiles that cover `width x height` samples; edge tiles are padded.
    pub fn covering(width: u32, height: u32, tile_size: u32) -> Grid {
        let step = tile_size - 1;
        Grid {
            tile_size,
            columns: (width.saturating_sub(1)).div_ceil(step).max(1),
            rows: (height.saturating_sub(1)).div_ceil(step).max(1),
        }
    }

    pub fn tiles(&self) -> impl Iterator<Item = TileId> + '_ {
        (0..self.rows).flat_map(move |y| (0..self.columns).map(move |x| TileId::new(x, y)))
    }

    pub fn len(&self) -> usize {
        self.columns as usize * self.rows as usize
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// One tile cut from the raster, with padding replicated from the last real sample.
#[derive(Debug, Clone)]
pub struct TileSamples {
    pub id: TileId,
    pub heights: Heights,
    /// Real samples `[columns, rows]`.
    pub valid: [u32; 2],
}

/// Cuts tile `id` out of `codes` (row-major `width x height`).
pub fn cut(
    codes: &[i32],
    width: u32,
    height: u32,
    grid: Grid,
    id: TileId,
    quantum_m: f64,
    offset_m: f64,
) -> TileSamples {
    let n = grid.tile_size;
    let (x0, y0) = (id.x * (n - 1), id.y * (n - 1));
    let mut tile = Vec::with_capacity((n * n) as usize);
    for y in 0..n {
        let sy = (y0 + y).min(height - 1) as usize;
        for x in 0..n {
            let sx = (x0 + x).min(width - 1) as usize;
            tile.push(codes[sy * width as usize + sx]);
        }
    }
    TileSamples {
        id,
        heights: Heights {
            width: n as u16,
            height: n as u16,
            quantum_m,
            offset_m,
            codes: tile,
        },
        valid: [(width - x0).min(n), (height - y0).min(n)],
    }
}

/// The next coarser level of a raster: every other sample of `source` (`from` samples),
/// `to` samples ([`terrain_shared::manifest::level_rasters`]); a sample one past the last
/// repeats it.
pub fn decimate(source: &[i32], from: RasterSize, to: RasterSize) -> Vec<i32> {
    let (fw, fh) = (from.width as usize, from.height as usize);
    let mut out = Vec::with_capacity(to.width as usize * to.height as usize);
    for y in 0..to.height as usize {
        let row = &source[(2 * y).min(fh - 1) * fw..][..fw];
        out.extend((0..to.width as usize).map(|x| row[(2 * x).min(fw - 1)]));
    }
    out
}

/// Largest vertical distance, metres, between tile `id` of level `k` (`k >= 1`) and the
/// level below it (`finer`, `finer_raster` samples), over every sample of that level under
/// the tile: the error of keeping every other sample of its `(2n - 1)^2` block. Both
/// surfaces are triangulated the strip masks' way, and the coarse one's cells are unions of
/// the fine one's, so the distance is largest at a fine sample: it bounds the distance
/// everywhere, not only there.
pub fn decimation_error(
    finer: &[i32],
    finer_raster: RasterSize,
    id: TileId,
    tile_size: u32,
    quantum_m: f64,
    offset_m: f64,
) -> f32 {
    let side = 2 * tile_size - 1;
    let grid = Grid::covering(finer_raster.width, finer_raster.height, side);
    let block = cut(
        finer,
        finer_raster.width,
        finer_raster.height,
        grid,
        TileId::new(id.x, id.y),
        quantum_m,
        offset_m,
    );
    let metres = block.heights.to_metres_f32();
    mask::max_vertical_error(&metres, side, 1)
}

/// Adds a tile's distance from the full-resolution surface to each of its mask errors (the
/// triangle inequality: mask to tile, tile to full resolution), rounding up to the
/// centimetre so the sums stay upper bounds.
pub fn add_deviation(mask_errors_m: &mut [f32], deviation_m: f32) {
    if deviation_m > 0.0 {
        for e in mask_errors_m {
            *e = ((*e + deviation_m) * 100.0).ceil() / 100.0;
        }
    }
}

/// Bounds, roughness and mask errors of one tile, all in metres.
#[derive(Debug, Clone, PartialEq)]
pub struct TileStats {
    pub min_m: f32,
    pub max_m: f32,
    pub roughness_m: f32,
    pub mask_errors_m: Vec<f32>,
}

/// Computes [`TileStats`] for a tile. Mask errors are rounded up to the centimetre so they
/// stay upper bounds after the rounding.
pub fn stats(tile: &TileSamples) -> TileStats {
    let n = tile.heights.width as usize;
    let metres = tile.heights.to_metres_f32();
    let (min_m, max_m) = metres
        .iter()
        .fold((f32::MAX, f32::MIN), |(lo, hi), &h| (lo.min(h), hi.max(h)));
    let mask_errors_m = (0..mask::level_count(n as u32))
        .map(|level| (mask::max_vertical_error(&metres, n as u32, level) * 100.0).ceil() / 100.0)
        .collect();
    TileStats {
        min_m,
        max_m,
        roughness_m: roughness(&metres, n, tile.valid),
        mask_errors_m,
    }
}

/// Mean terrain ruggedness index (Riley, DeGloria and Elliot 1999) over the real samples:
/// per sample, the root of the summed squared height differences to its neighbours within
/// the tile. A flat tile has 0.
fn roughness(metres: &[f32], n: usize, valid: [u32; 2]) -> f32 {
    let (vw, vh) = (valid[0] as usize, valid[1] as usize);
    let mut total = 0.0f64;
    for y in 0..vh {
        for x in 0..vw {
            let centre = metres[y * n + x];
            let mut sum = 0.0f32;
            for dy in -1isize..=1 {
                for dx in -1isize..=1 {
                    let (nx, ny) = (x as isize + dx, y as isize + dy);
                    if (dx, dy) != (0, 0)
                        && nx >= 0
                        && ny >= 0
                        && (nx as usize) < vw
                        && (ny as usize) < vh
                    {
                        let d = metres[ny as usize * n + nx as usize] - centre;
                        sum += d * d;
                    }
                }
            }
            total += f64::from(sum.sqrt());
        }
    }
    (total / (vw * vh) as f64) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_coarser_level_keeps_every_other_sample_and_measures_what_it_drops() {
        let (w, h) = (9u32, 6u32);
        let codes: Vec<i32> = (0..(w * h) as i32).collect();
        let from = RasterSize {
            width: w,
            height: h,
        };
        let to = RasterSize {
            width: 5,
            height: 4,
        };
        let coarse = decimate(&codes, from, to);
        // Row 3 of the coarse level is row 6 of the fine one, past its last row 5: it repeats it.
        assert_eq!(&coarse[..5], &[0, 2, 4, 6, 8]);
        assert_eq!(&coarse[15..], &[45, 47, 49, 51, 53]);
        // A plane loses nothing; a spike on a dropped sample is the whole error.
        let plane: Vec<i32> = (0..81).map(|i| 3 * (i % 9) + 2 * (i / 9)).collect();
        let r9 = RasterSize {
            width: 9,
            height: 9,
        };
        assert_eq!(
            decimation_error(&plane, r9, TileId::at(1, 0, 0), 5, 1.0, 0.0),
            0.0
        );
        let mut spiky = vec![0; 81];
        spiky[3 * 9 + 5] = 7;
        assert_eq!(
            decimation_error(&spiky, r9, TileId::at(1, 0, 0), 5, 1.0, 0.0),
            7.0
        );
        let mut errors = vec![0.0, 0.5];
        add_deviation(&mut errors, 7.0);
        assert_eq!(errors, vec![7.0, 7.5]);
    }

    #[test]
    fn grids_cover_rasters_with_shared_borders() {
        assert_eq!(
            Grid::covering(403, 344, 129),
            Grid {
                tile_size: 129,
                columns: 4,
                rows: 3
            }
        );
        assert_eq!(
            Grid::covering(129, 129, 129),
            Grid {
                tile_size: 129,
                columns: 1,
                rows: 1
            }
        );
        assert_eq!(
            Grid::covering(130, 129, 129),
            Grid {
                tile_size: 129,
                columns: 2,
                rows: 1
            }
        );
        assert_eq!(
            Grid::covering(4097, 4097, 129),
            Grid {
                tile_size: 129,
                columns: 32,
                rows: 32
            }
        );
        assert_eq!(
            Grid::covering(2, 2, 129),
            Grid {
                tile_size: 129,
                columns: 1,
                rows: 1
            }
        );
    }

    #[test]
    fn neighbouring_tiles_share_a_column_and_padding_repeats_the_edge() {
        let (w, h) = (7u32, 5u32);
        let codes: Vec<i32> = (0..(w * h) as i32).collect();
        let grid = Grid::covering(w, h, 5);
        assert_eq!((grid.columns, grid.rows), (2, 1));
        let a = cut(&codes, w, h, grid, TileId::new(0, 0), 1.0, 0.0);
        let b = cut(&codes, w, h, grid, TileId::new(1, 0), 1.0, 0.0);
        for y in 0..5 {
            assert_eq!(
                a.heights.codes[y * 5 + 4],
                b.heights.codes[y * 5],
                "row {y}"
            );
        }
        assert_eq!(b.valid, [3, 5]);
        // Column 4 of tile b is beyond the raster: it repeats raster column 6.
        assert_eq!(b.heights.codes[4], codes[6]);
        assert_eq!(b.heights.codes[3], codes[6]);
    }

    #[test]
    fn flat_tiles_are_smooth_and_free_at_every_mask_level() {
        let tile = TileSamples {
            id: TileId::new(0, 0),
            heights: Heights {
                width: 9,
                height: 9,
                quantum_m: 0.5,
                offset_m: 100.0,
                codes: vec![4; 81],
            },
            valid: [9, 9],
        };
        let s = stats(&tile);
        assert_eq!((s.min_m, s.max_m, s.roughness_m), (102.0, 102.0, 0.0));
        assert_eq!(s.mask_errors_m, vec![0.0; 8]);
    }

    #[test]
    fn a_rough_tile_is_rougher_and_its_errors_grow_with_the_level() {
        let codes = (0..81)
            .map(|i| if (i % 9 + i / 9) % 2 == 0 { 0 } else { 10 })
            .collect();
        let tile = TileSamples {
            id: TileId::new(0, 0),
            heights: Heights {
                width: 9,
                height: 9,
                quantum_m: 1.0,
                offset_m: 0.0,
                codes,
            },
            valid: [9, 9],
        };
        let s = stats(&tile);
        assert!(s.roughness_m > 10.0);
        assert_eq!(s.mask_errors_m[0], 0.0);
        assert!(s.mask_errors_m[1] >= 10.0 - 1e-3);
    }
}
