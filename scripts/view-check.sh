#!/usr/bin/env bash
# The windowed client on both Linux window systems: `terrain-client view` over the bundled
# jacksboro fixture, for a few seconds each under Xvfb (X11) and under a headless Weston
# (Wayland, no DISPLAY set), with the window's statistics printed (--print-stats). It passes
# when each run drew frames (a statistics line with a frame rate and triangles) and did not
# fail. Needs the release binaries (cargo build --release); installs xvfb and weston when
# missing (Debian, as root). Without them it says NOT RUN, and with REQUIRE_BROWSER=1 (as scripts/test.sh says) fails.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/gpu-env.sh >/dev/null
bin=target/release
seconds=${VIEW_SECONDS:-12}

need() { # command package
  command -v "$1" >/dev/null 2>&1 && return 0
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing $2 (for $1)"
    apt-get -o DPkg::Lock::Timeout=600 update -qq
    DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 install -y -qq \
      --no-install-recommends "$2" >/dev/null
  fi
  command -v "$1" >/dev/null 2>&1
}
if ! need Xvfb xvfb || ! need weston weston; then
  if [ "${REQUIRE_BROWSER:-}" = 1 ]; then
    echo "error: view-check: Xvfb or weston is missing and could not be installed" >&2
    exit 1
  fi
  echo "view-check: NOT RUN (Xvfb or weston missing: install the Debian packages xvfb and weston)"
  exit 0
fi

work=$(mktemp -d)
pids=()
trap 'kill "${pids[@]}" 2>/dev/null || true; rm -rf "$work"' EXIT
"$bin/terrain-server" build tests/fixtures/jacksboro/jacksboro_fault_dem.png --out "$work/db" \
  --no-web >"$work/build.log" 2>&1
"$bin/terrain-server" serve "$work/db" --addr 127.0.0.1:0 >"$work/serve.out" 2>"$work/serve.log" &
pids+=($!)
url=
for _ in $(seq 200); do
  url=$(sed -n 's/^listening on //p' "$work/serve.out")
  [ -n "$url" ] && break
  sleep 0.05
done
[ -n "$url" ] || { echo "error: view-check: the server did not start" >&2; cat "$work/serve.log" >&2; exit 1; }

view() { # name, then env assignments for the run
  local name=$1
  shift
  set +e
  env "$@" timeout "$seconds" "$bin/terrain-client" view --server "$url" --memory 32MiB \
    --print-stats >"$work/$name.log" 2>&1
  local rc=$?
  set -e
  # timeout ends a viewer that is still running: 124 is the expected end.
  local drawn
  drawn=$(grep -cE ' [0-9]+ fps, [1-9][0-9]* triangles' "$work/$name.log" || true)
  if [ "$rc" != 124 ] || [ "$drawn" -lt 2 ]; then
    echo "error: view-check: $name: exit $rc, $drawn statistics lines with frames drawn" >&2
    tail -20 "$work/$name.log" >&2
    exit 1
  fi
  echo "view-check: $name: $(grep -E ' fps, ' "$work/$name.log" | tail -1 | sed 's/^terrain-client view — //')"
}

Xvfb :97 -screen 0 1280x800x24 -nolisten tcp >"$work/xvfb.log" 2>&1 &
pids+=($!)
sleep 1
view x11 -u WAYLAND_DISPLAY DISPLAY=:97

mkdir -m 700 "$work/xdg"
XDG_RUNTIME_DIR="$work/xdg" weston --backend=headless-backend.so --socket=view-check \
  --width=1280 --height=800 >"$work/weston.log" 2>&1 &
pids+=($!)
for _ in $(seq 100); do
  [ -S "$work/xdg/view-check" ] && break
  sleep 0.1
done
view wayland -u DISPLAY XDG_RUNTIME_DIR="$work/xdg" WAYLAND_DISPLAY=view-check
