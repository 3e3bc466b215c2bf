//! quantized-mesh-1.0 terrain tiles for CesiumJS, with the `octvertexnormals` extension.
//!
//! Format: <https://github.com/CesiumGS/quantized-mesh>, checked against CesiumJS's reader
//! (`CesiumTerrainProvider.js`, `createQuantizedMeshTerrainData`). Tiles are on the
//! geographic tiling scheme (EPSG:4326): level 0 is 2 x 1 tiles of 180 degrees, TMS rows
//! counted from the south. A tile is laid out as follows, all little-endian:
//!
//! 1. header, 88 bytes: centre (ECEF, 3 x f64), minimum and maximum height (2 x f32),
//!    bounding sphere (centre 3 x f64, radius f64), horizon occlusion point (ellipsoid-scaled
//!    ECEF, 3 x f64);
//! 2. `vertexCount` (u32), then the u, v and height arrays, `vertexCount` u16 each, each
//!    zig-zag delta encoded;
//! 3. padding to the index width, `triangleCount` (u32) and the triangle indices, "high water
//!    mark" encoded: u16 indices, or u32 when `vertexCount > 65536`;
//! 4. the west, south, east and north edge vertices, each a u32 count then plain indices of
//!    the same width;
//! 5. extensions, each an id (u8), a length (u32) and that many bytes: here only
//!    `octvertexnormals` (id 1), two bytes per vertex.
//!
//! Gzip, when served, is the caller's.

use terrain_shared::mask;
use thiserror::Error;

/// WGS84 semi-major axis, metres.
pub const WGS84_A: f64 = 6_378_137.0;
/// WGS84 semi-minor axis, metres.
pub const WGS84_B: f64 = 6_356_752.314_245_179;
/// Largest quantized u, v and height: the east and north edges, and the maximum height.
pub const QUANTIZED_MAX: u16 = 32767;
/// Extension id of `octvertexnormals`.
pub const OCT_VERTEX_NORMALS: u8 = 1;

/// Bytes of the fixed header.
const HEADER_LEN: usize = 88;
/// Above this many vertices indices are 32-bit (the spec's and CesiumJS's `> 64 * 1024`).
const MAX_VERTICES_16_BIT: usize = 65536;
/// Magnitude (scaled space) of the horizon occlusion point of a tile for which no finite
/// point exists (one spanning a hemisphere, as at level 0): far along the direction to the
/// tile, where it stands for the point at infinity that would be exact.
const FALLBACK_OCCLUSION_MAGNITUDE: f64 = 1.0e6;

/// A tile's rectangle, degrees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeoRect {
    /// Western longitude.
    pub west: f64,
    /// Southern latitude.
    pub south: f64,
    /// Eastern longitude.
    pub east: f64,
    /// Northern latitude.
    pub north: f64,
}

impl GeoRect {
    /// Rectangle of tile `(level, x, y)` of the geographic tiling scheme: `2^(level+1)`
    /// columns from -180 eastward and `2^level` rows from -90 northward (TMS `y`).
    pub fn tile(level: u32, x: u32, y: u32) -> GeoRect {
        let size = 180.0 / 2f64.powi(level as i32);
        GeoRect {
            west: -180.0 + f64::from(x) * size,
            south: -90.0 + f64::from(y) * size,
            east: -180.0 + (f64::from(x) + 1.0) * size,
            north: -90.0 + (f64::from(y) + 1.0) * size,
        }
    }

    /// Longitude of quantized `u` (0 west, [`QUANTIZED_MAX`] east), as CesiumJS places it.
    pub fn lon_of(&self, u: u16) -> f64 {
        self.west + (self.east - self.west) * (f64::from(u) / f64::from(QUANTIZED_MAX))
    }

    /// Latitude of quantized `v` (0 south, [`QUANTIZED_MAX`] north), as CesiumJS places it.
    pub fn lat_of(&self, v: u16) -> f64 {
        self.south + (self.north - self.south) * (f64::from(v) / f64::from(QUANTIZED_MAX))
    }
}

/// A mesh over one tile: vertex positions as quantized u (west→east) and v (south→north)
/// in 0..=32767 and heights in metres above the WGS84 ellipsoid; triangles counter-clockwise
/// seen from above.
#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    /// Quantized longitude of each vertex, 0 (west edge) ..= 32767 (east edge).
    pub u: Vec<u16>,
    /// Quantized latitude of each vertex, 0 (south edge) ..= 32767 (north edge).
    pub v: Vec<u16>,
    /// Height of each vertex, metres above the WGS84 ellipsoid.
    pub height_m: Vec<f64>,
    /// Vertex indices of each triangle, counter-clockwise seen from above.
    pub triangles: Vec<[u32; 3]>,
}

/// Quantized position of sample `i` of `last + 1` along a side, 0..=32767.
fn quantize_index(i: u32, last: u32) -> u16 {
    let (i, last) = (u64::from(i), u64::from(last));
    ((i * 2 * u64::from(QUANTIZED_MAX) + last) / (2 * last)) as u16
}

/// The mesh of a regular grid of `side x side` heights (row 0 north, column 0 west,
/// `side = 2^k + 1`), keeping only the samples of strip-mask level `level`
/// (`terrain_shared::mask::kept_indices(side, level)`, same diagonal convention as
/// `terrain_shared::mask`: each kept cell between rows r0<r1 and columns c0<c1 splits along
/// the diagonal from (c0, r1) to (c1, r0)). Only kept samples become vertices.
///
/// Vertices are numbered in the order the triangles first use them, so [`encode`] keeps
/// them as they are. Panics if `side < 2` or `grid.len() != side^2` (caller bugs).
pub fn mesh_from_grid(grid: &[f64], side: u32, level: u32) -> Mesh {
    assert!(side >= 2, "a grid needs at least 2 samples per side");
    let n = side as usize;
    assert_eq!(grid.len(), n * n, "grid must hold side^2 heights");
    let last = side - 1;
    let kept = mask::kept_indices(side, level);
    let k = kept.len();

    struct Builder<'a> {
        grid: &'a [f64],
        n: usize,
        last: u32,
        kept: &'a [u32],
        k: usize,
        index_of: Vec<u32>,
        mesh: Mesh,
    }
    impl Builder<'_> {
        /// Index of the vertex at kept row `kr`, kept column `kc`, added on first use.
        fn vertex(&mut self, kr: usize, kc: usize) -> u32 {
            let slot = kr * self.k + kc;
            if self.index_of[slot] == u32::MAX {
                let (row, col) = (self.kept[kr], self.kept[kc]);
                self.index_of[slot] = self.mesh.u.len() as u32;
                self.mesh.u.push(quantize_index(col, self.last));
                self.mesh.v.push(quantize_index(self.last - row, self.last));
                self.mesh
                    .height_m
                    .push(self.grid[row as usize * self.n + col as usize]);
            }
            self.index_of[slot]
        }
    }

    let cells = k - 1;
    let mut b = Builder {
        grid,
        n,
        last,
        kept: &kept,
        k,
        index_of: vec![u32::MAX; k * k],
        mesh: Mesh {
            u: Vec::with_capacity(k * k),
            v: Vec::with_capacity(k * k),
            height_m: Vec::with_capacity(k * k),
            triangles: Vec::with_capacity(2 * cells * cells),
        },
    };
    for kr in 0..cells {
        for kc in 0..cells {
            // North-west half: NW, SW, NE; south-east half: SW, SE, NE. Both counter-clockwise
            // seen from above, split along SW-NE as `terrain_shared::mask` draws it. Vertices
            // are asked for in the order the triangles list them.
            let nw = b.vertex(kr, kc);
            let sw = b.vertex(kr + 1, kc);
            let ne = b.vertex(kr, kc + 1);
            b.mesh.triangles.push([nw, sw, ne]);
            let se = b.vertex(kr + 1, kc + 1);
            b.mesh.triangles.push([sw, se, ne]);
        }
    }
    b.mesh
}

/// The header of a tile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Header {
    /// Centre of the tile, ECEF metres (the rectangle's centre at mid height).
    pub center: [f64; 3],
    /// Height of quantized height 0, metres.
    pub min_height: f32,
    /// Height of quantized height 32767, metres.
    pub max_height: f32,
    /// Centre of a sphere holding every vertex, ECEF metres.
    pub bounding_sphere_center: [f64; 3],
    /// Radius of that sphere, metres.
    pub bounding_sphere_radius: f64,
    /// Horizon occlusion point, ellipsoid-scaled ECEF (ECEF divided by the radii).
    pub horizon_occlusion_point: [f64; 3],
}

/// A decoded tile (for tests and for checking what we serve).
#[derive(Debug, Clone, PartialEq)]
pub struct Decoded {
    /// The header.
    pub header: Header,
    /// The mesh, heights dequantized from the header's minimum and maximum.
    pub mesh: Mesh,
    /// Vertices listed on the west edge.
    pub west: Vec<u32>,
    /// Vertices listed on the south edge.
    pub south: Vec<u32>,
    /// Vertices listed on the east edge.
    pub east: Vec<u32>,
    /// Vertices listed on the north edge.
    pub north: Vec<u32>,
    /// Oct-encoded normal of each vertex, if the tile has the `octvertexnormals` extension.
    pub normals: Option<Vec<[u8; 2]>>,
}

/// Why bytes are not a quantized-mesh-1.0 tile.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum QuantizedMeshError {
    /// The bytes end inside a part of the tile.
    #[error("tile truncated: {len} bytes end inside the {part}")]
    Truncated {
        /// The part being read.
        part: &'static str,
        /// Length of the input.
        len: usize,
    },
    /// A decoded u, v or height lies outside 0..=32767.
    #[error("{axis} of vertex {vertex} is {value}, outside 0..=32767")]
    VertexOutOfRange {
        /// "u", "v" or "height".
        axis: &'static str,
        /// The vertex.
        vertex: usize,
        /// Its decoded value.
        value: i64,
    },
    /// A high-water-mark code is larger than the mark.
    #[error("triangle index {position}: code {code} exceeds the high water mark {highest}")]
    BadIndexCode {
        /// Position in the index list.
        position: usize,
        /// The code read.
        code: u32,
        /// The high water mark there.
        highest: u32,
    },
    /// An index refers to no vertex.
    #[error("{part} index {index} is not below the vertex count {vertex_count}")]
    IndexOutOfRange {
        /// "triangle" or the edge's name.
        part: &'static str,
        /// The index.
        index: u32,
        /// Number of vertices.
        vertex_count: u32,
    },
    /// The `octvertexnormals` extension's length is not two bytes per vertex.
    #[error("octvertexnormals extension is {len} bytes, {vertex_count} vertices need twice that")]
    NormalsLength {
        /// Length of the extension.
        len: u32,
        /// Number of vertices.
        vertex_count: u32,
    },
}

/// Height of quantized height `q` between `min` and `max`, as CesiumJS dequantizes it.
fn dequantize_height(min: f32, max: f32, q: u16) -> f64 {
    let (min, max) = (f64::from(min), f64::from(max));
    min + (max - min) * (f64::from(q) / f64::from(QUANTIZED_MAX))
}

/// Largest `f32` not above `x`.
fn f32_at_most(x: f64) -> f32 {
    let f = x as f32;
    if f64::from(f) > x { f.next_down() } else { f }
}

/// Smallest `f32` not below `x`.
fn f32_at_least(x: f64) -> f32 {
    let f = x as f32;
    if f64::from(f) < x { f.next_up() } else { f }
}

fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn scale(a: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

/// ECEF position, metres, of geodetic longitude and latitude (degrees) and height above the
/// WGS84 ellipsoid (metres).
pub fn geodetic_to_ecef(lon_deg: f64, lat_deg: f64, height_m: f64) -> [f64; 3] {
    let (sin_lat, cos_lat) = lat_deg.to_radians().sin_cos();
    let (sin_lon, cos_lon) = lon_deg.to_radians().sin_cos();
    let e2 = 1.0 - (WGS84_B * WGS84_B) / (WGS84_A * WGS84_A);
    let n = WGS84_A / (1.0 - e2 * sin_lat * sin_lat).sqrt();
    [
        (n + height_m) * cos_lat * cos_lon,
        (n + height_m) * cos_lat * sin_lon,
        (n * (1.0 - e2) + height_m) * sin_lat,
    ]
}

/// Unit normal of the WGS84 ellipsoid (geodetic up) at longitude and latitude, degrees.
pub fn geodetic_up(lon_deg: f64, lat_deg: f64) -> [f64; 3] {
    let (sin_lat, cos_lat) = lat_deg.to_radians().sin_cos();
    let (sin_lon, cos_lon) = lon_deg.to_radians().sin_cos();
    [cos_lat * cos_lon, cos_lat * sin_lon, sin_lat]
}

/// ECEF position divided by the ellipsoid's radii: the space of the horizon occlusion point.
fn to_scaled_space(p: [f64; 3]) -> [f64; 3] {
    [p[0] / WGS84_A, p[1] / WGS84_A, p[2] / WGS84_B]
}

/// ECEF positions of a mesh's vertices over `rect`.
pub fn vertex_positions(rect: &GeoRect, mesh: &Mesh) -> Vec<[f64; 3]> {
    mesh.u
        .iter()
        .zip(&mesh.v)
        .zip(&mesh.height_m)
        .map(|((&u, &v), &h)| geodetic_to_ecef(rect.lon_of(u), rect.lat_of(v), h))
        .collect()
}

/// Bounding sphere of `points` (not empty): the smaller of the spheres around the centre of
/// their bounding box and around Ritter's centre, each just holding every point.
fn bounding_sphere(points: &[[f64; 3]]) -> ([f64; 3], f64) {
    let radius_around =
        |c: [f64; 3]| -> f64 { points.iter().map(|&p| norm(sub(p, c))).fold(0.0, f64::max) };
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in points {
        for i in 0..3 {
            lo[i] = lo[i].min(p[i]);
            hi[i] = hi[i].max(p[i]);
        }
    }
    let box_center = scale(add(lo, hi), 0.5);

    // Ritter: a sphere on two far-apart points, grown to take in every point outside it.
    let first = points[0];
    let farthest_from = |c: [f64; 3]| -> [f64; 3] {
        let mut best = (c, -1.0);
        for &p in points {
            let d = norm(sub(p, c));
            if d > best.1 {
                best = (p, d);
            }
        }
        best.0
    };
    let a = farthest_from(first);
    let b = farthest_from(a);
    let mut center = scale(add(a, b), 0.5);
    let mut radius = norm(sub(b, a)) * 0.5;
    for &p in points {
        let d = norm(sub(p, center));
        if d > radius {
            let grown = (radius + d) * 0.5;
            center = add(center, scale(sub(p, center), (grown - radius) / d));
            radius = grown;
        }
    }

    let (box_radius, ritter_radius) = (radius_around(box_center), radius_around(center));
    if ritter_radius < box_radius {
        (center, ritter_radius)
    } else {
        (box_center, box_radius)
    }
}

/// CesiumJS's `computeMagnitude` (`EllipsoidalOccluder`): how far along the unit scaled-space
/// `direction` the horizon occlusion point must lie for `position` (ECEF) to be hidden
/// whenever the point is. Negative or infinite when no point on that ray will do.
fn culling_magnitude(position: [f64; 3], direction: [f64; 3]) -> f64 {
    let scaled = to_scaled_space(position);
    let magnitude_squared = dot(scaled, scaled);
    let magnitude = magnitude_squared.sqrt();
    let unit = scale(scaled, 1.0 / magnitude);
    // Points below the ellipsoid count as on it.
    let magnitude_squared = magnitude_squared.max(1.0);
    let magnitude = magnitude.max(1.0);
    let cos_alpha = dot(unit, direction);
    let sin_alpha = norm(cross(unit, direction));
    let cos_beta = 1.0 / magnitude;
    let sin_beta = (magnitude_squared - 1.0).sqrt() * cos_beta;
    1.0 / (cos_alpha * cos_beta - sin_alpha * sin_beta)
}

/// Horizon occlusion point (scaled space) of `positions` (ECEF) seen along `direction`
/// (ECEF, usually the bounding sphere's centre), per Cesium's horizon culling method
/// (`EllipsoidalOccluder.computeHorizonCullingPoint`). Where no finite point exists, one far
/// along the direction ([`FALLBACK_OCCLUSION_MAGNITUDE`]).
///
/// A tile spanning a hemisphere has no finite point along the bounding sphere's centre, and
/// that centre lies near the Earth's, in no useful direction: there the point is taken far
/// along `tile_direction` (the tile's centre on the ellipsoid), which is seen from wherever
/// any of the tile can be. A point far along a wrong direction would hide the tile from
/// every camera above it (a globe drawn without its level-0 tiles).
fn horizon_occlusion_point(
    direction: [f64; 3],
    tile_direction: [f64; 3],
    positions: &[[f64; 3]],
) -> [f64; 3] {
    let point = occlusion_point_along(direction, positions);
    if norm(point) < FALLBACK_OCCLUSION_MAGNITUDE {
        return point;
    }
    occlusion_point_along(tile_direction, positions)
}

/// [`horizon_occlusion_point`] along one direction, or the fallback far along it.
fn occlusion_point_along(direction: [f64; 3], positions: &[[f64; 3]]) -> [f64; 3] {
    let scaled = to_scaled_space(direction);
    let length = norm(scaled);
    let direction = if length > 0.0 && length.is_finite() {
        scale(scaled, 1.0 / length)
    } else {
        [1.0, 0.0, 0.0]
    };
    let mut magnitude: f64 = 1.0;
    for &p in positions {
        let m = culling_magnitude(p, direction);
        if !(m.is_finite() && m > 0.0) {
            magnitude = FALLBACK_OCCLUSION_MAGNITUDE;
            break;
        }
        magnitude = magnitude.max(m);
    }
    scale(direction, magnitude)
}

/// Area-weighted mean of the normals of the triangles around each vertex (ECEF, unit);
/// geodetic up at vertices that no triangle of non-zero area touches.
fn vertex_normals(rect: &GeoRect, mesh: &Mesh, positions: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let mut sums = vec![[0.0f64; 3]; positions.len()];
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| i as usize);
        // Twice the triangle's area, outward for a counter-clockwise triangle.
        let n = cross(
            sub(positions[b], positions[a]),
            sub(positions[c], positions[a]),
        );
        for i in [a, b, c] {
            sums[i] = add(sums[i], n);
        }
    }
    sums.iter()
        .enumerate()
        .map(|(i, &s)| {
            let length = norm(s);
            if length > 0.0 && length.is_finite() {
                scale(s, 1.0 / length)
            } else {
                geodetic_up(rect.lon_of(mesh.u[i]), rect.lat_of(mesh.v[i]))
            }
        })
        .collect()
}

fn sign_not_zero(x: f64) -> f64 {
    if x < 0.0 { -1.0 } else { 1.0 }
}

fn to_snorm(x: f64) -> u8 {
    ((x.clamp(-1.0, 1.0) * 0.5 + 0.5) * 255.0).round() as u8
}

fn from_snorm(x: u8) -> f64 {
    f64::from(x) / 255.0 * 2.0 - 1.0
}

/// Oct-encoding of a unit vector into two bytes, as CesiumJS's `AttributeCompression.octEncode`.
pub fn oct_encode(n: [f64; 3]) -> [u8; 2] {
    let l1 = n[0].abs() + n[1].abs() + n[2].abs();
    let (mut x, mut y) = (n[0] / l1, n[1] / l1);
    if n[2] < 0.0 {
        let (ox, oy) = (x, y);
        x = (1.0 - oy.abs()) * sign_not_zero(ox);
        y = (1.0 - ox.abs()) * sign_not_zero(oy);
    }
    [to_snorm(x), to_snorm(y)]
}

/// The unit vector of two oct-encoded bytes, as CesiumJS's `AttributeCompression.octDecode`.
pub fn oct_decode(e: [u8; 2]) -> [f64; 3] {
    let (mut x, mut y) = (from_snorm(e[0]), from_snorm(e[1]));
    let z = 1.0 - (x.abs() + y.abs());
    if z < 0.0 {
        let ox = x;
        x = (1.0 - y.abs()) * sign_not_zero(ox);
        y = (1.0 - ox.abs()) * sign_not_zero(y);
    }
    let v = [x, y, z];
    scale(v, 1.0 / norm(v))
}

fn zig_zag(delta: i32) -> u16 {
    ((delta << 1) ^ (delta >> 31)) as u16
}

fn un_zig_zag(value: u16) -> i64 {
    let value = i64::from(value);
    (value >> 1) ^ -(value & 1)
}

/// Appends `values` zig-zag delta encoded.
fn put_zig_zag(out: &mut Vec<u8>, values: &[u16]) {
    let mut previous = 0i32;
    for &value in values {
        let value = i32::from(value);
        out.extend_from_slice(&zig_zag(value - previous).to_le_bytes());
        previous = value;
    }
}

fn put_f64s(out: &mut Vec<u8>, values: &[f64]) {
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
}

fn put_u32(out: &mut Vec<u8>, value: u32) {
    out.extend_from_slice(&value.to_le_bytes());
}

fn put_index(out: &mut Vec<u8>, index: u32, wide: bool) {
    if wide {
        put_u32(out, index);
    } else {
        out.extend_from_slice(&(index as u16).to_le_bytes());
    }
}

/// The quantized-mesh-1.0 bytes of `mesh` over `rect`, with the octvertexnormals extension.
///
/// Vertices are renumbered in the order the triangles first use them (the high water mark
/// encoding needs it; [`mesh_from_grid`]'s order already is), unused ones last. Heights are
/// quantized between the header's minimum and maximum, `f32` values rounded outward from
/// the mesh's; positions, bounding sphere, horizon occlusion point and normals are computed
/// from the heights as CesiumJS will dequantize them.
///
/// Panics if the mesh is malformed (caller bugs): arrays of different lengths, u or v above
/// 32767, a triangle index out of range, a non-finite height, more than `u32::MAX` vertices.
pub fn encode(rect: &GeoRect, mesh: &Mesh) -> Vec<u8> {
    let count = mesh.u.len();
    assert!(
        mesh.v.len() == count && mesh.height_m.len() == count,
        "u, v and height_m must have one entry per vertex"
    );
    assert!(u32::try_from(count).is_ok(), "too many vertices");
    assert!(
        mesh.u.iter().chain(&mesh.v).all(|&q| q <= QUANTIZED_MAX),
        "u and v must be in 0..=32767"
    );
    assert!(
        mesh.height_m.iter().all(|h| h.is_finite()),
        "heights must be finite"
    );
    assert!(
        mesh.triangles
            .iter()
            .flatten()
            .all(|&i| (i as usize) < count),
        "triangle index out of range"
    );

    // Renumber vertices in order of first use.
    let mut new_of_old = vec![u32::MAX; count];
    let mut old_of_new = Vec::with_capacity(count);
    for &i in mesh.triangles.iter().flatten() {
        if new_of_old[i as usize] == u32::MAX {
            new_of_old[i as usize] = old_of_new.len() as u32;
            old_of_new.push(i as usize);
        }
    }
    for (i, slot) in new_of_old.iter_mut().enumerate() {
        if *slot == u32::MAX {
            *slot = old_of_new.len() as u32;
            old_of_new.push(i);
        }
    }
    let triangles: Vec<[u32; 3]> = mesh
        .triangles
        .iter()
        .map(|t| t.map(|i| new_of_old[i as usize]))
        .collect();

    // Heights: f32 bounds rounded outward, quantized between them.
    let (lo, hi) = if count == 0 {
        (0.0, 0.0)
    } else {
        let lo = mesh.height_m.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = mesh
            .height_m
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max);
        (f32_at_most(lo), f32_at_least(hi))
    };
    let range = f64::from(hi) - f64::from(lo);
    let quantize = |h: f64| -> u16 {
        if range > 0.0 {
            ((h - f64::from(lo)) / range * f64::from(QUANTIZED_MAX))
                .round()
                .clamp(0.0, f64::from(QUANTIZED_MAX)) as u16
        } else {
            0
        }
    };
    let u: Vec<u16> = old_of_new.iter().map(|&i| mesh.u[i]).collect();
    let v: Vec<u16> = old_of_new.iter().map(|&i| mesh.v[i]).collect();
    let h: Vec<u16> = old_of_new
        .iter()
        .map(|&i| quantize(mesh.height_m[i]))
        .collect();
    let served = Mesh {
        height_m: h.iter().map(|&q| dequantize_height(lo, hi, q)).collect(),
        u: u.clone(),
        v: v.clone(),
        triangles,
    };

    let center = geodetic_to_ecef(
        (rect.west + rect.east) * 0.5,
        (rect.south + rect.north) * 0.5,
        (f64::from(lo) + f64::from(hi)) * 0.5,
    );
    let positions = vertex_positions(rect, &served);
    let bound_points: &[[f64; 3]] = if positions.is_empty() {
        std::slice::from_ref(&center)
    } else {
        &positions
    };
    let (sphere_center, sphere_radius) = bounding_sphere(bound_points);
    let direction = if norm(sphere_center) > 0.0 {
        sphere_center
    } else {
        center
    };
    let occlusion = horizon_occlusion_point(direction, center, bound_points);
    let normals = vertex_normals(rect, &served, &positions);

    let wide = count > MAX_VERTICES_16_BIT;
    let index_bytes = if wide { 4 } else { 2 };
    let mut out = Vec::with_capacity(
        HEADER_LEN
            + 4
            + 6 * count
            + 4
            + 4 * 5
            + 3 * index_bytes * served.triangles.len()
            + 5
            + 2 * count,
    );

    put_f64s(&mut out, &center);
    out.extend_from_slice(&lo.to_le_bytes());
    out.extend_from_slice(&hi.to_le_bytes());
    put_f64s(&mut out, &sphere_center);
    put_f64s(&mut out, &[sphere_radius]);
    put_f64s(&mut out, &occlusion);

    put_u32(&mut out, count as u32);
    put_zig_zag(&mut out, &u);
    put_zig_zag(&mut out, &v);
    put_zig_zag(&mut out, &h);

    while out.len() % index_bytes != 0 {
        out.push(0);
    }
    put_u32(&mut out, served.triangles.len() as u32);
    let mut highest = 0u32;
    for &index in served.triangles.iter().flatten() {
        let code = highest - index;
        if code == 0 {
            highest += 1;
        }
        put_index(&mut out, code, wide);
    }

    let edge = |on_edge: &dyn Fn(usize) -> bool, key: &[u16]| -> Vec<u32> {
        let mut list: Vec<u32> = (0..count)
            .filter(|&i| on_edge(i))
            .map(|i| i as u32)
            .collect();
        list.sort_by_key(|&i| (key[i as usize], i));
        list
    };
    let west = edge(&|i| u[i] == 0, &v);
    let south = edge(&|i| v[i] == 0, &u);
    let east = edge(&|i| u[i] == QUANTIZED_MAX, &v);
    let north = edge(&|i| v[i] == QUANTIZED_MAX, &u);
    for list in [&west, &south, &east, &north] {
        put_u32(&mut out, list.len() as u32);
        for &i in list {
            put_index(&mut out, i, wide);
        }
    }

    out.push(OCT_VERTEX_NORMALS);
    put_u32(&mut out, 2 * count as u32);
    for &n in &normals {
        out.extend_from_slice(&oct_encode(n));
    }
    out
}

/// A cursor over the input that never reads past its end.
struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, len: u64, part: &'static str) -> Result<&'a [u8], QuantizedMeshError> {
        let truncated = QuantizedMeshError::Truncated {
            part,
            len: self.bytes.len(),
        };
        let remaining = self.bytes.len() - self.pos;
        let len = usize::try_from(len).map_err(|_| truncated.clone())?;
        if len > remaining {
            return Err(truncated);
        }
        let slice = &self.bytes[self.pos..self.pos + len];
        self.pos += len;
        Ok(slice)
    }

    fn array<const N: usize>(&mut self, part: &'static str) -> Result<[u8; N], QuantizedMeshError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N as u64, part)?);
        Ok(out)
    }

    fn u32(&mut self, part: &'static str) -> Result<u32, QuantizedMeshError> {
        Ok(u32::from_le_bytes(self.array(part)?))
    }

    fn f64s<const N: usize>(&mut self, part: &'static str) -> Result<[f64; N], QuantizedMeshError> {
        let mut out = [0.0; N];
        for v in &mut out {
            *v = f64::from_le_bytes(self.array(part)?);
        }
        Ok(out)
    }

    /// `count` indices of `width` bytes.
    fn indices(
        &mut self,
        count: u32,
        width: usize,
        part: &'static str,
    ) -> Result<Vec<u32>, QuantizedMeshError> {
        let bytes = self.take(u64::from(count) * width as u64, part)?;
        Ok(if width == 4 {
            bytes
                .chunks_exact(4)
                .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect()
        } else {
            bytes
                .chunks_exact(2)
                .map(|c| u32::from(u16::from_le_bytes([c[0], c[1]])))
                .collect()
        })
    }

    /// `count` zig-zag delta encoded u16, each checked to be in 0..=32767.
    fn zig_zag(&mut self, count: u32, axis: &'static str) -> Result<Vec<u16>, QuantizedMeshError> {
        let bytes = self.take(u64::from(count) * 2, "vertex data")?;
        let mut value = 0i64;
        let mut out = Vec::with_capacity(count as usize);
        for (vertex, c) in bytes.chunks_exact(2).enumerate() {
            value += un_zig_zag(u16::from_le_bytes([c[0], c[1]]));
            if !(0..=i64::from(QUANTIZED_MAX)).contains(&value) {
                return Err(QuantizedMeshError::VertexOutOfRange {
                    axis,
                    vertex,
                    value,
                });
            }
            out.push(value as u16);
        }
        Ok(out)
    }
}

/// Decodes a quantized-mesh-1.0 tile (not gzipped), checking that every index refers to a
/// vertex and every u, v and height is in range. Extensions other than `octvertexnormals`
/// are skipped. Never panics.
pub fn decode(bytes: &[u8]) -> Result<Decoded, QuantizedMeshError> {
    let mut r = Reader { bytes, pos: 0 };
    let center = r.f64s::<3>("header")?;
    let min_height = f32::from_le_bytes(r.array("header")?);
    let max_height = f32::from_le_bytes(r.array("header")?);
    let bounding_sphere_center = r.f64s::<3>("header")?;
    let [bounding_sphere_radius] = r.f64s::<1>("header")?;
    let horizon_occlusion_point = r.f64s::<3>("header")?;
    let header = Header {
        center,
        min_height,
        max_height,
        bounding_sphere_center,
        bounding_sphere_radius,
        horizon_occlusion_point,
    };

    let vertex_count = r.u32("vertex count")?;
    // Check the whole vertex block is there before allocating for it.
    if u64::from(vertex_count) * 6 > (bytes.len() - r.pos) as u64 {
        return Err(QuantizedMeshError::Truncated {
            part: "vertex data",
            len: bytes.len(),
        });
    }
    let u = r.zig_zag(vertex_count, "u")?;
    let v = r.zig_zag(vertex_count, "v")?;
    let h = r.zig_zag(vertex_count, "height")?;

    let width = if vertex_count as usize > MAX_VERTICES_16_BIT {
        4
    } else {
        2
    };
    let padding = (width - r.pos % width) % width;
    r.take(padding as u64, "index padding")?;
    let triangle_count = r.u32("triangle count")?;
    let codes = r.indices(triangle_count.saturating_mul(3), width, "triangle indices")?;
    if u64::from(triangle_count) * 3 != codes.len() as u64 {
        // Only when `triangle_count * 3` overflowed u32: far more than the input holds.
        return Err(QuantizedMeshError::Truncated {
            part: "triangle indices",
            len: bytes.len(),
        });
    }
    let mut highest = 0u32;
    let mut flat = Vec::with_capacity(codes.len());
    for (position, &code) in codes.iter().enumerate() {
        let index = highest
            .checked_sub(code)
            .ok_or(QuantizedMeshError::BadIndexCode {
                position,
                code,
                highest,
            })?;
        if index >= vertex_count {
            return Err(QuantizedMeshError::IndexOutOfRange {
                part: "triangle",
                index,
                vertex_count,
            });
        }
        if code == 0 {
            highest += 1;
        }
        flat.push(index);
    }
    let triangles: Vec<[u32; 3]> = flat.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect();

    let mut edges: [Vec<u32>; 4] = Default::default();
    for (list, part) in edges.iter_mut().zip(["west", "south", "east", "north"]) {
        let n = r.u32("edge vertex count")?;
        *list = r.indices(n, width, "edge indices")?;
        if let Some(&index) = list.iter().find(|&&i| i >= vertex_count) {
            return Err(QuantizedMeshError::IndexOutOfRange {
                part,
                index,
                vertex_count,
            });
        }
    }

    let mut normals = None;
    while r.pos < bytes.len() {
        let [id] = r.array::<1>("extension header")?;
        let len = r.u32("extension header")?;
        let data = r.take(u64::from(len), "extension")?;
        if id == OCT_VERTEX_NORMALS {
            if u64::from(len) != 2 * u64::from(vertex_count) {
                return Err(QuantizedMeshError::NormalsLength { len, vertex_count });
            }
            normals = Some(data.chunks_exact(2).map(|c| [c[0], c[1]]).collect());
        }
    }

    let [west, south, east, north] = edges;
    Ok(Decoded {
        header,
        mesh: Mesh {
            height_m: h
                .iter()
                .map(|&q| dequantize_height(min_height, max_height, q))
                .collect(),
            u,
            v,
            triangles,
        },
        west,
        south,
        east,
        north,
        normals,
    })
}

/// Height of the decoded surface at (lon, lat) inside rect, by the triangle that holds it
/// (barycentric), or None outside.
pub fn height_at(decoded: &Decoded, rect: &GeoRect, lon: f64, lat: f64) -> Option<f64> {
    if !(rect.west..=rect.east).contains(&lon) || !(rect.south..=rect.north).contains(&lat) {
        return None;
    }
    let q = f64::from(QUANTIZED_MAX);
    let p = [
        (lon - rect.west) / (rect.east - rect.west) * q,
        (lat - rect.south) / (rect.north - rect.south) * q,
    ];
    let mesh = &decoded.mesh;
    let at = |i: u32| -> Option<[f64; 2]> {
        let i = i as usize;
        Some([f64::from(*mesh.u.get(i)?), f64::from(*mesh.v.get(i)?)])
    };
    let cross2 = |o: [f64; 2], a: [f64; 2], b: [f64; 2]| -> f64 {
        (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
    };
    for t in &mesh.triangles {
        let (Some(a), Some(b), Some(c)) = (at(t[0]), at(t[1]), at(t[2])) else {
            continue;
        };
        let area = cross2(a, b, c);
        if area == 0.0 {
            continue;
        }
        let wa = cross2(p, b, c) / area;
        let wb = cross2(p, c, a) / area;
        let wc = 1.0 - wa - wb;
        const SLACK: f64 = -1e-9;
        if wa >= SLACK && wb >= SLACK && wc >= SLACK {
            let height = |i: u32| mesh.height_m.get(i as usize).copied();
            return Some(wa * height(t[0])? + wb * height(t[1])? + wc * height(t[2])?);
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    /// xorshift64*: reproducible numbers without a dependency.
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
        }

        /// Uniform in [0, 1).
        fn unit(&mut self) -> f64 {
            (self.next() >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// A `side x side` grid (row 0 north) of `f(column fraction east, row fraction north)`.
    fn grid(side: u32, f: impl Fn(f64, f64) -> f64) -> Vec<f64> {
        let last = f64::from(side - 1);
        let mut out = Vec::new();
        for row in 0..side {
            for col in 0..side {
                out.push(f(f64::from(col) / last, f64::from(side - 1 - row) / last));
            }
        }
        out
    }

    /// A tilted plane with a bump: 100..~1400 m.
    fn plane_and_bump(x: f64, y: f64) -> f64 {
        let bump = 900.0 * (-((x - 0.4).powi(2) + (y - 0.6).powi(2)) / 0.05).exp();
        100.0 + 300.0 * x + 200.0 * y + bump
    }

    fn range(values: &[f64]) -> f64 {
        let lo = values.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        hi - lo
    }

    fn sorted(mut v: Vec<u32>) -> Vec<u32> {
        v.sort_unstable();
        v
    }

    fn on_edge(mesh: &Mesh, f: impl Fn(u16, u16) -> bool) -> Vec<u32> {
        (0..mesh.u.len() as u32)
            .filter(|&i| f(mesh.u[i as usize], mesh.v[i as usize]))
            .collect()
    }

    /// Encodes and decodes, checking what every tile must satisfy.
    fn round_trip(rect: &GeoRect, mesh: &Mesh) -> Decoded {
        let decoded = decode(&encode(rect, mesh)).expect("our own tile decodes");
        assert_eq!(decoded.mesh.u, mesh.u);
        assert_eq!(decoded.mesh.v, mesh.v);
        assert_eq!(decoded.mesh.triangles, mesh.triangles);
        let tolerance = range(&mesh.height_m) / f64::from(QUANTIZED_MAX);
        for (got, want) in decoded.mesh.height_m.iter().zip(&mesh.height_m) {
            assert!((got - want).abs() <= tolerance, "height {got} for {want}");
        }
        assert_eq!(sorted(decoded.west.clone()), on_edge(mesh, |u, _| u == 0));
        assert_eq!(sorted(decoded.south.clone()), on_edge(mesh, |_, v| v == 0));
        assert_eq!(
            sorted(decoded.east.clone()),
            on_edge(mesh, |u, _| u == QUANTIZED_MAX)
        );
        assert_eq!(
            sorted(decoded.north.clone()),
            on_edge(mesh, |_, v| v == QUANTIZED_MAX)
        );
        assert_eq!(decoded.normals.as_ref().map(Vec::len), Some(mesh.u.len()));
        decoded
    }

    #[test]
    fn geographic_tiles_cover_the_globe_from_the_south_west() {
        assert_eq!(
            GeoRect::tile(0, 0, 0),
            GeoRect {
                west: -180.0,
                south: -90.0,
                east: 0.0,
                north: 90.0
            }
        );
        assert_eq!(
            GeoRect::tile(0, 1, 0),
            GeoRect {
                west: 0.0,
                south: -90.0,
                east: 180.0,
                north: 90.0
            }
        );
        assert_eq!(
            GeoRect::tile(1, 3, 1),
            GeoRect {
                west: 90.0,
                south: 0.0,
                east: 180.0,
                north: 90.0
            }
        );
    }

    #[test]
    fn grid_meshes_round_trip_at_levels_0_and_2() {
        let rect = GeoRect::tile(9, 560, 360);
        let heights = grid(9, plane_and_bump);
        for level in [0, 2] {
            let kept = mask::kept_indices(9, level).len();
            let mesh = mesh_from_grid(&heights, 9, level);
            assert_eq!(mesh.u.len(), kept * kept, "level {level}");
            assert_eq!(mesh.triangles.len(), 2 * (kept - 1) * (kept - 1));
            assert_eq!(
                decode(&encode(&rect, &mesh)).map(|d| d.west.len()),
                Ok(kept)
            );
            let decoded = round_trip(&rect, &mesh);
            let h = decoded.header;
            let lo = mesh.height_m.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = mesh
                .height_m
                .iter()
                .copied()
                .fold(f64::NEG_INFINITY, f64::max);
            assert!(f64::from(h.min_height) <= lo && lo - f64::from(h.min_height) < 1e-3);
            assert!(f64::from(h.max_height) >= hi && f64::from(h.max_height) - hi < 1e-3);
            let mid = (f64::from(h.min_height) + f64::from(h.max_height)) / 2.0;
            let center = geodetic_to_ecef(
                (rect.west + rect.east) / 2.0,
                (rect.south + rect.north) / 2.0,
                mid,
            );
            assert_eq!(h.center, center);
        }
    }

    #[test]
    fn meshes_follow_the_masks_diagonal() {
        // mask's own test: NW and SE corners lifted; split SW-NE, the centre lies on zeros.
        let samples = [8.0, 4.0, 0.0, 4.0, 0.0, 4.0, 0.0, 4.0, 8.0];
        let rect = GeoRect::tile(12, 100, 100);
        let tile = decode(&encode(&rect, &mesh_from_grid(&samples, 3, 1))).expect("decodes");
        let centre = height_at(
            &tile,
            &rect,
            (rect.west + rect.east) / 2.0,
            (rect.south + rect.north) / 2.0,
        );
        assert!(centre.is_some_and(|h| h.abs() < 1e-3), "{centre:?}");

        // At every sample of a rough grid, a level-2 tile is the surface `mask` computes.
        let side = 9u32;
        let mut rng = Rng(7);
        let heights: Vec<f64> = (0..side * side).map(|_| 1000.0 * rng.unit()).collect();
        let tile = decode(&encode(&rect, &mesh_from_grid(&heights, side, 2))).expect("decodes");
        let kept = mask::kept_indices(side, 2);
        let at = |c: u32, r: u32| heights[(r * side + c) as usize];
        for rows in kept.windows(2) {
            for cols in kept.windows(2) {
                let (r0, r1, c0, c1) = (rows[0], rows[1], cols[0], cols[1]);
                for r in r0..=r1 {
                    for c in c0..=c1 {
                        let su = f64::from(c - c0) / f64::from(c1 - c0);
                        let sv = f64::from(r - r0) / f64::from(r1 - r0);
                        let want = mask::cell_height(
                            at(c0, r0),
                            at(c1, r0),
                            at(c0, r1),
                            at(c1, r1),
                            su,
                            sv,
                        );
                        let lon = rect.west + (rect.east - rect.west) * f64::from(c) / 8.0;
                        let lat = rect.north - (rect.north - rect.south) * f64::from(r) / 8.0;
                        let got = height_at(&tile, &rect, lon, lat).expect("inside");
                        // Quantized heights, and u/v quantized to 1/32767 of a 1000 m/8 slope.
                        assert!((got - want).abs() < 0.1, "({c}, {r}): {got} vs {want}");
                    }
                }
            }
        }
    }

    #[test]
    fn indices_widen_above_65536_vertices() {
        let rect = GeoRect::tile(3, 5, 2);
        // Exact tile lengths: header, vertices, padding, triangles, edges, normals.
        let expected_len = |vertices: usize, per_side: usize, width: usize| {
            let vertex_end = HEADER_LEN + 4 + 6 * vertices;
            let padding = (width - vertex_end % width) % width;
            let triangles = 2 * (per_side - 1) * (per_side - 1);
            vertex_end
                + padding
                + 4
                + 3 * width * triangles
                + 4 * (4 + width * per_side)
                + 5
                + 2 * vertices
        };
        // 257^2 = 66049 vertices (odd: 2 bytes of padding), 256^2 = 65536, 129^2 = 16641.
        for (side, width) in [(257u32, 4usize), (256, 2), (129, 2)] {
            let mesh = mesh_from_grid(&grid(side, plane_and_bump), side, 0);
            let n = side as usize;
            assert_eq!(
                encode(&rect, &mesh).len(),
                expected_len(n * n, n, width),
                "side {side}"
            );
            round_trip(&rect, &mesh);
        }
    }

    #[test]
    fn encode_renumbers_vertices_in_order_of_first_use() {
        let rect = GeoRect::tile(5, 10, 10);
        let mesh = Mesh {
            u: vec![0, 32767, 7, 32767, 0],
            v: vec![32767, 0, 7, 32767, 0],
            height_m: vec![1.0, 2.0, 99.0, 3.0, 4.0],
            // NW, SW, NE then SW, SE, NE; vertex 2 unused.
            triangles: vec![[0, 4, 3], [4, 1, 3]],
        };
        let tile = decode(&encode(&rect, &mesh)).expect("decodes");
        assert_eq!(tile.mesh.triangles, vec![[0, 1, 2], [1, 3, 2]]);
        assert_eq!(tile.mesh.u, vec![0, 0, 32767, 32767, 7]);
        assert_eq!(tile.mesh.v, vec![32767, 0, 32767, 0, 7]);
        let heights: Vec<f64> = tile.mesh.height_m.iter().map(|h| h.round()).collect();
        assert_eq!(heights, vec![1.0, 4.0, 3.0, 2.0, 99.0]);
    }

    #[test]
    fn decode_rejects_indices_outside_the_mesh() {
        let rect = GeoRect::tile(5, 10, 10);
        let mesh = Mesh {
            u: vec![0, 0, 32767, 32767, 7],
            v: vec![32767, 0, 32767, 0, 7],
            height_m: vec![1.0, 4.0, 3.0, 2.0, 99.0],
            triangles: vec![[0, 1, 2], [1, 3, 2]],
        };
        let bytes = encode(&rect, &mesh);
        // Five vertices: u16 indices, triangles after 30 bytes of vertices and their count.
        let triangles_at = HEADER_LEN + 4 + 30 + 4;
        let west_at = triangles_at + 12 + 4;
        assert_eq!(
            bytes[triangles_at..triangles_at + 12],
            [0, 0, 0, 0, 0, 0, 2, 0, 0, 0, 2, 0]
        );
        assert_eq!(decode(&bytes).map(|d| d.west), Ok(vec![1, 0]));

        let mut corrupt = bytes.clone();
        corrupt[triangles_at + 6..triangles_at + 12].fill(0); // indices 3, 4, 5
        assert_eq!(
            decode(&corrupt).map(|_| ()),
            Err(QuantizedMeshError::IndexOutOfRange {
                part: "triangle",
                index: 5,
                vertex_count: 5
            })
        );
        let mut corrupt = bytes.clone();
        corrupt[triangles_at] = 1;
        assert_eq!(
            decode(&corrupt).map(|_| ()),
            Err(QuantizedMeshError::BadIndexCode {
                position: 0,
                code: 1,
                highest: 0
            })
        );
        let mut corrupt = bytes.clone();
        corrupt[west_at] = 5;
        assert_eq!(
            decode(&corrupt).map(|_| ()),
            Err(QuantizedMeshError::IndexOutOfRange {
                part: "west",
                index: 5,
                vertex_count: 5
            })
        );
        let mut corrupt = bytes;
        // u of the last vertex, delta encoded from the one before it (u 32767).
        let last_u = HEADER_LEN + 4 + 8;
        corrupt[last_u..last_u + 2].copy_from_slice(&[0, 0]); // +0: 32767, the east edge
        assert_eq!(decode(&corrupt).map(|d| d.mesh.u[4]), Ok(32767));
        corrupt[last_u..last_u + 2].copy_from_slice(&[2, 0]); // +1: 32768
        assert!(matches!(
            decode(&corrupt),
            Err(QuantizedMeshError::VertexOutOfRange {
                axis: "u",
                vertex: 4,
                ..
            })
        ));
    }

    #[test]
    fn height_at_reproduces_a_tilted_plane() {
        let rect = GeoRect {
            west: 10.0,
            south: 45.0,
            east: 10.25,
            north: 45.25,
        };
        let plane = |x: f64, y: f64| 100.0 + 3.0 * x + 5.0 * y;
        let heights = grid(17, plane);
        let mut rng = Rng(42);
        for level in [0, 3] {
            let tile =
                decode(&encode(&rect, &mesh_from_grid(&heights, 17, level))).expect("decodes");
            // Height quantization (8 m / 65534) plus u/v quantization (half of 1/32767 along
            // slopes of 3 and 5 m per tile).
            let tolerance = 2.0 * 8.0 / f64::from(QUANTIZED_MAX);
            for _ in 0..500 {
                let (x, y) = (rng.unit(), rng.unit());
                let lon = rect.west + x * (rect.east - rect.west);
                let lat = rect.south + y * (rect.north - rect.south);
                let got = height_at(&tile, &rect, lon, lat).expect("inside");
                assert!(
                    (got - plane(x, y)).abs() <= tolerance,
                    "level {level} ({x}, {y}): {got}"
                );
            }
            for (lon, lat) in [(rect.west, rect.south), (rect.east, rect.north)] {
                assert!(height_at(&tile, &rect, lon, lat).is_some());
            }
            for (lon, lat) in [(9.99, 45.1), (10.1, 45.26), (f64::NAN, 45.1)] {
                assert_eq!(height_at(&tile, &rect, lon, lat), None);
            }
        }
    }

    /// CesiumJS's `isScaledSpacePointVisible` for a camera outside the ellipsoid.
    fn visible(point: [f64; 3], camera: [f64; 3]) -> bool {
        let vh2 = dot(camera, camera) - 1.0;
        let vt = sub(point, camera);
        let vt_dot_vc = -dot(vt, camera);
        !(vt_dot_vc > vh2 && vt_dot_vc * vt_dot_vc / dot(vt, vt) > vh2)
    }

    #[test]
    fn a_half_sphere_tile_above_the_ellipsoid_is_seen_from_above_every_part_of_it() {
        // Level 0 of the geographic scheme: two tiles, each half the Earth. Heights above
        // the ellipsoid everywhere (the nearest edge's height off a DEM) leave no finite
        // horizon point; the one taken must not hide the tile from a camera above it.
        for (x, heights) in [(0u32, 268.5), (1, 4000.0), (0, 0.0)] {
            let rect = GeoRect::tile(0, x, 0);
            let grid = grid(17, |i, j| heights + 50.0 * plane_and_bump(i, j));
            let tile = round_trip(&rect, &mesh_from_grid(&grid, 17, 0));
            let point = tile.header.horizon_occlusion_point;
            for lon in [-170.0, -120.0, -84.25, -30.0, -5.0] {
                for lat in [-60.0, 0.0, 36.36, 80.0] {
                    let lon = lon + 180.0 * f64::from(x);
                    let camera = to_scaled_space(geodetic_to_ecef(lon, lat, 14_000.0));
                    assert!(
                        visible(point, camera),
                        "tile {x} at {heights} m: hidden from above {lon}, {lat} by {point:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn triangles_bounds_and_horizon_point_hold_the_tile() {
        let mut rng = Rng(3);
        let tiles = [
            (GeoRect::tile(9, 560, 360), 0),
            (GeoRect::tile(3, 5, 2), 2),
            (GeoRect::tile(1, 0, 0), 0),
            (GeoRect::tile(1, 2, 1), 1), // touches the north pole
            (GeoRect::tile(0, 1, 0), 0),
        ];
        for (rect, level) in tiles {
            let heights = grid(17, |x, y| 8.0 * plane_and_bump(x, y));
            let tile = round_trip(&rect, &mesh_from_grid(&heights, 17, level));
            let mesh = &tile.mesh;
            for t in &mesh.triangles {
                let [a, b, c] =
                    t.map(|i| [f64::from(mesh.u[i as usize]), f64::from(mesh.v[i as usize])]);
                let area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
                assert!(
                    area > 0.0,
                    "{rect:?}: triangle {t:?} is not counter-clockwise"
                );
            }
            let h = tile.header;
            let positions = vertex_positions(&rect, mesh);
            for p in &positions {
                let d = norm(sub(*p, h.bounding_sphere_center));
                assert!(
                    d <= h.bounding_sphere_radius,
                    "{rect:?}: {d} > {}",
                    h.bounding_sphere_radius
                );
            }
            // Not much bigger than it needs to be: at most the box's half-diagonal.
            let mut lo = [f64::INFINITY; 3];
            let mut hi = [f64::NEG_INFINITY; 3];
            for p in &positions {
                for i in 0..3 {
                    lo[i] = lo[i].min(p[i]);
                    hi[i] = hi[i].max(p[i]);
                }
            }
            assert!(h.bounding_sphere_radius <= norm(sub(hi, lo)) / 2.0 * (1.0 + 1e-12));

            let occlusion = h.horizon_occlusion_point;
            assert!(norm(occlusion) >= 1.0, "{rect:?}: {occlusion:?}");
            // Wherever the point is hidden behind the ellipsoid, so is every vertex (cameras
            // at 1.001 to 4 radii; half-sphere tiles only have an approximate point).
            if rect.east - rect.west >= 180.0 {
                // No finite point holds a half-sphere tile: one far along the direction.
                assert!((norm(occlusion) - FALLBACK_OCCLUSION_MAGNITUDE).abs() < 1e-3);
            } else {
                assert!(norm(occlusion) < 10.0, "{rect:?}: {occlusion:?}");
                let scaled: Vec<[f64; 3]> = positions.iter().map(|&p| to_scaled_space(p)).collect();
                let mut hidden = 0;
                for _ in 0..3000 {
                    let z = 2.0 * rng.unit() - 1.0;
                    let phi = std::f64::consts::TAU * rng.unit();
                    let r = (1.0 - z * z).sqrt();
                    let camera = scale([r * phi.cos(), r * phi.sin(), z], 1.001 + 3.0 * rng.unit());
                    if !visible(occlusion, camera) {
                        hidden += 1;
                        for &p in &scaled {
                            assert!(
                                !visible(p, camera),
                                "{rect:?}: a vertex shows from {camera:?}"
                            );
                        }
                    }
                }
                assert!(
                    hidden > 100,
                    "{rect:?}: the point is hardly ever hidden ({hidden})"
                );
            }
        }
    }

    #[test]
    fn flat_tiles_have_geodetic_up_normals() {
        let flat = vec![0.0; 81];
        let centre_up = |rect: &GeoRect| {
            geodetic_up(
                (rect.west + rect.east) / 2.0,
                (rect.south + rect.north) / 2.0,
            )
        };
        let degrees = |a: [f64; 3], b: [f64; 3]| dot(a, b).clamp(-1.0, 1.0).acos().to_degrees();
        // Small tiles: every normal is the centre's up; a bigger one: each vertex's own up.
        for (rect, per_vertex) in [
            (GeoRect::tile(12, 2200, 2900), false),
            (GeoRect::tile(12, 7000, 300), false),
            (GeoRect::tile(6, 100, 20), true),
        ] {
            let tile = decode(&encode(&rect, &mesh_from_grid(&flat, 9, 0))).expect("decodes");
            let normals = tile.normals.expect("normals");
            for (i, &e) in normals.iter().enumerate() {
                let up = if per_vertex {
                    geodetic_up(rect.lon_of(tile.mesh.u[i]), rect.lat_of(tile.mesh.v[i]))
                } else {
                    centre_up(&rect)
                };
                let angle = degrees(oct_decode(e), up);
                assert!(angle < 1.0, "{rect:?} vertex {i}: {angle} degrees off");
            }
        }
    }

    #[test]
    fn oct_encoding_round_trips_within_a_degree() {
        let mut rng = Rng(11);
        for _ in 0..5000 {
            let z = 2.0 * rng.unit() - 1.0;
            let phi = std::f64::consts::TAU * rng.unit();
            let r = (1.0 - z * z).sqrt();
            let n = [r * phi.cos(), r * phi.sin(), z];
            let back = oct_decode(oct_encode(n));
            let angle = dot(n, back).clamp(-1.0, 1.0).acos().to_degrees();
            assert!(angle < 1.0, "{n:?} -> {back:?}: {angle}");
        }
        // CesiumJS's own values for the axes.
        assert_eq!(oct_encode([0.0, 0.0, 1.0]), [128, 128]);
        assert_eq!(oct_encode([1.0, 0.0, 0.0]), [255, 128]);
        assert_eq!(oct_encode([0.0, 0.0, -1.0]), [255, 255]);
    }

    #[test]
    fn decode_rejects_every_truncation_and_survives_corruption() {
        let rect = GeoRect::tile(9, 560, 360);
        let bytes = encode(&rect, &mesh_from_grid(&grid(9, plane_and_bump), 9, 0));
        let extensions_start = bytes.len() - 5 - 2 * 81;
        for len in 0..bytes.len() {
            let result = decode(&bytes[..len]);
            if len == extensions_start {
                // A whole tile without extensions.
                assert_eq!(result.map(|d| d.normals), Ok(None));
            } else {
                assert!(result.is_err(), "a {len}-byte prefix decoded");
            }
        }
        assert!(decode(&bytes).is_ok());

        let mut rng = Rng(5);
        let mut decoded_anyway = 0;
        for round in 0..600 {
            let mut corrupt = bytes.clone();
            for _ in 0..1 + round % 4 {
                let at = (rng.next() % corrupt.len() as u64) as usize;
                corrupt[at] = rng.next() as u8;
            }
            if let Ok(tile) = decode(&corrupt) {
                decoded_anyway += 1;
                let _ = height_at(&tile, &rect, rect.west, rect.south);
            }
        }
        assert!(decoded_anyway < 600);
        // Counts made huge, and random bytes.
        for at in [HEADER_LEN, HEADER_LEN + 4 + 6 * 81] {
            let mut corrupt = bytes.clone();
            corrupt[at..at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
            assert!(decode(&corrupt).is_err());
        }
        for len in [0, 1, 50, 88, 92, 200, 5000] {
            let noise: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
            let _ = decode(&noise);
        }
    }
}
