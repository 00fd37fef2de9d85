"""Run one planted-bug controller (or the reference) over loopback UDP until SIGTERM.

    python tests/planted/run.py BUG --listen 127.0.0.1:RX --peer 127.0.0.1:FUZZER_RX [--command-every S]
"""
from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bugs import BUGS
from vm110.sim.controller import ControllerConfig
from vm110.sim.realtime import RealtimeRunner
from vm110.sim.transport import UdpConfig, UdpTransport, parse_address


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("bug", choices=sorted(BUGS))
    parser.add_argument("--listen", required=True)
    parser.add_argument("--peer", required=True)
    parser.add_argument("--command-every", type=float, default=0.5)
    args = parser.parse_args()
    controller = BUGS[args.bug](ControllerConfig(command_every_s=args.command_every))
    controller.keep_log = False      # as `vm110 simulate controller`: a log kept grows the RSS (the memory oracle)
    transport = UdpTransport(UdpConfig(listen=parse_address(args.listen), dest=parse_address(args.peer),
                                       source=("127.0.0.1", 0))).open()
    runner = RealtimeRunner([(controller, transport)])
    signal.signal(signal.SIGTERM, lambda *_: runner.stop(timeout=0))
    runner.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
