#!/usr/bin/env bash
# Builds the terrain client's browser page: the client compiled to wasm32 (web/, with
# wgpu's WebGPU and WebGL2 backends), bound to JavaScript by wasm-bindgen, and the page
# (web/page/) around it, into viewer/dist/client/. `terrain-server serve --viewer viewer/dist`
# serves it at /view/client/.
#
# Installs what it needs when missing: the wasm32-unknown-unknown target (rustup) and
# wasm-bindgen-cli at the version web/Cargo.toml pins (cargo install, from crates.io, into
# target/web-tools so nothing outside the repository changes).
#
#   bash scripts/build-web.sh            # optimised build (what the tests and users load)
#   bash scripts/build-web.sh --dev      # faster to compile, slower to run
#
# Idempotent; the page appears whole (written beside, then renamed). Exits non-zero on any
# failure.
set -euo pipefail
cd "$(dirname "$0")/.."

PROFILE=web
for arg in "$@"; do
  case "$arg" in
    --dev) PROFILE=dev ;;
    -h|--help) sed -n '2,14p' "$0"; exit 0 ;;
    *) echo "build-web.sh: unknown argument: $arg" >&2; exit 64 ;;
  esac
done
say() { printf '[build-web] %s\n' "$*"; }
fail() { printf '[build-web] ERROR: %s\n' "$*" >&2; exit 1; }
T0=$(date +%s)

# --- 1. the target and wasm-bindgen ---------------------------------------------------
if ! rustup target list --installed | grep -qx wasm32-unknown-unknown; then
  say "adding the wasm32-unknown-unknown target (rustup)"
  rustup target add wasm32-unknown-unknown || fail "rustup target add wasm32-unknown-unknown failed"
fi
VERSION=$(sed -n 's/^wasm-bindgen = "=\([0-9.]*\)"/\1/p' web/Cargo.toml)
[ -n "$VERSION" ] || fail "web/Cargo.toml pins no wasm-bindgen version (wasm-bindgen = \"=X.Y.Z\")"
TOOLS="$PWD/target/web-tools"
BINDGEN="$TOOLS/bin/wasm-bindgen"
if ! { [ -x "$BINDGEN" ] && "$BINDGEN" --version | grep -q " $VERSION\$"; }; then
  if command -v wasm-bindgen >/dev/null && wasm-bindgen --version | grep -q " $VERSION\$"; then
    BINDGEN=$(command -v wasm-bindgen)
  else
    say "installing wasm-bindgen-cli $VERSION into target/web-tools (cargo install, a few minutes once)"
    # A debug build: it compiles in two thirds of the time, and binds the module in seconds.
    cargo install --quiet --debug --root "$TOOLS" wasm-bindgen-cli --version "$VERSION" \
      || fail "cargo install wasm-bindgen-cli $VERSION failed"
  fi
fi
say "wasm-bindgen: $("$BINDGEN" --version)"

# --- 2. the client in wasm ------------------------------------------------------------
say "compiling the client for wasm32 ($PROFILE)"
cargo build --locked -p terrain-web --target wasm32-unknown-unknown --profile "$PROFILE" \
  || fail "the wasm build failed"
DIR=$([ "$PROFILE" = dev ] && echo debug || echo "$PROFILE")
WASM=target/wasm32-unknown-unknown/$DIR/terrain_web.wasm
[ -f "$WASM" ] || fail "missing $WASM"

# --- 3. the page ----------------------------------------------------------------------
mkdir -p viewer/dist
TMP=$(mktemp -d viewer/dist/.client.XXXXXX)
trap 'rm -rf "$TMP"' EXIT
"$BINDGEN" --target web --no-typescript --out-dir "$TMP/pkg" "$WASM" || fail "wasm-bindgen failed"
cp web/page/index.html web/page/main.js "$TMP/"
chmod 755 "$TMP"
rm -rf viewer/dist/client.old
[ -d viewer/dist/client ] && mv viewer/dist/client viewer/dist/client.old
mv "$TMP" viewer/dist/client
rm -rf viewer/dist/client.old
trap - EXIT
say "viewer/dist/client: $(du -sh viewer/dist/client | cut -f1) ($(du -h viewer/dist/client/pkg/terrain_web_bg.wasm | cut -f1) of wasm), in $(( $(date +%s) - T0 )) s"
say "serve it: terrain-server serve DB --viewer viewer/dist, then open http://HOST:PORT/view/client/"
