//! The two tilings the web's clients use: XYZ Web Mercator (MapLibre, PMTiles) and the
//! geographic tiling scheme of quantized-mesh (Cesium: level 0 is two tiles of 180
//! degrees, rows counted from the south as in TMS).

use std::f64::consts::PI;

/// WGS84 semi-major axis, metres: Web Mercator's sphere and the ground size of a degree of
/// longitude at the equator.
pub const EARTH_RADIUS_M: f64 = 6_378_137.0;
/// Web Mercator stops here (the square world): `atan(sinh(pi))`.
pub const MAX_MERCATOR_LAT: f64 = 85.051_128_779_806_59;
/// Samples per side of a quantized-mesh tile's grid (Cesium assumes 65 when it derives
/// its level errors).
pub const MESH_GRID: u32 = 65;

/// One tile of a tiling: zoom (or level), column, row.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TileXyz {
    pub z: u32,
    pub x: u32,
    pub y: u32,
}

/// Web Mercator: `(lon, lat)` degrees to fractional world pixels at `zoom` for tiles of
/// `size` pixels (x east, y south, pixel `(i, j)` spans `[i, i + 1]`).
pub fn mercator_pixel(lon: f64, lat: f64, zoom: u32, size: u32) -> (f64, f64) {
    let world = f64::from(size) * f64::from(1u32 << zoom.min(30));
    let lat = lat.clamp(-MAX_MERCATOR_LAT, MAX_MERCATOR_LAT).to_radians();
    let x = (lon + 180.0) / 360.0 * world;
    let y = (1.0 - (lat.tan() + 1.0 / lat.cos()).ln() / PI) / 2.0 * world;
    (x, y)
}

/// The inverse of [`mercator_pixel`]: world pixel coordinates to `(lon, lat)` degrees.
pub fn mercator_lon_lat(px: f64, py: f64, zoom: u32, size: u32) -> (f64, f64) {
    let world = f64::from(size) * f64::from(1u32 << zoom.min(30));
    let lon = px / world * 360.0 - 180.0;
    let n = PI * (1.0 - 2.0 * py / world);
    let lat = n.sinh().atan().to_degrees();
    (lon, lat)
}

/// The XYZ tiles of `zoom` that overlap `bounds` (`[west, south, east, north]`, degrees).
pub fn mercator_tiles(bounds: [f64; 4], zoom: u32, size: u32) -> Vec<TileXyz> {
    let [west, south, east, north] = bounds;
    let last = (1u32 << zoom) - 1;
    let tile = |p: f64| ((p / f64::from(size)).floor().max(0.0) as u32).min(last);
    let (x0, y0) = mercator_pixel(west, north, zoom, size);
    let (x1, y1) = mercator_pixel(east, south, zoom, size);
    let mut out = Vec::new();
    for y in tile(y0)..=tile(y1) {
        for x in tile(x0)..=tile(x1) {
            out.push(TileXyz { z: zoom, x, y });
        }
    }
    out
}

/// Ground metres of one Web Mercator pixel at `lat` and `zoom`.
pub fn mercator_pixel_m(lat: f64, zoom: u32, size: u32) -> f64 {
    2.0 * PI * EARTH_RADIUS_M * lat.to_radians().cos() / (f64::from(size) * f64::from(1u32 << zoom))
}

/// The finest zoom whose pixels at `lat` are no finer than `sample_m` (never below 0, at
/// most 24).
pub fn mercator_max_zoom(lat: f64, sample_m: f64, size: u32) -> u32 {
    (0..24u32)
        .take_while(|&z| mercator_pixel_m(lat, z + 1, size) >= sample_m * (1.0 - 1e-9))
        .last()
        .map_or(0, |z| z + 1)
}

/// Degrees per side of a geographic tile of `level`.
pub fn geographic_tile_deg(level: u32) -> f64 {
    180.0 / f64::from(1u32 << level)
}

/// The rectangle `[west, south, east, north]` of geographic tile `t` (TMS rows).
pub fn geographic_rect(t: TileXyz) -> [f64; 4] {
    let d = geographic_tile_deg(t.z);
    let west = -180.0 + f64::from(t.x) * d;
    let south = -90.0 + f64::from(t.y) * d;
    [west, south, west + d, south + d]
}

/// The range `(x0, x1, y0, y1)`, inclusive, of the geographic tiles of `level` that
/// overlap `bounds`; every tile at level 0 (Cesium asks for both).
pub fn geographic_range(bounds: [f64; 4], level: u32) -> (u32, u32, u32, u32) {
    let d = geographic_tile_deg(level);
    let columns = 2u32 << level;
    let rows = 1u32 << level;
    let [west, south, east, north] = bounds;
    let index = |v: f64, origin: f64, count: u32| {
        (((v - origin) / d).floor().max(0.0) as u32).min(count - 1)
    };
    if level == 0 {
        (0, 1, 0, 0)
    } else {
        (
            index(west, -180.0, columns),
            index(east, -180.0, columns),
            index(south, -90.0, rows),
            index(north, -90.0, rows),
        )
    }
}

/// The geographic tiles of `level` that overlap `bounds` ([`geographic_range`]).
pub fn geographic_tiles(bounds: [f64; 4], level: u32) -> Vec<TileXyz> {
    let (x0, x1, y0, y1) = geographic_range(bounds, level);
    let mut out = Vec::new();
    for y in y0..=y1 {
        for x in x0..=x1 {
            out.push(TileXyz { z: level, x, y });
        }
    }
    out
}

/// Ground metres between two samples of a quantized-mesh tile's grid at `level`, east-west
/// at `lat` (the shorter way away from the equator).
pub fn geographic_step_m(lat: f64, level: u32) -> f64 {
    (geographic_tile_deg(level) / f64::from(MESH_GRID - 1)).to_radians()
        * EARTH_RADIUS_M
        * lat.to_radians().cos()
}

/// The finest level whose grid steps at `lat` are no finer than `sample_m` (at most 24),
/// as for the XYZ zooms: nothing is resampled finer than level 0.
pub fn geographic_max_level(lat: f64, sample_m: f64) -> u32 {
    (0..24u32)
        .take_while(|&z| geographic_step_m(lat, z + 1) >= sample_m * (1.0 - 1e-9))
        .last()
        .map_or(0, |z| z + 1)
}

/// Cesium's largest geometric error for a level of the geographic scheme, metres
/// (`TerrainProvider.getEstimatedLevelZeroGeometricErrorForAHeightmap` with a 65-sample
/// grid and two level-0 tiles, halved per level): the error its level selection assumes
/// each tile's mesh keeps within.
pub fn cesium_level_error_m(level: u32) -> f64 {
    EARTH_RADIUS_M * 2.0 * PI * 0.25 / (f64::from(MESH_GRID) * 2.0) / f64::from(1u32 << level)
}

/// The coarsest level of a pyramid whose samples, `sample_m` apart at level 0 and twice
/// as far each level up, are no farther apart than `pixel_m`: the nearest finer level.
pub fn nearest_finer_level(pixel_m: f64, sample_m: f64, coarsest: u32) -> u32 {
    let mut level = 0;
    while level < coarsest && sample_m * f64::from(2u32 << level) <= pixel_m * (1.0 + 1e-9) {
        level += 1;
    }
    level
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mercator_pixels_invert() {
        for &(lon, lat) in &[(0.0, 0.0), (-84.4, 36.7), (139.0, -35.2), (179.9, 80.0)] {
            let (x, y) = mercator_pixel(lon, lat, 11, 256);
            let (lon2, lat2) = mercator_lon_lat(x, y, 11, 256);
            assert!(
                (lon - lon2).abs() < 1e-9 && (lat - lat2).abs() < 1e-9,
                "{lon},{lat}"
            );
        }
        // The world's corners and centre.
        assert_eq!(mercator_pixel(-180.0, MAX_MERCATOR_LAT, 0, 256).0, 0.0);
        let (x, y) = mercator_pixel(0.0, 0.0, 1, 256);
        assert!((x - 256.0).abs() < 1e-9 && (y - 256.0).abs() < 1e-9);
    }

    #[test]
    fn tiles_cover_the_bounds_and_no_more() {
        // Jacksboro: a third of a degree at 36.6 N.
        let bounds = [-84.41375, 36.4466, -84.0779, 36.73292];
        let tiles = mercator_tiles(bounds, 10, 256);
        for t in &tiles {
            let (w, n) = mercator_lon_lat(f64::from(t.x * 256), f64::from(t.y * 256), 10, 256);
            let (e, s) = mercator_lon_lat(
                f64::from((t.x + 1) * 256),
                f64::from((t.y + 1) * 256),
                10,
                256,
            );
            assert!(
                w < bounds[2] && e > bounds[0] && s < bounds[3] && n > bounds[1],
                "{t:?}"
            );
        }
        assert!(!tiles.is_empty() && tiles.len() <= 4, "{tiles:?}");
        assert_eq!(
            mercator_tiles(bounds, 0, 256),
            vec![TileXyz { z: 0, x: 0, y: 0 }]
        );
        assert_eq!(geographic_tiles(bounds, 0).len(), 2);
        for t in geographic_tiles(bounds, 12) {
            let [w, s, e, n] = geographic_rect(t);
            assert!(
                w < bounds[2] && e > bounds[0] && s < bounds[3] && n > bounds[1],
                "{t:?}"
            );
        }
    }

    #[test]
    fn the_finest_zoom_is_the_last_no_finer_than_the_samples() {
        let lat = 36.6;
        let z = mercator_max_zoom(lat, 74.3, 256);
        assert!(mercator_pixel_m(lat, z, 256) >= 74.3);
        assert!(mercator_pixel_m(lat, z + 1, 256) < 74.3);
        let l = geographic_max_level(lat, 74.3);
        assert!(geographic_step_m(lat, l) >= 74.3 && geographic_step_m(lat, l + 1) < 74.3);
        assert_eq!((z, l), (10, 11));
    }

    #[test]
    fn the_nearest_finer_level_is_no_coarser_than_the_pixel() {
        assert_eq!(nearest_finer_level(50.0, 74.3, 5), 0);
        assert_eq!(nearest_finer_level(148.6, 74.3, 5), 1);
        assert_eq!(nearest_finer_level(148.5, 74.3, 5), 0);
        assert_eq!(nearest_finer_level(1e9, 74.3, 5), 5);
        // Cesium's level-0 error for two 65-sample tiles.
        assert!((cesium_level_error_m(0) - 77_067.34).abs() < 0.1);
    }
}
