"""A Modbus device's answers (sans-I/O): its register image behind the request decoders.

* :class:`ModbusTarget`: one emulated device on the bus: its
  :class:`~hilsim.protocols.registers.RegisterImage` (the single live copy of its
  registers, updated by the device at the sensor's rate), its address (which a
  write may change), and the actions its writable registers trigger. It turns a
  request PDU into a response PDU, or into silence, as the real device does:
  01 for a function it lacks, 03 for a malformed request or a bad count or value,
  02 for an address outside the map, the map's code for a write to a read-only
  register. Requests are decoded and answered with the PDU codec of
  :mod:`hilsim.protocols.modbus_pdu`.
* :class:`TcpSession` and :class:`RtuSession`: one connection / one serial line:
  the request decoders of :mod:`hilsim.protocols.modbus` in, reply frames (bytes:
  MBAP / RTU ADUs of :mod:`hilsim.protocols.modbus_pdu`) out. TCP: a header that
  is not Modbus closes the session. RTU: a frame for another address is
  ignored, broadcast (address 0) writes are done without a reply.

Nothing a client sends raises out of this module: a failure inside is logged,
counted in ``stats.internal_errors`` and answered with 04 (or dropped).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable, Iterable, Mapping

from hilsim.protocols.codec import NEED_DATA
from hilsim.protocols.modbus import (
    CrcError,
    ForeignFrame,
    Malformed,
    NotModbusTcp,
    Request,
    RtuDialect,
    RtuRequestDecoder,
    TcpRequestDecoder,
)
from hilsim.protocols.modbus_pdu import (
    ReadRegisters,
    Response,
    decode_request,
    exception_response,
    mbap_frame,
    read_response,
    rtu_frame,
    write_response,
)
from hilsim.protocols.registers import (
    DEVICE_FAILURE,
    GATEWAY_NO_RESPONSE,
    ILLEGAL_FUNCTION,
    ILLEGAL_VALUE,
    ModbusError,
    Register,
    RegisterImage,
)

log = logging.getLogger("hilsim.links.modbus")  # the name its log lines always had

WriteAction = Callable[[Register, float], None]  # may raise ModbusError


@dataclass
class ModbusStats:
    """Counters of one server (a session's) or of one target (what it handled, over all its servers)."""

    requests: int = 0         # frames addressed to us and decoded
    replies: int = 0
    exceptions: int = 0       # replies that were exception responses
    ignored: int = 0          # RTU frames for other addresses
    broadcasts: int = 0
    crc_errors: int = 0       # RTU frames dropped for a bad CRC
    malformed: int = 0        # TCP headers that closed the connection; RTU: too short at silence, or
                              # undelimitable past MAX_RTU_ADU bytes
    dropped: int = 0          # replies not sent: the client did not read them
    throttled: int = 0        # times a client went over its request-rate budget
    internal_errors: int = 0  # our bugs (logged, answered 04)
    exception_codes: dict[int, int] = field(default_factory=dict)

    def count_exception(self, code: int) -> None:
        self.exceptions += 1
        self.exception_codes[code] = self.exception_codes.get(code, 0) + 1


class ModbusTarget:
    """One device on the bus: register image + address + write actions.

    image: the device's register image (read live on every request);
    device_id: its address (default: the map's); actions: on_write name ->
    callable(register, value in its unit) (may raise ModbusError); ``device_id``
    and ``store`` are built in. ``on_address_change(old, new)`` is called after
    an address write.
    """

    def __init__(self, image: RegisterImage, device_id: int | None = None, *,
                 actions: Mapping[str, WriteAction] | None = None, name: str = "",
                 on_address_change: Callable[[int, int], None] | None = None):
        self.image = image
        self.map = image.map
        self.name = name or image.map.name
        self.device_id = int(device_id if device_id is not None else image.map.device_id)
        if not 1 <= self.device_id <= 247:
            raise ValueError(f"{self.name}: device_id must be 1..247, got {self.device_id}")
        self.actions: dict[str, WriteAction] = dict(actions or {})
        missing = self.map.actions - set(self.actions) - {"device_id"}
        if missing:
            raise ValueError(f"{self.name}: map {self.map.name!r} needs write actions {sorted(missing)} "
                             "that the device does not provide")
        self.on_address_change = on_address_change
        self.stats = ModbusStats()
        self._functions = frozenset(self.map.read_functions) | frozenset(self.map.write_functions)
        for r in self.map.registers:
            if r.on_write == "device_id":
                image.store(r, self.device_id)

    silent = False  # fault injection: a dead sensor answers nothing (TCP: gateway exception 0B)

    def answers(self, unit: int, tcp: bool) -> bool:
        """Whether a request to address ``unit`` is ours (0 on RTU is broadcast, not 'ours')."""
        if self.silent:
            return False
        if unit == self.device_id or unit == self.map.transparent_id:
            return True
        return tcp and unit in (0, 255)

    def handle(self, unit: int, pdu: bytes, *, broadcast: bool = False) -> Response | None:
        """The response (to address ``unit``) to request ``pdu`` (function code + data);
        None when nothing is to be sent (broadcast)."""
        self.stats.requests += 1
        fc = pdu[0] if pdu else 0
        try:
            response = self._dispatch(fc, pdu)
        except ModbusError as exc:
            response = exception_response(fc, exc.code)
        except Exception:  # our bug: log it, answer "device failure", keep serving
            self.stats.internal_errors += 1
            log.exception("%s: error handling request %s", self.name, pdu.hex())
            response = exception_response(fc, DEVICE_FAILURE)
        if broadcast:
            self.stats.broadcasts += 1
            return None
        reply = Response(unit, response)
        if reply.is_exception:
            self.stats.count_exception(reply.exception_code)
        self.stats.replies += 1
        return reply

    def _dispatch(self, fc: int, pdu: bytes) -> bytes:
        """The response PDU; raises ModbusError for an exception response."""
        if fc not in self._functions:
            raise ModbusError(ILLEGAL_FUNCTION, f"function {fc:#04x}")
        req = decode_request(pdu)  # 01 for a function listed in the map that is not served here
        if isinstance(req, ReadRegisters):
            return read_response(fc, self.image.read(req.address, req.count))
        self._write(req.address, list(req.values))
        return write_response(req)

    def _write(self, address: int, words: list[int]) -> None:
        writes = self.image.check_write(address, words)
        for reg, value in writes:
            if reg.on_write == "device_id":
                self.set_device_id(int(value))
                continue
            if reg.on_write != "store":
                self.actions[reg.on_write](reg, value)
            self.image.store(reg, value)

    def set_device_id(self, new: int) -> None:
        """Move the device to address ``new`` (1..247); the address registers follow."""
        if not 1 <= new <= 247:
            raise ModbusError(ILLEGAL_VALUE, f"address {new} outside 1..247")
        old, self.device_id = self.device_id, int(new)
        for r in self.map.registers:
            if r.on_write == "device_id":
                self.image.store(r, self.device_id)
        if old != new:
            log.info("%s: device address %d -> %d", self.name, old, new)
            if self.on_address_change is not None:
                self.on_address_change(old, new)


class TcpSession:
    """Modbus TCP for one connection (sans-I/O).

    ``receive_data(bytes)`` then ``process(n)`` -> reply frames; ``closed`` with
    ``close_reason`` once the peer sent something that is not Modbus TCP.
    """

    def __init__(self, target: ModbusTarget, stats: ModbusStats | None = None):
        self.target = target
        self.stats = stats if stats is not None else ModbusStats()
        self.decoder = TcpRequestDecoder()

    @property
    def buffer(self) -> bytearray:
        """An unfinished ADU."""
        return self.decoder.buffer

    @property
    def closed(self) -> bool:
        return self.decoder.closed

    @property
    def close_reason(self) -> str:
        return self.decoder.close_reason

    def receive_data(self, data: bytes) -> None:
        self.decoder.receive_data(data)

    def has_frame(self) -> bool:
        """A complete frame is waiting."""
        return self.decoder.frame_length() > 0

    def process(self, max_frames: int = 1 << 30) -> list[bytes]:
        """Answer up to ``max_frames`` complete frames from the buffer."""
        out: list[bytes] = []
        for _ in range(max_frames):
            try:
                ev = self.decoder.next_event()
                if ev is NEED_DATA:
                    break
                if isinstance(ev, NotModbusTcp):
                    self.stats.malformed += 1
                    break
                assert isinstance(ev, Request)
                unit, pdu = ev.unit, ev.pdu
                self.stats.requests += 1
                if self.target.answers(unit, tcp=True):
                    resp = self.target.handle(unit, pdu)
                else:  # as a gateway whose serial device does not answer
                    resp = Response(unit, exception_response(pdu[0], GATEWAY_NO_RESPONSE))
                if resp is not None:
                    self.stats.replies += 1
                    if resp.is_exception:
                        self.stats.count_exception(resp.exception_code)
                    out.append(mbap_frame(ev.transaction_id, resp.unit, resp.pdu))
            except Exception:  # our bug: keep the connection and the server
                self.stats.internal_errors += 1
                log.exception("%s: error answering a request", self.target.name)
        return out


class RtuSession:
    """Modbus RTU for one serial line, any number of targets on it (sans-I/O).

    ``receive_data(bytes)`` -> the replies, in order, to every frame the length
    rules delimit (any number per call, however the bytes were cut: the replies
    depend only on the byte stream and where the line went idle); ``silence()``
    (the line idle for 3.5 characters) -> the replies to what that ends. The
    framing and its resynchronisation are :class:`~hilsim.protocols.modbus.RtuRequestDecoder`'s.
    Another protocol on the line (:meth:`add_dialect`: the KELLER bus) is told by function code
    and its frames go to its handlers (each returns its reply frame or None).
    """

    def __init__(self, targets: Iterable[ModbusTarget] = (), stats: ModbusStats | None = None):
        self.targets = list(targets)
        self.stats = stats if stats is not None else ModbusStats()
        self.decoder = RtuRequestDecoder()
        self.foreign: list[Callable[[bytes], bytes | None]] = []

    def add_dialect(self, dialect: RtuDialect, handler: Callable[[bytes], bytes | None]) -> None:
        """Serve ``dialect`` beside Modbus on this line: its frames go to ``handler``."""
        self.decoder.dialect = dialect
        self.foreign.append(handler)

    def remove_dialect(self, handler: Callable[[bytes], bytes | None]) -> None:
        if handler in self.foreign:
            self.foreign.remove(handler)
        if not self.foreign:
            self.decoder.dialect = None

    @property
    def buffer(self) -> bytearray:
        """Bytes of an unfinished (or undelimitable) frame."""
        return self.decoder.buffer

    @property
    def pending(self) -> bool:
        """Bytes of an unfinished (or undelimitable) frame are buffered."""
        return self.decoder.buffered_bytes > 0

    @property
    def resyncing(self) -> bool:
        """A frame failed its CRC (or ran past MAX_RTU_ADU) since the line was last idle: the
        session hunts for the next good frame until :meth:`silence` (call it when the line
        goes idle, even with nothing buffered)."""
        return self.decoder.resyncing

    def receive_data(self, data: bytes) -> list[bytes]:
        """Take bytes off the line; the replies to the frames they complete, in order."""
        self.decoder.receive_data(data)
        return self._answer()

    def silence(self) -> list[bytes]:
        """The line went idle: whatever is buffered ends there (at a frame boundary it is
        one frame); the next byte starts a frame."""
        self.decoder.silence()
        return self._answer()

    def _answer(self) -> list[bytes]:
        out: list[bytes] = []
        try:
            for _ in range(len(self.decoder.buffer) + 2):  # bounded: each event consumes bytes
                ev = self.decoder.next_event()
                if ev is NEED_DATA:
                    break
                if isinstance(ev, CrcError):
                    self.stats.crc_errors += 1
                elif isinstance(ev, Malformed):
                    self.stats.malformed += 1
                elif isinstance(ev, ForeignFrame):
                    replies = [r for r in (h(ev.frame) for h in list(self.foreign)) if r]
                    out += replies[:1]  # one device answers (two on the transparent address would collide)
                else:
                    reply = self._dispatch(ev.unit, ev.pdu)
                    if reply is not None:
                        out.append(reply)
        except Exception:  # our bug: drop what we have, keep serving
            self.stats.internal_errors += 1
            log.exception("rtu: framing failed on %s", self.decoder.buffer.hex())
            self.decoder.clear()
        return out

    def _dispatch(self, unit: int, pdu: bytes) -> bytes | None:
        try:
            if unit == 0:
                for t in self.targets:
                    t.handle(0, pdu, broadcast=True)
                self.stats.broadcasts += 1
                return None
            for t in self.targets:
                if t.answers(unit, tcp=False):
                    resp = t.handle(unit, pdu)
                    self.stats.requests += 1
                    if resp is None:
                        return None
                    self.stats.replies += 1
                    if resp.is_exception:
                        self.stats.count_exception(resp.exception_code)
                    return rtu_frame(resp.unit, resp.pdu)
            self.stats.ignored += 1
        except Exception:  # our bug
            self.stats.internal_errors += 1
            log.exception("rtu: error answering %d %s", unit, pdu.hex())
        return None


__all__ = ["ModbusStats", "ModbusTarget", "RtuSession", "TcpSession", "WriteAction"]
