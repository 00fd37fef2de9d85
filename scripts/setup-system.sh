#!/usr/bin/env bash
# Installs the Debian/Ubuntu packages the project needs, when any is missing.
# Non-interactive (the wireshark-common debconf question is pre-answered), root without sudo.
set -euo pipefail

packages=(tshark lua5.2 lua5.4 python3-venv iproute2 debootstrap chromium lua-check tmux gcc afl++ clang gdb)
commands=(tshark lua5.2 lua5.4 ip debootstrap chromium luacheck tmux gcc afl-clang-fast clang gdb)

missing=0
for c in "${commands[@]}"; do command -v "$c" >/dev/null 2>&1 || missing=1; done
python3 -c 'import venv, ensurepip' 2>/dev/null || missing=1
[ "$missing" = 0 ] && exit 0

if [ "$(id -u)" = 0 ]; then SUDO=(); else SUDO=(sudo); fi
export DEBIAN_FRONTEND=noninteractive
echo "wireshark-common wireshark-common/install-setuid boolean false" | "${SUDO[@]}" debconf-set-selections
"${SUDO[@]}" apt-get update -q
# python3-venv is only needed where python3 is Debian's own; skip it when apt does not know it.
apt-cache show python3-venv >/dev/null 2>&1 || packages=("${packages[@]/python3-venv}")
# clang's compiler-rt, for AFL_USE_ASAN=1 afl-clang-fast builds (coverage and AddressSanitizer at once).
clang_major=$(apt-cache depends clang 2>/dev/null | sed -n 's/.*Depends: clang-\([0-9]*\)$/\1/p' | head -1)
[ -n "$clang_major" ] && apt-cache show "libclang-rt-$clang_major-dev" >/dev/null 2>&1 && packages+=("libclang-rt-$clang_major-dev")
"${SUDO[@]}" apt-get install -y -q --no-install-recommends "${packages[@]}"
