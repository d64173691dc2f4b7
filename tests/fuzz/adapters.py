"""One way to drive every decoder: the codec contract (:mod:`hilsim.protocols.codec`).

:func:`feed` hands bytes to ``receive_data`` and drains ``next_event`` until NEED_DATA,
taking what the decoder wants sent back (``data_to_send()``) as :class:`Reply` events.
Decoders of whole units read them off the byte stream through a link:
:class:`Datagrams` (a 2-byte big-endian length before each; ``receive_data(datagram)``)
or :class:`CanRecords` (SocketCAN's 16-byte ``struct can_frame``; ``receive_frame(frame,
now)``, the clock 1 ms per frame plus the record's pause). The only other shapes: the DDF
reader's ProtocolError (raised by design on a broken stream) becomes :class:`PeerError`,
and the Modbus sessions answer requests (:func:`tcp_feed`, :func:`rtu_feed`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from hilsim.protocols import ddf
from hilsim.protocols import modbus_device as mb
from hilsim.protocols.can import CanFrame
from hilsim.protocols.codec import NEED_DATA
from hilsim.protocols.registers import RegisterImage, load_map
from hilsim.resources import data_path
from tests.fuzz.links import CanRecords, Datagrams

Events = list[Any]


@dataclass(frozen=True)
class Reply:
    """Bytes the decoder asks to send back to the peer."""

    data: bytes


@dataclass(frozen=True)
class Closed:
    """The decoder closed the connection (Modbus TCP: the peer is not speaking Modbus)."""

    reason: str


@dataclass(frozen=True)
class PeerError:
    """A ProtocolError the codec raises by design (DDF stream); the reader is dead after it."""

    reason: str


class PerFrame:
    """A stateless per-frame decoding function (``vesc_can.decode``) as a decoder of frames."""

    buffered_bytes = 0

    def __init__(self, decode: Callable[[CanFrame], Any]) -> None:
        self.decode, self._events = decode, []  # type: ignore[var-annotated]

    def receive_frame(self, frame: CanFrame, now: float) -> None:
        if (ev := self.decode(frame)) is not None:
            self._events.append(ev)

    def next_event(self) -> Any:
        return self._events.pop(0) if self._events else NEED_DATA


class Driven:
    """A decoder as a peer finds it, behind its link; ``then(event)`` adds a decoded message
    to each event (events become ``(event, then(event))``)."""

    def __init__(self, decoder: Any, link: Datagrams | CanRecords | None = None,
                 then: Callable[[Any], Any] | None = None) -> None:
        self.decoder, self.link, self.then = decoder, link, then
        self.now, self.dead = 0.0, False


def driven(factory: Callable[[], Any], link: type | None = None,
           then: Callable[[Any], Any] | None = None) -> Callable[[], Driven]:
    return lambda: Driven(factory(), link() if link else None, then)


def buffered(d: Driven) -> int:
    return d.decoder.buffered_bytes + (d.link.buffered_bytes if d.link else 0)


def _drain(d: Driven, limit: int) -> Events:
    out: Events = []
    send = getattr(d.decoder, "data_to_send", None)
    try:
        for _ in range(limit):
            ev = d.decoder.next_event()
            if send is not None and (data := send()):
                out.append(Reply(data))
            if ev is NEED_DATA:
                return out
            out.append(ev if d.then is None else (ev, d.then(ev)))
            if isinstance(ev, ddf.EndOfStream):
                d.dead = True
                return out
    except ddf.ProtocolError as exc:
        d.dead = True
        return out + [PeerError(str(exc))]
    raise AssertionError("decoder did not settle: more events than input bytes")


def feed(d: Driven, data: bytes) -> Events:
    """The bytes to the decoder (through its link), then every event it has."""
    if d.dead or not data:
        return []
    if d.link is None:
        d.decoder.receive_data(data)
        return _drain(d, 4 * len(data) + 1000)
    out: Events = []
    for unit, pause in d.link.units(data):
        if isinstance(unit, CanFrame):
            d.now += 0.001 + pause
            d.decoder.receive_frame(unit, d.now)
        else:
            d.decoder.receive_data(unit)
        out += _drain(d, 4 * len(data) + 1000)
    return out


def end(d: Driven) -> Events:
    """The end of the input (DDF: EOF is ``receive_data(b"")``)."""
    if d.dead:
        return []
    d.decoder.receive_data(b"")
    out = _drain(d, 10)
    d.dead = True
    return out


# ----------------------------------------------------------------- Modbus (device side, answers)

KELLER_MAP = "keller_serie30.toml"
KELLER_TRANSPARENT = 250  # every Keller answers it, whatever a garbage write did to its address


def keller_target() -> mb.ModbusTarget:
    image = RegisterImage(load_map(data_path("protocols", KELLER_MAP)))
    image.update({"pressure": 1.2e5, "temperature": 290.0})
    return mb.ModbusTarget(image, actions={"set_zero": lambda register, value: None})


def _checked(session: Any, replies: list[bytes]) -> Events:
    targets = getattr(session, "targets", None) or [session.target]
    if session.stats.internal_errors or any(t.stats.internal_errors for t in targets):
        raise AssertionError("Modbus: an internal error was caught and logged (see the log above)")
    return [Reply(r) for r in replies]


def tcp_feed(s: mb.TcpSession, data: bytes) -> Events:
    was_closed = s.closed
    s.receive_data(data)
    out = _checked(s, s.process())
    return out + [Closed(s.close_reason)] if s.closed and not was_closed else out


def rtu_feed(s: mb.RtuSession, data: bytes) -> Events:
    return _checked(s, s.receive_data(data))


def rtu_silence(s: mb.RtuSession) -> Events:
    return _checked(s, s.silence())
