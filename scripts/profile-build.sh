#!/usr/bin/env bash
# Where a build's time goes: `perf record` of `terrain-server build DEM [FLAGS…]`, every
# thread, then each sample put in the stage of the build it belongs to, and a table of the
# stages' shares of the CPU time.
#
#   bash scripts/profile-build.sh DEM [FLAGS…]
#   OUT=/tmp/profile-build bash scripts/profile-build.sh ../shared/data/himalaya_4097/g10g_himalaya_4097.png
#   RECORD=docs/benchmarks/build-profile.md bash scripts/profile-build.sh DEM   # and into BENCHMARKS.md
#
# perf samples at 199 Hz with DWARF call graphs (release builds keep no frame pointers;
# `debug = "line-tables-only"` gives perf what it unwinds with). A sample counts for the
# innermost frame that names a stage (a zstd call made by the heights codec is the codec's;
# a deflate call made by the web tiles' PNG encoder is the web tiles' deflate's). Writes into $OUT
# (default target/profile-build/): table.md, collapsed.txt (inferno's format),
# flamegraph.svg, perf.data. Needs perf, python3 and inferno (`cargo install inferno`).
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -ge 1 ] || { echo "usage: $0 DEM [FLAGS…]" >&2; exit 2; }
for tool in perf python3 inferno-collapse-perf inferno-flamegraph; do
  command -v "$tool" >/dev/null || { echo "error: $tool is not on PATH (Debian: linux-perf, python3; cargo install inferno)" >&2; exit 1; }
done
out=${OUT:-target/profile-build}
mkdir -p "$out"
out=$(cd "$out" && pwd)
cargo build --release --locked -p terrain-server -q
source scripts/stamp.sh
dem=$1
shift
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

/usr/bin/time -f '%e %M' -o "$work/time" \
  perf record -F 199 -g --call-graph dwarf,16384 -o "$out/perf.data" -- \
  target/release/terrain-server build "$dem" --out "$work/db" --quiet "$@" >"$work/summary.txt" 2>"$work/perf.log"
read -r wall rss <"$work/time"
perf script -i "$out/perf.data" 2>/dev/null >"$work/perf.script"
inferno-collapse-perf --all "$work/perf.script" >"$out/collapsed.txt"
inferno-flamegraph --title "terrain-server build $(basename "$dem") $*" "$out/collapsed.txt" >"$out/flamegraph.svg"
samples=$(sed -n 's/.*(\([0-9]*\) samples).*/\1/p' "$work/perf.log")

{
  echo "\`terrain-server build $(basename "$dem")${*:+ $*}\` under perf: $wall s wall, largest peak RSS of perf and the build $rss KiB, $samples samples at 199 Hz. Run: $(stamp_line)."
  echo
  python3 - "$out/collapsed.txt" <<'PYTHON'
"""Each sample's stage: the innermost frame that names one."""
import re
import sys
from collections import Counter

# (stage, pattern on a frame's name), innermost first wins; the order only matters
# between patterns that could both name one frame.
STAGES = [
    ("web tiles: deflate (PNG and gzip)", r"miniz_oxide|zlib_rs|flate2|\bpng::encoder|png::text_metadata"),
    ("web tiles: quantized-mesh", r"web::quantized_mesh"),
    ("web tiles: sampling and reprojecting the pyramid", r"web::(source|build|crs|tiling)"),
    ("heights codec: zstd", r"ZSTD_|zstd"),
    ("heights codec: prediction, rANS and framing", r"terrain_shared::(heights|rans|codec|tile_blob)"),
    # One stage: `build::tiles::stats` computes the strip-mask errors
    # (`terrain_shared::mask`) with the bounds and roughness, and the inlined frames do not
    # always say which of them a sample was in.
    ("tile statistics: strip-mask errors, bounds, roughness", r"terrain_shared::mask|build::tiles"),
    ("textures: colour, mips and JPEG", r"build::texture|jpeg|image::codecs"),
    ("reading the DEM (PNG decode)", r"png::decoder|fdeflate|build::input|inflate"),
    ("no-data voids", r"build::voids"),
    ("levels: the pyramid", r"build::levels"),
    ("quadtree patches: errors of triangles against the samples", r"patches::(Patch::error|Span)"),
    ("quadtree patches: triangles of merges and cuts", r"quadtree::(triangles_|representative|canonical|Cut::)"),
    ("quadtree patches: the rest (merging, the pyramid, bodies, index)", r"build::patches|terrain_shared::quadtree"),
    ("hashing (blake3)", r"blake3"),
    ("writing the database", r"db::|DbWriter|std::fs|std::io::Write"),
    ("kernel", r"_\[k\]$"),
]
compiled = [(stage, re.compile(p)) for stage, p in STAGES]
PATCHES = re.compile(r"build::patches|terrain_shared::quadtree")
total = 0
shares = Counter()
for line in open(sys.argv[1]):
    stack, _, count = line.rstrip("\n").rpartition(" ")
    count = int(count)
    total += count
    stage = "other (allocation, rayon's scheduling, the rest)"
    frames = stack.split(";")
    for depth in range(len(frames) - 1, -1, -1):
        hit = next((s for s, p in compiled if p.search(frames[depth])), None)
        if hit:
            stage = hit
            break
    # zstd compresses the patches' bodies too (the heights use it only with
    # `--heights-codec zstd`): a zstd sample under the patches is theirs.
    if stage == "heights codec: zstd" and any(PATCHES.search(f) for f in frames[:depth]):
        stage = "quadtree patches: zstd of the bodies"
    shares[stage] += count
print("| stage | share of the CPU time |")
print("|---|---:|")
for stage, count in shares.most_common():
    print(f"| {stage} | {100 * count / total:.1f}% |")
PYTHON
} >"$out/table.md"
cat "$out/table.md"
if [ -n "${RECORD:-}" ]; then
  { echo "<!-- written by \`bash scripts/profile-build.sh $(basename "$dem")${*:+ $*}\`; do not edit -->"; cat "$out/table.md"; } >"$RECORD"
  bash scripts/insert-generated.sh BENCHMARKS.md "$RECORD"
fi
