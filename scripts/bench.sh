#!/usr/bin/env bash
# Every benchmark behind BENCHMARKS.md, in one run, on the data kit in $TERRAIN_DATA_DIR.
# Writes its outputs under ${OUT:-out/bench}, and each bench's output, stamped with the
# commit, machine and date, into docs/benchmarks/ and BENCHMARKS.md's generated blocks.
# Needs nginx and wrk for the HTTP comparison (installed here when missing, as root), and
# SeaweedFS for the object store (scripts/scale-setup.sh). `ONLY=http` runs the databases
# and the HTTP benchmarks alone; `ONLY=build` the databases, the builder's benchmark and the
# heights codec's.
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
source scripts/stamp.sh
# Read before the first document is written: the run's own outputs are not its changes.
STAMP_COMMIT=$(stamp_commit)
export STAMP_COMMIT
cargo build --release --workspace --locked

# capture NAME LABEL COMMAND...: runs COMMAND, shows its output and writes it, stamped with
# this run's commit, machine and date, to docs/benchmarks/NAME.md for the generated block of
# the same name in BENCHMARKS.md (LABEL: the command as the document shows it).
captured=()
capture() {
  local name=$1 label=$2
  shift 2
  "$@" 2>/dev/null | tee "$out/$name.txt"
  {
    echo "<!-- written by \`bash scripts/bench.sh\` (\`$label\`); do not edit -->"
    echo "Run: $(stamp_line)."
    echo
    cat "$out/$name.txt"
  } >"docs/benchmarks/$name.md"
  captured+=("docs/benchmarks/$name.md")
}
bin=target/release

echo "== databases"
"$bin/terrain-server" build "$TERRAIN_DATA_DIR/puget_sound_1k/ps_height_1k.png" --out "$out/db/puget_sound_1k" --force --quiet --no-web
capture builder "terrain-server build himalaya_4097 --no-web" \
  /usr/bin/time -o /dev/stdout -f "himalaya_4097 (level 0 and its pyramid, no web tiles): built in %e s wall, peak RSS %M KiB" \
  "$bin/terrain-server" build "$TERRAIN_DATA_DIR/himalaya_4097/g10g_himalaya_4097.png" --out "$out/db/himalaya_4097" --force --quiet --no-web

if [ "${ONLY:-}" != http ]; then
  echo "== builder: levels in bounded memory, with and without voids"
  cargo bench -p terrain-server --bench build_memory -- "$out/build_memory" 2>/dev/null
  echo "== heights codec"
  capture codec "cargo bench -p terrain-server --bench codec" cargo bench -p terrain-server --bench codec
fi
if [ "${ONLY:-}" = build ]; then
  cp "$out/build_memory/build_memory.md" docs/benchmarks/
  bash scripts/insert-generated.sh BENCHMARKS.md docs/benchmarks/build_memory.md
  for file in "${captured[@]}"; do
    bash scripts/insert-generated.sh BENCHMARKS.md "$file"
  done
  exit 0
fi
echo "== HTTP: terrain-server against nginx"
capture http-himalaya "cargo bench -p terrain-server --bench http_vs_nginx -- DB/himalaya_4097" cargo bench -p terrain-server --bench http_vs_nginx -- "$out/db/himalaya_4097"
capture http-puget "cargo bench -p terrain-server --bench http_vs_nginx -- DB/puget_sound_1k" cargo bench -p terrain-server --bench http_vs_nginx -- "$out/db/puget_sound_1k"
echo "== HTTP: from an object store, cold and warm, and behind nginx's cache"
capture http-store "bash scripts/bench-store.sh DB/himalaya_4097 DB/puget_sound_1k" bash scripts/bench-store.sh "$out/db/himalaya_4097" "$out/db/puget_sound_1k"
if [ "${ONLY:-}" = http ]; then
  # `ONLY=http bash scripts/bench.sh`: the databases and the HTTP benchmarks alone.
  for file in "${captured[@]}"; do
    bash scripts/insert-generated.sh BENCHMARKS.md "$file"
  done
  exit 0
fi
echo "== a normal client under connection attacks"
capture connection-attacks "cargo test --release -p terrain-tests --test load -- --nocapture" cargo test --release -p terrain-tests --test load -- --nocapture
echo "== pager decision time"
capture pager "cargo bench -p terrain-client --bench pager" cargo bench -p terrain-client --bench pager
echo "== level of detail per frame (strip masks, importance, budget)"
capture lod "cargo bench -p terrain-client --bench lod" cargo bench -p terrain-client --bench lod
echo "== triangles per second on this machine's adapter"
capture render "cargo bench -p terrain-client --bench render" cargo bench -p terrain-client --bench render
echo "== web tiles against the native ones: bytes and requests a second"
capture web "cargo bench -p terrain-tests --bench web" cargo bench -p terrain-tests --bench web
echo "== streaming through 100 Mbit/s"
capture stream "cargo bench -p terrain-tests --bench stream -- DB/himalaya_4097" cargo bench -p terrain-tests --bench stream -- "$out/db/himalaya_4097"

echo "== flights over himalaya_4097"
"$bin/terrain-server" serve "$out/db/himalaya_4097" --addr 127.0.0.1:0 >"$out/server.stdout" 2>"$out/server.log" &
server=$!
trap 'kill "$server" 2>/dev/null || true' EXIT
for _ in $(seq 200); do
  url=$(sed -n 's/^listening on //p' "$out/server.stdout"); [ -n "$url" ] && break; sleep 0.05
done
# Paging and streaming only (--no-render): the memory figures of the paging benchmarks.
for memory in 32MiB 256MiB; do
  capture "flight-himalaya-$memory" "terrain-client fly --server URL --memory $memory --no-render" \
    /usr/bin/time -o /dev/stdout -f "the process's peak RSS: %M KiB" \
    "$bin/terrain-client" fly --server "$url" --memory "$memory" --out "$out/flight-himalaya-$memory" --no-render --frame-every 0
done
echo "== the manifest a client fetches before its first tile"
capture manifest "curl URL/v1/manifest.json, identity and gzip" bash -c '
  tiles=$(python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print(sum(len(l[\"tiles\"]) for l in m[\"levels\"]))" "$1/manifest.json" 2>/dev/null || echo 0)
  identity=$(curl -s -o /dev/null -w "%{size_download}" "$2/v1/manifest.json")
  gzip=$(curl -s --compressed -o /dev/null -w "%{size_download}" "$2/v1/manifest.json")
  echo "| himalaya_4097 | tiles | identity bytes | bytes a tile | gzip bytes | bytes a tile |"
  echo "|---|---:|---:|---:|---:|---:|"
  awk -v t="$tiles" -v i="$identity" -v g="$gzip" "BEGIN { printf \"| manifest.json | %d | %d | %.1f | %d | %.1f |\n\", t, i, (t ? i / t : 0), g, (t ? g / t : 0) }"
' manifest "$out/db/himalaya_4097" "$url"
SERVER="$url" OUT="$out" bash scripts/bench-levels.sh
captured+=(docs/benchmarks/levels.md)
kill "$server"; wait "$server" 2>/dev/null || true

echo "== quadtree patches: bytes per sample"
for dem in puget_sound_1k/ps_height_1k.png himalaya_4097/g10g_himalaya_4097.png; do
  name=$(basename "$(dirname "$dem")")
  capture "patches-$name" "terrain-server build $name --patches --no-web" bash -c \
    '"$1" build "$2" --out "$3" --patches --force --no-web 2>&1 | grep -E "^ *(heights|patches|tiles)"' \
    build "$bin/terrain-server" "$TERRAIN_DATA_DIR/$dem" "$out/db/$name-patches"
done

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
for file in "${captured[@]}"; do
  bash scripts/insert-generated.sh BENCHMARKS.md "$file"
done
