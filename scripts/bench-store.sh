#!/usr/bin/env bash
# Requests/s of the serving path with the database in an object store, beside the same
# database from a directory and behind nginx's cache, under the HTTP benchmark's load:
#
#   bash scripts/bench-store.sh DB [DB...]      # e.g. out/bench/db/himalaya_4097
#
# For each database: SeaweedFS (`weed mini`, scripts/scale-setup.sh installs it) with the
# database published to it, then `wrk -t2 -c64 --latency` cycling over every heights URL
# against, in turn:
#   directory        terrain-server serve DB (its cache of hot blobs warm);
#   store, no cache  serve s3://… --cache-bytes 0: every request a ranged GET to the store;
#   store, warm      serve s3://… after one pass over every URL: every blob in its cache;
#   nginx cache      nginx (proxy_cache, docker/nginx-replicas.conf.in) in front of the
#                    warm store replica, after one pass: every answer from nginx's cache.
# terrain-server and nginx get one worker each on the first CPU (taskset), wrk the second;
# weed is left to the scheduler (it runs only in the no-cache row). ROUNDS (default 3) runs
# of BENCH_SECONDS (default 10) each, after a 2 s warm-up; the median, minimum and maximum of
# requests/s and p99, and the store's GETs per request, from the replica's /metrics.
# Prints a table per database (stamped by scripts/bench.sh when it captures this).
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -ge 1 ] || { echo "usage: $0 DB [DB...]" >&2; exit 2; }
ROUNDS=${ROUNDS:-3}
SECONDS_PER_RUN=${BENCH_SECONDS:-10}
tools=$(bash scripts/scale-setup.sh)
WEED=$(sed -n 's/^weed: \([^ ]*\).*/\1/p' <<<"$tools")
NGINX=$(sed -n 's/^nginx: \([^ ]*\).*/\1/p' <<<"$tools")
command -v wrk >/dev/null || { echo "wrk is missing (Debian: apt-get install wrk)" >&2; exit 1; }
SERVER=target/release/terrain-server
[ -x "$SERVER" ] || cargo build --release --locked -p terrain-server -q

work=$(mktemp -d)
# nginx's workers run as an unprivileged user when it is started as root: they must reach it.
chmod 755 "$work"
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null || true; [ "${KEEP_WORK:-}" = 1 ] || rm -rf "$work"; }
trap cleanup EXIT
# KEEP_WORK=1 leaves the logs in $work.
if [ "$(nproc)" -ge 2 ] && command -v taskset >/dev/null; then
  ON_SERVER=(taskset -c 0); ON_WRK=(taskset -c 1); placement="terrain-server and nginx on CPU 0, wrk on CPU 1, weed unpinned"
else
  ON_SERVER=(); ON_WRK=(); placement="unpinned (fewer than 2 CPUs or no taskset)"
fi
source scripts/lib-store.sh
start_store "$WEED" "$work/store" "$work/store.log"
pids+=("$STORE_PID")
# Taken once the store holds its own ports.
read -r PROXY_PORT < <(free_ports 1)

serve() { # LOCATION EXTRA... -> sets base to its URL; its pid is the last of pids
  local log="$work/serve.$RANDOM"
  "${ON_SERVER[@]}" "$SERVER" serve "$@" --addr 127.0.0.1:0 --worker-threads 1 >"$log.out" 2>"$log.err" &
  pids+=($!)
  for _ in $(seq 400); do grep -q '^listening on ' "$log.out" 2>/dev/null && break; sleep 0.05; done
  base=$(sed -n 's/^listening on //p' "$log.out")
  [ -n "$base" ] || { cat "$log.err" >&2; exit 1; }
}
stop_last() { kill "${pids[-1]}" 2>/dev/null || true; wait "${pids[-1]}" 2>/dev/null || true; unset 'pids[-1]'; }
gets() { curl -s "$1/metrics" | awk '$1 == "store_gets_total" {printf "%d", $2; f=1} END {if (!f) print 0}'; }
one_pass() { # BASE: every URL once
  python3 - "$1" "$work/urls.txt" <<'EOF'
import sys, urllib.request
base, urls = sys.argv[1], sys.argv[2]
for path in open(urls).read().split():
    urllib.request.urlopen(base + path).read()
EOF
}
measure() { # LABEL BASE [METRICS_BASE]
  local label=$1 base=$2 metrics=${3:-} rps=() p99=() g0 g1 total=0
  "${ON_WRK[@]}" wrk -t2 -c64 -d2s -s "$work/cycle.lua" "$base" >/dev/null
  [ -n "$metrics" ] && g0=$(gets "$metrics")
  for _ in $(seq "$ROUNDS"); do
    "${ON_WRK[@]}" wrk -t2 -c64 -d"${SECONDS_PER_RUN}s" --latency -s "$work/cycle.lua" "$base" >"$work/wrk.txt"
    rps+=("$(awk '/^Requests\/sec:/ {printf "%d", $2}' "$work/wrk.txt")")
    p99+=("$(awk '$1 == "99%" {v=$2; if (v ~ /us$/) {sub(/us/,"",v); v/=1000} else if (v ~ /ms$/) {sub(/ms/,"",v)} else if (v ~ /s$/) {sub(/s/,"",v); v*=1000}; printf "%.2f", v}' "$work/wrk.txt")")
    total=$((total + $(awk '/requests in/ {print $1}' "$work/wrk.txt")))
  done
  local per="-"
  if [ -n "$metrics" ]; then g1=$(gets "$metrics"); per=$(awk -v g=$((g1 - g0)) -v n="$total" 'BEGIN {printf "%.3f", g / n}'); fi
  python3 - "$label" "$per" "${rps[*]}" "${p99[*]}" <<'EOF'
import statistics, sys
label, per, rps, p99 = sys.argv[1], sys.argv[2], [float(x) for x in sys.argv[3].split()], [float(x) for x in sys.argv[4].split()]
med = statistics.median
print(f"| {label} | {med(rps):,.0f} | {min(rps):,.0f} to {max(rps):,.0f} | {med(p99):.2f} | {min(p99):.2f} to {max(p99):.2f} | {per} |")
EOF
}

echo "placement: $placement; load: wrk -t2 -c64 -d${SECONDS_PER_RUN}s --latency over every heights URL, $ROUNDS rounds after a 2 s warm-up; $(nproc) CPUs, load average before: $(cut -d' ' -f1-3 /proc/loadavg)"
for db in "$@"; do
  db=$(cd "$db" && pwd)
  name=$(basename "$db")
  "$SERVER" publish "$db" "s3://tiles/$name" --quiet >/dev/null
  python3 - "$db/manifest.json" "$work/urls.txt" "$work/cycle.lua" <<'EOF'
import json, sys
m = json.load(open(sys.argv[1]))
cv = m["content_version"]
paths = [f"/v1/{cv}/levels/{l}/tiles/{x}/{y}/heights"
         for l, level in enumerate(m["levels"])
         for y in range(level["grid"]["rows"]) for x in range(level["grid"]["columns"])]
open(sys.argv[2], "w").write("\n".join(paths))
with open(sys.argv[3], "w") as f:
    f.write("local paths = {\n" + "".join(f'  "{p}",\n' for p in paths) + "}\n")
    f.write("local i = 0\nrequest = function()\n  i = i % #paths + 1\n  return wrk.format(\"GET\", paths[i])\nend\n")
EOF
  echo
  echo "$name: $(wc -l <"$work/urls.txt" | awk '{print $1 + 1}') heights URLs"
  echo
  echo "| served from | requests/s (median) | range | p99 ms (median) | range | GETs to the store a request |"
  echo "|---|---:|---|---:|---|---:|"
  serve "$db"; one_pass "$base"; measure "directory" "$base"; stop_last
  serve "s3://tiles/$name" --cache-bytes 0; measure "store, no cache" "$base" "$base"; stop_last
  serve "s3://tiles/$name"; one_pass "$base"; measure "store, cache warm" "$base" "$base"
  mkdir -p "$work/nginx-$name"
  sed -e "s|@DIR@|$work/nginx-$name|g" -e "s|@LISTEN@|127.0.0.1:$PROXY_PORT|" docker/nginx-replicas.conf.in \
    | sed 's|^    access_log .*|    access_log off;|' \
    | awk -v ups="        server ${base#http://};" '{ if ($0 == "@UPSTREAMS@") print ups; else print }' >"$work/nginx-$name/nginx.conf"
  "${ON_SERVER[@]}" "$NGINX" -p "$work/nginx-$name" -c "$work/nginx-$name/nginx.conf" -g 'daemon off;' 2>"$work/nginx-$name/stderr.log" &
  pids+=($!)
  for _ in $(seq 200); do curl -s -o /dev/null "http://127.0.0.1:$PROXY_PORT/healthz" && break; sleep 0.05; done
  one_pass "http://127.0.0.1:$PROXY_PORT"
  measure "nginx cache in front of the store replica" "http://127.0.0.1:$PROXY_PORT" "$base"
  stop_last; stop_last
done
echo
echo "load average after: $(cut -d' ' -f1-3 /proc/loadavg)"
