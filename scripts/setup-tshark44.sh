#!/usr/bin/env bash
# Builds, once, a Debian 13 "trixie" chroot with tshark 4.4 (Lua 5.4), in which the dissector's
# tests run a second time (tests/tshark_runner.py). Idempotent and non-interactive; needs root
# (no sudo) and deb.debian.org. The chroot is cached: VM110_TRIXIE_ROOT, default
# ${XDG_CACHE_HOME:-$HOME/.cache}/vm110/trixie. Prints the chroot's path on success.
set -euo pipefail

ROOT="${VM110_TRIXIE_ROOT:-${XDG_CACHE_HOME:-$HOME/.cache}/vm110/trixie}"
MIRROR="${VM110_DEBIAN_MIRROR:-http://deb.debian.org/debian}"
STAMP="$ROOT/.vm110-ready"
# Wireshark 4.4 loads no Lua plugin (nor -X lua_script) when run as root unless the global
# init.lua allows it; the tests run tshark as root inside this chroot.
INIT_LUA="$ROOT/usr/lib/x86_64-linux-gnu/wireshark/plugins/init.lua"

ready() { [ -f "$STAMP" ] && [ -f "$INIT_LUA" ] && chroot "$ROOT" tshark --version >/dev/null 2>&1; }

if [ "$(id -u)" != 0 ]; then
    ready && { echo "$ROOT"; exit 0; }
    echo "setup-tshark44: building the trixie chroot needs root (debootstrap, chroot)" >&2
    exit 1
fi

mkdir -p "$(dirname "$ROOT")"
exec 9>"$ROOT.lock"
flock 9  # parallel callers wait for one build
ready && { echo "$ROOT"; exit 0; }

if [ ! -x "$ROOT/usr/bin/apt-get" ]; then
    # Build beside the cache and move into place, so an interrupted run leaves no half chroot.
    build="$ROOT.build"
    rm -rf --one-file-system "$build"
    debootstrap --variant=minbase trixie "$build" "$MIRROR" >"$ROOT.log" 2>&1 \
        || { echo "setup-tshark44: debootstrap failed, see $ROOT.log" >&2; exit 1; }
    rm -rf --one-file-system "$ROOT"
    mv "$build" "$ROOT"
fi

cp /etc/resolv.conf "$ROOT/etc/resolv.conf" 2>/dev/null || true
in_root() { chroot "$ROOT" env DEBIAN_FRONTEND=noninteractive LC_ALL=C.UTF-8 "$@"; }
echo "wireshark-common wireshark-common/install-setuid boolean false" | in_root debconf-set-selections
{ in_root apt-get update -q && in_root apt-get install -y -q --no-install-recommends tshark; } >>"$ROOT.log" 2>&1 \
    || { echo "setup-tshark44: installing tshark in the chroot failed, see $ROOT.log" >&2; exit 1; }
in_root apt-get clean
mkdir -p "$(dirname "$INIT_LUA")"
echo "run_user_scripts_when_superuser = true -- vm110 test chroot: tshark runs as root" >"$INIT_LUA"
chroot "$ROOT" tshark --version | head -1 >&2
touch "$STAMP"
echo "$ROOT"
