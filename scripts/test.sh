#!/usr/bin/env bash
# The test command: builds the workspace in release (the end-to-end tests run its
# binaries), runs every test, and checks that docker-compose.yml parses.
# Installs what it needs when missing (Debian: docker-compose, and Mesa's software Vulkan
# driver for the render tests on machines without a GPU: see scripts/gpu-env.sh).
#
# The data-hungry tests read the data kit from $TERRAIN_DATA_DIR; without it they print
# "NOT RUN" and return. REQUIRE_DATA=1 (set by .ci/run) turns that into a failure; so does
# REQUIRE_GPU=1 for render tests without a Vulkan adapter, and REQUIRE_BROWSER=1 for the
# browser tests (MapLibre and Cesium in headless Chromium) without Chromium and the npm
# packages, which viewer/setup.sh installs here when it can (apt-get, npm ci), or without
# the wasm client's page, which scripts/build-web.sh builds (rustup, cargo install), and for the
# windowed client's check (scripts/view-check.sh) without Xvfb and Weston; and
# REQUIRE_STORE=1 for the scale-out tests (tests/e2e/scale.rs) without SeaweedFS's weed
# and nginx, which scripts/scale-setup.sh installs when it can (pip into a virtual
# environment, apt-get).
#
# Two tiers: the default runs every test but the longest flights, which say NOT RUN;
# TERRAIN_TEST_TIER=full (set by .ci/run) runs them too, and checks that the client and the
# server compile for Windows (x86_64-pc-windows-gnu, with Debian's MinGW for the C in build
# scripts).
set -euo pipefail
cd "$(dirname "$0")/.."

install_if_missing() { # command package
  command -v "$1" >/dev/null 2>&1 && return 0
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing $2 (for $1)"
    apt-get -o DPkg::Lock::Timeout=600 update -qq
    DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 install -y -qq --no-install-recommends "$2" >/dev/null
  else
    echo "error: $1 is missing; install the Debian package $2" >&2
    return 1
  fi
}

source scripts/gpu-env.sh
# The connection-attack test holds both ends of 5,000 connections in one process: raise the
# open-files limit to what the system allows (it says what it needs if that is too low).
ulimit -n "$(ulimit -Hn)" 2>/dev/null || true

if [ -z "${TERRAIN_DATA_DIR:-}" ]; then
  echo "note: TERRAIN_DATA_DIR is not set: tests that need the data kit will say NOT RUN"
fi

if ! bash viewer/setup.sh; then
  if [ "${REQUIRE_BROWSER:-}" = 1 ]; then
    echo "error: REQUIRE_BROWSER=1 but viewer/setup.sh failed" >&2
    exit 1
  fi
  echo "note: viewer/setup.sh failed: the browser tests will say NOT RUN"
fi

# The wasm client's page (the client compiled for the browser, viewer/dist/client): adds
# the wasm32 target and wasm-bindgen-cli when missing (rustup, crates.io).
if ! bash scripts/build-web.sh; then
  if [ "${REQUIRE_BROWSER:-}" = 1 ]; then
    echo "error: REQUIRE_BROWSER=1 but scripts/build-web.sh failed" >&2
    exit 1
  fi
  echo "note: scripts/build-web.sh failed: the wasm client's browser test will say NOT RUN"
fi

if ! bash scripts/scale-setup.sh; then
  if [ "${REQUIRE_STORE:-}" = 1 ]; then
    echo "error: REQUIRE_STORE=1 but scripts/scale-setup.sh failed" >&2
    exit 1
  fi
  echo "note: scripts/scale-setup.sh failed: the object-store and replica tests will say NOT RUN"
fi

cargo build --release --workspace --locked
cargo test --release --workspace --locked
# The windowed client under X11 (Xvfb) and Wayland (headless Weston).
bash scripts/view-check.sh

if [ "${TERRAIN_TEST_TIER:-}" = full ]; then
  # Windows: the client and the server compile (a check, not a build: nothing here runs
  # them). The README's platform table says so.
  rustup target list --installed | grep -qx x86_64-pc-windows-gnu || rustup target add x86_64-pc-windows-gnu
  install_if_missing x86_64-w64-mingw32-gcc gcc-mingw-w64-x86-64
  cargo check --locked -p terrain-client -p terrain-server --target x86_64-pc-windows-gnu
  echo "windows (x86_64-pc-windows-gnu): the client and the server compile"
else
  echo "note: the full tier's checks (the longest flights, Windows) did not run: TERRAIN_TEST_TIER=full runs them"
fi

install_if_missing docker-compose docker-compose
docker-compose -f docker-compose.yml config -q
echo "docker-compose.yml: parses"
