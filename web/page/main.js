// The page around the wasm client (terrain_web): the canvas, the animation loop, the
// controls and the overlay. Everything the client decides happens in the wasm module.
//
// URL parameters (all optional): server (default: this page's origin), mode (fly | flight),
// memory (e.g. 64MiB), limit_percent, fps (target frame rate), fixed_budget, method, filler,
// width and height (the canvas in pixels; default: the window), flight_fps, wall_clock=1 (the
// flight by the page's clock), loop=1 (the flight again at its end), ui=0 (no overlay or
// controls), paused=1 (wait for runTo or resume).
//
// window.terrainClient is what a driver (the headless tests) reads: `ready` (a promise),
// `errors`, `history` (one entry a frame: the figures the overlay shows, the wasm heap),
// `runTo(frame)` (draws until that frame is presented, then pauses), `resume()`,
// `runFor(seconds)` (draws freely that long, then pauses) and `last`.
import init, { Client } from './pkg/terrain_web.js';

const params = new URLSearchParams(location.search);
const $ = id => document.getElementById(id);
const canvas = $('terrain'), overlay = $('overlay'), errorBox = $('error');

if (params.get('ui') === '0') { overlay.style.display = 'none'; $('controls').style.display = 'none'; }

const errors = [];
function fail(message) {
  errors.push(String(message));
  console.error(String(message));
  errorBox.textContent = String(message);
  errorBox.style.display = 'block';
}
window.addEventListener('error', ev => fail(ev.message || 'error'));
window.addEventListener('unhandledrejection', ev => fail((ev.reason && ev.reason.message) || String(ev.reason)));

let settleReady;
const api = window.terrainClient = {
  ready: new Promise((resolve, reject) => { settleReady = { resolve, reject }; }),
  errors, history: [], last: null, paused: false,
  runTo: null, resume: null,
};
api.ready.catch(() => {});

const HISTORY_MAX = 20000; // about five minutes at 60 fps: the oldest go first, so the page stays bounded

function mib(bytes) { return (bytes / 1048576).toFixed(1); }

async function main() {
  const wasm = await init();
  const width = Number(params.get('width')) || window.innerWidth;
  const height = Number(params.get('height')) || window.innerHeight;
  canvas.width = width; canvas.height = height;
  canvas.style.width = width + 'px'; canvas.style.height = height + 'px';
  const mode = params.get('mode') || 'fly';
  const options = {
    memory: params.get('memory') || $('memory').value,
    target_fps: Number(params.get('fps') || $('fps').value),
    method: params.get('method') || $('method').value,
    filler: params.get('filler') || $('filler').value,
    mode,
  };
  if (params.get('limit_percent')) options.limit_percent = Number(params.get('limit_percent'));
  if (params.get('fixed_budget')) options.fixed_budget = Number(params.get('fixed_budget'));
  if (params.get('flight_fps')) options.flight_fps = Number(params.get('flight_fps'));
  if (params.get('wall_clock') === '1') options.wall_clock = true;
  if (params.get('loop') === '1') options.loop_flight = true;
  $('memory').value = options.memory; $('fps').value = options.target_fps;
  $('method').value = options.method; $('filler').value = options.filler; $('mode').value = mode;
  const server = params.get('server') || location.origin;
  const client = await Client.connect(canvas, server, JSON.stringify(options));
  api.info = { backend: client.backend(), adapter: client.adapter(), dataset: client.dataset(), server };

  // Controls.
  const keys = new Set();
  const axis = (plus, minus) => (plus.some(k => keys.has(k)) ? 1 : 0) - (minus.some(k => keys.has(k)) ? 1 : 0);
  const steer = () => client.steer(axis(['KeyW'], ['KeyS']), axis(['KeyD'], ['KeyA']),
    axis(['KeyE', 'Space'], ['KeyQ', 'ControlLeft', 'ControlRight']),
    keys.has('ShiftLeft') || keys.has('ShiftRight'));
  canvas.addEventListener('keydown', ev => { keys.add(ev.code); steer(); ev.preventDefault(); });
  canvas.addEventListener('keyup', ev => { keys.delete(ev.code); steer(); });
  canvas.addEventListener('blur', () => { keys.clear(); steer(); });
  let drag = null;
  canvas.addEventListener('pointerdown', ev => { drag = [ev.clientX, ev.clientY]; canvas.focus(); canvas.setPointerCapture(ev.pointerId); });
  canvas.addEventListener('pointerup', () => { drag = null; });
  canvas.addEventListener('pointermove', ev => {
    if (!drag) return;
    client.look(ev.clientX - drag[0], ev.clientY - drag[1], 0);
    drag = [ev.clientX, ev.clientY];
  });
  canvas.addEventListener('wheel', ev => { client.look(0, 0, -Math.sign(ev.deltaY)); ev.preventDefault(); }, { passive: false });
  const guarded = f => { try { f(); errorBox.style.display = 'none'; } catch (e) { fail(e.message || e); } };
  $('memory').addEventListener('change', () => guarded(() => client.set_memory($('memory').value, Number(options.limit_percent || 90))));
  $('fps').addEventListener('change', () => guarded(() => client.set_target_fps(Number($('fps').value))));
  const method = () => guarded(() => client.set_method($('method').value, $('filler').value));
  $('method').addEventListener('change', method);
  $('filler').addEventListener('change', method);
  $('mode').addEventListener('change', () => { params.set('mode', $('mode').value); location.search = params.toString(); });
  if (!params.get('width')) {
    window.addEventListener('resize', () => {
      canvas.width = window.innerWidth; canvas.height = window.innerHeight;
      canvas.style.width = canvas.width + 'px'; canvas.style.height = canvas.height + 'px';
      client.resize(canvas.width, canvas.height);
    });
  }

  // The loop.
  let stopAt = null, stopped = null;
  let fpsWindow = [];
  let lastDownload = [performance.now(), 0];
  function frame() {
    if (api.paused) return;
    let stats;
    try {
      stats = JSON.parse(client.frame());
    } catch (e) {
      fail(e.message || e);
      return;
    }
    const now = performance.now();
    stats.wasm_heap_bytes = wasm.memory.buffer.byteLength;
    stats.t_ms = Math.round(now);
    fpsWindow.push(now);
    while (fpsWindow.length && fpsWindow[0] < now - 1000) fpsWindow.shift();
    if (now - lastDownload[0] >= 1000) {
      stats.download_rate = (stats.bytes_downloaded - lastDownload[1]) * 1000 / (now - lastDownload[0]);
      lastDownload = [now, stats.bytes_downloaded];
    } else {
      stats.download_rate = api.last ? api.last.download_rate : 0;
    }
    stats.fps = fpsWindow.length;
    api.last = stats;
    api.history.push(stats);
    if (api.history.length > HISTORY_MAX) api.history.splice(0, api.history.length - HISTORY_MAX);
    overlay.textContent =
      `${api.info.dataset} · ${stats.method} · ${api.info.backend}\n` +
      `resident ${mib(stats.resident_bytes)} of ${mib(stats.limit_bytes)} MiB (peak ${mib(stats.peak_resident_bytes)}) · wasm heap ${mib(stats.wasm_heap_bytes)} MiB\n` +
      `belts ${stats.complete_belts}/${stats.belt_count} · tiles ${stats.resident_tiles} (+${stats.in_flight} in flight)\n` +
      `${stats.fps} fps` + (stats.target_fps ? ` (target ${stats.target_fps})` : '') +
      ` · ${stats.triangles.toLocaleString()} triangles` + (stats.budget ? ` (budget ${stats.budget.toLocaleString()})` : '') + '\n' +
      `download ${(stats.download_rate / 1024).toFixed(0)} KiB/s · ${mib(stats.bytes_downloaded)} MiB in ${stats.requests} requests` +
      (stats.failures ? ` · ${stats.failures} failed` : '');
    if (stopAt !== null && stats.frame >= stopAt) {
      api.paused = true;
      const s = stopped; stopAt = null; stopped = null;
      s(stats);
      return;
    }
    requestAnimationFrame(frame);
  }
  api.runTo = target => new Promise(resolve => {
    stopAt = target; stopped = resolve;
    if (api.paused) { api.paused = false; requestAnimationFrame(frame); }
  });
  api.runFor = seconds => new Promise(resolve => {
    api.resume();
    setTimeout(() => { api.paused = true; resolve(api.last); }, seconds * 1000);
  });
  api.resume = () => { if (api.paused) { api.paused = false; requestAnimationFrame(frame); } };
  api.paused = params.get('paused') === '1';
  settleReady.resolve(api.info);
  canvas.focus();
  requestAnimationFrame(frame);
}

main().catch(e => { fail(e.message || e); settleReady.reject(e); });
