#!/usr/bin/env bash
# Every benchmark behind BENCHMARKS.md, in one run, on the data kit in $TERRAIN_DATA_DIR.
# Writes its outputs under ${OUT:-out/bench}; takes about 6 minutes on 2 cores.
# Needs nginx and wrk for the HTTP comparison (installed here when missing, as root).
set -euo pipefail
cd "$(dirname "$0")/.."
: "${TERRAIN_DATA_DIR:?set TERRAIN_DATA_DIR to the data kit (the directory holding himalaya_4097/ and puget_sound_1k/)}"
export TERRAIN_DATA_DIR
# Absolute: cargo runs each bench binary from its own package's directory.
mkdir -p "${OUT:-out/bench}"
out=$(cd "${OUT:-out/bench}" && pwd)
for tool in nginx wrk; do
  command -v "$tool" >/dev/null || {
    apt-get -o DPkg::Lock::Timeout=600 update -qq
    DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 install -y -qq --no-install-recommends nginx wrk >/dev/null
  }
done
source scripts/gpu-env.sh
cargo build --release --workspace --locked
bin=target/release

echo "== databases"
"$bin/terrain-server" build "$TERRAIN_DATA_DIR/puget_sound_1k/ps_height_1k.png" --out "$out/db/puget_sound_1k" --force --quiet --no-web
/usr/bin/time -f "build: %e s wall, peak RSS %M KiB" \
  "$bin/terrain-server" build "$TERRAIN_DATA_DIR/himalaya_4097/g10g_himalaya_4097.png" --out "$out/db/himalaya_4097" --force --quiet --no-web

echo "== builder: levels in bounded memory, with and without voids"
cargo bench -p terrain-server --bench build_memory -- "$out/build_memory" 2>/dev/null
echo "== heights codec"
cargo bench -p terrain-server --bench codec 2>/dev/null
echo "== HTTP: terrain-server against nginx"
cargo bench -p terrain-server --bench http_vs_nginx -- "$out/db/himalaya_4097" 2>/dev/null
cargo bench -p terrain-server --bench http_vs_nginx -- "$out/db/puget_sound_1k" 2>/dev/null
echo "== pager decision time"
cargo bench -p terrain-client --bench pager 2>/dev/null
echo "== level of detail per frame (strip masks, importance, budget)"
cargo bench -p terrain-client --bench lod 2>/dev/null
echo "== triangles per second on this machine's adapter"
cargo bench -p terrain-client --bench render 2>/dev/null
echo "== web tiles against the native ones: bytes and requests a second"
cargo bench -p terrain-tests --bench web 2>/dev/null
echo "== streaming through 100 Mbit/s"
cargo bench -p terrain-tests --bench stream -- "$out/db/himalaya_4097" 2>/dev/null

echo "== flights over himalaya_4097"
"$bin/terrain-server" serve "$out/db/himalaya_4097" --addr 127.0.0.1:0 >"$out/server.stdout" 2>"$out/server.log" &
server=$!
trap 'kill "$server" 2>/dev/null || true' EXIT
for _ in $(seq 200); do
  url=$(sed -n 's/^listening on //p' "$out/server.stdout"); [ -n "$url" ] && break; sleep 0.05
done
# Paging and streaming only (--no-render): the memory figures of the paging benchmarks.
for memory in 32MiB 256MiB; do
  /usr/bin/time -f "process: peak RSS %M KiB" \
    "$bin/terrain-client" fly --server "$url" --memory "$memory" --out "$out/flight-himalaya-$memory" --quiet --no-render
done
kill "$server"; wait "$server" 2>/dev/null || true

echo "== frame-rate controller: rendered flights holding a target frame rate"
cargo bench -p terrain-tests --bench controller -- "$out/controller" 2>/dev/null
echo "== memory per method: the limit, and what the process holds beside it"
cargo bench -p terrain-tests --bench memory -- "$out/memory" 2>/dev/null

# The generated tables into the documents, stamped with this run's commit, machine and date.
for table in build_memory/build_memory.md controller/controller.md controller/controller.csv memory/memory.md memory/memory.csv; do
  cp "$out/$table" docs/benchmarks/
done
cp "$out/controller/jacksboro-60fps-16MiB-planar-shadow/render.png" docs/images/frame-rate-jacksboro-60.png
cp "$out/controller/jacksboro-30fps-16MiB-planar-shadow/render.png" docs/images/frame-rate-jacksboro-planar-shadow.png
bash scripts/insert-generated.sh BENCHMARKS.md docs/benchmarks/build_memory.md
bash scripts/insert-generated.sh BENCHMARKS.md docs/benchmarks/controller.md
bash scripts/insert-generated.sh BENCHMARKS.md docs/benchmarks/memory.md
