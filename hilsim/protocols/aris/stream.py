"""The ARIS availability beacon and the UDP frame stream (``FramePart`` datagrams), sans-I/O.

:func:`encode_availability` / :func:`decode_availability` for the 1 Hz beacon;
:func:`split_frame` (sonar side) and :class:`FrameAssembler` (client side) for frames.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Union

from google.protobuf.message import DecodeError

from hilsim.protocols import codec
from hilsim.protocols.codec import NEED_DATA, NeedData
from hilsim.protocols.aris.commands import BadCommand
from hilsim.protocols.aris.constants import HEADER_SIZE, MAX_DATAGRAM, MAX_FRAME_DATA, SYSTEM_1800
from hilsim.protocols.aris_pb import aris_availability_pb2 as pb_avail
from hilsim.protocols.aris_pb import aris_frame_stream_pb2 as pb_frame


@dataclass(frozen=True)
class Availability:
    """The beacon's fields. system_variants: the vendor's ``SystemVariants.enabled`` strings
    ("DF" Defender, "VG" Voyager; none for a plain ARIS)."""

    serial_number: int
    system_type: int = SYSTEM_1800
    software_version: tuple[int, int, int] = (2, 8, 0)
    connection_state: int = 0  # 0 AVAILABLE, 1 BUSY
    system_variants: tuple[str, ...] = ()


def encode_availability(a: Availability) -> bytes:
    """The beacon datagram; every field is set, so zeros are written too, and systemVariants
    (field 13) is its message, empty for a plain ARIS (``6a 00``)."""
    m = pb_avail.Availability()
    m.serialNumber = a.serial_number
    m.systemType = a.system_type  # type: ignore[assignment]
    m.softwareVersion.major, m.softwareVersion.minor, m.softwareVersion.buildnumber = a.software_version
    m.connectionState = a.connection_state  # type: ignore[assignment]
    m.systemVariants.SetInParent()
    m.systemVariants.enabled.extend(a.system_variants)
    return m.SerializeToString()


def decode_availability(data: bytes) -> Availability | BadCommand:
    m = pb_avail.Availability()
    try:
        m.ParseFromString(bytes(data))
    except (DecodeError, RuntimeWarning, ValueError) as exc:
        return BadCommand(f"not an Availability message: {exc}", len(data))
    if not m.HasField("serialNumber"):
        return BadCommand("Availability without serialNumber", len(data))
    v = m.softwareVersion
    return Availability(m.serialNumber, int(m.systemType), (v.major, v.minor, v.buildnumber),
                        int(m.connectionState), tuple(m.systemVariants.enabled))


# ------------------------------------------------------------- frame stream


def _frame_part(frame_index: int, total: int, offset: int, data: bytes, header: bytes | None) -> pb_frame.FramePart:
    m = pb_frame.FramePart()
    m.frame_index = frame_index
    m.total_data_size = total
    if header is not None:
        m.header = header
    m.data = data
    m.data_offset = offset
    m.ack_port = 0
    return m


def split_frame(frame_index: int, header: bytes, samples: bytes, max_datagram: int = MAX_DATAGRAM) -> list[bytes]:
    """One frame -> FramePart datagrams of at most ``max_datagram`` bytes.

    header: the 1024-byte frame header; its trailing zero bytes are not sent
    ("the bytes in use"; receivers pad to 1024). The first part carries it.
    Every part writes frame_index, total_data_size, data, data_offset and
    ack_port, even when zero.
    """
    if len(header) > HEADER_SIZE:
        raise ValueError("frame header is longer than 1024 bytes")
    used = bytes(header).rstrip(b"\0") or b"\0"
    total = len(samples)
    parts: list[bytes] = []
    offset = 0
    first = True
    while first or offset < total:
        head = used if first else None
        overhead = _frame_part(frame_index, total, offset, b"", head).ByteSize()
        room = max_datagram - overhead - 3  # data: tag + 2-byte length
        if room <= 0:
            raise ValueError("max_datagram too small for a frame part")
        chunk = samples[offset : offset + room]
        msg = _frame_part(frame_index, total, offset, bytes(chunk), head).SerializeToString()
        assert len(msg) <= max_datagram
        parts.append(msg)
        offset += len(chunk)
        first = False
    return parts


@dataclass(frozen=True)
class AssembledFrame:
    frame_index: int
    header: bytes  # 1024 bytes, zero-padded
    data: bytes  # total_data_size bytes, wire order


@dataclass(frozen=True)
class DroppedFrame:
    frame_index: int
    received: int
    total: int


@dataclass(frozen=True)
class BadDatagram(codec.BadFrame):
    """A datagram that is not a valid FramePart (``data`` is empty: the datagram is not kept)."""


AssemblerEvent = Union[AssembledFrame, DroppedFrame, BadDatagram]


class FrameAssembler:
    """Client side: FramePart datagrams -> whole frames (sans-I/O).

    Keeps one frame in progress; a part of a newer frame drops an incomplete
    older one (:class:`DroppedFrame`); parts of older frames are ignored.
    Memory is bounded by ``2 x max_data`` bytes: the frame and a map of the
    bytes received (a larger total_data_size is a :class:`BadDatagram`). A
    frame is complete when every byte was received, however the parts overlap.
    """

    def __init__(self, max_data: int = MAX_FRAME_DATA * 2) -> None:
        self.max_data = max_data
        self._index = -1
        self._total = 0
        self._data = bytearray()
        self._header: bytes | None = None
        self._got = bytearray()  # 1 per byte of the frame received
        self._received = 0
        self._done = -1
        self._events: deque[AssemblerEvent] = deque()

    @property
    def buffered_bytes(self) -> int:
        """The frame in progress and its map of received bytes."""
        return len(self._data) + len(self._got)

    def receive_data(self, datagram: bytes) -> None:
        """One whole datagram (UDP keeps their bounds: each call is one FramePart); drain with
        :meth:`next_event`."""
        self._events.extend(self.receive_datagram(datagram))

    def next_event(self) -> AssemblerEvent | NeedData:
        return self._events.popleft() if self._events else NEED_DATA

    def receive_datagram(self, datagram: bytes) -> list[AssemblerEvent]:
        """One datagram -> the events it gives at once (:meth:`receive_data` + :meth:`next_event`, in one call)."""
        m = pb_frame.FramePart()
        try:
            m.ParseFromString(bytes(datagram))
        except (DecodeError, RuntimeWarning, ValueError) as exc:
            return [BadDatagram(f"not a FramePart: {exc}")]
        for f in ("frame_index", "total_data_size", "data", "data_offset"):
            if not m.HasField(f):
                return [BadDatagram(f"FramePart without {f}")]
        idx, total, off = m.frame_index, m.total_data_size, m.data_offset
        if not 0 <= total <= self.max_data or off < 0 or off + len(m.data) > total:
            return [BadDatagram(f"FramePart out of bounds: total {total}, offset {off}, {len(m.data)} bytes")]
        out: list[AssemblerEvent] = []
        if idx <= self._done or (idx < self._index):
            return out
        if idx != self._index:
            if self._index >= 0 and self._index > self._done:
                out.append(DroppedFrame(self._index, self._received, self._total))
            self._index, self._total = idx, total
            self._data = bytearray(total)
            self._header, self._got, self._received = None, bytearray(total), 0
        if total != self._total:
            return out + [BadDatagram("total_data_size changed within a frame")]
        if m.HasField("header"):
            self._header = bytes(m.header[:HEADER_SIZE]).ljust(HEADER_SIZE, b"\0")
        n = len(m.data)
        self._received += n - self._got.count(1, off, off + n)
        self._got[off : off + n] = b"\x01" * n
        self._data[off : off + n] = m.data
        if self._received >= total and self._header is not None:
            out.append(AssembledFrame(idx, self._header, bytes(self._data)))
            self._done = idx
            self._data, self._got = bytearray(), bytearray()
        return out
