#!/usr/bin/env bash
# The wasm client in a browser tab over a long flight: the frame rate against its target and
# the wasm heap, as a user's tab runs it (the page's own clock and pace), in headless Chromium
# on SwiftShader (a CPU: the figures are SwiftShader's, not a GPU's), with WebGPU and again
# with WebGL2 (Chromium without WebGPU).
#
#   bash scripts/bench-web.sh [SECONDS]     # default 300, for each backend
#
# Flies the default flight of himalaya_4097 ($TERRAIN_DATA_DIR; jacksboro without it) again and
# again by the page's clock in 16 MiB for SECONDS on each backend, then writes
# docs/benchmarks/web-client.md (inserted into BENCHMARKS.md) and docs/images/web-client.png
# (the WebGPU page at the end, overlay included). Needs the release binaries (cargo build --release --workspace), viewer/setup.sh
# and scripts/build-web.sh to have run.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/stamp.sh
SECONDS_RUN=${1:-300}
MEMORY=16MiB
bin=target/release
for f in "$bin/terrain-server" viewer/dist/client/pkg/terrain_web_bg.wasm viewer/node_modules/puppeteer-core; do
  [ -e "$f" ] || { echo "error: $f is missing (cargo build --release --workspace; bash viewer/setup.sh; bash scripts/build-web.sh)" >&2; exit 1; }
done
work=$(mktemp -d)
trap 'kill "${server:-}" 2>/dev/null || true; rm -rf "$work"' EXIT
if [ -n "${TERRAIN_DATA_DIR:-}" ] && [ -f "$TERRAIN_DATA_DIR/himalaya_4097/g10g_himalaya_4097.png" ]; then
  dem="$TERRAIN_DATA_DIR/himalaya_4097/g10g_himalaya_4097.png"
else
  echo "note: TERRAIN_DATA_DIR has no himalaya_4097: flying the bundled jacksboro instead"
  dem=tests/fixtures/jacksboro/jacksboro_fault_dem.png
fi
echo "building $(basename "$dem") ..."
"$bin/terrain-server" build "$dem" --out "$work/db" --no-web >/dev/null
"$bin/terrain-server" serve "$work/db" --addr 127.0.0.1:0 --viewer viewer/dist >"$work/server.out" 2>"$work/server.log" &
server=$!
url=""
for _ in $(seq 100); do
  url=$(sed -n 's/^listening on //p' "$work/server.out")
  [ -n "$url" ] && break
  sleep 0.1
done
[ -n "$url" ] || { cat "$work/server.log" >&2; echo "error: the server did not start" >&2; exit 1; }
mkdir -p docs/benchmarks docs/images
# The commit measured, read before this run writes its figures into the tree
# (scripts/stamp.sh).
STAMP_COMMIT=$(stamp_commit)
export STAMP_COMMIT
page="$url/view/client/index.html?mode=flight&wall_clock=1&loop=1&memory=$MEMORY"
echo "flying for $SECONDS_RUN s in headless Chromium with WebGPU ..."
node tests/browser/client.mjs --page "$page" \
  --run-seconds "$SECONDS_RUN" --timeout-s $((SECONDS_RUN + 120)) --ui --shot "$work/shot.png" --out "$work/webgpu"
cp "$work/shot.png" docs/images/web-client.png
echo "flying for $SECONDS_RUN s in headless Chromium without WebGPU (WebGL2) ..."
node tests/browser/client.mjs --page "$page" --no-webgpu \
  --run-seconds "$SECONDS_RUN" --timeout-s $((SECONDS_RUN + 120)) --ui --out "$work/webgl2"
python3 - "$work/webgpu/result.json" "$work/webgl2/result.json" "$(stamp_line)" "$SECONDS_RUN" "$MEMORY" "$(basename "$dem")" > docs/benchmarks/web-client.md <<'PY'
import json, statistics, sys
paths, (stamp, seconds, memory, dem) = sys.argv[1:3], sys.argv[3:]
mib = lambda b: f"{b / 1048576:.1f}"

def measures(path):
    r = json.load(open(path))
    for key in ("errors", "console_errors", "failed_requests"):
        if r[key]:
            sys.exit(f"{path}: the page saw {key}: {r[key][:3]}")
    h = r["history"]
    t0 = h[0]["t_ms"]
    # One sample a whole second of the run (the page counts the frames of the second
    # before), after the first 5 s (the first tiles arriving).
    by_second = {}
    for s in h:
        sec = (s["t_ms"] - t0) // 1000
        if sec >= 5:
            by_second[sec] = s
    rates = [s["fps"] for s in by_second.values()]
    target = next((s["target_fps"] for s in h if s.get("target_fps")), None)
    within = sum(1 for f in rates if target and abs(f - target) <= 0.1 * target)
    frame_ms = [s["frame_ms"] for s in h[len(h) // 20:] if s["frame_ms"] > 0]
    heap = [s["wasm_heap_bytes"] for s in h]
    minute = max(1, len(h) // max(1, int(seconds) // 60))
    first, last = heap[:minute], heap[-minute:]
    limit = h[-1]["limit_bytes"]
    peak = max(s["resident_bytes"] for s in h)
    over = sum(1 for s in h if s["resident_bytes"] > s["limit_bytes"])
    return r, h, {
        "adapter": f"{r['info']['adapter']} ({r['info']['backend']})",
        "frames drawn": f"{len(h)}",
        "target frame rate": f"{target} fps",
        "frame rate, per second after the first 5 s: median (min-max)":
            f"{statistics.median(rates):.0f} ({min(rates)}-{max(rates)}) fps",
        "seconds within 10% of the target": f"{within} of {len(rates)}",
        "frame time as the controller measured it, median / 90th percentile":
            f"{statistics.median(frame_ms):.1f} / {statistics.quantiles(frame_ms, n=10)[-1]:.1f} ms",
        "triangles a frame, median": f"{statistics.median(s['triangles'] for s in h):,.0f}",
        "resident bytes, peak, against the limit":
            f"{mib(peak)} of {mib(limit)} MiB, over it at {over} frames",
        "wasm heap: first minute, peak": f"{mib(max(first))} MiB",
        "wasm heap: last minute, peak": f"{mib(max(last))} MiB",
        "wasm heap: peak of the run": f"{mib(max(heap))} MiB",
        "downloaded": f"{mib(h[-1]['bytes_downloaded'])} MiB in {h[-1]['requests']} requests, {h[-1]['failures']} failed",
    }

(r, h, gpu), (_, _, gl) = measures(paths[0]), measures(paths[1])
print("<!-- written by `bash scripts/bench-web.sh`; do not edit -->")
print(f"{stamp}; {r['chromium']}, SwiftShader on the CPU")
print()
print(f"The default flight of {dem}, flown again and again by the page's clock for {seconds} s in {memory} "
      f"with each backend (method {h[-1]['method']}).")
print()
print("| measure | WebGPU | WebGL2 (no WebGPU) |")
print("|---|---|---|")
for key in gpu:
    print(f"| {key} | {gpu[key]} | {gl[key]} |")
PY
bash scripts/insert-generated.sh BENCHMARKS.md docs/benchmarks/web-client.md
cat docs/benchmarks/web-client.md
