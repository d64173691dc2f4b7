"""socketcand's ASCII protocol, the server's side, sans-I/O (linux-can/socketcand).

Spec: ``protocols/socketcand.md``. Every message is ``< word ... >``. On
connect the server says ``< hi >``; the client opens a bus with
``< open can0 >`` (reply ``< ok >``, or ``< error ... >`` for a bus we do not
serve), then switches to raw mode with ``< rawmode >`` (``< ok >``). In raw
mode the server sends every bus frame as ``< frame ID SEC.USEC DATA >`` (ID
``%03X`` standard / ``%08X`` extended, DATA contiguous ``%02X``, empty for an
empty frame) and the client sends ``< send ID LEN B0 B1 ... >`` (an 8-digit ID
is extended, LEN and bytes in hex). ``< echo >`` is answered ``< echo >`` in
any state; ``< bcmmode >`` returns to BCM mode. The BCM commands (add,
update, delete, filter, subscribe ...) are not emulated: answered
``< error ... >``. ``< send >`` is accepted in BCM and raw mode.

Use: ``greeting()`` once, then ``receive_data(bytes)`` and ``next_event()``
until NEED_DATA; replies (each a whole message, to be sent on its own)
accumulate in ``replies()``. Text outside ``< >`` and messages longer than
``MAX_MESSAGE`` are skipped and counted; the buffer never holds more than
``MAX_MESSAGE`` bytes of an unfinished message. Never raises on peer input.
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass, field
from typing import Final, Union

from hilsim.protocols import codec
from hilsim.protocols.can import CanFrame
from hilsim.protocols.codec import NEED_DATA, NeedData

MAX_MESSAGE: Final = 256
HI: Final = b"< hi >"
OK: Final = b"< ok >"




class Mode(enum.Enum):
    NO_BUS = "no bus"
    BCM = "bcm"
    RAW = "raw"


@dataclass(frozen=True)
class BusOpened:
    channel: str


@dataclass(frozen=True)
class RawModeEntered:
    pass


@dataclass(frozen=True)
class SendFrame:
    frame: CanFrame


@dataclass(frozen=True)
class BadMessage(codec.BadInput):
    """A message that is not a valid command here (answered ``< error ... >``); ``text``: its words."""

    text: str = ""


Event = Union[BusOpened, RawModeEntered, SendFrame, BadMessage]


def format_frame(frame: CanFrame, timestamp: float) -> bytes:
    """``< frame ID SEC.USEC DATA >`` for a frame received at ``timestamp`` [s] (UNIX time)."""
    usec = int(round(max(0.0, timestamp) * 1e6))
    return f"< frame {frame.hex_id} {usec // 1_000_000}.{usec % 1_000_000:06d} {frame.data.hex().upper()} >".encode()


def format_send(frame: CanFrame) -> bytes:
    """Client side: ``< send ID LEN B0 ... >`` as python-can writes it."""
    data = " ".join(f"{b:x}" for b in frame.data)
    return f"< send {frame.hex_id} {len(frame.data):X} {data} >".encode()


def parse_frame_message(text: bytes) -> CanFrame | None:
    """Client side: a ``< frame ... >`` message -> frame (timestamp set), None if it is not one."""
    words = text.decode("ascii", "replace").split()
    if len(words) < 5 or words[:2] != ["<", "frame"] or words[-1] != ">":
        return None
    try:
        ident, ts = int(words[2], 16), float(words[3])
        data = bytes.fromhex(words[4]) if len(words) == 6 else b""
        return CanFrame(ident, data, len(words[2]) != 3, timestamp=ts)
    except ValueError:
        return None


def _parse_send(words: list[str]) -> CanFrame | str:
    """``send ID LEN B...`` (without the brackets) -> frame or the reason it is bad."""
    if len(words) < 3:
        return "send needs an id and a length"
    try:
        ident, n = int(words[1], 16), int(words[2], 16)
        data = bytes(int(b, 16) for b in words[3:])
    except ValueError:
        return "send: id, length and bytes must be hex"
    if not 0 <= n <= 8 or n != len(data):
        return f"send: length {words[2]} does not match {len(words) - 3} data bytes"
    ext = len(words[1]) == 8
    try:
        return CanFrame(ident, data, ext)
    except ValueError as exc:
        return f"send: {exc}"


@dataclass
class ServerStats:
    messages: int = 0
    frames: int = 0
    errors: int = 0
    bytes_skipped: int = 0


@dataclass
class SocketcandServer:
    """One client connection, server side. ``channels``: the bus names we serve."""

    channels: frozenset[str] = frozenset({"can0"})
    mode: Mode = Mode.NO_BUS
    channel: str = ""
    stats: ServerStats = field(default_factory=ServerStats)
    _buf: bytearray = field(default_factory=bytearray)
    _in_message: bool = False
    _discarding: bool = False
    _messages: deque[str | None] = field(default_factory=deque)
    _replies: list[bytes] = field(default_factory=list)

    def greeting(self) -> bytes:
        return HI

    @property
    def buffered_bytes(self) -> int:
        """Bytes of the unfinished line / message."""
        return len(self._buf)

    def receive_data(self, data: bytes) -> None:
        pos, end = 0, len(data)
        while pos < end:
            if not self._in_message:
                lt = data.find(b"<", pos)
                skipped = data[pos:end if lt < 0 else lt]
                self.stats.bytes_skipped += len(skipped) - sum(skipped.count(c) for c in b" \t\r\n")
                if lt < 0:
                    return
                self._in_message, self._discarding = True, False
                self._buf.clear()
                pos = lt + 1
                continue
            gt = data.find(b">", pos)
            stop = end if gt < 0 else gt
            if not self._discarding:
                if len(self._buf) + stop - pos > MAX_MESSAGE:
                    self._discarding = True
                    self._buf.clear()
                    self._messages.append(None)
                else:
                    self._buf += data[pos:stop]
            if gt < 0:
                return
            if not self._discarding:
                self._messages.append(self._buf.decode("ascii", "replace"))
            self._buf.clear()
            self._in_message = False
            pos = gt + 1

    def replies(self) -> list[bytes]:
        """Whole reply messages so far, in order (cleared)."""
        out, self._replies = self._replies, []
        return out

    def data_to_send(self) -> bytes:
        """The reply messages so far as one byte string (cleared); :meth:`replies` keeps them apart."""
        return b"".join(self.replies())

    def encode_frame(self, frame: CanFrame, timestamp: float) -> bytes:
        """The message for a bus frame; b"" unless this client is in raw mode."""
        return format_frame(frame, timestamp) if self.mode is Mode.RAW else b""

    def _bad(self, reason: str, text: str) -> BadMessage:
        self.stats.errors += 1
        self._replies.append(f"< error {reason} >".encode())
        return BadMessage(reason, text)

    def next_event(self) -> Event | NeedData:
        while self._messages:
            text = self._messages.popleft()
            self.stats.messages += 1
            if text is None:
                ev: Event | None = self._bad("message too long", "")
            else:
                ev = self._handle(text)
            if ev is not None:
                return ev
        return NEED_DATA

    def _handle(self, text: str) -> Event | None:
        words = text.split()
        if not words:
            return self._bad("empty message", text)
        cmd = words[0]
        if cmd == "echo":
            self._replies.append(b"< echo >")
            return None
        if self.mode is Mode.NO_BUS:
            if cmd == "open" and len(words) == 2:
                if words[1] not in self.channels:
                    return self._bad(f"could not open bus {words[1][:32]}", text)
                self.mode, self.channel = Mode.BCM, words[1]
                self._replies.append(OK)
                return BusOpened(words[1])
            return self._bad("open a bus first", text)
        if cmd == "rawmode" and len(words) == 1:
            self.mode = Mode.RAW
            self._replies.append(OK)
            return RawModeEntered()
        if cmd == "bcmmode" and len(words) == 1:
            self.mode = Mode.BCM
            self._replies.append(OK)
            return None
        if cmd == "send":
            frame = _parse_send(words)
            if isinstance(frame, str):
                return self._bad(frame, text)
            self.stats.frames += 1
            return SendFrame(frame)
        return self._bad(f"unsupported command {cmd[:32]}", text)
