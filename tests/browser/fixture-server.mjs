#!/usr/bin/env node
// A stand-in for the terrain server, for developing and debugging the browser side
// (viewer/ and tests/browser/check.mjs) without it. No dependencies beyond node itself.
//
//   node tests/browser/fixture-server.mjs [--port 0] [--host 127.0.0.1] [--log] [--fail REGEX]
//        [--terrain-encoding auto|identity|gzip-without-header]
//
//   --fail REGEX        request paths matching REGEX answer 404 (to see the clients report it)
//   --terrain-encoding  how .terrain bodies go out: auto (default) gzips them with
//                       Content-Encoding: gzip when the request accepts gzip; identity never
//                       compresses; gzip-without-header imitates a broken server
//
// prints "fixture-server listening on http://127.0.0.1:PORT" and serves:
//   /view/...                          viewer/dist/ (run viewer/setup.sh first)
//   /v1/terrarium.json                 TileJSON 3.0.0, raster-dem, encoding "terrarium"
//   /v1/terrain-rgb.json               the same with encoding "mapbox"
//   /v1/fixture1/terrarium/{z}/{x}/{y}.png     Terrarium PNGs of surfaceHeight() (zooms 0..12)
//   /v1/fixture1/terrain-rgb/{z}/{x}/{y}.png   Mapbox Terrain-RGB PNGs of the same surface
//   /v1/texture.json, /v1/fixture1/texture/{z}/{x}/{y}.png   solid-colour texture tiles
//   /v1/cesium/layer.json              quantized-mesh-1.0 layer (levels 0..14)
//   /v1/fixture1/cesium/{z}/{x}/{y}.terrain   quantized-mesh tiles of planeHeight() (TMS
//                                      rows, octvertexnormals when asked, gzip when accepted;
//                                      a query answers 400, as the terrain server does)
//   (tile paths without the "fixture1/" content-version segment work too)
//   /fixture/terrarium.pmtiles         a PMTiles v3 archive of the Terrarium pyramid
//                                      (HTTP Range requests answered with 206)
//   /fixture/stats                     request counts by status, and the URLs that failed
// Tiles outside BOUNDS answer 404 (a client that honours the TileJSON's bounds never asks).
//
// The MapLibre surface is h = 500 + 300 sin(40 lon) cos(40 lat) (lon, lat in degrees, the
// product in radians); Cesium's is a plane (clamped to a box around BOUNDS) whose triangle
// interpolation is exact, so sampleTerrainMostDetailed must return planeHeight() exactly.

import http from 'node:http';
import fs from 'node:fs';
import path from 'node:path';
import zlib from 'node:zlib';
import { fileURLToPath } from 'node:url';

const HERE = path.dirname(fileURLToPath(import.meta.url));
export const DIST = path.resolve(HERE, '../../viewer/dist');

export const BOUNDS = [11.30, 47.20, 11.50, 47.30]; // w, s, e, n
export const CENTER = [11.40, 47.25, 12];
export const MAXZOOM = 12;        // raster-dem and texture pyramids: 0..MAXZOOM
export const QM_MAXZOOM = 14;     // quantized-mesh levels: 0..QM_MAXZOOM
export const CONTENT_VERSION = 'fixture1'; // in tile paths, like the server's content version

export function surfaceHeight(lon, lat) {
  return 500 + 300 * Math.sin(lon * 40) * Math.cos(lat * 40);
}

const clamp = (v, lo, hi) => Math.min(hi, Math.max(lo, v));
export function planeHeight(lon, lat) {
  return 400 + 1000 * clamp(lon - 11.4, -0.15, 0.15) + 600 * clamp(lat - 47.25, -0.1, 0.1);
}

// ---------------------------------------------------------------------------------------
// PNG (8-bit RGB, no interlace)
const CRC_TABLE = (() => {
  const t = new Uint32Array(256);
  for (let n = 0; n < 256; n++) {
    let c = n;
    for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
    t[n] = c >>> 0;
  }
  return t;
})();
function crc32(buf) {
  let c = 0xffffffff;
  for (let i = 0; i < buf.length; i++) c = CRC_TABLE[(c ^ buf[i]) & 0xff] ^ (c >>> 8);
  return (c ^ 0xffffffff) >>> 0;
}
function pngChunk(type, data) {
  const len = Buffer.alloc(4);
  len.writeUInt32BE(data.length);
  const td = Buffer.concat([Buffer.from(type, 'ascii'), data]);
  const crc = Buffer.alloc(4);
  crc.writeUInt32BE(crc32(td));
  return Buffer.concat([len, td, crc]);
}
export function encodePNG(width, height, rgb) {
  const raw = Buffer.alloc((width * 3 + 1) * height);
  for (let y = 0; y < height; y++) {
    raw[y * (width * 3 + 1)] = 0; // filter: none
    rgb.copy(raw, y * (width * 3 + 1) + 1, y * width * 3, (y + 1) * width * 3);
  }
  const ihdr = Buffer.alloc(13);
  ihdr.writeUInt32BE(width, 0);
  ihdr.writeUInt32BE(height, 4);
  ihdr[8] = 8; ihdr[9] = 2; ihdr[10] = 0; ihdr[11] = 0; ihdr[12] = 0;
  return Buffer.concat([
    Buffer.from([0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a]),
    pngChunk('IHDR', ihdr),
    pngChunk('IDAT', zlib.deflateSync(raw, { level: 6 })),
    pngChunk('IEND', Buffer.alloc(0)),
  ]);
}

// ---------------------------------------------------------------------------------------
// Web Mercator XYZ
const tileLon = (x, z) => (x / 2 ** z) * 360 - 180;
const tileLat = (y, z) => (Math.atan(Math.sinh(Math.PI * (1 - (2 * y) / 2 ** z))) * 180) / Math.PI;
const lonX = (lon, z) => ((lon + 180) / 360) * 2 ** z;
const latY = (lat, z) => {
  const s = Math.sin((lat * Math.PI) / 180);
  return (0.5 - Math.log((1 + s) / (1 - s)) / (4 * Math.PI)) * 2 ** z;
};
export function mercatorTileInBounds(z, x, y, b = BOUNDS) {
  if (z < 0 || z > MAXZOOM || x < 0 || y < 0 || x >= 2 ** z || y >= 2 ** z) return false;
  return x >= Math.floor(lonX(b[0], z)) && x < Math.ceil(lonX(b[2], z)) &&
         y >= Math.floor(latY(b[3], z)) && y < Math.ceil(latY(b[1], z));
}
export function mercatorTilesInBounds(z, b = BOUNDS) {
  const out = [];
  for (let x = Math.floor(lonX(b[0], z)); x < Math.ceil(lonX(b[2], z)); x++)
    for (let y = Math.floor(latY(b[3], z)); y < Math.ceil(latY(b[1], z)); y++) out.push([x, y]);
  return out;
}

const demCache = new Map();
// encoding: 'terrarium' | 'mapbox'. Heights are sampled at pixel centres (MapLibre's reading).
export function demTile(encoding, z, x, y) {
  const key = `${encoding}/${z}/${x}/${y}`;
  let png = demCache.get(key);
  if (png) return png;
  const N = 256;
  const rgb = Buffer.alloc(N * N * 3);
  for (let j = 0; j < N; j++) {
    const lat = tileLat(y + (j + 0.5) / N, z);
    for (let i = 0; i < N; i++) {
      const lon = tileLon(x + (i + 0.5) / N, z);
      const h = surfaceHeight(lon, lat);
      const v = encoding === 'terrarium'
        ? Math.round((h + 32768) * 256)   // R*256 + G + B/256 - 32768
        : Math.round((h + 10000) * 10);   // (R*65536 + G*256 + B) / 10 - 10000
      const o = (j * N + i) * 3;
      rgb[o] = (v >> 16) & 255; rgb[o + 1] = (v >> 8) & 255; rgb[o + 2] = v & 255;
    }
  }
  png = encodePNG(N, N, rgb);
  demCache.set(key, png);
  return png;
}

const PALETTE = [[199, 214, 160], [222, 205, 160], [176, 200, 170], [214, 190, 150]];
const texCache = new Map();
export function textureTile(z, x, y) {
  const key = `${z}/${x}/${y}`;
  let png = texCache.get(key);
  if (png) return png;
  const c = PALETTE[(x + y) % 2 + 2 * (z % 2)];
  const rgb = Buffer.alloc(256 * 256 * 3);
  for (let p = 0; p < 256 * 256; p++) { rgb[p * 3] = c[0]; rgb[p * 3 + 1] = c[1]; rgb[p * 3 + 2] = c[2]; }
  png = encodePNG(256, 256, rgb);
  texCache.set(key, png);
  return png;
}

// ---------------------------------------------------------------------------------------
// PMTiles v3 (https://github.com/protomaps/PMTiles/blob/main/spec/v3/spec.md)
export function zxyToTileId(z, x, y) {
  let acc = 0;
  for (let i = 0; i < z; i++) acc += 4 ** i;
  const n = 2 ** z;
  let tx = x, ty = y, d = 0;
  for (let s = n / 2; s >= 1; s /= 2) {
    const rx = (tx & s) > 0 ? 1 : 0;
    const ry = (ty & s) > 0 ? 1 : 0;
    d += s * s * ((3 * rx) ^ ry);
    if (ry === 0) {               // rotate (in the s x s quadrant frame, as the reference does)
      if (rx === 1) { tx = s - 1 - (tx % s); ty = s - 1 - (ty % s); } else { tx %= s; ty %= s; }
      const t = tx; tx = ty; ty = t;
    } else { tx %= s; ty %= s; }
  }
  return acc + d;
}
function varint(n, out) {
  while (n >= 128) { out.push((n % 128) | 128); n = Math.floor(n / 128); }
  out.push(n);
}
export function buildPMTiles(encoding = 'terrarium') {
  const entries = [];
  for (let z = 0; z <= MAXZOOM; z++)
    for (const [x, y] of mercatorTilesInBounds(z)) entries.push({ id: zxyToTileId(z, x, y), data: demTile(encoding, z, x, y) });
  entries.sort((a, b) => a.id - b.id);
  let off = 0;
  for (const e of entries) { e.offset = off; e.length = e.data.length; off += e.length; }
  const dir = [];
  varint(entries.length, dir);
  let last = 0;
  for (const e of entries) { varint(e.id - last, dir); last = e.id; }
  for (const e of entries) varint(1, dir);          // run lengths
  for (const e of entries) varint(e.length, dir);
  entries.forEach((e, i) => {
    if (i > 0 && e.offset === entries[i - 1].offset + entries[i - 1].length) varint(0, dir);
    else varint(e.offset + 1, dir);
  });
  const rootDir = zlib.gzipSync(Buffer.from(dir));
  const meta = zlib.gzipSync(Buffer.from(JSON.stringify({
    name: 'fixture terrarium', format: 'png', type: 'baselayer', encoding,
    description: 'tests/browser/fixture-server.mjs', vector_layers: [],
  })));
  const tileData = Buffer.concat(entries.map((e) => e.data));
  const h = Buffer.alloc(127);
  h.write('PMTiles', 0, 'ascii');
  h[7] = 3;
  const u64 = (v, at) => h.writeBigUInt64LE(BigInt(v), at);
  const rootOff = 127, metaOff = rootOff + rootDir.length, dataOff = metaOff + meta.length;
  u64(rootOff, 8); u64(rootDir.length, 16);
  u64(metaOff, 24); u64(meta.length, 32);
  u64(dataOff + tileData.length, 40); u64(0, 48);   // no leaf directories
  u64(dataOff, 56); u64(tileData.length, 64);
  u64(entries.length, 72); u64(entries.length, 80); u64(entries.length, 88);
  h[96] = 1;      // clustered
  h[97] = 2;      // internal compression: gzip
  h[98] = 1;      // tile compression: none
  h[99] = 2;      // tile type: png
  h[100] = 0; h[101] = MAXZOOM;
  h.writeInt32LE(Math.round(BOUNDS[0] * 1e7), 102);
  h.writeInt32LE(Math.round(BOUNDS[1] * 1e7), 106);
  h.writeInt32LE(Math.round(BOUNDS[2] * 1e7), 110);
  h.writeInt32LE(Math.round(BOUNDS[3] * 1e7), 114);
  h[118] = CENTER[2];
  h.writeInt32LE(Math.round(CENTER[0] * 1e7), 119);
  h.writeInt32LE(Math.round(CENTER[1] * 1e7), 123);
  if (127 + rootDir.length > 16384) throw new Error('root directory too big for one 16 KiB read');
  return Buffer.concat([h, rootDir, meta, tileData]);
}

// ---------------------------------------------------------------------------------------
// quantized-mesh-1.0 (https://github.com/CesiumGS/quantized-mesh), geographic tiling scheme:
// level z has 2^(z+1) x 2^z tiles, x from -180, y (TMS) from -90.
const WGS84_A = 6378137.0;
const WGS84_B = 6356752.3142451793;
const E2 = 1 - (WGS84_B * WGS84_B) / (WGS84_A * WGS84_A);
function ecef(lonDeg, latDeg, h) {
  const lon = (lonDeg * Math.PI) / 180, lat = (latDeg * Math.PI) / 180;
  const s = Math.sin(lat), c = Math.cos(lat);
  const n = WGS84_A / Math.sqrt(1 - E2 * s * s);
  return [(n + h) * c * Math.cos(lon), (n + h) * c * Math.sin(lon), (n * (1 - E2) + h) * s];
}
export function qmTileRect(z, x, y) {
  const size = 180 / 2 ** z;
  return [-180 + x * size, -90 + y * size, -180 + (x + 1) * size, -90 + (y + 1) * size];
}
function qmRange(z, b = BOUNDS) {
  if (z === 0) return { startX: 0, startY: 0, endX: 1, endY: 0 };
  const size = 180 / 2 ** z;
  return {
    startX: Math.floor((b[0] + 180) / size), endX: Math.floor((b[2] + 180) / size),
    startY: Math.floor((b[1] + 90) / size), endY: Math.floor((b[3] + 90) / size),
  };
}
export function qmAvailable(z, x, y) {
  if (z < 0 || z > QM_MAXZOOM) return false;
  const r = qmRange(z);
  return x >= r.startX && x <= r.endX && y >= r.startY && y <= r.endY;
}
export function layerJson() {
  const available = [];
  for (let z = 0; z <= QM_MAXZOOM; z++) available.push([qmRange(z)]);
  return {
    tilejson: '2.1.0',
    name: 'fixture',
    description: 'tests/browser/fixture-server.mjs: a clamped plane',
    version: '1.0.0',
    format: 'quantized-mesh-1.0',
    scheme: 'tms',
    // an absolute path without a query, as the terrain server writes it
    tiles: [`/v1/${CONTENT_VERSION}/cesium/{z}/{x}/{y}.terrain`],
    projection: 'EPSG:4326',
    minzoom: 0,
    maxzoom: QM_MAXZOOM,
    bounds: BOUNDS,
    extensions: ['octvertexnormals'],
    available,
    max_error_m: Array.from({ length: QM_MAXZOOM + 1 }, (_, z) => 77067.34 / 2 ** z / 16),
  };
}

// Cesium's EllipsoidalOccluder.computeHorizonCullingPoint, in the ellipsoid-scaled frame.
function horizonOcclusionPoint(center, points) {
  const scale = (p) => [p[0] / WGS84_A, p[1] / WGS84_A, p[2] / WGS84_B];
  const norm = (v) => Math.hypot(v[0], v[1], v[2]);
  const sc = scale(center);
  const dl = norm(sc);
  const d = [sc[0] / dl, sc[1] / dl, sc[2] / dl];
  let best = 0;
  for (const p of points) {
    const sp = scale(p);
    let m2 = sp[0] ** 2 + sp[1] ** 2 + sp[2] ** 2;
    let m = Math.sqrt(m2);
    const dir = [sp[0] / m, sp[1] / m, sp[2] / m];
    m2 = Math.max(1, m2); m = Math.max(1, m);
    const cosA = dir[0] * d[0] + dir[1] * d[1] + dir[2] * d[2];
    const cr = [dir[1] * d[2] - dir[2] * d[1], dir[2] * d[0] - dir[0] * d[2], dir[0] * d[1] - dir[1] * d[0]];
    const sinA = norm(cr);
    const cosB = 1 / m;
    const sinB = Math.sqrt(m2 - 1) * cosB;
    const cand = 1 / (cosA * cosB - sinA * sinB);
    if (!(cand > 0)) return [d[0] * 1e3, d[1] * 1e3, d[2] * 1e3]; // tile too big: "far away"
    best = Math.max(best, cand);
  }
  return [d[0] * best, d[1] * best, d[2] * best];
}
function octEncode(v) {
  const l1 = Math.abs(v[0]) + Math.abs(v[1]) + Math.abs(v[2]);
  let x = v[0] / l1, y = v[1] / l1;
  if (v[2] < 0) {
    const ox = x, oy = y;
    x = (1 - Math.abs(oy)) * (ox >= 0 ? 1 : -1);
    y = (1 - Math.abs(ox)) * (oy >= 0 ? 1 : -1);
  }
  const snorm = (f) => Math.round((clamp(f, -1, 1) * 0.5 + 0.5) * 255);
  return [snorm(x), snorm(y)];
}
const zigzag = (n) => ((n << 1) ^ (n >> 31)) >>> 0;

const GRID = 17;
export function quantizedMeshTile(z, x, y, withNormals) {
  const [w, s, e, n] = qmTileRect(z, x, y);
  // vertices of a GRID x GRID lattice; triangles row by row
  const verts = [];
  for (let j = 0; j < GRID; j++)
    for (let i = 0; i < GRID; i++) {
      const u = Math.round((i * 32767) / (GRID - 1)), v = Math.round((j * 32767) / (GRID - 1));
      const lon = w + ((e - w) * u) / 32767, lat = s + ((n - s) * v) / 32767;
      verts.push({ u, v, lon, lat, h: planeHeight(lon, lat) });
    }
  const tris = [];
  for (let j = 0; j < GRID - 1; j++)
    for (let i = 0; i < GRID - 1; i++) {
      const a = j * GRID + i, b = a + 1, c = a + GRID, d = c + 1;
      tris.push(a, b, d, a, d, c);
    }
  // renumber the vertices in order of first use (what high-water-mark coding needs)
  const remap = new Map();
  const order = [];
  for (const t of tris) if (!remap.has(t)) { remap.set(t, order.length); order.push(t); }
  const V = order.map((k) => verts[k]);
  const idx = tris.map((t) => remap.get(t));

  let minH = Infinity, maxH = -Infinity;
  for (const v of V) { minH = Math.min(minH, v.h); maxH = Math.max(maxH, v.h); }
  const span = maxH - minH > 1e-6 ? maxH - minH : 1;
  const hq = V.map((v) => Math.round(((v.h - minH) / span) * 32767));

  const center = ecef((w + e) / 2, (s + n) / 2, (minH + maxH) / 2);
  const pts = V.map((v) => ecef(v.lon, v.lat, v.h));
  let radius = 0;
  for (const p of pts) radius = Math.max(radius, Math.hypot(p[0] - center[0], p[1] - center[1], p[2] - center[2]));
  const hop = horizonOcclusionPoint(center, pts);

  const parts = [];
  const hdr = Buffer.alloc(88);
  hdr.writeDoubleLE(center[0], 0); hdr.writeDoubleLE(center[1], 8); hdr.writeDoubleLE(center[2], 16);
  hdr.writeFloatLE(minH, 24); hdr.writeFloatLE(maxH, 28);
  hdr.writeDoubleLE(center[0], 32); hdr.writeDoubleLE(center[1], 40); hdr.writeDoubleLE(center[2], 48);
  hdr.writeDoubleLE(radius, 56);
  hdr.writeDoubleLE(hop[0], 64); hdr.writeDoubleLE(hop[1], 72); hdr.writeDoubleLE(hop[2], 80);
  parts.push(hdr);

  const nv = V.length;
  const vd = Buffer.alloc(4 + nv * 6);
  vd.writeUInt32LE(nv, 0);
  const enc = (vals, at) => {
    let prev = 0;
    vals.forEach((val, k) => { vd.writeUInt16LE(zigzag(val - prev), at + k * 2); prev = val; });
  };
  enc(V.map((v) => v.u), 4);
  enc(V.map((v) => v.v), 4 + nv * 2);
  enc(hq, 4 + nv * 4);
  parts.push(vd);
  // 16-bit indices (nv <= 65536); the vertex data ends 2-byte aligned already
  const td = Buffer.alloc(4 + idx.length * 2);
  td.writeUInt32LE(idx.length / 3, 0);
  let highest = 0;
  idx.forEach((k, m) => {
    const code = highest - k;
    td.writeUInt16LE(code, 4 + m * 2);
    if (code === 0) highest++;
  });
  parts.push(td);
  const edge = (pred, key) => {
    const list = V.map((v, k) => [v, k]).filter(([v]) => pred(v)).sort((a, b) => key(a[0]) - key(b[0])).map(([, k]) => k);
    const b = Buffer.alloc(4 + list.length * 2);
    b.writeUInt32LE(list.length, 0);
    list.forEach((k, m) => b.writeUInt16LE(k, 4 + m * 2));
    return b;
  };
  parts.push(edge((v) => v.u === 0, (v) => v.v));        // west
  parts.push(edge((v) => v.v === 0, (v) => v.u));        // south
  parts.push(edge((v) => v.u === 32767, (v) => v.v));    // east
  parts.push(edge((v) => v.v === 32767, (v) => v.u));    // north
  if (withNormals) {
    // the ellipsoid's normal (the plane's slope is ignored: this is a fixture)
    const nb = Buffer.alloc(5 + nv * 2);
    nb[0] = 1; nb.writeUInt32LE(nv * 2, 1);
    V.forEach((v, k) => {
      const lo = (v.lon * Math.PI) / 180, la = (v.lat * Math.PI) / 180;
      const [ox, oy] = octEncode([Math.cos(la) * Math.cos(lo), Math.cos(la) * Math.sin(lo), Math.sin(la)]);
      nb[5 + k * 2] = ox; nb[6 + k * 2] = oy;
    });
    parts.push(nb);
  }
  return Buffer.concat(parts);
}

// ---------------------------------------------------------------------------------------
// HTTP
const TYPES = {
  '.html': 'text/html; charset=utf-8', '.js': 'text/javascript; charset=utf-8',
  '.mjs': 'text/javascript; charset=utf-8', '.css': 'text/css; charset=utf-8',
  '.json': 'application/json', '.png': 'image/png', '.jpg': 'image/jpeg', '.jpeg': 'image/jpeg',
  '.gif': 'image/gif', '.svg': 'image/svg+xml', '.wasm': 'application/wasm',
  '.xml': 'application/xml', '.txt': 'text/plain; charset=utf-8',
};

// fail: a RegExp (or its source); matching request paths answer 404 (to see the client's
// error reporting work).
// terrainEncoding: 'auto' (gzip with Content-Encoding when the request accepts it), 'identity'
// (never compressed), 'gzip-without-header' (a broken server: gzip bytes, no Content-Encoding).
export function startServer({ port = 0, host = '127.0.0.1', log = false, fail = null, terrainEncoding = 'auto' } = {}) {
  const failRe = fail ? new RegExp(fail) : null;
  const stats = { requests: 0, by_status: {}, failed: [] };
  let pmtilesBuf = null;
  const server = http.createServer((req, res) => {
    const url = new URL(req.url, `http://${req.headers.host || host}`);
    const origin = `http://${req.headers.host || `${host}:${server.address().port}`}`;
    const p = decodeURIComponent(url.pathname);
    stats.requests++;
    const send = (status, body, headers = {}) => {
      stats.by_status[status] = (stats.by_status[status] || 0) + 1;
      if (status >= 400) stats.failed.push(`${status} ${req.method} ${req.url}`);
      if (log) process.stderr.write(`${status} ${req.method} ${req.url}\n`);
      res.writeHead(status, { 'Access-Control-Allow-Origin': '*', 'Cache-Control': 'no-cache', ...headers });
      res.end(req.method === 'HEAD' ? undefined : body);
    };
    const json = (obj) => send(200, JSON.stringify(obj), { 'Content-Type': 'application/json' });
    const png = (buf) => send(200, buf, { 'Content-Type': 'image/png' });
    let m;
    try {
      if (failRe && failRe.test(p)) return send(404, 'failed on purpose (--fail)');
      if (req.method === 'OPTIONS') return send(204, '', { 'Access-Control-Allow-Headers': '*', 'Access-Control-Allow-Methods': 'GET, HEAD' });
      if (p === '/fixture/stats') return send(200, JSON.stringify(stats), { 'Content-Type': 'application/json' });
      if (p === '/' || p === '/view' || p === '/view/') return send(302, '', { Location: '/view/index.html' });
      if (p.startsWith('/view/')) {
        const rel = path.normalize(p.slice('/view/'.length));
        const file = path.join(DIST, rel);
        if (rel.startsWith('..') || !file.startsWith(DIST + path.sep)) return send(403, 'forbidden');
        let st;
        try { st = fs.statSync(file); } catch { return send(404, `not found: ${p} (did viewer/setup.sh run?)`); }
        if (!st.isFile()) return send(404, 'not a file');
        return send(200, fs.readFileSync(file), { 'Content-Type': TYPES[path.extname(file)] || 'application/octet-stream' });
      }
      if (p === '/v1/terrarium.json' || p === '/v1/terrain-rgb.json' || p === '/v1/texture.json') {
        const name = p.slice(4, -5);
        const tj = {
          tilejson: '3.0.0',
          name: `fixture ${name}`,
          tiles: [`${origin}/v1/${CONTENT_VERSION}/${name}/{z}/{x}/{y}.png`],
          minzoom: 0, maxzoom: MAXZOOM, bounds: BOUNDS, center: CENTER, tileSize: 256, scheme: 'xyz',
        };
        if (name === 'terrarium') tj.encoding = 'terrarium';
        if (name === 'terrain-rgb') tj.encoding = 'mapbox';
        return json(tj);
      }
      if ((m = /^\/v1\/(?:[A-Za-z0-9]+\/)?(terrarium|terrain-rgb|texture)\/(\d+)\/(\d+)\/(\d+)\.png$/.exec(p))) {
        const [z, x, y] = [+m[2], +m[3], +m[4]];
        if (!mercatorTileInBounds(z, x, y)) return send(404, 'tile outside the bounds');
        if (m[1] === 'texture') return png(textureTile(z, x, y));
        return png(demTile(m[1] === 'terrarium' ? 'terrarium' : 'mapbox', z, x, y));
      }
      if (p === '/v1/cesium/layer.json') return json(layerJson());
      if ((m = /^\/v1\/(?:[A-Za-z0-9]+\/)?cesium\/(\d+)\/(\d+)\/(\d+)\.terrain$/.exec(p))) {
        if (url.search) return send(400, 'no query on tile URLs (as the terrain server)');
        const [z, x, y] = [+m[1], +m[2], +m[3]];
        if (!qmAvailable(z, x, y)) return send(404, 'tile not available');
        const accept = req.headers.accept || '';
        const normals = /octvertexnormals/.test(accept);
        let body = quantizedMeshTile(z, x, y, normals);
        const headers = { 'Content-Type': 'application/vnd.quantized-mesh' + (normals ? ';extensions=octvertexnormals' : '') };
        if (terrainEncoding === 'gzip-without-header') {
          body = zlib.gzipSync(body);
        } else if (terrainEncoding === 'auto' && /\bgzip\b/.test(req.headers['accept-encoding'] || '')) {
          body = zlib.gzipSync(body);
          headers['Content-Encoding'] = 'gzip';
        }
        return send(200, body, headers);
      }
      if (p === '/fixture/terrarium.pmtiles') {
        if (!pmtilesBuf) pmtilesBuf = buildPMTiles('terrarium');
        const total = pmtilesBuf.length;
        const headers = { 'Content-Type': 'application/vnd.pmtiles', 'Accept-Ranges': 'bytes', ETag: '"fixture-1"' };
        const range = req.headers.range;
        if (!range) return send(200, pmtilesBuf, headers);
        const r = /^bytes=(\d*)-(\d*)$/.exec(range);
        if (!r) return send(416, '', { ...headers, 'Content-Range': `bytes */${total}` });
        let a, b;
        if (r[1] === '') { a = Math.max(0, total - Number(r[2])); b = total - 1; } else { a = Number(r[1]); b = r[2] === '' ? total - 1 : Math.min(Number(r[2]), total - 1); }
        if (a >= total || a > b) return send(416, '', { ...headers, 'Content-Range': `bytes */${total}` });
        return send(206, pmtilesBuf.subarray(a, b + 1), { ...headers, 'Content-Range': `bytes ${a}-${b}/${total}` });
      }
      return send(404, 'not found');
    } catch (e) {
      return send(500, String((e && e.stack) || e));
    }
  });
  return new Promise((resolve, reject) => {
    server.once('error', reject);
    server.listen(port, host, () => {
      const addr = server.address();
      resolve({ server, stats, url: `http://${host}:${addr.port}`, port: addr.port });
    });
  });
}

if (process.argv[1] && path.resolve(process.argv[1]) === fileURLToPath(import.meta.url)) {
  const args = process.argv.slice(2);
  const opt = (name, dflt) => { const i = args.indexOf(name); return i >= 0 ? args[i + 1] : dflt; };
  if (!fs.existsSync(path.join(DIST, 'index.html'))) {
    process.stderr.write(`warning: ${DIST}/index.html is missing: run viewer/setup.sh\n`);
  }
  const { url } = await startServer({
    port: Number(opt('--port', 0)), host: opt('--host', '127.0.0.1'), log: args.includes('--log'), fail: opt('--fail', null),
    terrainEncoding: opt('--terrain-encoding', 'auto'),
  });
  process.stdout.write(`fixture-server listening on ${url}\n`);
  process.stdout.write(`  MapLibre: ${url}/view/index.html?client=maplibre\n`);
  process.stdout.write(`  PMTiles:  ${url}/view/index.html?client=maplibre&source=pmtiles&pmtiles=${encodeURIComponent(url + '/fixture/terrarium.pmtiles')}\n`);
  process.stdout.write(`  Cesium:   ${url}/view/index.html?client=cesium\n`);
}
