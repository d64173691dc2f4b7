"""An slcan (Lawicel) USB-CAN adapter emulated on a pty, as a CAN bus.

Built on :class:`hilsim.links.pty.PtyLink` (raw pty, stable symlink, survives
the client closing and reopening the port) and the
:mod:`hilsim.protocols.slcan` codec. python-can (``interface="slcan",
channel=PATH``) and dronecan (``dronecan.make_node(PATH, ...)``) open it as
they open a real adapter. The adapter forwards bus frames to the host only
while the channel is open (after ``O``). A frame the host sends beyond the
bus's capacity at the selected bitrate (``S`` code) is refused with BEL and
counted, as an adapter with a full transmit buffer does; frames to the host
beyond that capacity are dropped and counted too.

tty_baudrate [bit/s] paces the bytes on the pty (0: unpaced, like a USB CDC
adapter, whose nominal baud rate means nothing).

A host that reads slowly never gets a cut line (python-can's slcan reader
raises on one): a frame is written only while fewer than ``max_backlog`` bytes
wait unread (in the pty and in the link's queue), else it is dropped whole
and counted. The pty link's own policy for a reader that falls behind (flush
everything unread beyond 2 KiB, which can cut a line in half) is turned off
for this link; this bus's whole-line dropping replaces it.
"""

from __future__ import annotations

import fcntl
import logging
import os
import struct
import termios
from pathlib import Path
from typing import Any

from hilsim.links.can.bus import CanBus, TokenBucket
from hilsim.links.pty import PtyLink
from hilsim.protocols import slcan
from hilsim.protocols.can import CanFrame

log = logging.getLogger(__name__)


class _LinePtyLink(PtyLink):
    """PtyLink without the flush of an unread backlog: that flush can cut a line in half, and the
    slcan bus bounds the backlog itself by dropping whole lines."""

    def _slave_backlog(self) -> int:
        return 0


class SlcanBus(CanBus):
    """path: the symlink clients open (None: only /dev/pts/N)."""

    transport = "slcan"

    def __init__(self, name: str, channel: str = "can0", *, path: str | os.PathLike[str] | None = None,
                 bitrate: int | None = 1_000_000, burst: float = 0.05, tty_baudrate: int = 0,
                 max_backlog: int = 3072) -> None:
        super().__init__(name, channel, bitrate=bitrate, burst=burst)
        self.max_backlog = max_backlog
        self.reply_limit = max_backlog + 512  # replies may use a little more (all within the tty buffer, 4 KiB)
        self.replies_dropped = 0
        self._written = 0  # bytes handed to the link
        self.link = _LinePtyLink(name, Path(path) if path else None, baudrate=tty_baudrate, on_data=self._on_data)
        self.codec = slcan.SlcanAdapter(bitrate=bitrate or 1_000_000)
        self._in_budget: TokenBucket | None = None
        self._out_budget: TokenBucket | None = None

    @property
    def address(self) -> str:
        return self.link.path

    @property
    def extra(self) -> dict[str, Any]:
        return {"interface": "slcan", "channel": self.link.path, "bitrate": self.codec.bitrate,
                "bus": self.channel}

    @property
    def has_listeners(self) -> bool:
        return self.codec.is_open

    def status(self) -> dict[str, float]:
        out = super().status()
        out["channel_open"] = float(self.codec.is_open)
        out["pty_bytes_discarded"] = float(self.link.bytes_discarded)
        out["replies_dropped"] = float(self.replies_dropped)
        return out

    def _budgets(self) -> None:
        if self.bitrate:
            self.bitrate = self.codec.bitrate or self.bitrate
            self._in_budget, self._out_budget = self.new_budget(), self.new_budget()

    async def _start(self) -> None:
        self._budgets()
        await self.link.start()

    async def _close(self) -> None:
        await self.link.close()

    def _on_data(self, data: bytes) -> None:
        codec = self.codec
        codec.receive_data(data)
        for _ in range(100_000):
            ev = codec.next_event()
            if ev is slcan.NEED_DATA:
                break
            if isinstance(ev, slcan.Transmit):
                if not self.from_peer(ev.frame, None, self._in_budget):
                    codec.reject_transmit()
            elif isinstance(ev, slcan.BitrateSet) and ev.bitrate:
                self._budgets()
            elif isinstance(ev, slcan.Opened):
                self.stats.clients = 1
            elif isinstance(ev, slcan.Closed):
                self.stats.clients = 0
            elif isinstance(ev, slcan.BadLine):
                self.stats.errors += 1
                log.debug("%s: %s: %r", self.name, ev.reason, ev.line[:40])
        out = codec.data_to_send()
        if out:
            room = self.reply_limit - self.backlog()
            if len(out) > room:  # the host is not reading: keep whole replies that fit, drop the rest
                cut = max(out.rfind(b"\r", 0, max(room, 0)), out.rfind(b"\a", 0, max(room, 0))) + 1
                self.replies_dropped += out[cut:].count(b"\r") + out[cut:].count(b"\a")
                out = out[:cut]
            if out:
                self._write(out)

    def _write(self, data: bytes) -> None:
        self._written += len(data)
        self.link.write(data)

    def backlog(self) -> int:
        """Bytes written for the host that it has not read yet (queued in the link or in the pty)."""
        queued = self._written - self.link.bytes_out - self.link.bytes_discarded
        unread = 0
        if self.link.slave >= 0:
            try:
                unread = struct.unpack("i", fcntl.ioctl(self.link.slave, termios.FIONREAD, b"\0\0\0\0"))[0]
            except OSError:
                unread = 0
        return max(0, queued) + unread

    def _to_peers(self, frame: CanFrame, exclude: Any) -> None:
        line = self.codec.encode_frame(frame)
        if not line:
            return  # channel closed: the adapter is not listening (not a drop)
        if self._out_budget is not None and not self._out_budget.take(frame.bits_on_wire):
            self.stats.dropped_out += 1
            return
        if self.backlog() + len(line) > self.max_backlog:
            self.stats.dropped_out += 1  # the host is not keeping up: drop whole lines, never cut one
            return
        self._write(line)
