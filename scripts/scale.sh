#!/usr/bin/env bash
# Serving at scale, on this machine: a SeaweedFS object store, a build written to it, two
# (or --replicas N) stateless `terrain-server serve s3://…` replicas and nginx caching in
# front, then two flights through nginx (cold cache, then warm). Prints what the store, the
# replicas' caches and nginx's cache did, and writes OUT/summary.md (stamped with the commit
# and the machine).
#
#   bash scripts/scale.sh                       # the bundled jacksboro sample
#   bash scripts/scale.sh DEM [--memory 16MiB] [--replicas 2] [--out out/scale] [--keep]
#                            [--record docs/benchmarks/scale-NAME.md]
#
# DEM is any input `terrain-server build` takes (for example the data kit's
# himalaya_4097/himalaya_4097.png). --keep leaves everything running until Ctrl-C, to look
# around (the store's S3 endpoint, each replica's /metrics, nginx) by hand. --record FILE
# also writes the summary to FILE and puts it into README.md's generated block of that name.
# Installs weed and nginx when missing (scripts/scale-setup.sh).
set -euo pipefail
cd "$(dirname "$0")/.."

ARGS="$*"
DEM=tests/fixtures/jacksboro/jacksboro_fault_dem.png
MEMORY=16MiB
REPLICAS=2
OUT=out/scale
KEEP=0
RECORD=""
while [ $# -gt 0 ]; do
  case "$1" in
    --memory) MEMORY="$2"; shift 2 ;;
    --replicas) REPLICAS="$2"; shift 2 ;;
    --out) OUT="$2"; shift 2 ;;
    --keep) KEEP=1; shift ;;
    --record) RECORD="$2"; shift 2 ;;
    -h|--help) sed -n '2,16p' "$0"; exit 0 ;;
    -*) echo "scale.sh: unknown option $1 (see --help)" >&2; exit 64 ;;
    *) DEM="$1"; shift ;;
  esac
done
[ -e "$DEM" ] || { echo "scale.sh: $DEM does not exist" >&2; exit 66; }
say() { printf '[scale] %s\n' "$*"; }

tools=$(bash scripts/scale-setup.sh)
WEED=$(sed -n 's/^weed: \([^ ]*\).*/\1/p' <<<"$tools")
NGINX=$(sed -n 's/^nginx: \([^ ]*\).*/\1/p' <<<"$tools")
cargo build --release --locked -p terrain-server -p terrain-client -q
SERVER=target/release/terrain-server
CLIENT=target/release/terrain-client
source scripts/stamp.sh

rm -rf "$OUT"
mkdir -p "$OUT"/store "$OUT"/nginx
OUT=$(cd "$OUT" && pwd)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null || true; }
trap cleanup EXIT

source scripts/lib-store.sh
NAME=$(basename "${DEM%.*}")
URL="s3://tiles/$NAME"

start_store "$WEED" "$OUT/store" "$OUT/store.log"
pids+=("$STORE_PID")
# Taken once the store holds its own ports.
read -r NGINX_PORT < <(free_ports 1)
say "object store: weed mini, S3 on $AWS_ENDPOINT, data in $OUT/store"

say "building $DEM into $URL"
built=0
for attempt in 1 2 3 4 5; do
  if /usr/bin/time -f '%e s, peak RSS %M KiB' -o "$OUT/build.time" \
      "$SERVER" build "$DEM" --out "$URL" -q >"$OUT/build.txt" 2>"$OUT/build.err"; then
    built=1; break
  fi
  say "the store is not taking writes yet (attempt $attempt): $(tail -n1 "$OUT/build.err")"; sleep 2
done
[ "$built" = 1 ] || { cat "$OUT/build.err" >&2; exit 1; }
cat "$OUT/build.txt"

upstreams=""
bases=()
for i in $(seq "$REPLICAS"); do
  "$SERVER" serve "$URL" --addr 127.0.0.1:0 >"$OUT/replica$i.out" 2>"$OUT/replica$i.log" &
  pids+=($!)
  for _ in $(seq 200); do grep -q '^listening on ' "$OUT/replica$i.out" 2>/dev/null && break; sleep 0.05; done
  base=$(sed -n 's/^listening on //p' "$OUT/replica$i.out")
  [ -n "$base" ] || { cat "$OUT/replica$i.log" >&2; exit 1; }
  bases+=("$base")
  upstreams+="        server ${base#http://} max_fails=1 fail_timeout=2s;"$'\n'
  say "replica $i: $base"
done

sed -e "s|@DIR@|$OUT/nginx|g" -e "s|@LISTEN@|127.0.0.1:$NGINX_PORT|" docker/nginx-replicas.conf.in \
  | awk -v ups="$upstreams" '{ if ($0 == "@UPSTREAMS@") printf "%s", ups; else print }' >"$OUT/nginx/nginx.conf"
"$NGINX" -p "$OUT/nginx" -c "$OUT/nginx/nginx.conf" -g 'daemon off;' 2>"$OUT/nginx/stderr.log" &
pids+=($!)
PROXY="http://127.0.0.1:$NGINX_PORT"
for _ in $(seq 200); do curl -s -o /dev/null "$PROXY/healthz" && break; sleep 0.05; done
say "nginx: $PROXY (cache in $OUT/nginx/cache)"

gets() { local n=0; for b in "${bases[@]}"; do
  n=$((n + $(curl -s "$b/metrics" | awk '$1 == "store_gets_total" {printf "%d", $2}'))); done; echo "$n"; }
lines() { wc -l <"$OUT/nginx/access.log" 2>/dev/null || echo 0; }

flight() { # name
  local before_gets before_lines
  before_gets=$(gets); before_lines=$(lines)
  "$CLIENT" fly --server "$PROXY" --no-render --memory "$MEMORY" --out "$OUT/$1" -q | tee "$OUT/$1.txt"
  local after_lines; after_lines=$(lines)
  local hits; hits=$(tail -n +"$((before_lines + 1))" "$OUT/nginx/access.log" | grep -c '^HIT ' || true)
  echo "$1|$((after_lines - before_lines))|$hits|$(( $(gets) - before_gets ))|$(grep -o '[0-9]* failures' "$OUT/$1.txt" | head -n1)" >>"$OUT/flights.txt"
}
say "flight 1 through nginx, cold cache"
flight cold
say "flight 2 through nginx, warm cache"
flight warm

{
  echo "**$NAME** through a SeaweedFS store, $REPLICAS replicas and nginx, flights at $MEMORY:"
  echo
  echo "Run: $(stamp_line)."
  echo
  echo "Build to the store: $(cat "$OUT/build.time"); $(grep '^published' "$OUT/build.txt")"
  echo
  echo "| flight | client requests through nginx | nginx cache hits | GETs to the store | client failures |"
  echo "|---|---:|---:|---:|---|"
  while IFS='|' read -r name requests hits g failures; do
    echo "| $name | $requests | $hits | $g | $failures |"
  done <"$OUT/flights.txt"
  echo
  echo "Each replica's store metrics at the end:"
  echo
  echo '```'
  i=0
  for b in "${bases[@]}"; do
    i=$((i + 1))
    curl -s "$b/metrics" | grep -E '^(store|blob_cache)_' | sed "s/^/replica $i: /"
  done
  echo '```'
} >"$OUT/summary.md"
cat "$OUT/summary.md"
if [ -n "$RECORD" ]; then
  { echo "<!-- written by \`bash scripts/scale.sh $ARGS\`; do not edit -->"; cat "$OUT/summary.md"; } >"$RECORD"
  bash scripts/insert-generated.sh README.md "$RECORD"
fi

if [ "$KEEP" = 1 ]; then
  say "running until Ctrl-C: nginx $PROXY, replicas ${bases[*]}, S3 $AWS_ENDPOINT"
  wait
fi
