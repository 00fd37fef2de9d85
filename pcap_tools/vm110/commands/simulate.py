"""Run a simulated base unit (`bu`) or the reference machine controller (`controller`) over UDP.

Default network set-up is the specification's: multicast group 239.255.42.20, inputs on port 5825
(BU -> controller), outputs on 5827, TTL 1. `--peer`/`--listen` switch to unicast (for example two
simulators on loopback: see captures/README.md). Logs what the node does and detects to stdout,
and a summary line at the end. Stops after `--duration` seconds, on Ctrl-C or on SIGTERM.
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
from typing import Any, Callable

from .. import constants as C
from ..errors import CliError
from ..sim.bu import DEFAULT_ORIGIN, BaseUnit, BaseUnitConfig
from ..sim.controller import Controller, ControllerConfig
from ..sim.impair import Impairer, Impairment
from ..sim.lifecycle import DEFAULT_SILENCE_S, parse_restart
from ..sim.realtime import RealtimeRunner
from ..sim.remote import Remote
from ..sim.transport import UdpConfig, UdpTransport, multicast_config, parse_address


def _window(text: str) -> tuple[float, float]:
    start, sep, end = text.partition(":")
    try:
        window = (float(start), float(end))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:END in seconds, got {text!r}") from None
    if not sep or window[1] <= window[0]:
        raise argparse.ArgumentTypeError(f"expected START:END in seconds with END > START, got {text!r}")
    return window


def _restart(text: str) -> str:
    try:
        parse_restart(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected AT or AT:NEW_PORT (seconds, port 1-65535), got {text!r}") from None
    return text


def _int(text: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None


def add_network_arguments(parser: argparse.ArgumentParser) -> None:
    net = parser.add_argument_group("network")
    net.add_argument("--group", default=C.MULTICAST_GROUP, help=f"multicast group (default {C.MULTICAST_GROUP})")
    net.add_argument("--port", type=int, default=C.INPUT_PORT,
                     help=f"input port; outputs use port + {C.OUTPUT_PORT_OFFSET} (default {C.INPUT_PORT})")
    net.add_argument("--iface", default="0.0.0.0", help="IPv4 address of the interface for multicast")
    net.add_argument("--peer", help="unicast HOST:PORT to send to instead of the group")
    net.add_argument("--listen", help="unicast HOST:PORT to receive on instead of joining the group")
    net.add_argument("--source", help="HOST:PORT to send from (default: the interface and this side's port)")


def add_impairment_arguments(parser: argparse.ArgumentParser) -> None:
    imp = parser.add_argument_group("impairments (of what this node sends; reproducible with --seed)")
    imp.add_argument("--seed", type=int, default=0)
    imp.add_argument("--loss", type=float, default=0.0, metavar="PCT")
    imp.add_argument("--duplicate", type=float, default=0.0, metavar="PCT", help="PCT %% delivered twice")
    imp.add_argument("--mirror", type=float, default=0.0, metavar="PCT",
                     help="PCT %% seen twice 0.05-3 ms apart, as a switch mirror port shows them to a capture "
                          "(over sockets the peer gets the copy too)")
    imp.add_argument("--reorder", type=float, default=0.0, metavar="PCT")
    imp.add_argument("--delay", type=float, default=0.0, metavar="MS")
    imp.add_argument("--jitter", type=float, default=0.0, metavar="MS")
    imp.add_argument("--corrupt", type=float, default=0.0, metavar="PCT", help="corrupt the CRC of PCT %%")
    imp.add_argument("--outage", type=_window, action="append", default=[], metavar="START:END",
                     help="send nothing between these times (s); repeatable")
    imp.add_argument("--stall", type=_window, action="append", default=[], metavar="START:END",
                     help="the node hangs: neither sends nor receives; repeatable")
    imp.add_argument("--glink", type=_window, action="append", default=[], metavar="START:END",
                     help="G-Link fallback: slower VRPO (controller), later VRAI (BU); repeatable")
    life = parser.add_argument_group("life of the node")
    life.add_argument("--stop-at", type=float, metavar="S", help="send nothing from S seconds on, for good")
    life.add_argument("--restart", type=_restart, action="append", default=[], metavar="AT[:NEW_PORT]",
                      help="go down at AT s and come back after --restart-silence with serials and command IDs "
                           "afresh, sending from NEW_PORT if given (0: a new ephemeral port); repeatable")
    life.add_argument("--restart-silence", type=float, default=DEFAULT_SILENCE_S, metavar="S",
                      help=f"seconds down at each restart (default {DEFAULT_SILENCE_S:g})")
    life.add_argument("--restart-serial", type=_int, default=0, metavar="N", help="first serial after a restart")
    life.add_argument("--serial-start", type=_int, default=0, metavar="N",
                      help="first serial (e.g. above 32767, to reboot from there)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="role", metavar="ROLE", required=True)
    bu = sub.add_parser("bu", help="simulated base unit", description="Simulated base unit (VRPI, VRCI, VRAI).")
    bu.add_argument("--script", help="remote/operator script (JSON, see vm110.sim.remote)")
    bu.add_argument("--disarmed", action="store_true", help="no RU armed (default: one RU armed)")
    bu.add_argument("--unarmed-rus", type=int, default=0, help="unarmed RUs reported when disarmed")
    bu.add_argument("--no-motion", action="store_true", help="joysticks and switches stay at rest")
    bu.add_argument("--command-every", type=float, default=0.0, metavar="S", help="an operator command every S s")
    bu.add_argument("--origin", type=_int, default=DEFAULT_ORIGIN, help=f"BU origin (default 0x{DEFAULT_ORIGIN:04x})")
    bu.add_argument("--command-id-start", type=_int, default=0)
    ctl = sub.add_parser("controller", help="reference machine controller",
                         description="Reference machine controller (VRPO, VRAO, VRCO).")
    ctl.add_argument("--period", type=float, default=100.0, metavar="MS", help="VRPO period (default 100)")
    ctl.add_argument("--data-size", type=int, default=64, help="periodic data bytes (>488: bursts)")
    ctl.add_argument("--vrco-timeout", type=float, default=float(C.VRCO_GIVE_UP_MS), metavar="MS")
    ctl.add_argument("--vrpi-timeout", type=float, default=float(C.VRPI_WATCHDOG_MS), metavar="MS")
    ctl.add_argument("--command-every", type=float, default=0.0, metavar="S", help="a VRCO every S s")
    ctl.add_argument("--command-id-start", type=_int, default=0)
    for p in (bu, ctl):
        add_network_arguments(p)
        add_impairment_arguments(p)
        p.add_argument("--duration", type=float, help="seconds to run (default: until interrupted)")
        p.add_argument("--json", action="store_true", help="log events as JSON lines")
        p.add_argument("--quiet", action="store_true", help="only the summary at the end")


def udp_config(args: argparse.Namespace) -> UdpConfig:
    """The sockets for the role from the network options."""
    if not 0 < args.port <= 0xFFFF - C.OUTPUT_PORT_OFFSET:
        raise CliError(f"--port must be 1..{0xFFFF - C.OUTPUT_PORT_OFFSET} (the output port is port + 2)")
    cfg = multicast_config(args.role, args.group, args.port, args.iface)
    if args.peer:
        cfg.dest = parse_address(args.peer)
    if args.listen:
        cfg.listen, cfg.group = parse_address(args.listen), None
    if args.source:
        cfg.source = parse_address(args.source)
    return cfg


def impairment(args: argparse.Namespace) -> Impairment:
    return Impairment(loss=args.loss, duplicate=args.duplicate, mirror=args.mirror, reorder=args.reorder,
                      delay_ms=args.delay,
                      jitter_ms=args.jitter, corrupt=args.corrupt, outages=tuple(args.outage), seed=args.seed)


def life(args: argparse.Namespace) -> dict[str, Any]:
    """The `Life` fields of the node's configuration from the options."""
    if args.restart_silence <= 0 or args.stop_at is not None and args.stop_at < 0:
        raise CliError("--restart-silence must be > 0 and --stop-at >= 0")
    restarts = tuple(sorted((parse_restart(text, args.restart_silence, args.restart_serial) for text in args.restart),
                            key=lambda r: r.at_s))
    return {"stalls": tuple(args.stall), "restarts": restarts, "stop_at_s": args.stop_at}


def build_node(args: argparse.Namespace, printer: Callable[[str], None]) -> Any:
    if args.role == "bu":
        remote = Remote.load(args.script) if args.script else Remote.simple(
            armed=not args.disarmed, unarmed_rus=args.unarmed_rus, motion=not args.no_motion,
            command_every=args.command_every)
        cfg = BaseUnitConfig(origin=args.origin, command_id_start=args.command_id_start,
                             glink=tuple(args.glink), seed=args.seed, **life(args))
        return BaseUnit(remote, cfg, printer=printer, serial_start=args.serial_start)
    if args.data_size < 0 or args.period <= 0:
        raise CliError("--data-size must be >= 0 and --period > 0")
    cfg = ControllerConfig(period_ms=args.period, data_size=args.data_size, vrco_timeout_ms=args.vrco_timeout,
                           vrpi_timeout_ms=args.vrpi_timeout, command_every_s=args.command_every,
                           command_id_start=args.command_id_start, glink=tuple(args.glink), **life(args))
    return Controller(cfg, printer=printer, serial_start=args.serial_start)


def run(args: argparse.Namespace) -> int:
    if args.duration is not None and args.duration <= 0:
        raise CliError("--duration must be positive")

    def printer(line: str) -> None:
        if not args.quiet and not args.json:
            print(line, flush=True)

    node = build_node(args, printer)
    if args.json and not args.quiet:
        node.listeners.append(lambda entry: print(json.dumps(entry), flush=True))
    imp = impairment(args)
    transport = UdpTransport(udp_config(args), Impairer(imp, args.role) if imp.active() else None).open()
    runner = RealtimeRunner([(node, transport)])
    rx, tx = transport.rx_address, transport.tx_address
    print(f"{args.role}: receiving on {rx[0]}:{rx[1]}"
          f"{' (group ' + transport.config.group + ')' if transport.config.group else ''}, "
          f"sending from {tx[0]}:{tx[1]} to {transport.config.dest[0]}:{transport.config.dest[1]}", flush=True)
    signal.signal(signal.SIGTERM, lambda *_: runner.stop(timeout=0))
    try:
        runner.run(args.duration)
    finally:
        print(json.dumps({"summary": node.summary()}), flush=True)
        sys.stdout.flush()
    return 0
