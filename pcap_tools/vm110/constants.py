"""Protocol constants of TS-0006 and of interpretation.md, written down once.

Every other module (and, by the shared vectors, the Lua dissector) takes its numbers from here.
"""
from __future__ import annotations

import enum

# --- Framing (TS-0006 section 3) -------------------------------------------------------------
ID_LEN = 4
HEADER_LEN = 12
CRC_LEN = 4
PREFIX_LEN = ID_LEN + HEADER_LEN          # packet ID + header: where the payload starts
OVERHEAD = PREFIX_LEN + CRC_LEN           # UDP payload length = OVERHEAD + size
MAX_PAYLOAD = 492
MAX_PACKET = OVERHEAD + MAX_PAYLOAD
SUPPORTED_REVISION = 0


class PacketType(str, enum.Enum):
    """The six packet IDs; the 4th character gives the direction."""

    VRPI = "VRPI"
    VRPO = "VRPO"
    VRCI = "VRCI"
    VRCO = "VRCO"
    VRAI = "VRAI"
    VRAO = "VRAO"

    @property
    def direction(self) -> "Direction":
        return Direction.INPUT if self.value[3] == "I" else Direction.OUTPUT


class Direction(str, enum.Enum):
    INPUT = "Input"     # base unit -> machine controller
    OUTPUT = "Output"   # machine controller -> base unit


PACKET_DESCRIPTIONS = {
    PacketType.VRPI: "VisionRemote Periodic Input",
    PacketType.VRPO: "VisionRemote Periodic Output",
    PacketType.VRCI: "VisionRemote Command Input",
    PacketType.VRCO: "VisionRemote Command Output",
    PacketType.VRAI: "VisionRemote Acknowledge Input",
    PacketType.VRAO: "VisionRemote Acknowledge Output",
}

# Field sizes the declaration in vm110.protocol uses (payload layouts and their bounds are derived there).
VRPO_MAX_DATA = 488
COMMAND_DATA_LEN = 16
VRPI_SPARE_LEN = 6

# Which acknowledgement answers which command (the spec's "VRPO" in 4.6 is a typo for VRCO).
ACK_OF = {PacketType.VRAO: PacketType.VRCI, PacketType.VRAI: PacketType.VRCO}


# --- Enums (TS-0006 section 4.1) -------------------------------------------------------------
class BuState(enum.IntEnum):
    INITIAL = 0x00
    STOPPED = 0x01
    EXTERNAL_LINK_ERROR = 0x02
    BLOCKED = 0x03
    FAILED = 0x04
    DISARMED = 0x10
    ARMED = 0x11


class LinkStatus(enum.IntEnum):
    UNUSED = 0
    OPERATIONAL = 1
    NO_LINK = 2
    LINK_ERROR = 3
    INTERFACE_ERROR = 4
    DATA_ERROR = 5
    PASSIVE = 6


class RuState(enum.IntEnum):
    INITIAL = 0
    DISARMED = 1
    ARMED = 2
    ENABLED = 3
    STOPPED = 4


class RuDisabled(enum.IntEnum):
    ENABLED = 0
    TILT = 1
    INACTIVITY = 2


class RuCable(enum.IntEnum):
    WIRELESS = 0
    CABLE = 1


class RuDocked(enum.IntEnum):
    NOT_DOCKED = 0
    DOCKED = 1


class EncoderSwitch(enum.IntEnum):
    RELEASED = 0
    PUSHED = 1


# Display names: the same strings are the dissector's value strings (checked by the vectors).
BU_STATE_NAMES = {
    BuState.INITIAL: "Initial",
    BuState.STOPPED: "Stopped",
    BuState.EXTERNAL_LINK_ERROR: "External link error",
    BuState.BLOCKED: "Blocked",
    BuState.FAILED: "Failed",
    BuState.DISARMED: "Disarmed",
    BuState.ARMED: "Armed",
}
LINK_STATUS_NAMES = {
    LinkStatus.UNUSED: "Unused",
    LinkStatus.OPERATIONAL: "Operational",
    LinkStatus.NO_LINK: "No link",
    LinkStatus.LINK_ERROR: "Link error",
    LinkStatus.INTERFACE_ERROR: "Interface error",
    LinkStatus.DATA_ERROR: "Data error",
    LinkStatus.PASSIVE: "Passive",
}
RU_STATE_NAMES = {
    RuState.INITIAL: "Initial",
    RuState.DISARMED: "Disarmed",
    RuState.ARMED: "Armed",
    RuState.ENABLED: "Enabled",
    RuState.STOPPED: "Stopped",
}
RU_DISABLED_NAMES = {
    RuDisabled.ENABLED: "Enabled",
    RuDisabled.TILT: "Disabled (tilt)",
    RuDisabled.INACTIVITY: "Disabled (inactivity)",
}
RU_CABLE_NAMES = {RuCable.WIRELESS: "Wireless", RuCable.CABLE: "Cable"}
RU_DOCKED_NAMES = {RuDocked.NOT_DOCKED: "Not docked", RuDocked.DOCKED: "Docked"}
ENCODER_SWITCH_NAMES = {EncoderSwitch.RELEASED: "Released", EncoderSwitch.PUSHED: "Pushed"}

# ES-Link relays are open while the BU state is below Disarmed (section 4.1.1).
ES_RELAYS_CLOSED_FROM = BuState.DISARMED

# --- Documented value ranges (warnings, not illegal) -----------------------------------------
JOYSTICK_LIMIT = 1000
PERCENT_MAX = 100
VLAPS_MAX = 3
SWITCH_MIN = -1
SWITCH_MAX = 1000
JOYSTICKS = 4
SWITCHES = 8


# --- Problems (illegal, section 5.1.5) and warnings: the names are shared with the dissector --
CRC_GOOD = "Good"
CRC_BAD = "Bad"


class Problem(str, enum.Enum):
    UNKNOWN_ID = "unknown_id"
    BAD_CRC = "bad_crc"
    REVISION = "revision"
    SIZE_MISMATCH = "size_mismatch"
    SIZE_TOO_LARGE = "size_too_large"
    TRUNCATED = "truncated"


class WarningCode(str, enum.Enum):
    """Warning codes; a decoded warning is "code" or "code:field"."""

    SPARE_NONZERO = "spare_nonzero"
    ORIGIN_NONZERO = "origin_nonzero"
    OUT_OF_RANGE = "out_of_range"
    UNKNOWN_ENUM = "unknown_enum"
    DISARMED_RU_DATA = "disarmed_ru_data"
    EXTRA_PAYLOAD = "extra_payload"


# --- Network defaults (section 2.2) ----------------------------------------------------------
MULTICAST_GROUP = "239.255.42.20"
INPUT_PORT = 5825
OUTPUT_PORT_OFFSET = 2
OUTPUT_PORT = INPUT_PORT + OUTPUT_PORT_OFFSET
MULTICAST_TTL = 1

# --- Timing in milliseconds (section 5.1) ----------------------------------------------------
VRPI_PERIOD_MS = 125
VRPI_WATCHDOG_MS = 500
VRPO_PERIOD_MIN_MS = 50
VRPO_PERIOD_MAX_MS = 200
VRPO_WATCHDOG_MS = 2000
COMMAND_RESEND_MS = 100
VRCI_FAIL_MS = 2000
VRCO_GIVE_UP_MS = 2000
VRPO_BURST_GAP_MS = 20

# --- Serial numbers and command IDs ----------------------------------------------------------
SERIAL_MODULUS = 1 << 16
SERIAL_HALF = SERIAL_MODULUS // 2
