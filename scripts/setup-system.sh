#!/usr/bin/env bash
# Installs the Debian/Ubuntu packages the project needs, when any is missing.
# Non-interactive (the wireshark-common debconf question is pre-answered), root without sudo.
set -euo pipefail

packages=(tshark lua5.2 lua5.4 python3-venv iproute2 debootstrap lua-check tmux gcc afl++ clang gdb)
commands=(tshark lua5.2 lua5.4 ip debootstrap luacheck tmux gcc afl-clang-fast clang gdb)
# Where apt has them: chromium (the HTML report's browser tests; Ubuntu ships it only as a snap, and
# those tests are skipped there) and Debian's archive keyring (debootstrap of the test chroots on a
# host that is not Debian).
optional=(chromium debian-archive-keyring)

installed() { dpkg-query -W -f '${Status}' "$1" 2>/dev/null | grep -q "ok installed"; }
# A package apt can install itself (`apt-cache show` also answers for a virtual one, such as
# Ubuntu's chromium, which only its snap wrapper provides).
known() {
    local candidate
    candidate=$(apt-cache policy "$1" 2>/dev/null | sed -n 's/^ *Candidate: //p')
    [ -n "$candidate" ] && [ "$candidate" != "(none)" ]
}

missing=0
for c in "${commands[@]}"; do command -v "$c" >/dev/null 2>&1 || missing=1; done
for p in "${optional[@]}"; do if known "$p" && ! installed "$p"; then missing=1; fi; done
python3 -c 'import venv, ensurepip' 2>/dev/null || missing=1
[ "$missing" = 0 ] && exit 0

if [ "$(id -u)" = 0 ]; then SUDO=(); else SUDO=(sudo); fi
export DEBIAN_FRONTEND=noninteractive
echo "wireshark-common wireshark-common/install-setuid boolean false" | "${SUDO[@]}" debconf-set-selections
"${SUDO[@]}" apt-get update -q
for p in "${optional[@]}"; do if known "$p"; then packages+=("$p"); fi; done
# python3-venv is only needed where python3 is Debian's own; skip it when apt does not know it.
known python3-venv || packages=("${packages[@]/python3-venv}")
# clang's compiler-rt, for AFL_USE_ASAN=1 afl-clang-fast builds (coverage and AddressSanitizer at once).
clang_major=$(apt-cache depends clang 2>/dev/null | sed -n 's/.*Depends: clang-\([0-9]*\)$/\1/p' | head -1)
[ -n "$clang_major" ] && known "libclang-rt-$clang_major-dev" && packages+=("libclang-rt-$clang_major-dev")
"${SUDO[@]}" apt-get install -y -q --no-install-recommends "${packages[@]}"
