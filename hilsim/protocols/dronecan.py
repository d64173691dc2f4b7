"""DroneCAN / UAVCAN v0 on classic CAN: the ESC messages and the node heartbeat, sans-I/O.

Spec: ``protocols/dronecan-esc.md``. Our own implementation of the v0 framing:

* identifier (29 bits, message frame): priority [28:24] | data type id [23:8] |
  service flag [7] = 0 | source node id [6:0];
* every frame ends in a tail byte: start [7], end [6], toggle [5] (0 on the
  first frame, alternating), transfer id [4:0] (per data type and source, +1 mod 32);
* a payload over 7 bytes is a multi-frame transfer whose first frame begins
  with the transfer CRC, CRC-16-CCITT-FALSE (poly 0x1021, init 0xFFFF) over
  the data type signature (8 bytes, little-endian) then the payload, sent
  little-endian;
* payload bits are packed MSB-first; a scalar goes in as its little-endian
  bytes, the last partial byte contributing its low bits; the last dynamic
  array of a message has no length prefix (tail array optimisation).

Types here: ``uavcan.equipment.esc.RawCommand`` (1030, int14[<=20] tail array,
-8192..8191 = -100..100 % power), ``uavcan.equipment.esc.Status`` (1034, 14 bytes:
u32 error_count, f16 voltage [V], f16 current [A], f16 temperature [K], i18 rpm,
u7 power_rating_pct, u5 esc_index) and ``uavcan.protocol.NodeStatus`` (341, 7 bytes).

:class:`TransferReceiver` reassembles transfers from frames (bounded sessions
and payloads, CRC checked) and never raises on bus input.
"""

from __future__ import annotations

import binascii
import math
import struct
from collections import deque
from dataclasses import dataclass, field
from typing import Final, Sequence, Union

from hilsim.protocols.can import CanFrame
from hilsim.protocols.codec import NEED_DATA, NeedData

RAW_COMMAND_DTID: Final = 1030
RAW_COMMAND_SIGNATURE: Final = 0x217F5C87D7EC951D
ESC_STATUS_DTID: Final = 1034
ESC_STATUS_SIGNATURE: Final = 0xA9AF28AEA2FBB254
NODE_STATUS_DTID: Final = 341
NODE_STATUS_SIGNATURE: Final = 0x0F0868D0C1A7C6F1
RAW_COMMAND_MAX: Final = 8191
RAW_COMMAND_LEN_MAX: Final = 20

HEALTH_OK: Final = 0
MODE_OPERATIONAL: Final = 0
MODE_INITIALIZATION: Final = 1

SIGNATURES: Final[dict[int, int]] = {
    RAW_COMMAND_DTID: RAW_COMMAND_SIGNATURE,
    ESC_STATUS_DTID: ESC_STATUS_SIGNATURE,
    NODE_STATUS_DTID: NODE_STATUS_SIGNATURE,
}


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16-CCITT-FALSE (poly 0x1021, init 0xFFFF, not reflected), continued from ``crc``."""
    return binascii.crc_hqx(data, crc)


def transfer_crc(signature: int, payload: bytes) -> int:
    """The multi-frame transfer CRC: over the 64-bit signature (little-endian) then the payload."""
    return crc16(payload, crc16(signature.to_bytes(8, "little")))


# ---------------------------------------------------------------- identifiers


def message_id(priority: int, dtid: int, source_node: int) -> int:
    """29-bit identifier of a message frame."""
    if not (0 <= priority <= 31 and 0 <= dtid <= 0xFFFF and 1 <= source_node <= 127):
        raise ValueError(f"bad DroneCAN message id parts: priority {priority}, dtid {dtid}, node {source_node}")
    return (priority << 24) | (dtid << 8) | source_node


@dataclass(frozen=True)
class FrameId:
    priority: int
    dtid: int             # for anonymous messages only its 2 low bits are known
    service: bool
    source_node: int      # 0: anonymous
    dest_node: int = 0    # services only
    request: bool = False


def parse_id(arbitration_id: int) -> FrameId:
    """Split an identifier into its fields (any 29-bit value is valid)."""
    prio = (arbitration_id >> 24) & 0x1F
    source = arbitration_id & 0x7F
    if arbitration_id & 0x80:
        return FrameId(prio, (arbitration_id >> 16) & 0xFF, True, source, (arbitration_id >> 8) & 0x7F,
                       bool(arbitration_id & 0x8000))
    if source == 0:
        return FrameId(prio, (arbitration_id >> 8) & 0x3, False, 0)
    return FrameId(prio, (arbitration_id >> 8) & 0xFFFF, False, source)


# ---------------------------------------------------------------- bit packing


class BitWriter:
    """v0 bit stream writer (MSB-first, scalars as little-endian bytes)."""

    def __init__(self) -> None:
        self._acc = 0
        self._bits = 0

    def write(self, value: int, nbits: int) -> None:
        value &= (1 << nbits) - 1
        while nbits > 0:
            take = min(8, nbits)
            self._acc = (self._acc << take) | (value & ((1 << take) - 1))
            self._bits += take
            value >>= 8
            nbits -= take

    def to_bytes(self) -> bytes:
        pad = (-self._bits) % 8
        n = (self._bits + pad) // 8
        return (self._acc << pad).to_bytes(n, "big") if n else b""


class BitReader:
    """v0 bit stream reader; reading past the end raises EOFError (callers catch it)."""

    def __init__(self, data: bytes) -> None:
        self._acc = int.from_bytes(data, "big")
        self.total = 8 * len(data)
        self.pos = 0

    @property
    def remaining(self) -> int:
        return self.total - self.pos

    def _take(self, n: int) -> int:
        if n > self.remaining:
            raise EOFError
        shift = self.total - self.pos - n
        self.pos += n
        return (self._acc >> shift) & ((1 << n) - 1)

    def read_unsigned(self, nbits: int) -> int:
        value, k = 0, 0
        while nbits > 0:
            take = min(8, nbits)
            value |= self._take(take) << (8 * k)
            k += 1
            nbits -= take
        return value

    def read_signed(self, nbits: int) -> int:
        v = self.read_unsigned(nbits)
        return v - (1 << nbits) if v & (1 << (nbits - 1)) else v


def _f16_bits(value: float) -> int:
    v = float(value)
    if math.isfinite(v):
        v = max(-65504.0, min(65504.0, v))
    return int.from_bytes(struct.pack("<e", v), "little")


def _f16_value(bits: int) -> float:
    return float(struct.unpack("<e", bits.to_bytes(2, "little"))[0])


# ---------------------------------------------------------------- messages


@dataclass(frozen=True)
class RawCommand:
    """uavcan.equipment.esc.RawCommand: one int14 per ESC index, -8192..8191."""

    cmd: tuple[int, ...]

    def encode(self) -> bytes:
        if len(self.cmd) > RAW_COMMAND_LEN_MAX:
            raise ValueError(f"RawCommand carries at most {RAW_COMMAND_LEN_MAX} values, got {len(self.cmd)}")
        w = BitWriter()
        for c in self.cmd:
            if not -8192 <= c <= 8191:
                raise ValueError(f"RawCommand value {c} outside -8192..8191")
            w.write(c, 14)
        return w.to_bytes()

    @staticmethod
    def decode(payload: bytes) -> "RawCommand | None":
        """None if the payload cannot be a RawCommand (more than 20 values)."""
        n = (8 * len(payload)) // 14
        if n > RAW_COMMAND_LEN_MAX:
            return None
        r = BitReader(payload)
        return RawCommand(tuple(r.read_signed(14) for _ in range(n)))

    def normalized(self, index: int) -> float | None:
        """Command for ESC ``index`` as a fraction in [-1, 1] (None if the array is shorter)."""
        if index >= len(self.cmd):
            return None
        return max(-1.0, min(1.0, self.cmd[index] / RAW_COMMAND_MAX))


@dataclass(frozen=True)
class EscStatus:
    """uavcan.equipment.esc.Status (voltage [V], current [A], temperature [K], rpm [rev/min])."""

    error_count: int
    voltage: float
    current: float
    temperature: float
    rpm: int
    power_rating_pct: int
    esc_index: int

    def encode(self) -> bytes:
        """Values beyond a field's range saturate (f16 at +-65504)."""
        w = BitWriter()
        w.write(max(0, min(0xFFFFFFFF, int(self.error_count))), 32)
        w.write(_f16_bits(self.voltage), 16)
        w.write(_f16_bits(self.current), 16)
        w.write(_f16_bits(self.temperature), 16)
        w.write(max(-(1 << 17), min((1 << 17) - 1, int(self.rpm))), 18)
        w.write(max(0, min(127, int(self.power_rating_pct))), 7)
        if not 0 <= self.esc_index <= 31:
            raise ValueError(f"esc_index {self.esc_index} outside 0..31")
        w.write(self.esc_index, 5)
        return w.to_bytes()

    @staticmethod
    def decode(payload: bytes) -> "EscStatus | None":
        r = BitReader(payload)
        try:
            return EscStatus(r.read_unsigned(32), _f16_value(r.read_unsigned(16)), _f16_value(r.read_unsigned(16)),
                             _f16_value(r.read_unsigned(16)), r.read_signed(18), r.read_unsigned(7),
                             r.read_unsigned(5))
        except EOFError:
            return None


@dataclass(frozen=True)
class NodeStatus:
    """uavcan.protocol.NodeStatus, the 1 Hz heartbeat every node sends."""

    uptime_sec: int
    health: int = HEALTH_OK
    mode: int = MODE_OPERATIONAL
    sub_mode: int = 0
    vendor_specific_status_code: int = 0

    def encode(self) -> bytes:
        w = BitWriter()
        w.write(max(0, min(0xFFFFFFFF, int(self.uptime_sec))), 32)
        w.write(self.health, 2)
        w.write(self.mode, 3)
        w.write(self.sub_mode, 3)
        w.write(self.vendor_specific_status_code, 16)
        return w.to_bytes()

    @staticmethod
    def decode(payload: bytes) -> "NodeStatus | None":
        r = BitReader(payload)
        try:
            return NodeStatus(r.read_unsigned(32), r.read_unsigned(2), r.read_unsigned(3), r.read_unsigned(3),
                              r.read_unsigned(16))
        except EOFError:
            return None


Message = Union[RawCommand, EscStatus, NodeStatus]
_DTIDS: Final[dict[type, int]] = {RawCommand: RAW_COMMAND_DTID, EscStatus: ESC_STATUS_DTID,
                                  NodeStatus: NODE_STATUS_DTID}


def decode_message(dtid: int, payload: bytes) -> Message | None:
    """Payload of a known data type -> message (None if unknown or malformed)."""
    if dtid == RAW_COMMAND_DTID:
        return RawCommand.decode(payload)
    if dtid == ESC_STATUS_DTID:
        return EscStatus.decode(payload)
    if dtid == NODE_STATUS_DTID:
        return NodeStatus.decode(payload)
    return None


# ---------------------------------------------------------------- transfers


def encode_transfer(payload: bytes, dtid: int, signature: int, source_node: int, transfer_id: int,
                    priority: int = 16) -> list[CanFrame]:
    """A message transfer -> its frames (single frame up to 7 payload bytes)."""
    ident = message_id(priority, dtid, source_node)
    tid = transfer_id & 0x1F
    if len(payload) <= 7:
        return [CanFrame(ident, bytes(payload) + bytes([0xC0 | tid]))]
    body = transfer_crc(signature, payload).to_bytes(2, "little") + payload
    frames, toggle = [], 0
    chunks = [body[i:i + 7] for i in range(0, len(body), 7)]
    for k, chunk in enumerate(chunks):
        tail = (0x80 if k == 0 else 0) | (0x40 if k == len(chunks) - 1 else 0) | (toggle << 5) | tid
        frames.append(CanFrame(ident, chunk + bytes([tail])))
        toggle ^= 1
    return frames


def encode_message(message: Message, source_node: int, transfer_id: int, priority: int = 16) -> list[CanFrame]:
    """A message -> the frames of one transfer."""
    dtid = _DTIDS[type(message)]
    return encode_transfer(message.encode(), dtid, SIGNATURES[dtid], source_node, transfer_id, priority)


class TransferIds:
    """Next transfer id per (data type id, source node): 0, 1, ..., 31, 0, ..."""

    def __init__(self) -> None:
        self._next: dict[tuple[int, int], int] = {}

    def next(self, dtid: int, source_node: int) -> int:
        key = (dtid, source_node)
        tid = self._next.get(key, 0)
        self._next[key] = (tid + 1) & 0x1F
        return tid


@dataclass(frozen=True)
class Transfer:
    """A complete message transfer."""

    dtid: int
    source_node: int
    priority: int
    transfer_id: int
    payload: bytes
    timestamp: float


@dataclass
class ReceiverStats:
    transfers: int = 0
    frames: int = 0
    ignored: int = 0            # services, anonymous, unknown data types, standard ids
    bad_frames: int = 0         # empty frame, unexpected toggle / transfer id / start
    crc_errors: int = 0
    too_long: int = 0           # payload over max_payload: dropped
    timeouts: int = 0           # sessions abandoned midway
    evicted: int = 0            # sessions dropped because too many were open


@dataclass
class _Session:
    transfer_id: int
    toggle: int
    started: float
    last: float
    data: bytearray


@dataclass
class TransferReceiver:
    """Frames -> complete message transfers of the data types in ``signatures``.

    ``receive_frame(frame, now)`` then ``next_event()`` until NEED_DATA (or
    ``receive(frame, now)``: the :class:`Transfer` ``frame`` completes, else None). At most ``max_sessions`` transfers are assembled at once
    (the oldest is dropped), each at most ``max_payload`` bytes; a session idle
    for ``timeout`` [s] is abandoned. Never raises on bus input.
    """

    signatures: dict[int, int] = field(default_factory=lambda: dict(SIGNATURES))
    max_payload: int = 64
    max_sessions: int = 32
    timeout: float = 2.0
    stats: ReceiverStats = field(default_factory=ReceiverStats)
    _sessions: dict[tuple[int, int], _Session] = field(default_factory=dict)
    _done: deque[Transfer] = field(default_factory=deque)

    def receive_frame(self, frame: CanFrame, now: float) -> None:
        """One frame from the bus at ``now`` [s] (the codec contract on frames: whole CAN frames
        instead of bytes); drain the transfers it completes with :meth:`next_event`."""
        t = self.receive(frame, now)
        if t is not None:
            self._done.append(t)

    def next_event(self) -> Transfer | NeedData:
        return self._done.popleft() if self._done else NEED_DATA

    @property
    def buffered_bytes(self) -> int:
        """Payload bytes of the transfers being assembled."""
        return sum(len(s.data) for s in self._sessions.values())

    def receive(self, frame: CanFrame, now: float) -> Transfer | None:
        """One frame -> the transfer it completes, or None (:meth:`receive_frame` + :meth:`next_event` in one call)."""
        self.stats.frames += 1
        if not frame.is_extended or frame.is_remote:
            self.stats.ignored += 1
            return None
        fid = parse_id(frame.arbitration_id)
        if fid.service or fid.source_node == 0 or fid.dtid not in self.signatures:
            self.stats.ignored += 1
            return None
        if not frame.data:
            self.stats.bad_frames += 1
            return None
        tail = frame.data[-1]
        start, end, toggle, tid = bool(tail & 0x80), bool(tail & 0x40), (tail >> 5) & 1, tail & 0x1F
        body = frame.data[:-1]
        key = (fid.dtid, fid.source_node)
        if start and end:
            if toggle:
                self.stats.bad_frames += 1
                return None
            self._sessions.pop(key, None)
            self.stats.transfers += 1
            return Transfer(fid.dtid, fid.source_node, fid.priority, tid, bytes(body), now)
        if start:
            if toggle or len(body) < 2:
                self.stats.bad_frames += 1
                self._sessions.pop(key, None)
                return None
            self._expire(now)
            if key not in self._sessions and len(self._sessions) >= self.max_sessions:
                oldest = min(self._sessions, key=lambda k: self._sessions[k].last)
                del self._sessions[oldest]
                self.stats.evicted += 1
            self._sessions[key] = _Session(tid, 1, now, now, bytearray(body))
            return None
        s = self._sessions.get(key)
        if s is None:
            self.stats.bad_frames += 1  # middle or end of a transfer whose start we missed
            return None
        if now - s.last > self.timeout:
            del self._sessions[key]
            self.stats.timeouts += 1
            self.stats.bad_frames += 1
            return None
        if tid != s.transfer_id or toggle != s.toggle:
            del self._sessions[key]
            self.stats.bad_frames += 1
            return None
        if len(s.data) + len(body) > self.max_payload + 2:
            del self._sessions[key]
            self.stats.too_long += 1
            return None
        s.data += body
        s.toggle ^= 1
        s.last = now
        if not end:
            return None
        del self._sessions[key]
        crc, payload = int.from_bytes(s.data[:2], "little"), bytes(s.data[2:])
        if transfer_crc(self.signatures[fid.dtid], payload) != crc:
            self.stats.crc_errors += 1
            return None
        self.stats.transfers += 1
        return Transfer(fid.dtid, fid.source_node, fid.priority, tid, payload, s.started)

    def _expire(self, now: float) -> None:
        stale = [k for k, s in self._sessions.items() if now - s.last > self.timeout]
        for k in stale:
            del self._sessions[k]
            self.stats.timeouts += 1

    @property
    def open_sessions(self) -> int:
        return len(self._sessions)


def raw_command_values(fractions: Sequence[float]) -> RawCommand:
    """Host side helper: fractions in [-1, 1] -> a RawCommand (x 8191, clipped)."""
    return RawCommand(tuple(max(-8192, min(8191, round(f * RAW_COMMAND_MAX))) for f in fractions))
