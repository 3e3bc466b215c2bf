#!/usr/bin/env bash
# The levels benchmark on its own: the himalaya_4097 flight at 16 MiB paged as a pyramid of
# levels (each policy) and as level 0 alone, against the full-resolution reference and the
# byte oracle (`terrain-client bench levels`). Writes docs/benchmarks/levels.md (stamped
# with the commit, machine and date; BENCHMARKS.md and docs/evaluation.md show it) and
# docs/images/levels-himalaya-16MiB.png. `scripts/bench.sh` runs it as one of its sections.
#
#   TERRAIN_DATA_DIR=DIR bash scripts/bench-levels.sh
#
# SERVER=URL uses a server already serving himalaya_4097 (bench.sh's); otherwise the
# database is built under ${OUT:-out/bench}/db and served here on a loopback port.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/gpu-env.sh
source scripts/stamp.sh
mkdir -p "${OUT:-out/bench}"
out=$(cd "${OUT:-out/bench}" && pwd)
bin=target/release
url=${SERVER:-}
if [ -z "$url" ]; then
  : "${TERRAIN_DATA_DIR:?set TERRAIN_DATA_DIR to the data kit (the directory holding himalaya_4097/)}"
  cargo build --release -p terrain-server -p terrain-client --locked
  db="$out/db/himalaya_4097"
  [ -f "$db/manifest.json" ] || "$bin/terrain-server" build "$TERRAIN_DATA_DIR/himalaya_4097/g10g_himalaya_4097.png" --out "$db" --force --quiet --no-web
  "$bin/terrain-server" serve "$db" --addr 127.0.0.1:0 >"$out/levels-server.stdout" 2>"$out/levels-server.log" &
  server=$!
  trap 'kill "$server" 2>/dev/null || true' EXIT
  for _ in $(seq 200); do
    url=$(sed -n 's/^listening on //p' "$out/levels-server.stdout"); [ -n "$url" ] && break; sleep 0.05
  done
  [ -n "$url" ] || { echo "error: the server did not start; see $out/levels-server.log" >&2; exit 1; }
fi
echo "== levels: the himalaya flight at 16 MiB, a pyramid against level 0 alone, against the byte oracle"
"$bin/terrain-client" bench levels --server "$url" --memory 16MiB --out "$out/levels"
# The stamp before this run writes into the tree, so that it names the commit as it was.
stamp=$(stamp_line)
cp "$out/levels/levels.png" docs/images/levels-himalaya-16MiB.png
{
  echo "<!-- written by \`bash scripts/bench.sh\` or \`bash scripts/bench-levels.sh\` (\`terrain-client bench levels --server URL --memory 16MiB\`); do not edit -->"
  echo "Run: $stamp."
  echo
  cat "$out/levels/levels.md"
} >docs/benchmarks/levels.md
echo "wrote docs/benchmarks/levels.md"
bash scripts/insert-generated.sh BENCHMARKS.md docs/benchmarks/levels.md
