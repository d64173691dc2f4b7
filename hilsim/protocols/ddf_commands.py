"""Command lines from a DDF-stream client, and the server's replies (sans-I/O).

Spec: ``protocols/ddf-stream.md``, "Commands". The client may write ASCII
lines on the same TCP connection that carries the DDF stream:

    RATE <hz>                           frame rate, 0.1..30 [Hz]
    WINDOW <start_code> <length_code>   window codes, 1..31 and 0..3
    GAIN <db>                           receiver gain, integer 0..40 [dB]
    PING

Keywords are case-insensitive, words are separated by spaces or tabs, lines
end in LF or CRLF. The server answers every non-blank line, in order, with
``OK <canonical command>`` or ``ERR <reason>``. Replies do not go into the
byte stream between frames (that would break the DDF file the client is
receiving): they ride in the reply area of the frame header of the next
frame sent to that client (:func:`pack_replies`, :func:`decode_replies`).
"""

from __future__ import annotations

import re
from collections import deque
from dataclasses import dataclass
from typing import Final, Sequence, Union

from hilsim.protocols import codec
from hilsim.protocols.ddf import (
    LENGTH_CODE_MAX,
    LENGTH_CODE_MIN,
    NEED_DATA,
    REPLY_AREA_SIZE,
    START_CODE_MAX,
    START_CODE_MIN,
    NeedData,
    ProtocolError,
)

MAX_LINE_BYTES: Final = 256  # one command line before its LF (a CR counts)
MAX_REPLY_BYTES: Final = 127  # one reply line, LF included

RATE_MIN_HZ: Final = 0.1
RATE_MAX_HZ: Final = 30.0
GAIN_MIN_DB: Final = 0
GAIN_MAX_DB: Final = 40


@dataclass(frozen=True)
class SetRate:
    rate_hz: float  # [Hz] 0.1..30


@dataclass(frozen=True)
class SetWindow:
    start_code: int  # 1..31
    length_code: int  # 0..3


@dataclass(frozen=True)
class SetGain:
    gain_db: int  # [dB] 0..40


@dataclass(frozen=True)
class Ping:
    pass


@dataclass(frozen=True)
class BadCommand(codec.BadInput):
    """A line that is not a valid command; answer ``ERR <reason>``, go on."""

    line: bytes = b""  # the offending line (at most MAX_LINE_BYTES of it)


Command = Union[SetRate, SetWindow, SetGain, Ping]
CommandEvent = Union[SetRate, SetWindow, SetGain, Ping, BadCommand]
_RATE_RE: Final = re.compile(r"(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)\Z")
_INT_RE: Final = re.compile(r"[0-9]+\Z")
_USAGE: Final = {
    "RATE": "RATE <hz>",
    "WINDOW": "WINDOW <start_code> <length_code>",
    "GAIN": "GAIN <db>",
    "PING": "PING",
}


def _show(token: str) -> str:
    return '"' + (token if len(token) <= 24 else token[:21] + "...") + '"'


def _parse_line(raw: bytes) -> CommandEvent | None:
    """One line without its LF -> event, or None for a blank line."""
    if raw.endswith(b"\r"):
        raw = raw[:-1]
    for column, byte in enumerate(raw, 1):
        if byte >= 0x80:
            return BadCommand(f"non-ASCII byte 0x{byte:02X} at column {column}", raw)
        if (byte < 0x20 and byte != 0x09) or byte == 0x7F:
            return BadCommand(f"control byte 0x{byte:02X} at column {column}", raw)
    words = raw.decode("ascii").split()
    if not words:
        return None
    keyword, args = words[0].upper(), words[1:]
    if keyword not in _USAGE:
        return BadCommand(f"unknown command {_show(words[0])}; commands: RATE WINDOW GAIN PING", raw)
    wanted = {"RATE": 1, "WINDOW": 2, "GAIN": 1, "PING": 0}[keyword]
    if len(args) != wanted:
        return BadCommand(f"{keyword} takes {wanted} argument(s): {_USAGE[keyword]}", raw)
    if keyword == "PING":
        return Ping()
    if keyword == "RATE":
        if not _RATE_RE.match(args[0]):
            return BadCommand(f"RATE {_show(args[0])} is not a decimal number", raw)
        rate = float(args[0])
        if not RATE_MIN_HZ <= rate <= RATE_MAX_HZ:
            return BadCommand(f"RATE {_show(args[0])} out of range 0.1..30 Hz", raw)
        return SetRate(rate)
    for arg in args:
        if not _INT_RE.match(arg):
            return BadCommand(f"{keyword} {_show(arg)} is not a non-negative integer", raw)
    if keyword == "GAIN":
        gain = int(args[0])
        if not GAIN_MIN_DB <= gain <= GAIN_MAX_DB:
            return BadCommand(f"GAIN {_show(args[0])} out of range 0..40 dB", raw)
        return SetGain(gain)
    start, length = int(args[0]), int(args[1])
    if not START_CODE_MIN <= start <= START_CODE_MAX:
        return BadCommand(f"WINDOW start code {_show(args[0])} out of range 1..31", raw)
    if not LENGTH_CODE_MIN <= length <= LENGTH_CODE_MAX:
        return BadCommand(f"WINDOW length code {_show(args[1])} out of range 0..3", raw)
    return SetWindow(start, length)


class CommandDecoder:
    """Client -> server command lines (server side), sans-I/O.

    ``receive_data(bytes)`` then ``next_event()`` until NEED_DATA. Lines end
    in LF or CRLF; blank lines are ignored. A line longer than MAX_LINE_BYTES
    is dropped up to its LF and reported once as BadCommand; the partial line
    held never exceeds MAX_LINE_BYTES, whatever the client sends. Complete
    lines wait in a queue until next_event returns them, so drain after each
    receive_data. Never raises on any input.
    """

    def __init__(self) -> None:
        self._partial = bytearray()
        self._discarding = False
        self._lines: deque[bytes | BadCommand] = deque()

    @property
    def buffered_bytes(self) -> int:
        """Bytes of the incomplete line held (<= MAX_LINE_BYTES)."""
        return len(self._partial)

    @property
    def pending_lines(self) -> int:
        return len(self._lines)

    def _overlong(self, head: bytes) -> None:
        self._lines.append(BadCommand(f"line longer than {MAX_LINE_BYTES} bytes", head))

    def receive_data(self, data: bytes) -> None:
        pos, end = 0, len(data)
        while pos < end:
            lf = data.find(b"\n", pos)
            if self._discarding:
                if lf < 0:
                    return
                self._discarding = False
                pos = lf + 1
                continue
            stop = end if lf < 0 else lf
            if len(self._partial) + stop - pos > MAX_LINE_BYTES:
                room = MAX_LINE_BYTES - len(self._partial)
                self._overlong(bytes(self._partial) + data[pos : pos + room])
                self._partial.clear()
                self._discarding = lf < 0
                pos = end if lf < 0 else lf + 1
                continue
            self._partial += data[pos:stop]
            if lf < 0:
                return
            self._lines.append(bytes(self._partial))
            self._partial.clear()
            pos = lf + 1

    def next_event(self) -> CommandEvent | NeedData:
        while self._lines:
            item = self._lines.popleft()
            event = item if isinstance(item, BadCommand) else _parse_line(item)
            if event is not None:
                return event
        return NEED_DATA


def command_text(command: Command) -> str:
    """Canonical text of a command, e.g. ``RATE 12.5``, ``WINDOW 2 2``."""
    if isinstance(command, SetRate):
        text = repr(float(command.rate_hz))
        return "RATE " + (text[:-2] if text.endswith(".0") else text)
    if isinstance(command, SetWindow):
        return f"WINDOW {command.start_code} {command.length_code}"
    if isinstance(command, SetGain):
        return f"GAIN {command.gain_db}"
    return "PING"


def encode_command(command: Command) -> bytes:
    """Client side: a command -> its LF-terminated line; ValueError if out of range."""
    line = command_text(command).encode("ascii")
    event = _parse_line(line)
    if isinstance(event, BadCommand):
        raise ValueError(event.reason)
    return line + b"\n"


def encode_reply(ok: bool, text: str = "") -> bytes:
    """``OK <text>\\n`` or ``ERR <text>\\n``, cut to MAX_REPLY_BYTES.

    text must be printable ASCII (ValueError otherwise); a longer reply is
    shortened and ends in ``...``.
    """
    if any(not 0x20 <= ord(ch) <= 0x7E for ch in text):
        raise ValueError(f"reply text must be printable ASCII: {text!r}")
    line = ("OK" if ok else "ERR") + (" " + text if text else "")
    if len(line) + 1 > MAX_REPLY_BYTES:
        line = line[: MAX_REPLY_BYTES - 4] + "..."
    return line.encode("ascii") + b"\n"


def pack_replies(lines: Sequence[bytes]) -> tuple[bytes, int]:
    """Reply lines -> (FrameHeader.replies, how many lines it took, in order).

    Takes whole lines while they fit the 255 usable bytes; the server keeps
    the rest for the next frame it sends to that client.
    """
    packed = b""
    for count, line in enumerate(lines):
        if not line.endswith(b"\n") or len(line) > MAX_REPLY_BYTES or b"\0" in line:
            raise ValueError(f"not a reply line from encode_reply: {line!r}")
        if len(packed) + len(line) >= REPLY_AREA_SIZE:
            return packed, count
        packed += line
    return packed, len(lines)


@dataclass(frozen=True)
class Reply:
    ok: bool
    text: str


def decode_replies(replies: bytes) -> list[Reply]:
    """Client side: FrameHeader.replies -> replies in the order sent."""
    if not replies:
        return []
    if not replies.endswith(b"\n"):
        raise ProtocolError(f"reply area does not end in LF: {replies[-40:]!r}")
    out = []
    for line in replies[:-1].split(b"\n"):
        status, _, text = line.decode("ascii", errors="replace").partition(" ")
        if status not in ("OK", "ERR"):
            raise ProtocolError(f"bad reply line {line!r}")
        out.append(Reply(status == "OK", text))
    return out
