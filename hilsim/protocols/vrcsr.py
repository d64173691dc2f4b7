"""VideoRay VRCSR over RS-485 (videoray/Thruster): thruster group commands, sans-I/O.

Spec: ``protocols/vrcsr.md``. Little-endian. A packet::

    sync(2) node_id(1) flags(1) csr_address(1) length(1) | header CRC32(4) | payload(length) | payload CRC32(4)

Requests start ``F5 5F``, responses ``F0 0F``; both CRC32s are zlib's CRC-32,
stored little-endian. The propulsion command is a write to the custom-command
register 0xF0, usually to the thruster group 0x81::

    payload = 0xAA, reply_node_id(1), float32 power[motor_id] ...   (power in [-1, 1])

``flags`` choose the reply of the thruster named by ``reply_node_id``: 0x02
the standard response (device type u8, rpm f32, bus voltage f32 [V], bus
current f32 [A], temperature f32 [degC], fault u8), 0x01 an ACK (device type
only), 0x00 none.

:class:`PacketDecoder` turns bytes into packets, skipping and counting
garbage, truncated packets and bad CRCs, and resynchronises on the next
valid packet. The length field is one byte, so a packet is at most 269
bytes and nothing larger is ever buffered beyond the last chunk fed. Those
rules live in :mod:`hilsim.protocols.framing`, shared with VESC UART;
decoding costs amortized linear time however the bytes are cut.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from typing import ClassVar, Final, Sequence

from hilsim.protocols.codec import NEED_DATA, NeedData
from hilsim.protocols.framing import NEED, OK, ResyncFramer, Verdict

SYNC_REQUEST: Final = b"\xf5\x5f"
SYNC_RESPONSE: Final = b"\xf0\x0f"
HEADER_SIZE: Final = 6
CRC_SIZE: Final = 4
ADDR_CUSTOM_COMMAND: Final = 0xF0
PROPULSION_COMMAND: Final = 0xAA
THRUSTER_GROUP_ID: Final = 0x81
FLAG_NONE: Final = 0x00
FLAG_ACK: Final = 0x01
FLAG_STANDARD: Final = 0x02
STANDARD_RESPONSE_SIZE: Final = 1 + 4 * 4 + 1


def crc32(data: bytes | bytearray) -> int:
    return zlib.crc32(data) & 0xFFFFFFFF


@dataclass(frozen=True)
class Packet:
    """One VRCSR packet (request or response)."""

    node_id: int
    flags: int
    address: int
    payload: bytes
    response: bool = False

    def encode(self) -> bytes:
        if not (0 <= self.node_id <= 255 and 0 <= self.flags <= 255 and 0 <= self.address <= 255):
            raise ValueError(f"bad VRCSR header fields: {self!r}")
        if len(self.payload) > 255:
            raise ValueError(f"VRCSR payload is {len(self.payload)} bytes; at most 255")
        header = (SYNC_RESPONSE if self.response else SYNC_REQUEST) + bytes(
            [self.node_id, self.flags, self.address, len(self.payload)])
        out = header + struct.pack("<I", crc32(header))
        if self.payload:
            out += self.payload + struct.pack("<I", crc32(self.payload))
        return out




@dataclass
class DecoderStats:
    packets: int = 0
    header_crc_errors: int = 0
    payload_crc_errors: int = 0
    bytes_skipped: int = 0


@dataclass
class PacketDecoder(ResyncFramer[Packet]):
    """Bytes -> :class:`Packet` events (``responses``: decode ``F0 0F`` packets instead).
    Never raises on any input.

    The resynchronisation rules and their linear cost are :class:`~hilsim.protocols.framing.ResyncFramer`'s;
    this class gives VRCSR's framing: the sync bytes, the two CRCs, what is counted.
    """

    marker_size: ClassVar[int] = len(SYNC_REQUEST)

    responses: bool = False
    stats: DecoderStats = field(default_factory=DecoderStats)

    def next_event(self) -> Packet | NeedData:
        pkt = self._next_frame()
        return NEED_DATA if pkt is None else pkt

    def _find_start(self, buf: bytearray, i: int) -> int:
        return buf.find(SYNC_RESPONSE if self.responses else SYNC_REQUEST, i)

    def _partial_start(self, buf: bytearray, i: int) -> int:
        return 1 if buf[-1] == (SYNC_RESPONSE if self.responses else SYNC_REQUEST)[0] else 0

    def _judge(self, buf: bytearray, i: int) -> Verdict:
        have = len(buf) - i
        if have < HEADER_SIZE + CRC_SIZE:
            return NEED, HEADER_SIZE + CRC_SIZE
        if struct.unpack_from("<I", buf, i + HEADER_SIZE)[0] != crc32(buf[i:i + HEADER_SIZE]):
            return "header", 0
        n = buf[i + 5]
        total = HEADER_SIZE + CRC_SIZE + (n + CRC_SIZE if n else 0)
        if have < total:
            return NEED, total
        if n:
            p0 = i + HEADER_SIZE + CRC_SIZE
            if struct.unpack_from("<I", buf, p0 + n)[0] != crc32(buf[p0:p0 + n]):
                return "payload", 0
        return OK, total

    def _event(self, buf: bytearray, i: int, total: int) -> Packet:
        p0 = i + HEADER_SIZE + CRC_SIZE
        self.stats.packets += 1
        return Packet(buf[i + 2], buf[i + 3], buf[i + 4], bytes(buf[p0:p0 + buf[i + 5]]), self.responses)

    def _rejected(self, kind: str) -> None:
        if kind == "header":
            self.stats.header_crc_errors += 1
        else:
            self.stats.payload_crc_errors += 1

    def _skipped(self, n: int) -> None:
        self.stats.bytes_skipped += n


# ---------------------------------------------------------------- messages


@dataclass(frozen=True)
class PropulsionCommand:
    """Power set-points for a group: ``powers[motor_id]`` in [-1, 1] (negative = reverse)."""

    reply_node_id: int
    powers: tuple[float, ...]

    def payload(self) -> bytes:
        return bytes([PROPULSION_COMMAND, self.reply_node_id & 0xFF]) + b"".join(
            struct.pack("<f", max(-1.0, min(1.0, p))) for p in self.powers)

    @staticmethod
    def decode(payload: bytes) -> "PropulsionCommand | None":
        """None unless the payload is 0xAA, a node id, then whole float32s (at most 63)."""
        if len(payload) < 2 or payload[0] != PROPULSION_COMMAND or (len(payload) - 2) % 4:
            return None
        n = (len(payload) - 2) // 4
        return PropulsionCommand(payload[1], struct.unpack_from(f"<{n}f", payload, 2))


def propulsion_request(powers: Sequence[float], reply_node_id: int, flags: int = FLAG_STANDARD,
                       node_id: int = THRUSTER_GROUP_ID) -> bytes:
    """Host side: the bytes of a propulsion command to ``node_id`` (default the thruster group)."""
    cmd = PropulsionCommand(reply_node_id, tuple(float(p) for p in powers))
    return Packet(node_id, flags, ADDR_CUSTOM_COMMAND, cmd.payload()).encode()


@dataclass(frozen=True)
class StandardResponse:
    """The thruster's standard response payload (rpm [rev/min], bus_v [V], bus_i [A], temp [degC])."""

    device_type: int
    rpm: float
    bus_v: float
    bus_i: float
    temp: float
    fault: int

    def payload(self) -> bytes:
        return struct.pack("<BffffB", self.device_type & 0xFF, self.rpm, self.bus_v, self.bus_i, self.temp,
                           self.fault & 0xFF)

    @staticmethod
    def decode(payload: bytes) -> "StandardResponse | None":
        if len(payload) != STANDARD_RESPONSE_SIZE:
            return None
        return StandardResponse(*struct.unpack("<BffffB", payload))


def response(node_id: int, flags: int, address: int, payload: bytes) -> bytes:
    """Device side: a response packet from ``node_id``."""
    return Packet(node_id, flags, address, payload, response=True).encode()
