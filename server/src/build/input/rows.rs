//! Reading a height file a row at a time, in memory bounded by a row (a strip, or a row of
//! tiles, for GeoTIFF) whatever the file's size: 8- and 16-bit greyscale PNG through the
//! `png` crate's row reader, GeoTIFF strip by strip or by rows of tiles through the `tiff`
//! crate, `.hgt` row by row from the file. Samples go through the same rules as in the
//! whole-file readers ([`super::samples`]).
//!
//! A build reads a streamed file twice: [`RowReader::scan`] first, because what must be
//! known before the first tile depends on every sample (a float raster's quantum, the
//! heights' range that computed textures are tinted over, whether there are voids to
//! fill), then [`CodeRows`] while building. A file whose second reading differs from its
//! scan is refused ([`InputError::Changed`]). What the row reader does not handle (an
//! interlaced or animated PNG, an image that is not a PNG) gives `None` from [`open`], and
//! the caller reads the file whole.

use super::samples::{FloatCodes, FloatNodata, FloatRaster, FloatStats, IntNodata};
use super::{Format, InputError, ReadOptions};
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};
use terrain_shared::manifest::Georeference;

/// What a streamed file says about itself before its samples.
#[derive(Debug, Clone, PartialEq)]
pub struct RowHeader {
    pub width: u32,
    pub height: u32,
    /// The file's format, for messages.
    pub format: &'static str,
    pub georeference: Option<Georeference>,
    /// Sample spacing in metres when the file implies it (GeoTIFF, `.hgt`).
    pub spacing_m: Option<[f64; 2]>,
}

/// A height file opened for reading row by row.
#[derive(Debug)]
pub struct RowReader {
    path: PathBuf,
    options: ReadOptions,
    header: RowHeader,
    decoder: Decoder,
    rows_read: u32,
}

/// One row as the file holds it, with the rule that says which samples are no-data.
#[derive(Debug)]
enum RawRow<'a> {
    Int(&'a [i32], IntNodata),
    Float(&'a [f64], FloatNodata),
}

#[derive(Debug)]
enum Decoder {
    Png(Box<PngRows>),
    Tiff(Box<TiffRows>),
    Hgt(HgtRows),
}

/// Opens `path` for reading row by row, or `None` when it must be read whole (see the
/// module docs). Refuses what the whole-file reader refuses before the samples: an
/// unreadable header, a header whose decoded size the file cannot hold.
pub fn open(path: &Path, options: &ReadOptions) -> Result<Option<RowReader>, InputError> {
    if !(options.float_quantum_m.is_finite() && options.float_quantum_m > 0.0) {
        return Err(InputError::BadQuantum(options.float_quantum_m));
    }
    let io = |source| InputError::Io {
        path: path.into(),
        source,
    };
    let file = File::open(path).map_err(io)?;
    let file_bytes = file.metadata().map_err(io)?.len();
    let file = BufReader::new(file);
    let opened = match Format::of(path) {
        Format::Png => PngRows::open(file, path, file_bytes, options.nodata)?
            .map(|(header, rows)| (header, Decoder::Png(Box::new(rows)))),
        Format::GeoTiff => {
            let (header, rows) = TiffRows::open(file, path, file_bytes, options)?;
            Some((header, Decoder::Tiff(Box::new(rows))))
        }
        Format::Hgt => {
            let (header, rows) = HgtRows::open(file, path, file_bytes)?;
            Some((header, Decoder::Hgt(rows)))
        }
    };
    Ok(opened.map(|(header, decoder)| RowReader {
        path: path.into(),
        options: *options,
        header,
        decoder,
        rows_read: 0,
    }))
}

/// What a first pass over a streamed file found: everything a build must know before its
/// first tile.
#[derive(Debug, Clone)]
pub struct Scan {
    path: PathBuf,
    options: ReadOptions,
    pub header: RowHeader,
    /// Samples that are voids: no-data, and (with [`super::OutOfRange::Nodata`]) float
    /// samples no code holds.
    pub voids: usize,
    /// Float samples no code holds, counted in `voids`.
    pub out_of_range_voids: usize,
    /// Metres per code step, as far as the file knows (1 for integers).
    pub quantum_m: f64,
    /// Smallest and largest code of the samples that are not voids.
    pub code_range: (i32, i32),
    floats: Option<FloatCodes>,
}

impl RowReader {
    pub fn header(&self) -> &RowHeader {
        &self.header
    }

    /// Reads every row once and returns what they hold ([`Scan`]), or the error the
    /// whole-file reader gives for the same file.
    pub fn scan(mut self) -> Result<Scan, InputError> {
        let mut ints = IntScan::default();
        let mut floats: Option<FloatStats> = None;
        let quantum_m = self.options.float_quantum_m;
        let path = self.path.clone();
        let mut y = 0;
        while let Some(row) = self.next_raw()? {
            match row {
                RawRow::Int(codes, nodata) => ints.add(codes, nodata),
                RawRow::Float(values, nodata) => {
                    let stats = floats.get_or_insert_with(|| FloatStats::new(quantum_m));
                    for (x, &v) in values.iter().enumerate() {
                        stats.add(x as u32, y, v, nodata.is_void(v));
                    }
                }
            }
            y += 1;
        }
        if ints.samples > 0 && floats.is_some() {
            return Err(InputError::Tiff {
                path,
                message: "its chunks mix integer and float samples".into(),
            });
        }
        let header = self.header.clone();
        let (voids, out_of_range_voids, quantum_m, code_range, floats) = match floats {
            None => (ints.voids, 0, 1.0, (ints.min, ints.max), None),
            Some(stats) => {
                let codes = stats.finish(&FloatRaster {
                    path: &path,
                    quantum_m,
                    out_of_range: self.options.out_of_range,
                })?;
                let range = codes.coded.map_or((0, 0), |(lo, hi)| {
                    (codes.code(lo).unwrap_or(0), codes.code(hi).unwrap_or(0))
                });
                let voids = codes.no_data + codes.out_of_range;
                (
                    voids,
                    codes.out_of_range,
                    codes.quantum_m,
                    range,
                    Some(codes),
                )
            }
        };
        super::check_shape(&path, header.width, header.height)?;
        let samples = header.width as usize * header.height as usize;
        if voids > 0 && voids == samples {
            return Err(InputError::AllVoid { path });
        }
        Ok(Scan {
            path,
            options: self.options,
            header,
            voids,
            out_of_range_voids,
            quantum_m,
            code_range,
            floats,
        })
    }

    /// The next row as the file holds it; `None` after the last.
    fn next_raw(&mut self) -> Result<Option<RawRow<'_>>, InputError> {
        if self.rows_read == self.header.height {
            return Ok(None);
        }
        let path = &self.path;
        let row = match &mut self.decoder {
            Decoder::Png(rows) => rows.next(path)?,
            Decoder::Tiff(rows) => rows.next(path)?,
            Decoder::Hgt(rows) => rows.next(path)?,
        };
        let Some(row) = row else {
            return Err(InputError::Image {
                path: path.clone(),
                message: format!(
                    "its data ends after {} of {} rows",
                    self.rows_read, self.header.height
                ),
            });
        };
        let width = self.header.width as usize;
        let length = match &row {
            RawRow::Int(codes, _) => codes.len(),
            RawRow::Float(values, _) => values.len(),
        };
        if length != width {
            return Err(InputError::Image {
                path: path.clone(),
                message: format!("row {} has {length} samples, not {width}", self.rows_read),
            });
        }
        self.rows_read += 1;
        Ok(Some(row))
    }
}

/// Voids and range of integer samples.
#[derive(Debug)]
struct IntScan {
    samples: usize,
    voids: usize,
    min: i32,
    max: i32,
}

impl Default for IntScan {
    fn default() -> IntScan {
        IntScan {
            samples: 0,
            voids: 0,
            min: i32::MAX,
            max: i32::MIN,
        }
    }
}

impl IntScan {
    fn add(&mut self, codes: &[i32], nodata: IntNodata) {
        self.samples += codes.len();
        for &c in codes {
            if nodata.is_void(c) {
                self.voids += 1;
            } else {
                self.min = self.min.min(c);
                self.max = self.max.max(c);
            }
        }
    }
}

/// A row's codes and which of them are voids.
pub type RowWithVoids<'a> = (&'a [i32], &'a [bool]);

/// Rows of height codes for the builder: a streamed file converted as its [`Scan`] decided,
/// or a raster held whole. A streamed file with voids gives them filled, once its fills are
/// given ([`CodeRows::with_fills`]); before, [`CodeRows::next_row_with_voids`] gives the rows
/// as the file holds them, voids marked, for the passes that find and solve the voids.
#[derive(Debug)]
pub struct CodeRows {
    /// The file, for messages (empty for a raster in memory).
    path: PathBuf,
    source: Source,
    row: Vec<i32>,
    voids: Vec<bool>,
    next: u32,
    /// Void samples the scan counted, and those seen so far.
    expected_voids: usize,
    seen_voids: usize,
    fills: Option<crate::build::voids::FillStream>,
}

#[derive(Debug)]
enum Source {
    Stream {
        reader: Box<RowReader>,
        floats: Option<FloatCodes>,
        /// The scan's code range: a code outside it means the file changed.
        range: (i32, i32),
    },
    Memory {
        codes: Vec<i32>,
        width: usize,
        height: u32,
    },
}

impl CodeRows {
    /// Opens the scanned file again to read its codes. A file with voids needs its fills
    /// ([`CodeRows::with_fills`]) before [`CodeRows::next_row`].
    pub fn stream(scan: &Scan) -> Result<CodeRows, InputError> {
        let changed = || InputError::Changed {
            path: scan.path.clone(),
        };
        let reader = open(&scan.path, &scan.options)?.ok_or_else(changed)?;
        if reader.header != scan.header {
            return Err(changed());
        }
        Ok(CodeRows {
            path: scan.path.clone(),
            source: Source::Stream {
                reader: Box::new(reader),
                floats: scan.floats,
                range: scan.code_range,
            },
            row: Vec::new(),
            voids: Vec::new(),
            next: 0,
            expected_voids: scan.voids,
            seen_voids: 0,
            fills: None,
        })
    }

    /// These rows with their voids filled by `fills` (found and solved over the same rows).
    pub fn with_fills(mut self, fills: crate::build::voids::FillStream) -> CodeRows {
        self.fills = Some(fills);
        self
    }

    /// The rows of a raster in memory (`codes` row-major, `width` samples a row).
    pub fn memory(codes: Vec<i32>, width: u32) -> CodeRows {
        let height = codes.len().checked_div(width as usize).unwrap_or(0) as u32;
        CodeRows {
            path: PathBuf::new(),
            source: Source::Memory {
                codes,
                width: width as usize,
                height,
            },
            row: Vec::new(),
            voids: Vec::new(),
            next: 0,
            expected_voids: 0,
            seen_voids: 0,
            fills: None,
        }
    }

    /// The next row of codes, north first, voids filled; `None` after the last.
    pub fn next_row(&mut self) -> Result<Option<&[i32]>, InputError> {
        if matches!(self.source, Source::Memory { .. }) {
            return self.next_memory_row();
        }
        if self.next_stream_row()?.is_none() {
            return Ok(None);
        }
        // Every row goes through the fills, voids or not: they label the rows again as
        // they pass, and a row left out would join the voids above and below it.
        match &mut self.fills {
            Some(fills) => {
                fills
                    .apply(&mut self.row, &self.voids)
                    .map_err(|source| InputError::Io {
                        path: std::env::temp_dir(),
                        source,
                    })?
            }
            None if self.voids.iter().any(|&v| v) => {
                return Err(InputError::Changed {
                    path: self.path.clone(),
                });
            }
            None => {}
        }
        Ok(Some(&self.row))
    }

    /// The next row as the file holds it, its void samples marked (their codes 0); `None`
    /// after the last. Streamed files only.
    pub fn next_row_with_voids(&mut self) -> Result<Option<RowWithVoids<'_>>, InputError> {
        Ok(self
            .next_stream_row()?
            .map(|()| (self.row.as_slice(), self.voids.as_slice())))
    }

    fn next_memory_row(&mut self) -> Result<Option<&[i32]>, InputError> {
        let y = self.next;
        match &mut self.source {
            Source::Memory {
                codes,
                width,
                height,
            } => {
                if y == *height {
                    return Ok(None);
                }
                self.next += 1;
                Ok(codes.get(y as usize * *width..(y as usize + 1) * *width))
            }
            // Only rasters in memory come here (`next_row`).
            Source::Stream { .. } => Ok(None),
        }
    }

    /// Reads the next streamed row into `row` and `voids`; `None` after the last.
    fn next_stream_row(&mut self) -> Result<Option<()>, InputError> {
        let Source::Stream {
            reader,
            floats,
            range: (low, high),
        } = &mut self.source
        else {
            return Ok(None);
        };
        let changed = || InputError::Changed {
            path: self.path.clone(),
        };
        let Some(raw) = reader.next_raw()? else {
            // Every void the scan counted, no more, no fewer.
            if self.seen_voids != self.expected_voids {
                return Err(changed());
            }
            return Ok(None);
        };
        self.row.clear();
        self.voids.clear();
        let in_range = |c: i32| (*low..=*high).contains(&c);
        let converted = match (raw, floats) {
            (RawRow::Int(codes, nodata), None) => codes.iter().all(|&c| {
                let void = nodata.is_void(c);
                self.row.push(if void { 0 } else { c });
                self.voids.push(void);
                void || in_range(c)
            }),
            (RawRow::Float(values, nodata), Some(floats)) => values.iter().all(|&v| {
                // No-data, and a value no code holds (refused by the scan unless made a
                // void there), are voids.
                let code = (!nodata.is_void(v)).then(|| floats.code(v)).flatten();
                self.row.push(code.unwrap_or(0));
                self.voids.push(code.is_none());
                code.is_none_or(in_range)
            }),
            _ => false,
        };
        self.seen_voids += self.voids.iter().filter(|&&v| v).count();
        if !converted || self.seen_voids > self.expected_voids {
            return Err(changed());
        }
        self.next += 1;
        Ok(Some(()))
    }
}

/// 8- or 16-bit greyscale PNG rows.
struct PngRows {
    reader: png::Reader<BufReader<File>>,
    sixteen: bool,
    nodata: IntNodata,
    row: Vec<i32>,
}

impl std::fmt::Debug for PngRows {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PngRows")
            .field("sixteen", &self.sixteen)
            .finish_non_exhaustive()
    }
}

impl PngRows {
    /// `None` for what the whole-file reader must handle: not a PNG by content (the image
    /// reader guesses by content, as the whole-file reader does), interlaced, animated, or
    /// anything but 8- or 16-bit grey once expanded as the `image` crate expands it.
    fn open(
        mut file: BufReader<File>,
        path: &Path,
        file_bytes: u64,
        nodata: Option<f64>,
    ) -> Result<Option<(RowHeader, PngRows)>, InputError> {
        use std::io::{BufRead, Seek};
        let image_error = |e: png::DecodingError| InputError::Image {
            path: path.into(),
            message: e.to_string(),
        };
        let io = |source| InputError::Io {
            path: path.into(),
            source,
        };
        let start = file.fill_buf().map_err(io)?;
        if !start.starts_with(&[137, 80, 78, 71, 13, 10, 26, 10]) {
            return Ok(None);
        }
        file.rewind().map_err(io)?;
        let mut decoder = png::Decoder::new(file);
        decoder.set_transformations(png::Transformations::EXPAND);
        let reader = decoder.read_info().map_err(image_error)?;
        let info = reader.info();
        let (width, height) = (info.width, info.height);
        let sixteen = match reader.output_color_type() {
            (png::ColorType::Grayscale, png::BitDepth::Eight) => false,
            (png::ColorType::Grayscale, png::BitDepth::Sixteen) => true,
            _ => return Ok(None),
        };
        if info.interlaced || info.is_animated() {
            return Ok(None);
        }
        let sample_bytes = if sixteen { 2 } else { 1 };
        super::check_decoded_size(path, (width, height), sample_bytes, file_bytes as usize)?;
        let header = RowHeader {
            width,
            height,
            format: "PNG",
            georeference: None,
            spacing_m: None,
        };
        let rows = PngRows {
            reader,
            sixteen,
            nodata: nodata.map_or(IntNodata::None, |v| IntNodata::Code(v as i64)),
            row: Vec::with_capacity(width as usize),
        };
        Ok(Some((header, rows)))
    }

    fn next(&mut self, path: &Path) -> Result<Option<RawRow<'_>>, InputError> {
        let row = self.reader.next_row().map_err(|e| InputError::Image {
            path: path.into(),
            message: e.to_string(),
        })?;
        let Some(row) = row else { return Ok(None) };
        self.row.clear();
        if self.sixteen {
            let samples = row.data().chunks_exact(2);
            self.row
                .extend(samples.map(|b| i32::from(u16::from_be_bytes([b[0], b[1]]))));
        } else {
            self.row.extend(row.data().iter().map(|&b| i32::from(b)));
        }
        Ok(Some(RawRow::Int(&self.row, self.nodata)))
    }
}

/// GeoTIFF rows, read a strip or a row of tiles at a time.
struct TiffRows {
    decoder: tiff::decoder::Decoder<BufReader<File>>,
    width: u32,
    height: u32,
    /// Samples of a chunk (strip or tile) across and down.
    chunk: (u32, u32),
    /// Chunks in a row of chunks, and in the file.
    across: u32,
    chunks: u32,
    nodata: Option<f64>,
    /// The current row of chunks, full rows, and how many of them have been handed out.
    buffered: Buffered,
    buffered_rows: u32,
    handed_out: u32,
    next_chunk_row: u32,
}

#[derive(Debug)]
enum Buffered {
    Int(Vec<i32>),
    Float(Vec<f64>, FloatNodata),
}

impl std::fmt::Debug for TiffRows {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TiffRows")
            .field("chunk", &self.chunk)
            .field("next_chunk_row", &self.next_chunk_row)
            .finish_non_exhaustive()
    }
}

impl TiffRows {
    fn open(
        file: BufReader<File>,
        path: &Path,
        file_bytes: u64,
        options: &ReadOptions,
    ) -> Result<(RowHeader, TiffRows), InputError> {
        use tiff::decoder::{ChunkType, Decoder};
        let err = |e: tiff::TiffError| super::tiff_error(path, e.to_string());
        let mut decoder = Decoder::new(file).map_err(err)?;
        let header = super::geotiff_header(&mut decoder, path, file_bytes as usize, options)?;
        let chunk = decoder.chunk_dimensions();
        if chunk.0 == 0 || chunk.1 == 0 {
            return Err(super::tiff_error(
                path,
                format!("chunks of {chunk:?} samples"),
            ));
        }
        let (across, chunks) = match decoder.get_chunk_type() {
            ChunkType::Strip => (1, decoder.strip_count().map_err(err)?),
            ChunkType::Tile => (
                header.width.div_ceil(chunk.0),
                decoder.tile_count().map_err(err)?,
            ),
        };
        let rows = TiffRows {
            decoder,
            width: header.width,
            height: header.height,
            chunk,
            across,
            chunks,
            nodata: header.nodata,
            buffered: Buffered::Int(Vec::new()),
            buffered_rows: 0,
            handed_out: 0,
            next_chunk_row: 0,
        };
        let header = RowHeader {
            width: header.width,
            height: header.height,
            format: "GeoTIFF",
            georeference: header.georeference,
            spacing_m: header.spacing_m,
        };
        Ok((header, rows))
    }

    fn next(&mut self, path: &Path) -> Result<Option<RawRow<'_>>, InputError> {
        if self.handed_out == self.buffered_rows {
            if self.rows_before(self.next_chunk_row) >= self.height {
                return Ok(None);
            }
            self.read_chunk_row(path)?;
        }
        let width = self.width as usize;
        let at = self.handed_out as usize * width;
        self.handed_out += 1;
        Ok(Some(match &self.buffered {
            Buffered::Int(codes) => RawRow::Int(
                &codes[at..at + width],
                self.nodata.map_or(IntNodata::None, IntNodata::Value),
            ),
            Buffered::Float(values, nodata) => RawRow::Float(&values[at..at + width], *nodata),
        }))
    }

    /// Image rows above row of chunks `chunk_row`, at most the image's height.
    fn rows_before(&self, chunk_row: u32) -> u32 {
        (u64::from(chunk_row) * u64::from(self.chunk.1)).min(u64::from(self.height)) as u32
    }

    /// Reads the next row of chunks into full-width rows.
    fn read_chunk_row(&mut self, path: &Path) -> Result<(), InputError> {
        let err = |message: String| super::tiff_error(path, message);
        let done = self.rows_before(self.next_chunk_row);
        let rows = self.chunk.1.min(self.height.saturating_sub(done));
        let width = self.width as usize;
        let first = self.next_chunk_row * self.across;
        for column in 0..self.across {
            let index = first + column;
            if index >= self.chunks {
                return Err(err(format!(
                    "{} chunks, fewer than its size needs",
                    self.chunks
                )));
            }
            let (chunk_width, chunk_rows) = self.decoder.chunk_data_dimensions(index);
            let x0 = (column * self.chunk.0) as usize;
            if chunk_rows != rows || x0 + chunk_width as usize > width {
                return Err(err(format!(
                    "chunk {index} is {chunk_width}x{chunk_rows} samples, which does not fit the image"
                )));
            }
            let result = self
                .decoder
                .read_chunk(index)
                .map_err(|e| err(e.to_string()))?;
            let chunk = Chunk::of(result, self.nodata).map_err(err)?;
            let expected = chunk_width as usize * chunk_rows as usize;
            if chunk.len() != expected {
                return Err(err(format!(
                    "{} samples in chunk {index} of {chunk_width}x{chunk_rows}: multi-band images are not heights",
                    chunk.len()
                )));
            }
            if column == 0 {
                self.buffered =
                    chunk.empty_like(std::mem::take(&mut self.buffered), width * rows as usize);
            }
            if !self.buffered.place(&chunk, x0, chunk_width as usize, width) {
                return Err(err("its chunks mix sample types".into()));
            }
        }
        self.buffered_rows = rows;
        self.handed_out = 0;
        self.next_chunk_row += 1;
        Ok(())
    }
}

/// One decoded chunk's samples.
#[derive(Debug)]
enum Chunk {
    Int(Vec<i32>),
    Float(Vec<f64>, FloatNodata),
}

impl Chunk {
    fn of(result: tiff::decoder::DecodingResult, nodata: Option<f64>) -> Result<Chunk, String> {
        use tiff::decoder::DecodingResult;
        Ok(match result {
            DecodingResult::I16(v) => Chunk::Int(v.into_iter().map(i32::from).collect()),
            DecodingResult::U16(v) => Chunk::Int(v.into_iter().map(i32::from).collect()),
            DecodingResult::U8(v) => Chunk::Int(v.into_iter().map(i32::from).collect()),
            DecodingResult::F32(v) => Chunk::Float(
                v.into_iter().map(f64::from).collect(),
                FloatNodata::for_f32(nodata),
            ),
            DecodingResult::F64(v) => Chunk::Float(v, FloatNodata::for_f64(nodata)),
            other => {
                return Err(format!(
                    "sample type {} (supported: int16, uint16, uint8, float32, float64)",
                    super::sample_type_name(&other)
                ));
            }
        })
    }

    fn len(&self) -> usize {
        match self {
            Chunk::Int(v) => v.len(),
            Chunk::Float(v, _) => v.len(),
        }
    }

    /// A buffer of `size` samples of this chunk's kind, reusing `old`'s allocation when it
    /// is of that kind.
    fn empty_like(&self, old: Buffered, size: usize) -> Buffered {
        match (self, old) {
            (Chunk::Int(_), Buffered::Int(mut codes)) => {
                codes.clear();
                codes.resize(size, 0);
                Buffered::Int(codes)
            }
            (Chunk::Int(_), _) => Buffered::Int(vec![0; size]),
            (Chunk::Float(_, nodata), Buffered::Float(mut values, _)) => {
                values.clear();
                values.resize(size, 0.0);
                Buffered::Float(values, *nodata)
            }
            (Chunk::Float(_, nodata), _) => Buffered::Float(vec![0.0; size], *nodata),
        }
    }
}

impl Default for Buffered {
    fn default() -> Buffered {
        Buffered::Int(Vec::new())
    }
}

impl Buffered {
    /// Copies a chunk's rows (`chunk_width` samples each) to columns `x0..` of rows `width`
    /// samples long; `false` when the chunk is not of the buffer's kind.
    fn place(&mut self, chunk: &Chunk, x0: usize, chunk_width: usize, width: usize) -> bool {
        fn copy<T: Copy>(out: &mut [T], source: &[T], x0: usize, chunk_width: usize, width: usize) {
            for (y, source) in source.chunks_exact(chunk_width.max(1)).enumerate() {
                let at = y * width + x0;
                out[at..at + chunk_width].copy_from_slice(source);
            }
        }
        match (self, chunk) {
            (Buffered::Int(out), Chunk::Int(source)) => copy(out, source, x0, chunk_width, width),
            (Buffered::Float(out, _), Chunk::Float(source, _)) => {
                copy(out, source, x0, chunk_width, width);
            }
            _ => return false,
        }
        true
    }
}

/// SRTM `.hgt` rows: big-endian int16, void -32768.
#[derive(Debug)]
struct HgtRows {
    file: BufReader<File>,
    bytes: Vec<u8>,
    row: Vec<i32>,
}

impl HgtRows {
    fn open(
        file: BufReader<File>,
        path: &Path,
        file_bytes: u64,
    ) -> Result<(RowHeader, HgtRows), InputError> {
        let (side, georeference, spacing_m) = super::hgt_header(file_bytes, path)?;
        let header = RowHeader {
            width: side,
            height: side,
            format: "SRTM .hgt",
            georeference,
            spacing_m,
        };
        let rows = HgtRows {
            file,
            bytes: vec![0; 2 * side as usize],
            row: Vec::with_capacity(side as usize),
        };
        Ok((header, rows))
    }

    fn next(&mut self, path: &Path) -> Result<Option<RawRow<'_>>, InputError> {
        self.file
            .read_exact(&mut self.bytes)
            .map_err(|source| InputError::Io {
                path: path.into(),
                source,
            })?;
        self.row.clear();
        self.row.extend(
            self.bytes
                .chunks_exact(2)
                .map(|b| i32::from(i16::from_be_bytes([b[0], b[1]]))),
        );
        Ok(Some(RawRow::Int(&self.row, super::HGT_NODATA)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::build::input::{OutOfRange, decode_heights};
    use tiff::encoder::{TiffEncoder, colortype};

    const OPTIONS: ReadOptions = ReadOptions {
        nodata: None,
        float_quantum_m: 0.01,
        out_of_range: OutOfRange::Refuse,
    };

    /// Codes of a `width x height` raster that rise, fall and repeat without a pattern a
    /// reader could get right by accident.
    fn samples(width: u32, height: u32) -> Vec<i32> {
        (0..u64::from(width) * u64::from(height))
            .map(|i| ((i * 7919) % 4001) as i32 - 1000 + (i / u64::from(width)) as i32)
            .collect()
    }

    fn png_bytes(width: u32, height: u32, values: &[i32], sixteen: bool) -> Vec<u8> {
        let mut out = std::io::Cursor::new(Vec::new());
        let encoder = image::codecs::png::PngEncoder::new(&mut out);
        if sixteen {
            let raw: Vec<u16> = values.iter().map(|&v| v.clamp(0, 65535) as u16).collect();
            image::ImageBuffer::<image::Luma<u16>, _>::from_raw(width, height, raw)
                .expect("size")
                .write_with_encoder(encoder)
                .expect("encodes");
        } else {
            let raw: Vec<u8> = values.iter().map(|&v| v.clamp(0, 255) as u8).collect();
            image::GrayImage::from_raw(width, height, raw)
                .expect("size")
                .write_with_encoder(encoder)
                .expect("encodes");
        }
        out.into_inner()
    }

    /// A GeoTIFF in strips of `rows_per_strip` rows, with a no-data tag when given.
    fn tiff_bytes<C: colortype::ColorType>(
        width: u32,
        height: u32,
        values: &[C::Inner],
        rows_per_strip: u32,
        nodata: Option<&str>,
    ) -> Vec<u8>
    where
        [C::Inner]: tiff::encoder::TiffValue,
    {
        let mut out = std::io::Cursor::new(Vec::new());
        let mut encoder = TiffEncoder::new(&mut out).expect("encoder");
        let mut image = encoder.new_image::<C>(width, height).expect("image");
        image.rows_per_strip(rows_per_strip).expect("strips");
        if let Some(nodata) = nodata {
            image
                .encoder()
                .write_tag(tiff::tags::Tag::GdalNodata, nodata)
                .expect("tag");
        }
        image.write_data(values).expect("data");
        out.into_inner()
    }

    /// An uncompressed little-endian int16 TIFF in `tile x tile` tiles, written by hand (the
    /// `tiff` crate writes strips only); tiles past the edge are padded with zeros.
    fn tiled_tiff_bytes(width: u32, height: u32, values: &[i32], tile: u32) -> Vec<u8> {
        let (across, down) = (width.div_ceil(tile), height.div_ceil(tile));
        let tile_bytes = tile * tile * 2;
        let count = across * down;
        let entries: u16 = 10;
        let ifd = 8u32;
        let offsets_at = ifd + 2 + 12 * u32::from(entries) + 4;
        let counts_at = offsets_at + 4 * count;
        let data_at = counts_at + 4 * count;
        let mut out = Vec::new();
        out.extend_from_slice(b"II*\0");
        out.extend_from_slice(&ifd.to_le_bytes());
        out.extend_from_slice(&entries.to_le_bytes());
        let mut entry = |tag: u16, kind: u16, n: u32, value: u32| {
            out.extend_from_slice(&tag.to_le_bytes());
            out.extend_from_slice(&kind.to_le_bytes());
            out.extend_from_slice(&n.to_le_bytes());
            out.extend_from_slice(&value.to_le_bytes());
        };
        let (short, long) = (3, 4);
        entry(256, long, 1, width);
        entry(257, long, 1, height);
        entry(258, short, 1, 16);
        entry(259, short, 1, 1);
        entry(262, short, 1, 1);
        entry(277, short, 1, 1);
        entry(322, long, 1, tile);
        entry(323, long, 1, tile);
        entry(324, long, count, offsets_at);
        entry(325, long, count, counts_at);
        out.extend_from_slice(&0u32.to_le_bytes());
        // SampleFormat is left out: unsigned 16-bit, so keep the samples non-negative.
        for i in 0..count {
            out.extend_from_slice(&(data_at + i * tile_bytes).to_le_bytes());
        }
        for _ in 0..count {
            out.extend_from_slice(&tile_bytes.to_le_bytes());
        }
        for t in 0..count {
            let (tx, ty) = (t % across, t / across);
            for y in ty * tile..(ty + 1) * tile {
                for x in tx * tile..(tx + 1) * tile {
                    let v = if x < width && y < height {
                        values[(y * width + x) as usize]
                    } else {
                        0
                    };
                    out.extend_from_slice(&(v.clamp(0, 65535) as u16).to_le_bytes());
                }
            }
        }
        out
    }

    /// Reads a file row by row as a build does: the scan, then (without voids) the codes.
    fn stream(path: &Path, options: &ReadOptions) -> Result<(Scan, Option<Vec<i32>>), InputError> {
        let reader = open(path, options)?.expect("a format the row reader handles");
        let scan = reader.scan()?;
        if scan.voids > 0 {
            return Ok((scan, None));
        }
        let mut rows = CodeRows::stream(&scan)?;
        let mut codes = Vec::new();
        while let Some(row) = rows.next_row()? {
            codes.extend_from_slice(row);
        }
        Ok((scan, Some(codes)))
    }

    /// Writes `bytes` as the file `name` and checks that reading it row by row gives what
    /// reading it whole gives: the same error, or the same size, georeference, quantum,
    /// voids, code range and (without voids) codes.
    fn check_streams_as_read_whole(name: &str, bytes: &[u8], options: ReadOptions) {
        let dir = tempfile::tempdir().expect("temporary directory");
        let path = dir.path().join(name);
        std::fs::write(&path, bytes).expect("write");
        let whole = decode_heights(bytes, Format::of(&path), &path, &options);
        let streamed = stream(&path, &options);
        let (raster, (scan, codes)) = match (whole, streamed) {
            (Err(w), Err(s)) => return assert_eq!(w.to_string(), s.to_string(), "{name}"),
            (Ok(raster), Ok(streamed)) => (raster, streamed),
            (w, s) => panic!("{name}: whole {:?}, streamed {:?}", w.err(), s.err()),
        };
        let header = &scan.header;
        assert_eq!(
            (header.width, header.height, header.format),
            (raster.width, raster.height, raster.format),
            "{name}"
        );
        assert_eq!(header.georeference, raster.georeference, "{name}");
        assert_eq!(header.spacing_m, raster.spacing_m, "{name}");
        assert_eq!(scan.quantum_m, raster.quantum_m, "{name}");
        assert_eq!(scan.voids, raster.void_count(), "{name}");
        assert_eq!(scan.out_of_range_voids, raster.out_of_range_voids, "{name}");
        let valid = raster
            .codes
            .iter()
            .enumerate()
            .filter(|&(i, _)| raster.voids.get(i) != Some(&true))
            .map(|(_, &c)| c);
        let range = valid.fold((i32::MAX, i32::MIN), |(lo, hi), c| (lo.min(c), hi.max(c)));
        assert_eq!(scan.code_range, range, "{name}");
        assert_eq!(codes.is_none(), scan.voids > 0, "{name}");
        if let Some(codes) = codes {
            assert_eq!(codes, raster.codes, "{name}");
        }
    }

    #[test]
    fn every_streamed_format_reads_as_the_whole_file_reader_reads_it() {
        let (w, h) = (37, 21);
        let values = samples(w, h);
        let positive: Vec<i32> = values.iter().map(|v| v + 1000).collect();
        let with_nodata = ReadOptions {
            nodata: Some(1000.0),
            ..OPTIONS
        };
        check_streams_as_read_whole("a.png", &png_bytes(w, h, &positive, true), OPTIONS);
        check_streams_as_read_whole("a.png", &png_bytes(w, h, &positive, true), with_nodata);
        check_streams_as_read_whole("b.png", &png_bytes(w, h, &positive, false), OPTIONS);
        let ints: Vec<i16> = values.iter().map(|&v| v as i16).collect();
        for rows_per_strip in [1, 4, h] {
            let tiff = tiff_bytes::<colortype::GrayI16>(w, h, &ints, rows_per_strip, None);
            check_streams_as_read_whole("c.tif", &tiff, OPTIONS);
        }
        let tiff = tiff_bytes::<colortype::GrayI16>(w, h, &ints, 5, Some("-1000"));
        check_streams_as_read_whole("d.tif", &tiff, OPTIONS);
        check_streams_as_read_whole("e.tif", &tiled_tiff_bytes(w, h, &positive, 16), OPTIONS);
        let whole: Vec<f32> = values.iter().map(|&v| v as f32).collect();
        let fractions: Vec<f32> = values.iter().map(|&v| v as f32 / 8.0).collect();
        let fractions_f64: Vec<f64> = values.iter().map(|&v| f64::from(v) / 3.0).collect();
        for (name, floats) in [("f.tif", &whole), ("g.tif", &fractions)] {
            let tiff = tiff_bytes::<colortype::Gray32Float>(w, h, floats, 3, None);
            check_streams_as_read_whole(name, &tiff, OPTIONS);
        }
        let tiff = tiff_bytes::<colortype::Gray64Float>(w, h, &fractions_f64, 7, None);
        check_streams_as_read_whole("h.tif", &tiff, OPTIONS);
        // Floats no code holds: refused alike, or voids alike.
        let mut marked = fractions.clone();
        marked[40] = f32::MIN;
        marked[700] = 1e30;
        let tiff = tiff_bytes::<colortype::Gray32Float>(w, h, &marked, 2, None);
        check_streams_as_read_whole("i.tif", &tiff, OPTIONS);
        let as_nodata = ReadOptions {
            out_of_range: OutOfRange::Nodata,
            ..OPTIONS
        };
        check_streams_as_read_whole("i.tif", &tiff, as_nodata);
        // SRTM: 1201^2 big-endian samples, voids at -32768.
        let side = 1201;
        let mut hgt: Vec<u8> = samples(side, side)
            .iter()
            .flat_map(|&v| (v as i16).to_be_bytes())
            .collect();
        check_streams_as_read_whole("N46W122.hgt", &hgt, OPTIONS);
        hgt[2 * 5000..2 * 5000 + 2].copy_from_slice(&(-32768i16).to_be_bytes());
        check_streams_as_read_whole("N46W122.hgt", &hgt, OPTIONS);
        check_streams_as_read_whole("N46W122.hgt", &hgt[..1000], OPTIONS);
        // Too small, and not a PNG at all (the whole-file reader's case).
        check_streams_as_read_whole("j.png", &png_bytes(1, 5, &[1, 2, 3, 4, 5], true), OPTIONS);
    }

    #[test]
    fn a_gdal_nodata_tag_that_is_not_a_number_is_refused_by_both_readers() {
        let (w, h) = (9, 6);
        let ints: Vec<i16> = (0..w * h)
            .map(|i| if i == 7 { -32768 } else { i as i16 })
            .collect();
        let tiff = tiff_bytes::<colortype::GrayI16>(w, h, &ints, 2, Some("abc"));
        let dir = tempfile::tempdir().expect("temporary directory");
        let path = dir.path().join("abc.tif");
        std::fs::write(&path, &tiff).expect("write");
        let whole = decode_heights(&tiff, Format::of(&path), &path, &OPTIONS)
            .expect_err("an unreadable GDAL_NODATA is refused");
        assert!(
            whole.to_string().contains(
                "its GDAL_NODATA tag \"abc\" is not a number; give the no-data value with --nodata"
            ),
            "{whole}"
        );
        check_streams_as_read_whole("abc.tif", &tiff, OPTIONS);
        // With --nodata given, the tag is not read.
        let given = ReadOptions {
            nodata: Some(-32768.0),
            ..OPTIONS
        };
        check_streams_as_read_whole("abc.tif", &tiff, given);
        // An empty tag says nothing.
        let empty = tiff_bytes::<colortype::GrayI16>(w, h, &ints, 2, Some(""));
        check_streams_as_read_whole("empty.tif", &empty, OPTIONS);
    }

    #[test]
    fn a_file_that_changes_between_the_scan_and_the_build_is_refused() {
        let (w, h) = (9, 6);
        let dir = tempfile::tempdir().expect("temporary directory");
        let path = dir.path().join("changing.png");
        let values: Vec<i32> = (0..w * h).map(|i| i as i32).collect();
        std::fs::write(&path, png_bytes(w, h, &values, true)).expect("write");
        let scan = open(&path, &OPTIONS)
            .expect("opens")
            .expect("streams")
            .scan()
            .expect("scans");
        let mut changed = values.clone();
        changed[30] = 1000;
        std::fs::write(&path, png_bytes(w, h, &changed, true)).expect("write");
        let mut rows = CodeRows::stream(&scan).expect("same header");
        let error = std::iter::from_fn(|| rows.next_row().transpose().map(|r| r.map(<[i32]>::len)))
            .find_map(Result::err);
        assert!(
            matches!(error, Some(InputError::Changed { .. })),
            "{error:?}"
        );
    }
}
