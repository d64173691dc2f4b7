"""slcan (Lawicel ASCII CAN over a serial line), the adapter's side, sans-I/O.

Spec: ``protocols/slcan.md``. The host writes commands ended by CR; the
adapter answers CR for OK and BEL (``\\a``) for an error, and writes every
frame it receives from the bus as a line. Commands handled::

    C             close the channel            O   open     L   open listen-only
    Sn            bitrate code 0..8 (closed)   sXXYY  BTR registers (closed)
    F             status flags -> "F00"        V   version -> "V1013"   N  serial -> "NA123"
    tIIILDD..     standard frame               TIIIIIIIILDD..   extended frame
    rIIIL         standard remote frame        RIIIIIIIIL       extended remote frame
    Mxxxxxxxx mxxxxxxxx  acceptance code/mask (accepted, not applied)
    Z0            timestamps off (Z1 is refused: no timestamps here)
    (empty line)  OK

A transmitted frame is acknowledged ``z`` / ``Z`` + CR (standard / extended)
while the channel is open, BEL otherwise. ``O`` on an open channel is
accepted (python-can sends it twice); ``S`` on an open channel is refused.
Hex digits are accepted in either case (python-can writes upper case,
dronecan lower case). A line longer than ``MAX_LINE`` is discarded up to its
CR and answered BEL, so the buffer never exceeds ``MAX_LINE`` bytes.

Use: ``receive_data(bytes)``, then ``next_event()`` until NEED_DATA; replies
accumulate in ``data_to_send()``. A :class:`Transmit` event is acknowledged
OK unless the caller calls ``reject_transmit()`` before the next
``next_event()`` (e.g. the bus is over capacity: a real adapter answers BEL
when its transmit buffer is full). ``encode_frame(frame)`` gives the line
for a frame from the bus (empty while the channel is closed).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Final, Union

from hilsim.protocols import codec
from hilsim.protocols.can import CanFrame
from hilsim.protocols.codec import NEED_DATA, NeedData

OK: Final = b"\r"
ERROR: Final = b"\a"
MAX_LINE: Final = 64       # the longest valid line is 27 bytes (T + 8 + 1 + 16 + 1)
BITRATES: Final[dict[int, int]] = {0: 10_000, 1: 20_000, 2: 50_000, 3: 100_000, 4: 125_000,
                                   5: 250_000, 6: 500_000, 7: 800_000, 8: 1_000_000}
_HEX: Final = frozenset(b"0123456789abcdefABCDEF")




@dataclass(frozen=True)
class Transmit:
    """The host asks to send ``frame`` on the bus."""

    frame: CanFrame


@dataclass(frozen=True)
class Opened:
    listen_only: bool


@dataclass(frozen=True)
class Closed:
    pass


@dataclass(frozen=True)
class BitrateSet:
    bitrate: int          # [bit/s]; 0 when set by BTR registers


@dataclass(frozen=True)
class BadLine(codec.BadInput):
    """A line that is not a valid command (answered BEL)."""

    line: bytes = b""


Event = Union[Transmit, Opened, Closed, BitrateSet, BadLine]


def _parse_hex(s: bytes) -> int | None:
    if not s or any(c not in _HEX for c in s):
        return None
    return int(s, 16)


def parse_frame_line(line: bytes) -> CanFrame | str:
    """A ``t``/``T``/``r``/``R`` line without its CR -> frame, or the reason it is not one."""
    if not line or line[:1] not in (b"t", b"T", b"r", b"R"):
        return "not a frame line"
    ext = line[:1] in (b"T", b"R")
    remote = line[:1] in (b"r", b"R")
    n_id = 8 if ext else 3
    if len(line) < 1 + n_id + 1:
        return "frame line too short"
    ident = _parse_hex(line[1:1 + n_id])
    dlc_c = line[1 + n_id]
    if ident is None or not 0x30 <= dlc_c <= 0x38:
        return "bad id or length digit"
    if ident > (0x1FFFFFFF if ext else 0x7FF):
        return "id out of range"
    dlc = dlc_c - 0x30
    rest = line[2 + n_id:]
    if remote:
        if rest:
            return "remote frame with data"
        return CanFrame(ident, b"", ext, True, dlc)
    if len(rest) != 2 * dlc:
        return f"{dlc} data bytes announced, {len(rest) / 2:g} given"
    if rest and _parse_hex(rest) is None:
        return "bad hex data"
    return CanFrame(ident, bytes.fromhex(rest.decode("ascii")), ext)


def format_frame(frame: CanFrame, lowercase: bool = False) -> bytes:
    """A frame -> its line with CR (``t12340011223344\\r``)."""
    kind = "R" if frame.is_remote else "T"
    head = (kind if frame.is_extended else kind.lower()) + frame.hex_id
    if frame.is_remote:
        line = f"{head}{frame.dlc}"
    else:
        line = f"{head}{len(frame.data)}{frame.data.hex().upper()}"
    if lowercase:
        line = line[0] + line[1:].lower()
    return line.encode("ascii") + b"\r"


@dataclass
class CodecStats:
    lines: int = 0
    frames: int = 0
    errors: int = 0          # lines answered BEL
    overlong: int = 0


@dataclass
class SlcanAdapter:
    """The adapter side of slcan. Never raises on any input."""

    is_open: bool = False
    listen_only: bool = False
    bitrate: int = 1_000_000
    version: bytes = b"V1013"
    serial_number: bytes = b"NA123"
    stats: CodecStats = field(default_factory=CodecStats)
    _buf: bytearray = field(default_factory=bytearray)
    _discarding: bool = False
    _out: bytearray = field(default_factory=bytearray)
    _ack_pending: bytes = b""
    _pending: deque[bytes | None] = field(default_factory=deque)  # complete lines; None = overlong

    @property
    def buffered_bytes(self) -> int:
        """Bytes of the unfinished line / message."""
        return len(self._buf)

    def receive_data(self, data: bytes) -> None:
        """Bytes from the host. At most MAX_LINE bytes of an unfinished line are kept."""
        for chunk in data.split(b"\n"):  # some hosts end lines in CR LF: LF is ignored
            self._feed(chunk)

    def _feed(self, data: bytes) -> None:
        pos = 0
        while pos < len(data):
            cr = data.find(b"\r", pos)
            stop = len(data) if cr < 0 else cr
            if self._discarding:
                if cr >= 0:
                    self._discarding = False
                    self._buf.clear()
                pos = stop + 1
                continue
            if len(self._buf) + stop - pos > MAX_LINE:
                self.stats.overlong += 1
                self._lines_overlong()
                self._discarding = cr < 0
                pos = stop + 1
                continue
            self._buf += data[pos:stop]
            if cr < 0:
                return
            self._pending.append(bytes(self._buf))
            self._buf.clear()
            pos = cr + 1

    def _lines_overlong(self) -> None:
        self._buf.clear()
        self._pending.append(None)

    def data_to_send(self) -> bytes:
        """Replies so far (in order); clears them."""
        self._flush_ack()
        out = bytes(self._out)
        self._out.clear()
        return out

    def reject_transmit(self) -> None:
        """Answer the last Transmit with BEL instead of OK (the frame was not sent)."""
        if self._ack_pending:
            self._ack_pending = b""
            self._out += ERROR
            self.stats.errors += 1

    def _flush_ack(self) -> None:
        if self._ack_pending:
            self._out += self._ack_pending
            self._ack_pending = b""

    def encode_frame(self, frame: CanFrame) -> bytes:
        """The line for a frame received from the bus; b"" while the channel is closed."""
        return format_frame(frame) if self.is_open else b""

    def _error(self, reason: str, line: bytes) -> BadLine:
        self._out += ERROR
        self.stats.errors += 1
        return BadLine(reason, line)

    def next_event(self) -> Event | NeedData:
        self._flush_ack()
        while self._pending:
            line = self._pending.popleft()
            self.stats.lines += 1
            if line is None:
                return self._error(f"line longer than {MAX_LINE} bytes", b"")
            ev = self._command(line)
            if ev is not None:
                return ev
        return NEED_DATA

    def _command(self, line: bytes) -> Event | None:
        if not line:
            self._out += OK
            return None
        c, arg = line[:1], line[1:]
        if c in (b"t", b"T", b"r", b"R"):
            if not self.is_open or self.listen_only:
                return self._error("channel not open for sending", line)
            frame = parse_frame_line(line)
            if isinstance(frame, str):
                return self._error(frame, line)
            self.stats.frames += 1
            self._ack_pending = b"Z\r" if frame.is_extended else b"z\r"
            return Transmit(frame)
        if c in (b"O", b"L") and not arg:
            was = (self.is_open, self.listen_only)
            self.is_open, self.listen_only = True, c == b"L"
            self._out += OK
            return Opened(self.listen_only) if was != (True, self.listen_only) else None
        if c == b"C" and not arg:
            was_open = self.is_open
            self.is_open = False
            self._out += OK
            return Closed() if was_open else None
        if c == b"S":
            if self.is_open:
                return self._error("bitrate change while open", line)
            code = _parse_hex(arg) if len(arg) == 1 else None
            if code is None or code not in BITRATES:
                return self._error("bitrate code must be 0..8", line)
            self.bitrate = BITRATES[code]
            self._out += OK
            return BitrateSet(self.bitrate)
        if c == b"s":
            if self.is_open or len(arg) != 4 or _parse_hex(arg) is None:
                return self._error("BTR needs 4 hex digits while closed", line)
            self._out += OK
            return BitrateSet(0)
        if c == b"F" and not arg:
            self._out += b"F00\r"
            return None
        if c == b"V" and not arg:
            self._out += self.version + b"\r"
            return None
        if c == b"N" and not arg:
            self._out += self.serial_number + b"\r"
            return None
        if c in (b"M", b"m") and len(arg) == 8 and _parse_hex(arg) is not None:
            self._out += OK
            return None
        if line == b"Z0":
            self._out += OK
            return None
        return self._error("unknown or unsupported command", line)
