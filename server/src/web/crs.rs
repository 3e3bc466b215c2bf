//! Coordinate reference systems of a georeferenced raster: placing its samples on the globe
//! as WGS84 longitude/latitude, and back.
//!
//! Supported CRS, given as `EPSG:<code>`:
//! - EPSG:4326, WGS84 longitude/latitude in degrees, `origin` and `sample_step` taken as
//!   `[longitude, latitude]`. EPSG:4269 (NAD83) and EPSG:4258 (ETRS89) are read as WGS84
//!   too: they differ from it by about a metre.
//! - EPSG:32601–32660 and EPSG:32701–32760, WGS84 UTM zones north and south.
//! - EPSG:26901–26923, NAD83 UTM zones 1–23 north, projected on the WGS84 datum: an
//!   approximation within 2 m.
//! - EPSG:3857, Web Mercator.
//!
//! Projections are computed by [`proj4rs`] (pure Rust, radians for geographic coordinates).
//! Longitudes are not wrapped into [-180, 180]: they run continuously across a raster, so
//! one that crosses the antimeridian has bounds with `east` above 180 (or `west` below
//! -180).

use std::f64::consts::PI;
use std::fmt;

use proj4rs::Proj;
use proj4rs::transform::transform;
use terrain_shared::manifest::Georeference;

/// The supported CRS, as error messages name them.
const SUPPORTED: &str = "EPSG:4326 (EPSG:4269 and EPSG:4258 read as WGS84), \
     EPSG:32601-32660 and EPSG:32701-32760 (WGS84 UTM), \
     EPSG:26901-26923 (NAD83 UTM, read as WGS84) and EPSG:3857 (Web Mercator)";

/// WGS84 longitude/latitude, the other end of every projection.
const WGS84_LONLAT: &str = "+proj=longlat +datum=WGS84 +no_defs";

/// Sphere radius of Web Mercator, metres.
const WEB_MERCATOR_RADIUS: f64 = 6_378_137.0;

/// Points sampled on each side of a projected raster's border by [`Placement::bounds`].
const BORDER_POINTS_PER_SIDE: u32 = 64;

/// How far a latitude may stray beyond a pole, in degrees, and still be read as the pole.
const POLE_TOLERANCE: f64 = 1e-9;

/// Why a georeference cannot be placed on the globe.
#[derive(Debug, thiserror::Error)]
pub enum CrsError {
    /// The raster has no georeference, or its georeference names no CRS.
    #[error("the raster has no georeference or its georeference names no CRS")]
    Missing,
    /// The CRS is not one this module can place on the globe.
    #[error("unsupported CRS `{crs}`: supported are {}", SUPPORTED)]
    Unsupported {
        /// The CRS as the georeference names it.
        crs: String,
    },
    /// The origin has a coordinate that is not finite.
    #[error("georeference origin {origin:?} is not finite")]
    BadOrigin {
        /// The origin as given.
        origin: [f64; 2],
    },
    /// The sample step has a component that is zero or not finite.
    #[error("georeference sample step {step:?} must be finite and non-zero in x and y")]
    BadStep {
        /// The sample step as given.
        step: [f64; 2],
    },
    /// A raster with no samples has no bounds.
    #[error("a raster of {width}x{height} samples has no bounds")]
    Empty {
        /// Samples across.
        width: u32,
        /// Samples down.
        height: u32,
    },
    /// A point could not be converted: outside the projection's domain, beyond a pole, or
    /// with a coordinate or result that is not finite.
    #[error("{0}")]
    Projection(String),
}

/// A raster placed on the globe: converts between sample coordinates (col, row: fractional,
/// (0,0) the centre of the north-west sample) and WGS84 longitude/latitude in degrees.
#[derive(Clone)]
pub struct Placement {
    /// The CRS, normalised to `EPSG:<code>`.
    crs: String,
    /// CRS coordinates of sample (0, 0).
    origin: [f64; 2],
    /// CRS units per sample, `[x, y]`.
    step: [f64; 2],
    /// How CRS coordinates relate to longitude/latitude.
    kind: Kind,
}

/// How a CRS relates to WGS84 longitude/latitude.
#[derive(Clone)]
enum Kind {
    /// CRS coordinates are longitude/latitude in degrees.
    Geographic,
    /// CRS coordinates are projected.
    Projected(Box<Projected>),
}

/// A projected CRS and its inverse.
#[derive(Clone)]
struct Projected {
    /// The proj string `proj` was built from.
    definition: String,
    /// The projection.
    proj: Proj,
    /// WGS84 longitude/latitude (radians).
    lonlat: Proj,
    /// Which of the longitudes 360° apart a point of the CRS has.
    wrap: LonWrap,
}

/// Which of the longitudes 360° apart a projected point has.
#[derive(Clone, Copy, Debug)]
enum LonWrap {
    /// The one nearest the projection's central meridian (degrees): a transverse Mercator
    /// never reaches 180° from it.
    Meridian(f64),
    /// Web Mercator: the one `x / radius` says, so that x beyond ±π·radius keeps going.
    Mercator,
}

impl fmt::Debug for Placement {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let definition = match &self.kind {
            Kind::Geographic => WGS84_LONLAT,
            Kind::Projected(p) => p.definition.as_str(),
        };
        f.debug_struct("Placement")
            .field("crs", &self.crs)
            .field("proj", &definition)
            .field("origin", &self.origin)
            .field("sample_step", &self.step)
            .finish()
    }
}

impl Placement {
    /// Places a raster by its georeference; see the module docs for the supported CRS.
    pub fn new(georeference: Option<&Georeference>) -> Result<Placement, CrsError> {
        let georeference = georeference.ok_or(CrsError::Missing)?;
        let given = georeference.crs.as_deref().map(str::trim).unwrap_or("");
        if given.is_empty() {
            return Err(CrsError::Missing);
        }
        let unsupported = || CrsError::Unsupported {
            crs: given.to_string(),
        };
        let code = epsg_code(given).ok_or_else(unsupported)?;
        let (zone, south) = match code {
            4326 | 4269 | 4258 => (None, false),
            3857 => (None, false),
            32601..=32660 => (Some(code - 32600), false),
            32701..=32760 => (Some(code - 32700), true),
            26901..=26923 => (Some(code - 26900), false),
            _ => return Err(unsupported()),
        };
        let origin = georeference.origin;
        if !origin.iter().all(|v| v.is_finite()) {
            return Err(CrsError::BadOrigin { origin });
        }
        let step = georeference.sample_step;
        if !step.iter().all(|v| v.is_finite() && *v != 0.0) {
            return Err(CrsError::BadStep { step });
        }
        let kind = match (code, zone) {
            (4326 | 4269 | 4258, _) => Kind::Geographic,
            (_, Some(zone)) => {
                let definition = format!(
                    "+proj=utm +zone={zone}{} +datum=WGS84 +units=m +no_defs",
                    if south { " +south" } else { "" }
                );
                let central_meridian = -183.0 + 6.0 * f64::from(zone);
                Kind::Projected(Box::new(Projected::new(
                    definition,
                    LonWrap::Meridian(central_meridian),
                )?))
            }
            _ => {
                let definition = format!(
                    "+proj=merc +a={WEB_MERCATOR_RADIUS} +b={WEB_MERCATOR_RADIUS} +lat_ts=0 \
                     +lon_0=0 +x_0=0 +y_0=0 +k=1 +units=m +no_defs"
                );
                Kind::Projected(Box::new(Projected::new(definition, LonWrap::Mercator)?))
            }
        };
        Ok(Placement {
            crs: format!("EPSG:{code}"),
            origin,
            step,
            kind,
        })
    }

    /// The CRS, as `EPSG:<code>`.
    pub fn crs(&self) -> &str {
        &self.crs
    }

    /// WGS84 longitude and latitude, degrees, of sample coordinates (col, row).
    pub fn to_lon_lat(&self, col: f64, row: f64) -> Result<(f64, f64), CrsError> {
        if !(col.is_finite() && row.is_finite()) {
            return Err(CrsError::Projection(format!(
                "sample ({col}, {row}) is not finite"
            )));
        }
        let x = self.origin[0] + col * self.step[0];
        let y = self.origin[1] + row * self.step[1];
        let (lon, lat) = match &self.kind {
            Kind::Geographic => (x, y),
            Kind::Projected(p) => {
                let mut point = (x, y, 0.0);
                transform(&p.proj, &p.lonlat, &mut point).map_err(|e| {
                    CrsError::Projection(format!(
                        "{} ({x}, {y}) to longitude/latitude: {e}",
                        self.crs
                    ))
                })?;
                let hint = match p.wrap {
                    LonWrap::Meridian(meridian) => meridian,
                    LonWrap::Mercator => (x / WEB_MERCATOR_RADIUS).to_degrees(),
                };
                (
                    unwrap_degrees(point.0.to_degrees(), hint),
                    point.1.to_degrees(),
                )
            }
        };
        if !(lon.is_finite() && lat.is_finite()) {
            return Err(CrsError::Projection(format!(
                "{} ({x}, {y}) gives no finite longitude/latitude",
                self.crs
            )));
        }
        if lat.abs() > 90.0 + POLE_TOLERANCE {
            return Err(CrsError::Projection(format!(
                "sample ({col}, {row}) of {} is at latitude {lat}, beyond a pole",
                self.crs
            )));
        }
        Ok((lon, lat.clamp(-90.0, 90.0)))
    }

    /// Sample coordinates (col, row) of a WGS84 longitude and latitude in degrees. For a
    /// geographic CRS the longitude is used as given, not wrapped.
    pub fn to_sample(&self, lon: f64, lat: f64) -> Result<(f64, f64), CrsError> {
        if !(lon.is_finite() && lat.is_finite()) {
            return Err(CrsError::Projection(format!(
                "longitude/latitude ({lon}, {lat}) is not finite"
            )));
        }
        if lat.abs() > 90.0 + POLE_TOLERANCE {
            return Err(CrsError::Projection(format!(
                "latitude {lat} is beyond a pole"
            )));
        }
        let lat = lat.clamp(-90.0, 90.0);
        let (x, y) = match &self.kind {
            Kind::Geographic => (lon, lat),
            Kind::Projected(p) => {
                // proj4rs rejects longitudes beyond ±10 radians: hand it the one in [-180, 180).
                let mut point = (unwrap_degrees(lon, 0.0).to_radians(), lat.to_radians(), 0.0);
                transform(&p.lonlat, &p.proj, &mut point).map_err(|e| {
                    CrsError::Projection(format!(
                        "longitude/latitude ({lon}, {lat}) to {}: {e}",
                        self.crs
                    ))
                })?;
                let mut x = point.0;
                if let LonWrap::Mercator = p.wrap {
                    // Keep x continuous with the longitude asked for, past ±180°.
                    let period = 2.0 * PI * WEB_MERCATOR_RADIUS;
                    let wanted = lon.to_radians() * WEB_MERCATOR_RADIUS;
                    x += ((wanted - x) / period).round() * period;
                }
                (x, point.1)
            }
        };
        let col = (x - self.origin[0]) / self.step[0];
        let row = (y - self.origin[1]) / self.step[1];
        if !(col.is_finite() && row.is_finite()) {
            return Err(CrsError::Projection(format!(
                "longitude/latitude ({lon}, {lat}) gives no finite {} coordinates",
                self.crs
            )));
        }
        Ok((col, row))
    }

    /// Longitude/latitude bounds [west, south, east, north] of the samples (0,0)..(width-1,height-1),
    /// for a projected CRS taken over the raster's whole border (64 points a side), not just
    /// its corners, and reaching a pole when the raster contains it.
    pub fn bounds(&self, width: u32, height: u32) -> Result<[f64; 4], CrsError> {
        if width == 0 || height == 0 {
            return Err(CrsError::Empty { width, height });
        }
        let (w, h) = (f64::from(width - 1), f64::from(height - 1));
        let mut bounds = [
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ];
        let mut add = |(lon, lat): (f64, f64)| {
            bounds[0] = bounds[0].min(lon);
            bounds[1] = bounds[1].min(lat);
            bounds[2] = bounds[2].max(lon);
            bounds[3] = bounds[3].max(lat);
        };
        match &self.kind {
            // Longitude and latitude are linear in the sample coordinates: the corners bound them.
            Kind::Geographic => {
                for (col, row) in [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)] {
                    add(self.to_lon_lat(col, row)?);
                }
            }
            Kind::Projected(p) => {
                let n = BORDER_POINTS_PER_SIDE;
                for i in 0..=n {
                    let t = f64::from(i) / f64::from(n);
                    for (col, row) in [(t * w, 0.0), (t * w, h), (0.0, t * h), (w, t * h)] {
                        add(self.to_lon_lat(col, row)?);
                    }
                }
                // A raster around a pole reaches it, and every longitude, inside its border.
                if let LonWrap::Meridian(meridian) = p.wrap {
                    for pole in [90.0, -90.0] {
                        let inside = self.to_sample(meridian, pole).is_ok_and(|(col, row)| {
                            (0.0..=w).contains(&col) && (0.0..=h).contains(&row)
                        });
                        if inside {
                            add((meridian - 180.0, pole));
                            add((meridian + 180.0, pole));
                        }
                    }
                }
            }
        }
        Ok(bounds)
    }
}

impl Projected {
    /// The projection `definition` describes, and WGS84 longitude/latitude.
    fn new(definition: String, wrap: LonWrap) -> Result<Projected, CrsError> {
        let parse = |s: &str| {
            Proj::from_proj_string(s)
                .map_err(|e| CrsError::Projection(format!("proj string `{s}`: {e}")))
        };
        Ok(Projected {
            proj: parse(&definition)?,
            lonlat: parse(WGS84_LONLAT)?,
            definition,
            wrap,
        })
    }
}

/// The EPSG code of `EPSG:<code>` (prefix in any case).
fn epsg_code(crs: &str) -> Option<u32> {
    let (authority, code) = crs.split_once(':')?;
    if !authority.trim().eq_ignore_ascii_case("EPSG") {
        return None;
    }
    let code = code.trim();
    if code.is_empty() || !code.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    code.parse().ok()
}

/// The longitude 360° apart from `lon` (or `lon` itself) nearest `hint`, all in degrees.
fn unwrap_degrees(lon: f64, hint: f64) -> f64 {
    hint + (lon - hint + 180.0).rem_euclid(360.0) - 180.0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn placement(crs: &str, origin: [f64; 2], step: [f64; 2]) -> Placement {
        Placement::new(Some(&Georeference {
            crs: Some(crs.to_string()),
            origin,
            sample_step: step,
        }))
        .expect("a valid case")
    }

    /// Independent reference: WGS84 UTM (easting, northing) of a point by Snyder's
    /// transverse Mercator series (USGS Professional Paper 1395, eqs. 3-21, 8-9, 8-10),
    /// good to centimetres within a few degrees of the central meridian.
    fn snyder_utm(lon: f64, lat: f64, zone: u32, south: bool) -> (f64, f64) {
        let a = 6_378_137.0_f64;
        let f = 1.0 / 298.257_223_563;
        let e2 = f * (2.0 - f);
        let (e4, e6) = (e2 * e2, e2 * e2 * e2);
        let ep2 = e2 / (1.0 - e2);
        let k0 = 0.9996;
        let phi = lat.to_radians();
        let lam0 = (-183.0 + 6.0 * f64::from(zone)).to_radians();
        let (sin, cos, tan) = (phi.sin(), phi.cos(), phi.tan());
        let n = a / (1.0 - e2 * sin * sin).sqrt();
        let t = tan * tan;
        let c = ep2 * cos * cos;
        let aa = (lon.to_radians() - lam0) * cos;
        let m = a
            * ((1.0 - e2 / 4.0 - 3.0 * e4 / 64.0 - 5.0 * e6 / 256.0) * phi
                - (3.0 * e2 / 8.0 + 3.0 * e4 / 32.0 + 45.0 * e6 / 1024.0) * (2.0 * phi).sin()
                + (15.0 * e4 / 256.0 + 45.0 * e6 / 1024.0) * (4.0 * phi).sin()
                - (35.0 * e6 / 3072.0) * (6.0 * phi).sin());
        let x = k0
            * n
            * (aa
                + (1.0 - t + c) * aa.powi(3) / 6.0
                + (5.0 - 18.0 * t + t * t + 72.0 * c - 58.0 * ep2) * aa.powi(5) / 120.0);
        let y = k0
            * (m + n
                * tan
                * (aa * aa / 2.0
                    + (5.0 - t + 9.0 * c + 4.0 * c * c) * aa.powi(4) / 24.0
                    + (61.0 - 58.0 * t + t * t + 600.0 * c - 330.0 * ep2) * aa.powi(6) / 720.0));
        (500_000.0 + x, if south { 10_000_000.0 + y } else { y })
    }

    /// CRS (easting, northing) of sample coordinates.
    fn crs_xy(p: &Placement, (col, row): (f64, f64)) -> (f64, f64) {
        (p.origin[0] + col * p.step[0], p.origin[1] + row * p.step[1])
    }

    #[test]
    fn geographic_round_trip() {
        let p = placement("EPSG:4326", [-122.5, 47.25], [0.001, -0.001]);
        assert_eq!(p.crs(), "EPSG:4326");
        let (lon, lat) = p.to_lon_lat(100.0, 250.0).expect("a valid case");
        assert!((lon - -122.4).abs() < 1e-12 && (lat - 47.0).abs() < 1e-12);
        for (col, row) in [(0.0, 0.0), (12.25, 7.5), (3999.0, 1999.0), (-3.5, 10.0)] {
            let (lon, lat) = p.to_lon_lat(col, row).expect("a valid case");
            let (c, r) = p.to_sample(lon, lat).expect("a valid case");
            assert!(
                (c - col).abs() < 1e-6 && (r - row).abs() < 1e-6,
                "{col},{row} -> {c},{r}"
            );
        }
    }

    #[test]
    fn geographic_bounds_are_corners() {
        let p = placement("EPSG:4326", [10.0, 50.0], [0.5, -0.25]);
        assert_eq!(
            p.bounds(21, 41).expect("a valid case"),
            [10.0, 40.0, 20.0, 50.0]
        );
        // Steps running east to west and south to north.
        let p = placement("epsg:4269", [20.0, 40.0], [-0.5, 0.25]);
        assert_eq!(p.crs(), "EPSG:4269");
        assert_eq!(
            p.bounds(21, 41).expect("a valid case"),
            [10.0, 40.0, 20.0, 50.0]
        );
        assert_eq!(
            p.bounds(1, 1).expect("a valid case"),
            [20.0, 40.0, 20.0, 40.0]
        );
        assert!(matches!(
            p.bounds(0, 5),
            Err(CrsError::Empty {
                width: 0,
                height: 5
            })
        ));
    }

    #[test]
    fn utm_north_known_point() {
        // Mount Rainier summit, zone 10N. Snyder's series agrees with a third reference,
        // Krüger's series (Karney 2011, to n³), computed outside this crate.
        let (lon, lat) = (-121.7604, 46.8529);
        let (e, n) = snyder_utm(lon, lat, 10, false);
        assert!(
            (e - 594_499.18).abs() < 0.05 && (n - 5_189_563.52).abs() < 0.05,
            "{e} {n}"
        );
        let p = placement("EPSG:32610", [500_000.0, 5_200_000.0], [10.0, -10.0]);
        let (x, y) = crs_xy(&p, p.to_sample(lon, lat).expect("a valid case"));
        assert!(
            (x - e).abs() < 1.0 && (y - n).abs() < 1.0,
            "{x} {y} vs {e} {n}"
        );
        let (col, row) = ((e - 500_000.0) / 10.0, (5_200_000.0 - n) / 10.0);
        let (lon2, lat2) = p.to_lon_lat(col, row).expect("a valid case");
        // 1 m is about 1e-5 degrees.
        assert!(
            (lon2 - lon).abs() < 2e-5 && (lat2 - lat).abs() < 1e-5,
            "{lon2} {lat2}"
        );
    }

    #[test]
    fn utm_round_trip() {
        let p = placement("EPSG:32610", [550_000.0, 5_250_000.0], [30.0, -30.0]);
        for (col, row) in [
            (0.0, 0.0),
            (0.5, 0.25),
            (1234.75, 987.125),
            (4095.0, 4095.0),
        ] {
            let (lon, lat) = p.to_lon_lat(col, row).expect("a valid case");
            let (c, r) = p.to_sample(lon, lat).expect("a valid case");
            assert!(
                (c - col).abs() < 1e-6 && (r - row).abs() < 1e-6,
                "{col},{row} -> {c},{r}"
            );
        }
    }

    #[test]
    fn utm_south_known_point_and_round_trip() {
        // Sydney Opera House, zone 56S.
        let (lon, lat) = (151.2153, -33.8568);
        let (e, n) = snyder_utm(lon, lat, 56, true);
        assert!(
            (e - 334_900.57).abs() < 0.05 && (n - 6_252_288.75).abs() < 0.05,
            "{e} {n}"
        );
        let p = placement("EPSG:32756", [300_000.0, 6_300_000.0], [5.0, -5.0]);
        let (x, y) = crs_xy(&p, p.to_sample(lon, lat).expect("a valid case"));
        assert!(
            (x - e).abs() < 1.0 && (y - n).abs() < 1.0,
            "{x} {y} vs {e} {n}"
        );
        for (col, row) in [(0.0, 0.0), (6960.5, 9628.25), (20_000.0, 100.0)] {
            let (lon, lat) = p.to_lon_lat(col, row).expect("a valid case");
            assert!(lat < 0.0);
            let (c, r) = p.to_sample(lon, lat).expect("a valid case");
            assert!(
                (c - col).abs() < 1e-6 && (r - row).abs() < 1e-6,
                "{col},{row} -> {c},{r}"
            );
        }
    }

    #[test]
    fn nad83_utm_reads_as_wgs84_utm() {
        let nad83 = placement("EPSG:26910", [500_000.0, 5_200_000.0], [10.0, -10.0]);
        let wgs84 = placement("EPSG:32610", [500_000.0, 5_200_000.0], [10.0, -10.0]);
        assert_eq!(nad83.crs(), "EPSG:26910");
        assert_eq!(
            nad83.to_lon_lat(9453.0, 1053.0).expect("a valid case"),
            wgs84.to_lon_lat(9453.0, 1053.0).expect("a valid case")
        );
    }

    #[test]
    fn web_mercator_known_values_and_round_trip() {
        let p = placement("EPSG:3857", [0.0, 0.0], [1.0, -1.0]);
        let (x, _) = crs_xy(&p, p.to_sample(180.0, 0.0).expect("a valid case"));
        assert!((x - 20_037_508.34).abs() < 0.01, "{x}");
        let (x, _) = crs_xy(&p, p.to_sample(-180.0, 0.0).expect("a valid case"));
        assert!((x + 20_037_508.34).abs() < 0.01, "{x}");
        // Spherical, no datum shift: y = R ln tan(π/4 + φ/2).
        let (_, y) = crs_xy(&p, p.to_sample(0.0, 45.0).expect("a valid case"));
        let expected = WEB_MERCATOR_RADIUS * (PI / 4.0 + 45f64.to_radians() / 2.0).tan().ln();
        assert!((y - expected).abs() < 1e-6, "{y} vs {expected}");
        let (lon, lat) = p
            .to_lon_lat(20_037_508.342_789_244, -20_037_508.342_789_244)
            .expect("a valid case");
        assert!((lon - 180.0).abs() < 1e-9 && (lat - 85.051_128_779_806_6).abs() < 1e-9);

        let p = placement("EPSG:3857", [-13_600_000.0, 6_000_000.0], [19.1, -19.1]);
        for (col, row) in [(0.0, 0.0), (100.5, 3.25), (5000.0, 8000.0)] {
            let (lon, lat) = p.to_lon_lat(col, row).expect("a valid case");
            let (c, r) = p.to_sample(lon, lat).expect("a valid case");
            assert!(
                (c - col).abs() < 1e-6 && (r - row).abs() < 1e-6,
                "{col},{row} -> {c},{r}"
            );
        }
        assert!(p.to_sample(0.0, 90.0).is_err());
    }

    #[test]
    fn projected_bounds_cover_the_whole_border() {
        // Zone 10N, eastings 400–600 km: the north edge bulges north at the central
        // meridian (easting 500 km), above both northern corners.
        let p = placement("EPSG:32610", [400_000.0, 5_300_000.0], [100.0, -100.0]);
        let [west, south, east, north] = p.bounds(2001, 2001).expect("a valid case");
        let corners = [(0.0, 0.0), (2000.0, 0.0), (0.0, 2000.0), (2000.0, 2000.0)]
            .map(|(c, r)| p.to_lon_lat(c, r).expect("a valid case"));
        let (_, mid_north) = p.to_lon_lat(1000.0, 0.0).expect("a valid case");
        let corner_north = corners.iter().map(|c| c.1).fold(f64::MIN, f64::max);
        assert!(mid_north > corner_north + 1e-3);
        assert!((north - mid_north).abs() < 1e-9, "{north} vs {mid_north}");
        for (lon, lat) in corners {
            assert!(west <= lon && lon <= east && south <= lat && lat <= north);
        }
    }

    #[test]
    fn bounds_across_the_antimeridian_and_around_a_pole() {
        // Zone 60N (central meridian 177°), eastings 400–900 km near the equator: past 180°.
        let p = placement("EPSG:32660", [400_000.0, 100_000.0], [1000.0, -1000.0]);
        let [west, _, east, _] = p.bounds(501, 101).expect("a valid case");
        assert!(
            west > 175.0 && west < 177.0 && east > 180.0 && east < 181.0,
            "{west} {east}"
        );
        // Zone 33N around the north pole (at northing 9,997,964.94).
        let p = placement("EPSG:32633", [400_000.0, 10_100_000.0], [1000.0, -1000.0]);
        let [west, _, east, north] = p.bounds(201, 201).expect("a valid case");
        assert_eq!((west, east, north), (15.0 - 180.0, 15.0 + 180.0, 90.0));
    }

    #[test]
    fn unsupported_and_missing_crs_are_errors() {
        let georeference = |crs: Option<&str>| Georeference {
            crs: crs.map(str::to_string),
            origin: [0.0, 0.0],
            sample_step: [1.0, -1.0],
        };
        for crs in [
            "EPSG:2193",
            "EPSG:32661",
            "EPSG:26924",
            "ESRI:102100",
            "EPSG:",
        ] {
            let err = Placement::new(Some(&georeference(Some(crs)))).expect_err("unsupported");
            assert!(
                matches!(&err, CrsError::Unsupported { crs: c } if c == crs),
                "{err:?}"
            );
            let message = err.to_string();
            assert!(
                message.contains(crs) && message.contains("EPSG:3857"),
                "{message}"
            );
        }
        assert!(matches!(Placement::new(None), Err(CrsError::Missing)));
        assert!(matches!(
            Placement::new(Some(&georeference(None))),
            Err(CrsError::Missing)
        ));
        assert!(matches!(
            Placement::new(Some(&georeference(Some(" ")))),
            Err(CrsError::Missing)
        ));
    }

    #[test]
    fn bad_georeferences_and_points_are_errors() {
        let new = |origin: [f64; 2], step: [f64; 2]| {
            Placement::new(Some(&Georeference {
                crs: Some("EPSG:32610".to_string()),
                origin,
                sample_step: step,
            }))
        };
        assert!(matches!(
            new([0.0, 0.0], [10.0, 0.0]),
            Err(CrsError::BadStep { .. })
        ));
        assert!(matches!(
            new([0.0, 0.0], [f64::NAN, -1.0]),
            Err(CrsError::BadStep { .. })
        ));
        assert!(matches!(
            new([f64::INFINITY, 0.0], [1.0, -1.0]),
            Err(CrsError::BadOrigin { .. })
        ));

        let p = placement("EPSG:32610", [500_000.0, 5_200_000.0], [10.0, -10.0]);
        assert!(p.to_lon_lat(f64::NAN, 0.0).is_err());
        assert!(p.to_sample(0.0, f64::INFINITY).is_err());
        assert!(p.to_sample(-121.0, 91.0).is_err());
        let g = placement("EPSG:4326", [0.0, 89.0], [1.0, -1.0]);
        assert!(g.to_lon_lat(0.0, -2.0).is_err());
        assert!(g.to_sample(0.0, -90.5).is_err());
    }
}
