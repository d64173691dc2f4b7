"""Modbus TCP (MBAP) and Modbus RTU request framing, device side (sans-I/O).

Bytes from a master in, :class:`Request` events out, as the codec contract
(:mod:`hilsim.protocols.codec`) has it: ``receive_data(bytes)`` then
``next_event()`` until :data:`NEED_DATA`. The PDUs, frames and CRC are
:mod:`hilsim.protocols.modbus_pdu`'s; the answers are built in
:mod:`hilsim.protocols.modbus_device` (a device's registers); the transports are
:mod:`hilsim.links.modbus`.

* :class:`TcpRequestDecoder`: MBAP headers (7 bytes) + PDU. A header that is
  not Modbus TCP (protocol id != 0, length outside 2..:data:`MAX_TCP_LENGTH`)
  gives :class:`NotModbusTcp` once and the decoder is closed (real devices
  close the connection; MBAP has no marker to resynchronise on).
* :class:`RtuRequestDecoder`: requests delimited by the length their function
  code defines (:func:`rtu_request_length`), so frames back to back are each
  decoded, in order. A frame with a bad CRC gives :class:`CrcError` (once per
  loss of sync); then, until a frame checks out or the line goes idle
  (:meth:`RtuRequestDecoder.silence`), the decoder hunts byte by byte for the
  next frame whose length rule and CRC agree. What the rules cannot delimit is
  one frame when the line goes idle (3.5 characters); a frame too short at
  silence, or more than :data:`MAX_RTU_ADU` bytes that no rule delimits, gives
  :class:`Malformed`. At most :data:`MAX_RTU_ADU` bytes are kept beyond the
  last chunk fed.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Final, Optional, Protocol, Union

from hilsim.protocols import codec
from hilsim.protocols.codec import NEED_DATA, NeedData
from hilsim.protocols.modbus_pdu import MBAP, RTU_MIN_SIZE, crc_ok

MAX_RTU_ADU: Final = 256
MAX_TCP_LENGTH: Final = 254  # MBAP length field: unit id + PDU (max 253 bytes)

DIALECT_MAX_BURST: Final = 16  # a dialect frame failing its check at its length: the gap decides up to this
RTU_NEED_MORE = 0      # rtu_request_length: more bytes are needed to tell
RTU_UNDELIMITED = -1   # rtu_request_length: the length rules cannot tell (ends at silence)
# Request ADU lengths (address + PDU + CRC) by function code, from the Modbus application
# protocol spec V1.1b3 (section 6) and its serial line spec.
_RTU_FIXED = {0x01: 8, 0x02: 8, 0x03: 8, 0x04: 8, 0x05: 8, 0x06: 8,  # address, count/value
              0x07: 4, 0x0B: 4, 0x0C: 4, 0x11: 4,                    # no data
              0x16: 10,                                              # mask write: address, AND, OR
              0x18: 6}                                               # read FIFO: address
# function code -> index of the byte count in the ADU; length = count + index + 3 (count byte, CRC)
_RTU_COUNTED = {0x0F: 6, 0x10: 6,  # address, quantity, byte count
                0x14: 2, 0x15: 2,  # file records: byte count
                0x17: 10}          # read address, quantity, write address, quantity, byte count
# 08 diagnostics: sub-functions with 2 bytes of data; 00 (return query data) echoes any
# data, and the reserved ones are undefined. 15 (Modbus Plus statistics) is in PI-MBUS-300.
_RTU_DIAGNOSTIC_SUBS = frozenset([0x01, 0x02, 0x03, 0x04, *range(0x0A, 0x13), 0x14, 0x15])


def rtu_request_length(buf: bytes | bytearray, pos: int = 0) -> int:
    """Length of the RTU request starting at ``buf[pos]`` by its function code:
    :data:`RTU_NEED_MORE` if more bytes must arrive to tell, :data:`RTU_UNDELIMITED`
    if the rules cannot (an unknown or user function, 08/00 with other than 2 bytes
    of data, 2B with a MEI type other than 0E, a length over :data:`MAX_RTU_ADU`).

    08/00 is taken as 8 bytes only when those 8 bytes carry a good CRC (the spec
    allows any data; masters send 2 bytes), the reserved 08 sub-functions are not
    delimited, and a function code with the top bit set (an exception response, not
    a request) is not taken as 5 bytes.
    """
    avail = len(buf) - pos
    if avail < 2:
        return RTU_NEED_MORE
    fc = buf[pos + 1]
    if fc in _RTU_FIXED:
        return _RTU_FIXED[fc]
    if fc in _RTU_COUNTED:
        at = _RTU_COUNTED[fc]
        if avail <= at:
            return RTU_NEED_MORE
        n = buf[pos + at] + at + 3
        return n if n <= MAX_RTU_ADU else RTU_UNDELIMITED
    if fc == 0x08:
        if avail < 4:
            return RTU_NEED_MORE
        sub = (buf[pos + 2] << 8) | buf[pos + 3]
        if sub in _RTU_DIAGNOSTIC_SUBS:
            return 8
        if sub != 0:
            return RTU_UNDELIMITED
        if avail < 8:
            return RTU_NEED_MORE
        return 8 if crc_ok(buf, pos, pos + 8) else RTU_UNDELIMITED
    if fc == 0x2B:
        if avail < 3:
            return RTU_NEED_MORE
        return 7 if buf[pos + 2] == 0x0E else RTU_UNDELIMITED  # read device identification
    return RTU_UNDELIMITED


# ------------------------------------------------------------------ events


@dataclass(frozen=True)
class Request:
    """One request addressed to ``unit`` (RTU: 0 is broadcast): ``pdu`` is the function code and
    its data; ``transaction_id`` is MBAP's (0 on RTU)."""

    unit: int
    pdu: bytes
    transaction_id: int = 0


@dataclass(frozen=True)
class NotModbusTcp(codec.BadFrame):
    """An MBAP header that is not Modbus TCP; the decoder is closed after it (``data``: the header)."""


@dataclass(frozen=True)
class CrcError(codec.BadFrame):
    """An RTU frame (by its length rule, or the bytes before a silence) whose CRC is wrong."""


@dataclass(frozen=True)
class Malformed(codec.BadFrame):
    """RTU bytes that cannot be a frame: too short at silence, or no rule delimits them within
    :data:`MAX_RTU_ADU` bytes."""


@dataclass(frozen=True)
class ForeignFrame:
    """A frame of the other protocol sharing the RTU line (:class:`RtuDialect`), whole (CRC included)."""

    frame: bytes


class RtuDialect(Protocol):
    """Another protocol on the same serial line, told from Modbus by its function codes, as a
    KELLER Series 30 serves the KELLER bus beside Modbus RTU (:mod:`hilsim.protocols.keller_bus`)."""

    def owns(self, function: int) -> bool:
        """A request with this function code is the dialect's."""

    def request_length(self, buf: bytes | bytearray, pos: int) -> int:
        """As :func:`rtu_request_length`, for the dialect's function codes."""

    def crc_ok(self, buf: bytes | bytearray, start: int, end: int) -> bool:
        """``buf[start:end]`` ends with a good check in the dialect's byte order."""


TcpEvent = Union[Request, NotModbusTcp]
RtuEvent = Union[Request, CrcError, Malformed, ForeignFrame]


# ------------------------------------------------------------------ Modbus TCP


_MBAP_PID_LENGTH: Final = struct.Struct(">HH")  # protocol id, length (after the transaction id)


class TcpRequestDecoder:
    """MBAP byte stream -> :class:`Request` (or one :class:`NotModbusTcp`, then nothing)."""

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.closed = False
        self.close_reason = ""
        self._bad: NotModbusTcp | None = None

    @property
    def buffered_bytes(self) -> int:
        return len(self.buffer)

    def receive_data(self, data: bytes) -> None:
        if not self.closed:
            self.buffer += data

    def frame_length(self) -> int:
        """Length of the complete ADU at the head of the buffer, 0 if incomplete (or closed). A
        header that is not Modbus TCP closes the decoder here; ``next_event`` then reports it."""
        buf = self.buffer
        if self.closed or len(buf) < 7:
            return 0
        pid, length = _MBAP_PID_LENGTH.unpack_from(buf, 2)
        if pid != 0 or not 2 <= length <= MAX_TCP_LENGTH:
            self.closed = True
            self.close_reason = f"not Modbus TCP (protocol id {pid}, length {length})"
            self._bad = NotModbusTcp(self.close_reason, bytes(buf[:7]))
            buf.clear()
            return 0
        return 6 + length if len(buf) >= 6 + length else 0

    def next_event(self) -> TcpEvent | NeedData:
        n = self.frame_length()
        if self._bad is not None:
            ev, self._bad = self._bad, None
            return ev
        if not n:
            return NEED_DATA
        frame = bytes(self.buffer[:n])
        del self.buffer[:n]
        tid, _, _, unit = MBAP.unpack_from(frame)
        return Request(unit, frame[7:], tid)


# ------------------------------------------------------------------ Modbus RTU


class RtuRequestDecoder:
    """RTU byte stream (and the line's silences) -> :class:`Request`, :class:`CrcError`,
    :class:`Malformed`. Call :meth:`silence` when the line has been idle for 3.5 characters
    (even with nothing buffered), then drain. ``dialect``: another protocol on the line; its
    frames (by its length rule and check, or the bytes before a silence when only its check
    holds) come as :class:`ForeignFrame`."""

    def __init__(self, dialect: Optional[RtuDialect] = None) -> None:
        self.dialect = dialect
        self.buffer = bytearray()  # unconsumed bytes once drained
        self._pos = 0
        self._resyncing = False
        self._final = False

    @property
    def buffered_bytes(self) -> int:
        return len(self.buffer) - self._pos

    @property
    def resyncing(self) -> bool:
        """A frame failed its CRC (or ran past MAX_RTU_ADU) since the line was last idle."""
        return self._resyncing

    def receive_data(self, data: bytes) -> None:
        self.buffer += data

    def silence(self) -> None:
        """The line went idle: what is buffered ends there (at a frame boundary it is one frame);
        the next byte starts a frame. Drain the events it gives."""
        self._final = True

    def clear(self) -> None:
        """Drop everything buffered (after an internal error)."""
        self.buffer.clear()
        self._pos = 0

    def next_event(self) -> RtuEvent | NeedData:
        buf, final = self.buffer, self._final
        while True:  # bounded: each pass moves _pos on, or returns
            pos = self._pos
            avail = len(buf) - pos
            if avail <= 0:
                break
            dialect = self.dialect if self.dialect is not None and avail >= 2 and self.dialect.owns(buf[pos + 1]) \
                else None
            n = rtu_request_length(buf, pos) if dialect is None else dialect.request_length(buf, pos)
            if 0 < n <= avail:  # a complete frame by the length rules
                end = pos + n
                if dialect is not None and dialect.crc_ok(buf, pos, end):
                    self._resyncing = False
                    self._pos = end
                    return ForeignFrame(bytes(buf[pos:end]))
                if dialect is None and crc_ok(buf, pos, end):
                    self._resyncing = False
                    self._pos = end
                    return Request(buf[pos], bytes(buf[pos + 1:end - 2]))
                if dialect is not None and not self._resyncing:  # the dialect's device takes the burst
                    if not final and avail <= DIALECT_MAX_BURST:  # as one frame at the gap (a wrong length)
                        break
                    if final and dialect.crc_ok(buf, pos, len(buf)):
                        self._pos = len(buf)
                        return ForeignFrame(bytes(buf[pos:]))
                self._pos = pos + 1  # a garbled frame (or, hunting, not a frame start): look one byte on
                if not self._resyncing:
                    self._resyncing = True
                    return CrcError("bad CRC", bytes(buf[pos:end]))
                continue
            if self._resyncing:  # hunting: only frames the rules delimit can be found
                if final or n == RTU_UNDELIMITED:
                    self._pos = pos + 1
                    continue
                break  # a candidate still arriving
            if not final:
                if n == RTU_UNDELIMITED and avail > MAX_RTU_ADU:  # longer than any frame
                    self._resyncing = True
                    self._pos = pos + 1
                    return Malformed(f"no frame delimited in {avail} bytes", bytes(buf[pos:pos + 16]))
                break  # wait for the rest of the frame, or for silence
            # the line went idle at a frame boundary: the rest is one frame
            self._pos = len(buf)
            if avail < RTU_MIN_SIZE:
                return Malformed(f"a frame of {avail} bytes", bytes(buf[pos:]))
            if crc_ok(buf, pos, len(buf)):
                return Request(buf[pos], bytes(buf[pos + 1:len(buf) - 2]))
            if self.dialect is not None and self.dialect.crc_ok(buf, pos, len(buf)):
                return ForeignFrame(bytes(buf[pos:]))  # the dialect's device answers (a wrong length...)
            self._resyncing = True  # garbled, or frames run together: look inside for good ones
            self._pos = pos + 1
            return CrcError("bad CRC", bytes(buf[pos:pos + MAX_RTU_ADU]))
        del buf[:self._pos]
        self._pos = 0
        if final:
            buf.clear()
            self._resyncing = self._final = False
        return NEED_DATA


__all__ = ["MAX_RTU_ADU", "MAX_TCP_LENGTH", "NEED_DATA", "RTU_MIN_SIZE", "RTU_NEED_MORE",
           "RTU_UNDELIMITED", "CrcError", "ForeignFrame", "Malformed", "RtuDialect", "NotModbusTcp", "Request", "RtuEvent",
           "RtuRequestDecoder", "TcpEvent", "TcpRequestDecoder", "rtu_request_length"]
