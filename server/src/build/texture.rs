//! Per-tile textures: resampled from a source image or computed from the heights, then
//! cut into a mip chain stored coarsest first, so a client can fetch level by level
//! (the strip-mask paper's progressive texture transfer).
//!
//! **Texel registration.** A tile's texture covers the square from its first sample to its
//! last, edge to edge; texel `i` of `size` has its centre at sample coordinate
//! `x0 + (i + 0.5) * (tile_size - 1) / size`, exactly what a GPU sampler does with
//! `u = (x - x0) / (tile_size - 1)`. A source image is located on the raster in one of
//! two ways ([`Registration`]):
//! - *edge-aligned* (`cell-centred`, `same extent`): the image spans the raster's first to
//!   last sample; with `width - 1` texels, each texel fills the cell between four samples
//!   (Puget Sound's texture);
//! - *sample-centred*: texel centres sit on samples, so the image reaches half a sample
//!   beyond the raster on every side.

use image::{Rgb, RgbImage};
use terrain_shared::TileId;
use terrain_shared::manifest::ImageFormat;

use super::tiles::{Band, Grid, Siblings};

/// Coarsest level's side, or the finest's if smaller: 8 texels still show a tile's main colour.
pub const COARSEST_SIZE: u32 = 8;
/// Default JPEG quality: visually clean for terrain at a third of PNG's size.
pub const DEFAULT_JPEG_QUALITY: u8 = 85;

/// Where a source image sits on the raster. See the module docs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Registration {
    /// Image edges on the first and last samples (`cell-centred`, `same extent`).
    EdgeAligned,
    /// Texel centres on samples.
    SampleCentred,
}

impl Registration {
    /// Reads the `texture_registration` of a `dataset.json`.
    pub fn from_dataset(text: &str) -> Option<Registration> {
        match text.to_ascii_lowercase().replace(['_', ' '], "-").as_str() {
            "cell-centred" | "cell-centered" | "same-extent" | "edge-aligned" => {
                Some(Registration::EdgeAligned)
            }
            "sample-centred" | "sample-centered" | "point" => Some(Registration::SampleCentred),
            _ => None,
        }
    }
}

/// Number of levels for a finest side of `size` texels.
pub fn level_count(size: u32) -> u32 {
    let coarsest = COARSEST_SIZE.min(size);
    (size / coarsest).trailing_zeros() + 1
}

/// The finest side that keeps a source image's detail: its texels per raster cell times
/// the tile's cells, rounded to a power of two, between 16 and 1024.
pub fn size_for_source(image_width: u32, raster_width: u32, tile_size: u32) -> u32 {
    let per_cell = f64::from(image_width) / f64::from(raster_width.saturating_sub(1).max(1));
    let texels = (per_cell * f64::from(tile_size - 1)).max(1.0);
    (2f64.powf(texels.log2().round()) as u32).clamp(16, 1024)
}

/// Resamples the part of `source` over tile `id` to `size x size` texels (bilinear).
pub fn from_image(
    source: &RgbImage,
    registration: Registration,
    raster: (u32, u32),
    grid: Grid,
    id: TileId,
    size: u32,
) -> RgbImage {
    let (rw, rh) = (f64::from(raster.0), f64::from(raster.1));
    let (iw, ih) = (f64::from(source.width()), f64::from(source.height()));
    let cells = f64::from(grid.tile_size - 1);
    let (x0, y0) = (f64::from(id.x) * cells, f64::from(id.y) * cells);
    RgbImage::from_fn(size, size, |i, j| {
        // Sample coordinates of this texel's centre, then the image's continuous texel
        // coordinates of that point (texel k spans [k, k + 1]).
        let sx = x0 + (f64::from(i) + 0.5) * cells / f64::from(size);
        let sy = y0 + (f64::from(j) + 0.5) * cells / f64::from(size);
        let (px, py) = match registration {
            Registration::EdgeAligned => (sx / (rw - 1.0) * iw, sy / (rh - 1.0) * ih),
            Registration::SampleCentred => ((sx + 0.5) / rw * iw, (sy + 0.5) / rh * ih),
        };
        bilinear(source, px - 0.5, py - 0.5)
    })
}

fn bilinear(image: &RgbImage, x: f64, y: f64) -> Rgb<u8> {
    let max_x = f64::from(image.width() - 1);
    let max_y = f64::from(image.height() - 1);
    let (x, y) = (x.clamp(0.0, max_x), y.clamp(0.0, max_y));
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (x0, y0) = (x0 as u32, y0 as u32);
    let (x1, y1) = (
        (x0 + 1).min(image.width() - 1),
        (y0 + 1).min(image.height() - 1),
    );
    let p = |x, y| image.get_pixel(x, y).0.map(f64::from);
    let (a, b, c, d) = (p(x0, y0), p(x1, y0), p(x0, y1), p(x1, y1));
    Rgb(std::array::from_fn(|k| {
        let top = a[k] + (b[k] - a[k]) * fx;
        let bottom = c[k] + (d[k] - c[k]) * fx;
        (top + (bottom - top) * fy).round().clamp(0.0, 255.0) as u8
    }))
}

/// What a tile's finest texture (`size` texels a side) contributes to its parent's: the
/// texture halved (each texel the mean of four, as a mip level), and, for a tile whose
/// sibling the grid lacks ([`Edges`]), its last column or row at full size, which stand in
/// for the missing one. The half is held as a PNG: the builder holds this for every tile of
/// a tile row until its parents are made, and a computed or photographic texture
/// compresses about 3:1 losslessly (2.8 to 3.1 on himalaya_4097), so a carried texture
/// costs about a twelfth of the texture's bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct ChildTexture {
    size: u32,
    half_png: Vec<u8>,
    last_column: Vec<[u8; 3]>,
    last_row: Vec<[u8; 3]>,
}

/// Which edges of its texture a tile keeps for its parent: those a missing sibling repeats
/// (see [`from_children`] and [`Grid::missing_siblings`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Edges {
    pub last_column: bool,
    pub last_row: bool,
}

impl Edges {
    /// The edges a tile keeps when it lacks the `missing` siblings: its last column for a
    /// missing east one, its last row for a missing south one. A texture of one texel has
    /// no half, so it keeps both.
    pub fn for_missing(missing: Siblings, size: u32) -> Edges {
        let one_texel = size < 2;
        Edges {
            last_column: one_texel || missing.east,
            last_row: one_texel || missing.south,
        }
    }
}

impl ChildTexture {
    pub fn of(finest: &RgbImage, edges: Edges) -> Result<ChildTexture, image::ImageError> {
        let size = finest.width();
        let last = size.saturating_sub(1);
        let column = |keep: bool| -> Vec<[u8; 3]> {
            let texels = if keep { 0..finest.height() } else { 0..0 };
            texels.map(|y| finest.get_pixel(last, y).0).collect()
        };
        let row = |keep: bool| -> Vec<[u8; 3]> {
            let texels = if keep { 0..size } else { 0..0 };
            texels.map(|x| finest.get_pixel(x, last).0).collect()
        };
        Ok(ChildTexture {
            size,
            half_png: if size >= 2 {
                // The encoder's buffer is sized for the raw texels: a third of it is kept.
                let mut png = encode(&halve(finest), ImageFormat::Png, DEFAULT_JPEG_QUALITY)?;
                png.shrink_to_fit();
                png
            } else {
                Vec::new()
            },
            last_column: column(edges.last_column),
            last_row: row(edges.last_row),
        })
    }

    /// The carried texture as bytes, for a region job's hand-over to the merge
    /// ([`super::jobs`]): its size, then the halved PNG, the last column and the last row,
    /// each after its length (u32, little-endian).
    pub fn write_to(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.size.to_le_bytes());
        out.extend_from_slice(&(self.half_png.len() as u32).to_le_bytes());
        out.extend_from_slice(&self.half_png);
        for texels in [&self.last_column, &self.last_row] {
            out.extend_from_slice(&(texels.len() as u32).to_le_bytes());
            out.extend(texels.iter().flatten());
        }
    }

    /// Reads what [`ChildTexture::write_to`] wrote from the front of `bytes`, advancing it;
    /// `None` when `bytes` is too short or its lengths do not fit the size.
    pub fn read_from(bytes: &mut &[u8]) -> Option<ChildTexture> {
        fn take<'a>(bytes: &mut &'a [u8], n: usize) -> Option<&'a [u8]> {
            let (head, rest) = (bytes.len() >= n).then(|| bytes.split_at(n))?;
            *bytes = rest;
            Some(head)
        }
        fn word(bytes: &mut &[u8]) -> Option<u32> {
            Some(u32::from_le_bytes(take(bytes, 4)?.try_into().ok()?))
        }
        let size = word(bytes)?;
        let png_len = word(bytes)? as usize;
        let half_png = take(bytes, png_len)?.to_vec();
        let mut texels = || -> Option<Vec<[u8; 3]>> {
            let n = word(bytes)? as usize;
            if n > size as usize {
                return None;
            }
            let raw = take(bytes, 3 * n)?;
            Some(raw.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect())
        };
        let last_column = texels()?;
        let last_row = texels()?;
        Some(ChildTexture {
            size,
            half_png,
            last_column,
            last_row,
        })
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.half_png.len() + 3 * (self.last_column.len() + self.last_row.len())
    }

    /// The texture halved; `None` for a texture of one texel, which has no half.
    fn half(&self) -> Result<Option<RgbImage>, image::ImageError> {
        if self.half_png.is_empty() {
            return Ok(None);
        }
        let image = image::load_from_memory_with_format(&self.half_png, image::ImageFormat::Png)?;
        Ok(Some(image.into_rgb8()))
    }

    /// Texel `(x, y)` of the finest texture, for one on its last column or row.
    fn edge_texel(&self, x: u32, y: u32) -> Option<[u8; 3]> {
        let on_column = (x + 1 == self.size)
            .then(|| self.last_column.get(y as usize))
            .flatten();
        let on_row = (y + 1 == self.size)
            .then(|| self.last_row.get(x as usize))
            .flatten();
        on_column.or(on_row).copied()
    }
}

/// Output texel `(x, y)` of a 2:1 reduction: the rounded mean of the four mosaic texels
/// `texel` gives under it.
fn box_2x2(texel: &impl Fn(u32, u32) -> [u32; 3], x: u32, y: u32) -> Rgb<u8> {
    let (a, b, c, d) = (
        texel(2 * x, 2 * y),
        texel(2 * x + 1, 2 * y),
        texel(2 * x, 2 * y + 1),
        texel(2 * x + 1, 2 * y + 1),
    );
    Rgb(std::array::from_fn(|k| {
        ((a[k] + b[k] + c[k] + d[k] + 2) / 4) as u8
    }))
}

/// Where texel `(px, py)` of the 2x2 mosaic of `child(cx, cy)` textures of side `size`
/// comes from: that child's texel, or, for a missing child (past the terrain's east or
/// south edge), the nearest texel of the child west of it, north of it, or north-west.
fn mosaic_source<C>(
    child: impl Fn(u32, u32) -> Option<C>,
    px: u32,
    py: u32,
    size: u32,
) -> Option<(C, u32, u32)> {
    let (cx, cy) = (px / size, py / size);
    let (ix, iy) = (px % size, py % size);
    child(cx, cy)
        .map(|c| (c, ix, iy))
        .or_else(|| child(0, cy).map(|c| (c, size - 1, iy)))
        .or_else(|| child(cx, 0).map(|c| (c, ix, size - 1)))
        .or_else(|| child(0, 0).map(|c| (c, size - 1, size - 1)))
}

/// A parent tile's finest texture, `size` texels, filtered from its children's (north-west,
/// north-east, south-west, south-east; `None` past the grid's edge, where the nearest
/// existing texels are repeated): the 2x2 mosaic, each output texel the mean of four.
///
/// The four texels of an output texel lie in one child (for `size >= 2`), so where that
/// child exists the output is its [`ChildTexture`]'s half; where it is missing, the texels
/// repeated from a neighbour are on that neighbour's last column or row.
pub fn from_children(
    children: &[Option<&ChildTexture>],
    size: u32,
) -> Result<RgbImage, image::ImageError> {
    let child = |cx: u32, cy: u32| children.get((cy * 2 + cx) as usize).copied().flatten();
    let halves = (0..4)
        .map(|i| child(i % 2, i / 2).map_or(Ok(None), ChildTexture::half))
        .collect::<Result<Vec<_>, _>>()?;
    // Texel (px, py) of the mosaic, where it is a child's edge texel or repeats one.
    let texel = |px: u32, py: u32| -> [u32; 3] {
        mosaic_source(child, px, py, size)
            .and_then(|(c, x, y)| c.edge_texel(x, y))
            .map_or([0, 0, 0], |t| t.map(u32::from))
    };
    Ok(RgbImage::from_fn(size, size, |x, y| {
        let (cx, cy) = (2 * x / size, 2 * y / size);
        let half = size / 2;
        let own = halves.get((cy * 2 + cx) as usize).and_then(Option::as_ref);
        if let Some(texel) = own.and_then(|h| h.get_pixel_checked(x - cx * half, y - cy * half)) {
            return *texel;
        }
        box_2x2(&texel, x, y)
    }))
}

/// Heights in metres for computed textures, from the rows a [`Band`] holds (a tile row's
/// and [`GENERATED_HALO_ROWS`] either side, or a whole raster).
#[derive(Debug, Clone, Copy)]
pub struct HeightField<'a> {
    pub band: &'a Band,
    pub quantum_m: f64,
    pub offset_m: f64,
    pub spacing_m: [f64; 2],
    /// The dataset's range, so tint colours agree across tiles.
    pub min_m: f64,
    pub max_m: f64,
}

impl HeightField<'_> {
    /// Height at sample `(x, y)`, the raster's edge repeated beyond it.
    fn at(&self, x: i64, y: i64) -> f64 {
        let x = x.clamp(0, i64::from(self.band.width()) - 1) as usize;
        let y = y.clamp(0, i64::from(self.band.height()) - 1) as u32;
        self.offset_m + self.quantum_m * f64::from(self.band.row(y).get(x))
    }

    /// Hypsometric tint shaded by a light from the north-west, 45 degrees up (the
    /// cartographic convention), at sample `(x, y)`.
    fn colour(&self, x: i64, y: i64) -> [f64; 3] {
        let h = self.at(x, y);
        let dzdx = (self.at(x + 1, y) - self.at(x - 1, y)) / (2.0 * self.spacing_m[0]);
        let dzdy = (self.at(x, y + 1) - self.at(x, y - 1)) / (2.0 * self.spacing_m[1]);
        // Axes: x east, y south, z up. Light azimuth 315 degrees, altitude 45 degrees.
        let (alt, az) = (45f64.to_radians(), 315f64.to_radians());
        let light = [alt.cos() * az.sin(), -alt.cos() * az.cos(), alt.sin()];
        let normal = [-dzdx, -dzdy, 1.0];
        let len = (normal[0] * normal[0] + normal[1] * normal[1] + 1.0).sqrt();
        let lambert =
            ((normal[0] * light[0] + normal[1] * light[1] + normal[2] * light[2]) / len).max(0.0);
        // Flat ground gets 0.25 + 0.75 = full tint; slopes facing away darken to 0.25.
        let shade = 0.25 + 0.75 * (lambert / alt.sin()).min(1.3);
        let tint = tint(h, self.min_m, self.max_m);
        tint.map(|c| c * shade)
    }
}

/// Colour of height `h` on a hypsometric ramp over `[min, max]`; at or below 0 m on a
/// dataset that also has land, water.
fn tint(h: f64, min: f64, max: f64) -> [f64; 3] {
    const WATER: [f64; 3] = [59.0, 110.0, 168.0];
    const RAMP: [(f64, [f64; 3]); 7] = [
        (0.00, [58.0, 125.0, 68.0]),
        (0.15, [106.0, 168.0, 79.0]),
        (0.35, [200.0, 192.0, 106.0]),
        (0.55, [176.0, 132.0, 76.0]),
        (0.75, [140.0, 106.0, 85.0]),
        (0.90, [184.0, 176.0, 168.0]),
        (1.00, [255.0, 255.0, 255.0]),
    ];
    if h <= 0.0 && max > 0.0 && min <= 0.0 {
        return WATER;
    }
    let t = if max > min {
        ((h - min) / (max - min)).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let i = RAMP
        .iter()
        .rposition(|(stop, _)| *stop <= t)
        .unwrap_or(0)
        .min(RAMP.len() - 2);
    let ((t0, c0), (t1, c1)) = (RAMP[i], RAMP[i + 1]);
    let f = ((t - t0) / (t1 - t0)).clamp(0.0, 1.0);
    std::array::from_fn(|k| c0[k] + (c1[k] - c0[k]) * f)
}

/// Rows a computed texture reads beyond its tile's, above and below: a texel's colour is
/// shaded with the slope at the samples around it, which reach one row further.
pub const GENERATED_HALO_ROWS: u32 = 1;

/// Computes tile `id`'s texture from the heights at `size x size` texels: colours at the
/// samples around each texel centre, blended bilinearly. Reads the field's rows from
/// [`GENERATED_HALO_ROWS`] above the tile's first to as many below its last.
pub fn generated(field: &HeightField<'_>, grid: Grid, id: TileId, size: u32) -> RgbImage {
    let cells = f64::from(grid.tile_size - 1);
    let (x0, y0) = (f64::from(id.x) * cells, f64::from(id.y) * cells);
    // Each texel blends the colours of the four samples around its centre: per axis, the
    // sample below the centre and its fraction of the way to the next.
    let along = |origin: f64| -> Vec<(i64, f64)> {
        (0..size)
            .map(|i| {
                let s = origin + (f64::from(i) + 0.5) * cells / f64::from(size);
                let f = s.floor();
                (f as i64, s - f)
            })
            .collect()
    };
    let (columns, rows) = (along(x0), along(y0));
    // Every sample's colour once (neighbouring texels share samples: four times fewer
    // colours than texels' corners at one texel a cell), in the rectangle the texels use.
    let span = |axis: &[(i64, f64)]| {
        let first = axis.first().map_or(0, |a| a.0);
        let last = axis.last().map_or(0, |a| a.0) + 1;
        (first, (last - first + 1) as usize)
    };
    let ((cx, cw), (cy, ch)) = (span(&columns), span(&rows));
    let colours: Vec<[f64; 3]> = (0..ch as i64)
        .flat_map(|dy| (0..cw as i64).map(move |dx| field.colour(cx + dx, cy + dy)))
        .collect();
    let colour = |x: i64, y: i64| colours[(y - cy) as usize * cw + (x - cx) as usize];
    RgbImage::from_fn(size, size, |i, j| {
        let ((ix, tx), (iy, ty)) = (columns[i as usize], rows[j as usize]);
        let (a, b, c, d) = (
            colour(ix, iy),
            colour(ix + 1, iy),
            colour(ix, iy + 1),
            colour(ix + 1, iy + 1),
        );
        Rgb(std::array::from_fn(|k| {
            let top = a[k] + (b[k] - a[k]) * tx;
            let bottom = c[k] + (d[k] - c[k]) * tx;
            (top + (bottom - top) * ty).round().clamp(0.0, 255.0) as u8
        }))
    })
}

/// The mip chain of `finest`, coarsest first, by 2x2 box filtering.
pub fn mip_chain(finest: RgbImage) -> Vec<RgbImage> {
    let levels = level_count(finest.width());
    let mut chain = vec![finest];
    for _ in 1..levels {
        let Some(prev) = chain.last() else { break };
        let next = halve(prev);
        chain.push(next);
    }
    chain.reverse();
    chain
}

/// `image` at half its size, each texel the mean of four (2x2 box filter, rounded).
fn halve(image: &RgbImage) -> RgbImage {
    let half = image.width() / 2;
    RgbImage::from_fn(half, half, |x, y| {
        let p = |dx, dy| image.get_pixel(2 * x + dx, 2 * y + dy).0.map(u32::from);
        let (a, b, c, d) = (p(0, 0), p(1, 0), p(0, 1), p(1, 1));
        Rgb(std::array::from_fn(|k| {
            ((a[k] + b[k] + c[k] + d[k] + 2) / 4) as u8
        }))
    })
}

/// Encodes one level.
pub fn encode(
    image: &RgbImage,
    format: ImageFormat,
    jpeg_quality: u8,
) -> Result<Vec<u8>, image::ImageError> {
    let mut out = std::io::Cursor::new(Vec::new());
    match format {
        ImageFormat::Jpeg => {
            image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, jpeg_quality)
                .encode_image(image)?;
        }
        ImageFormat::Png => {
            image.write_with_encoder(image::codecs::png::PngEncoder::new(&mut out))?;
        }
    }
    Ok(out.into_inner())
}

/// The definition [`from_children`] is tested against: the children's full textures side
/// by side (a missing child repeating its neighbours' nearest texels), each output texel the
/// mean of four.
#[cfg(test)]
pub(crate) fn filter_mosaic(children: &[Option<&RgbImage>], size: u32) -> RgbImage {
    let child = |cx: u32, cy: u32| children.get((cy * 2 + cx) as usize).copied().flatten();
    let texel = |px: u32, py: u32| -> [u32; 3] {
        mosaic_source(child, px, py, size)
            .map_or([0, 0, 0], |(c, x, y)| c.get_pixel(x, y).0.map(u32::from))
    };
    RgbImage::from_fn(size, size, |x, y| box_2x2(&texel, x, y))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A texture of `size` texels whose colours follow no pattern (splitmix64 of `seed`).
    fn noise(size: u32, seed: u64) -> RgbImage {
        let mut state = seed;
        RgbImage::from_fn(size, size, |_, _| {
            state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            let [r, g, b, ..] = (z ^ (z >> 31)).to_le_bytes();
            Rgb([r, g, b])
        })
    }

    /// Filters four children's textures, those `present` only, both from what a child
    /// carries and from the full textures, and checks they agree.
    fn check_parent_texture(size: u32, present: [bool; 4]) {
        let textures: Vec<RgbImage> = (0..4)
            .map(|i| noise(size, 7 * u64::from(size) + i))
            .collect();
        let full: Vec<Option<&RgbImage>> = textures
            .iter()
            .zip(present)
            .map(|(t, p)| p.then_some(t))
            .collect();
        // A 2x2 grid, or one whose east column or south row the pattern leaves out.
        let (columns, rows) = (1 + u32::from(present[1]), 1 + u32::from(present[2]));
        let grid = Grid {
            tile_size: 3,
            columns,
            rows,
        };
        let carried: Vec<Option<ChildTexture>> = (0..4)
            .map(|i| {
                let edges = Edges::for_missing(grid.missing_siblings(i % 2, i / 2), size);
                full[i as usize].map(|t| ChildTexture::of(t, edges).expect("encodes"))
            })
            .collect();
        let carried: Vec<Option<&ChildTexture>> = carried.iter().map(Option::as_ref).collect();
        let parent = from_children(&carried, size).expect("decodes");
        assert_eq!(
            parent,
            filter_mosaic(&full, size),
            "size {size}, children {present:?}"
        );
    }

    #[test]
    fn a_parent_texture_from_carried_halves_equals_the_filtered_mosaic() {
        // The children a grid's edge leaves: none, the east column, the south row, both.
        let patterns = [
            [true, true, true, true],
            [true, false, true, false],
            [true, true, false, false],
            [true, false, false, false],
        ];
        for size in [1, 2, 4, 16, 128] {
            for present in patterns {
                check_parent_texture(size, present);
            }
        }
    }

    #[test]
    fn level_counts_reach_down_to_the_coarsest_size() {
        assert_eq!(level_count(128), 5); // 8, 16, 32, 64, 128
        assert_eq!(level_count(8), 1);
        assert_eq!(level_count(4), 1);
    }

    #[test]
    fn source_density_sets_the_finest_size() {
        assert_eq!(size_for_source(1024, 1025, 129), 128); // Puget Sound: one texel per cell
        assert_eq!(size_for_source(1024, 1200, 129), 128); // Grand Canyon: 0.85 per cell
        assert_eq!(size_for_source(4096, 1025, 129), 512);
    }

    #[test]
    fn mip_chains_are_coarsest_first_and_average() {
        let finest = RgbImage::from_fn(16, 16, |x, _| {
            if x < 8 {
                Rgb([0, 0, 0])
            } else {
                Rgb([200, 100, 50])
            }
        });
        let chain = mip_chain(finest);
        assert_eq!(
            chain.iter().map(|l| l.width()).collect::<Vec<_>>(),
            vec![8, 16]
        );
        assert_eq!(chain[0].get_pixel(0, 0).0, [0, 0, 0]);
        assert_eq!(chain[0].get_pixel(7, 0).0, [200, 100, 50]);
    }

    #[test]
    fn cell_centred_texels_land_on_their_cells() {
        // A 4x4-sample raster with a 3x3 cell-centred image: texel (i, j) covers the cell
        // between samples i..i+1, j..j+1. One tile of 5 samples (4 cells) covers cells 0..4,
        // of which 3 are real; with 4 texels per side tile texel k is cell k.
        let source = RgbImage::from_fn(3, 3, |x, y| Rgb([(x * 80) as u8, (y * 80) as u8, 7]));
        let grid = Grid {
            tile_size: 5,
            columns: 1,
            rows: 1,
        };
        let tile = from_image(
            &source,
            Registration::EdgeAligned,
            (4, 4),
            grid,
            TileId::new(0, 0),
            4,
        );
        for k in 0..3 {
            assert_eq!(
                tile.get_pixel(k, k).0,
                [(k * 80) as u8, (k * 80) as u8, 7],
                "texel {k}"
            );
        }
    }

    #[test]
    fn generated_textures_tint_low_green_high_white_and_sea_blue() {
        assert_eq!(tint(0.0, -10.0, 100.0), [59.0, 110.0, 168.0]);
        assert_eq!(tint(100.0, 10.0, 100.0), [255.0, 255.0, 255.0]);
        assert_eq!(tint(10.0, 10.0, 100.0), [58.0, 125.0, 68.0]);
        // Shading: a slope facing the north-west light is brighter than one facing away.
        let codes: Vec<i32> = (0..25).map(|i| (i % 5) * 10).collect(); // rises to the east
        let band = Band::whole(&codes, 5, 5);
        let field = HeightField {
            band: &band,
            quantum_m: 1.0,
            offset_m: 1.0,
            spacing_m: [10.0, 10.0],
            min_m: 0.0,
            max_m: 1000.0,
        };
        let west_facing = field.colour(2, 2);
        let mirrored: Vec<i32> = (0..25).map(|i| (4 - i % 5) * 10).collect();
        let mirrored = Band::whole(&mirrored, 5, 5);
        let east_facing = HeightField {
            band: &mirrored,
            ..field
        }
        .colour(2, 2);
        assert!(west_facing[1] > east_facing[1]);
    }
}
