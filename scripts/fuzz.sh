#!/usr/bin/env bash
# Fuzzes every decoder of untrusted bytes: the heights codec, the manifest parser and the
# builder's PNG, GeoTIFF and .hgt readers (the cargo-fuzz targets in fuzz/; what each feeds
# to which function is fuzz/src/lib.rs).
#
#   scripts/fuzz.sh [SECONDS_PER_TARGET] [TARGET...]
#
# Each target runs from its committed corpus (fuzz/corpus/<target>) until it has run
# $FUZZ_RUNS inputs (default 1,000,000) or SECONDS_PER_TARGET (default 900) have passed,
# under a 2 GiB memory limit and a 10 s limit per input; then one line says the inputs run,
# the seconds and the crashes. It exits non-zero when a target crashed or fell short of
# $FUZZ_RUNS.
#
# New inputs go to fuzz/target/work/<target>; FUZZ_KEEP=1 merges those that add coverage
# into fuzz/corpus/<target>, which tests/e2e/fuzz_corpora.rs replays on stable. A crash is
# written to fuzz/artifacts/<target>/: fix the code, then copy the file to
# fuzz/regressions/<target>/ so the tests keep replaying it.
#
# Needs the nightly toolchain (libFuzzer's instrumentation); installs cargo-fuzz when
# missing. Nothing in scripts/test.sh depends on this script.
set -euo pipefail
cd "$(dirname "$0")/../fuzz"

seconds=${1:-900}
shift || true
all=(heights_decode manifest_parse read_png read_geotiff read_hgt)
if [ $# -eq 0 ]; then targets=("${all[@]}"); else targets=("$@"); fi
runs=${FUZZ_RUNS:-1000000}

if ! rustup toolchain list 2>/dev/null | grep -q '^nightly'; then
  echo "error: fuzzing needs a nightly toolchain: rustup toolchain install nightly" >&2
  exit 2
fi
command -v cargo-fuzz >/dev/null || cargo +nightly install cargo-fuzz --locked
cargo +nightly fuzz build

failed=0
printf '%-16s %10s %8s %8s\n' target inputs seconds crashes
for target in "${targets[@]}"; do
  work=target/work/$target
  mkdir -p "$work" "artifacts/$target"
  before=$(ls "artifacts/$target" | wc -l)
  started=$(date +%s)
  cargo +nightly fuzz run "$target" "$work" "corpus/$target" -- \
    -runs="$runs" -max_total_time="$seconds" -rss_limit_mb=2048 -timeout=10 \
    -print_final_stats=1 >"$work.log" 2>&1 || true
  elapsed=$(($(date +%s) - started))
  inputs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$work.log" | tail -n 1)
  crashes=$(($(ls "artifacts/$target" | wc -l) - before))
  printf '%-16s %10s %8s %8s\n' "$target" "${inputs:-?}" "$elapsed" "$crashes"
  if [ "$crashes" -gt 0 ] || [ "${inputs:-0}" -lt "$runs" ]; then
    failed=1
    grep -m 5 -E 'panicked|ERROR|SUMMARY' "$work.log" | sed 's/^/    /' || true
    echo "    log: fuzz/$work.log"
  fi
  if [ "${FUZZ_KEEP:-0}" = 1 ]; then
    cargo +nightly fuzz run "$target" "corpus/$target" "$work" -- -merge=1 >>"$work.log" 2>&1
  fi
done
exit "$failed"
