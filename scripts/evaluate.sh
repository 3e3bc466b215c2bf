#!/usr/bin/env bash
# Regenerates docs/evaluation.md and its pictures in docs/evaluation/: the accuracy sweeps
# (error against triangles and frame time, cracks against budget, triangles used against
# needed) and the stability matrix, measured against full-resolution reference frames.
#
#   bash scripts/evaluate.sh                                    # jacksboro only (in-repo)
#   TERRAIN_DATA_DIR=../shared/data bash scripts/evaluate.sh    # Puget Sound headline and
#                                                               # every dataset scenario
#   bash scripts/evaluate.sh alps=path/to/alps.tif [NAME=DEM ...]  # and DEMs of your own:
#       each is swept too, and the stability matrix runs its altitude scenarios on it
#   REUSE=1 bash scripts/evaluate.sh [NAME=DEM ...]   # only assemble docs/evaluation.md from
#       the runs already in docs/evaluation/ (after re-running one bench there by hand)
#
# Builds each database into a temporary directory, serves it on a free local port, runs
# `terrain-client bench accuracy` and `bench stability`, and assembles the document.
set -euo pipefail
# DEMs of one's own, NAME=DEM: checked, and their paths made absolute before the cd below.
owns=()
for own in "$@"; do
  name=${own%%=*}
  dem=${own#*=}
  if [ "$name" = "$own" ] || ! [[ "$name" =~ ^[A-Za-z0-9_-]+$ ]]; then
    echo "error: $own: expected NAME=DEM, NAME of letters, digits, - and _ (a DEM of your own to evaluate too)" >&2
    exit 2
  fi
  [ -f "$dem" ] || { echo "error: $dem: no such file" >&2; exit 2; }
  owns+=("$name=$(realpath "$dem")")
done
set -- "${owns[@]}"
cd "$(dirname "$0")/.."

reuse=${REUSE:-0}
docs=docs/evaluation
own_sections=()
headline=jacksboro
[ -n "${TERRAIN_DATA_DIR:-}" ] && headline=puget
if [ "$reuse" = 1 ]; then
  for own in "$@"; do own_sections+=("${own%%=*}"); done
  [ -f "$docs/stability/stability.md" ] || { echo "error: REUSE=1 needs the runs in $docs" >&2; exit 2; }
else
source scripts/gpu-env.sh
cargo build --release --locked -p terrain-server -p terrain-client
bin=target/release
work=$(mktemp -d)
pids=()
trap 'kill "${pids[@]}" 2>/dev/null || true; rm -rf "$work"' EXIT
rm -rf "$docs"
mkdir -p "$docs"

# serve NAME INPUT: builds INPUT and serves it; sets $url.
serve() {
  "$bin/terrain-server" build "$2" --out "$work/$1" --patches --no-web >"$work/$1.build.log" 2>&1
  "$bin/terrain-server" serve "$work/$1" --addr 127.0.0.1:0 >"$work/$1.stdout" 2>"$work/$1.log" &
  pids+=($!)
  url=
  for _ in $(seq 200); do
    url=$(sed -n 's/^listening on //p' "$work/$1.stdout")
    [ -n "$url" ] && return 0
    sleep 0.05
  done
  echo "error: the server for $1 did not start" >&2
  cat "$work/$1.log" >&2
  exit 1
}

serve jacksboro tests/fixtures/jacksboro/jacksboro_fault_dem.png
jacksboro=$url
data=()
own_sections=()
headline=jacksboro
primary=$jacksboro
if [ -n "${TERRAIN_DATA_DIR:-}" ]; then
  kit=$TERRAIN_DATA_DIR
  serve puget "$kit/puget_sound_1k/ps_height_1k.png"
  puget=$url
  headline=puget
  primary=$puget
  serve grand_canyon_hoppe "$kit/grand_canyon_hoppe/gcanyon_elev_crop.bw.png"
  data+=(--data "grand_canyon_hoppe=$url")
  serve srtm_geotiff "$kit/srtm_geotiff/mt_rainier_90m.tif"
  data+=(--data "srtm_geotiff=$url")
  serve himalaya_4097 "$kit/himalaya_4097/g10g_himalaya_4097.png"
  data+=(--data "himalaya_4097=$url")
  "$bin/terrain-client" bench accuracy --server "$puget" --out "$docs/accuracy-puget" \
    --methods strip-masks,geomipmap,pgm,projective-grid,quadtree-patches --block-grids \
    | tee "$work/accuracy-puget.txt"
  # The quadtree patches without geomorphing, for the popping figure with it on and off.
  "$bin/terrain-client" bench accuracy --server "$puget" --out "$docs/accuracy-puget-no-morph" \
    --methods quadtree-patches --no-morph --label "puget_sound_1k, no morphing" \
    | tee "$work/accuracy-puget-no-morph.txt"
  # The guaranteed methods at 1 px against the oracle that frees the samples off screen.
  "$bin/terrain-client" bench accuracy --server "$puget" --out "$docs/accuracy-puget-on-screen" \
    --methods strip-masks,geomipmap,projective-grid,quadtree-patches --fillers none \
    --budgets 1000000 --max-errors-px 1 --grids 256x144 --popping-frames 0 --on-screen-oracle \
    --label "puget_sound_1k, on-screen oracle" | tee "$work/accuracy-puget-on-screen.txt"
  # The projected grids' paper tables, on the papers' own flight area.
  "$bin/terrain-client" bench grids --server "$puget" --out "$docs/grids" --cameras 3 \
    | tee "$work/grids.txt"
fi
"$bin/terrain-client" bench accuracy --server "$jacksboro" --out "$docs/accuracy-jacksboro" \
  --methods strip-masks,geomipmap,pgm,projective-grid,quadtree-patches --block-grids \
  | tee "$work/accuracy-jacksboro.txt"
"$bin/terrain-client" bench accuracy --server "$jacksboro" --out "$docs/accuracy-jacksboro-on-screen" \
  --methods strip-masks,geomipmap,projective-grid,quadtree-patches --fillers none \
  --budgets 1000000 --max-errors-px 1 --grids 256x144 --popping-frames 0 --on-screen-oracle \
  --label "jacksboro, on-screen oracle" | tee "$work/accuracy-jacksboro-on-screen.txt"
for own in "$@"; do
  name=${own%%=*}
  serve "$name" "${own#*=}"
  data+=(--data "$name=$url")
  "$bin/terrain-client" bench accuracy --server "$url" --out "$docs/accuracy-$name" \
    --methods strip-masks,geomipmap,pgm,projective-grid,quadtree-patches --label "$name" \
    | tee "$work/accuracy-$name.txt"
  own_sections+=("$name")
done
# Every method and crack filler in every scenario: each keeps its memory limit or is
# refused at start (memory-below-one-belt), which the table says.
"$bin/terrain-client" bench stability --server "$primary" "${data[@]}" --out "$docs/stability" \
  --methods strip-masks,reference,geomipmap,pgm,projective-grid,quadtree-patches \
  --fillers none,skirts,planar-shadow,planar-shadow-paper \
  | tee "$work/stability.txt"
# The crack fillers where methods are known to fail, each against the same frame without it.
"$bin/terrain-client" bench stability --server "$primary" --out "$docs/stability-fillers" \
  --methods strip-masks --fillers none,skirts,planar-shadow,planar-shadow-paper \
  --scenarios grazing-1deg,grazing-3deg,grazing-5deg,above-horizon,low-near-peak,below-surface,far-outside \
  | tee "$work/stability-fillers.txt"

fi

section() { # DATASET DIR
  echo "### $1"
  echo
  cat "$2/summary.md"
  echo
  if [ -f "$2/block-grids.md" ]; then
    cat "$2/block-grids.md"
    echo
  fi
  for chart in error-vs-triangles error-vs-frame-time error-vs-bytes popping cracks-vs-budget fillers-vs-budget used-vs-needed; do
    [ -f "$2/$chart.png" ] || continue
    echo "![$chart](evaluation/${2#docs/evaluation/}/$chart.png)"
    echo
  done
}

{
  cat <<EOF
# Evaluation: accuracy against speed, and stability

Regenerated by \`bash scripts/evaluate.sh\` (with \`TERRAIN_DATA_DIR\` set for the Puget Sound
headline and the dataset scenarios) on $(date -u +%Y-%m-%d), at commit $(git rev-parse --short HEAD)$(git diff --quiet HEAD -- client server shared 2>/dev/null || echo ' with local changes')$([ "$reuse" = 1 ] && echo ', assembled (REUSE=1) from runs made earlier, some by hand at earlier commits'). Every figure below comes from that run; the raw
per-frame rows are in \`docs/evaluation/*/accuracy.csv\` and \`stability/stability.csv\`.

## How frames are measured

- **Reference**: the same renderer at the same camera with every visible resident tile at
  full resolution (mask level 0), no budget, no filler (\`--method reference\`). In the
  accuracy sweep the whole database is resident, every texture level loaded.
- **Screen-space error** (Löffler et al.'s error-bounded projective grid, Tables 1 and 2;
  Yusov and Turlapov's screen-space error): the depth buffer is read back and turned into
  the world point each pixel shows; the error is the distance in pixels between that point
  and the true surface's point straight above or below it (the full-resolution mesh,
  split along the strips' diagonals), both projected. Reported as a distribution: mean,
  95th and 99th percentiles (each the mean over cameras of a frame's percentile), max and
  the share of terrain pixels above 1 px. The max is a single pixel, and often the
  measure's floor (below). Pixels showing a crack filler count too: a filler is drawn
  below the surface, so a visible one is a geometric error.
- **Crack pixels**: where the reference shows terrain and the frame shows a filler filling
  a crack, or the background with terrain above and below it in the same column. **Holes**
  are those left showing the background. A frame with a filler is drawn twice more: without
  it (pixels whose depth differs show the filler) and with the *crack probe*, deep skirts
  under every side a drawn tile shares (a side whose neighbour draws the same samples hides
  its skirt under that neighbour, so the probe differs from the unfilled frame exactly
  where the mesh has a crack). **Filler / leaks**: the pixels showing the filler, and of
  those the ones where the probe finds no crack (the filler shows past the border, a
  skyline, or in front of a surface). **Silhouette** pixels show the sky where the
  reference has terrain above the frame's own skyline: a coarser surface lower against the
  sky, an error of the level of detail rather than a crack.
- **Methods, each a curve over its own knob**: strip masks over a fixed global budget
  (shared by importance, within the 1 px error cap; the paper's crack fillers),
  GeoMipMaps over their error threshold (\`--max-errors-px\`, 0.5 to 16 px: each tile cut
  into GeoMipMaps of 9x9 samples, each drawn at the coarsest level, every 2^k-th sample,
  whose error projected at its own box is within it; borders stitched by adding the finer
  neighbour's vertices, so no filler is needed), and the projected
  grids over their grid size (\`--grids\`, 64x36 to 512x288 vertices): persistent grid
  mapping (\`pgm\`, a uniform screen grid cast from an auxiliary camera onto averaged
  height pyramids) and the error-bounded projective grid (\`projective-grid\`: warped to
  square cells on the ground, its error bound from min/max pyramids, rays cast in every
  pixel whose bound passes 1 px; the last column gives the share of pixels past the bound
  and the share ray cast, those and the pixels no grid triangle covered). The charts draw one
  line per method and filler and, dashed black, the Pareto front over all of them.
- **Oracle**: per camera and threshold, the fewest triangles of a right-triangulated
  irregular network (longest-edge bisection, as the Martini library builds for map
  clients) over every full-resolution tile in view, such that every sample stays within
  the threshold on screen (its vertical error projected by the same bound the methods use,
  at that sample). Top-down refinement with conformity closure gives the smallest such
  network (\`client/src/eval/oracle.rs\`, checked against a brute-force search of every
  network of small tiles). It is the least among those networks, not among every possible
  mesh; "used / oracle" is the triangles a method drew over the oracle's, over all cameras.
- **Bytes held**: what the scene holds after the frame, CPU bytes plus every GPU
  allocation for the terrain, with the whole database resident: the cost of each method's
  representation (index sets, per-tile buffers, texture blocks) on top of the same tiles.
- **Popping**: on an approach (40 frames from the first camera along its view direction,
  the distance to the ground it looks at halving over the flight, so that each tile's and
  patch's projected error doubles once and its level switches about once), each pixel's
  colour change (mean absolute difference of R, G, B) and depth change (percent of the
  distance) between consecutive frames; a method's mean and 99th percentile minus the
  reference's over the same cameras (\`client/src/eval/popping.rs\`). The means sum every
  step's change, so a level that switches at once and one that morphs over many frames give
  the same mean; the **jump** tells them apart: per step the mean change, and the largest
  excess of one step over the mean of the two steps beside it, in colour and in depth. What
  neighbouring steps share (edges re-sampled as the camera moves, an error that grows as
  the camera nears the surface) cancels; a switch made in one frame stands out (tested). A
  still camera gives zero (tested).
- **PSNR** of the colours against the reference.
- **Triangles needed**: per tile, the coarsest mask whose maximum vertical error (the
  builder's per-mask errors) keeps every pixel the tile draws within 1 px, by the bound of
  \`lod::needed\` (the view depth of the box's nearest corner and the angle off the view
  axis, not the distance alone, which lets errors past 1 px through off the axis); summed
  over the drawn tiles. GeoMipMaps choose their levels with the same bound, from level
  errors measured over every triangle a level draws under any stitch.
- **The measure's floor**: each sweep also measures the reference itself against the true
  surface; what it gets wrong (a rasterizer pinhole showing a point under the surface, on
  one or two pixels) no method can do better than, and is named in each summary's header.
- The strip masks never give a tile more than its needed mask (\`--no-error-cap\` lifts
  it), so a flat tile draws its coarsest mask.
- Budgets are fixed per row so that error against triangles does not depend on the
  machine; frame times are medians of three draws on the adapter named in each section.

## Accuracy sweeps

EOF
  if [ "$headline" = puget ]; then
    section "Puget Sound (headline)" "$docs/accuracy-puget"
  fi
  section "Jacksboro (bundled)" "$docs/accuracy-jacksboro"
  for name in "${own_sections[@]}"; do
    section "$name (given)" "$docs/accuracy-$name"
  done
  if [ -f docs/evaluation-h100/summary.md ]; then
    echo "### Puget Sound on a GPU"
    echo
    echo "The same sweep at 1920x1080 with \`--repeats 5 --methods strip-masks,geomipmap\`, run on an NVIDIA H100 (kept in"
    echo "\`docs/evaluation-h100/\`, not regenerated by this script: it needs that machine). It was measured"
    echo "on earlier code, before the sound error bound, the exact GeoMipMap level errors and MapBlocks: its"
    echo "GeoMipMaps rows show the 4.7 px maximum that those changes address, and draw whole tiles, not 9x9 blocks."
    echo "Error at a given budget differs from the 640x360 rows because pixels are smaller."
    echo
    cat docs/evaluation-h100/summary.md
    echo
    for chart in error-vs-frame-time error-vs-triangles; do
      echo "![$chart on the GPU](evaluation-h100/$chart.png)"
      echo
    done
  fi
  echo "## Against the on-screen oracle"
  echo
  echo "The oracle above meshes every full-resolution tile in view whole: a sample of such a tile is"
  echo "held to the threshold on screen or not, so a method that culls inside a tile (GeoMipMaps' 9x9"
  echo "blocks, the projected grids' screen grid) can draw fewer triangles than it on a camera. Here the"
  echo "guaranteed methods at their 1 px settings again, against the oracle that frees every sample"
  echo "none of whose cells is in view (\`bench accuracy --on-screen-oracle\`): it culls inside a tile as"
  echo "finely as any method can, and is the stricter yardstick."
  echo
  for d in puget jacksboro; do
    [ -f "$docs/accuracy-$d-on-screen/summary.md" ] || continue
    echo "### ${d/puget/Puget Sound}"
    echo
    awk '/^The oracle per camera/ {p = 1} /^Resident geometry/ {p = 0} p' \
      "$docs/accuracy-$d-on-screen/summary.md"
    echo
  done
  if [ -f "$docs/accuracy-puget-no-morph/accuracy.csv" ]; then
    echo "## Quadtree patches: popping with geomorphing on and off"
    echo
    echo "The Puget Sound sweep's quadtree patches again with \`--no-morph\` (levels switch at once, at"
    echo "the threshold, and textures do not blend). Popping is the measure above, per setting of the"
    echo "tolerance, on the approach: the method's frame-to-frame change minus the reference's (colour"
    echo "mean, depth 99th percentile in %), and the jump of the largest step over its neighbours"
    echo "(colour, depth in %)."
    echo
    echo "| tolerance (px) | morphing: colour / depth p99 (%) / jump colour / jump depth (%) | no morphing: the same | triangles on / off |"
    echo "|---:|---:|---:|---:|"
    paste -d'|' <(grep '^| quadtree-patches | ' "$docs/accuracy-puget/summary.md") \
      <(grep '^| quadtree-patches | ' "$docs/accuracy-puget-no-morph/summary.md") |
      awk -F"|" '{ printf "| %s | %s | %s | %s / %s |\n", $3, $21, $44, $4, $27 }'
    echo
    echo "![popping without morphing](evaluation/accuracy-puget-no-morph/popping.png)"
    echo
  fi
  if [ -f "$docs/grids/grids.md" ]; then
    echo "## The projected grids' paper tables"
    echo
    echo "\`terrain-client bench grids\` runs the sweep above over the grid sizes the papers print,"
    echo "persistent grid mapping uniform, the projective grid uniform and warped, with and without"
    echo "ray casting; frame rates are medians of three draws (of the first grid of each run, one of them"
    echo "built the pipelines)."
    echo
    cat "$docs/grids/grids.md"
    echo
  fi
  if [ -f docs/benchmarks/levels.md ]; then
    echo "## Bytes against the byte oracle: the himalaya levels flight"
    echo
    echo "\`scripts/bench-levels.sh\` (also a section of \`scripts/bench.sh\`, which writes the file shown here:"
    echo "\`docs/benchmarks/levels.md\`, not rerun by this script) flies the default himalaya_4097"
    echo "flight at 16 MiB, 480x270, as a pyramid of levels (each way of sharing the limit) and as level"
    echo "0 alone. The **byte oracle** is, at every frame, the fewest whole tiles that draw the view"
    echo "within 1 px: the level choice of the client run over the whole pyramid, each visible part"
    echo "from the coarsest tile whose builder-measured deviation from full resolution projects within"
    echo "the threshold at its box's nearest point (\`Scene::bytes_needed\`). Held: those tiles as the"
    echo "pager counts them at their coarsest texture; downloaded: every tile the oracle needed at any"
    echo "frame, once (blob and coarsest texture). The flights' held bytes set against it are their"
    echo "tiles' own, the method's shared bytes apart. Textures are counted at their coarsest level, so the"
    echo "oracle is a floor where the screen resolves finer ones."
    echo
    sed '/^<!--/d' docs/benchmarks/levels.md
    echo
  fi
  echo "## Stability matrix"
  echo
  echo "Each run streams its own scene along the scenario's cameras (paging, fetching, textures"
  echo "and the frame-rate controller at 60 fps, as \`fly\` does), lets the last view settle and"
  echo "measures it against the reference at that camera. Memory is the peak the scene counted"
  echo "against the limit and the peak it held (CPU bytes plus every GPU allocation made for the"
  echo "terrain), against a limit of at most three quarters of the whole database, so that it binds"
  echo "in every scenario; frame times are of the streamed frames."
  echo
  sed 's|(images/|(evaluation/stability/images/|g' "$docs/stability/stability.md"
  echo
  if [ -f "$docs/stability-fillers/stability.md" ]; then
    echo "### The crack fillers where methods are known to fail"
    echo
    echo "The strip masks with each filler in the scenarios of grazing views, looking above the"
    echo "horizon, low near the highest peak, under the surface and far outside. Each run streams"
    echo "its own scene, so the frame-rate controller gives each its own budget: a filler is"
    echo "compared with the same frame drawn without it (\"without the filler\"), not with the"
    echo "\`none\` run."
    echo
    sed 's|(images/|(evaluation/stability-fillers/images/|g' "$docs/stability-fillers/stability.md"
    echo
  fi
  cat docs/evaluation-reading.md
} >docs/evaluation.md
echo "wrote docs/evaluation.md and docs/evaluation/"
