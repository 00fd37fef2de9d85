"""Both simulators with the specification's multicast set-up (group 239.255.42.20, ports 5825/5827,
TTL 1), inside a network namespace this test creates: its only interface is its own loopback, so
the multicast never reaches a real interface. Skipped without root or `ip netns`."""
from __future__ import annotations

import errno
import json
import os
import subprocess
import sys


def test_multicast_defaults_inside_a_namespace(netns):
    run = ["ip", "netns", "exec", netns, sys.executable, "-m", "vm110", "simulate"]
    common = ["--iface", "127.0.0.1", "--duration", "2.5", "--json"]
    with subprocess.Popen(run + ["controller", *common], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True) as ctl:
        bu = subprocess.run(run + ["bu", "--command-every", "0.5", *common], capture_output=True, text=True, timeout=30)
        ctl_out, ctl_err = ctl.communicate(timeout=30)
    assert bu.returncode == 0 and ctl.returncode == 0, bu.stderr
    # The sockets line on stderr: stdout is the JSON log alone.
    assert "group 239.255.42.20" in bu.stderr and "to 239.255.42.20:5825" in bu.stderr
    assert "to 239.255.42.20:5827" in ctl_err
    bu_log = [json.loads(line) for line in bu.stdout.splitlines()]
    ctl_log = [json.loads(line) for line in ctl_out.splitlines()]
    assert bu_log[-1]["summary"]["received"]["VRPO"] >= 15 and ctl_log[-1]["summary"]["received"]["VRPI"] >= 12
    acked = [e["command_id"] for e in bu_log if e.get("event") == "command_acked"]
    assert len(acked) >= 3 and acked == [e["command_id"] for e in ctl_log if e.get("event") == "executed"]


def test_a_peer_out_of_reach_is_said_not_sent_to_in_silence(netns):
    """The namespace routes nothing but its loopback and multicast: the kernel refuses every packet
    to 10.0.0.5. Trial: the BU ran its whole --duration with nothing said, its summary counting the
    refused packets as sent, and the user looked for the fault in the controller."""
    ip = ["ip", "netns", "exec", netns]
    assert subprocess.run(ip + ["ip", "route", "get", "10.0.0.5"], capture_output=True).returncode != 0
    bu = subprocess.run(ip + [sys.executable, "-m", "vm110", "simulate", "bu", "--peer", "10.0.0.5:5825",
                              "--listen", "127.0.0.1:5827", "--duration", "0.4", "--json"],
                        capture_output=True, text=True, timeout=30)
    assert bu.returncode == 0, bu.stderr
    log = [json.loads(line) for line in bu.stdout.splitlines()]
    unreachable = os.strerror(errno.ENETUNREACH)
    assert [(e["error"], e["to"]) for e in log if e.get("event") == "send_failed"] == [(unreachable, "10.0.0.5:5825")]
    summary = log[-1]["summary"]
    assert summary["send_errors"] == {unreachable: summary["sent"]["VRPI"]} and summary["sent"]["VRPI"] >= 3


def test_a_group_that_cannot_be_joined_says_why(netns):
    """Joining the group failed with "No such device" alone, for an --iface that is no address of
    the machine and for a machine with no route for multicast: the user was sent to look for a
    device. Now the line says which of the two, and the way out."""
    run = ["ip", "netns", "exec", netns, sys.executable, "-m", "vm110", "simulate", "bu", "--duration", "0.2"]
    wrong = subprocess.run(run + ["--iface", "10.9.9.9"], capture_output=True, text=True, timeout=30)
    subprocess.run(["ip", "-n", netns, "route", "del", "224.0.0.0/4"], check=True, capture_output=True)
    unrouted = subprocess.run(run, capture_output=True, text=True, timeout=30)
    for done in (wrong, unrouted):
        assert done.returncode == 2 and not done.stdout and len(done.stderr.splitlines()) == 1, done.stderr
        assert done.stderr.startswith("vm110 simulate: cannot receive on 0.0.0.0:5827 (group 239.255.42.20): ")
    assert "--iface 10.9.9.9 is not the address of an interface of this machine" in wrong.stderr
    assert "no route for multicast: give --iface" in unrouted.stderr and "ip route add 224.0.0.0/4" in unrouted.stderr


def test_a_log_whose_reader_goes_away_ends_the_run_interrupted_with_its_summary(netns):
    """Sim trial: `simulate bu | head -1` ended at the next log line with exit 0 and no summary
    (README: simulate exits 0 only when its --duration ran out). A closed pipe now ends the run as
    a pipe's writer ends: exit 130, the summary on stderr, `end` closed_pipe."""
    run = subprocess.Popen(["ip", "netns", "exec", netns, sys.executable, "-m", "vm110", "simulate", "bu",
                            "--duration", "60", "--command-every", "0.2"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert run.stdout is not None
    assert b"command_sent" in run.stdout.readline()
    run.stdout.close()
    _, err = run.communicate(timeout=30)
    assert run.returncode == 130, err
    summary = json.loads(err.splitlines()[-1])
    assert summary["end"] == "closed_pipe" and summary["summary"]["commands_sent"] >= 1
