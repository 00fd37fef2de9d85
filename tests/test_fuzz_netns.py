"""`vm110 fuzz` with the specification's multicast set-up (--group, TTL 1) against the reference
controller, inside a network namespace this test creates: its only interface is its own loopback,
so the multicast never reaches a real interface. Skipped without root or `ip netns`."""
from __future__ import annotations

import json
import subprocess
import sys


from vm110 import constants as C

def test_fuzz_over_multicast_inside_a_namespace(netns, tmp_path):
    inside = ["ip", "netns", "exec", netns, sys.executable, "-m", "vm110"]
    controller = f"{sys.executable} -m vm110 simulate controller --iface 127.0.0.1 --command-every 0.5 --quiet"
    result = subprocess.run(inside + ["fuzz", "--target", f"{C.MULTICAST_GROUP}:{C.INPUT_PORT}", "--allow-remote",
                                      "--group", C.MULTICAST_GROUP, "--target-cmd", controller,
                                      "--duration", "4", "--out", str(tmp_path)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads((tmp_path / "findings.json").read_text())
    assert summary["findings"] == [] and summary["cases_run"] > 50
