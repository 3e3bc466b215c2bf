//! Cutting a level's raster into tiles of `(2^n + 1)^2` samples that share their border
//! rows and columns, and the per-tile metadata a client needs before the heights: bounds,
//! roughness and the error of every strip-mask level.
//!
//! The builder holds a level a [`Band`] of rows at a time and cuts from that; [`cut`],
//! [`decimate`] and [`decimation_error`] are the same operations on a whole raster in
//! memory, the definitions the band-wise builder is tested against.

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

    /// Which siblings of tile `(x, y)` (the tiles sharing its parent on the next coarser
    /// level) lie past the grid: east when it is the last of an odd number of columns,
    /// south likewise for rows.
    pub fn missing_siblings(&self, x: u32, y: u32) -> Siblings {
        Siblings {
            east: x + 1 == self.columns && self.columns % 2 == 1,
            south: y + 1 == self.rows && self.rows % 2 == 1,
        }
    }
}

/// Siblings a tile lacks ([`Grid::missing_siblings`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Siblings {
    pub east: bool,
    pub south: bool,
}

impl Siblings {
    /// The missing siblings of tile `id`: east, south, and south-east when both are.
    pub fn ids(self, id: TileId) -> impl Iterator<Item = TileId> {
        let at = move |dx, dy| TileId::at(id.level, id.x + dx, id.y + dy);
        [
            self.east.then(|| at(1, 0)),
            self.south.then(|| at(0, 1)),
            (self.east && self.south).then(|| at(1, 1)),
        ]
        .into_iter()
        .flatten()
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
    let row = |y: u32| Row::wide(&codes[y as usize * width as usize..][..width as usize]);
    cut_with(row, width, height, grid, id, (quantum_m, offset_m))
}

/// Cuts tile `id` of a `width x height` raster whose row `y` (`y < height`) is `row(y)`.
/// Samples past the last row or column repeat it, also for a tile that lies wholly past the
/// raster (the padding children of [`crate::build::levels`]).
pub fn cut_with<'a>(
    row: impl Fn(u32) -> Row<'a>,
    width: u32,
    height: u32,
    grid: Grid,
    id: TileId,
    (quantum_m, offset_m): (f64, f64),
) -> TileSamples {
    let n = grid.tile_size;
    let (x0, y0) = (id.x * (n - 1), id.y * (n - 1));
    let mut tile = Vec::with_capacity((n * n) as usize);
    for y in 0..n {
        row((y0 + y).min(height - 1)).extend_clamped(&mut tile, x0, n);
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
        valid: [
            width.saturating_sub(x0).min(n),
            height.saturating_sub(y0).min(n),
        ],
    }
}

/// One row of codes: a row a [`Band`] holds, or every `stride`-th sample of one (a row of
/// a coarser level, seen through the finer level's band).
#[derive(Debug, Clone, Copy)]
pub struct Row<'a> {
    codes: RowCodes<'a>,
    stride: usize,
    /// Samples in the row.
    width: usize,
}

#[derive(Debug, Clone, Copy)]
enum RowCodes<'a> {
    /// Offsets from a base code.
    Narrow(&'a [u16], i32),
    Wide(&'a [i32]),
}

impl<'a> Row<'a> {
    /// A row of codes as they are.
    pub fn wide(codes: &'a [i32]) -> Row<'a> {
        Row {
            codes: RowCodes::Wide(codes),
            stride: 1,
            width: codes.len(),
        }
    }

    /// Every other sample of this row, `width` of them, the last repeated past the end: the
    /// row of the next coarser level ([`decimate`]). A sample past the end of this row is
    /// past the end of the one it was taken from, so one clamp at the bottom is enough.
    pub fn halved(self, width: u32) -> Row<'a> {
        Row {
            stride: 2 * self.stride,
            width: width as usize,
            ..self
        }
    }

    pub fn len(&self) -> usize {
        self.width
    }

    pub fn is_empty(&self) -> bool {
        self.width == 0
    }

    /// Code `x` (`x < len`).
    pub fn get(&self, x: usize) -> i32 {
        match self.codes {
            RowCodes::Narrow(values, base) => {
                base + i32::from(values[(self.stride * x).min(values.len() - 1)])
            }
            RowCodes::Wide(codes) => codes[(self.stride * x).min(codes.len() - 1)],
        }
    }

    /// Appends codes `x0..x0 + count`, those past the last repeating it.
    fn extend_clamped(&self, out: &mut Vec<i32>, x0: u32, count: u32) {
        let last = self.width.saturating_sub(1);
        let xs = (x0..x0 + count).map(|x| (x as usize).min(last));
        match self.codes {
            RowCodes::Narrow(..) => out.extend(xs.map(|x| self.get(x))),
            RowCodes::Wide(codes) if self.stride == 1 => out.extend(xs.map(|x| codes[x])),
            RowCodes::Wide(..) => out.extend(xs.map(|x| self.get(x))),
        }
    }
}

/// Consecutive rows of one level's raster, at most a fixed number: what the builder stores
/// of a level at a time. Rows live in a ring of slots allocated once. Codes are held as
/// 16-bit offsets from the raster's lowest code when its range allows (every 8- or 16-bit
/// input, and any level made from one), else as they are: a band costs 2 bytes a sample
/// for most DEMs.
#[derive(Debug, Clone)]
pub struct Band {
    width: u32,
    /// The whole raster's height.
    height: u32,
    /// Slots, rows.
    capacity: u32,
    /// Raster rows held: `first..next`.
    first: u32,
    next: u32,
    codes: Codes,
}

#[derive(Debug, Clone)]
enum Codes {
    Narrow { base: i32, values: Vec<u16> },
    Wide(Vec<i32>),
}

impl Band {
    /// An empty band of a `width x height` raster whose codes lie in `code_range`, holding
    /// at most `rows` rows, starting at row 0.
    pub fn new(width: u32, height: u32, rows: u32, code_range: (i32, i32)) -> Band {
        let size = width as usize * rows as usize;
        let (low, high) = code_range;
        let codes = if i64::from(high) - i64::from(low) <= i64::from(u16::MAX) {
            Codes::Narrow {
                base: low,
                values: vec![0; size],
            }
        } else {
            Codes::Wide(vec![0; size])
        };
        Band {
            width,
            height,
            capacity: rows,
            first: 0,
            next: 0,
            codes,
        }
    }

    /// A band holding all of a raster (`codes` row-major, `width x height`).
    pub fn whole(codes: &[i32], width: u32, height: u32) -> Band {
        let range = codes
            .iter()
            .fold((i32::MAX, i32::MIN), |(lo, hi), &c| (lo.min(c), hi.max(c)));
        let mut band = Band::new(width, height, height, range);
        for row in codes.chunks_exact(width.max(1) as usize) {
            band.push_row(row);
        }
        band
    }

    pub fn width(&self) -> u32 {
        self.width
    }

    pub fn height(&self) -> u32 {
        self.height
    }

    /// Raster row of the first row held.
    pub fn first(&self) -> u32 {
        self.first
    }

    /// The raster row the next [`Band::push_row`] adds.
    pub fn next_row(&self) -> u32 {
        self.next
    }

    /// Whether raster row `y` (the last row for `y` past it) is held.
    pub fn holds(&self, y: u32) -> bool {
        (self.first..self.next).contains(&y.min(self.height - 1))
    }

    /// Adds the next row (`width` codes within the band's code range).
    ///
    /// Panics if the band is full (a caller's bug, never data-dependent).
    pub fn push_row(&mut self, row: &[i32]) {
        assert!(
            self.next - self.first < self.capacity,
            "band of {} rows is full",
            self.capacity
        );
        let width = self.width as usize;
        let at = (self.next % self.capacity) as usize * width;
        match &mut self.codes {
            Codes::Narrow { base, values } => {
                let base = *base;
                for (out, &c) in values[at..at + width].iter_mut().zip(row) {
                    debug_assert!(u16::try_from(c - base).is_ok(), "code {c} out of range");
                    *out = (c - base).clamp(0, i32::from(u16::MAX)) as u16;
                }
            }
            Codes::Wide(codes) => codes[at..at + width].copy_from_slice(&row[..width]),
        }
        self.next += 1;
    }

    /// Forgets the rows above raster row `y`.
    pub fn drop_before(&mut self, y: u32) {
        self.first = y.clamp(self.first, self.next);
    }

    /// Starts the band afresh at raster row `y`, forgetting every row held.
    pub fn restart_at(&mut self, y: u32) {
        self.first = y;
        self.next = y;
    }

    /// Raster row `y`, or the last row for `y` past it. The row must be held (a caller's
    /// bug otherwise, which debug builds catch; release builds read the nearest row held).
    pub fn row(&self, y: u32) -> Row<'_> {
        let y = y.min(self.height - 1);
        debug_assert!(
            self.holds(y),
            "row {y} is not in the band {}..{}",
            self.first,
            self.next
        );
        let y = y.clamp(self.first, self.next.saturating_sub(1).max(self.first));
        let width = self.width as usize;
        let at = (y % self.capacity.max(1)) as usize * width;
        let codes = match &self.codes {
            Codes::Narrow { base, values } => RowCodes::Narrow(&values[at..at + width], *base),
            Codes::Wide(codes) => RowCodes::Wide(&codes[at..at + width]),
        };
        Row {
            codes,
            stride: 1,
            width,
        }
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
///
/// The block is the tile's four children side by side (or, past the finer grid's edge,
/// what cutting them would give: padding), and no coarse cell straddles two of them, so
/// this is the largest of the children's [`TileStats::half_resolution_error_m`]: the
/// builder takes it from them and never holds the block.
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

/// The error of keeping every other sample of `tile` (mask level 1), as
/// [`TileStats::half_resolution_error_m`]: for the padding-only children a parent on the
/// grid's edge lacks.
pub fn half_resolution_error(tile: &TileSamples) -> f32 {
    let n = u32::from(tile.heights.width);
    mask::max_vertical_error(&tile.heights.to_metres_f32(), n, 1)
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
    /// The error of keeping every other sample of the tile (mask level 1), not rounded:
    /// what the tile adds to its parent's [`decimation_error`]. 0 for a tile of 2 samples.
    pub half_resolution_error_m: f32,
}

/// Computes [`TileStats`] for a tile. Mask errors are rounded up to the centimetre so they
/// stay upper bounds after the rounding.
pub fn stats(tile: &TileSamples) -> TileStats {
    let n = tile.heights.width as usize;
    let metres = tile.heights.to_metres_f32();
    let (min_m, max_m) = metres
        .iter()
        .fold((f32::MAX, f32::MIN), |(lo, hi), &h| (lo.min(h), hi.max(h)));
    let errors_m: Vec<f32> = (0..mask::level_count(n as u32))
        .map(|level| mask::max_vertical_error(&metres, n as u32, level))
        .collect();
    TileStats {
        min_m,
        max_m,
        roughness_m: roughness(&metres, n, tile.valid),
        mask_errors_m: errors_m
            .iter()
            .map(|e| (e * 100.0).ceil() / 100.0)
            .collect(),
        half_resolution_error_m: errors_m.get(1).copied().unwrap_or(0.0),
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
