#!/usr/bin/env bash
# The Debian testing "forky" chroot with tshark 4.6 (Lua 5.4): see scripts/tshark-chroot.sh.
# debootstrap may not know forky yet: sid's script bootstraps it. VM110_FORKY_ROOT moves its cache.
exec "$(dirname "$0")/tshark-chroot.sh" forky forky /usr/share/debootstrap/scripts/sid
