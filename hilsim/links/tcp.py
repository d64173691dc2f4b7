"""A TCP server link: many clients, each with its own bounded queue of whole messages.

The device above it hands over whole messages (a sonar frame, a reply) and
decides what bytes mean; this module only moves them. Guarantees:

* a client that reads too slowly loses whole messages (counted), never half
  of one, and never slows the others: each client has a queue of at most
  ``queue_len`` messages, a transport buffer capped at ``write_buffer`` bytes
  and (with ``sndbuf``) a capped kernel send buffer, so memory per client is bounded;
* at most ``max_clients`` connections. When the server is full, a newcomer evicts the
  client that has gone longest without progress, if that one has been so for more than
  ``evict_grace`` [s]: *stalled* (a message to it has waited on the peer that long: it does
  not read) or, on a ``command_channel`` (clients are expected to send: requests, pings,
  fire messages), *idle* (nothing received from it and nothing taken by it that long; a
  keep-alive the device sends with ``progress=False`` does not count: the kernel takes small
  messages for a peer that hung as well as for one that reads). A
  stream whose clients only listen (``command_channel=False``) never counts a listener it has
  nothing to send as idle. Each eviction is logged with its reason and counted
  (``LinkStats.evicted``). A server full of clients making progress refuses the newcomer, with
  a log line (at most one a second per server, with how many were not shown, so a flood cannot
  flood the log). So a client that crashed without closing, or a script that connects and
  hangs, holds a slot only while no one else needs it;
* one client blasting bytes cannot starve the others: the loop serves everyone
  else between two chunks of one client's input; a client whose chunks cost its
  (synchronous) ``on_data`` more than ``CHUNK_TIME`` of CPU is read in smaller ones
  (down to ``MIN_READ`` bytes), so no chunk holds the loop long; and a client whose
  input costs more than ``cpu_share`` of the loop (with ``cpu_burst`` [s] of
  credit) is read more slowly: the kernel's buffers fill and TCP pushes back on it.
  An async ``on_data`` paces itself (Modbus: its request budget);
* whatever a client sends or however it disconnects (mid-message, reset,
  half-open), the server keeps serving the others;
* no slot is held forever by a client that is gone or does nothing: TCP
  keep-alive probes (after ``keepalive`` [s] of silence, 3 probes 10 s apart)
  close connections whose peer vanished without FIN or RST (a half-open
  connection); a client that sent nothing and was sent nothing for
  ``idle_timeout`` [s] is dropped (for request/response protocols; off for
  streams whose clients only listen); a client that has not taken any of what
  it was sent for ``stall_timeout`` [s] (it never reads) is dropped. Each drop
  is logged with its reason.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import socket
import time
from dataclasses import dataclass, field
from typing import Awaitable, Callable

log = logging.getLogger(__name__)

CHUNK_TIME = 0.002  # [s] of CPU: a client whose chunk of input took longer is read in smaller ones
MIN_READ = 256      # [bytes]
EVICT_GRACE = 5.0   # [s] a client without progress this long may be evicted for a newcomer (full server)


@dataclass
class LinkStats:
    connected: int = 0
    accepted: int = 0
    refused: int = 0
    messages_sent: int = 0
    bytes_sent: int = 0
    messages_dropped: int = 0
    bytes_received: int = 0
    throttled: int = 0          # clients read more slowly for the CPU their input took
    idle_drops: int = 0         # clients dropped after idle_timeout without traffic either way
    stall_drops: int = 0        # clients dropped after stall_timeout without reading
    evicted: int = 0            # clients evicted (stalled or idle past evict_grace) to admit a newcomer


@dataclass(eq=False)
class Client:
    """One connected peer."""

    id: int
    peer: str
    writer: asyncio.StreamWriter
    queue: asyncio.Queue[tuple[bytes, bool]]  # (message, whether taking it is progress)
    sent: int = 0
    dropped: int = 0
    closed: bool = False
    cpu_credit: float = 0.0  # [s] of loop time this client's input may still take at once
    cpu_t: float = 0.0       # [s] monotonic time of the last refill
    throttled: bool = False
    read_size: int = 4096    # [bytes] adapted to what its input costs
    last_active: float = 0.0           # [s] monotonic: the last byte received or message taken
    last_progress: float = 0.0         # [s] monotonic: the same, keep-alives (progress=False) not counted
    writing_since: float | None = None  # [s] monotonic: start of the write now waiting on the peer
    state: dict = field(default_factory=dict)  # the device's per-client state (codec, settings)

    def __repr__(self) -> str:
        return f"Client#{self.id}({self.peer})"


OnConnect = Callable[[Client], Awaitable[None] | None]
OnData = Callable[[Client, bytes], Awaitable[None] | None]
OnDisconnect = Callable[[Client], Awaitable[None] | None]


def _set_keepalive(sock: socket.socket, idle: float) -> None:
    """TCP keep-alive: probe after ``idle`` [s] of silence, 3 probes 10 s apart (Linux options where
    the platform has them): a peer that vanished is noticed in about ``idle`` + 30 s."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        for opt, value in (("TCP_KEEPIDLE", max(1, int(idle))), ("TCP_KEEPINTVL", 10), ("TCP_KEEPCNT", 3)):
            if hasattr(socket, opt):
                sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, opt), value)
    except OSError:  # noqa: PERF203 - a socket that refuses the options still serves
        pass


async def _maybe_await(x: Awaitable[None] | None) -> None:
    if x is not None:
        await x


class TcpServer:
    """An asyncio TCP server with per-client bounded, whole-message send queues."""

    _ids = itertools.count(1)

    def __init__(self, name: str, host: str = "127.0.0.1", port: int = 0, *,
                 max_clients: int = 32, queue_len: int = 4, write_buffer: int = 256 * 1024,
                 read_size: int = 4096, idle_timeout: float | None = None,
                 stall_timeout: float | None = 30.0, keepalive: float | None = 30.0, sndbuf: int | None = None,
                 cpu_share: float | None = 0.25, cpu_burst: float = 0.05,
                 evict_grace: float | None = EVICT_GRACE, command_channel: bool = True,
                 on_connect: OnConnect | None = None, on_data: OnData | None = None,
                 on_disconnect: OnDisconnect | None = None) -> None:
        self.name = name
        self.host = host
        self.port = port
        self.max_clients = max_clients
        self.queue_len = queue_len
        self.write_buffer = write_buffer
        self.read_size = read_size
        self.idle_timeout = idle_timeout if idle_timeout else None
        self.stall_timeout = stall_timeout if stall_timeout else None
        self.keepalive = keepalive if keepalive else None
        self.sndbuf = sndbuf
        self.cpu_share = cpu_share
        self.cpu_burst = cpu_burst
        self.evict_grace = evict_grace if evict_grace is not None and evict_grace > 0 else None
        self.command_channel = command_channel
        self._last_refusal_log = -1e9
        self._unlogged_refusals = 0
        self.on_connect = on_connect
        self.on_data = on_data
        self.on_disconnect = on_disconnect
        self.clients: dict[int, Client] = {}
        self.stats = LinkStats()
        self._server: asyncio.base_events.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._watchdog: asyncio.Task[None] | None = None

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    async def start(self) -> tuple[str, int]:
        """Listen; returns the bound (host, port) (port 0 picks a free one)."""
        self._server = await asyncio.start_server(self._handle, self.host, self.port, limit=self.read_size * 4)
        sock = self._server.sockets[0]
        self.host, self.port = sock.getsockname()[:2]
        log.info("%s listening on %s", self.name, self.address)
        limits = [x for x in (self.idle_timeout, self.stall_timeout) if x]
        if limits:
            self._watchdog = self._spawn(self._watch(min(1.0, min(limits) / 4)))
        return self.host, self.port

    async def close(self) -> None:
        """Stop listening and drop every client."""
        if self._server is not None:
            self._server.close()
        for c in list(self.clients.values()):
            self._drop(c)
        for t in list(self._tasks):
            t.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._server is not None:
            try:
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
            except (asyncio.TimeoutError, Exception):  # noqa: BLE001 - shutting down regardless
                pass
            self._server = None

    def broadcast(self, message: bytes, only: Callable[[Client], bool] | None = None) -> int:
        """Queue ``message`` for every client (or those ``only`` accepts); returns how many took it."""
        n = 0
        for c in list(self.clients.values()):
            if only is None or only(c):
                n += self.send(c, message)
        return n

    def send(self, client: Client, message: bytes, *, progress: bool = True) -> bool:
        """Queue a whole message for one client; False (and counted) if its queue is full.
        ``progress=False``: a keep-alive, whose taking does not make the client less idle."""
        if client.closed:
            return False
        try:
            client.queue.put_nowait((message, progress))
            return True
        except asyncio.QueueFull:
            client.dropped += 1
            self.stats.messages_dropped += 1
            return False

    def disconnect(self, client: Client) -> None:
        """Close a client's connection (the device decided so)."""
        self._drop(client)

    # -- internals --

    def _spawn(self, coro: Awaitable[None]) -> asyncio.Task[None]:
        t = asyncio.ensure_future(coro)
        self._tasks.add(t)
        t.add_done_callback(self._tasks.discard)
        return t

    def _drop(self, c: Client) -> None:
        if c.closed:
            return
        c.closed = True
        self.clients.pop(c.id, None)
        self.stats.connected = len(self.clients)
        try:
            c.writer.transport.abort()
        except Exception:  # noqa: BLE001 - already gone
            pass

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        peer_s = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)
        if len(self.clients) >= self.max_clients and not self._evict_for(peer_s):
            self.stats.refused += 1
            self._log_refusal(peer_s)
            writer.transport.abort()
            return
        writer.transport.set_write_buffer_limits(high=self.write_buffer)
        sock = writer.get_extra_info("socket")
        if self.sndbuf is not None and sock is not None:
            # bound what the kernel holds for a client that does not read, too
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.sndbuf)
        if self.keepalive is not None and sock is not None:
            _set_keepalive(sock, self.keepalive)
        now = time.monotonic()
        c = Client(next(self._ids), peer_s, writer, asyncio.Queue(self.queue_len),
                   cpu_credit=self.cpu_burst, cpu_t=now, read_size=self.read_size, last_active=now,
                   last_progress=now)
        self.clients[c.id] = c
        self.stats.accepted += 1
        self.stats.connected = len(self.clients)
        log.info("%s: client %s connected (%d now)", self.name, peer_s, len(self.clients))
        sender = self._spawn(self._send_loop(c))
        try:
            if self.on_connect is not None:
                await _maybe_await(self.on_connect(c))
            while not c.closed:
                data = await reader.read(c.read_size)
                if not data:
                    break
                c.last_active = c.last_progress = time.monotonic()
                self.stats.bytes_received += len(data)
                if self.on_data is not None:
                    # CPU time of this thread, not wall time: on a loaded machine the time the OS
                    # gives other processes must not be charged to a well-behaved client
                    t0 = time.thread_time()
                    result = self.on_data(c, data)
                    if result is not None:
                        await result  # an async handler paces itself
                    else:
                        used = time.thread_time() - t0
                        if used > CHUNK_TIME:  # costly input: smaller chunks, shorter holds of the loop
                            c.read_size = max(MIN_READ, c.read_size // 2)
                        elif used < CHUNK_TIME / 4 and c.read_size < self.read_size:
                            c.read_size = min(self.read_size, 2 * c.read_size)
                        wait = self._charge(c, used)
                        if wait > 0:
                            await asyncio.sleep(wait)
                # let the others in before this client's next chunk (asyncio hands over up to
                # 256 KiB per read, which read() would otherwise return chunk after chunk)
                await asyncio.sleep(0)
        except (ConnectionError, OSError):
            pass
        except asyncio.CancelledError:
            pass
        except Exception:  # a device bug must not take the server down: log it loudly
            log.exception("%s: error while serving %s", self.name, peer_s)
        finally:
            self._drop(c)
            sender.cancel()
            log.info("%s: client %s disconnected (sent %d, dropped %d)", self.name, peer_s, c.sent, c.dropped)
            if self.on_disconnect is not None:
                try:
                    await _maybe_await(self.on_disconnect(c))
                except Exception:  # noqa: BLE001
                    log.exception("%s: on_disconnect failed", self.name)

    async def _watch(self, every: float) -> None:
        """Drop clients idle for ``idle_timeout`` or not reading for ``stall_timeout``."""
        while True:
            await asyncio.sleep(every)
            now = time.monotonic()
            for c in list(self.clients.values()):
                if self.stall_timeout is not None and c.writing_since is not None \
                        and now - c.writing_since > self.stall_timeout:
                    self.stats.stall_drops += 1
                    log.warning("%s: client %s has taken nothing it was sent for %.0f s (not reading): dropped",
                                self.name, c.peer, now - c.writing_since)
                    self._drop(c)
                elif self.idle_timeout is not None and c.writing_since is None and c.queue.empty() \
                        and now - c.last_active > self.idle_timeout:
                    self.stats.idle_drops += 1
                    log.info("%s: client %s sent nothing and was sent nothing for %.0f s (idle): dropped",
                             self.name, c.peer, now - c.last_active)
                    self._drop(c)

    def stale_for(self, c: Client, now: float | None = None) -> tuple[float, str]:
        """How long [s] client ``c`` has gone without progress, and why: ``"stalled"`` (a message to
        it has waited on the peer since then), ``"idle"`` (command channel: nothing received from it
        and nothing taken by it since then); ``(0.0, "")`` while it makes progress."""
        now = time.monotonic() if now is None else now
        if c.writing_since is not None:
            return now - c.writing_since, "stalled"
        if self.command_channel and c.queue.empty():
            return now - c.last_progress, "idle"
        return 0.0, ""

    def _evict_for(self, newcomer: str) -> bool:
        """Full server: evict the client longest without progress if that exceeds ``evict_grace``;
        True if a slot was freed."""
        if self.evict_grace is None:
            return False
        now = time.monotonic()
        victim: Client | None = None
        worst, why = self.evict_grace, ""
        for c in self.clients.values():
            age, reason = self.stale_for(c, now)
            if age > worst:
                victim, worst, why = c, age, reason
        if victim is None:
            return False
        self.stats.evicted += 1
        what = ("has taken nothing it was sent" if why == "stalled"
                else "sent nothing and took nothing but keep-alives")
        log.warning("%s: client %s evicted (%s: %s for %.1f s) to admit %s: client limit %d reached",
                    self.name, victim.peer, why, what, worst, newcomer, self.max_clients)
        self._drop(victim)
        return True

    def _log_refusal(self, peer: str) -> None:
        now = time.monotonic()
        if now - self._last_refusal_log >= 1.0:
            more = (f" ({self._unlogged_refusals} more refused since the last such line)"
                    if self._unlogged_refusals else "")
            log.warning("%s: refused %s: client limit %d reached%s", self.name, peer, self.max_clients, more)
            self._last_refusal_log, self._unlogged_refusals = now, 0
        else:
            self._unlogged_refusals += 1

    def _charge(self, c: Client, used: float) -> float:
        """Charge ``used`` [s] of loop time to client ``c``; returns how long [s] to wait before
        reading it again (0 while it is within ``cpu_share``)."""
        if not self.cpu_share:
            return 0.0
        now = time.monotonic()
        c.cpu_credit = min(self.cpu_burst, c.cpu_credit + (now - c.cpu_t) * self.cpu_share) - used
        c.cpu_t = now
        if c.cpu_credit >= 0.0:
            return 0.0
        if not c.throttled:
            c.throttled = True
            self.stats.throttled += 1
            log.info("%s: %s: its input takes over %.0f %% of the loop; reading it more slowly",
                     self.name, c.peer, 100 * self.cpu_share)
        return -c.cpu_credit / self.cpu_share

    async def _send_loop(self, c: Client) -> None:
        try:
            while not c.closed:
                msg, progress = await c.queue.get()
                c.writing_since = time.monotonic()
                c.writer.write(msg)
                await c.writer.drain()
                c.last_active = time.monotonic()
                if progress:
                    c.last_progress = c.last_active
                c.writing_since = None
                c.sent += 1
                self.stats.messages_sent += 1
                self.stats.bytes_sent += len(msg)
        except (ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            self._drop(c)


async def serve_with_fallback(name: str, make: Callable[[int], TcpServer], port: int) -> tuple[TcpServer, str, int]:
    """Start ``make(port)``; a vendor's fixed port that is taken (another bridge, the real device's
    software) falls back to a free port with a warning, as the endpoints then show. Returns the server
    and its bound host and port."""
    import errno

    server = make(port)
    try:
        host, bound = await server.start()
    except OSError as exc:
        if exc.errno != errno.EADDRINUSE or port == 0:
            raise
        log.warning("%s: TCP port %d is taken; serving on a free port instead (clients that only try %d "
                    "will not find it)", name, port, port)
        server = make(0)
        host, bound = await server.start()
    return server, host, bound
