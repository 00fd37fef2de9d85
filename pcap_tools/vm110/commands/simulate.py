"""Run a simulated base unit (`bu`) or the reference machine controller (`controller`) over UDP.

Default network set-up is the specification's: multicast group 239.255.42.20, inputs on port 5825
(BU -> controller), outputs on 5827, TTL 1. `--peer`/`--listen` switch to unicast (for example two
simulators on loopback: see README.md, "Simulators and synthesis"). Logs what the node does and detects to stdout,
and a summary line at the end; the sockets it uses go to stderr first, so that stdout is the log
alone (JSON lines only with `--json`). Stops after `--duration` seconds (exit 0), on Ctrl-C, SIGTERM or
SIGHUP (an interruption: the summary still comes, exit 130). `--crc`, `--crc-order`, `--serial-scope` and
`--vrpo-start` speak another reading of TS-0006, as `analyze` reads one under the same options.
"""
from __future__ import annotations

import argparse
import ipaddress
import itertools
import json
import math
import signal
import socket
import sys
import time
from typing import Any, Callable, Optional, Sequence

from .. import constants as C
from ..closedpipe import silence_stdout
from ..errors import EXIT_INTERRUPTED, EXIT_OK, CliError
from ..monitor.stopping import STOPPING
from ..numbers import fields, number, span
from ..sim.bu import DEFAULT_ORIGIN, BaseUnit, BaseUnitConfig
from ..sim.claim import claim_origin
from ..sim.clock import WallClock, seconds
from ..sim.controller import Controller, ControllerConfig
from ..sim.impair import REORDER_SPREAD, Impairer, Impairment
from ..sim.lifecycle import DEFAULT_SILENCE_S, Restart
from ..sim.realtime import RealtimeRunner
from ..sim.remote import EVERY_LEAST_S, Remote
from ..sim.transport import Address, UdpConfig, UdpTransport, multicast_config, parse_address
from ..timefmt import utc_iso
from .options import (INPUT_PORT, INPUT_PORT_HELP, SEED, VRPO_START, VRPO_START_HELP, add_reading_options,
                      reading_of)


# A run is at most 30 days (as the fuzzer's); every time in it (windows, stop, restarts) too.
MAX_S = 30 * 86400
TIME = number(0, MAX_S, "s")
DURATION = number(0, MAX_S, "s", allow_zero=False)
EVERY = number(0, MAX_S, "s", least=EVERY_LEAST_S)   # 0: never
WINDOW = span(TIME)
RESTART = fields(("AT", "NEW_PORT"), (TIME, number(0, 0xFFFF, integer=True)), required=1)
PCT = number(0, 100, "percent")
# Packets held back overtake each other less the more are held: out of order most at 50 (about a
# sixth of VRPI), and 100, a delay of every packet, reordered as few as 2 does.
REORDER = number(0, 50, "percent")
DELAY = number(0, 60_000, "ms")
# From the clock's step, 1 µs: a shorter one is 0 µs (a period of 0 sent VRPO back to back, 200,000 a second).
PERIOD = number(0.001, 60_000, "ms")
TIMEOUT = number(0.001, 3_600_000, "ms")
WORD = number(0, 0xFFFF, integer=True)             # serials, command IDs, origins: 16 bits (0x.. too)
UNARMED_RUS = number(0, 0xFF, integer=True)        # a byte of VRPI
DATA_SIZE = number(0, 0xFFFF, "bytes", integer=True)


def add_network_arguments(parser: argparse.ArgumentParser) -> None:
    net = parser.add_argument_group("network")
    net.add_argument("--group", default=C.MULTICAST_GROUP, help=f"multicast group (default {C.MULTICAST_GROUP})")
    net.add_argument("--port", type=INPUT_PORT, default=C.INPUT_PORT, help=INPUT_PORT_HELP)
    net.add_argument("--iface", default="0.0.0.0", help="IPv4 address of the interface for multicast")
    net.add_argument("--peer", help="unicast HOST:PORT to send to instead of the group")
    net.add_argument("--listen", help="unicast HOST:PORT to receive on instead of joining the group")
    net.add_argument("--source", help="HOST:PORT to send from (default: the interface and this side's port; "
                                      "not the other side's, nor the one it receives on)")


def add_impairment_arguments(parser: argparse.ArgumentParser) -> None:
    imp = parser.add_argument_group("impairments (of what this node sends; reproducible with --seed)")
    imp.add_argument("--seed", type=SEED, default=0,
                     help=f"seed of the impairments' random choices, {SEED.range_text} (default 0)")
    imp.add_argument("--loss", type=PCT, default=0.0, metavar="PCT", help=f"PCT lost, {PCT.range_text}")
    imp.add_argument("--duplicate", type=PCT, default=0.0, metavar="PCT",
                     help=f"PCT delivered twice, {PCT.range_text}")
    imp.add_argument("--mirror", type=PCT, default=0.0, metavar="PCT",
                     help="PCT seen twice 0.05-3 ms apart, as a switch mirror port shows them to a capture "
                          f"(over sockets the peer gets the copy too), {PCT.range_text}")
    low, high = (f * Impairment.reorder_ms for f in REORDER_SPREAD)
    imp.add_argument("--reorder", type=REORDER, default=0.0, metavar="PCT",
                     help=f"PCT held back {low:g}-{high:g} ms, so that packets sent meanwhile overtake them, "
                          f"{REORDER.range_text} (held back together they overtake each other less: 100 only "
                          "delayed all)")
    imp.add_argument("--delay", type=DELAY, default=0.0, metavar="MS",
                     help=f"every packet sent MS later, {DELAY.range_text}")
    imp.add_argument("--jitter", type=DELAY, default=0.0, metavar="MS",
                     help=f"extra delay up to MS, {DELAY.range_text}")
    imp.add_argument("--corrupt", type=PCT, default=0.0, metavar="PCT",
                     help=f"corrupt the CRC of PCT, {PCT.range_text}")
    imp.add_argument("--outage", type=WINDOW, action="append", default=[], metavar="START:END",
                     help=f"send nothing between these times, {WINDOW.range_text}; repeatable")
    imp.add_argument("--stall", type=WINDOW, action="append", default=[], metavar="START:END",
                     help=f"the node hangs: neither sends nor receives, {WINDOW.range_text}; repeatable")
    imp.add_argument("--glink", type=WINDOW, action="append", default=[], metavar="START:END",
                     help="G-Link fallback: slower VRPO (controller), later VRAI (BU), "
                          f"{WINDOW.range_text}; repeatable")
    life = parser.add_argument_group("life of the node")
    life.add_argument("--stop-at", type=TIME, metavar="S",
                      help=f"send nothing from S seconds on, for good, {TIME.range_text}")
    life.add_argument("--restart", type=RESTART, action="append", default=[], metavar="AT[:NEW_PORT]",
                      help="go down at AT s and come back after --restart-silence with serials and command IDs "
                           "afresh, sending from NEW_PORT if given (0: a new ephemeral port), "
                           f"{RESTART.range_text}; repeatable")
    life.add_argument("--restart-silence", type=DURATION, metavar="S",
                      help=f"seconds down at each restart, {DURATION.range_text} (default {DEFAULT_SILENCE_S:g})")
    life.add_argument("--restart-serial", type=WORD, metavar="N",
                      help=f"first serial after a restart, {WORD.range_text}")
    life.add_argument("--serial-start", type=WORD, default=0, metavar="N",
                      help=f"first serial (e.g. above 32767, to reboot from there), {WORD.range_text}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="role", metavar="ROLE", required=True)
    bu = sub.add_parser("bu", help="simulated base unit", description="Simulated base unit (VRPI, VRCI, VRAI).")
    bu.add_argument("--script", help="remote/operator script (JSON, see vm110.sim.remote)")
    bu.add_argument("--disarmed", action="store_true", help="no RU armed (default: one RU armed)")
    bu.add_argument("--unarmed-rus", type=UNARMED_RUS, default=0, metavar="N",
                    help="unarmed RUs reported (beside the armed one, or alone with --disarmed), "
                         f"{UNARMED_RUS.range_text}")
    bu.add_argument("--no-motion", action="store_true", help="joysticks and switches stay at rest")
    bu.add_argument("--command-every", type=EVERY, default=0.0, metavar="S",
                    help=f"an operator command every S s, {EVERY.range_text} (0, the default: none)")
    bu.add_argument("--origin", type=WORD, default=DEFAULT_ORIGIN, metavar="N",
                    help=f"BU origin, {WORD.range_text} (default 0x{DEFAULT_ORIGIN:04x})")
    bu.add_argument("--command-id-start", type=WORD, default=0, metavar="N",
                    help=f"first command ID, {WORD.range_text}")
    ctl = sub.add_parser("controller", help="reference machine controller",
                         description="Reference machine controller (VRPO, VRAO, VRCO).")
    ctl.add_argument("--period", type=PERIOD, default=100.0, metavar="MS",
                     help=f"VRPO period, {PERIOD.range_text} (default 100)")
    ctl.add_argument("--data-size", type=DATA_SIZE, default=64, metavar="BYTES",
                     help=f"periodic data bytes (>488: bursts), {DATA_SIZE.range_text} (default 64)")
    ctl.add_argument("--vrco-timeout", type=TIMEOUT, default=float(C.VRCO_GIVE_UP_MS), metavar="MS",
                     help=f"give a VRCO up when not acknowledged within MS, {TIMEOUT.range_text} "
                          f"(default {C.VRCO_GIVE_UP_MS})")
    ctl.add_argument("--vrpi-timeout", type=TIMEOUT, default=float(C.VRPI_WATCHDOG_MS), metavar="MS",
                     help=f"flag a VRPI timeout after MS without VRPI, {TIMEOUT.range_text} "
                          f"(default {C.VRPI_WATCHDOG_MS})")
    ctl.add_argument("--command-every", type=EVERY, default=0.0, metavar="S",
                     help=f"a VRCO every S s, {EVERY.range_text} (0, the default: none)")
    ctl.add_argument("--command-id-start", type=WORD, default=0, metavar="N",
                     help=f"first command ID, {WORD.range_text}")
    for p in (bu, ctl):       # (the BU judges the controller's VRPO bursts by it)
        p.add_argument("--vrpo-start", type=VRPO_START, default=0, metavar="N", help=VRPO_START_HELP)
        add_reading_options(p, found=False)     # (another reading of TS-0006: analyze takes the same)
        add_network_arguments(p)
        add_impairment_arguments(p)
        p.add_argument("--duration", type=DURATION, metavar="S",
                       help=f"seconds to run, {DURATION.range_text} (default: until interrupted)")
        p.add_argument("--json", action="store_true", help="log events as JSON lines")
        p.add_argument("--quiet", action="store_true", help="only the summary at the end")


def udp_config(args: argparse.Namespace) -> UdpConfig:
    """The sockets for the role from the network options."""
    _ipv4("--iface", args.iface)
    if not _ipv4("--group", args.group).is_multicast:
        raise CliError(f"--group: {args.group[:40]!r} is not a multicast address (224.0.0.0 to 239.255.255.255)")
    cfg = multicast_config(args.role, args.group, args.port, args.iface)
    if args.peer:
        cfg.dest = _address("--peer", args.peer, lowest_port=1)
        peer = ipaddress.IPv4Address(cfg.dest[0])
        if peer.is_global and not peer.is_multicast:      # (said, not refused: plants use odd ranges)
            print(f"vm110 simulate: note: --peer {cfg.dest[0]} is a public address; an EG-Link peer sits on "
                  "the local network", file=sys.stderr)
    if args.listen:
        cfg.listen, cfg.group = _address("--listen", args.listen), None
    if args.source:
        cfg.source = _address("--source", args.source)
    return cfg


def _check_source_ports(role: str, input_port: int, cfg: UdpConfig, restarts: Sequence[Restart]) -> None:
    """The ports the node sends from (--source, a restart's new port) may be neither the other
    side's EG-Link port (TS-0006 2.2: inputs from the input port, outputs from the output port; a
    BU sending from the output port passed for the controller to every reader that goes by ports)
    nor the port the node receives on (that failed with "Address already in use", at the restart
    hours into a run, and blamed "another program")."""
    (rx_host, rx_port), (tx_host, tx_port) = cfg.listen, cfg.source
    shared = rx_host == tx_host or "0.0.0.0" in (rx_host, tx_host) or ipaddress.IPv4Address(rx_host).is_multicast
    own, other = (input_port, input_port + C.OUTPUT_PORT_OFFSET)
    if role == "controller":
        own, other = other, own
    names = {"bu": "base unit", "controller": "controller"}
    sources = [(f"--source {tx_host}:{tx_port}", tx_port)] + [(f"--restart {r.at_s:g}:{r.port}", r.port)
                                                             for r in restarts if r.port is not None]
    for option, port in sources:
        if port == other:
            peer = "controller" if role == "bu" else "bu"
            raise CliError(f"{option}: port {port} is the {names[peer]}'s (--port {input_port}); a {names[role]} "
                           f"sends from its own, {own}, or a port that is neither")
        if port and port == rx_port and shared:
            raise CliError(f"{option}: the node receives on port {rx_port} ({rx_host}); it must send from another")


def _ipv4(option: str, text: str) -> ipaddress.IPv4Address:
    try:
        return ipaddress.IPv4Address(text)
    except ValueError:
        raise CliError(f"{option}: {text[:40]!r} is not an IPv4 address") from None


def _address(option: str, text: str, lowest_port: int = 0) -> Address:
    """IPv4:PORT given to `option`; port 0 (any free one) only where a socket is bound to it."""
    try:
        host, port = parse_address(text)
    except CliError as exc:
        raise CliError(f"{option}: {exc}") from None
    if port < lowest_port:
        raise CliError(f"{option}: port {port} is not one to send to (1 to 65535)")
    return host, port


def impairment(args: argparse.Namespace) -> Impairment:
    return Impairment(loss=args.loss, duplicate=args.duplicate, mirror=args.mirror, reorder=args.reorder,
                      delay_ms=args.delay,
                      jitter_ms=args.jitter, corrupt=args.corrupt, outages=tuple(args.outage), seed=args.seed)


def life(args: argparse.Namespace) -> dict[str, Any]:
    """The `Life` fields of the node's configuration from the options."""
    if not args.restart:      # (they were taken without a word, and nothing restarted)
        given = [name for name, value in (("--restart-silence", args.restart_silence),
                                          ("--restart-serial", args.restart_serial)) if value is not None]
        if given:
            raise CliError(f"{given[0]} is for a --restart AT[:NEW_PORT]; none was given")
    silence = DEFAULT_SILENCE_S if args.restart_silence is None else args.restart_silence
    serial = 0 if args.restart_serial is None else args.restart_serial
    restarts = tuple(sorted((Restart(at, silence, serial, 0, port) for at, port in args.restart),
                            key=lambda r: r.at_s))
    # (start, end, option, what it is): a node that hangs, is down or has stopped cannot begin
    # another of them (a restart lost in another; a stall ending after the stall it began in, its
    # log going back in time).
    windows = [(a, b, "--stall", f"the stall {a:g}:{b:g}") for a, b in args.stall]
    windows += [(r.at_s, r.at_s + r.silence_s, "--restart",
                 f"the restart at {r.at_s:g} s (down for --restart-silence {r.silence_s:g} s)") for r in restarts]
    if args.stop_at is not None:
        stop = args.stop_at
        windows.append((stop, math.inf, "--stop-at", f"--stop-at {stop:g} (sends nothing from then on)"))
    windows.sort(key=lambda w: w[:2])
    for before, after in itertools.pairwise(windows):
        if after[0] < before[1]:
            raise CliError(f"{after[2]}: {after[0]:g} s is within {before[3]}")
    return {"stalls": tuple(args.stall), "restarts": restarts, "stop_at_s": args.stop_at}


def build_node(args: argparse.Namespace, printer: Callable[[int, str], None]) -> Any:
    """The node of the options; its log goes to `printer` (and the JSON listener), none is kept:
    a run goes on for days, and the summary needs only the counts."""
    node = _node(args, printer)
    node.keep_log = False
    return node


def _node(args: argparse.Namespace, printer: Callable[[int, str], None]) -> Any:
    if args.role == "bu":
        if args.script:
            given = [name for name, on in (("--disarmed", args.disarmed), ("--unarmed-rus", args.unarmed_rus),
                                           ("--no-motion", args.no_motion), ("--command-every", args.command_every))
                     if on]
            if given:
                raise CliError(f"{given[0]} and --script contradict each other: the script says what the remote does")
        remote = Remote.load(args.script) if args.script else Remote.simple(
            armed=not args.disarmed, unarmed_rus=args.unarmed_rus, motion=not args.no_motion,
            command_every=args.command_every)
        bu_cfg = BaseUnitConfig(origin=args.origin, command_id_start=args.command_id_start,
                                glink=tuple(args.glink), seed=args.seed, vrpo_start=args.vrpo_start, **life(args))
        return BaseUnit(remote, bu_cfg, printer=printer, **wire(args))
    cfg = ControllerConfig(period_ms=args.period, data_size=args.data_size, vrco_timeout_ms=args.vrco_timeout,
                           vrpi_timeout_ms=args.vrpi_timeout, command_every_s=args.command_every,
                           command_id_start=args.command_id_start, first_packet_number=args.vrpo_start,
                           glink=tuple(args.glink), **life(args))
    return Controller(cfg, printer=printer, **wire(args))


def wire(args: argparse.Namespace) -> dict[str, Any]:
    """How the node numbers and checks its packets (the `Node` arguments) from the options."""
    return {"serial_start": args.serial_start, **reading_of(args).node_options()}


def sockets_line(role: str, transport: UdpTransport) -> str:
    """Where the node receives and sends, as opened (port 0 resolved)."""
    rx, tx, (dest_host, dest_port) = transport.rx_address, transport.tx_address, transport.config.dest
    group = f" (group {transport.config.group})" if transport.config.group else ""
    return f"{role}: receiving on {rx[0]}:{rx[1]}{group}, sending from {tx[0]}:{tx[1]} to {dest_host}:{dest_port}"


def run(args: argparse.Namespace) -> int:
    # SIGTERM (systemd, `timeout`, a test harness) and SIGHUP (its terminal or SSH session closed)
    # are interruptions like Ctrl-C: the loop ends at its next turn, the sockets close, the summary
    # is printed, exit 130 (SIGTERM ended it 0, a clean end to a supervisor; SIGHUP killed it
    # without its summary). Before the loop runs, and at a second signal, it stops at once.
    stopped_by: list[str] = []
    runner: Optional[RealtimeRunner] = None

    def interrupt(signum: int, frame: Any) -> None:
        if stopped_by or runner is None:
            raise KeyboardInterrupt
        stopped_by.append(signal.Signals(signum).name)
        runner.stop(timeout=0)

    previous = {sig: signal.signal(sig, interrupt) for sig in STOPPING}
    claims: list[Optional[socket.socket]] = []
    try:
        node, runner = _prepare(args, claims)
        _run(args, node, runner, stopped_by)
    finally:
        for claim in claims:
            if claim is not None:
                claim.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return EXIT_INTERRUPTED if stopped_by else EXIT_OK


def _prepare(args: argparse.Namespace, claims: list[Optional[socket.socket]]) -> tuple[Any, RealtimeRunner]:
    """The node and its runner, sockets open, a BU's origin claimed (in `claims`: `sim.claim`); each
    log line carries the wall-clock time in ISO 8601 UTC, then the node's own seconds from its start."""
    clock = WallClock()

    def printer(now: int, line: str) -> None:
        if not args.quiet and not args.json:
            print(f"{utc_iso(clock.wall(now))} {line}", flush=True)

    sockets = udp_config(args)      # its errors before anything starts
    node = build_node(args, printer)
    _check_source_ports(args.role, args.port, sockets, node.restarts)
    if args.json and not args.quiet:
        node.listeners.append(lambda entry: print(json.dumps({"time_utc": utc_iso(clock.wall(seconds(entry["t"]))),
                                                              **entry}), flush=True))
    imp = impairment(args)
    # (--corrupt spoils the CRC of the variant sent: one of another variant could be right by chance)
    impairer = Impairer(imp, args.role, args.crc, args.crc_order) if imp.active() else None
    if args.role == "bu" and sockets.source[1]:   # (closed by `run`, or by the kernel however the process ends)
        claims.append(claim_origin(sockets.dest, sockets.source, args.origin))
    transport = UdpTransport(sockets, impairer).open()
    print(f"{utc_iso(time.time())} {sockets_line(args.role, transport)}", file=sys.stderr, flush=True)
    return node, RealtimeRunner([(node, transport)], clock)


def _run(args: argparse.Namespace, node: Any, runner: RealtimeRunner, stopped_by: list[str]) -> None:
    ended = "error"       # (a failure during the run, e.g. a restart's new port taken, said "duration")
    try:
        runner.run(args.duration)
        ended = "duration"
    except BrokenPipeError:
        # The log's reader went away (`| head`): the run ends there, as a pipe's writer does, and
        # is no run that reached its --duration (exit 130); the summary goes to stderr.
        silence_stdout()
        stopped_by.append("closed_pipe")
    finally:
        if stopped_by:
            print(f"{utc_iso(time.time())} {args.role}: stopped by {stopped_by[0]}", file=sys.stderr, flush=True)
        # How the run ended, in the log too (a log kept without stderr): its --duration, a signal or an error.
        end = stopped_by[0] if stopped_by else ended
        summary = json.dumps({"time_utc": utc_iso(time.time()), "end": end, "summary": node.summary()})
        try:
            print(summary, file=sys.stderr if "closed_pipe" in stopped_by else sys.stdout, flush=True)
        except BrokenPipeError:     # (gone as the run ended: its summary is not lost either)
            silence_stdout()
            print(summary, file=sys.stderr, flush=True)
