//! Reading height rasters and their metadata: 16/8-bit grey PNG, GeoTIFF (int16, uint16,
//! float32, with no-data and geotransform), SRTM `.hgt`, and a `dataset.json` beside the
//! input. Everything is turned into integer height *codes* at the source's own precision,
//! so the database stays lossless.
//!
//! Two ways in, one set of rules:
//!
//! - *whole*: every reader works on bytes in memory ([`decode_heights`]); [`read_heights`]
//!   reads the file first. Any byte string gives a raster or an [`InputError`], never a
//!   panic, and never an allocation the input's size cannot justify (the fuzz targets in
//!   `fuzz/` hold it to that; their corpora are replayed by the end-to-end tests).
//! - *row by row* ([`rows`]): the builder's way, in memory bounded by a row whatever the
//!   file's size, for PNG, GeoTIFF and `.hgt`.
//!
//! Both turn samples into codes through [`samples`] (no-data, the float quantum, samples
//! out of range), so a file gives the same codes either way (tested).
//!
//! This module only reads; merging the metadata with command-line flags is `mod.rs`'s job.

pub mod rows;
mod samples;

pub use rows::{CodeRows, RowHeader, RowReader, Scan};
use samples::{FloatNodata, FloatRaster, FloatStats, IntNodata};
use serde::Deserialize;
use std::fmt;
use std::io::Cursor;
use std::path::{Path, PathBuf};
use terrain_shared::manifest::Georeference;
use thiserror::Error;

/// A height raster as read: codes, voids and whatever the file said about itself.
#[derive(Debug, Clone)]
pub struct Raster {
    pub width: u32,
    pub height: u32,
    /// Row-major, row 0 north. Values at voids are meaningless until filled.
    pub codes: Vec<i32>,
    /// `true` where the source had no data; empty when there is none.
    pub voids: Vec<bool>,
    /// Metres per code step and metres at code 0, as far as the file knows.
    pub quantum_m: f64,
    pub offset_m: f64,
    /// What the file says about its own position and spacing.
    pub georeference: Option<Georeference>,
    /// Sample spacing in metres when the file implies it (GeoTIFF, `.hgt`).
    pub spacing_m: Option<[f64; 2]>,
    /// The file's format, for messages.
    pub format: &'static str,
    /// Float samples no height code could hold that became voids ([`OutOfRange::Nodata`]).
    pub out_of_range_voids: usize,
}

impl Raster {
    pub fn void_count(&self) -> usize {
        self.voids.iter().filter(|&&v| v).count()
    }
}

/// Why an input could not be read.
#[derive(Debug, Error)]
pub enum InputError {
    #[error("cannot read {path}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path} is not a regular file ({what}): the builder reads DEM and texture files")]
    NotAFile { path: PathBuf, what: &'static str },
    #[error("{path} is not a readable image: {message}")]
    Image { path: PathBuf, message: String },
    #[error("{path} is a {found} image; heights must be 8- or 16-bit greyscale")]
    NotGrey { path: PathBuf, found: String },
    #[error("{path}: unsupported GeoTIFF: {message}")]
    Tiff { path: PathBuf, message: String },
    #[error(
        "{path}: {bytes} bytes is not an SRTM .hgt size (1201^2 or 3601^2 big-endian int16 samples)"
    )]
    HgtSize { path: PathBuf, bytes: u64 },
    #[error("{path}: cannot parse dataset description: {message}")]
    Dataset { path: PathBuf, message: String },
    #[error("{path}: raster is {width}x{height}; at least 2x2 samples are needed")]
    TooSmall {
        path: PathBuf,
        width: u32,
        height: u32,
    },
    #[error("{path}: every sample is no-data")]
    AllVoid { path: PathBuf },
    #[error(
        "{path}: {width}x{height} samples of {bytes_per_sample} bytes from a {file_bytes}-byte file: \
         more than its compression can hold ({max_ratio}:1 at most)"
    )]
    Bomb {
        path: PathBuf,
        width: u32,
        height: u32,
        bytes_per_sample: u64,
        file_bytes: usize,
        max_ratio: u64,
    },
    #[error(
        "{path}: {count} of {total} float samples lie outside ±{limit_m} m, all that \
         height codes hold at a quantum of {quantum_m} m: {samples}. If they mark no-data, give \
         --nodata VALUE, or --out-of-range nodata to take every such sample as no-data"
    )]
    OutOfRange {
        path: PathBuf,
        count: usize,
        total: usize,
        quantum_m: Metres,
        limit_m: Metres,
        /// The first few, in row-major order.
        samples: SampleList,
    },
    #[error(
        "{path}: a float quantum of {quantum_m} m holds heights within ±{limit_m} m, but the \
         samples span {min_m} .. {max_m} m: give --float-quantum {needed_m:.1e} or coarser"
    )]
    QuantumTooFine {
        path: PathBuf,
        quantum_m: Metres,
        limit_m: Metres,
        min_m: f64,
        max_m: f64,
        needed_m: f64,
    },
    #[error("float quantum {0} m is not a positive finite number")]
    BadQuantum(f64),
    #[error("{path} changed while it was read: its samples differ from those of the first reading")]
    Changed { path: PathBuf },
}

/// Float samples named in a message: `value at (x, y)`, and how many more there are.
#[derive(Debug, Clone, PartialEq)]
pub struct SampleList {
    pub first: Vec<(u32, u32, f64)>,
    pub more: usize,
}

impl fmt::Display for SampleList {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, &(x, y, value)) in self.first.iter().enumerate() {
            let sep = if i == 0 { "" } else { ", " };
            // A float32 sample reads as it was written (1e30, not 1.0000000150474662e30).
            let narrow = value as f32;
            if f64::from(narrow) == value {
                write!(f, "{sep}{narrow:e} at ({x}, {y})")?;
            } else {
                write!(f, "{sep}{value:e} at ({x}, {y})")?;
            }
        }
        if self.more > 0 {
            write!(f, " and {} more", self.more)?;
        }
        Ok(())
    }
}

/// Metres in a message: at least three decimals and four significant digits, trailing zeros
/// dropped; below a micrometre in scientific notation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Metres(pub f64);

impl fmt::Display for Metres {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let magnitude = self.0.abs();
        if magnitude != 0.0 && magnitude < 1e-6 {
            return write!(f, "{:e}", self.0);
        }
        let decimals = (3.0 - magnitude.log10().floor()).clamp(3.0, 9.0) as usize;
        let text = format!("{:.*}", decimals, self.0);
        f.write_str(text.trim_end_matches('0').trim_end_matches('.'))
    }
}

/// What the builder does with float samples that no height code can hold at the quantum:
/// values beyond `i32::MAX` quanta from zero, and infinities. (NaN is always no-data: it is
/// how GDAL and most tools mark it in float rasters.)
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum OutOfRange {
    /// Stop with an error that says how many there are and where.
    #[default]
    Refuse,
    /// Take them as no-data: they are filled from their neighbours like any void, and
    /// counted in a warning. For float rasters that mark no-data with -3.4e38 or 1e30
    /// without a tag saying so.
    Nodata,
}

/// The height formats the builder reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// 8- or 16-bit greyscale PNG (or any image the `image` crate recognises by content).
    Png,
    GeoTiff,
    /// SRTM `.hgt`: the file name gives the south-west corner.
    Hgt,
}

impl Format {
    /// By file extension: `.tif`/`.tiff`, `.hgt`, anything else is read as an image.
    pub fn of(path: &Path) -> Format {
        let ext = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        match ext.as_str() {
            "tif" | "tiff" => Format::GeoTiff,
            "hgt" => Format::Hgt,
            _ => Format::Png,
        }
    }
}

/// How heights are read, beyond what the file says.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReadOptions {
    /// Raster value meaning no data, overriding the file's own.
    pub nodata: Option<f64>,
    /// Precision kept for floating-point heights that are not whole numbers.
    pub float_quantum_m: f64,
    pub out_of_range: OutOfRange,
}

/// Largest ratio of decoded bytes to file bytes an image format can reach: deflate (PNG,
/// TIFF) tops out near 1032:1 and TIFF's LZW near 2730:1 (4096-byte strings from 12-bit
/// codes). A header that claims more than this asks for memory its data cannot fill.
pub const MAX_COMPRESSION_RATIO: u64 = 4096;
/// The no-data value of SRTM `.hgt` files.
const HGT_NODATA: IntNodata = IntNodata::Code(-32768);

/// Reads a height raster from a file, choosing the reader by file extension.
pub fn read_heights(path: &Path, options: &ReadOptions) -> Result<Raster, InputError> {
    let bytes = std::fs::read(path).map_err(|source| InputError::Io {
        path: path.into(),
        source,
    })?;
    decode_heights(&bytes, Format::of(path), path, options)
}

/// Reads a height raster from the bytes of a file. `path` names it in messages and, for
/// `.hgt`, gives the corner; nothing is read from it.
pub fn decode_heights(
    bytes: &[u8],
    format: Format,
    path: &Path,
    options: &ReadOptions,
) -> Result<Raster, InputError> {
    if !(options.float_quantum_m.is_finite() && options.float_quantum_m > 0.0) {
        return Err(InputError::BadQuantum(options.float_quantum_m));
    }
    let raster = match format {
        Format::GeoTiff => read_geotiff(bytes, path, options)?,
        Format::Hgt => read_hgt(bytes, path)?,
        Format::Png => read_png(bytes, path, options.nodata)?,
    };
    check_shape(path, raster.width, raster.height)?;
    if !raster.voids.is_empty() && raster.voids.iter().all(|&v| v) {
        return Err(InputError::AllVoid { path: path.into() });
    }
    Ok(raster)
}

/// Refuses a raster smaller than one cell.
fn check_shape(path: &Path, width: u32, height: u32) -> Result<(), InputError> {
    if width < 2 || height < 2 {
        return Err(InputError::TooSmall {
            path: path.into(),
            width,
            height,
        });
    }
    Ok(())
}

/// Refuses a header whose decoded size its file cannot hold (see [`MAX_COMPRESSION_RATIO`]).
fn check_decoded_size(
    path: &Path,
    (width, height): (u32, u32),
    bytes_per_sample: u64,
    file_bytes: usize,
) -> Result<(), InputError> {
    let decoded = u64::from(width) * u64::from(height) * bytes_per_sample;
    if decoded > (file_bytes as u64).saturating_mul(MAX_COMPRESSION_RATIO) {
        return Err(InputError::Bomb {
            path: path.into(),
            width,
            height,
            bytes_per_sample,
            file_bytes,
            max_ratio: MAX_COMPRESSION_RATIO,
        });
    }
    Ok(())
}

fn read_png(bytes: &[u8], path: &Path, nodata: Option<f64>) -> Result<Raster, InputError> {
    use image::ImageDecoder as _;
    let image_error = |e: image::ImageError| InputError::Image {
        path: path.into(),
        message: e.to_string(),
    };
    let decoder = image::ImageReader::new(Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|source| InputError::Io {
            path: path.into(),
            source,
        })?
        .into_decoder()
        .map_err(image_error)?;
    let pixel_bytes = u64::from(decoder.color_type().bytes_per_pixel());
    check_decoded_size(path, decoder.dimensions(), pixel_bytes, bytes.len())?;
    let image = image::DynamicImage::from_decoder(decoder).map_err(image_error)?;
    let (width, height) = (image.width(), image.height());
    let codes: Vec<i32> = match image {
        image::DynamicImage::ImageLuma16(img) => {
            img.into_raw().into_iter().map(i32::from).collect()
        }
        image::DynamicImage::ImageLuma8(img) => img.into_raw().into_iter().map(i32::from).collect(),
        other => {
            return Err(InputError::NotGrey {
                path: path.into(),
                found: format!("{:?}", other.color()),
            });
        }
    };
    let nodata = nodata.map_or(IntNodata::None, |v| IntNodata::Code(v as i64));
    let voids = voids_where(&codes, nodata);
    Ok(Raster {
        width,
        height,
        codes,
        voids,
        quantum_m: 1.0,
        offset_m: 0.0,
        georeference: None,
        spacing_m: None,
        format: "PNG",
        out_of_range_voids: 0,
    })
}

/// `true` where a sample is no-data; empty when none is.
fn voids_where(codes: &[i32], nodata: IntNodata) -> Vec<bool> {
    if codes.iter().any(|&c| nodata.is_void(c)) {
        codes.iter().map(|&c| nodata.is_void(c)).collect()
    } else {
        Vec::new()
    }
}

fn tiff_error(path: &Path, message: String) -> InputError {
    InputError::Tiff {
        path: path.into(),
        message,
    }
}

/// What a GeoTIFF says about itself before its samples.
#[derive(Debug, Clone)]
struct GeoTiffHeader {
    width: u32,
    height: u32,
    nodata: Option<f64>,
    georeference: Option<Georeference>,
    spacing_m: Option<[f64; 2]>,
}

/// Reads a GeoTIFF's size, no-data and georeference, refusing more than one sample per
/// pixel and a size the file cannot hold.
fn geotiff_header<R: std::io::Read + std::io::Seek>(
    decoder: &mut tiff::decoder::Decoder<R>,
    path: &Path,
    file_bytes: usize,
    options: &ReadOptions,
) -> Result<GeoTiffHeader, InputError> {
    use tiff::tags::Tag;
    let err = |e: tiff::TiffError| tiff_error(path, e.to_string());
    let (width, height) = decoder.dimensions().map_err(err)?;
    let colour = decoder.colortype().map_err(err)?;
    if colour.num_samples() != 1 {
        return Err(tiff_error(
            path,
            format!(
                "{} samples per pixel: multi-band images are not heights",
                colour.num_samples()
            ),
        ));
    }
    let sample_bytes = u64::from(colour.bit_depth()).div_ceil(8);
    check_decoded_size(path, (width, height), sample_bytes, file_bytes)?;
    let nodata = match options.nodata {
        Some(v) => Some(v),
        // A tag that says something but not a number is refused: taken as no tag, its
        // voids (-32768 in an int16 SRTM file) would be built as heights.
        None => match decoder
            .find_tag(Tag::GdalNodata)
            .ok()
            .flatten()
            .and_then(|v| v.into_string().ok())
        {
            None => None,
            Some(text) => {
                let value = text.trim_matches(char::from(0)).trim();
                if value.is_empty() {
                    None
                } else {
                    Some(value.parse::<f64>().map_err(|_| InputError::Tiff {
                        path: path.into(),
                        message: format!(
                            "its GDAL_NODATA tag {value:?} is not a number; give the no-data value with --nodata"
                        ),
                    })?)
                }
            }
        },
    };
    let scale = decoder
        .find_tag(Tag::ModelPixelScaleTag)
        .ok()
        .flatten()
        .and_then(|v| v.into_f64_vec().ok());
    let tie = decoder
        .find_tag(Tag::ModelTiepointTag)
        .ok()
        .flatten()
        .and_then(|v| v.into_f64_vec().ok());
    let keys = decoder
        .find_tag(Tag::GeoKeyDirectoryTag)
        .ok()
        .flatten()
        .and_then(|v| v.into_u16_vec().ok());
    let crs = keys.as_deref().and_then(epsg_from_geokeys);
    let pixel_is_point = keys.as_deref().and_then(|k| geokey(k, 1025)) == Some(2);
    let georeference = match (scale.as_deref(), tie.as_deref()) {
        (Some([sx, sy, ..]), Some([i, j, _, x, y, ..])) => {
            // Sample centres: PixelIsArea tie points name the corner of pixel (i, j).
            let half = if pixel_is_point { 0.0 } else { 0.5 };
            Some(Georeference {
                crs: crs.map(|c| format!("EPSG:{c}")),
                origin: [x + (half - i) * sx, y - (half - j) * sy],
                sample_step: [*sx, -*sy],
            })
        }
        _ => None,
    };
    let spacing_m = georeference
        .as_ref()
        .and_then(|g| spacing_from_georeference(g, height));
    Ok(GeoTiffHeader {
        width,
        height,
        nodata,
        georeference,
        spacing_m,
    })
}

fn read_geotiff(bytes: &[u8], path: &Path, options: &ReadOptions) -> Result<Raster, InputError> {
    use tiff::decoder::{Decoder, DecodingResult};
    let err = |e: tiff::TiffError| tiff_error(path, e.to_string());
    let mut decoder = Decoder::new(Cursor::new(bytes)).map_err(err)?;
    let header = geotiff_header(&mut decoder, path, bytes.len(), options)?;
    let (width, height) = (header.width, header.height);
    let image = decoder.read_image().map_err(err)?;

    let int_nodata = header.nodata.map_or(IntNodata::None, IntNodata::Value);
    let floats = FloatRaster {
        path,
        quantum_m: options.float_quantum_m,
        out_of_range: options.out_of_range,
    };
    let (codes, voids, quantum_m, out_of_range_voids) = match image {
        DecodingResult::I16(v) => ints(v.into_iter().map(i32::from), int_nodata),
        DecodingResult::U16(v) => ints(v.into_iter().map(i32::from), int_nodata),
        DecodingResult::U8(v) => ints(v.into_iter().map(i32::from), int_nodata),
        DecodingResult::F32(v) => {
            let values: Vec<f64> = v.into_iter().map(f64::from).collect();
            quantize(&values, width, FloatNodata::for_f32(header.nodata), &floats)?
        }
        DecodingResult::F64(v) => {
            quantize(&v, width, FloatNodata::for_f64(header.nodata), &floats)?
        }
        other => {
            return Err(tiff_error(
                path,
                format!(
                    "sample type {} (supported: int16, uint16, uint8, float32, float64)",
                    sample_type_name(&other)
                ),
            ));
        }
    };
    if codes.len() != width as usize * height as usize {
        return Err(tiff_error(
            path,
            format!(
                "{} samples for {width}x{height}: multi-band images are not heights",
                codes.len()
            ),
        ));
    }
    let voids = if voids.iter().any(|&v| v) {
        voids
    } else {
        Vec::new()
    };
    Ok(Raster {
        width,
        height,
        codes,
        voids,
        quantum_m,
        offset_m: 0.0,
        georeference: header.georeference,
        spacing_m: header.spacing_m,
        format: "GeoTIFF",
        out_of_range_voids,
    })
}

/// Codes, voids, the quantum used, and how many samples became voids for being out of range.
type Quantized = (Vec<i32>, Vec<bool>, f64, usize);

/// Integer samples: codes as they are, a 1 m quantum.
fn ints(values: impl Iterator<Item = i32>, nodata: IntNodata) -> Quantized {
    let codes: Vec<i32> = values.collect();
    let voids = codes.iter().map(|&c| nodata.is_void(c)).collect();
    (codes, voids, 1.0, 0)
}

/// Float samples (`width` a row), turned into codes by the rules of [`samples`]: a first
/// pass over all of them chooses the quantum, a second converts.
fn quantize(
    values: &[f64],
    width: u32,
    nodata: FloatNodata,
    raster: &FloatRaster<'_>,
) -> Result<Quantized, InputError> {
    let width = u64::from(width.max(1));
    let mut stats = FloatStats::new(raster.quantum_m);
    for (i, &v) in values.iter().enumerate() {
        let (x, y) = (i as u64 % width, i as u64 / width);
        stats.add(x as u32, y as u32, v, nodata.is_void(v));
    }
    let rule = stats.finish(raster)?;
    let mut codes = Vec::with_capacity(values.len());
    let mut voids = Vec::with_capacity(values.len());
    for &v in values {
        let code = (!nodata.is_void(v)).then(|| rule.code(v)).flatten();
        codes.push(code.unwrap_or(0));
        voids.push(code.is_none());
    }
    Ok((codes, voids, rule.quantum_m, rule.out_of_range))
}

fn sample_type_name(result: &tiff::decoder::DecodingResult) -> &'static str {
    use tiff::decoder::DecodingResult as D;
    match result {
        D::U32(_) => "uint32",
        D::U64(_) => "uint64",
        D::I8(_) => "int8",
        D::I32(_) => "int32",
        D::I64(_) => "int64",
        D::F16(_) => "float16",
        _ => "this one",
    }
}

/// The value of one GeoKey, from a GeoKeyDirectory (header of 4, then 4 shorts per key).
fn geokey(keys: &[u16], id: u16) -> Option<u16> {
    keys.get(4..)?
        .chunks_exact(4)
        .find(|k| k[0] == id && k[1] == 0)
        .map(|k| k[3])
}

fn epsg_from_geokeys(keys: &[u16]) -> Option<u16> {
    // ProjectedCSTypeGeoKey (3072) wins over GeographicTypeGeoKey (2048); 32767 = user-defined.
    [3072, 2048]
        .iter()
        .filter_map(|&id| geokey(keys, id))
        .find(|&c| c != 32767 && c != 0)
}

/// Metres between samples for a georeference: degrees converted at the raster's centre
/// latitude (WGS84 series expansions), anything else taken to be metres already.
pub fn spacing_from_georeference(g: &Georeference, rows: u32) -> Option<[f64; 2]> {
    let [sx, sy] = g.sample_step;
    let geographic = g
        .crs
        .as_deref()
        .is_some_and(|c| c == "EPSG:4326" || c == "EPSG:4269" || c == "EPSG:4258");
    if geographic {
        let lat = (g.origin[1] + sy * f64::from(rows.saturating_sub(1)) / 2.0).to_radians();
        Some([
            sx.abs() * metres_per_degree_lon(lat),
            sy.abs() * metres_per_degree_lat(lat),
        ])
    } else if g.crs.is_some() {
        Some([sx.abs(), sy.abs()])
    } else {
        None
    }
}

fn metres_per_degree_lat(lat: f64) -> f64 {
    111_132.92 - 559.82 * (2.0 * lat).cos() + 1.175 * (4.0 * lat).cos()
}

fn metres_per_degree_lon(lat: f64) -> f64 {
    111_412.84 * lat.cos() - 93.5 * (3.0 * lat).cos()
}

/// SRTM `.hgt`: big-endian int16, 1201^2 (3") or 3601^2 (1") samples, void -32768. The name
/// (e.g. `N46W122.hgt`) gives the south-west corner; row 0 is the north edge.
fn read_hgt(bytes: &[u8], path: &Path) -> Result<Raster, InputError> {
    let (side, georeference, spacing_m) = hgt_header(bytes.len() as u64, path)?;
    let codes: Vec<i32> = bytes
        .chunks_exact(2)
        .map(|b| i32::from(i16::from_be_bytes([b[0], b[1]])))
        .collect();
    let voids = voids_where(&codes, HGT_NODATA);
    Ok(Raster {
        width: side,
        height: side,
        codes,
        voids,
        quantum_m: 1.0,
        offset_m: 0.0,
        georeference,
        spacing_m,
        format: "SRTM .hgt",
        out_of_range_voids: 0,
    })
}

/// Side, georeference and spacing of an `.hgt` file of `bytes` bytes.
type HgtHeader = (u32, Option<Georeference>, Option<[f64; 2]>);

/// What an `.hgt` file's length and name say: its side, and from the name its georeference.
fn hgt_header(bytes: u64, path: &Path) -> Result<HgtHeader, InputError> {
    let side: u32 = match bytes {
        n if n == 2 * 1201 * 1201 => 1201,
        n if n == 2 * 3601 * 3601 => 3601,
        n => {
            return Err(InputError::HgtSize {
                path: path.into(),
                bytes: n,
            });
        }
    };
    let step = 1.0 / f64::from(side - 1);
    let georeference = hgt_corner(path).map(|(lat, lon)| Georeference {
        crs: Some("EPSG:4326".into()),
        origin: [lon, lat + 1.0],
        sample_step: [step, -step],
    });
    let spacing_m = georeference
        .as_ref()
        .and_then(|g| spacing_from_georeference(g, side));
    Ok((side, georeference, spacing_m))
}

/// South-west corner `(lat, lon)` from an SRTM file name such as `N46W122.hgt`.
fn hgt_corner(path: &Path) -> Option<(f64, f64)> {
    let name = path.file_stem()?.to_string_lossy().to_ascii_uppercase();
    let (ns, rest) = name.split_at_checked(1)?;
    let split = rest.find(['E', 'W'])?;
    let (lat, rest) = rest.split_at(split);
    let (ew, lon) = rest.split_at(1);
    let lat: f64 = lat.parse().ok()?;
    let lon: f64 = lon.get(..3)?.parse().ok()?;
    let lat = if ns == "S" {
        -lat
    } else if ns == "N" {
        lat
    } else {
        return None;
    };
    let lon = if ew == "W" { -lon } else { lon };
    Some((lat, lon))
}

/// The `dataset.json` that may sit beside an input (format of the bundled data kit).
/// Every field is optional: flags and the file's own metadata fill the gaps.
#[derive(Debug, Clone, Default, Deserialize)]
pub struct DatasetInfo {
    pub texture: Option<String>,
    pub spacing_m: Option<[f64; 2]>,
    pub spacing_m_at_center: Option<[f64; 2]>,
    pub spacing_deg: Option<[f64; 2]>,
    pub north_west_corner_deg: Option<[f64; 2]>,
    pub height_scale_m: Option<f64>,
    pub height_offset_m: Option<f64>,
    pub nodata: Option<f64>,
    pub crs: Option<String>,
    pub texture_registration: Option<String>,
}

impl DatasetInfo {
    /// Reads `dataset.json` from the directory of `heights`, if there is one.
    pub fn beside(heights: &Path) -> Result<Option<(PathBuf, DatasetInfo)>, InputError> {
        let path = heights
            .parent()
            .unwrap_or(Path::new("."))
            .join("dataset.json");
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read(&path).map_err(|source| InputError::Io {
            path: path.clone(),
            source,
        })?;
        let info = serde_json::from_slice(&text).map_err(|e| InputError::Dataset {
            path: path.clone(),
            message: e.to_string(),
        })?;
        Ok(Some((path, info)))
    }

    /// Sample spacing in metres, from the most direct field available.
    pub fn spacing(&self, rows: u32) -> Option<[f64; 2]> {
        if let Some(s) = self.spacing_m.or(self.spacing_m_at_center) {
            return Some(s);
        }
        let [dx, dy] = self.spacing_deg?;
        let [lon, lat] = self.north_west_corner_deg?;
        spacing_from_georeference(
            &Georeference {
                crs: Some("EPSG:4326".into()),
                origin: [lon, lat],
                sample_step: [dx, -dy],
            },
            rows,
        )
    }

    pub fn georeference(&self) -> Option<Georeference> {
        let [dx, dy] = self.spacing_deg?;
        let [lon, lat] = self.north_west_corner_deg?;
        Some(Georeference {
            crs: self.crs.clone(),
            origin: [lon, lat],
            sample_step: [dx, -dy],
        })
    }
}

/// Refuses an input that is not a regular file (after symbolic links): a device, a FIFO,
/// a socket or a directory.
pub fn check_regular_file(path: &Path) -> Result<(), InputError> {
    let meta = std::fs::metadata(path).map_err(|source| InputError::Io {
        path: path.into(),
        source,
    })?;
    if meta.is_file() {
        return Ok(());
    }
    let what = if meta.is_dir() {
        "a directory"
    } else {
        file_kind(&meta)
    };
    Err(InputError::NotAFile {
        path: path.into(),
        what,
    })
}

#[cfg(unix)]
fn file_kind(meta: &std::fs::Metadata) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    let t = meta.file_type();
    if t.is_char_device() {
        "a character device"
    } else if t.is_block_device() {
        "a block device"
    } else if t.is_fifo() {
        "a FIFO"
    } else if t.is_socket() {
        "a socket"
    } else {
        "not a file"
    }
}

#[cfg(not(unix))]
fn file_kind(_: &std::fs::Metadata) -> &'static str {
    "not a file"
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hgt_names_give_the_south_west_corner() {
        assert_eq!(hgt_corner(Path::new("N46W122.hgt")), Some((46.0, -122.0)));
        assert_eq!(hgt_corner(Path::new("/x/s10e005.HGT")), Some((-10.0, 5.0)));
        assert_eq!(hgt_corner(Path::new("rainier.hgt")), None);
    }

    #[test]
    fn degree_spacing_shrinks_east_west_with_latitude() {
        let at = |lat: f64| {
            spacing_from_georeference(
                &Georeference {
                    crs: Some("EPSG:4326".into()),
                    origin: [0.0, lat],
                    sample_step: [1.0 / 1200.0, -1.0 / 1200.0],
                },
                1,
            )
            .expect("geographic")
        };
        // 3 arc-seconds: about 92.6 m north-south everywhere, 74.3 m east-west at 36.6 N (jacksboro's dataset.json).
        let [ew, ns] = at(36.6);
        assert!(
            (ew - 74.3).abs() < 0.3 && (ns - 92.5).abs() < 0.3,
            "{ew} {ns}"
        );
        assert!(at(60.0)[0] < at(0.0)[0] / 1.9);
    }

    /// Quantizes a float raster 4 samples wide (NaN is no-data) from `t.tif`.
    fn quantize(
        values: &[f64],
        quantum_m: f64,
        out_of_range: OutOfRange,
    ) -> Result<Quantized, InputError> {
        let floats = FloatRaster {
            path: Path::new("t.tif"),
            quantum_m,
            out_of_range,
        };
        super::quantize(values, 4, FloatNodata::NanOnly, &floats)
    }

    /// Quantizes and checks codes, the voids' indices, the quantum and the out-of-range count.
    fn check(
        values: &[f64],
        quantum_m: f64,
        policy: OutOfRange,
        expect: (&[i32], &[usize], f64, usize),
    ) {
        let (codes, voids, q, outside) =
            quantize(values, quantum_m, policy).unwrap_or_else(|e| panic!("{values:?}: {e}"));
        let voids: Vec<usize> = (0..voids.len()).filter(|&i| voids[i]).collect();
        assert_eq!((&codes[..], &voids[..], q, outside), expect, "{values:?}");
    }

    /// Quantizes expecting an error and checks its message.
    fn check_refused(values: &[f64], quantum_m: f64, policy: OutOfRange, message: &str) {
        match quantize(values, quantum_m, policy) {
            Ok(q) => panic!("{values:?} at {quantum_m}: accepted as {q:?}"),
            Err(e) => assert_eq!(e.to_string(), message, "{values:?}"),
        }
    }

    #[test]
    fn whole_floats_stay_lossless_and_others_use_the_quantum() {
        use OutOfRange::Refuse;
        check(
            &[1.0, 2.0, f64::NAN, 4.0],
            0.01,
            Refuse,
            (&[1, 2, 0, 4], &[2], 1.0, 0),
        );
        check(&[1.25, 2.0], 0.01, Refuse, (&[125, 200], &[], 0.01, 0));
        // An infinity or a huge marker does not make whole-number data fractional.
        check(
            &[1.0, 2.0, f64::INFINITY],
            0.01,
            OutOfRange::Nodata,
            (&[1, 2, 0], &[2], 1.0, 1),
        );
        // The edges of what a code holds: i32::MAX quanta is stored, one more is not.
        let max = f64::from(i32::MAX);
        check(
            &[-max, max],
            1.0,
            Refuse,
            (&[-i32::MAX, i32::MAX], &[], 1.0, 0),
        );
        check(
            &[0.5, max * 0.01],
            0.01,
            Refuse,
            (&[50, i32::MAX], &[], 0.01, 0),
        );
    }

    #[test]
    fn floats_no_code_holds_are_refused_with_their_count_and_place() {
        use OutOfRange::Refuse;
        let f32_lowest = f64::from(f32::MIN);
        check_refused(
            &[16.5, 1e30, 20.0, 21.0, f64::NEG_INFINITY, f32_lowest, 1.0],
            0.01,
            Refuse,
            "t.tif: 3 of 7 float samples lie outside ±21474836.47 m, all that height codes hold \
             at a quantum of 0.01 m: 1e30 at (1, 0), -inf at (0, 1), -3.4028235e38 at \
             (1, 1). If they mark no-data, give --nodata VALUE, or --out-of-range nodata to take \
             every such sample as no-data",
        );
        // Whole numbers keep a 1 m quantum, whose range is larger; the list stops at five.
        let mut many = vec![f32_lowest; 9];
        many.push(100.0);
        check_refused(
            &many,
            0.01,
            Refuse,
            "t.tif: 9 of 10 float samples lie outside ±2147483647 m, all that height codes hold \
             at a quantum of 1 m: -3.4028235e38 at (0, 0), -3.4028235e38 at \
             (1, 0), -3.4028235e38 at (2, 0), -3.4028235e38 at (3, 0), \
             -3.4028235e38 at (0, 1) and 4 more. If they mark no-data, give --nodata \
             VALUE, or --out-of-range nodata to take every such sample as no-data",
        );
    }

    #[test]
    fn out_of_range_floats_become_voids_when_asked() {
        check(
            &[
                16.5,
                1e30,
                20.0,
                f64::NAN,
                f64::NEG_INFINITY,
                f64::from(f32::MIN),
            ],
            0.01,
            OutOfRange::Nodata,
            (&[1650, 0, 2000, 0, 0, 0], &[1, 3, 4, 5], 0.01, 3),
        );
    }

    #[test]
    fn a_quantum_too_fine_for_the_heights_is_refused_whatever_the_policy() {
        for policy in [OutOfRange::Refuse, OutOfRange::Nodata] {
            check_refused(
                &[16.25, 180.0, 1e30, 17.0],
                1e-12,
                policy,
                "t.tif: a float quantum of 1e-12 m holds heights within ±0.002147 m, but the samples span 16.25 .. 180 m: give --float-quantum \
                 8.4e-8 or coarser",
            );
        }
        // The suggested quantum holds them.
        check(
            &[16.25, -180.0],
            8.4e-8,
            OutOfRange::Refuse,
            (&[193452381, -2142857143], &[], 8.4e-8, 0),
        );
    }
}
