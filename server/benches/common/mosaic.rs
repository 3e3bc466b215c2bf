//! A larger DEM made from a smaller one, in bounded memory: four copies of a `w x h` 16-bit
//! greyscale PNG in a `(2w - 1) x (2h - 1)` one, the source in the north-west quarter and
//! mirrored east-west, north-south and both in the others. The copies share the middle row
//! and column, and mirroring makes every seam join equal samples, so the mosaic is as
//! smooth (and as hard to compress) as its source: a fair "same terrain, four times the
//! samples" input for the builder's memory benchmark.
//!
//! Memory is a few rows whatever the size: the source is decoded row by row to a raw
//! temporary file (2 bytes a sample), which the southern half reads back in reverse.

use anyhow::{Context, bail};
use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::path::Path;

/// Writes the mirrored 2x2 mosaic of `source` to `out`; returns its `[width, height]`.
pub fn write_mirrored(source: &Path, out: &Path) -> anyhow::Result<[u32; 2]> {
    let (width, height, mut raw) = decode_to_raw(source)?;
    let (out_width, out_height) = (2 * width - 1, 2 * height - 1);
    let file = File::create(out).with_context(|| format!("cannot create {}", out.display()))?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), out_width, out_height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Sixteen);
    encoder.set_compression(png::Compression::Balanced);
    let mut writer = encoder
        .write_header()
        .context("cannot write the PNG header")?;
    let mut stream = writer
        .stream_writer()
        .context("cannot start the PNG data")?;
    let row_bytes = 2 * width as usize;
    let mut row = vec![0u8; row_bytes];
    let mut mirrored = Vec::with_capacity(2 * out_width as usize);
    for y in 0..out_height {
        let source_row = if y < height { y } else { out_height - 1 - y };
        raw.seek(SeekFrom::Start(u64::from(source_row) * row_bytes as u64))?;
        raw.read_exact(&mut row)
            .context("cannot read the raw copy back")?;
        mirrored.clear();
        mirrored.extend_from_slice(&row);
        // Columns w..2w-1 repeat columns w-2..0.
        for x in (0..width as usize - 1).rev() {
            mirrored.extend_from_slice(&row[2 * x..2 * x + 2]);
        }
        stream
            .write_all(&mirrored)
            .with_context(|| format!("cannot write {}", out.display()))?;
    }
    stream.finish().context("cannot finish the PNG data")?;
    writer.finish().context("cannot finish the PNG")?;
    Ok([out_width, out_height])
}

/// Decodes a 16-bit greyscale PNG row by row into an anonymous temporary file of its
/// big-endian samples; returns its size and the file.
fn decode_to_raw(source: &Path) -> anyhow::Result<(u32, u32, File)> {
    let input = File::open(source).with_context(|| format!("cannot open {}", source.display()))?;
    let decoder = png::Decoder::new(std::io::BufReader::new(input));
    let mut reader = decoder
        .read_info()
        .with_context(|| format!("{} is not a readable PNG", source.display()))?;
    let info = reader.info();
    let (width, height) = (info.width, info.height);
    if info.color_type != png::ColorType::Grayscale
        || info.bit_depth != png::BitDepth::Sixteen
        || info.interlaced
        || width < 2
        || height < 2
    {
        bail!(
            "{} must be a non-interlaced 16-bit greyscale PNG of at least 2x2 samples",
            source.display()
        );
    }
    let mut raw = BufWriter::new(tempfile::tempfile().context("cannot create a temporary file")?);
    while let Some(row) = reader.next_row().context("cannot decode a row")? {
        raw.write_all(row.data())?;
    }
    let raw = raw.into_inner().context("cannot write the raw copy")?;
    Ok((width, height, raw))
}

#[allow(dead_code)] // Used by the build_memory bench, not by the mosaic example.
/// Writes `source` (a 16-bit greyscale PNG) to `out` with voids punched in it, as SRTM's
/// radar shadows are: discs of 1 to 25 samples' radius, and a few of 60, scattered by a
/// fixed sequence until `share` of the samples are voids, each holding `nodata`. Returns the
/// void samples. Memory: the source decoded whole (2 bytes a sample) and the void mask.
pub fn write_with_voids(source: &Path, out: &Path, share: f64, nodata: u16) -> anyhow::Result<u64> {
    let (width, height, mut raw) = decode_to_raw(source)?;
    let (w, h) = (width as usize, height as usize);
    let mut voids = vec![false; w * h];
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move |n: usize| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state % n as u64) as usize
    };
    let target = (share * (w * h) as f64) as usize;
    let mut count = 0;
    let mut disc = 0;
    while count < target {
        let r = if disc % 50 == 0 { 60 } else { 1 + next(25) };
        disc += 1;
        let (cx, cy) = (next(w), next(h));
        for y in cy.saturating_sub(r)..(cy + r + 1).min(h) {
            for x in cx.saturating_sub(r)..(cx + r + 1).min(w) {
                let (dx, dy) = (x as f64 - cx as f64, y as f64 - cy as f64);
                if dx.hypot(dy) <= r as f64 && !voids[y * w + x] {
                    voids[y * w + x] = true;
                    count += 1;
                }
            }
        }
    }
    let file = File::create(out).with_context(|| format!("cannot create {}", out.display()))?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), width, height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Sixteen);
    encoder.set_compression(png::Compression::Balanced);
    let mut writer = encoder
        .write_header()
        .context("cannot write the PNG header")?;
    let mut stream = writer
        .stream_writer()
        .context("cannot start the PNG data")?;
    raw.seek(SeekFrom::Start(0))?;
    let mut row = vec![0u8; 2 * w];
    for y in 0..h {
        raw.read_exact(&mut row)
            .context("cannot read the raw copy back")?;
        for x in 0..w {
            if voids[y * w + x] {
                row[2 * x..2 * x + 2].copy_from_slice(&nodata.to_be_bytes());
            }
        }
        stream
            .write_all(&row)
            .with_context(|| format!("cannot write {}", out.display()))?;
    }
    stream.finish().context("cannot finish the PNG data")?;
    writer.finish().context("cannot finish the PNG")?;
    Ok(count as u64)
}
