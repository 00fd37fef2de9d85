#!/usr/bin/env bash
# The Debian 13 "trixie" chroot with tshark 4.4 (Lua 5.4): see scripts/tshark-chroot.sh.
# VM110_TRIXIE_ROOT moves its cache.
exec "$(dirname "$0")/tshark-chroot.sh" trixie trixie
