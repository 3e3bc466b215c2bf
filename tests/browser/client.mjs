#!/usr/bin/env node
// Drives the wasm client's page (web/page, built into viewer/dist/client by
// scripts/build-web.sh) in headless Chromium with WebGPU (SwiftShader), and writes what it saw.
//
//   node tests/browser/client.mjs --page <url of /view/client/index.html with its query>
//        --out <dir> --frames 30,60,90 [--settle-frames 600] [--timeout-s 300]
//        [--width 960 --height 540] [--chromium /usr/bin/chromium] [--no-webgpu]
//        [--run-seconds S] [--ui] [--shot FILE] [--steer]
//
// The page is opened paused; for each of --frames it draws up to that frame and takes
// <out>/frame-<N>.png of the canvas; with --settle-frames it then draws on (the camera where
// the last frame left it) until the scene has settled or that many more frames have passed,
// and takes <out>/settled.png; with --run-seconds it then lets the page draw freely (at its
// own pace, as a user's tab does) for S seconds. --no-webgpu runs Chromium without WebGPU
// (as a browser that has none): the page draws with WebGL2 (SwiftShader through ANGLE). --ui keeps the page's overlay and controls, and --shot FILE writes a screenshot of
// the whole page at the end. --steer (for ?mode=fly) then holds W for 40 frames and drags
// the mouse 200 px to the right, as a user flies, then sets the panel (target 30 fps, 8MiB,
// GeoMipMaps): result.steer has the camera (x, y, z, yaw, pitch) before, after the key and
// after the drag, and the target, limit and method the frames after each setting reported;
// <out>/steer.png is the view at the end.
// Writes <out>/result.json:
//   { ok, reason?, info: {backend, adapter, dataset, server}, history: [one object a frame:
//     the page's figures, wasm_heap_bytes], stops: [{frame, file}], settled: {frame, file}?,
//     errors: [page errors], console_errors: [...], failed_requests: [...],
//     external_requests: [...], console_messages: [...], seconds, chromium }
// Exit status: 0 when the run reached its end (the caller judges what it saw); 2 when it
// could not (no chromium or puppeteer-core, the page's ready rejected, a timeout).
import fs from 'node:fs';
import path from 'node:path';
import { createRequire } from 'node:module';
import { fileURLToPath } from 'node:url';

const HERE = path.dirname(fileURLToPath(import.meta.url));
const VIEWER = path.resolve(HERE, '../../viewer');
const T0 = Date.now();
const since = t => Math.round((Date.now() - t) / 10) / 100;

function parseArgs(argv) {
  const a = { timeoutS: 300, width: 960, height: 540, frames: [], settleFrames: 0,
    chromium: process.env.CHROMIUM || '/usr/bin/chromium', noWebgpu: false };
  for (let i = 0; i < argv.length; i++) {
    const k = argv[i];
    const v = () => { if (i + 1 >= argv.length) throw new Error(`${k} needs a value`); return argv[++i]; };
    switch (k) {
      case '--page': a.page = v(); break;
      case '--out': a.out = v(); break;
      case '--frames': a.frames = v().split(',').filter(Boolean).map(Number); break;
      case '--settle-frames': a.settleFrames = Number(v()); break;
      case '--timeout-s': a.timeoutS = Number(v()); break;
      case '--width': a.width = Number(v()); break;
      case '--height': a.height = Number(v()); break;
      case '--chromium': a.chromium = v(); break;
      case '--no-webgpu': a.noWebgpu = true; break;
      case '--run-seconds': a.runSeconds = Number(v()); break;
      case '--ui': a.ui = true; break;
      case '--shot': a.shot = v(); break;
      case '--steer': a.steer = true; break;
      case '-h': case '--help':
        process.stdout.write(fs.readFileSync(fileURLToPath(import.meta.url), 'utf8').split('\n').slice(1, 20).map(l => l.replace(/^\/\/ ?/, '')).join('\n') + '\n');
        process.exit(0);
        break;
      default: throw new Error(`unknown argument ${k}`);
    }
  }
  if (!a.page || !a.out) throw new Error('--page and --out are required');
  for (const f of a.frames) if (!Number.isInteger(f) || f < 0) throw new Error(`--frames: ${f} is not a frame number`);
  return a;
}

const result = { ok: false, reason: null, info: null, history: [], stops: [], settled: null, errors: [],
  console_errors: [], failed_requests: [], external_requests: [], console_messages: [], seconds: 0, chromium: null };
let outDir = null;
function finish(code) {
  result.seconds = since(T0);
  if (outDir) {
    fs.mkdirSync(outDir, { recursive: true });
    fs.writeFileSync(path.join(outDir, 'result.json'), JSON.stringify(result, null, 1) + '\n');
  }
  process.stderr.write(result.ok
    ? `client.mjs: ok in ${result.seconds} s: ${result.history.length} frames, ${result.errors.length} page errors, ${result.console_errors.length} console errors, ${result.failed_requests.length} failed requests\n`
    : `client.mjs: NOT ok after ${result.seconds} s: ${result.reason}\n`);
  process.exit(code);
}
const isLoopback = u => {
  try {
    const { protocol, hostname } = new URL(u);
    if (!/^(https?|wss?):$/.test(protocol)) return true;
    return hostname === 'localhost' || hostname === '[::1]' || /^127\./.test(hostname);
  } catch { return true; }
};

let args;
try { args = parseArgs(process.argv.slice(2)); } catch (e) { result.reason = e.message; finish(2); }
outDir = args.out;
let puppeteer;
try {
  puppeteer = createRequire(path.join(VIEWER, 'package.json'))('puppeteer-core');
} catch (e) { result.reason = `puppeteer-core is not installed (bash viewer/setup.sh): ${e.message}`; finish(2); }
if (!fs.existsSync(args.chromium)) { result.reason = `no chromium at ${args.chromium}`; finish(2); }

const deadline = T0 + args.timeoutS * 1000;
const left = () => Math.max(1, deadline - Date.now());
function withTimeout(promise, what) {
  let timer;
  return Promise.race([promise, new Promise((_, reject) => {
    timer = setTimeout(() => reject(new Error(`timed out ${what} (--timeout-s ${args.timeoutS})`)), left());
  })]).finally(() => clearTimeout(timer));
}

const flags = ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader', `--window-size=${args.width},${args.height}`];
// WebGPU on SwiftShader; its canvases reach the page's compositor (and so screenshots) only
// when the compositor runs on SwiftShader's Vulkan too.
if (args.noWebgpu) flags.push('--disable-features=WebGPU', '--disable-webgpu');
else flags.push('--enable-unsafe-webgpu', '--enable-features=Vulkan', '--use-vulkan=swiftshader');
let browser;
try {
  browser = await puppeteer.launch({ executablePath: args.chromium, headless: true, args: flags,
    protocolTimeout: args.timeoutS * 1000 + 60000 });
  result.chromium = await browser.version();
  const page = await browser.newPage();
  await page.setViewport({ width: args.width, height: args.height });
  page.on('console', m => {
    const line = `${m.type()}: ${m.text()}`;
    result.console_messages.push(line);
    if (m.type() === 'error') result.console_errors.push(m.text());
  });
  page.on('pageerror', e => result.errors.push(String(e && e.message || e)));
  page.on('requestfailed', r => {
    const why = r.failure() && r.failure().errorText;
    if (why !== 'net::ERR_ABORTED') result.failed_requests.push(`${why} ${r.url()}`);
  });
  page.on('request', r => { if (!isLoopback(r.url())) result.external_requests.push(r.url()); });
  page.on('response', r => { if (r.status() >= 400) result.failed_requests.push(`${r.status()} ${r.url()}`); });
  const url = new URL(args.page);
  url.searchParams.set('paused', '1');
  if (!args.ui) url.searchParams.set('ui', '0');
  url.searchParams.set('width', String(args.width));
  url.searchParams.set('height', String(args.height));
  await withTimeout(page.goto(url.toString(), { waitUntil: 'load' }), 'loading the page');
  result.info = await withTimeout(page.evaluate(() => window.terrainClient.ready), 'waiting for the client');
  const canvas = await page.$('#terrain');
  const shot = async name => {
    const file = path.join(outDir, name);
    await canvas.screenshot({ path: file });
    return name;
  };
  fs.mkdirSync(outDir, { recursive: true });
  for (const frame of args.frames) {
    const stats = await withTimeout(page.evaluate(f => window.terrainClient.runTo(f), frame), `drawing up to frame ${frame}`);
    result.stops.push({ frame: stats.frame, file: await shot(`frame-${frame}.png`) });
  }
  if (args.settleFrames > 0) {
    const stats = await withTimeout(page.evaluate(async n => {
      const api = window.terrainClient;
      const end = (api.last ? api.last.frame : 0) + n;
      let s = api.last;
      while (!(s && s.settled) && (!s || s.frame < end)) s = await api.runTo((s ? s.frame : 0) + 1);
      // One more frame once settled: what was drawn with every tile in place.
      return api.runTo(s.frame + 1);
    }, args.settleFrames), 'waiting for the scene to settle');
    result.settled = { frame: stats.frame, settled: stats.settled, file: await shot('settled.png') };
  }
  if (args.steer) {
    const runTo = n => withTimeout(page.evaluate(f => window.terrainClient.runTo(f), n), `drawing up to frame ${n}`);
    const start = await page.evaluate(() => window.terrainClient.last ? window.terrainClient.last.frame : 0);
    const before = await runTo(start + 20);
    await page.focus('#terrain');
    await page.keyboard.down('KeyW');
    const afterKey = await runTo(before.frame + 40);
    await page.keyboard.up('KeyW');
    const box = await canvas.boundingBox();
    const [x, y] = [box.x + box.width / 2, box.y + box.height / 2];
    await page.mouse.move(x, y);
    await page.mouse.down();
    await page.mouse.move(x + 200, y, { steps: 10 });
    await page.mouse.up();
    const afterDrag = await runTo(afterKey.frame + 10);
    // The panel, as a user sets it: each control's change event, then a few frames.
    const set = (id, value) => page.$eval(id, (el, v) => { el.value = v; el.dispatchEvent(new Event('change')); }, value);
    await set('#fps', '30');
    const afterFps = await runTo(afterDrag.frame + 5);
    await set('#memory', '8MiB');
    const afterMemory = await runTo(afterFps.frame + 5);
    await set('#method', 'geomipmap');
    const afterMethod = await runTo(afterMemory.frame + 5);
    result.steer = { before: before.camera, after_key: afterKey.camera, after_drag: afterDrag.camera,
      target_fps: afterFps.target_fps, limit_bytes: afterMemory.limit_bytes, method: afterMethod.method };
    await shot('steer.png');
  }
  if (args.runSeconds > 0) {
    await withTimeout(page.evaluate(s => window.terrainClient.runFor(s), args.runSeconds), `running ${args.runSeconds} s`);
  }
  if (args.shot) await page.screenshot({ path: args.shot });
  result.history = await page.evaluate(() => window.terrainClient.history);
  result.errors.push(...await page.evaluate(() => window.terrainClient.errors));
  result.ok = true;
} catch (e) {
  result.reason = e.message || String(e);
}
try { await browser?.close(); } catch { /* gone already */ }
finish(result.ok ? 0 : 2);
