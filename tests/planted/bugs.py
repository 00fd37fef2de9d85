"""Planted-bug controllers: the reference controller with one realistic defect each.

Every class names the fuzzer oracle that must catch it (`ORACLE`). They change the reference
controller only through its documented hooks (see vm110.sim.controller).
"""
from __future__ import annotations

import os
from typing import Optional

from vm110 import constants as C
from vm110.decode import decode
from vm110.sim.clock import ms
from vm110.sim.controller import Controller, ControllerConfig
from vm110.sim.impair import mangle
from vm110.sim.node import Meta, Rx

CRASH_EXIT_CODE = 3


class CrashOnJoystick(Controller):
    """Dies on joystick 1 = -32768: abs() of the most negative 16-bit value overflows (C habit)."""

    ORACLE = "crash"

    def on_vrpi(self, rx: Rx, now: int) -> None:
        if decode(rx.data).get("joystick1") == -0x8000:
            os._exit(CRASH_EXIT_CODE)
        super().on_vrpi(rx, now)


class StallAfterOversize(Controller):
    """Stops sending VRPO for good after a datagram longer than the largest legal packet
    (a receive buffer of MAX_PACKET bytes overflows into the VRPO timer)."""

    ORACLE = "stall"
    dead = False

    def receive(self, data: bytes, now: int, src: object = None) -> None:
        if len(data) > C.MAX_PACKET:
            self.dead = True
        super().receive(data, now, src)

    def vrpo_payloads(self, now: int) -> list[bytes]:
        return [] if self.dead else super().vrpo_payloads(now)


class AckBadCrc(Controller):
    """Checks the CRC of everything but commands: a VRCI with a bad CRC is acknowledged (and run)."""

    ORACLE = "illegal_acked"

    def on_illegal(self, data: bytes, problems: list[str], now: int, src: object) -> None:
        if data[:C.ID_LEN] == C.PacketType.VRCI.value.encode() and problems == [C.Problem.BAD_CRC.value]:
            fields = decode(data)
            self.on_vrci(Rx(C.PacketType.VRCI, fields["origin"], fields["serial"],
                            data[C.PREFIX_LEN:C.PREFIX_LEN + fields["size"]], data, src), now)


class NoReack(Controller):
    """Acknowledges a command ID only the first time: retransmissions get no VRAO."""

    ORACLE = "missing_ack"

    def on_vrci(self, rx: Rx, now: int) -> None:
        if self.handled.recent(rx, int.from_bytes(rx.payload[:2], "little"), now):
            return
        super().on_vrci(rx, now)


class BadCrcAfterWrap(Controller):
    """Sends the VRAO for command ID 65535 with a bad CRC (an off-by-one at the ID wrap)."""

    ORACLE = "malformed_output"

    def transmit(self, data: bytes, now: int, meta: Meta) -> None:
        if meta.ptype is C.PacketType.VRAO and meta.key == C.SERIAL_MODULUS - 1:
            data = mangle(data, C.Problem.BAD_CRC.value)[0]
        super().transmit(data, now, meta)


class ResendAfterVrai(Controller):
    """Ignores VRAI: keeps resending each VRCO every 100 ms until its give-up timeout."""

    ORACLE = "vrco_retransmit"

    def on_vrai(self, rx: Rx, now: int) -> None:
        self.event(now, "vrai_ignored", command_id=int.from_bytes(rx.payload[:2], "little"))


class NoVrcoResend(Controller):
    """Sends each VRCO once: the resends are lost before the wire, so an unacknowledged command
    is silently dropped."""

    ORACLE = "vrco_retransmit"

    def transmit(self, data: bytes, now: int, meta: Meta) -> None:
        command = self.in_flight.get(meta.key) if meta.ptype is C.PacketType.VRCO else None
        if command is not None and command["count"] >= 1:     # counted after sending
            return
        super().transmit(data, now, meta)


class TwoExceptions(Controller):
    """Two bugs of a controller in Python, each an uncaught exception: a KeyError on command ID
    65535 (a table of the IDs it knows) and a ZeroDivisionError on a battery of 0 %."""

    ORACLE = "crash"

    def on_vrci(self, rx: Rx, now: int) -> None:
        if decode(rx.data).get("command_id") == 0xFFFF:
            raise KeyError(0xFFFF)
        super().on_vrci(rx, now)

    def on_vrpi(self, rx: Rx, now: int) -> None:
        battery = decode(rx.data).get("ru_battery")
        if battery is not None:
            100 // battery
        super().on_vrpi(rx, now)


class CrashOnEmptyCommand(Controller):
    """Dies on command data FF 00 ...: opcode 0xFF carries its argument count, here 0, and the
    handler reads its first argument all the same (an IndexError, as a controller in Python dies)."""

    ORACLE = "crash"

    def on_vrci(self, rx: Rx, now: int) -> None:
        data = decode(rx.data).get("command_data", b"")
        if data[:1] == b"\xff":
            arguments = data[2:2 + data[1]]
            arguments[0]
        super().on_vrci(rx, now)


class NoAckWhileLoading(Controller):
    """Executes but does not acknowledge the commands that come in the first 240 ms after its
    first VRPO, while it loads its recipe (the ack flag is cleared by the loader): a bug that
    replays only when a command comes as early in its life as in the run's confirming replay."""

    ORACLE = "missing_ack"
    LOADING_US = ms(240)   # (the run replays 135 ms after it, --replay waited 250 ms: margins for a loaded machine)
    started = 0

    def start(self, now: int) -> None:
        self.started = now
        super().start(now)

    def acknowledge(self, command_id: int, now: int) -> None:
        if now - self.started >= self.LOADING_US:
            super().acknowledge(command_id, now)


class AcksResendsOnly(Controller):
    """Not a bug: ignores the first transmission of each command ID (one that came while it was
    busy, or that its scan cycle did not read) and acknowledges the base unit's resend of it, which
    comes 100 ms later (TS-0006 5.1.3)."""

    ORACLE = None

    def __init__(self, config: Optional[ControllerConfig] = None) -> None:
        super().__init__(config)
        self.missed: set[int] = set()

    def on_vrci(self, rx: Rx, now: int) -> None:
        command_id = int.from_bytes(rx.payload[:2], "little")
        if command_id not in self.missed:
            self.missed.add(command_id)
            return
        super().on_vrci(rx, now)


class NeverAck(Controller):
    """Executes every command and acknowledges none, however often the base unit resends it."""

    ORACLE = "missing_ack"

    def acknowledge(self, command_id: int, now: int) -> None:
        pass


BUGS: dict[str, type[Controller]] = {
    "reference": Controller,
    "crash-on-joystick": CrashOnJoystick,
    "stall-after-oversize": StallAfterOversize,
    "ack-bad-crc": AckBadCrc,
    "no-reack": NoReack,
    "bad-crc-after-wrap": BadCrcAfterWrap,
    "resend-after-vrai": ResendAfterVrai,
    "no-vrco-resend": NoVrcoResend,
    "two-exceptions": TwoExceptions,
    "crash-on-empty-command": CrashOnEmptyCommand,
    "no-ack-while-loading": NoAckWhileLoading,
    "acks-resends-only": AcksResendsOnly,
    "never-ack": NeverAck,
}
