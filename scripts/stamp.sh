#!/usr/bin/env bash
# The stamp of a figure written by a shell script, as tests/src/stamp.rs writes it for the
# benches: `commit C, CPU (N cores, M GiB), YYYY-MM-DD`. Sourced: defines stamp_line.
# A script that writes tracked files while it runs exports STAMP_COMMIT=$(stamp_commit)
# before its first write, so that its own outputs do not stamp it "-dirty" (the Rust
# benches read the same variable, tests/src/stamp.rs).
stamp_commit() {
  local hash dirty
  hash=$(git rev-parse --short=7 HEAD 2>/dev/null || echo unknown)
  dirty=$(git status --porcelain --untracked-files=no 2>/dev/null | head -c1)
  [ -n "$dirty" ] && hash="$hash-dirty"
  echo "$hash"
}
stamp_line() {
  local hash cpu cores gib
  hash=${STAMP_COMMIT:-$(stamp_commit)}
  cpu=$(sed -n 's/^model name[[:space:]]*:[[:space:]]*//p' /proc/cpuinfo 2>/dev/null | head -n1)
  cores=$(nproc 2>/dev/null || echo 1)
  gib=$(awk '/^MemTotal:/ {printf "%.0f", $2 / 1048576}' /proc/meminfo 2>/dev/null)
  echo "commit $hash, ${cpu:-unknown CPU} ($cores cores, ${gib:-?} GiB), $(date -u +%Y-%m-%d)"
}
