#!/usr/bin/env bash
# Frame times of every method at its 1 px setting, this checkout against an earlier commit,
# in the same run: both clients are built, then `terrain-client bench accuracy` runs each
# over the same databases in alternating rounds (before, after, before, ...), so that the
# machine's load falls on both alike. Prints, per dataset and method, each round's frame
# time (the median of `--repeats 5` draws per camera, mean over the 8 cameras: the
# summary's `frame (ms)`) and the median over the rounds, and writes them to
# OUT/frame-times.md with the stamp of this run.
#
#   bash scripts/frame-times.sh BEFORE_COMMIT [ROUNDS]
#
# The 1 px settings: the strip masks with a budget past their 1 px cap (1,000,000),
# GeoMipMaps and the quadtree patches at 1 px, the projected grids at 256x144 (the
# projective grid at 1 px). Jacksboro always; Puget Sound too when TERRAIN_DATA_DIR holds
# the data kit. Outputs under ${OUT:-out/frame-times}.
set -euo pipefail
cd "$(dirname "$0")/.."
before=${1:?usage: bash scripts/frame-times.sh BEFORE_COMMIT [ROUNDS]}
rounds=${2:-3}
git rev-parse --verify --quiet "$before^{commit}" >/dev/null || { echo "error: $before is not a commit here" >&2; exit 2; }
source scripts/gpu-env.sh
source scripts/stamp.sh
mkdir -p "${OUT:-out/frame-times}"
out=$(cd "${OUT:-out/frame-times}" && pwd)

echo "== building this checkout and $before"
cargo build --release -p terrain-server -p terrain-client --locked
tree="$out/before-tree"
rm -rf "$tree"
git worktree prune
git worktree add --detach --force "$tree" "$before" >/dev/null
trap 'git worktree remove --force "$tree" 2>/dev/null || true; kill $(jobs -p) 2>/dev/null || true' EXIT
(cd "$tree" && CARGO_TARGET_DIR="$out/before-target" cargo build --release -p terrain-client --locked)
after_bin=target/release/terrain-client
before_bin="$out/before-target/release/terrain-client"

declare -A dems=([jacksboro]=tests/fixtures/jacksboro/jacksboro_fault_dem.png)
if [ -n "${TERRAIN_DATA_DIR:-}" ] && [ -f "$TERRAIN_DATA_DIR/puget_sound_1k/ps_height_1k.png" ]; then
  dems[puget_sound_1k]=$TERRAIN_DATA_DIR/puget_sound_1k/ps_height_1k.png
else
  echo "NOT RUN: Puget Sound (set TERRAIN_DATA_DIR to the data kit to include it)"
fi
declare -A urls=()
for name in "${!dems[@]}"; do
  target/release/terrain-server build "${dems[$name]}" --out "$out/db/$name" --force --quiet --no-web --patches >/dev/null
  target/release/terrain-server serve "$out/db/$name" --addr 127.0.0.1:0 >"$out/$name.stdout" 2>"$out/$name.log" &
  for _ in $(seq 200); do
    urls[$name]=$(sed -n 's/^listening on //p' "$out/$name.stdout"); [ -n "${urls[$name]}" ] && break; sleep 0.05
  done
  [ -n "${urls[$name]}" ] || { echo "error: the server of $name did not start; see $out/$name.log" >&2; exit 1; }
done

mkdir -p "$out/runs"
for round in $(seq "$rounds"); do
  for which in before after; do
    bin=$after_bin; [ "$which" = before ] && bin=$before_bin
    for name in "${!dems[@]}"; do
      echo "== round $round of $rounds: $which, $name"
      "$bin" bench accuracy --server "${urls[$name]}" --out "$out/runs/$which-$name-$round" \
        --methods strip-masks,geomipmap,pgm,projective-grid,quadtree-patches --fillers none \
        --budgets 1000000 --max-errors-px 1 --grids 256x144 --popping-frames 0 --repeats 5 \
        >"$out/runs/$which-$name-$round.txt" 2>&1 || { echo "error: see $out/runs/$which-$name-$round.txt" >&2; exit 1; }
    done
  done
done

python3 - "$out" "$before" "$(git rev-parse --short HEAD)" "$(stamp_line)" <<'EOF'
import collections, glob, os, statistics, sys
out, before, after, stamp = sys.argv[1:]
times = collections.defaultdict(list)
for path in sorted(glob.glob(os.path.join(out, "runs", "*", "summary.md"))):
    which, name, _ = os.path.basename(os.path.dirname(path)).split("-", 2)
    header = None
    for line in open(path):
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells[0] == "method":
            header = cells
            continue
        if header is None or len(cells) != len(header) or cells[0].startswith("---"):
            continue
        times[(name, cells[0], which)].append(float(cells[header.index("frame (ms)")]))
lines = [f"Run: {stamp}. Frame time (ms, llvmpipe) at each method's 1 px setting, before ({before}) and after ({after}), rounds alternating.", "",
         "| dataset | method | before: rounds | median | after: rounds | median | after / before |", "|---|---|---|---:|---|---:|---:|"]
for (name, method) in sorted({(k[0], k[1]) for k in times}):
    b, a = times[(name, method, "before")], times[(name, method, "after")]
    mb, ma = statistics.median(b), statistics.median(a)
    lines.append(f"| {name} | {method} | {', '.join(f'{x:.1f}' for x in b)} | {mb:.1f} | {', '.join(f'{x:.1f}' for x in a)} | {ma:.1f} | {ma / mb:.2f} |")
text = "\n".join(lines) + "\n"
open(os.path.join(out, "frame-times.md"), "w").write(text)
print(text)
EOF
echo "wrote $out/frame-times.md"
