#!/usr/bin/env bash
# Builds, once, a cached Debian chroot with tshark, in which the dissector's tests run on another
# Wireshark version (tests/tshark_runner.py). Idempotent and non-interactive; needs root (no sudo).
#   scripts/tshark-chroot.sh NAME SUITE [DEBOOTSTRAP_SCRIPT]
# NAME bookworm (Debian 12, Wireshark 4.0), trixie (Debian 13, 4.4) or forky (Debian testing, 4.6);
# tests/tshark_runner.py --setup (`make tsharks`) calls it for each version the host's tshark does
# not stand for. The chroot is cached in ${VM110_<NAME>_ROOT:-${XDG_CACHE_HOME:-$HOME/.cache}/vm110/<name>}.
# Packages come from the Debian mirror this machine's apt uses (its sources; VM110_DEBIAN_MIRROR
# overrides) through its apt proxy, if any: nothing is fetched from an address written into the project.
# Prints the chroot's path on success.
set -euo pipefail

name="$1" suite="$2" script="${3:-}"
var="VM110_$(echo "$name" | tr a-z A-Z)_ROOT"
ROOT="${!var:-${XDG_CACHE_HOME:-$HOME/.cache}/vm110/$name}"
STAMP="$ROOT/.vm110-ready"
# Wireshark 4.4 and later load no Lua plugin (nor -X lua_script) when run as root unless the
# global init.lua allows it; the tests run tshark as root inside the chroot.
INIT_LUA="$ROOT/usr/lib/x86_64-linux-gnu/wireshark/plugins/init.lua"
say() { echo "tshark-chroot $name: $*" >&2; }

ready() { [ -f "$STAMP" ] && [ -f "$INIT_LUA" ] && chroot "$ROOT" tshark --version >/dev/null 2>&1; }

if [ "$(id -u)" != 0 ]; then
    ready && { echo "$ROOT"; exit 0; }
    say "building the chroot needs root (debootstrap, chroot)"
    exit 1
fi

# The first Debian archive among this machine's apt sources (deb822 or one-line format).
host_mirror() {
    local f
    for f in /etc/apt/sources.list.d/*.sources; do
        if [ -f "$f" ]; then awk '/^URIs:/ {for (i = 2; i <= NF; i++) print $i}' "$f"; fi
    done
    for f in /etc/apt/sources.list /etc/apt/sources.list.d/*.list; do
        if [ -f "$f" ]; then awk '$1 == "deb" {for (i = 2; i <= NF; i++) if ($i ~ /:\/\//) {print $i; break}}' "$f"; fi
    done
}
MIRROR="${VM110_DEBIAN_MIRROR:-$(host_mirror | grep -E '/debian/?$' | head -n 1)}"
[ -n "$MIRROR" ] || { say "no Debian archive in this machine's apt sources; set VM110_DEBIAN_MIRROR"; exit 1; }
# The host apt's proxy, for debootstrap (environment) and for apt inside the chroot (its config).
proxy="$(apt-config dump 2>/dev/null | sed -n 's/^Acquire::http::Proxy "\(.*\)";$/\1/p' | head -n 1)"
if [ -n "$proxy" ]; then export http_proxy="${http_proxy:-$proxy}"; fi

mkdir -p "$(dirname "$ROOT")"
exec 9>"$ROOT.lock"
flock 9  # parallel callers wait for one build
ready && { echo "$ROOT"; exit 0; }

if [ ! -x "$ROOT/usr/bin/apt-get" ]; then
    # Build beside the cache and move into place, so an interrupted run leaves no half chroot.
    build="$ROOT.build"
    rm -rf --one-file-system "$build"
    debootstrap --variant=minbase "$suite" "$build" "$MIRROR" ${script:+"$script"} >"$ROOT.log" 2>&1 \
        || { say "debootstrap failed, see $ROOT.log"; exit 1; }
    rm -rf --one-file-system "$ROOT"
    mv "$build" "$ROOT"
fi

cp /etc/resolv.conf "$ROOT/etc/resolv.conf" 2>/dev/null || true
for f in /etc/apt/apt.conf.d/*; do
    grep -qi proxy "$f" 2>/dev/null && cp "$f" "$ROOT/etc/apt/apt.conf.d/"
done
# A testing archive's Release file can be past its Valid-Until date.
echo 'Acquire::Check-Valid-Until "false";' >"$ROOT/etc/apt/apt.conf.d/99vm110-valid-until"
in_root() { chroot "$ROOT" env DEBIAN_FRONTEND=noninteractive LC_ALL=C.UTF-8 "$@"; }
echo "wireshark-common wireshark-common/install-setuid boolean false" | in_root debconf-set-selections
{ in_root apt-get update -q && in_root apt-get install -y -q --no-install-recommends tshark; } >>"$ROOT.log" 2>&1 \
    || { say "installing tshark in the chroot failed, see $ROOT.log"; exit 1; }
in_root apt-get clean
mkdir -p "$(dirname "$INIT_LUA")"
echo "run_user_scripts_when_superuser = true -- vm110 test chroot: tshark runs as root" >"$INIT_LUA"
chroot "$ROOT" tshark --version | head -1 >&2
touch "$STAMP"
echo "$ROOT"
