"""VESC UART packets (vedderb/bldc ``packet.c`` / ``commands.c``), sans-I/O.

Spec: ``protocols/vesc-uart.md``. A packet on the wire::

    0x02 LEN(1)   payload CRC16 0x03     payload of 1..255 bytes
    0x03 LEN(2)   payload CRC16 0x03     payload of 256..65535 bytes (LEN big-endian)

CRC16 is CRC-16/XMODEM (poly 0x1021, init 0) of the payload, big-endian.
The payload's first byte is the command (COMM_*), then big-endian fields.

:class:`PacketDecoder` turns a byte stream into payloads: ``receive_data``
then ``next_event`` until ``NEED_DATA``. Garbage, truncated packets and bad
CRCs are skipped and counted, and the decoder resynchronises on the next
valid packet, also when a bogus length field claims more bytes than will
come (a complete valid packet later in the buffer wins). A length over
``max_payload`` is rejected at once, so nothing is allocated for it; the
buffer never holds more than one maximal packet plus the last chunk fed
(and, until they are dropped in bulk, as many consumed bytes). Those rules
live in :mod:`hilsim.protocols.framing`, shared with VRCSR; decoding costs
amortized linear time however the bytes are cut.
"""

from __future__ import annotations

import binascii
import math
import re
import struct
from dataclasses import dataclass, field
from typing import Final, Union

from hilsim.protocols.codec import NEED_DATA, NeedData
from hilsim.protocols.framing import NEED, OK, ResyncFramer, Verdict

START_SHORT: Final = 0x02
START_LONG: Final = 0x03
END: Final = 0x03
MAX_PAYLOAD: Final = 512          # the firmware's PACKET_MAX_PL_LEN

_START: Final = re.compile(b"[\x02\x03]")  # START_SHORT or START_LONG

COMM_FW_VERSION: Final = 0
COMM_GET_VALUES: Final = 4
COMM_SET_DUTY: Final = 5
COMM_SET_CURRENT: Final = 6
COMM_SET_CURRENT_BRAKE: Final = 7
COMM_SET_RPM: Final = 8
COMM_ALIVE: Final = 30
COMM_FORWARD_CAN: Final = 34
COMM_GET_VALUES_SELECTIVE: Final = 50


def crc16(data: bytes | bytearray) -> int:
    """CRC-16/XMODEM of ``data`` (poly 0x1021, init 0, no reflection)."""
    return binascii.crc_hqx(data, 0)


def frame(payload: bytes) -> bytes:
    """Wrap a payload (1..65535 bytes) in a packet."""
    n = len(payload)
    if not 1 <= n <= 0xFFFF:
        raise ValueError(f"VESC payload must be 1..65535 bytes, got {n}")
    head = bytes([START_SHORT, n]) if n <= 255 else bytes([START_LONG]) + n.to_bytes(2, "big")
    return head + payload + crc16(payload).to_bytes(2, "big") + bytes([END])




@dataclass
class DecoderStats:
    packets: int = 0
    crc_errors: int = 0          # framed correctly, CRC wrong
    framing_errors: int = 0      # bad end byte or a length out of range
    bytes_skipped: int = 0       # bytes thrown away while resynchronising


@dataclass
class PacketDecoder(ResyncFramer[bytes]):
    """Byte stream -> payloads (bytes). Never raises on any input.

    The resynchronisation rules and their linear cost are :class:`~hilsim.protocols.framing.ResyncFramer`'s;
    this class gives VESC's framing: where a packet starts, what makes it valid, what is counted.
    """

    max_payload: int = MAX_PAYLOAD
    stats: DecoderStats = field(default_factory=DecoderStats)

    def next_event(self) -> bytes | NeedData:
        """The next complete, valid payload, or NEED_DATA."""
        payload = self._next_frame()
        return NEED_DATA if payload is None else payload

    def _find_start(self, buf: bytearray, i: int) -> int:
        m = _START.search(buf, i)
        return -1 if m is None else m.start()

    def _judge(self, buf: bytearray, i: int) -> Verdict:
        hl = 2 if buf[i] == START_SHORT else 3
        have = len(buf) - i
        if have < hl:
            return NEED, hl
        n = buf[i + 1] if hl == 2 else (buf[i + 1] << 8) | buf[i + 2]
        if n == 0 or n > self.max_payload or (hl == 3 and n <= 255):
            return "length", 0
        total = hl + n + 3
        if have < total:
            return NEED, total
        end = i + total
        if buf[end - 1] != END:
            return "end", 0
        if crc16(buf[i + hl:end - 3]) != (buf[end - 3] << 8) | buf[end - 2]:
            return "crc", 0
        return OK, total

    def _event(self, buf: bytearray, i: int, total: int) -> bytes:
        self.stats.packets += 1
        return bytes(buf[i + (2 if buf[i] == START_SHORT else 3):i + total - 3])

    def _rejected(self, kind: str) -> None:
        if kind == "crc":
            self.stats.crc_errors += 1
        else:
            self.stats.framing_errors += 1

    def _dropped(self) -> None:
        self.stats.framing_errors += 1  # a bogus length: a valid packet came before it was complete

    def _skipped(self, n: int) -> None:
        self.stats.bytes_skipped += n


# ---------------------------------------------------------------- messages


@dataclass(frozen=True)
class SetDuty:
    duty: float            # [1] -1..1 (x 1e5 on the wire)


@dataclass(frozen=True)
class SetCurrent:
    current: float         # [A] motor current (x 1e3 on the wire)


@dataclass(frozen=True)
class SetCurrentBrake:
    current: float         # [A] (x 1e3 on the wire)


@dataclass(frozen=True)
class SetRpm:
    erpm: float            # [rev/min] electrical (integer on the wire)


@dataclass(frozen=True)
class GetValues:
    mask: int | None = None   # None: COMM_GET_VALUES (all fields); else COMM_GET_VALUES_SELECTIVE


@dataclass(frozen=True)
class GetFwVersion:
    pass


@dataclass(frozen=True)
class Alive:
    pass


@dataclass(frozen=True)
class ForwardCan:
    """COMM_FORWARD_CAN: ``inner`` is meant for the ESC with ``controller_id`` on the CAN bus."""

    controller_id: int
    inner: "Command"


@dataclass(frozen=True)
class Unsupported:
    """A well-framed payload this emulation does not act on (counted, no reply)."""

    command: int
    reason: str


Command = Union[SetDuty, SetCurrent, SetCurrentBrake, SetRpm, GetValues, GetFwVersion, Alive, ForwardCan]

_SCALED: Final[dict[int, tuple[type, float]]] = {
    COMM_SET_DUTY: (SetDuty, 1e5), COMM_SET_CURRENT: (SetCurrent, 1e3),
    COMM_SET_CURRENT_BRAKE: (SetCurrentBrake, 1e3), COMM_SET_RPM: (SetRpm, 1.0),
}


def decode_command(payload: bytes, _depth: int = 0) -> Command | Unsupported:
    """A payload from the host -> a command (never raises)."""
    if not payload:
        return Unsupported(-1, "empty payload")
    cmd, body = payload[0], payload[1:]
    if cmd in _SCALED:
        cls, scale = _SCALED[cmd]
        if len(body) < 4:
            return Unsupported(cmd, f"command {cmd} needs 4 data bytes, got {len(body)}")
        return cls(struct.unpack(">i", body[:4])[0] / scale)
    if cmd == COMM_GET_VALUES:
        return GetValues()
    if cmd == COMM_GET_VALUES_SELECTIVE:
        if len(body) < 4:
            return Unsupported(cmd, "GET_VALUES_SELECTIVE needs a 4-byte mask")
        return GetValues(int.from_bytes(body[:4], "big"))
    if cmd == COMM_FW_VERSION:
        return GetFwVersion()
    if cmd == COMM_ALIVE:
        return Alive()
    if cmd == COMM_FORWARD_CAN:
        if len(body) < 2 or _depth:
            return Unsupported(cmd, "FORWARD_CAN needs an id and a payload (and no nesting)")
        inner = decode_command(body[1:], _depth + 1)
        if isinstance(inner, Unsupported):
            return inner
        return ForwardCan(body[0], inner)
    return Unsupported(cmd, f"command {cmd} not emulated")


def _i32(value: float, scale: float) -> bytes:
    raw = round(value * scale)
    if not -(2 ** 31) <= raw < 2 ** 31:
        raise ValueError(f"{value} x {scale:g} does not fit an int32")
    return struct.pack(">i", raw)


def encode_command(command: Command) -> bytes:
    """Host side: a command -> its payload (wrap it with :func:`frame`)."""
    if isinstance(command, SetDuty):
        return bytes([COMM_SET_DUTY]) + _i32(command.duty, 1e5)
    if isinstance(command, SetCurrent):
        return bytes([COMM_SET_CURRENT]) + _i32(command.current, 1e3)
    if isinstance(command, SetCurrentBrake):
        return bytes([COMM_SET_CURRENT_BRAKE]) + _i32(command.current, 1e3)
    if isinstance(command, SetRpm):
        return bytes([COMM_SET_RPM]) + _i32(command.erpm, 1.0)
    if isinstance(command, GetValues):
        if command.mask is None:
            return bytes([COMM_GET_VALUES])
        return bytes([COMM_GET_VALUES_SELECTIVE]) + (command.mask & 0xFFFFFFFF).to_bytes(4, "big")
    if isinstance(command, GetFwVersion):
        return bytes([COMM_FW_VERSION])
    if isinstance(command, Alive):
        return bytes([COMM_ALIVE])
    if isinstance(command, ForwardCan):
        if isinstance(command.inner, ForwardCan):
            raise ValueError("FORWARD_CAN cannot be nested")
        return bytes([COMM_FORWARD_CAN, command.controller_id & 0xFF]) + encode_command(command.inner)
    raise TypeError(f"not a VESC UART command: {command!r}")


# ---------------------------------------------------------------- values reply


@dataclass(frozen=True)
class Values:
    """The COMM_GET_VALUES reply (firmware 5.x/6.x field order; mask bit in brackets).

    Temperatures [degC], currents [A], voltages [V], rpm electrical [rev/min],
    amp_hours [Ah], watt_hours [Wh], pid_pos [deg].
    """

    temp_fet: float = 0.0              # [0]  int16 x 10
    temp_motor: float = 0.0            # [1]  int16 x 10
    avg_motor_current: float = 0.0     # [2]  int32 x 100
    avg_input_current: float = 0.0     # [3]  int32 x 100
    avg_id: float = 0.0                # [4]  int32 x 100
    avg_iq: float = 0.0                # [5]  int32 x 100
    duty_now: float = 0.0              # [6]  int16 x 1000
    rpm: float = 0.0                   # [7]  int32 (ERPM)
    v_in: float = 0.0                  # [8]  int16 x 10
    amp_hours: float = 0.0             # [9]  int32 x 1e4
    amp_hours_charged: float = 0.0     # [10] int32 x 1e4
    watt_hours: float = 0.0            # [11] int32 x 1e4
    watt_hours_charged: float = 0.0    # [12] int32 x 1e4
    tachometer: int = 0                # [13] int32
    tachometer_abs: int = 0            # [14] int32
    fault_code: int = 0                # [15] uint8
    pid_pos: float = 0.0               # [16] int32 x 1e6
    controller_id: int = 0             # [17] uint8
    temp_mos1: float = 0.0             # [18] 3 x int16 x 10
    temp_mos2: float = 0.0
    temp_mos3: float = 0.0
    avg_vd: float = 0.0                # [19] int32 x 1000
    avg_vq: float = 0.0                # [20] int32 x 1000
    status: int = 0                    # [21] uint8: bit0 timeout, bit1 kill switch


# (mask bit, [(field, struct code, scale)])
_LAYOUT: Final[list[tuple[int, list[tuple[str, str, float]]]]] = [
    (0, [("temp_fet", "h", 10)]), (1, [("temp_motor", "h", 10)]),
    (2, [("avg_motor_current", "i", 100)]), (3, [("avg_input_current", "i", 100)]),
    (4, [("avg_id", "i", 100)]), (5, [("avg_iq", "i", 100)]), (6, [("duty_now", "h", 1000)]),
    (7, [("rpm", "i", 1)]), (8, [("v_in", "h", 10)]), (9, [("amp_hours", "i", 1e4)]),
    (10, [("amp_hours_charged", "i", 1e4)]), (11, [("watt_hours", "i", 1e4)]),
    (12, [("watt_hours_charged", "i", 1e4)]), (13, [("tachometer", "i", 1)]),
    (14, [("tachometer_abs", "i", 1)]), (15, [("fault_code", "B", 1)]), (16, [("pid_pos", "i", 1e6)]),
    (17, [("controller_id", "B", 1)]),
    (18, [("temp_mos1", "h", 10), ("temp_mos2", "h", 10), ("temp_mos3", "h", 10)]),
    (19, [("avg_vd", "i", 1000)]), (20, [("avg_vq", "i", 1000)]), (21, [("status", "B", 1)]),
]
ALL_FIELDS: Final = (1 << 22) - 1
_LIMITS: Final = {"h": (-32768, 32767), "i": (-(2 ** 31), 2 ** 31 - 1), "B": (0, 255)}


def _raw(value: float, code: str, scale: float) -> int:
    lo, hi = _LIMITS[code]
    v = float(value) * scale
    if not math.isfinite(v):
        v = 0.0
    return int(min(max(round(v), lo), hi))  # saturate like the firmware's clipped casts


def encode_values(values: Values, mask: int | None = None) -> bytes:
    """The reply payload to GET_VALUES (``mask`` None) or GET_VALUES_SELECTIVE (``mask``).

    Values beyond a field's integer range saturate."""
    out = bytearray([COMM_GET_VALUES if mask is None else COMM_GET_VALUES_SELECTIVE])
    if mask is not None:
        out += (mask & 0xFFFFFFFF).to_bytes(4, "big")
    use = ALL_FIELDS if mask is None else mask
    for bit, fields in _LAYOUT:
        if use & (1 << bit):
            for name, code, scale in fields:
                out += struct.pack(">" + code, _raw(getattr(values, name), code, scale))
    return bytes(out)


def decode_values(payload: bytes) -> Values | None:
    """Host side: a GET_VALUES(_SELECTIVE) reply -> Values (absent fields 0); None if malformed."""
    if not payload or payload[0] not in (COMM_GET_VALUES, COMM_GET_VALUES_SELECTIVE):
        return None
    pos, mask = 1, ALL_FIELDS
    if payload[0] == COMM_GET_VALUES_SELECTIVE:
        if len(payload) < 5:
            return None
        mask, pos = int.from_bytes(payload[1:5], "big"), 5
    got: dict[str, float | int] = {}
    for bit, fields in _LAYOUT:
        if not mask & (1 << bit):
            continue
        for name, code, scale in fields:
            size = struct.calcsize(code)
            if pos + size > len(payload):
                return None
            raw = struct.unpack(">" + code, payload[pos:pos + size])[0]
            pos += size
            got[name] = raw if code == "B" or name.startswith("tachometer") else raw / scale
    return Values(**got)  # type: ignore[arg-type]


@dataclass(frozen=True)
class FwVersion:
    major: int = 6
    minor: int = 2
    hw_name: str = "hilsim"
    uuid: bytes = bytes(12)


def encode_fw_version(v: FwVersion) -> bytes:
    """Reply to COMM_FW_VERSION: major, minor, hardware name (NUL-ended), 12-byte UUID,
    pairing done, test version, hardware type (0 = VESC), custom config count."""
    name = v.hw_name.encode("ascii", "replace")[:31]
    return bytes([COMM_FW_VERSION, v.major & 0xFF, v.minor & 0xFF]) + name + b"\0" + v.uuid[:12].ljust(12, b"\0") \
        + bytes([0, 0, 0, 0])
