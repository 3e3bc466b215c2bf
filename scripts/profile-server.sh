#!/usr/bin/env bash
# Profiles the release `terrain-server serve` under the HTTP benchmark's load: where each
# layer of a tile request spends the server's CPU.
#
#   scripts/profile-server.sh DB [SECONDS]
#   OUT=/tmp/profile scripts/profile-server.sh out/bench/db/himalaya_4097 20
#
# The server runs on one CPU with one worker thread (`taskset`), wrk with the benchmark's
# settings (`wrk -t2 -c64`, cycling over every heights URL of the database) on another, so
# the load generator never shows up in the server's samples. After a warm-up, `perf record`
# samples the server for SECONDS (default 15) at 999 Hz with DWARF call graphs (release
# builds keep no frame pointers; `debug = "line-tables-only"` gives perf the line tables it
# unwinds and names inlined frames with).
#
# Writes into $OUT (default target/profile/):
#   flamegraph.svg   the server's samples, one tower per call path (inferno);
#   top.txt          the wrk summary, the functions with the most samples of their own,
#                    and the share of samples in each layer of the request path;
#   collapsed.txt    one line per distinct stack (inlined frames included) with its CPU
#                    time in nanoseconds (inferno's format), what the flame graph draws;
#   perf.data        the raw recording, for `perf report -i`.
#
# Settings: TERRAIN_BENCH_CONNECTIONS (default 64, as the benchmark), PROFILE_CALL_GRAPH
# (dwarf, or fp for a binary built with frame pointers), PROFILE_TOP (functions listed,
# default 40), TERRAIN_SERVER (a server binary to use instead of building the release one).
# Needs: perf, wrk, taskset, curl, jq, python3, and inferno (`cargo install inferno`).
set -euo pipefail

if [ $# -lt 1 ] || [ $# -gt 2 ]; then
  echo "usage: $0 DB [SECONDS]" >&2
  exit 2
fi
db=$1
seconds=${2:-15}
repo=$(cd "$(dirname "$0")/.." && pwd)
out=${OUT:-$repo/target/profile}
connections=${TERRAIN_BENCH_CONNECTIONS:-64}
call_graph=${PROFILE_CALL_GRAPH:-dwarf}
top=${PROFILE_TOP:-40}
# Warm-up before sampling: page cache, TCP connections, the allocator's free lists.
warm_up_seconds=2
# 999 Hz rather than 1000 so the sampling never runs in lockstep with a 1 ms timer.
frequency=999

export PATH="$PATH:$HOME/.cargo/bin"
for tool in perf wrk taskset curl jq python3 inferno-collapse-perf inferno-flamegraph; do
  if ! command -v "$tool" >/dev/null; then
    echo "error: $tool is not on PATH (Debian: apt-get install linux-perf wrk util-linux curl jq python3; cargo install inferno)" >&2
    exit 1
  fi
done
if [ ! -f "$db/manifest.json" ]; then
  echo "error: $db is not a tile database (no manifest.json); build one with terrain-server build" >&2
  exit 1
fi

if [ -z "${TERRAIN_SERVER:-}" ]; then
  (cd "$repo" && cargo build --release -p terrain-server --quiet)
  binary=$repo/target/release/terrain-server
else
  binary=$TERRAIN_SERVER
fi

# The first usable CPU serves, the second loads; with one CPU both share it and the
# profile still holds, but the wrk summary is then no throughput figure.
cpus=$(python3 -c 'import os; print(" ".join(map(str, sorted(os.sched_getaffinity(0)))))')
read -r -a cpu_list <<<"$cpus"
server_cpu=${cpu_list[0]}
if [ "${#cpu_list[@]}" -ge 2 ]; then
  wrk_cpu=${cpu_list[1]}
else
  wrk_cpu=$server_cpu
  echo "warning: one usable CPU: server and wrk share CPU $server_cpu (unpinned figures)" >&2
fi

mkdir -p "$out"
rm -f "$out/perf.data" "$out/perf.data.old"
work=$(mktemp -d)
server_pid=
cleanup() {
  if [ -n "$server_pid" ] && kill -0 "$server_pid" 2>/dev/null; then
    kill -TERM "$server_pid"
    wait "$server_pid" 2>/dev/null || true
  fi
  rm -rf "$work"
}
trap cleanup EXIT

# The one stdout line names the port (see server/src/http/cli.rs).
mkfifo "$work/stdout"
RUST_LOG=warn taskset -c "$server_cpu" "$binary" serve "$db" \
  --addr 127.0.0.1:0 --worker-threads 1 >"$work/stdout" 2>"$out/server.log" &
server_pid=$!
exec 3<"$work/stdout"
if ! read -r -t 60 line <&3; then
  echo "error: the server printed no address; its log:" >&2
  cat "$out/server.log" >&2
  exit 1
fi
addr=${line#listening on http://}

# Every level's tiles, as terrain_shared::routes::heights spells them, cycled per wrk thread as in the benchmark.
curl -fsS "http://$addr/v1/manifest.json" >"$work/manifest.json"
{
  echo "local paths = {"
  jq -r '.content_version as $v | .levels | to_entries[] | .key as $l | .value.grid as $g
         | range(0; $g.rows) as $y | range(0; $g.columns) as $x
         | "  \"/v1/\($v)/levels/\($l)/tiles/\($x)/\($y)/heights\","' "$work/manifest.json"
  echo "}"
  echo "local i = 0"
  echo "request = function()"
  echo "  i = i % #paths + 1"
  echo "  return wrk.format(\"GET\", paths[i])"
  echo "end"
} >"$work/cycle.lua"
tiles=$(jq '[.levels[].grid | .rows * .columns] | add' "$work/manifest.json")

load() {
  taskset -c "$wrk_cpu" wrk -t2 -c"$connections" -d"$1"s --latency -s "$work/cycle.lua" "http://$addr"
}

echo "server on CPU $server_cpu (pid $server_pid), wrk on CPU $wrk_cpu, $tiles heights URLs, $seconds s sampled"
load "$warm_up_seconds" >/dev/null
# perf runs on wrk's CPU too, so writing its samples costs the server nothing.
taskset -c "$wrk_cpu" perf record -e cpu-clock -F "$frequency" -g --call-graph "$call_graph" \
  -p "$server_pid" -o "$out/perf.data" -- sleep "$seconds" 2>"$work/perf-record.log" &
perf_pid=$!
load "$seconds" >"$work/wrk.txt"
wait "$perf_pid"
cat "$work/wrk.txt"
load_average=$(cut -d' ' -f1-3 /proc/loadavg)

# The flame graph shows inlined frames too: most of tower's and axum's layers are inlined
# in a release build. Their names come from DWARF without a module path but with every
# generic argument (some holding `;`, which the collapsed format cannot carry), so the
# layer table below reads the symbol-table frames only; an inlined layer's cost counts
# for the function it was inlined into.
perf script -i "$out/perf.data" --inline 2>/dev/null >"$work/perf.script"
inferno-collapse-perf --all "$work/perf.script" >"$out/collapsed.txt"
perf script -i "$out/perf.data" 2>/dev/null >"$work/perf-symbols.script"
inferno-collapse-perf --all "$work/perf-symbols.script" >"$work/collapsed-symbols.txt"
inferno-flamegraph --title "terrain-server, $tiles heights URLs, wrk -t2 -c$connections, $(basename "$db")" \
  "$out/collapsed.txt" >"$out/flamegraph.svg"

{
  echo "terrain-server under wrk -t2 -c$connections on $(basename "$db") ($tiles heights URLs)"
  echo "server CPU $server_cpu, wrk CPU $wrk_cpu, $seconds s at $frequency Hz, call graph $call_graph"
  echo "CPU: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2- | sed 's/^ //'), load average after: $load_average"
  echo
  cat "$work/wrk.txt"
  echo
  requests=$(awk '/requests in/ { print $1 }' "$work/wrk.txt")
  python3 - "$work/collapsed-symbols.txt" "$top" "${requests:-0}" <<'PYTHON'
"""Self time per function and the share of samples in each layer of the request path."""
import re
import sys
from collections import Counter

collapsed, top, requests = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
stacks = []
for line in open(collapsed):
    stack, _, count = line.rstrip("\n").rpartition(" ")
    stacks.append((stack.split(";"), int(count)))
total = sum(count for _, count in stacks)
if total == 0:
    sys.exit("no samples")

def name(frame):
    """A frame as `module::path::Type::method`, without generic arguments, so patterns can
    match a module path from the start."""
    # inferno appends _[k] to kernel frames.
    frame = re.sub(r"_\[[a-z]\]$", "", frame)
    # `<hyper::proto::h1::role::Server as hyper::proto::h1::Http1Transaction>::encode`
    # is the self type's method.
    implementation = re.match(r"<(?:&(?:mut )?)?([^<> ]+)", frame)
    if implementation:
        return implementation.group(1) + "::" + frame.rsplit(">::", 1)[-1]
    while True:
        stripped = re.sub(r"<[^<>]*>", "", frame)
        if stripped == frame:
            return frame
        frame = stripped

# cpu-clock samples carry their period: the counts are nanoseconds of the server's CPU.
print(f"{total / 1e9:.2f} s of server CPU sampled", end="")
if requests:
    # wrk's count covers the sampled seconds within the warm-up's rounding.
    per_request_us = total / 1e3 / requests
    print(f" over {requests} requests: {per_request_us:.1f} us per request, so 1% = {per_request_us / 100:.2f} us", end="")
print("\n\nthe functions with the most of it as their own (self time):")
leaves = Counter()
for frames, count in stacks:
    leaves[name(frames[-1])] += count
for function, count in leaves.most_common(top):
    print(f"{100 * count / total:6.2f}%  {function[:150]}")

# Each layer: a pattern on frame names. A sample counts for a layer when its stack holds a
# matching frame ("inclusive", the cost of the layer and everything it calls), and for
# the innermost matching layer alone ("attributed", so the attributed shares add up to
# 100%: a malloc called from the metrics middleware is the allocator's, its caller's
# other work the middleware's).
LAYERS = [
    ("kernel: socket write (writev, TCP send)", r"__x64_sys_(write|writev|sendto|sendmsg)$|do_writev|sock_write_iter|tcp_sendmsg"),
    ("kernel: socket read (read, TCP receive)", r"__x64_sys_(read|recvfrom|recvmsg)$|ksys_read|sock_read_iter|tcp_recvmsg"),
    ("kernel: epoll", r".*epoll"),
    ("kernel: syscall entry and exit", r"entry_SYSCALL_64|do_syscall_64|syscall_exit"),
    ("allocator (malloc, free)", r"(__libc_)?(malloc|free|realloc|calloc|cfree)$|_int_(malloc|free)|tcache_|malloc_consolidate|__rust_(alloc|dealloc|realloc)|alloc::alloc::"),
    ("memcpy, memmove", r"__mem(cpy|move)"),
    ("tracing (spans, events, subscriber)", r"tracing(_core|_subscriber)?::"),
    ("metrics: prometheus counters, histogram", r"prometheus_client::"),
    ("metrics middleware (observe, CountedBody)", r"terrain_server::http::metrics::"),
    ("handler: entity (ETag, If-None-Match, headers)", r"terrain_server::http::routes::entity|headers::"),
    ("handler: heights (checks, lookup)", r"terrain_server::http::routes::(heights|Conditional)|terrain_server::db::|terrain_server::http::AppState"),
    ("axum: Path extraction", r"axum::extract::path|serde::de|percent_encoding"),
    ("axum: routing (Router, matchit, MatchedPath)", r"axum::routing|matchit::|axum::extract::matched_path"),
    ("etag weakening (map_response)", r"terrain_server::http::weaken_etag_when_encoded"),
    ("axum: from_fn, map_response glue", r"axum::middleware::"),
    ("axum: Body boxing", r"axum_core::body|http_body_util::"),
    ("tower-http: CORS", r"tower_http::cors"),
    ("tower-http: compression", r"tower_http::compression|async_compression|flate2"),
    ("tower: load shed, concurrency limit, timeout", r"tower::(load_shed|limit|timeout|util)|axum::error_handling"),
    ("tokio: timers (header read timeout, request timeout)", r"tokio::time|tokio::runtime::time|hyper_util::rt::tokio::Tokio(Timer|Sleep)"),
    ("serve: connection task, service_fn", r"terrain_server::http::serve::"),
    ("hyper: parse request head", r"hyper::proto::h1::role::Server::parse|httparse::"),
    ("hyper: encode response head", r"hyper::proto::h1::role::Server::encode|hyper::headers::"),
    ("hyper: dispatch, buffers, body", r"hyper::|hyper_util::"),
    ("http: HeaderMap, Extensions", r"http::"),
    ("bytes", r"bytes::"),
    ("tokio: scheduler, I/O driver", r"tokio::"),
]
compiled = [(label, re.compile(pattern)) for label, pattern in LAYERS]
inclusive, attributed = Counter(), Counter()
for frames, count in stacks:
    names = [name(frame) for frame in frames]
    for label, pattern in compiled:
        if any(pattern.match(frame) for frame in names):
            inclusive[label] += count
    owner = "other (user space outside the layers above)"
    for frame in reversed(names):
        hit = next((label for label, pattern in compiled if pattern.match(frame)), None)
        if hit:
            owner = hit
            break
    else:
        if any(frame.endswith("_[k]") for frame in frames):
            owner = "kernel: other"
    attributed[owner] += count

print()
print("layers, share of the server's samples:")
print(f"{'inclusive':>10} {'attributed':>11}  layer")
for label, _ in LAYERS + [("kernel: other", None), ("other (user space outside the layers above)", None)]:
    if inclusive[label] or attributed[label]:
        print(f"{100 * inclusive[label] / total:9.2f}% {100 * attributed[label] / total:10.2f}%  {label}")
PYTHON
} >"$out/top.txt"

perf report -i "$out/perf.data" --no-children --sort symbol --stdio --percent-limit 0.5 \
  -g none 2>/dev/null >"$out/report.txt" || true
echo
cat "$out/top.txt"
echo
echo "wrote $out/flamegraph.svg, $out/top.txt, $out/report.txt, $out/collapsed.txt, $out/perf.data"
