#!/usr/bin/env bash
# Installs what the browser-side end-to-end checks need, and builds viewer/dist/.
#   - Debian's chromium (apt-get) when /usr/bin/chromium is missing;
#   - npm ci in viewer/ (maplibre-gl, pmtiles, cesium, puppeteer-core at the locked versions),
#     skipped when node_modules was installed from the same package-lock.json (--force: always);
#   - viewer/dist/: the page (src/) plus the libraries' run-time files, served by the
#     server under /view/.
# Idempotent. Exits non-zero on any failure.
set -euo pipefail

FORCE=0
for arg in "$@"; do
  case "$arg" in
    --force) FORCE=1 ;;
    -h|--help) sed -n '2,9p' "$0"; exit 0 ;;
    *) echo "setup.sh: unknown argument: $arg" >&2; exit 64 ;;
  esac
done

HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
cd "$HERE"
T0=$(date +%s.%N)
say() { printf '[viewer/setup] %s\n' "$*"; }
fail() { printf '[viewer/setup] ERROR: %s\n' "$*" >&2; exit 1; }
elapsed() { awk -v a="$1" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }'; }

# --- 1. chromium ---------------------------------------------------------------------
if [ -x /usr/bin/chromium ]; then
  say "chromium present: $(/usr/bin/chromium --version 2>/dev/null | tail -n 1)"
else
  say "installing Debian's chromium with apt-get (about 124 MB download) ..."
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null || fail "not root and no sudo: install chromium by hand (apt-get install chromium)"
    SUDO="sudo"
  fi
  t=$(date +%s.%N)
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq || fail "apt-get update failed"
  $SUDO apt-get install -y -qq --no-install-recommends chromium >/dev/null \
    || fail "apt-get install chromium failed"
  [ -x /usr/bin/chromium ] || fail "apt-get ran but /usr/bin/chromium is still missing"
  say "chromium installed in $(elapsed "$t") s: $(/usr/bin/chromium --version 2>/dev/null | tail -n 1)"
fi

# --- 2. npm ci -----------------------------------------------------------------------
command -v node >/dev/null || fail "node is not installed"
command -v npm >/dev/null || fail "npm is not installed"
[ -f package-lock.json ] || fail "viewer/package-lock.json is missing"
STAMP=node_modules/.setup-lock-sha256
LOCK_SUM=$(sha256sum package-lock.json | cut -d' ' -f1)
if [ "$FORCE" -eq 0 ] && [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$LOCK_SUM" ] \
   && [ -d node_modules/maplibre-gl ] && [ -d node_modules/cesium ] \
   && [ -d node_modules/pmtiles ] && [ -d node_modules/puppeteer-core ]; then
  say "node_modules up to date with package-lock.json (node $(node --version)); npm ci skipped"
else
  say "npm ci (node $(node --version), npm $(npm --version)) ..."
  t=$(date +%s.%N)
  # cesium and puppeteer-core declare node >= 22; both work on node 20 (engine warnings only).
  npm ci --no-audit --no-fund --loglevel=error || fail "npm ci failed"
  echo "$LOCK_SUM" > "$STAMP"
  say "npm ci done in $(elapsed "$t") s"
fi

# --- 3. dist/ ------------------------------------------------------------------------
NM=node_modules
MLD=$NM/maplibre-gl/dist
CES=$NM/cesium/Build/Cesium
for f in src/index.html src/app.js "$MLD/maplibre-gl.mjs" "$MLD/maplibre-gl-worker.mjs" \
         "$MLD/maplibre-gl.css" "$NM/pmtiles/dist/pmtiles.js" "$CES/Cesium.js"; do
  [ -f "$f" ] || fail "missing $f"
done
for d in Workers ThirdParty Assets Widgets; do
  [ -d "$CES/$d" ] || fail "missing $CES/$d"
done

t=$(date +%s.%N)
TMP=$(mktemp -d "$HERE/.dist.XXXXXX")
trap 'rm -rf "$TMP"' EXIT
cp src/index.html src/app.js "$TMP/"
# MapLibre GL JS 6 ships ES modules only (.mjs). They are copied as .js so that any static
# server's JavaScript content type applies (module scripts and module workers are refused
# unless served as text/javascript). The page sets the worker's URL itself
# (maplibregl.setWorkerUrl), so the bundle's own "./maplibre-gl-worker.mjs" is not used.
# The source-map comments are dropped: the maps are not copied.
sed '/^\/\/# sourceMappingURL=/d' "$MLD/maplibre-gl.mjs" > "$TMP/maplibre-gl.js"
sed '/^\/\/# sourceMappingURL=/d' "$MLD/maplibre-gl-worker.mjs" > "$TMP/maplibre-gl-worker.js"
cp "$MLD/maplibre-gl.css" "$TMP/maplibre-gl.css"
# pmtiles' IIFE build: defines the global `pmtiles`.
sed '/^\/\/# sourceMappingURL=/d' "$NM/pmtiles/dist/pmtiles.js" > "$TMP/pmtiles.js"
mkdir -p "$TMP/cesium"
cp "$CES/Cesium.js" "$TMP/cesium/"
cp -R "$CES/Workers" "$CES/ThirdParty" "$CES/Assets" "$CES/Widgets" "$TMP/cesium/"
# versions, for the page's info and for humans
node -e '
  const v = n => require("./node_modules/" + n + "/package.json").version;
  process.stdout.write(JSON.stringify({"maplibre-gl": v("maplibre-gl"), pmtiles: v("pmtiles"),
    cesium: v("cesium"), "puppeteer-core": v("puppeteer-core")}, null, 1) + "\n");
' > "$TMP/versions.json" || fail "could not read the packages' versions"
# The wasm client's page (scripts/build-web.sh builds it into dist/client) stays.
[ -d dist/client ] && mv dist/client "$TMP/client"
rm -rf dist
mv "$TMP" dist
chmod 755 dist
trap - EXIT
say "dist/ built in $(elapsed "$t") s: $(du -sh dist | cut -f1), $(find dist -type f | wc -l) files"
say "versions: $(tr -d '\n ' < dist/versions.json)"
say "done in $(elapsed "$T0") s"
