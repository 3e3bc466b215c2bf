#!/usr/bin/env node
// Checks the viewer page and check.mjs against fixture-server.mjs (not the real server):
//
//   node tests/browser/selftest.mjs [--out DIR] [--only NAME[,NAME...]] [--timeout-s 90]
//
// Needs viewer/setup.sh to have run. Each case runs check.mjs in its own Chromium and
// leaves DIR/<case>/result.json and screenshot.png (DIR defaults to a fresh folder in /tmp).
// Ends with "N passed, N failed"; exit status 1 when any case failed.

import fs from 'node:fs';
import os from 'node:os';
import path from 'node:path';
import { spawn } from 'node:child_process';
import { fileURLToPath } from 'node:url';
import { startServer, surfaceHeight, planeHeight, BOUNDS } from './fixture-server.mjs';

const HERE = path.dirname(fileURLToPath(import.meta.url));
const CHECK = path.join(HERE, 'check.mjs');

const argv = process.argv.slice(2);
const opt = (name, dflt) => { const i = argv.indexOf(name); return i >= 0 ? argv[i + 1] : dflt; };
const OUT = path.resolve(opt('--out', fs.mkdtempSync(path.join(os.tmpdir(), 'browser-selftest-'))));
const ONLY = opt('--only', null)?.split(',');
const TIMEOUT_S = Number(opt('--timeout-s', 90));
fs.mkdirSync(OUT, { recursive: true });

// points well inside BOUNDS (and inside the box where planeHeight is a plane)
const [w, s, e, n] = BOUNDS;
const POINTS = [];
for (const fx of [0.1, 0.37, 0.5, 0.74, 0.9]) for (const fy of [0.15, 0.5, 0.85]) {
  POINTS.push({ lon: +(w + (e - w) * fx).toFixed(6), lat: +(s + (n - s) * fy).toFixed(6) });
}
const pointsFile = path.join(OUT, 'points.json');
fs.writeFileSync(pointsFile, JSON.stringify(POINTS, null, 1));

function runCheck(page, out, extra = []) {
  return new Promise((resolve) => {
    const t = Date.now();
    const child = spawn(process.execPath, [CHECK, '--page', page, '--points', pointsFile, '--out', out,
      '--timeout-s', String(TIMEOUT_S), ...extra], { stdio: ['ignore', 'inherit', 'inherit'] });
    child.on('exit', (code) => {
      let result = null;
      try { result = JSON.parse(fs.readFileSync(path.join(out, 'result.json'), 'utf8')); } catch { /* none */ }
      resolve({ code, result, wall: (Date.now() - t) / 1000 });
    });
  });
}

function maxDiff(elevations, f) {
  let worst = 0;
  for (let i = 0; i < POINTS.length; i++) {
    const h = elevations[i];
    if (typeof h !== 'number') return Infinity;
    worst = Math.max(worst, Math.abs(h - f(POINTS[i].lon, POINTS[i].lat)));
  }
  return worst;
}

const clean = (r) => r.errors.length === 0 && r.console_errors.length === 0 && r.failed_requests.length === 0 &&
  r.external_requests.length === 0;
const summary = (r) => `errors ${r.errors.length}, console_errors ${r.console_errors.length}, failed ${r.failed_requests.length}` +
  (r.errors.length ? ` (first: ${JSON.stringify(r.errors[0]).slice(0, 300)})` : '');

// each case: [name, server options, page query, judge(result, code) -> null (pass) or why not]
const good = (f, tol) => (r, code) => {
  if (code !== 0 || !r.ok) return `not ok (exit ${code}): ${r && r.reason}`;
  if (!clean(r)) return summary(r);
  const d = maxDiff(r.elevations, f);
  if (!(d <= tol)) return `elevations off by up to ${d} m (tolerance ${tol}): ${JSON.stringify(r.elevations)}`;
  return null;
};
const CASES = [
  ['maplibre-terrarium', {}, 'client=maplibre', good(surfaceHeight, 2)],
  ['maplibre-terrain-rgb', {}, 'client=maplibre&dem=terrain-rgb', good(surfaceHeight, 2)],
  ['maplibre-pitched', {}, 'client=maplibre&lon=11.4&lat=47.25&zoom=12.3&pitch=60&bearing=30', good(surfaceHeight, 2)],
  ['maplibre-pmtiles', {}, (url) => `client=maplibre&source=pmtiles&pmtiles=${encodeURIComponent(url + '/fixture/terrarium.pmtiles')}`,
    good(surfaceHeight, 2)],
  ['cesium', {}, 'client=cesium', good(planeHeight, 0.05)],
  ['cesium-pitched', {}, 'client=cesium&lon=11.4&lat=47.12&height=9000&heading=0&pitch=-30', good(planeHeight, 0.05)],
  ['maplibre-404-seen', { fail: '^/v1/(fixture1/)?terrarium/1[12]/' }, 'client=maplibre', (r, code) => {
    if (code !== 0 || !r.ok) return `not ok (exit ${code}): ${r && r.reason}`;
    if (!r.failed_requests.some((f) => f.status === 404)) return 'no 404 in failed_requests';
    if (!r.errors.some((x) => x.status === 404)) return 'no 404 in the page errors';
    return null;
  }],
  ['cesium-404-seen', { fail: '^/v1/(fixture1/)?cesium/(9|10)/' }, 'client=cesium', (r, code) => {
    if (code !== 0 || !r.ok) return `not ok (exit ${code}): ${r && r.reason}`;
    if (!r.failed_requests.some((f) => f.status === 404)) return 'no 404 in failed_requests';
    if (!r.errors.some((x) => x.kind === 'cesium-terrain')) return 'no terrainProvider.errorEvent in the page errors';
    return null;
  }],
  ['cesium-gzip-without-header-seen', { terrainEncoding: 'gzip-without-header' }, 'client=cesium', (r, code) => {
    if (code !== 0 || !r.ok) return `not ok (exit ${code}): ${r && r.reason}`;
    if (!r.errors.some((x) => x.kind === 'cesium-terrain')) return 'the broken tiles were not reported';
    if (r.elevations.some((h) => h !== null)) return 'elevations from broken tiles';
    return null;
  }],
  ['timeout-exit-2', {}, 'client=cesium', (r, code) => {
    if (code !== 2) return `exit ${code}, want 2`;
    if (!r || r.ok !== false || !/timed out/.test(r.reason || '')) return `result: ${r && r.reason}`;
    return null;
  }, ['--timeout-s', '2']],
  ['no-chromium-exit-2', {}, 'client=maplibre', (r, code) => {
    if (code !== 2) return `exit ${code}, want 2`;
    if (!r || r.ok !== false || !/chromium/.test(r.reason || '')) return `result: ${r && r.reason}`;
    return null;
  }, ['--chromium', '/nonexistent/chromium']],
];

let passed = 0, failed = 0;
const servers = new Map();
async function serverFor(opts) {
  const key = JSON.stringify(opts);
  if (!servers.has(key)) servers.set(key, await startServer(opts));
  return servers.get(key);
}
for (const [name, sopts, query, judge, extra] of CASES) {
  if (ONLY && !ONLY.includes(name)) continue;
  const srv = await serverFor(sopts);
  const q = typeof query === 'function' ? query(srv.url) : query;
  const page = `${srv.url}/view/index.html?${q}`;
  const out = path.join(OUT, name);
  fs.rmSync(out, { recursive: true, force: true });
  const { code, result, wall } = await runCheck(page, out, extra || []);
  let why;
  try { why = judge(result, code); } catch (err) { why = `judge threw: ${err.message}`; }
  const t = result && result.timings ? ` ready ${result.timings.ready_s ?? '-'} s,` : '';
  if (why === null) { passed++; console.log(`PASS ${name} (${wall.toFixed(1)} s,${t} ${out})`); }
  else { failed++; console.log(`FAIL ${name} (${wall.toFixed(1)} s,${t} ${out}): ${why}`); }
}
for (const { server } of servers.values()) server.close();
console.log(`${passed} passed, ${failed} failed`);
process.exit(failed ? 1 : 0);
