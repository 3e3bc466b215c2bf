#!/usr/bin/env bash
# A build split into region jobs that write to an object store, then a merge from the store
# into the store, on this machine: a SeaweedFS store on loopback, N jobs
# (`terrain-server build DEM --region I/N --out s3://tiles/jobs/NAME`) run P at a time as
# separate processes (as a job runner would run them on N machines), `terrain-server merge
# s3://tiles/jobs/NAME --out s3://tiles/NAME`, and one ordinary build of the same DEM to
# compare with. Prints each job's and the merge's time, peak RSS and bytes, whether the
# merged content version is the single build's, and writes OUT/summary.md (stamped with
# the commit and the machine).
#
#   bash scripts/build-jobs.sh                  # the bundled jacksboro sample, 3 jobs
#   bash scripts/build-jobs.sh DEM [--jobs 3] [--parallel 1] [--out out/build-jobs]
#                              [--record docs/benchmarks/build-jobs-NAME.md]
#
# --record FILE also writes the summary to FILE and puts it into README.md's generated block
# of that name. Installs weed when missing (scripts/scale-setup.sh).
set -euo pipefail
cd "$(dirname "$0")/.."

ARGS="$*"
DEM=tests/fixtures/jacksboro/jacksboro_fault_dem.png
JOBS=3
PARALLEL=1
OUT=out/build-jobs
RECORD=""
while [ $# -gt 0 ]; do
  case "$1" in
    --jobs) JOBS="$2"; shift 2 ;;
    --parallel) PARALLEL="$2"; shift 2 ;;
    --out) OUT="$2"; shift 2 ;;
    --record) RECORD="$2"; shift 2 ;;
    -h|--help) sed -n '2,17p' "$0"; exit 0 ;;
    -*) echo "build-jobs.sh: unknown option $1 (see --help)" >&2; exit 64 ;;
    *) DEM="$1"; shift ;;
  esac
done
[ -e "$DEM" ] || { echo "build-jobs.sh: $DEM does not exist" >&2; exit 66; }
say() { printf '[build-jobs] %s\n' "$*"; }

tools=$(bash scripts/scale-setup.sh)
WEED=$(sed -n 's/^weed: \([^ ]*\).*/\1/p' <<<"$tools")
cargo build --release --locked -p terrain-server -q
SERVER=$(pwd)/target/release/terrain-server
source scripts/stamp.sh

rm -rf "$OUT"
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null || true; }
trap cleanup EXIT

source scripts/lib-store.sh
start_store "$WEED" "$OUT/store" "$OUT/store.log"
pids+=("$STORE_PID")
NAME=$(basename "${DEM%.*}")
JOBS_URL="s3://tiles/jobs/$NAME"
DB_URL="s3://tiles/$NAME"
say "object store: weed mini, S3 on $AWS_ENDPOINT"
say "one build of $DEM, to compare with"
/usr/bin/time -f '%e|%M' -o "$OUT/one.time" "$SERVER" build "$DEM" --out "$OUT/one" -q >"$OUT/one.txt"
ONE_VERSION=$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["content_version"])' "$OUT/one/manifest.json")
# The store takes a moment to take writes after it answers: the comparison build is
# published to it until it does.
for attempt in 1 2 3 4 5 6 7 8 9 10; do
  "$SERVER" publish "$OUT/one" s3://tiles/one -q >"$OUT/probe.txt" 2>&1 && break
  say "the store is not taking writes yet (attempt $attempt)"; sleep 2
done

say "$JOBS region jobs, $PARALLEL at a time, each uploading to $JOBS_URL"
export SERVER DEM JOBS JOBS_URL OUT
started=$(date +%s.%N)
seq 0 $((JOBS - 1)) | xargs -P "$PARALLEL" -I{} sh -c \
  '/usr/bin/time -f "%e|%M" -o "$OUT/job-{}.time" "$SERVER" build "$DEM" --region {}/"$JOBS" --out "$JOBS_URL" -q >"$OUT/job-{}.txt" 2>"$OUT/job-{}.err" || { cat "$OUT/job-{}.err" >&2; exit 255; }'
jobs_wall=$(python3 -c "import sys; print(f'{float(sys.argv[2]) - float(sys.argv[1]):.1f}')" "$started" "$(date +%s.%N)")

say "merge from $JOBS_URL into $DB_URL"
/usr/bin/time -f '%e|%M' -o "$OUT/merge.time" "$SERVER" merge "$JOBS_URL" --out "$DB_URL" -q >"$OUT/merge.txt"
MERGED_VERSION=$(sed -n 's/^published .*content version \([0-9a-f]*\).*/\1/p' "$OUT/merge.txt")
cat "$OUT/merge.txt"

mib() { python3 -c "import sys; print(f'{int(sys.argv[1]) / 1048576:.1f}')" "$1"; }
{
  echo "**$NAME** built as $JOBS region jobs ($PARALLEL at a time on this machine) writing to a SeaweedFS store, and a merge from the store into the store:"
  echo
  echo "Run: $(stamp_line)."
  echo
  echo "| process | tiles | seconds | peak RSS | to the store |"
  echo "|---|---|---:|---:|---:|"
  for i in $(seq 0 $((JOBS - 1))); do
    IFS='|' read -r s rss <"$OUT/job-$i.time"
    tiles=$(sed -n 's/^  tiles *//p' "$OUT/job-$i.txt")
    up=$(sed -n 's/^  uploaded *\([0-9.]* MiB\).*/\1/p' "$OUT/job-$i.txt")
    echo "| job $i/$JOBS | $tiles | $s | $((rss / 1024)) MiB | $up |"
  done
  IFS='|' read -r s rss <"$OUT/merge.time"
  up=$(sed -n 's/^published .*, \([0-9.]* MiB\) uploaded.*/\1/p' "$OUT/merge.txt")
  levels=$(sed -n 's/^  tiles .*; \([0-9]* levels, [0-9]* tiles in all\)/\1/p' "$OUT/merge.txt")
  echo "| merge | $levels | $s | $((rss / 1024)) MiB | $up |"
  IFS='|' read -r s rss <"$OUT/one.time"
  echo "| one build, for comparison (to a directory) | the same | $s | $((rss / 1024)) MiB | |"
  echo
  echo "The jobs took $jobs_wall s of wall time together. Each job read the whole DEM ($(mib "$(stat -c %s "$DEM")") MiB) and held only its own region's files; the merge held no DEM, only the database it wrote and one job file at a time."
  echo
  if [ "$MERGED_VERSION" = "$ONE_VERSION" ]; then
    echo "Merged content version $MERGED_VERSION: the same as one build's."
  else
    echo "Merged content version ${MERGED_VERSION:-none}, one build's $ONE_VERSION: **they differ**."
  fi
} >"$OUT/summary.md"
cat "$OUT/summary.md"
if [ -n "$RECORD" ]; then
  { echo "<!-- written by \`bash scripts/build-jobs.sh $ARGS\`; do not edit -->"; cat "$OUT/summary.md"; } >"$RECORD"
  bash scripts/insert-generated.sh README.md "$RECORD"
fi
[ "$MERGED_VERSION" = "$ONE_VERSION" ]
