"""A serial port emulated by a pseudo-terminal, with a stable symlink for clients.

The client (a thruster driver, a Modbus master, python-can's slcan) opens the
pty's slave side by its path, exactly as it would open ``/dev/ttyUSB0``; the
device reads and writes the master side here. Properties:

* raw mode (no echo, no line editing), set on both ends;
* a stable symlink (``link``) to the slave, removed on :meth:`close`;
* the slave stays open on our side too, so a client may close and reopen the
  port at will: nothing errors, the device keeps its state, and bytes written
  while nobody listens are discarded rather than delivered stale (the input
  queue is flushed when it fills);
* ``bit_error_rate`` > 0 flips bits both ways, as a noisy line does (fault injection);
* output is paced at the configured baud rate (``bits_per_byte`` / baud per
  byte, 10 bits for 8N1), so replies arrive when a real line would deliver them.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import os
import termios
import time
import tty
from collections import deque
from pathlib import Path
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)


def bits_per_byte(parity: str = "N", stop_bits: int = 1) -> int:
    """Bits on the wire per byte: start + 8 data + parity + stop."""
    return 1 + 8 + (0 if parity.upper() == "N" else 1) + stop_bits


class PtyLink:
    """One emulated serial port.

    name: for logs; link: symlink path for clients (``None``: only the /dev/pts path);
    baudrate [bit/s] paces output (0 = unpaced); on_data(bytes) gets what the client writes.
    """

    def __init__(self, name: str, link: str | os.PathLike[str] | None = None, *, baudrate: int = 115200,
                 parity: str = "N", stop_bits: int = 1, on_data: Callable[[bytes], None] | None = None,
                 max_pending: int = 64 * 1024) -> None:
        self.name = name
        self.link = Path(link) if link is not None else None
        self.baudrate = int(baudrate)
        self.parity = parity
        self.stop_bits = stop_bits
        self.on_data = on_data
        self.max_pending = max_pending
        self.master = -1
        self.slave = -1
        self.slave_path = ""
        self.bytes_in = 0
        self.bytes_out = 0
        self.bytes_discarded = 0
        self._out: deque[bytes] = deque()
        self._out_len = 0
        self._writer: asyncio.Task[None] | None = None
        self._wake = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self.bit_error_rate = 0.0   # fault injection: probability of each bit flipping, both ways
        self.bits_flipped = 0
        self._rng = np.random.default_rng(abs(hash(name)) % (2**32))

    FAULTS = ("bit_errors",)

    def set_fault(self, fault: str, on: bool, params: "dict[str, float] | None" = None) -> None:
        """``bit_errors`` (``rate``: probability per bit, default 1e-3) on or off."""
        if fault != "bit_errors":
            raise ValueError(f"a serial line has no fault {fault!r}")
        self.bit_error_rate = float((params or {}).get("rate", 1e-3)) if on else 0.0

    @property
    def path(self) -> str:
        """The path clients open: the symlink if there is one, else /dev/pts/N."""
        return str(self.link) if self.link is not None else self.slave_path

    @property
    def byte_time(self) -> float:
        """[s] time one byte takes on the wire at the configured baud rate."""
        return bits_per_byte(self.parity, self.stop_bits) / self.baudrate if self.baudrate > 0 else 0.0

    async def start(self) -> str:
        """Create the pty (and symlink); start serving. Returns the client path."""
        self._loop = asyncio.get_running_loop()
        self.master, self.slave = os.openpty()
        for fd in (self.master, self.slave):
            tty.setraw(fd, termios.TCSANOW)
        os.set_blocking(self.master, False)
        self.slave_path = os.ttyname(self.slave)
        if self.link is not None:
            self.link.parent.mkdir(parents=True, exist_ok=True)
            if self.link.is_symlink() or self.link.exists():
                if not self.link.is_symlink():
                    raise FileExistsError(f"{self.name}: {self.link} exists and is not a symlink; refusing to replace it")
                self.link.unlink()
            self.link.symlink_to(self.slave_path)
        self._loop.add_reader(self.master, self._readable)
        self._writer = asyncio.ensure_future(self._write_loop())
        log.info("%s on %s (%s, %d baud)", self.name, self.path, self.slave_path, self.baudrate)
        return self.path

    def write(self, data: bytes) -> None:
        """Queue bytes for the client (paced at the baud rate). Beyond ``max_pending``
        queued bytes the oldest are discarded and counted."""
        if self.master < 0 or not data:
            return
        self._out.append(bytes(data))
        self._out_len += len(data)
        while self._out_len > self.max_pending and len(self._out) > 1:
            old = self._out.popleft()
            self._out_len -= len(old)
            self.bytes_discarded += len(old)
        self._wake.set()

    async def drain(self) -> None:
        """Wait until everything queued has been handed to the pty."""
        while self._out and self.master >= 0:
            await asyncio.sleep(self.byte_time or 0.001)

    async def close(self) -> None:
        if self._loop is not None and self.master >= 0:
            try:
                self._loop.remove_reader(self.master)
            except Exception:  # noqa: BLE001 - loop closing
                pass
        if self._writer is not None:
            self._writer.cancel()
            try:
                await self._writer
            except (asyncio.CancelledError, Exception):  # noqa: BLE001
                pass
        for fd in (self.master, self.slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = -1
        if self.link is not None and self.link.is_symlink():
            try:
                self.link.unlink()
            except OSError:
                pass

    # -- internals --

    def _readable(self) -> None:
        try:
            data = os.read(self.master, 4096)  # a chunk per loop turn: a flooding host cannot stall the loop
        except BlockingIOError:
            return
        except OSError as exc:  # EIO: no slave open (we hold one, so rare)
            if exc.errno != errno.EIO:
                log.warning("%s: read error %s", self.name, exc)
            return
        if not data:
            return
        if self.bit_error_rate > 0:
            data = self._corrupt(data)
        self.bytes_in += len(data)
        if self.on_data is not None:
            try:
                self.on_data(data)
            except Exception:  # a device bug must not stop the port
                log.exception("%s: error handling %d bytes", self.name, len(data))

    def _slave_backlog(self) -> int:
        """Bytes written to the client that nobody has read yet."""
        import fcntl
        import struct

        try:
            buf = fcntl.ioctl(self.slave, termios.FIONREAD, b"\0\0\0\0")
            return int(struct.unpack("i", buf)[0])
        except OSError:
            return 0

    async def _write_loop(self) -> None:
        line_free = time.monotonic()  # when the emulated line finishes what was already sent
        while True:
            if not self._out:
                self._wake.clear()
                await self._wake.wait()
                continue
            chunk = self._out.popleft()
            self._out_len -= len(chunk)
            # nobody reading? drop what is queued in the tty rather than deliver it stale later
            if self._slave_backlog() > 2048:
                termios.tcflush(self.slave, termios.TCIFLUSH)
            if self.byte_time <= 0:
                self._write_now(chunk)
                continue
            # bytes become readable when a real line would have delivered them:
            # slices of about 2 ms of line time, each written at the end of its slot
            step = max(1, int(0.002 / self.byte_time))
            line_free = max(line_free, time.monotonic())
            for i in range(0, len(chunk), step):
                piece = chunk[i:i + step]
                line_free += len(piece) * self.byte_time
                delay = line_free - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                self._write_now(piece)

    def _corrupt(self, data: bytes) -> bytes:
        """Flip each bit with probability ``bit_error_rate`` (a noisy line)."""
        bits = np.unpackbits(np.frombuffer(data, dtype=np.uint8))
        flips = self._rng.random(bits.size) < self.bit_error_rate
        n = int(np.count_nonzero(flips))
        if n == 0:
            return data
        self.bits_flipped += n
        return np.packbits(bits ^ flips).tobytes()

    def _write_now(self, data: bytes) -> None:
        if self.bit_error_rate > 0:
            data = self._corrupt(data)
        view = memoryview(data)
        for _ in range(100):
            if not view:
                return
            try:
                n = os.write(self.master, view)
                view = view[n:]
                self.bytes_out += n
            except BlockingIOError:  # the client's input queue is full: it is not reading
                termios.tcflush(self.slave, termios.TCIFLUSH)
            except OSError as exc:
                log.warning("%s: write error %s; %d bytes discarded", self.name, exc, len(view))
                break
        self.bytes_discarded += len(view)
