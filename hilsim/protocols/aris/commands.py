"""The ARIS command channel, sonar side (sans-I/O): command events, their encoding, :class:`CommandReader`.

Each command on the TCP channel is a 4-byte big-endian length then a serialized
``Command`` (``protocols/aris/aris_commands.proto``).
"""

from __future__ import annotations

import heapq
import struct
from collections import deque
from dataclasses import dataclass
from typing import Union

from google.protobuf import unknown_fields
from google.protobuf.message import DecodeError, Message

from hilsim.protocols import codec
from hilsim.protocols.aris.constants import (
    MAX_COMMAND_LENGTH,
    PING,
    SET_ACOUSTICS,
    SET_DATETIME,
    SET_FOCUS,
    SET_FRAMESTREAM_RECEIVER,
    SET_SALINITY,
)
from hilsim.protocols.aris.settings import AcousticSettings
from hilsim.protocols.aris_pb import aris_commands_pb2 as pb_cmd
from hilsim.protocols.codec import NEED_DATA, NeedData



@dataclass(frozen=True)
class SetDateTime:
    text: str  # "2014-Jan-31 23:58:15"


@dataclass(frozen=True)
class SetFrameStreamReceiver:
    port: int
    ip: str | None = None  # None: the TCP peer's address


@dataclass(frozen=True)
class SetAcoustics:
    settings: AcousticSettings


@dataclass(frozen=True)
class SetSalinity:
    salinity: int  # [ppt] 0, 15 or 35


@dataclass(frozen=True)
class SetFocus:
    focus_range: float | None = None  # [m]
    position: int | None = None  # motor units


@dataclass(frozen=True)
class Ping:
    pass


@dataclass(frozen=True)
class Unsupported:
    """A well-formed command of a type we accept but do not act on."""

    command_type: int


@dataclass(frozen=True)
class BadCommand(codec.BadInput):
    """A length-prefixed frame whose payload is not a valid Command (``length``: its payload size)."""

    length: int = 0


@dataclass(frozen=True, init=False)
class Oversize(codec.Oversize):
    """A length prefix above the bound; the reader resynchronises."""

    def __init__(self, length: int, reason: str = "length prefix beyond the reader's bound") -> None:
        object.__setattr__(self, "reason", reason)
        object.__setattr__(self, "length", length)


class Junk(codec.CountedJunk):
    """Bytes skipped while resynchronising (``Junk(n_bytes)``)."""


Command = Union[SetDateTime, SetFrameStreamReceiver, SetAcoustics, SetSalinity, SetFocus, Ping]
CommandEvent = Union[SetDateTime, SetFrameStreamReceiver, SetAcoustics, SetSalinity, SetFocus, Ping,
                     Unsupported, BadCommand, Oversize, Junk]


def _settings_pb(s: AcousticSettings, m: pb_cmd.Command.SetAcousticSettings) -> None:
    m.cookie = s.cookie
    m.frameRate = s.frame_rate
    m.samplesPerBeam = s.samples_per_beam
    m.sampleStartDelay = s.sample_start_delay
    m.cyclePeriod = s.cycle_period
    m.samplePeriod = s.sample_period
    m.pulseWidth = s.pulse_width
    m.pingMode = s.ping_mode
    m.enableTransmit = s.enable_transmit
    m.frequency = s.frequency  # type: ignore[assignment]
    m.enable150Volts = s.enable_150_volts
    m.receiverGain = s.receiver_gain


def command_message(cmd: Command) -> pb_cmd.Command:
    """A command event -> the protobuf Command (every field set explicitly)."""
    m = pb_cmd.Command()
    if isinstance(cmd, SetDateTime):
        m.type = SET_DATETIME  # type: ignore[assignment]
        m.dateTime.dateTime = cmd.text
    elif isinstance(cmd, SetFrameStreamReceiver):
        m.type = SET_FRAMESTREAM_RECEIVER  # type: ignore[assignment]
        m.frameStreamReceiver.port = cmd.port
        if cmd.ip is not None:
            m.frameStreamReceiver.ip = cmd.ip
    elif isinstance(cmd, SetAcoustics):
        m.type = SET_ACOUSTICS  # type: ignore[assignment]
        _settings_pb(cmd.settings, m.settings)
    elif isinstance(cmd, SetSalinity):
        m.type = SET_SALINITY  # type: ignore[assignment]
        m.salinity.salinity = cmd.salinity  # type: ignore[assignment]
    elif isinstance(cmd, SetFocus):
        m.type = SET_FOCUS  # type: ignore[assignment]
        m.focusPosition.SetInParent()
        if cmd.focus_range is not None:
            m.focusPosition.focusRange = cmd.focus_range
        if cmd.position is not None:
            m.focusPosition.position = cmd.position
    elif isinstance(cmd, Ping):
        m.type = PING  # type: ignore[assignment]
        m.ping.SetInParent()
    else:
        raise ValueError(f"not a command: {cmd!r}")
    return m


def frame_command(payload: bytes) -> bytes:
    """Prefix ``payload`` with its 4-byte big-endian length."""
    return struct.pack(">I", len(payload)) + payload


def encode_command(cmd: Command) -> bytes:
    """A command event -> length prefix + serialized Command."""
    return frame_command(command_message(cmd).SerializeToString())


def _unknown_numbers(m: Message) -> set[int]:
    """Field numbers in ``m``'s unknown fields (proto2: an enum value the enum lacks lands there)."""
    return {f.field_number for f in unknown_fields.UnknownFieldSet(m)}


def _has_unknown(m: Message) -> bool:
    if len(unknown_fields.UnknownFieldSet(m)):
        return True
    for fd, v in m.ListFields():
        if fd.message_type is not None and _has_unknown(v):
            return True
    return False


def parse_command(payload: bytes, strict: bool = False) -> CommandEvent:
    """One serialized Command -> a command event, Unsupported or BadCommand (never raises).

    Read as the sonar reads proto2 and proto3 clients alike: a scalar or enum field that is
    absent has its default (proto3 clients omit defaults: a SetDateTime arrives without
    ``type``, SET_DATETIME being 0); a message field keeps its presence (proto3 too), so a
    command type without its message is a BadCommand. strict: also reject unknown fields
    and unknown types (used while resynchronising).
    """
    m = pb_cmd.Command()
    try:
        m.ParseFromString(payload)
    except (DecodeError, RuntimeWarning, ValueError) as exc:
        return BadCommand(f"not a Command: {exc}", len(payload))
    if not m.HasField("type") and _unknown_numbers(m) & {1}:
        return BadCommand("Command with an unknown type", len(payload))
    if strict and _has_unknown(m):
        return BadCommand("unknown fields", len(payload))
    t = int(m.type)  # proto3 semantics: absent is the default, SET_DATETIME (0), as proto3 clients send it
    if t == SET_DATETIME and m.HasField("dateTime"):
        text: object = m.dateTime.dateTime
        if not isinstance(text, str):  # proto2 strings are not checked: invalid UTF-8 comes back as bytes
            return BadCommand("dateTime is not UTF-8 text", len(payload))
        return SetDateTime(text)
    if t == SET_FRAMESTREAM_RECEIVER and m.HasField("frameStreamReceiver"):
        r = m.frameStreamReceiver
        ip: object = r.ip if r.HasField("ip") else None
        if ip is not None and not isinstance(ip, str):
            return BadCommand("frameStreamReceiver ip is not UTF-8 text", len(payload))
        return SetFrameStreamReceiver(int(r.port), ip)
    if t == SET_ACOUSTICS and m.HasField("settings"):
        s = m.settings
        return SetAcoustics(AcousticSettings(
            cookie=s.cookie, frame_rate=float(s.frameRate), samples_per_beam=s.samplesPerBeam,
            sample_start_delay=s.sampleStartDelay, cycle_period=s.cyclePeriod, sample_period=s.samplePeriod,
            pulse_width=s.pulseWidth, ping_mode=s.pingMode, enable_transmit=s.enableTransmit,
            frequency=int(s.frequency), enable_150_volts=s.enable150Volts, receiver_gain=float(s.receiverGain)))
    if t == SET_SALINITY and m.HasField("salinity"):
        return SetSalinity(int(m.salinity.salinity))
    if t == SET_FOCUS and m.HasField("focusPosition"):
        f = m.focusPosition
        return SetFocus(float(f.focusRange) if f.HasField("focusRange") else None,
                        int(f.position) if f.HasField("position") else None)
    if t == PING:
        return Ping()
    if t in (SET_DATETIME, SET_FRAMESTREAM_RECEIVER, SET_ACOUSTICS, SET_SALINITY, SET_FOCUS):
        return BadCommand(f"command type {t} without its message", len(payload))
    if strict:
        return BadCommand(f"command type {t} not handled", len(payload))
    return Unsupported(t)


class CommandReader(codec.ByteBuffer):
    """Incremental decoder of the ARIS command channel (sonar side).

    ``receive_data(bytes)`` then ``next_event()`` until NEED_DATA. In sync, each
    frame is a 4-byte big-endian length and that many payload bytes. A length
    above ``max_length`` gives :class:`Oversize`, a payload that is not a valid
    Command gives :class:`BadCommand`; either drops the reader out of sync. Out
    of sync it looks, byte by byte, for the first offset holding a complete
    frame whose payload parses strictly (known type, its message, no unknown
    fields), reports the bytes before it as :class:`Junk` and goes on in sync.
    Memory: the buffer holds at most ``max_length + 4`` bytes beyond what was
    fed since the last drain; a 4 GB length prefix allocates nothing. Out of
    sync, the offsets still waiting for bytes are remembered (at most
    ``max_length + 4`` of them, about 150 bytes of bookkeeping each).

    Cost: amortized linear in the bytes received, however they are cut. In
    sync, a frame still arriving is not looked at again until the stream
    reaches its end (``_wait_end``). Out of sync, every offset is judged once
    when its length prefix is whole: a length above the bound or a complete
    frame that does not parse is forgotten (more bytes cannot change it), a
    frame still incomplete is remembered with the stream offset it needs
    (``_waiting``, a heap) and parsed once when that offset arrives;
    ``_scan`` is how far offsets were judged. Offsets are stream offsets
    (``_base`` is the offset of ``_buf[0]``), untouched when consumed bytes
    are dropped.
    """

    def __init__(self, max_length: int = MAX_COMMAND_LENGTH) -> None:
        super().__init__()  # _buf, _pos and _base: the stream offset of _buf[0]
        self.max_length = int(max_length)
        self._synced = True
        self._pending: list[CommandEvent] = []
        self._wait_end = 0  # in sync: the frame at _pos is incomplete until the stream reaches this offset
        # out of sync: offsets below _scan are judged; the incomplete ones as (offset needed, offset) in
        # _waiting, and in ascending order in _waiting_order (those still in _waiting_set are incomplete)
        self._scan = 0
        self._waiting: list[tuple[int, int]] = []
        self._waiting_order: deque[int] = deque()
        self._waiting_set: set[int] = set()
        self.errors = 0
        self.commands = 0

    def events(self) -> list[CommandEvent]:
        """Every event available now (drains the reader)."""
        out: list[CommandEvent] = []
        while (ev := self.next_event()) is not NEED_DATA:
            out.append(ev)
        return out

    def next_event(self) -> CommandEvent | NeedData:
        if self._pending:
            return self._pending.pop(0)
        ev = self._next_synced() if self._synced else self._resync()  # None: nothing more in the buffer
        if ev is None:
            return NEED_DATA
        if isinstance(ev, (BadCommand, Oversize)):
            self.errors += 1
        elif not isinstance(ev, Junk):
            self.commands += 1
        return ev

    def _next_synced(self) -> CommandEvent | None:
        buf, pos = self._buf, self._pos
        if len(buf) - pos < 4 or self._base + len(buf) < self._wait_end:
            return None
        (length,) = struct.unpack_from(">I", buf, pos)
        if length > self.max_length:
            self._synced = False
            self._pos = pos + 1
            return Oversize(length)
        end = pos + 4 + length
        if len(buf) < end:
            self._wait_end = self._base + end
            return None
        ev = parse_command(bytes(buf[pos + 4 : end]))
        if isinstance(ev, BadCommand):
            self._synced = False
            self._pos = pos + 1
        else:
            self._pos = end
        return ev

    def _resync(self) -> CommandEvent | None:
        """The first offset (from _pos) holding a complete frame that parses strictly.

        Same outcome as trying every offset from _pos on every call; only
        offsets whose frame became complete and offsets not judged before are
        looked at (see the class docstring).
        """
        buf, base, start = self._buf, self._base, self._base + self._pos
        stream_end = base + len(buf)
        waiting, waiting_set = self._waiting, self._waiting_set
        best, best_end = -1, 0
        best_ev: CommandEvent | None = None
        while waiting and waiting[0][0] <= stream_end:
            end, j = heapq.heappop(waiting)
            waiting_set.discard(j)
            if j < start:
                continue
            ev = parse_command(bytes(buf[j + 4 - base : end - base]), strict=True)
            if not isinstance(ev, BadCommand) and (best < 0 or j < best):
                best, best_end, best_ev = j, end, ev
        if best < 0:
            # offsets below _scan are not commands or still incomplete: judge the new ones in order
            j = max(self._scan, start)
            while j <= stream_end - 4:
                (length,) = struct.unpack_from(">I", buf, j - base)
                if length <= self.max_length:
                    end = j + 4 + length
                    if end > stream_end:
                        heapq.heappush(waiting, (end, j))
                        self._waiting_order.append(j)
                        waiting_set.add(j)
                    else:
                        ev = parse_command(bytes(buf[j + 4 - base : end - base]), strict=True)
                        if not isinstance(ev, BadCommand):
                            best, best_end, best_ev = j, end, ev
                            break
                j += 1
            self._scan = j
        if best_ev is not None:
            # every offset remembered lies before best_end (it was judged when the stream ended
            # before best_end), where the reader goes on in sync: forget them
            waiting.clear()
            self._waiting_order.clear()
            waiting_set.clear()
            self._synced = True
            self._pos = best_end - base
            if best > start:
                self._pending.append(best_ev)
                self.commands += 1
                return Junk(best - start)
            return best_ev
        order = self._waiting_order
        while order and (order[0] < start or order[0] not in waiting_set):
            order.popleft()
        keep_from = order[0] if order else max(start, stream_end - 3)
        if keep_from > start:
            self._pos = keep_from - base
            return Junk(keep_from - start)
        return None
