//! Reading height rasters and their metadata: 16/8-bit grey PNG, GeoTIFF (int16, uint16,
//! float32, with no-data and geotransform), SRTM `.hgt`, and a `dataset.json` beside the
//! input. Everything is turned into integer height *codes* at the source's own precision,
//! so the database stays lossless.
//!
//! This module only reads; merging the metadata with command-line flags is `mod.rs`'s job.

use serde::Deserialize;
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
}

impl Raster {
    pub fn void_count(&self) -> usize {
        self.voids.iter().filter(|&&v| v).count()
    }
}

/// Why an input could not be read.
#[derive(Debug, Error)]
pub enum InputError {
    #[error("cannot read {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
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
}

/// Reads a height raster, choosing the reader by file extension (then by content for PNG).
/// `float_quantum_m` is the precision kept for floating-point heights that are not whole numbers.
pub fn read_heights(
    path: &Path,
    nodata: Option<f64>,
    float_quantum_m: f64,
) -> Result<Raster, InputError> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let raster = match ext.as_str() {
        "tif" | "tiff" => read_geotiff(path, nodata, float_quantum_m)?,
        "hgt" => read_hgt(path)?,
        _ => read_png(path, nodata)?,
    };
    if raster.width < 2 || raster.height < 2 {
        return Err(InputError::TooSmall {
            path: path.into(),
            width: raster.width,
            height: raster.height,
        });
    }
    if !raster.voids.is_empty() && raster.voids.iter().all(|&v| v) {
        return Err(InputError::AllVoid { path: path.into() });
    }
    Ok(raster)
}

fn read_png(path: &Path, nodata: Option<f64>) -> Result<Raster, InputError> {
    let image = image::ImageReader::open(path)
        .map_err(|source| InputError::Io {
            path: path.into(),
            source,
        })?
        .with_guessed_format()
        .map_err(|source| InputError::Io {
            path: path.into(),
            source,
        })?
        .decode()
        .map_err(|e| InputError::Image {
            path: path.into(),
            message: e.to_string(),
        })?;
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
    let voids = voids_where(&codes, nodata.map(|v| v as i64));
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
    })
}

fn voids_where(codes: &[i32], nodata: Option<i64>) -> Vec<bool> {
    match nodata {
        Some(v) if codes.iter().any(|&c| i64::from(c) == v) => {
            codes.iter().map(|&c| i64::from(c) == v).collect()
        }
        _ => Vec::new(),
    }
}

fn read_geotiff(
    path: &Path,
    nodata_flag: Option<f64>,
    float_quantum_m: f64,
) -> Result<Raster, InputError> {
    use tiff::decoder::{Decoder, DecodingResult};
    use tiff::tags::Tag;
    let err = |message: String| InputError::Tiff {
        path: path.into(),
        message,
    };
    let file = std::fs::File::open(path).map_err(|source| InputError::Io {
        path: path.into(),
        source,
    })?;
    let mut decoder =
        Decoder::new(std::io::BufReader::new(file)).map_err(|e| err(e.to_string()))?;
    let (width, height) = decoder.dimensions().map_err(|e| err(e.to_string()))?;
    let nodata = match nodata_flag {
        Some(v) => Some(v),
        None => decoder
            .find_tag(Tag::GdalNodata)
            .ok()
            .flatten()
            .and_then(|v| v.into_string().ok())
            .and_then(|s| s.trim_matches(char::from(0)).trim().parse::<f64>().ok()),
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
    let image = decoder.read_image().map_err(|e| err(e.to_string()))?;

    let is_void_f = |v: f64| !v.is_finite() || nodata.is_some_and(|n| v == n);
    let (codes, voids, quantum_m): (Vec<i32>, Vec<bool>, f64) = match image {
        DecodingResult::I16(v) => {
            let voids = v.iter().map(|&c| is_void_f(f64::from(c))).collect();
            (v.into_iter().map(i32::from).collect(), voids, 1.0)
        }
        DecodingResult::U16(v) => {
            let voids = v.iter().map(|&c| is_void_f(f64::from(c))).collect();
            (v.into_iter().map(i32::from).collect(), voids, 1.0)
        }
        DecodingResult::U8(v) => {
            let voids = v.iter().map(|&c| is_void_f(f64::from(c))).collect();
            (v.into_iter().map(i32::from).collect(), voids, 1.0)
        }
        DecodingResult::F32(v) => {
            quantize_floats(v.into_iter().map(f64::from), &is_void_f, float_quantum_m)
        }
        DecodingResult::F64(v) => quantize_floats(v.into_iter(), &is_void_f, float_quantum_m),
        other => {
            return Err(err(format!(
                "sample type {} (supported: int16, uint16, uint8, float32, float64)",
                sample_type_name(&other)
            )));
        }
    };
    if codes.len() != width as usize * height as usize {
        return Err(err(format!(
            "{} samples for {width}x{height}: multi-band images are not heights",
            codes.len()
        )));
    }
    let voids = if voids.iter().any(|&v| v) {
        voids
    } else {
        Vec::new()
    };

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
    Ok(Raster {
        width,
        height,
        codes,
        voids,
        quantum_m,
        offset_m: 0.0,
        georeference,
        spacing_m,
        format: "GeoTIFF",
    })
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

/// Floating-point heights: whole numbers keep a 1 m quantum (lossless); anything else is
/// rounded to `quantum_m`, which the manifest then records.
fn quantize_floats(
    values: impl Iterator<Item = f64>,
    is_void: &dyn Fn(f64) -> bool,
    quantum_m: f64,
) -> (Vec<i32>, Vec<bool>, f64) {
    let values: Vec<f64> = values.collect();
    let voids: Vec<bool> = values.iter().map(|&v| is_void(v)).collect();
    let whole = values
        .iter()
        .zip(&voids)
        .all(|(v, &void)| void || v.fract() == 0.0);
    let q = if whole { 1.0 } else { quantum_m };
    let codes = values
        .iter()
        .zip(&voids)
        .map(|(&v, &void)| {
            if void {
                0
            } else {
                (v / q)
                    .round()
                    .clamp(f64::from(i32::MIN), f64::from(i32::MAX)) as i32
            }
        })
        .collect();
    (codes, voids, q)
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
fn read_hgt(path: &Path) -> Result<Raster, InputError> {
    let bytes = std::fs::read(path).map_err(|source| InputError::Io {
        path: path.into(),
        source,
    })?;
    let side: u32 = match bytes.len() {
        n if n == 2 * 1201 * 1201 => 1201,
        n if n == 2 * 3601 * 3601 => 3601,
        n => {
            return Err(InputError::HgtSize {
                path: path.into(),
                bytes: n as u64,
            });
        }
    };
    let codes: Vec<i32> = bytes
        .chunks_exact(2)
        .map(|b| i32::from(i16::from_be_bytes([b[0], b[1]])))
        .collect();
    let voids = voids_where(&codes, Some(-32768));
    let step = 1.0 / f64::from(side - 1);
    let georeference = hgt_corner(path).map(|(lat, lon)| Georeference {
        crs: Some("EPSG:4326".into()),
        origin: [lon, lat + 1.0],
        sample_step: [step, -step],
    });
    let spacing_m = georeference
        .as_ref()
        .and_then(|g| spacing_from_georeference(g, side));
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
    })
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

    #[test]
    fn whole_floats_stay_lossless_and_others_use_the_quantum() {
        let (codes, _, q) =
            quantize_floats([1.0, 2.0, f64::NAN].into_iter(), &|v: f64| v.is_nan(), 0.01);
        assert_eq!((codes, q), (vec![1, 2, 0], 1.0));
        let (codes, _, q) = quantize_floats([1.25, 2.0].into_iter(), &|_| false, 0.01);
        assert_eq!((codes, q), (vec![125, 200], 0.01));
    }
}
