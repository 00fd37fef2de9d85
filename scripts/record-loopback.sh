#!/usr/bin/env bash
# Records a real capture: the simulated base unit and the reference controller talk over loopback
# UDP sockets while dumpcap captures on `lo`. Nothing leaves the machine (127.0.0.0/8 only).
#
#   scripts/record-loopback.sh [OUT] [SECONDS]      (default captures/loopback-recorded.pcapng, 12 s)
#
# BU 127.0.0.10 sends inputs from :5825 to the controller's 127.0.0.20:5825; the controller sends
# outputs from :5827 to the BU's 127.0.0.10:5827 — the ports of the specification, unicast.
# Link type: Linux loopback is Ethernet-framed (DLT_EN10MB, all-zero MACs). Needs capture rights
# on `lo` (root, or dumpcap with cap_net_raw). The simulators' logs go to OUT.bu.log and
# OUT.controller.log.
set -euo pipefail
cd "$(dirname "$0")/.."

out=${1:-captures/loopback-recorded.pcapng}
seconds=${2:-12}
vm110=.venv/bin/vm110
bu=127.0.0.10
controller=127.0.0.20
in_port=5825
out_port=$((in_port + 2))

rm -f "$out"
dumpcap -q -i lo -f "udp and (port $in_port or port $out_port)" -a "duration:$((seconds + 3))" -w "$out" &
dumpcap_pid=$!
trap 'kill "$dumpcap_pid" 2>/dev/null || true' EXIT
for _ in $(seq 50); do [ -s "$out" ] && break; sleep 0.1; done   # capture running before traffic starts

"$vm110" simulate controller --listen "$controller:$in_port" --peer "$bu:$out_port" \
    --source "$controller:$out_port" --duration "$seconds" --command-every 3 >"$out.controller.log" 2>&1 &
controller_pid=$!
"$vm110" simulate bu --listen "$bu:$out_port" --peer "$controller:$in_port" --source "$bu:$in_port" \
    --duration "$seconds" --command-every 1 --loss 5 --seed 1 --stall 6:6.8 >"$out.bu.log" 2>&1
wait "$controller_pid"
wait "$dumpcap_pid"
trap - EXIT
chmod 644 "$out"
echo "recorded $out ($(capinfos -c -M "$out" 2>/dev/null | awk -F: '/Number of packets/ {gsub(/ /, "", $2); print $2}') packets)"
