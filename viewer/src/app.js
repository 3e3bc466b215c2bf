// The terrain viewer: MapLibre GL JS or CesiumJS on the server's own tiles.
//
// Served under /view/ by the terrain server (or tests/browser/fixture-server.mjs), with the
// data on the same origin:
//   /v1/terrarium.json, /v1/terrain-rgb.json   TileJSON 3.0.0 of raster-dem tiles
//   /v1/texture.json                           TileJSON of raster tiles
//   /v1/cesium/layer.json                      quantized-mesh layer (+ bounds, max_error_m)
//
// Query parameters:
//   client=maplibre|cesium          (default maplibre)
//   source=tilejson|pmtiles         MapLibre only; pmtiles needs pmtiles=<absolute .pmtiles URL>
//   dem=terrarium|terrain-rgb       MapLibre TileJSON to use (default terrarium)
//   texture=0                       no texture layer
//   hillshade=standard|basic|combined|igor|multidirectional   MapLibre hillshade method
//   lon, lat, zoom, pitch, bearing  MapLibre camera (degrees; pitch 0 = straight down)
//   lon, lat, height, heading, pitch  Cesium camera position (height in metres above the
//                                   ellipsoid; pitch -90 = straight down)
//   Without lon/lat the view fits the TileJSON's / layer.json's bounds.
//   status=0                        no status line (it is hidden anyway once ready)
//
// window.terrainTest (made in index.html) gets: ready, errors, elevations(points), info.

const T = window.terrainTest;
const note = T._note;
const info = T.info;
const params = new URLSearchParams(location.search);
const statusEl = document.getElementById('status');

function status(text) {
  if (statusEl) statusEl.textContent = text;
}
if (params.get('status') === '0' && statusEl) statusEl.classList.add('hidden');

function num(name) {
  const v = params.get(name);
  if (v === null || v.trim() === '') return undefined;
  const n = Number(v);
  if (!Number.isFinite(n)) throw new Error(`query parameter ${name}=${v} is not a number`);
  return n;
}

function abs(path) {
  return new URL(path, location.href).href;
}

// ---------------------------------------------------------------------------------------
// Failed requests made from this page's main thread (fetch and XMLHttpRequest). Requests
// made by workers are not seen here: the driver records every request at the browser.
info.requests = 0;
info.failed_requests = 0;
const realFetch = window.fetch.bind(window);
window.fetch = async function (input, init) {
  const url = typeof input === 'string' ? input : (input && input.url) || String(input);
  info.requests++;
  try {
    const resp = await realFetch(input, init);
    if (resp.status >= 400) {
      info.failed_requests++;
      note('fetch', `HTTP ${resp.status} for ${url}`, { url, status: resp.status });
    }
    return resp;
  } catch (e) {
    if (!(e && e.name === 'AbortError')) {
      info.failed_requests++;
      note('fetch', `${e && e.message} for ${url}`, { url });
    }
    throw e;
  }
};
const XHR = window.XMLHttpRequest;
const xhrOpen = XHR.prototype.open;
const xhrSend = XHR.prototype.send;
XHR.prototype.open = function (method, url, ...rest) {
  this.__url = String(url);
  return xhrOpen.call(this, method, url, ...rest);
};
XHR.prototype.send = function (...args) {
  info.requests++;
  this.addEventListener('load', () => {
    if (this.status >= 400) {
      info.failed_requests++;
      note('xhr', `HTTP ${this.status} for ${this.__url}`, { url: this.__url, status: this.status });
    }
  });
  this.addEventListener('error', () => {
    info.failed_requests++;
    note('xhr', `network error for ${this.__url}`, { url: this.__url });
  });
  return xhrSend.apply(this, args);
};

async function getJSON(url) {
  const resp = await fetch(url, { headers: { Accept: 'application/json' } });
  if (!resp.ok) throw new Error(`GET ${url}: HTTP ${resp.status}`);
  return resp.json();
}

function loadScript(src) {
  return new Promise((resolve, reject) => {
    const s = document.createElement('script');
    s.src = src;
    s.onload = () => resolve();
    s.onerror = () => reject(new Error(`could not load ${src}`));
    document.head.appendChild(s);
  });
}

function loadCSS(href) {
  return new Promise((resolve, reject) => {
    const l = document.createElement('link');
    l.rel = 'stylesheet';
    l.href = href;
    l.onload = () => resolve();
    l.onerror = () => reject(new Error(`could not load ${href}`));
    document.head.appendChild(l);
  });
}

function webglRenderer() {
  try {
    const c = document.createElement('canvas');
    const gl = c.getContext('webgl2') || c.getContext('webgl');
    if (!gl) return null;
    const ext = gl.getExtension('WEBGL_debug_renderer_info');
    const r = gl.getParameter(ext ? ext.UNMASKED_RENDERER_WEBGL : gl.RENDERER);
    const lose = gl.getExtension('WEBGL_lose_context');
    if (lose) lose.loseContext();
    return String(r);
  } catch (e) {
    return null;
  }
}

function validBounds(b) {
  return Array.isArray(b) && b.length === 4 && b.every(Number.isFinite) && b[0] < b[2] && b[1] < b[3];
}

// ---------------------------------------------------------------------------------------
// MapLibre GL JS
async function startMapLibre() {
  const maplibregl = await import('./maplibre-gl.js');
  await loadCSS(abs('maplibre-gl.css'));
  // The bundle would look for ./maplibre-gl-worker.mjs; setup.sh copies it as .js.
  maplibregl.setWorkerUrl(abs('maplibre-gl-worker.js'));
  info.maplibre_version = maplibregl.getVersion ? maplibregl.getVersion() : undefined;

  const source = params.get('source') || 'tilejson';
  const dem = params.get('dem') || 'terrarium';
  const withTexture = params.get('texture') !== '0';
  info.source = source;

  let demSource;
  let bounds;
  if (source === 'pmtiles') {
    const url = params.get('pmtiles');
    if (!url) throw new Error('source=pmtiles needs pmtiles=<absolute URL of a .pmtiles archive>');
    await loadScript(abs('pmtiles.js'));
    const protocol = new window.pmtiles.Protocol();
    maplibregl.addProtocol('pmtiles', protocol.tile);
    const archive = new window.pmtiles.PMTiles(url);
    protocol.add(archive);
    const h = await archive.getHeader();
    info.pmtiles_header = {
      minZoom: h.minZoom, maxZoom: h.maxZoom, tileType: h.tileType,
      tileCompression: h.tileCompression, numAddressedTiles: h.numAddressedTiles,
      bounds: [h.minLon, h.minLat, h.maxLon, h.maxLat], center: [h.centerLon, h.centerLat, h.centerZoom],
    };
    if (h.tileType !== 2 && h.tileType !== 4 && h.tileType !== 3) {
      note('pmtiles', `PMTiles tile type ${h.tileType} is not PNG (2), JPEG (3) or WebP (4)`);
    }
    bounds = [h.minLon, h.minLat, h.maxLon, h.maxLat];
    demSource = { type: 'raster-dem', url: 'pmtiles://' + url, encoding: 'terrarium', tileSize: 256 };
    info.encoding = 'terrarium';
  } else if (source === 'tilejson') {
    const name = dem === 'terrain-rgb' ? 'terrain-rgb' : 'terrarium';
    const tjUrl = abs(`/v1/${name}.json`);
    const tj = await getJSON(tjUrl);
    info.tilejson = { tiles: tj.tiles, minzoom: tj.minzoom, maxzoom: tj.maxzoom, bounds: tj.bounds,
                      encoding: tj.encoding, tileSize: tj.tileSize, tilejson: tj.tilejson };
    info.encoding = tj.encoding;
    if (!tj.encoding) note('tilejson', `${tjUrl} has no "encoding" (MapLibre would assume "mapbox")`);
    bounds = tj.bounds;
    // encoding comes from the TileJSON itself (MapLibre applies the TileJSON's "encoding").
    demSource = { type: 'raster-dem', url: tjUrl, tileSize: tj.tileSize || 256 };
  } else {
    throw new Error(`unknown source=${source} (tilejson or pmtiles)`);
  }

  const sources = {
    dem: demSource,
    'dem-hillshade': { ...demSource },
  };
  const layers = [{ id: 'background', type: 'background', paint: { 'background-color': '#d9d5c7' } }];
  if (withTexture) {
    sources.texture = { type: 'raster', url: abs('/v1/texture.json'), tileSize: 256 };
    layers.push({ id: 'texture', type: 'raster', source: 'texture', paint: { 'raster-opacity': 0.6 } });
  }
  layers.push({
    id: 'hillshade', type: 'hillshade', source: 'dem-hillshade',
    paint: { 'hillshade-method': params.get('hillshade') || 'standard', 'hillshade-exaggeration': 0.7, 'hillshade-shadow-color': '#3b3122',
             'hillshade-highlight-color': '#fffdf4', 'hillshade-accent-color': '#5a4b33' },
  });
  // Off the DEM the tiles hold the nearest edge's height, so the surface ends level with the
  // edge; a hillshade there would draw the edge's profile drawn out in streaks. Cover it
  // with the background's colour: what lies outside the bounds is plain ground.
  if (validBounds(bounds)) {
    const [w, s, e, n] = bounds;
    sources.outside = { type: 'geojson', data: { type: 'Feature', properties: {}, geometry: {
      type: 'Polygon',
      coordinates: [[[-180, -85.06], [180, -85.06], [180, 85.06], [-180, 85.06], [-180, -85.06]],
                    [[w, s], [w, n], [e, n], [e, s], [w, s]]] } } };
    layers.push({ id: 'outside', type: 'fill', source: 'outside',
                  paint: { 'fill-color': '#d9d5c7', 'fill-antialias': false } });
  }
  const style = { version: 8, sources, layers, terrain: { source: 'dem', exaggeration: 1 } };

  const lon = num('lon'), lat = num('lat');
  const opts = {
    container: 'map',
    style,
    attributionControl: false,
    maxPitch: 85,
    pitch: num('pitch') ?? 0,
    bearing: num('bearing') ?? 0,
    fadeDuration: 0,
    canvasContextAttributes: { preserveDrawingBuffer: true, antialias: false },
  };
  if (lon !== undefined && lat !== undefined) {
    opts.center = [lon, lat];
    opts.zoom = num('zoom') ?? 12;
  } else if (validBounds(bounds)) {
    opts.bounds = [[bounds[0], bounds[1]], [bounds[2], bounds[3]]];
    opts.fitBoundsOptions = { padding: 20 };
    if (num('zoom') !== undefined) note('params', 'zoom is ignored without lon and lat');
  } else {
    note('bounds', `no usable bounds (${JSON.stringify(bounds)}) and no lon/lat: the view is the whole world`);
    opts.center = [0, 0];
    opts.zoom = num('zoom') ?? 1;
  }

  const map = new maplibregl.Map(opts);
  window.map = map;
  info.tiles_loaded = {};
  info.tile_errors = 0;
  map.on('error', (e) => {
    const err = e && e.error;
    const msg = (err && (err.message || String(err))) || 'map error';
    const extra = { sourceId: e.sourceId };
    if (err && err.status) extra.status = err.status;
    if (err && err.url) extra.url = err.url;
    if (e.tile) {
      info.tile_errors++;
      const c = e.tile.tileID && e.tile.tileID.canonical;
      if (c) extra.tile = `${c.z}/${c.x}/${c.y}`;
    }
    note('maplibre', msg, extra);
  });
  map.on('data', (e) => {
    if (e.dataType === 'source' && e.tile && e.sourceId) {
      info.tiles_loaded[e.sourceId] = (info.tiles_loaded[e.sourceId] || 0) + 1;
    }
  });

  await new Promise((resolve, reject) => {
    map.once('load', resolve);
    // an error before 'load' that is not about a source or tile (the style itself) is fatal
    const onError = (e) => {
      if (map.loaded()) { map.off('error', onError); return; }
      if (!(e && (e.sourceId || e.tile))) { map.off('error', onError); reject((e && e.error) || new Error('style error')); }
    };
    map.on('error', onError);
  });
  info.loaded_ms = Math.round(performance.now());

  // ready: an 'idle' with the terrain's source loaded (idle also fires when tiles failed:
  // those failures are in errors[]).
  await new Promise((resolve) => {
    const check = () => {
      const ok = map.isSourceLoaded('dem') && map.areTilesLoaded() && !!map.terrain;
      if (ok) { map.off('idle', check); resolve(); }
    };
    map.on('idle', check);
    map.triggerRepaint();
  });

  const exaggeration = () => {
    const t = map.getTerrain && map.getTerrain();
    return (t && t.exaggeration) || 1;
  };
  T.elevations = async (points) => points.map((p) => {
    const ll = new maplibregl.LngLat(p.lon, p.lat);
    let h = map.queryTerrainElevation(ll);
    if (h === null || h === undefined || !Number.isFinite(h)) return null;
    // queryTerrainElevation answers 0 where no DEM tile is loaded: tell that apart.
    const terrain = map.terrain;
    if (terrain && typeof terrain.getElevationAndDEMStateForLngLat === 'function') {
      const z = (map.transform && map.transform.tileZoom) ??
                (map._camera && map._camera.projectedCamera && map._camera.projectedCamera.tileZoom) ??
                Math.floor(map.getZoom());
      try {
        const st = terrain.getElevationAndDEMStateForLngLat(ll, z);
        if (st && st.demState !== 'loaded') return null;
      } catch (e) { /* internal API changed: keep the public answer */ }
    }
    return h / exaggeration();
  });

  info.client = 'maplibre';
  info.zoom = map.getZoom();
  info.center = map.getCenter().toArray();
  info.pitch = map.getPitch();
  info.bearing = map.getBearing();
  info.bounds = bounds;
}

// ---------------------------------------------------------------------------------------
// CesiumJS
async function startCesium() {
  window.CESIUM_BASE_URL = abs('cesium/');
  await loadCSS(abs('cesium/Widgets/widgets.css'));
  await loadScript(abs('cesium/Cesium.js'));
  const Cesium = window.Cesium;
  info.cesium_version = Cesium.VERSION;

  const terrainUrl = abs('/v1/cesium/');
  const layer = await getJSON(terrainUrl + 'layer.json');
  info.layer = { bounds: layer.bounds, maxzoom: layer.maxzoom, minzoom: layer.minzoom,
                 extensions: layer.extensions, max_error_m: layer.max_error_m, format: layer.format };

  let provider;
  try {
    provider = await Cesium.CesiumTerrainProvider.fromUrl(terrainUrl, { requestVertexNormals: true });
  } catch (e) {
    throw new Error(`CesiumTerrainProvider.fromUrl(${terrainUrl}): ${e && (e.message || e)}`);
  }
  info.has_vertex_normals = provider.hasVertexNormals;
  info.tiles_failed = 0;
  provider.errorEvent.addEventListener((err) => {
    info.tiles_failed++;
    note('cesium-terrain', (err && err.message) || 'terrain tile error',
         { x: err && err.x, y: err && err.y, level: err && err.level });
  });

  const viewer = new Cesium.Viewer('map', {
    baseLayer: false,
    baseLayerPicker: false,
    geocoder: false,
    timeline: false,
    animation: false,
    homeButton: false,
    sceneModePicker: false,
    navigationHelpButton: false,
    fullscreenButton: false,
    infoBox: false,
    selectionIndicator: false,
    vrButton: false,
    skyBox: false,
    skyAtmosphere: false,
    shadows: false,
    terrainProvider: provider,
    requestRenderMode: false,
    contextOptions: { webgl: { preserveDrawingBuffer: true, alpha: false } },
  });
  window.viewer = viewer;
  const scene = viewer.scene;
  const globe = scene.globe;
  scene.fog.enabled = false;
  if (scene.sun) scene.sun.show = false;
  if (scene.moon) scene.moon.show = false;
  if (scene.skyAtmosphere) scene.skyAtmosphere.show = false;
  globe.showGroundAtmosphere = false;
  globe.enableLighting = false;
  globe.baseColor = Cesium.Color.fromCssColorString('#d9d5c7');
  scene.backgroundColor = Cesium.Color.fromCssColorString('#1d2126');
  // no credits box over the picture (the data is ours; Cesium's own logo is kept small)
  viewer.cesiumWidget.creditContainer.style.display = 'none';

  scene.renderError.addEventListener((_scene, e) => {
    note('cesium-render', (e && (e.stack || e.message)) || String(e));
  });

  // texture imagery, Web Mercator XYZ from texture.json
  if (params.get('texture') !== '0') {
    const tj = await getJSON(abs('/v1/texture.json'));
    const tiles = tj.tiles && tj.tiles[0];
    if (!tiles) {
      note('tilejson', '/v1/texture.json has no tiles');
    } else {
      const ip = new Cesium.UrlTemplateImageryProvider({
        url: tiles,
        tilingScheme: new Cesium.WebMercatorTilingScheme(),
        minimumLevel: 0,
        maximumLevel: Number.isFinite(tj.maxzoom) ? tj.maxzoom : undefined,
        rectangle: validBounds(tj.bounds) ? Cesium.Rectangle.fromDegrees(...tj.bounds) : undefined,
        tileWidth: tj.tileSize || 256,
        tileHeight: tj.tileSize || 256,
      });
      info.imagery_failed = 0;
      ip.errorEvent.addEventListener((err) => {
        info.imagery_failed++;
        note('cesium-imagery', (err && err.message) || 'imagery tile error',
             { x: err && err.x, y: err && err.y, level: err && err.level });
      });
      const l = viewer.imageryLayers.addImageryProvider(ip);
      l.alpha = 0.85;
    }
  }

  // camera
  const bounds = validBounds(layer.bounds) ? layer.bounds : null;
  const lon = num('lon'), lat = num('lat'), height = num('height');
  const heading = Cesium.Math.toRadians(num('heading') ?? 0);
  const pitch = Cesium.Math.toRadians(num('pitch') ?? -90);
  if (lon !== undefined && lat !== undefined) {
    viewer.camera.setView({
      destination: Cesium.Cartesian3.fromDegrees(lon, lat, height ?? 5000),
      orientation: { heading, pitch, roll: 0 },
    });
  } else if (bounds) {
    if (height !== undefined) {
      viewer.camera.setView({
        destination: Cesium.Cartesian3.fromDegrees((bounds[0] + bounds[2]) / 2, (bounds[1] + bounds[3]) / 2, height),
        orientation: { heading, pitch, roll: 0 },
      });
    } else {
      viewer.camera.setView({ destination: Cesium.Rectangle.fromDegrees(...bounds) });
    }
  } else {
    note('bounds', `layer.json has no usable bounds (${JSON.stringify(layer.bounds)})`);
  }

  // ready: globe.tilesLoaded on two frames in a row, after the globe has had work to do
  info.frames = 0;
  let sawWork = false;
  globe.tileLoadProgressEvent.addEventListener((n) => { if (n > 0) sawWork = true; });
  await new Promise((resolve) => {
    let streak = 0;
    const remove = scene.postRender.addEventListener(() => {
      info.frames++;
      streak = globe.tilesLoaded ? streak + 1 : 0;
      if (streak >= 2 && (sawWork || info.frames > 120)) {
        remove();
        resolve();
      }
    });
  });

  T.elevations = async (points) => {
    const carto = points.map((p) => Cesium.Cartographic.fromDegrees(p.lon, p.lat));
    const out = await Cesium.sampleTerrainMostDetailed(provider, carto);
    return out.map((c) => (c && Number.isFinite(c.height) ? c.height : null));
  };

  info.client = 'cesium';
  const c = viewer.camera.positionCartographic;
  info.camera = { lon: Cesium.Math.toDegrees(c.longitude), lat: Cesium.Math.toDegrees(c.latitude),
                  height: c.height, heading: Cesium.Math.toDegrees(viewer.camera.heading),
                  pitch: Cesium.Math.toDegrees(viewer.camera.pitch) };
  info.bounds = bounds;
}

// ---------------------------------------------------------------------------------------
async function main() {
  const t0 = performance.now();
  info.renderer = webglRenderer();
  const client = params.get('client') || 'maplibre';
  status(`${client}: loading…`);
  if (client === 'maplibre') await startMapLibre();
  else if (client === 'cesium') await startCesium();
  else throw new Error(`unknown client=${client} (maplibre or cesium)`);
  info.ready_ms = Math.round(performance.now() - t0);
  status(`${client}: ready in ${(info.ready_ms / 1000).toFixed(1)} s, ${T.errors.length} errors`);
  if (statusEl) statusEl.classList.add('hidden');
}

main().then(
  () => T._settle.resolve(),
  (e) => {
    const msg = (e && (e.message || String(e))) || 'failed';
    note('fatal', (e && e.stack) || msg);
    info.fatal = msg;
    status(`failed: ${msg}`);
    T._settle.reject(e instanceof Error ? e : new Error(msg));
  },
);
