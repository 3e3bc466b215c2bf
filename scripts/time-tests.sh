#!/usr/bin/env bash
# How long the two test tiers take here, each from a fresh clone of this commit (a new
# target directory: the build is part of the time), written stamped into
# docs/benchmarks/test-times.md.
#
#   bash scripts/time-tests.sh            # both tiers (the full one needs the data kit)
#   TIERS=default bash scripts/time-tests.sh
#   CACHE=1 bash scripts/time-tests.sh    # the clone builds into this checkout's target/
#       (dependencies already built: what a newcomer's second run, or one after the demo,
#       costs); without it each clone builds everything from scratch
#
# The default tier runs the README's test command without the data kit (what a newcomer
# runs); the full tier runs .ci/run (data kit, GPU adapter and browser required).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/stamp.sh
repo=$(pwd)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
rows=()
for tier in ${TIERS:-default full}; do
  rm -rf "$work/clone"
  git clone -q "$repo" "$work/clone"
  # The npm packages come from the registry as on any fresh machine.
  log="$work/$tier.log"
  if [ "${CACHE:-}" = 1 ]; then
    export CARGO_TARGET_DIR="$repo/target"
    build="dependencies built before (this checkout's target/)"
  else
    unset CARGO_TARGET_DIR
    build="from scratch"
  fi
  start=$(date +%s)
  if [ "$tier" = full ]; then
    (cd "$work/clone" && TERRAIN_DATA_DIR="${TERRAIN_DATA_DIR:-$repo/../shared/data}" bash .ci/run) >"$log" 2>&1 && ok=passed || ok=FAILED
  else
    (cd "$work/clone" && env -u TERRAIN_DATA_DIR -u REQUIRE_DATA -u REQUIRE_GPU -u REQUIRE_BROWSER -u TERRAIN_TEST_TIER bash scripts/test.sh) >"$log" 2>&1 && ok=passed || ok=FAILED
  fi
  seconds=$(( $(date +%s) - start ))
  passed=$(grep -o '[0-9]* passed' "$log" | awk '{s += $1} END {print s + 0}')
  failed=$(grep -o '[0-9]* failed' "$log" | awk '{s += $1} END {print s + 0}')
  not_run=$(grep -c '^NOT RUN\|NOT RUN:' "$log" || true)
  echo "$tier: $ok in $seconds s ($passed passed, $failed failed, $not_run NOT RUN lines)"
  # The log stays (cargo's build times and each test binary's are in it).
  mkdir -p out && cp "$log" "out/test-times-$tier.log"
  [ "$ok" = passed ] || tail -n 40 "$log"
  # Stamped from the clone: the commit that ran, not this checkout's edits.
  stamp=$(cd "$work/clone" && stamp_line)
  rows+=("| $tier | \`$( [ "$tier" = full ] && echo "bash .ci/run" || echo "bash scripts/test.sh" )\` | $stamp | $build | $ok | $(( seconds / 60 )) min $(( seconds % 60 )) s | $passed | $failed | $not_run |")
done
table=docs/benchmarks/test-times.md
# A tier not run this time keeps its row from the last run that timed it.
for tier in default full; do
  case " ${TIERS:-default full} " in *" $tier "*) continue ;; esac
  old=$(grep "^| $tier | " "$table" 2>/dev/null || true)
  [ -n "$old" ] && rows+=("$old")
done
{
  echo "<!-- written by \`bash scripts/time-tests.sh\`; do not edit -->"
  echo "Each tier from a fresh clone of the commit named, its build included; each row stamped by its own run."
  echo
  echo "| tier | command | run | build | result | time | tests passed | failed | NOT RUN lines |"
  echo "|---|---|---|---|---|---:|---:|---:|---:|"
  printf '%s\n' "${rows[@]}" | sort
} >"$table"
bash scripts/insert-generated.sh README.md "$table"
echo "docs/benchmarks/test-times.md written"
