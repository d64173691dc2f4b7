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
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from hilsim.links.can.bus import CanBus, TokenBucket
from hilsim.links.pty import PtyLink
from hilsim.protocols import slcan
from hilsim.protocols.can import CanFrame

log = logging.getLogger(__name__)


class SlcanBus(CanBus):
    """path: the symlink clients open (None: only /dev/pts/N)."""

    transport = "slcan"

    def __init__(self, name: str, channel: str = "can0", *, path: str | os.PathLike[str] | None = None,
                 bitrate: int | None = 1_000_000, burst: float = 0.05, tty_baudrate: int = 0) -> None:
        super().__init__(name, channel, bitrate=bitrate, burst=burst)
        self.link = PtyLink(name, Path(path) if path else None, baudrate=tty_baudrate, on_data=self._on_data)
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

    def status(self) -> dict[str, float]:
        out = super().status()
        out["channel_open"] = float(self.codec.is_open)
        out["pty_bytes_discarded"] = float(self.link.bytes_discarded)
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
            self.link.write(out)

    def _to_peers(self, frame: CanFrame, exclude: Any) -> None:
        line = self.codec.encode_frame(frame)
        if not line:
            return  # channel closed: the adapter is not listening (not a drop)
        if self._out_budget is not None and not self._out_budget.take(frame.bits_on_wire):
            self.stats.dropped_out += 1
            return
        self.link.write(line)
