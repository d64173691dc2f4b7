"""Resynchronising packet framing over a byte stream (sans-I/O), shared by the serial decoders.

The VESC UART and VRCSR decoders frame packets the same way: a start
marker, a header giving the length, the payload and a check (CRC). Both must
survive garbage, cut packets, bad checks and a header whose bogus length
claims bytes that never come. :class:`ResyncFramer` holds those rules once; a
protocol supplies four things: where the next start marker is
(:meth:`~ResyncFramer._find_start`), a verdict on the bytes at a start
(:meth:`~ResyncFramer._judge`), the event for a valid packet
(:meth:`~ResyncFramer._event`) and its counters (the ``_rejected``,
``_dropped`` and ``_skipped`` hooks).

The rules. The *candidate* is the first start marker in the buffer; the bytes
before it are skipped. Its verdict is one of

* ``"ok"``: a complete, valid packet of ``n`` bytes: its event is returned
  and its bytes consumed;
* ``"need"``: incomplete, judged again once ``n`` bytes are there. It may be
  a packet still arriving or garbage whose length field claims bytes that will
  never come: if a complete valid packet already starts after it, the
  candidate was garbage and is dropped (bytes up to that packet skipped);
  otherwise the decoder waits for data;
* anything else (a bad CRC, a wrong end byte, a length out of range: the
  protocol names the kind): counted, and the decoder moves on by one byte.

The buffer never holds more than one packet (the waiting candidate) plus the
last chunk fed, plus at most as many already consumed bytes (they are
dropped when that is at least half the buffer, so consuming is amortized
O(1) per byte rather than a copy of the buffer per packet).

Cost: amortized linear in the bytes received, however they are cut. Judging
everything again whenever a byte arrives is quadratic in the longest length
a header may claim (a byte-at-a-time peer sending a start marker with a large
length, then near-miss headers, cost a few kB/s). Instead the framer
remembers

* for the waiting candidate, the stream offset it needs (``_wait_end``):
  until the stream gets there it is not looked at again;
* for the starts after it, how far it has looked (``_scan``) and, of those
  it looked at, the ones still incomplete in a heap keyed by the offset each
  needs (``_later``); complete invalid ones are forgotten (more bytes cannot
  change them);
* the packet a search found (``_found_at``), so it is not checked twice.

Each start is therefore judged a bounded number of times (once per header
stage the protocol has, and once complete), and each byte is searched for
start markers once. All these offsets are absolute stream offsets
(``_base`` is the offset of ``_buf[0]``), so dropping consumed bytes does not
touch them.

When a search finds a later packet, everything remembered lies before that
packet's end, which is where decoding goes on: every remembered start was
looked at when the stream ended before the found packet's end (a start
waiting in the heap was incomplete then), so the memory is cleared.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from typing import ClassVar, Final, Generic, TypeVar

from hilsim.protocols.codec import ByteBuffer

OK: Final = "ok"
NEED: Final = "need"

T = TypeVar("T")

Verdict = tuple[str, int]
"""(kind, n): ``(OK, total length)``, ``(NEED, bytes from the start needed to judge again)`` or
``(reason, _)`` for a complete invalid packet (``reason`` is the protocol's, e.g. ``"crc"``)."""


@dataclass
class ResyncFramer(ByteBuffer, Generic[T]):
    """Base of a resynchronising packet decoder (see the module docstring for the rules).

    A subclass (usually a dataclass too: these fields are not ``__init__``
    arguments) implements the hooks and exposes ``next_event`` on top of
    :meth:`_next_frame`. ``receive_data`` and ``buffered_bytes`` (of
    :class:`~hilsim.protocols.codec.ByteBuffer`, whose buffer fields are
    declared here for the dataclass) are public.
    """

    marker_size: ClassVar[int] = 1  # bytes of a start marker

    _buf: bytearray = field(default_factory=bytearray, init=False, repr=False, compare=False)
    _pos: int = field(default=0, init=False, repr=False, compare=False)    # first unconsumed byte of _buf
    _base: int = field(default=0, init=False, repr=False, compare=False)   # stream offset of _buf[0]
    _wait_at: int = field(default=-1, init=False, repr=False, compare=False)   # waiting candidate's offset
    _wait_end: int = field(default=0, init=False, repr=False, compare=False)   # ... judged again from here
    _scan: int = field(default=0, init=False, repr=False, compare=False)       # later starts looked at below
    _later: list[tuple[int, int]] = field(default_factory=list, init=False, repr=False, compare=False)
    _found_at: int = field(default=-1, init=False, repr=False, compare=False)  # a search's valid packet
    _found_total: int = field(default=0, init=False, repr=False, compare=False)

    # ------------------------------------------------------------ protocol hooks

    def _find_start(self, buf: bytearray, i: int) -> int:
        """Index of the first start marker at or after index ``i`` of ``buf``, or -1."""
        raise NotImplementedError

    def _partial_start(self, buf: bytearray, i: int) -> int:
        """With no start marker in ``buf[i:]``: how many trailing bytes may begin one (kept)."""
        return 0

    def _judge(self, buf: bytearray, i: int) -> Verdict:
        """The verdict on the packet starting at index ``i`` (a start marker) of ``buf``."""
        raise NotImplementedError

    def _event(self, buf: bytearray, i: int, total: int) -> T:
        """The event of the valid ``total``-byte packet at index ``i`` (count it here)."""
        raise NotImplementedError

    def _rejected(self, kind: str) -> None:
        """A complete candidate was invalid for the reason ``kind``; the decoder moves on one byte."""

    def _dropped(self) -> None:
        """An incomplete candidate was dropped because a valid packet follows it."""

    def _skipped(self, n: int) -> None:
        """``n`` bytes were thrown away while resynchronising."""

    # ------------------------------------------------------------ stream

    def _skip(self, n: int) -> None:
        self._pos += n
        self._skipped(n)

    def _next_frame(self) -> T | None:
        """The next valid packet's event, or None when more data is needed."""
        buf = self._buf
        while True:
            i, size, base = self._pos, len(self._buf), self._base
            if i >= size:
                return None
            at = base + i
            if at == self._wait_at and base + size < self._wait_end:
                kind, n = NEED, self._wait_end - at      # still incomplete: not judged again
            elif at == self._found_at:
                kind, n = OK, self._found_total          # checked by the search that found it
            else:
                if at != self._wait_at:
                    s = self._find_start(buf, i)
                    if s < 0:
                        self._skip(size - i - self._partial_start(buf, i))
                        return None
                    if s > i:
                        self._skip(s - i)
                        i, at = s, base + s
                kind, n = self._judge(buf, i)
            if kind == OK:
                self._pos = i + n
                self._found_at = -1
                return self._event(buf, i, n)
            if kind == NEED:
                self._wait_at, self._wait_end = at, at + n
                later = self._find_later(at)
                if later < 0:
                    return None
                self._dropped()
                self._skip(later - at)
                continue
            self._rejected(kind)
            self._skip(1)

    def _find_later(self, candidate: int) -> int:
        """Stream offset of the first complete valid packet after ``candidate``, or -1.

        Judges only the starts whose awaited bytes have come and the starts in
        bytes not searched before; see the module docstring.
        """
        buf, base = self._buf, self._base
        stream_end = base + len(buf)
        later = self._later
        best, best_total = -1, 0
        while later and later[0][0] <= stream_end:
            _, p = heapq.heappop(later)
            if p <= candidate:
                continue  # consumed or skipped meanwhile
            kind, n = self._judge(buf, p - base)
            if kind == OK:
                if best < 0 or p < best:
                    best, best_total = p, n
            elif kind == NEED:
                heapq.heappush(later, (p + n, p))
        if best < 0:
            # every start before _scan is invalid or still incomplete: look on from there
            j = self._scan
            if j <= candidate:
                j = candidate + 1
            while True:
                s = self._find_start(buf, j - base)
                if s < 0:
                    last = stream_end - self.marker_size + 1  # a marker may begin here, not yet whole
                    self._scan = max(j, last)
                    return -1
                p = base + s
                kind, n = self._judge(buf, s)
                if kind == OK:
                    best, best_total = p, n
                    break
                if kind == NEED:
                    heapq.heappush(later, (p + n, p))
                j = p + 1
        # everything remembered lies before best + best_total, where decoding goes on
        later.clear()
        self._scan = best + best_total
        self._found_at, self._found_total = best, best_total
        return best
