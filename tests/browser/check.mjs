#!/usr/bin/env node
// Drives the viewer page (viewer/src) in headless Chromium and writes what it saw.
//
//   node tests/browser/check.mjs --page <url of index.html with its query> --points <points.json>
//        --out <dir> [--timeout-s 90] [--width 800 --height 500] [--chromium /usr/bin/chromium]
//
// points.json: [{"lon": .., "lat": ..}, ...]
// Writes <out>/screenshot.png and <out>/result.json:
//   { ok, reason?, elevations: [metres|null], errors: [...page errors...], console_errors: [...],
//     failed_requests: [...], aborted_requests: [...], external_requests: [...], requests: N,
//     seconds, timings: {...}, renderer, info: {...page's terrainTest.info...}, page,
//     console_messages: [...], request_log: ["STATUS METHOD URL CONTENT-TYPE", ...], chromium }
//   (failed_requests: requestfailed other than net::ERR_ABORTED, and responses >= 400;
//    aborted_requests: requests the page cancelled itself; external_requests: any request
//    to a host other than 127.0.0.0/8, localhost or [::1], also listed in errors)
// Exit status: 0 when the check ran to its end (ok: true), whatever errors it saw (the caller
// judges them); 2 when it could not (no chromium or puppeteer-core, launch failure, the page's
// ready rejected or timed out, bad arguments): result.json then has ok: false and the reason.
//
// Needs viewer/setup.sh to have run (Debian's chromium, viewer/node_modules/puppeteer-core).

import fs from 'node:fs';
import path from 'node:path';
import { createRequire } from 'node:module';
import { fileURLToPath, pathToFileURL } from 'node:url';

const HERE = path.dirname(fileURLToPath(import.meta.url));
const VIEWER = path.resolve(HERE, '../../viewer');
const T0 = Date.now();
const since = (t) => Math.round((Date.now() - t) / 10) / 100;
let TIMEOUT_S = 90;

function parseArgs(argv) {
  const a = { timeoutS: 90, width: 800, height: 500, chromium: process.env.CHROMIUM || '/usr/bin/chromium' };
  for (let i = 0; i < argv.length; i++) {
    const k = argv[i];
    const v = () => {
      if (i + 1 >= argv.length) throw new Error(`${k} needs a value`);
      return argv[++i];
    };
    switch (k) {
      case '--page': a.page = v(); break;
      case '--points': a.points = v(); break;
      case '--out': a.out = v(); break;
      case '--timeout-s': a.timeoutS = Number(v()); break;
      case '--width': a.width = Number(v()); break;
      case '--height': a.height = Number(v()); break;
      case '--chromium': a.chromium = v(); break;
      case '-h': case '--help':
        process.stdout.write(fs.readFileSync(fileURLToPath(import.meta.url), 'utf8').split('\n').slice(1, 17).map((l) => l.replace(/^\/\/ ?/, '')).join('\n') + '\n');
        process.exit(0);
        break;
      default: throw new Error(`unknown argument ${k}`);
    }
  }
  for (const [k, n] of [['--timeout-s', a.timeoutS], ['--width', a.width], ['--height', a.height]]) {
    if (!Number.isFinite(n) || n <= 0) throw new Error(`${k} must be a positive number`);
  }
  return a;
}

const result = {
  ok: false,
  reason: null,
  page: null,
  elevations: [],
  errors: [],
  console_errors: [],
  failed_requests: [],
  aborted_requests: [],
  external_requests: [],
  requests: 0,
  seconds: 0,
  timings: {},
  renderer: null,
  info: null,
  console_messages: [],
  request_log: [],
  chromium: null,
};
let outDir = null;

function writeResult() {
  result.seconds = since(T0);
  if (!outDir) return;
  try {
    fs.mkdirSync(outDir, { recursive: true });
    fs.writeFileSync(path.join(outDir, 'result.json'), JSON.stringify(result, null, 2) + '\n');
  } catch (e) {
    process.stderr.write(`check.mjs: could not write result.json: ${e.message}\n`);
  }
}

function finish(code) {
  writeResult();
  const line = result.ok
    ? `check.mjs: ok in ${result.seconds} s: ${result.errors.length} page errors, ${result.console_errors.length} console errors, ${result.failed_requests.length} failed of ${result.requests} requests`
    : `check.mjs: NOT ok after ${result.seconds} s: ${result.reason}`;
  process.stderr.write(line + '\n');
  process.exit(code);
}

function withTimeout(promise, ms, what) {
  let timer;
  return Promise.race([
    promise,
    new Promise((_, reject) => {
      timer = setTimeout(() => reject(Object.assign(new Error(`timed out ${what} (${since(T0)} s into the run, --timeout-s ${TIMEOUT_S})`), { timeout: true })), Math.max(1, ms));
    }),
  ]).finally(() => clearTimeout(timer));
}

const isLoopback = (u) => {
  try {
    const { protocol, hostname } = new URL(u);
    if (!/^(https?|wss?):$/.test(protocol)) return true; // data:, blob:, chrome-extension: ...
    return hostname === 'localhost' || hostname === '[::1]' || hostname === '::1' || /^127\./.test(hostname);
  } catch {
    return true;
  }
};

async function main() {
  let args;
  try {
    args = parseArgs(process.argv.slice(2));
    if (!args.out) throw new Error('--out <dir> is required');
    outDir = path.resolve(args.out);
    if (!args.page) throw new Error('--page <url> is required');
    if (!args.points) throw new Error('--points <points.json> is required');
    fs.mkdirSync(outDir, { recursive: true });
  } catch (e) {
    result.reason = `bad arguments: ${e.message}`;
    return finish(2);
  }
  result.page = args.page;
  TIMEOUT_S = args.timeoutS;
  const deadline = T0 + args.timeoutS * 1000;
  const left = () => deadline - Date.now();

  let points;
  try {
    points = JSON.parse(fs.readFileSync(args.points, 'utf8'));
    if (!Array.isArray(points) || !points.every((p) => p && Number.isFinite(p.lon) && Number.isFinite(p.lat))) {
      throw new Error('expected [{"lon": number, "lat": number}, ...]');
    }
    points = points.map((p) => ({ lon: p.lon, lat: p.lat }));
  } catch (e) {
    result.reason = `bad points file ${args.points}: ${e.message}`;
    return finish(2);
  }

  if (!fs.existsSync(args.chromium)) {
    result.reason = `no chromium at ${args.chromium}: run viewer/setup.sh`;
    return finish(2);
  }
  let puppeteer;
  const ti = Date.now();
  try {
    const req = createRequire(path.join(VIEWER, 'package.json'));
    puppeteer = (await import(pathToFileURL(req.resolve('puppeteer-core')).href)).default;
  } catch (e) {
    result.reason = `puppeteer-core not found in ${VIEWER}/node_modules (run viewer/setup.sh): ${e.message}`;
    return finish(2);
  }

  result.timings.import_s = since(ti);
  let browser;
  const tl = Date.now();
  try {
    browser = await withTimeout(puppeteer.launch({
      executablePath: args.chromium,
      headless: true,
      defaultViewport: { width: args.width, height: args.height, deviceScaleFactor: 1 },
      args: [
        '--no-sandbox',
        '--use-angle=swiftshader',
        '--enable-unsafe-swiftshader',
        '--disable-dev-shm-usage',
        `--window-size=${args.width},${args.height}`,
        '--hide-scrollbars',
        '--mute-audio',
      ],
    }), Math.min(left(), 30000), 'launching chromium');
    result.chromium = await browser.version();
  } catch (e) {
    result.reason = `could not launch ${args.chromium}: ${e.message}`;
    return finish(2);
  }
  result.timings.launch_s = since(tl);

  let code = 2;
  try {
    const page = await browser.newPage();
    await page.setViewport({ width: args.width, height: args.height, deviceScaleFactor: 1 });
    page.on('console', (msg) => {
      const loc = msg.location && msg.location();
      const text = msg.text();
      if (result.console_messages.length < 300) result.console_messages.push(`${msg.type()}: ${text}`);
      if (msg.type() === 'error') {
        result.console_errors.push(loc && loc.url ? `${text} (${loc.url}${loc.lineNumber !== undefined ? ':' + loc.lineNumber : ''})` : text);
      }
    });
    page.on('pageerror', (err) => {
      result.console_errors.push(`uncaught: ${(err && (err.message || String(err))) || err}`);
    });
    page.on('request', (req) => {
      result.requests++;
      const u = req.url();
      if (!isLoopback(u)) result.external_requests.push(u);
    });
    page.on('requestfailed', (req) => {
      const f = req.failure();
      const err = (f && f.errorText) || 'failed';
      const entry = { url: req.url(), error: err, resource: req.resourceType() };
      if (err === 'net::ERR_ABORTED') result.aborted_requests.push(entry); // cancelled by the page
      else result.failed_requests.push(entry);
    });
    page.on('response', (resp) => {
      if (result.request_log.length < 2000) {
        result.request_log.push(`${resp.status()} ${resp.request().method()} ${resp.url()} ${resp.headers()['content-type'] || ''}`);
      }
      if (resp.status() >= 400) {
        result.failed_requests.push({ url: resp.url(), status: resp.status(), resource: resp.request().resourceType() });
      }
    });

    const tg = Date.now();
    await withTimeout(page.goto(args.page, { waitUntil: 'domcontentloaded', timeout: 0 }), left(), 'opening the page');
    result.timings.goto_s = since(tg);
    await withTimeout(page.waitForFunction(() => !!window.terrainTest, { timeout: 0, polling: 100 }), left(),
      'waiting for window.terrainTest');

    const readyOutcome = await withTimeout(page.evaluate(() => window.terrainTest.ready.then(
      () => ({ ok: true }),
      (e) => ({ ok: false, error: String((e && (e.message || e)) || 'rejected') }),
    )), left(), 'waiting for terrainTest.ready').catch((e) => ({ ok: false, error: e.message, timeout: !!e.timeout }));
    result.timings.ready_s = since(tg);

    if (readyOutcome.ok) {
      const te = Date.now();
      try {
        const el = await withTimeout(page.evaluate((pts) => window.terrainTest.elevations(pts), points), left(),
          'reading elevations');
        result.elevations = el.map((h) => (typeof h === 'number' && Number.isFinite(h) ? h : null));
        result.timings.elevations_s = since(te);
        result.ok = true;
        code = 0;
      } catch (e) {
        result.reason = `elevations failed: ${e.message}`;
      }
    } else {
      result.reason = readyOutcome.timeout ? readyOutcome.error : `terrainTest.ready rejected: ${readyOutcome.error}`;
    }

    // what the page knows (also after a failure: it says why)
    const tp = Date.now();
    try {
      const pageState = await withTimeout(page.evaluate(() => ({
        errors: (window.terrainTest && window.terrainTest.errors) || [],
        info: (window.terrainTest && window.terrainTest.info) || null,
      })), Math.max(left(), 5000), 'reading terrainTest.errors');
      result.errors = JSON.parse(JSON.stringify(pageState.errors));
      result.info = JSON.parse(JSON.stringify(pageState.info));
      result.renderer = (result.info && result.info.renderer) || null;
      result.timings.page_state_s = since(tp);
    } catch (e) {
      result.errors.push({ kind: 'driver', message: `could not read the page's errors: ${e.message}` });
    }
    for (const u of result.external_requests) result.errors.push({ kind: 'external-request', message: `request left 127.0.0.1: ${u}` });

    const ts = Date.now();
    try {
      await withTimeout(page.screenshot({ path: path.join(outDir, 'screenshot.png'), type: 'png' }),
        Math.max(left(), 15000), 'taking the screenshot');
      result.timings.screenshot_s = since(ts);
      result.screenshot = path.join(outDir, 'screenshot.png');
    } catch (e) {
      if (result.ok) { result.ok = false; code = 2; result.reason = `screenshot failed: ${e.message}`; }
    }
  } catch (e) {
    result.reason = result.reason || `${e.message}`;
  } finally {
    const tc = Date.now();
    await withTimeout(browser.close(), 10000, 'closing chromium').catch(() => {
      try { browser.process() && browser.process().kill('SIGKILL'); } catch { /* gone */ }
    });
    result.timings.close_s = since(tc);
  }
  return finish(code);
}

main().catch((e) => {
  result.reason = `driver crashed: ${(e && e.stack) || e}`;
  finish(2);
});
