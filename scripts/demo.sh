#!/usr/bin/env bash
# The main job: build a tile database from the bundled jacksboro DEM (once), serve it on
# a free local port, stream every tile through the client (verified against the manifest
# and decoded), fly the default camera path headless, rendering every frame (strip masks
# under a triangle budget that holds 60 fps, planar shadows, textures refined within the
# memory budget), and write to out/: an overview picture of the terrain, per-tile CSV,
# the flight's frames, per-frame CSV and charts, the server's Prometheus metrics, and
# summaries. With --window it opens the interactive viewer on the served database instead.
#
#   bash scripts/demo.sh            # everything under out/
#   bash scripts/demo.sh --window   # fly over it yourself (needs a display)
#   OUT=/tmp/run bash scripts/demo.sh
set -euo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-out}
mkdir -p "$out"
window=false
case "${1:-}" in
  --window) window=true ;;
  "") ;;
  *) echo "usage: bash scripts/demo.sh [--window]" >&2; exit 2 ;;
esac
source scripts/gpu-env.sh

cargo build --release --workspace --locked
bin=target/release
db="$out/db/jacksboro"
if [ ! -f "$db/manifest.json" ]; then
  "$bin/terrain-server" build tests/fixtures/jacksboro/jacksboro_fault_dem.png --out "$db"
else
  echo "reusing the database in $db (delete it to rebuild)"
fi

"$bin/terrain-server" serve "$db" --addr 127.0.0.1:0 >"$out/server.stdout" 2>"$out/server.log" &
server=$!
trap 'kill "$server" 2>/dev/null || true' EXIT
url=
for _ in $(seq 200); do
  url=$(sed -n 's/^listening on //p' "$out/server.stdout")
  [ -n "$url" ] && break
  kill -0 "$server" 2>/dev/null || { cat "$out/server.log" >&2; exit 1; }
  sleep 0.05
done
[ -n "$url" ] || { echo "error: the server did not start" >&2; exit 1; }
echo "serving $db at $url"

if $window; then
  "$bin/terrain-client" view --server "$url" --memory 3MiB
  exit 0
fi
"$bin/terrain-client" fetch --server "$url" --out "$out/fetch"
"$bin/terrain-client" fly --server "$url" --memory 3MiB --out "$out/flight"
curl -fsS "$url/metrics" >"$out/metrics.txt"
kill -TERM "$server"
wait "$server" || true
trap - EXIT

echo
echo "wrote:"
echo "  $out/fetch/overview.png   the whole terrain, from the served textures"
echo "  $out/fetch/tiles.csv      per tile: bytes, bounds, roughness, fetch and decode times"
echo "  $out/flight/frames/       rendered frames of the flight, one a second"
echo "  $out/flight/flight.csv    per frame: viewpoint, belts, memory, downloads, triangles, masks, frame times"
echo "  $out/flight/flight.png    paging: memory against the limit, tiles, belts, download rate"
echo "  $out/flight/render.png    rendering: target and obtained frame rate, triangles per frame, visible tiles"
echo "  $out/metrics.txt          the server's Prometheus metrics after the run"
echo "  $out/server.log           the server's log"
