"""The one codec contract every wire protocol in :mod:`hilsim.protocols` follows (sans-I/O).

As h11 does it: a stream decoder is a pure object fed with bytes and drained of
events; an encoder is a function (or method) that returns bytes. No sockets,
no asyncio, no clocks.

Decoders::

    dec = SomeDecoder()
    dec.receive_data(chunk)            # any cut of the byte stream, any number of times
    while (ev := dec.next_event()) is not NEED_DATA:
        handle(ev)                     # a decoded message, or a BadInput event

or, the same thing, ``for ev in drain(dec, chunk): ...``.

* :data:`NEED_DATA` is the one "need more bytes" sentinel of the whole package.
* Every event a decoder returns for bad peer input is a :class:`BadInput`
  (:class:`Junk` for bytes skipped while resynchronising, :class:`Oversize` for a
  length beyond the decoder's bound, :class:`BadFrame` for a complete frame whose
  check or contents are wrong). A device counts them and answers as the real
  device would; nothing in a decoder raises on peer input. Protocols subclass
  these where they carry more (a message id, a header).
* A decoder's memory is bounded: the longest message it accepts plus the
  last chunk it was fed (``buffered_bytes`` tells).
* Decoders give the same events however the input is cut (whole, byte at a
  time): the fuzz target table (``tests/fuzz/targets.py``) holds every decoder
  to that.

A decoder that buffers bytes builds on :class:`ByteBuffer` (``receive_data``, ``buffered_bytes``).
Line protocols (NMEA 0183, JSON lines, text commands) frame with :class:`LineFramer`.
File readers take ``bytes`` or a binary stream (``typing.BinaryIO``), never a path.

Decoders of whole link units follow the same contract with the unit in place of a
byte chunk: a datagram decoder's ``receive_data(datagram)`` takes exactly one
datagram (UDP keeps their bounds: ``aris.FrameAssembler``); a CAN decoder takes
``receive_frame(frame, now)`` (``dronecan.TransferReceiver``). Either is drained
with ``next_event()`` as above.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import ClassVar, Final, Generic, Iterator, Protocol, TypeVar, Union


class NeedData(enum.Enum):
    NEED_DATA = "NEED_DATA"


NEED_DATA: Final = NeedData.NEED_DATA
"""Returned by ``next_event()`` when the decoder needs more bytes."""

E = TypeVar("E", covariant=True)


@dataclass(frozen=True)
class BadInput:
    """Base of every bad-input event: the peer sent something the device would not accept.

    reason: one line saying what was wrong (for logs and counters)."""

    reason: str = ""


@dataclass(frozen=True)
class Junk(BadInput):
    """``n_bytes`` skipped while looking for the next frame start."""

    n_bytes: int = 0


@dataclass(frozen=True, init=False)
class CountedJunk(Junk):
    """A :class:`Junk` made from its count: ``Junk(n_bytes)``, or ``Junk(n_bytes, reason)``. A
    protocol's subclass names its own default reason in ``DEFAULT_REASON``."""

    DEFAULT_REASON: ClassVar[str] = "bytes skipped while resynchronising"

    def __init__(self, n_bytes: int, reason: str | None = None) -> None:
        object.__setattr__(self, "reason", self.DEFAULT_REASON if reason is None else reason)
        object.__setattr__(self, "n_bytes", n_bytes)


@dataclass(frozen=True)
class Oversize(BadInput):
    """A frame announcing ``length`` bytes beyond the decoder's bound; the decoder resynchronises."""

    length: int = 0


@dataclass(frozen=True)
class BadFrame(BadInput):
    """A complete frame that is not valid (bad checksum or CRC, bad contents); ``data`` is (up to
    a bounded prefix of) its bytes."""

    data: bytes = b""


class StreamDecoder(Protocol[E]):
    """What every stream decoder provides."""

    def receive_data(self, data: bytes) -> None:
        """Append bytes received from the peer (any cut; ``b""`` is allowed and changes nothing)."""

    def next_event(self) -> Union[E, NeedData]:
        """The next event, or :data:`NEED_DATA` when the buffered bytes hold no more."""

    @property
    def buffered_bytes(self) -> int:
        """Bytes received and not yet consumed or skipped."""


def drain(decoder: StreamDecoder[E], data: bytes = b"", limit: int = 100_000) -> Iterator[E]:
    """Feed ``data`` and yield events until :data:`NEED_DATA`, at most ``limit`` of them: what is
    left stays buffered for the next call (a device's handler is bounded per chunk of input, and a
    decoder bug that never returns NEED_DATA cannot hang the event loop)."""
    if data:
        decoder.receive_data(data)
    for _ in range(limit):
        ev = decoder.next_event()
        if ev is NEED_DATA:
            return
        yield ev


class ByteBuffer:
    """The receive buffer a stream decoder builds on: ``_buf`` holds the bytes received, ``_pos`` is
    the first one not yet consumed or skipped, ``_base`` the stream offset of ``_buf[0]`` (an offset
    kept as ``_base + index`` survives the dropping of consumed bytes). A decoder consumes by moving
    ``_pos``; :meth:`receive_data` drops the consumed bytes once they are at least half the buffer,
    so consuming costs amortized O(1) per byte rather than a copy of the buffer per packet.

    A subclass calls ``super().__init__()`` and implements ``next_event``; ``buffered_bytes`` and
    ``receive_data`` of :class:`StreamDecoder` are these."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._pos = 0
        self._base = 0

    @property
    def buffered_bytes(self) -> int:
        """Bytes received and not yet consumed or skipped."""
        return len(self._buf) - self._pos

    def receive_data(self, data: bytes) -> None:
        """Append bytes received from the peer (any cut; ``b""`` is allowed and changes nothing)."""
        pos = self._pos
        if pos and 2 * pos >= len(self._buf):
            del self._buf[:pos]
            self._base += pos
            self._pos = 0
        self._buf += data


@dataclass(frozen=True)
class Line:
    """One line without its terminator (``\\n``, ``\\r\\n``; a lone ``\\r`` too when the framer allows it)."""

    data: bytes


class LineFramer(ByteBuffer):
    """Splits a byte stream into lines (sans-I/O), for NMEA 0183, JSON lines and text commands.

    ``next_event()`` gives :class:`Line` (terminator removed), :class:`Oversize` for a line
    longer than ``max_line`` bytes (its bytes up to the next terminator are dropped; the
    framer is in step again at the next line; its ``length`` is ``max_line + 1`` however the
    input was cut), or :data:`NEED_DATA`. ``cr_ends_line``: a
    lone CR ends a line too (some serial consoles send CR only). Blank lines are given as
    empty :class:`Line` events only when ``keep_blank``. Memory: at most ``max_line`` bytes
    plus the last chunk.
    """

    def __init__(self, max_line: int = 4096, *, cr_ends_line: bool = False, keep_blank: bool = False) -> None:
        if max_line < 1:
            raise ValueError("max_line must be positive")
        super().__init__()
        self.max_line = int(max_line)
        self.cr_ends_line = cr_ends_line
        self.keep_blank = keep_blank
        self._scanned = 0       # bytes from _pos already searched for a terminator
        self._discarding = False  # inside an oversize line: drop bytes to the next terminator
        self._dropped = 0
        self.lines = 0
        self.oversize = 0

    def _find_end(self, start: int) -> tuple[int, int]:
        """(index of the terminator, its length) at or after ``start``, or (-1, 0)."""
        buf = self._buf
        nl = buf.find(b"\n", start)
        if not self.cr_ends_line:
            return (nl, 1) if nl >= 0 else (-1, 0)
        cr = buf.find(b"\r", start, nl if nl >= 0 else len(buf))
        if cr >= 0:
            if cr + 1 < len(buf) and buf[cr + 1] == 0x0A:
                return cr, 2
            if cr + 1 == len(buf):
                return -1, 0  # CR at the end: wait for a possible LF
            return cr, 1
        return (nl, 1) if nl >= 0 else (-1, 0)

    def next_event(self) -> Union[Line, Oversize, NeedData]:
        while True:
            start = self._pos
            end, tlen = self._find_end(start + self._scanned)
            if end < 0:
                pending = len(self._buf) - start
                if self._discarding:
                    keep = 1 if self.cr_ends_line and self._buf.endswith(b"\r") else 0
                    self._dropped += pending - keep
                    self._pos = len(self._buf) - keep
                    self._scanned = 0
                elif pending > self.max_line:
                    self.oversize += 1
                    self._discarding = True
                    self._dropped = pending
                    self._pos = len(self._buf)
                    self._scanned = 0
                    return Oversize(f"line longer than {self.max_line} bytes", self.max_line + 1)
                else:
                    self._scanned = max(0, pending - 1)  # a CR at the end may pair with the next LF
                return NEED_DATA
            self._pos = end + tlen
            self._scanned = 0
            if self._discarding:
                self._discarding = False
                self._dropped = 0
                continue
            raw = bytes(self._buf[start:end])
            if raw.endswith(b"\r"):
                raw = raw[:-1]
            if len(raw) > self.max_line:
                self.oversize += 1
                return Oversize(f"line longer than {self.max_line} bytes", self.max_line + 1)
            if not raw and not self.keep_blank:
                continue
            self.lines += 1
            return Line(raw)


L = TypeVar("L")


class LineDecoder(Generic[L]):
    """A line protocol's decoder: a :class:`LineFramer` and :meth:`parse_line`, which turns one line
    (terminator removed) into an event or a :class:`BadInput`. ``next_event`` gives those events
    and the framer's :class:`Oversize`; ``good`` and ``bad`` count them. Subclasses set
    ``MAX_LINE``, ``CR_ENDS_LINE`` (a lone CR ends a line) and ``SKIP_BLANK`` (lines of only
    whitespace are skipped, not parsed)."""

    MAX_LINE = 4096
    CR_ENDS_LINE = False
    SKIP_BLANK = False

    def __init__(self, max_line: int | None = None) -> None:
        self._lines = LineFramer(max_line or self.MAX_LINE, cr_ends_line=self.CR_ENDS_LINE)
        self.good = 0
        self.bad = 0

    @property
    def buffered_bytes(self) -> int:
        return self._lines.buffered_bytes

    def receive_data(self, data: bytes) -> None:
        self._lines.receive_data(data)

    def parse_line(self, line: bytes) -> Union[L, BadInput]:
        raise NotImplementedError

    def next_event(self) -> Union[L, BadInput, NeedData]:
        while True:
            ev = self._lines.next_event()
            if ev is NEED_DATA:
                return NEED_DATA
            if isinstance(ev, Oversize):
                self.bad += 1
                return ev
            assert isinstance(ev, Line)
            if self.SKIP_BLANK and not ev.data.strip():
                continue
            out = self.parse_line(ev.data)
            if isinstance(out, BadInput):
                self.bad += 1
            else:
                self.good += 1
            return out
