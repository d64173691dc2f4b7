"""Modbus TCP and Modbus RTU (on a pty) servers around one shared register image.

Layers, innermost first (the first two sans-I/O, in :mod:`hilsim.protocols`):

* :mod:`hilsim.protocols.modbus`: request framing, MBAP and RTU (the RTU
  length rules, CRC, resynchronisation, silence), as the codec contract has it;
* :mod:`hilsim.protocols.modbus_device`: :class:`ModbusTarget` (one device's
  registers, address and write actions: a request PDU -> the response the real
  device gives) and :class:`TcpSession` / :class:`RtuSession` (bytes in, reply
  frames out); re-exported here;
* :class:`ModbusTcpServer` (on :class:`hilsim.links.tcp.TcpServer`: client limit
  with a log line, per-client bounded queues) and :class:`ModbusRtuServer` (on
  :class:`hilsim.links.pty.PtyLink`: a stable path, replies paced at the baud
  rate, survives the client closing and reopening the port).

Why not pymodbus's own server classes: each keeps its own copy of the registers
(a TCP and an RTU server would hold two states), the RTU one opens a serial
port itself (a pty pair and a relay for the baud pacing) and hunts past frames
with an unknown function instead of answering 01, the device address cannot
change at run time, and there is no client limit. The wire encoding is our own
small codec too (:mod:`hilsim.protocols.modbus_pdu`: importing pymodbus would pull
asyncio, socket and ssl into the sans-I/O layer). Nothing a client sends raises
out of this module: a failure inside is logged, counted in
``stats.internal_errors`` and answered with 04.
"""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path
from typing import Callable, Iterable

from hilsim.links.pty import PtyLink
from hilsim.links.tcp import EVICT_GRACE, Client, TcpServer
from hilsim.protocols.modbus import (MAX_RTU_ADU, MAX_TCP_LENGTH, RTU_NEED_MORE, RTU_UNDELIMITED, RtuDialect,
                                     rtu_request_length)
from hilsim.protocols.modbus_device import ModbusStats, ModbusTarget, RtuSession, TcpSession, WriteAction

log = logging.getLogger(__name__)


class ModbusTcpServer:
    """Modbus TCP on ``host:port`` (0: a free port) for one target.

    max_clients: connections beyond it are refused with a log line;
    max_rate [requests/s]: each client's budget (token bucket of ``burst`` requests;
    0: none); a client over it is not read from until it is back within budget, so
    a flood slows only the flooder (TCP backpressure), never loses or garbles answers;
    batch: requests answered per client before letting the others in;
    write_buffer [bytes]: replies a client has not read beyond this are dropped (counted);
    idle_timeout [s]: a client that sent nothing and was sent nothing this long is dropped
    (None: never; done by :class:`~hilsim.links.tcp.TcpServer`); evict_grace [s]: when full, a
    newcomer evicts the client longest without a request (or not reading its replies) if
    that exceeds this (None or 0: never; :class:`~hilsim.links.tcp.TcpServer`).
    A peer that does not speak Modbus TCP is closed at once (holding it would let a
    reconnecting one fill the client slots); those closings log one warning a second.
    """

    def __init__(self, name: str, target: ModbusTarget, host: str = "127.0.0.1", port: int = 0, *,
                 max_clients: int = 32, max_rate: float = 1000.0, burst: int = 32, batch: int = 4,
                 write_buffer: int = 64 * 1024, idle_timeout: float | None = None,
                 evict_grace: float | None = EVICT_GRACE):
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
                              idle_timeout=idle_timeout, evict_grace=evict_grace,
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

    def add_dialect(self, dialect: RtuDialect, handler: Callable[[bytes], bytes | None]) -> None:
        """Serve another protocol beside Modbus on this line, told by function code (the KELLER bus)."""
        self.session.add_dialect(dialect, handler)

    def remove_dialect(self, handler: Callable[[bytes], bytes | None]) -> None:
        self.session.remove_dialect(handler)

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



class SerialLineTcpServer:
    """The RTU line on ``host:port`` as a serial device server passes it on (an RS-485 to
    Ethernet converter in TCP-server raw mode): each client's bytes are a serial line of
    their own, Modbus RTU frames and the line's other dialect (the KELLER bus) alike, with
    the same targets and dialect handlers as the line's session ``line`` (a
    :class:`ModbusRtuServer`'s ``session``, or one of its own). A pause of ``gap`` [s] in a
    client's bytes ends a frame, as silence on the wire does."""

    def __init__(self, name: str, line: RtuSession, host: str = "127.0.0.1", port: int = 0, *,
                 max_clients: int = 8, gap: float = 0.005, idle_timeout: float | None = None):
        self.name = name
        self.line = line
        self.gap = float(gap)
        self.stats = ModbusStats()
        self.link = TcpServer(name, host, port, max_clients=max_clients, read_size=1024,
                              idle_timeout=idle_timeout, on_connect=self._on_connect, on_data=self._on_data,
                              on_disconnect=self._on_disconnect)

    @property
    def address(self) -> str:
        return self.link.address

    async def start(self) -> tuple[str, int]:
        return await self.link.start()

    async def close(self) -> None:
        await self.link.close()

    def _on_connect(self, client: Client) -> None:
        session = RtuSession((), self.stats)
        session.targets = self.line.targets          # the same targets (the line's list) ...
        session.foreign = self.line.foreign          # ... and dialect handlers
        session.decoder.dialect = self.line.decoder.dialect
        client.state["session"] = session
        client.state["timer"] = None

    def _on_disconnect(self, client: Client) -> None:
        timer = client.state.get("timer")
        if timer is not None:
            timer.cancel()

    def _write(self, client: Client, frames: list[bytes]) -> None:
        if frames and not client.closed and not client.writer.transport.is_closing():
            client.writer.write(b"".join(frames))

    def _on_data(self, client: Client, data: bytes) -> None:
        session: RtuSession = client.state["session"]
        session.decoder.dialect = self.line.decoder.dialect
        self._write(client, session.receive_data(data))
        if client.state["timer"] is not None:
            client.state["timer"].cancel()
        client.state["timer"] = asyncio.get_running_loop().call_later(self.gap, self._on_silence, client)

    def _on_silence(self, client: Client) -> None:
        client.state["timer"] = None
        self._write(client, client.state["session"].silence())


__all__ = ["MAX_RTU_ADU", "MAX_TCP_LENGTH", "RTU_NEED_MORE", "RTU_UNDELIMITED", "ModbusRtuServer", "ModbusStats", "ModbusTarget", "ModbusTcpServer",
           "RtuSession", "SerialLineTcpServer", "TcpSession", "WriteAction", "rtu_request_length"]
