"""A socketcand-compatible TCP server as a CAN bus (python-can's ``socketcand`` client connects).

Built on :class:`hilsim.links.tcp.TcpServer` (per-client bounded queues, a
client limit with a log line). Per client, the :mod:`hilsim.protocols.socketcand`
codec: ``< hi >`` on connect, ``< open CHANNEL >`` and ``< rawmode >`` each
answered ``< ok >`` as a message of its own, as python-can checks each reply
by exact match of one ``recv``. Bus frames reach a client only once it is in
raw mode and ``raw_grace`` [s] has passed, so no frame can arrive glued to
the last ``< ok >``. A frame a client sends goes to the devices and to every
other raw client, never back to its sender (as socketcand does).
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

from hilsim.links.can.bus import CanBus, TokenBucket
from hilsim.links.tcp import EVICT_GRACE, Client, TcpServer
from hilsim.protocols import socketcand as sc
from hilsim.protocols.can import CanFrame

log = logging.getLogger(__name__)


class SocketcandBus(CanBus):
    """host/port: where to listen (port 0 picks a free one); max_clients: beyond it
    connections are refused with a log line, unless a client has gone ``evict_grace`` [s]
    without progress (sent nothing and taken nothing, or not reading): the newcomer evicts it
    (:class:`~hilsim.links.tcp.TcpServer`); queue_len: frames queued per client."""

    transport = "socketcand"

    def __init__(self, name: str, channel: str = "can0", *, host: str = "127.0.0.1", port: int = 0,
                 bitrate: int | None = 1_000_000, burst: float = 0.05, max_clients: int = 8,
                 queue_len: int = 2048, raw_grace: float = 0.2, evict_grace: float | None = EVICT_GRACE) -> None:
        super().__init__(name, channel, bitrate=bitrate, burst=burst)
        self.raw_grace = raw_grace
        self.server = TcpServer(name, host, port, max_clients=max_clients, queue_len=queue_len,
                                evict_grace=evict_grace, on_connect=self._on_connect, on_data=self._on_data,
                                on_disconnect=self._on_disconnect)

    @property
    def address(self) -> str:
        return self.server.address

    @property
    def extra(self) -> dict[str, Any]:
        return {"interface": "socketcand", "channel": self.channel, "host": self.server.host,
                "port": self.server.port}

    @property
    def has_listeners(self) -> bool:
        now = time.monotonic()
        return any(self._ready(c, now) for c in self.server.clients.values())

    def status(self) -> dict[str, float]:
        out = super().status()
        out["refused"] = float(self.server.stats.refused)
        return out

    async def _start(self) -> None:
        await self.server.start()

    async def _close(self) -> None:
        await self.server.close()

    # -- per client ---------------------------------------------------------------

    def _on_connect(self, client: Client) -> None:
        codec = sc.SocketcandServer(frozenset({self.channel}))
        client.state.update(codec=codec, budget=self.new_budget(), raw_at=None)
        self.server.send(client, codec.greeting())
        self.stats.clients = len(self.server.clients)

    def _on_disconnect(self, client: Client) -> None:
        self.stats.clients = len(self.server.clients)

    def _on_data(self, client: Client, data: bytes) -> None:
        codec: sc.SocketcandServer = client.state["codec"]
        budget: TokenBucket | None = client.state["budget"]
        codec.receive_data(data)
        for _ in range(100_000):
            ev = codec.next_event()
            for reply in codec.replies():  # each reply a message of its own, in order
                self.server.send(client, reply)
            if ev is sc.NEED_DATA:
                break
            if isinstance(ev, sc.SendFrame):
                self.from_peer(ev.frame, client, budget)
            elif isinstance(ev, sc.RawModeEntered):
                client.state["raw_at"] = time.monotonic()
            elif isinstance(ev, sc.BadMessage):
                self.stats.errors += 1
                log.debug("%s: %s: %s", self.name, client, ev.reason)

    def _ready(self, client: Client, now: float) -> bool:
        raw_at = client.state.get("raw_at")
        if raw_at is None or now - raw_at < self.raw_grace:
            return False
        return client.state["codec"].mode is sc.Mode.RAW

    def _to_peers(self, frame: CanFrame, exclude: Any) -> None:
        now = time.monotonic()
        message = b""
        for client in list(self.server.clients.values()):
            if client is exclude or not self._ready(client, now):
                continue
            if not message:
                message = sc.format_frame(frame, time.time())
            if not self.server.send(client, message):
                self.stats.dropped_out += 1

    def _forward(self, frame: CanFrame, source: Any) -> None:
        if len(self.server.clients) > 1:
            self.stats.forwarded += 1
            self._to_peers(frame, source)

    async def wait_clients(self, n: int, timeout: float = 5.0) -> bool:
        """Wait until ``n`` clients are in raw mode and past the grace (tests, benchmarks)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            now = time.monotonic()
            if sum(self._ready(c, now) for c in self.server.clients.values()) >= n:
                return True
            await asyncio.sleep(0.01)
        return False
