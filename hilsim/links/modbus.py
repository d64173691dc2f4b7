"""Modbus TCP and Modbus RTU (on a pty) servers around one shared register image.

Layers, innermost first:

* :class:`ModbusTarget`: one emulated device on the bus: its
  :class:`~hilsim.protocols.registers.RegisterImage` (the single live copy of its
  registers, updated by the device at the sensor's rate), its address (which a
  write may change), and the actions its writable registers trigger. It turns a
  request PDU into a response PDU, or into silence, as the real device does:
  01 for a function it lacks, 03 for a malformed request or a bad count or value,
  02 for an address outside the map, the map's code for a write to a read-only
  register. Requests are decoded by pymodbus's PDU decoder and answered with
  pymodbus's response classes.
* :class:`TcpSession` and :class:`RtuSession`: sans-I/O framing (bytes in, reply
  frames out) with pymodbus's ``FramerSocket`` (MBAP) and ``FramerRTU`` (CRC,
  encoding). TCP: a header that is not Modbus (protocol id != 0, length outside
  2..254) closes the connection. RTU: requests are delimited by the length their
  function code defines (:func:`rtu_request_length`), so frames that arrive
  back to back are each answered, in order; a frame with a bad CRC is dropped in
  silence (and the next good frame found behind it), a frame for another address
  is ignored, broadcast (address 0) writes are done without a reply, and what the
  length rules cannot delimit is taken as one frame when the line has been idle
  for 3.5 characters (as a real device does).
* :class:`ModbusTcpServer` (on :class:`hilsim.links.tcp.TcpServer`: client limit
  with a log line, per-client bounded queues) and :class:`ModbusRtuServer` (on
  :class:`hilsim.links.pty.PtyLink`: a stable path, replies paced at the baud
  rate, survives the client closing and reopening the port).

Why not pymodbus's own server classes: each keeps its own copy of the registers
(a TCP and an RTU server would hold two states), the RTU one opens a serial
port itself (a pty pair and a relay for the baud pacing) and hunts past frames
with an unknown function instead of answering 01, the device address cannot
change at run time, and there is no client limit. pymodbus's framers and PDU
classes do the wire encoding here; the transport and the device's behaviour
are ours. Nothing a client sends raises out of this module: a failure inside
is logged, counted in ``stats.internal_errors`` and answered with 04.
"""

from __future__ import annotations

import asyncio
import logging
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Mapping

from pymodbus.framer import FramerRTU, FramerSocket
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersResponse,
    ReadInputRegistersResponse,
    WriteMultipleRegistersResponse,
    WriteSingleRegisterResponse,
)

from hilsim.links.pty import PtyLink
from hilsim.links.tcp import Client, TcpServer
from hilsim.protocols.registers import (
    DEVICE_FAILURE,
    GATEWAY_NO_RESPONSE,
    ILLEGAL_FUNCTION,
    ILLEGAL_VALUE,
    ModbusError,
    Register,
    RegisterImage,
)

log = logging.getLogger(__name__)

WriteAction = Callable[[Register, float], None]  # may raise ModbusError
MAX_RTU_ADU = 256
MAX_TCP_LENGTH = 254  # MBAP length field: unit id + PDU (max 253 bytes)
_DECODER = DecodePDU(True)  # request decoder (server side); stateless


RTU_NEED_MORE = 0      # rtu_request_length: more bytes are needed to tell
RTU_UNDELIMITED = -1   # rtu_request_length: the length rules cannot tell (ends at silence)
# Request ADU lengths (address + PDU + CRC) by function code, from the Modbus application
# protocol spec V1.1b3 (section 6) and its serial line spec; pymodbus 3.16's request classes
# (rtu_frame_size, rtu_byte_count_pos) agree where both define one.
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

    Unlike pymodbus: 08/00 is taken as 8 bytes only when those 8 bytes carry a good
    CRC (the spec allows any data; masters send 2 bytes), the reserved 08
    sub-functions are not delimited, and a function code with the top bit set (an
    exception response, not a request) is not taken as 5 bytes.
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
        return 8 if _crc_ok(buf, pos, pos + 8) else RTU_UNDELIMITED
    if fc == 0x2B:
        if avail < 3:
            return RTU_NEED_MORE
        return 7 if buf[pos + 2] == 0x0E else RTU_UNDELIMITED  # read device identification
    return RTU_UNDELIMITED


_CRC_TABLE = tuple(FramerRTU.crc16_table)


def _crc_ok(buf: bytes | bytearray, start: int, end: int) -> bool:
    """``buf[start:end]`` ends with the CRC-16/MODBUS of the bytes before it (low byte first).
    pymodbus's table, in place: about twice as fast as ``FramerRTU.compute_CRC`` on a
    slice, which counts while hunting through garbage (a CRC per candidate start)."""
    crc, table = 0xFFFF, _CRC_TABLE
    for i in range(start, end - 2):
        crc = (crc >> 8) ^ table[(crc ^ buf[i]) & 0xFF]
    return crc == buf[end - 2] | (buf[end - 1] << 8)


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

    def handle(self, unit: int, pdu: bytes, *, broadcast: bool = False) -> ModbusPDU | None:
        """The response PDU (dev_id = ``unit``) to request ``pdu`` (function code + data);
        None when nothing is to be sent (broadcast)."""
        self.stats.requests += 1
        fc = pdu[0] if pdu else 0
        try:
            response = self._dispatch(fc, pdu)
        except ModbusError as exc:
            response = ExceptionResponse(fc & 0x7F, exc.code)
        except Exception:  # our bug: log it, answer "device failure", keep serving
            self.stats.internal_errors += 1
            log.exception("%s: error handling request %s", self.name, pdu.hex())
            response = ExceptionResponse(fc & 0x7F, DEVICE_FAILURE)
        if broadcast:
            self.stats.broadcasts += 1
            return None
        if isinstance(response, ExceptionResponse):
            self.stats.count_exception(response.exception_code)
        self.stats.replies += 1
        response.dev_id = unit
        return response

    def _dispatch(self, fc: int, pdu: bytes) -> ModbusPDU:
        if fc not in self._functions:
            raise ModbusError(ILLEGAL_FUNCTION, f"function {fc:#04x}")
        if fc in (3, 4, 6):
            if len(pdu) != 5:
                raise ModbusError(ILLEGAL_VALUE, f"function {fc}: PDU of {len(pdu)} bytes")
        elif fc == 16:
            if len(pdu) < 6:
                raise ModbusError(ILLEGAL_VALUE, "function 16: short PDU")
            count, nbytes = struct.unpack(">HB", pdu[3:6])
            if not 1 <= count <= 123 or nbytes != 2 * count or len(pdu) != 6 + nbytes:
                raise ModbusError(ILLEGAL_VALUE, f"function 16: count {count}, byte count {nbytes}")
        else:  # a function listed in the map that this server does not implement
            raise ModbusError(ILLEGAL_FUNCTION, f"function {fc:#04x} not implemented")
        req = _DECODER.decode(pdu)
        if req is None:  # pymodbus refused it (count out of 1..125)
            raise ModbusError(ILLEGAL_VALUE, "request does not decode")
        if fc in (3, 4):
            regs = self.image.read(req.address, req.count)
            cls = ReadHoldingRegistersResponse if fc == 3 else ReadInputRegistersResponse
            return cls(registers=regs)
        values = list(req.registers)
        self._write(req.address, values)
        if fc == 6:
            return WriteSingleRegisterResponse(address=req.address, registers=values)
        return WriteMultipleRegistersResponse(address=req.address, count=len(values))

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
    """Modbus TCP framing for one connection (sans-I/O).

    ``receive_data(bytes)`` then ``process(n)`` -> reply frames; ``closed`` with
    ``close_reason`` once the peer sent something that is not Modbus TCP.
    """

    def __init__(self, target: ModbusTarget, stats: ModbusStats | None = None):
        self.target = target
        self.stats = stats if stats is not None else ModbusStats()
        self.framer = FramerSocket(_DECODER)
        self.buffer = bytearray()
        self.closed = False
        self.close_reason = ""

    def receive_data(self, data: bytes) -> None:
        if not self.closed:
            self.buffer += data

    def _frame_length(self) -> int:
        """Length of the complete frame at the buffer's head, 0 if incomplete;
        closes the session on a header that is not Modbus TCP."""
        buf = self.buffer
        if len(buf) < 7:
            return 0
        pid, length = struct.unpack_from(">HH", buf, 2)
        if pid != 0 or not 2 <= length <= MAX_TCP_LENGTH:
            self.closed = True
            self.close_reason = f"not Modbus TCP (protocol id {pid}, length {length})"
            self.stats.malformed += 1
            self.buffer.clear()
            return 0
        return 6 + length if len(buf) >= 6 + length else 0

    def has_frame(self) -> bool:
        """A complete frame is waiting."""
        return not self.closed and self._frame_length() > 0

    def process(self, max_frames: int = 1 << 30) -> list[bytes]:
        """Answer up to ``max_frames`` complete frames from the buffer."""
        out: list[bytes] = []
        for _ in range(max_frames):
            n = self._frame_length()
            if not n:
                break
            frame = bytes(self.buffer[:n])
            del self.buffer[:n]
            try:
                _, unit, tid, pdu = self.framer.decode(frame)
                self.stats.requests += 1
                if self.target.answers(unit, tcp=True):
                    resp = self.target.handle(unit, pdu)
                else:  # as a gateway whose serial device does not answer
                    resp = ExceptionResponse(pdu[0] & 0x7F, GATEWAY_NO_RESPONSE, device_id=unit)
                if resp is not None:
                    self.stats.replies += 1
                    if isinstance(resp, ExceptionResponse):
                        self.stats.count_exception(resp.exception_code)
                    resp.transaction_id = tid
                    out.append(self.framer.buildFrame(resp))
            except Exception:  # our bug: keep the connection and the server
                self.stats.internal_errors += 1
                log.exception("%s: error framing %s", self.target.name, frame.hex())
        return out


class RtuSession:
    """Modbus RTU framing for one serial line, any number of targets on it (sans-I/O).

    ``receive_data(bytes)`` -> the replies, in order, to every frame the length
    rules delimit (any number per call, however the bytes were cut: the replies
    depend only on the byte stream and where the line went idle); ``silence()``
    (the line idle for 3.5 characters) -> the rest of the buffer taken as one
    frame (an unknown function, a garbled or cut frame).

    The length of a request comes from its function code (:func:`rtu_request_length`),
    not from pymodbus's ``FramerRTU.decode``, which reports the whole buffer as
    used once it finds a frame (so of two frames in one read only the first was
    answered) and drops the whole buffer on a bad CRC. A frame whose CRC fails is
    dropped and counted; then, until a frame checks out or the line goes idle, the
    session hunts byte by byte, from the byte after the garbled frame's first, for
    the next frame whose length rule and CRC agree (a corrupted function code or
    byte count must not cost the frames behind it; a candidate still arriving is
    waited for, and given up at silence). While hunting, a function the rules
    cannot delimit is skipped: such a frame sent right behind a garbled one,
    without a gap, is lost with it (as on a real bus, where no gap separates
    them). At most :data:`MAX_RTU_ADU` bytes are kept.
    """

    def __init__(self, targets: Iterable[ModbusTarget] = (), stats: ModbusStats | None = None):
        self.targets = list(targets)
        self.stats = stats if stats is not None else ModbusStats()
        self.framer = FramerRTU(_DECODER)  # replies are built with pymodbus's encoder
        self.buffer = bytearray()
        self._resyncing = False

    @property
    def pending(self) -> bool:
        """Bytes of an unfinished (or undelimitable) frame are buffered."""
        return bool(self.buffer)

    @property
    def resyncing(self) -> bool:
        """A frame failed its CRC (or ran past MAX_RTU_ADU) since the line was last idle: the
        session hunts for the next good frame until :meth:`silence` (call it when the line
        goes idle, even with nothing buffered)."""
        return self._resyncing

    def receive_data(self, data: bytes) -> list[bytes]:
        """Take bytes off the line; the replies to the frames they complete, in order."""
        self.buffer += data
        return self._parse(final=False)

    def silence(self) -> list[bytes]:
        """The line went idle: whatever is buffered ends there (at a frame boundary it is
        one frame); the next byte starts a frame."""
        out = self._parse(final=True)
        self.buffer.clear()
        self._resyncing = False
        return out

    def _parse(self, final: bool) -> list[bytes]:
        """Answer the frames in the buffer and drop what is consumed. ``final``: no more
        bytes come before the next frame (the line is idle)."""
        buf = self.buffer
        out: list[bytes] = []
        pos = 0
        try:
            for _ in range(len(buf) + 1):  # bounded: each pass moves pos on or stops
                avail = len(buf) - pos
                if avail <= 0:
                    break
                n = rtu_request_length(buf, pos)
                if 0 < n <= avail:  # a complete frame by the length rules
                    end = pos + n
                    if _crc_ok(buf, pos, end):
                        self._resyncing = False
                        reply = self._dispatch(buf[pos], bytes(buf[pos + 1:end - 2]))
                        if reply is not None:
                            out.append(reply)
                        pos = end
                    else:  # a garbled frame (or, hunting, not a frame start): look one byte on
                        if not self._resyncing:
                            self.stats.crc_errors += 1
                            self._resyncing = True
                        pos += 1
                    continue
                if self._resyncing:  # hunting: only frames the rules delimit can be found
                    if final or n == RTU_UNDELIMITED:
                        pos += 1
                        continue
                    break  # a candidate still arriving
                if not final:
                    if n == RTU_UNDELIMITED and avail > MAX_RTU_ADU:  # longer than any frame
                        self.stats.malformed += 1
                        self._resyncing = True
                        pos += 1
                        continue
                    break  # wait for the rest of the frame, or for silence
                # the line went idle at a frame boundary: the rest is one frame
                start, pos = pos, len(buf)
                if avail < FramerRTU.MIN_SIZE:
                    self.stats.malformed += 1
                elif _crc_ok(buf, start, pos):
                    reply = self._dispatch(buf[start], bytes(buf[start + 1:pos - 2]))
                    if reply is not None:
                        out.append(reply)
                else:  # garbled, or frames run together: look inside for good ones
                    self.stats.crc_errors += 1
                    self._resyncing = True
                    pos = start + 1
        except Exception:  # our bug: drop what we have, keep serving
            self.stats.internal_errors += 1
            log.exception("rtu: framing failed on %s", buf.hex())
            pos = len(buf)
        del buf[:pos]
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
                    if isinstance(resp, ExceptionResponse):
                        self.stats.count_exception(resp.exception_code)
                    return self.framer.buildFrame(resp)
            self.stats.ignored += 1
        except Exception:  # our bug
            self.stats.internal_errors += 1
            log.exception("rtu: error answering %d %s", unit, pdu.hex())
        return None


class ModbusTcpServer:
    """Modbus TCP on ``host:port`` (0: a free port) for one target.

    max_clients: connections beyond it are refused with a log line;
    max_rate [requests/s]: each client's budget (token bucket of ``burst`` requests;
    0: none); a client over it is not read from until it is back within budget, so
    a flood slows only the flooder (TCP backpressure), never loses or garbles answers;
    batch: requests answered per client before letting the others in;
    write_buffer [bytes]: replies a client has not read beyond this are dropped (counted);
    idle_timeout [s]: a client that sent nothing and was sent nothing this long is dropped
    (None: never; done by :class:`~hilsim.links.tcp.TcpServer`).
    A peer that does not speak Modbus TCP is closed at once (holding it would let a
    reconnecting one fill the client slots); those closings log one warning a second.
    """

    def __init__(self, name: str, target: ModbusTarget, host: str = "127.0.0.1", port: int = 0, *,
                 max_clients: int = 32, max_rate: float = 1000.0, burst: int = 32, batch: int = 4,
                 write_buffer: int = 64 * 1024, idle_timeout: float | None = None):
        if max_rate < 0 or burst < 1:
            raise ValueError(f"{name}: max_rate must be >= 0 and burst >= 1")
        self.name = name
        self.target = target
        self.max_rate = float(max_rate)
        self.burst = int(burst)
        self.batch = max(1, int(batch))
        self.write_buffer = int(write_buffer)
        self._last_warning = -1e9
        self._unlogged = 0
        self.stats = ModbusStats()
        self.link = TcpServer(name, host, port, max_clients=max_clients, read_size=1024,
                              idle_timeout=idle_timeout,
                              on_connect=self._on_connect, on_data=self._on_data)

    @property
    def address(self) -> str:
        return self.link.address

    async def start(self) -> tuple[str, int]:
        return await self.link.start()

    async def close(self) -> None:
        await self.link.close()

    def _log_closing(self, client: Client, reason: str) -> None:
        """One warning per second at most, with how many were not shown."""
        now = time.monotonic()
        if now - self._last_warning >= 1.0:
            more = f" ({self._unlogged} more since the last such line)" if self._unlogged else ""
            log.warning("%s: closing %s: %s%s", self.name, client.peer, reason, more)
            self._last_warning, self._unlogged = now, 0
        else:
            self._unlogged += 1

    def _reply(self, client: Client, frame: bytes) -> None:
        """Write a reply at once (no extra loop turn through the link's queue); a client
        that does not read its replies loses them once ``write_buffer`` bytes are pending."""
        transport = client.writer.transport
        if client.closed or transport.is_closing():
            return
        if transport.get_write_buffer_size() > self.write_buffer:
            self.stats.dropped += 1
            return
        client.writer.write(frame)

    def _on_connect(self, client: Client) -> None:
        client.state["session"] = TcpSession(self.target, self.stats)
        client.state["bucket"] = [float(self.burst), time.monotonic(), False]  # tokens, time, throttled

    async def _allowance(self, client: Client) -> int:
        """Requests this client may send now (waits while it is over its budget)."""
        if self.max_rate <= 0:
            return self.batch
        bucket = client.state["bucket"]
        for _ in range(100):  # bounded: each wait refills at least one token
            now = time.monotonic()
            bucket[0] = min(float(self.burst), bucket[0] + (now - bucket[1]) * self.max_rate)
            bucket[1] = now
            if bucket[0] >= 1.0:
                return min(self.batch, int(bucket[0]))
            if not bucket[2]:
                bucket[2] = True
                self.stats.throttled += 1
                log.info("%s: %s over %g requests/s: throttled", self.name, client.peer, self.max_rate)
            await asyncio.sleep((1.0 - bucket[0]) / self.max_rate)
        return 1

    async def _on_data(self, client: Client, data: bytes) -> None:
        session: TcpSession = client.state["session"]
        session.receive_data(data)
        for _ in range(1 << 16):  # bounded by the data received (read_size bytes per call)
            n = await self._allowance(client) if session.has_frame() else self.batch
            frames = session.process(n)
            if self.max_rate > 0:
                client.state["bucket"][0] -= len(frames)
            for frame in frames:
                self._reply(client, frame)
            if session.closed:
                self._log_closing(client, session.close_reason)
                self.link.disconnect(client)
                return
            if not session.has_frame():
                return
            await asyncio.sleep(0)  # a client pipelining many requests waits its turn


class ModbusRtuServer:
    """Modbus RTU on an emulated serial port: clients open ``path`` (a symlink to a pty).

    baudrate [bit/s] paces the replies; parity ``N``/``E``/``O``; targets share the line.
    """

    def __init__(self, name: str, path: str | Path | None, targets: Iterable[ModbusTarget] = (), *,
                 baudrate: int = 9600, parity: str = "N", stop_bits: int = 1):
        if parity.upper() not in ("N", "E", "O"):
            raise ValueError(f"{name}: parity must be N, E or O, got {parity!r}")
        self.name = name
        self.stats = ModbusStats()
        self.session = RtuSession(targets, self.stats)
        self.link = PtyLink(name, path, baudrate=baudrate, parity=parity.upper(), stop_bits=stop_bits,
                            on_data=self._on_data)
        self._timer: asyncio.TimerHandle | None = None

    @property
    def path(self) -> str:
        return self.link.path

    @property
    def baudrate(self) -> int:
        return self.link.baudrate

    @property
    def silence_time(self) -> float:
        """[s] idle time that ends a frame: 3.5 characters, at least 2 ms (pty scheduling)."""
        return max(3.5 * self.link.byte_time, 0.002)

    def attach(self, target: ModbusTarget) -> None:
        """Put another device on this line (a distinct address)."""
        for t in self.session.targets:
            if t.device_id == target.device_id:
                raise ValueError(f"{self.name}: address {target.device_id} already used by {t.name}")
        self.session.targets.append(target)

    def detach(self, target: ModbusTarget) -> None:
        if target in self.session.targets:
            self.session.targets.remove(target)

    async def start(self) -> str:
        return await self.link.start()

    async def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        await self.link.close()

    def _on_data(self, data: bytes) -> None:
        for frame in self.session.receive_data(data):
            self.link.write(frame)
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self.session.pending or self.session.resyncing:
            self._timer = asyncio.get_running_loop().call_later(self.silence_time, self._on_silence)

    def _on_silence(self) -> None:
        self._timer = None
        for frame in self.session.silence():
            self.link.write(frame)


__all__ = ["RTU_NEED_MORE", "RTU_UNDELIMITED", "ModbusRtuServer", "ModbusStats", "ModbusTarget", "ModbusTcpServer",
           "RtuSession", "TcpSession", "WriteAction", "rtu_request_length"]
