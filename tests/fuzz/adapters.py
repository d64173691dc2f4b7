"""How to drive each decoder: a factory, ``feed(decoder, data) -> events``, what it retains.

Each feed hands the bytes to the codec with its own API and drains it
(``receive_data`` + ``next_event`` until NEED_DATA, ``receive``, ``process``).
Bytes the decoder wants sent back come out as :class:`Reply` events, a
connection it closes as :class:`Closed`, the DDF reader's ProtocolError (raised
by design on a broken stream) as :class:`PeerError`. CAN decoders take frames:
:class:`CanRecords` makes them from SocketCAN's 16-byte ``struct can_frame``
records; the ARIS frame assembler takes datagrams: :class:`Datagrams` reads
them with a 2-byte big-endian length before each.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import struct
import types
import typing
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from hilsim.links import modbus as mb
from hilsim.protocols import aris, ddf, ddf_commands, dronecan, oculus, slcan, socketcand, vesc_can, vesc_uart, vrcsr
from hilsim.protocols.can import CanFrame
from hilsim.protocols.registers import RegisterImage, load_map
from hilsim.resources import data_path

Events = list[Any]


# ----------------------------------------------------------------- events the adapters add


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


def same(a: Any, b: Any) -> bool:
    """Equality for events, with NaN equal to NaN (decoded floats often are NaN)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"))
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if dataclasses.is_dataclass(a):
        return all(same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    return bool(a == b)


@dataclass(frozen=True, eq=False)
class Canon:
    """An event compared with :func:`same`."""

    event: Any

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Canon) and same(self.event, other.event)

    __hash__ = None  # type: ignore[assignment]


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except Exception:  # noqa: BLE001 - a hint we cannot resolve is not checked
        return {}


def well_typed(value: Any, hint: Any) -> bool:
    """Whether ``value`` fits its annotation (str, bytes, int, float, bool, None, unions, tuples and
    dataclasses are checked; anything else, numpy arrays included, passes)."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return any(well_typed(value, a) for a in typing.get_args(hint))
    if hint is type(None):
        return value is None
    if hint is float:
        return isinstance(value, (float, int)) and not isinstance(value, bool)
    if hint in (int, str, bytes, bool):
        return isinstance(value, hint)
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(well_typed(v, args[0]) for v in value)
        return len(args) == len(value) and all(well_typed(v, a) for v, a in zip(value, args))
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return isinstance(value, hint) and not badly_typed(value)
    return True


def badly_typed(event: Any) -> str:
    """The first field of a dataclass event (or of one in a tuple) whose value does not fit its
    annotation, as ``Class.field=value``; "" if none."""
    if isinstance(event, tuple):
        return next((bad for e in event if (bad := badly_typed(e))), "")
    if not dataclasses.is_dataclass(event) or isinstance(event, type):
        return ""
    hints = _hints(type(event))
    for f in dataclasses.fields(event):
        value = getattr(event, f.name)
        if f.name in hints and not well_typed(value, hints[f.name]):
            return f"{type(event).__name__}.{f.name}={value!r}"
    return ""


# ----------------------------------------------------------------- draining


def _drain(next_event: Callable[[], Any], need_data: Any, limit: int) -> Events:
    out: Events = []
    for _ in range(limit):
        ev = next_event()
        if ev is need_data or ev is None:
            return out
        out.append(ev)
    raise AssertionError("decoder did not settle: more events than input bytes")


def _limit(data: bytes) -> int:
    return 4 * len(data) + 1000


# ----------------------------------------------------------------- DDF stream (client side)


class DdfClient:
    """A DdfReader and whether it already raised (the caller then drops the stream)."""

    def __init__(self) -> None:
        self.reader = ddf.DdfReader()
        self.dead = False
        self.ended = False


def _ddf_drain(c: DdfClient, limit: int) -> Events:
    out: Events = []
    try:
        for _ in range(limit):
            ev = c.reader.next_event()
            if ev is ddf.NEED_DATA:
                return out
            out.append(ev)
            if isinstance(ev, ddf.EndOfStream):
                return out
    except ddf.ProtocolError as exc:
        c.dead = True
        return out + [PeerError(str(exc))]
    raise AssertionError("DdfReader did not settle")


def ddf_feed(c: DdfClient, data: bytes) -> Events:
    if c.dead or c.ended or not data:
        return []
    c.reader.receive_data(data)
    return _ddf_drain(c, _limit(data))


def ddf_end(c: DdfClient) -> Events:
    if c.dead or c.ended:
        return []
    c.ended = True
    c.reader.receive_data(b"")
    return _ddf_drain(c, 10)


# ----------------------------------------------------------------- DDF command lines (server side)


def lines_feed(d: ddf_commands.CommandDecoder, data: bytes) -> Events:
    d.receive_data(data)
    return _drain(d.next_event, ddf.NEED_DATA, _limit(data))


# ----------------------------------------------------------------- Oculus (sonar side: client -> sonar)


def oculus_feed(r: oculus.OculusReader, data: bytes) -> Events:
    r.receive_data(data)
    return _drain(r.next_event, oculus.NEED_DATA, _limit(data))


# ----------------------------------------------------------------- ARIS command channel (sonar side)


def aris_feed(r: aris.CommandReader, data: bytes) -> Events:
    r.receive_data(data)
    return _drain(r.next_event, None, _limit(data))


# ----------------------------------------------------------------- ARIS frame stream (client side, UDP)


class Datagrams:
    """Bytes -> datagrams, each a 2-byte big-endian length then that many bytes."""

    def __init__(self) -> None:
        self._partial = bytearray()

    @property
    def buffered_bytes(self) -> int:
        return len(self._partial)

    def datagrams(self, data: bytes) -> list[bytes]:
        self._partial += data
        out, pos = [], 0
        while len(self._partial) - pos >= 2:
            n = int.from_bytes(self._partial[pos : pos + 2], "big")
            if len(self._partial) - pos - 2 < n:
                break
            out.append(bytes(self._partial[pos + 2 : pos + 2 + n]))
            pos += 2 + n
        del self._partial[:pos]
        return out


def datagram(d: bytes) -> bytes:
    return len(d).to_bytes(2, "big") + d


class ArisClient:
    def __init__(self) -> None:
        self.link = Datagrams()
        self.assembler = aris.FrameAssembler()


def assembler_feed(c: ArisClient, data: bytes) -> Events:
    out: Events = []
    for d in c.link.datagrams(data):
        out += c.assembler.receive_datagram(d)
    return out


def assembler_buffered(c: ArisClient) -> int:
    return c.link.buffered_bytes + len(c.assembler._data) + len(c.assembler._got)


# ----------------------------------------------------------------- socketcand (server side)


def socketcand_feed(s: socketcand.SocketcandServer, data: bytes) -> Events:
    s.receive_data(data)
    out: Events = []
    for _ in range(_limit(data)):
        ev = s.next_event()
        out += [Reply(r) for r in s.replies()]
        if ev is socketcand.NEED_DATA:
            return out
        out.append(ev)
    raise AssertionError("socketcand did not settle")


# ----------------------------------------------------------------- slcan (adapter side)


def slcan_feed(a: slcan.SlcanAdapter, data: bytes) -> Events:
    a.receive_data(data)
    out: Events = []
    for _ in range(_limit(data)):
        ev = a.next_event()
        sent = a.data_to_send()
        if sent:
            out.append(Reply(sent))
        if ev is slcan.NEED_DATA:
            return out
        out.append(ev)
    raise AssertionError("slcan did not settle")


# ----------------------------------------------------------------- VESC UART (ESC side)


def vesc_uart_feed(d: vesc_uart.PacketDecoder, data: bytes) -> Events:
    d.receive_data(data)
    payloads = _drain(d.next_event, vesc_uart.NEED_DATA, _limit(data))
    return [(p, vesc_uart.decode_command(p)) for p in payloads]


# ----------------------------------------------------------------- VRCSR (thruster side)


def vrcsr_feed(d: vrcsr.PacketDecoder, data: bytes) -> Events:
    d.receive_data(data)
    packets = _drain(d.next_event, vrcsr.NEED_DATA, _limit(data))
    return [(p, vrcsr.PropulsionCommand.decode(p.payload)) for p in packets]


# ----------------------------------------------------------------- CAN frames from bytes


CAN_EFF_FLAG = 0x80000000


CAN_RTR_FLAG = 0x40000000


CAN_ERR_FLAG = 0x20000000


CAN_RECORD = struct.Struct("<IBxBx8s")  # struct can_frame: can_id, len, __pad, __res0, len8_dlc, data[8]
PAUSE_UNIT = 0.02  # [s] per unit of __res0, read here as the pause before the frame


CAN_RECORD_SIZE = CAN_RECORD.size


def can_record(frame: CanFrame) -> bytes:
    """A frame as SocketCAN's ``struct can_frame`` (can_id little-endian, as on x86)."""
    can_id = frame.arbitration_id | (CAN_EFF_FLAG if frame.is_extended else 0) | (
        CAN_RTR_FLAG if frame.is_remote else 0)
    return CAN_RECORD.pack(can_id, frame.dlc, 0, frame.data.ljust(8, b"\0"))


class CanRecords:
    """Bytes -> CanFrames. Error frames and lengths over 8 are dropped (the kernel refuses them).

    ``__res0`` (0 from the kernel) is read as the bus's silence before the frame in
    PAUSE_UNIT steps (:attr:`pauses`), so a fuzzer can reach the receivers' timeouts.
    """

    def __init__(self) -> None:
        self._partial = bytearray()
        self.dropped = 0
        self.pauses: list[float] = []  # [s] before each frame of the last frames() call

    @property
    def buffered_bytes(self) -> int:
        return len(self._partial)

    def frames(self, data: bytes) -> list[CanFrame]:
        self._partial += data
        n = len(self._partial) // CAN_RECORD_SIZE
        out = []
        self.pauses = []
        for i in range(n):
            can_id, length, pause, payload = CAN_RECORD.unpack_from(self._partial, i * CAN_RECORD_SIZE)
            if can_id & CAN_ERR_FLAG or length > 8:
                self.dropped += 1
                continue
            self.pauses.append(pause * PAUSE_UNIT)
            ext, rtr = bool(can_id & CAN_EFF_FLAG), bool(can_id & CAN_RTR_FLAG)
            ident = can_id & (0x1FFFFFFF if ext else 0x7FF)
            if rtr:
                out.append(CanFrame(ident, b"", ext, True, length))
            else:
                out.append(CanFrame(ident, bytes(payload[:length]), ext))
        del self._partial[: n * CAN_RECORD_SIZE]
        return out


class VescCanNode:
    def __init__(self) -> None:
        self.link = CanRecords()


def vesc_can_feed(n: VescCanNode, data: bytes) -> Events:
    out: Events = []
    for f in n.link.frames(data):
        ev = vesc_can.decode(f)
        if ev is not None:
            out.append(ev)
    return out


# ----------------------------------------------------------------- DroneCAN (ESC side)


class DroneCanNode:
    """TransferReceiver behind a CAN record adapter; the clock advances 1 ms per frame, plus its pause."""

    def __init__(self) -> None:
        self.link = CanRecords()
        self.rx = dronecan.TransferReceiver()
        self.now = 0.0


def dronecan_feed(n: DroneCanNode, data: bytes) -> Events:
    out: Events = []
    for f, pause in zip(n.link.frames(data), n.link.pauses):
        n.now += 0.001 + pause
        t = n.rx.receive(f, n.now)
        if t is not None:
            out.append((t, dronecan.decode_message(t.dtid, t.payload)))
    return out


def dronecan_buffered(n: DroneCanNode) -> int:
    return n.link.buffered_bytes + sum(len(s.data) for s in n.rx._sessions.values())


# ----------------------------------------------------------------- Modbus (device side, through pymodbus)


KELLER_MAP = "keller_serie30.toml"


KELLER_TRANSPARENT = 250  # every Keller answers it, whatever a garbage write did to its address


def keller_target() -> mb.ModbusTarget:
    image = RegisterImage(load_map(data_path("protocols", KELLER_MAP)))
    image.update({"pressure": 1.2e5, "temperature": 290.0})
    return mb.ModbusTarget(image, actions={"set_zero": lambda register, value: None})


def _internal(stats: mb.ModbusStats, target: mb.ModbusTarget) -> None:
    if stats.internal_errors or target.stats.internal_errors:
        raise AssertionError("Modbus: an internal error was caught and logged (see the log above)")


class ModbusTcpConnection:
    def __init__(self) -> None:
        self.target = keller_target()
        self.session = mb.TcpSession(self.target)
        self.told = False


def tcp_feed(c: ModbusTcpConnection, data: bytes) -> Events:
    c.session.receive_data(data)
    out: Events = [Reply(r) for r in c.session.process()]
    if c.session.closed and not c.told:
        c.told = True
        out.append(Closed(c.session.close_reason))
    _internal(c.session.stats, c.target)
    return out


class ModbusRtuLine:
    def __init__(self) -> None:
        self.target = keller_target()
        self.session = mb.RtuSession([self.target])


def rtu_feed(line: ModbusRtuLine, data: bytes) -> Events:
    out: Events = [Reply(r) for r in line.session.receive_data(data)]
    _internal(line.session.stats, line.target)
    return out


def rtu_silence(line: ModbusRtuLine) -> Events:
    out: Events = [Reply(r) for r in line.session.silence()]
    _internal(line.session.stats, line.target)
    return out
