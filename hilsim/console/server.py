"""The console's web server: one page, its assets, and one WebSocket per page.

Built on aiohttp: its server runs on the asyncio loop it is started in (``AppRunner`` and a
listening socket of our own), so it shares the bridge's loop with every link and the scheduler and needs
no thread, no second loop and no signal handling of its own (uvicorn wants to own the
loop and the signals; Starlette would need it). One package gives HTTP, WebSockets with
back-pressure (``await send_bytes`` waits while the socket's buffer is full) and a test
client.

Exposure: it binds the bridge's address (127.0.0.1 unless ``--bind``). It serves only the
assets packed in ``hilsim/console/static`` (looked up by name in a fixed table, never a
path from the URL), sends a Content-Security-Policy that lets the page load nothing and
connect nowhere but this server, and refuses WebSockets whose ``Origin`` is another site
(so a web page elsewhere cannot drive the bridge through a browser). Bounded like the
TCP servers: at most ``max_connections`` connections (closed at once beyond; idle ones are
closed after 15 s) and ``max_pages`` WebSockets (503 beyond), refusals logged at most once
a second; each page message at most 1 kB, commands at most 20 a second per page.
"""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import time
from importlib import resources
from typing import Any, Callable

from aiohttp import WSMsgType, web

from hilsim.console.commands import Refused, fault_menu, parse_command
from hilsim.console.hub import Hub

log = logging.getLogger("hilsim.console")

ASSETS = {"index.html": "text/html", "console.js": "application/javascript", "console.css": "text/css"}
CSP = ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; "
       "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")
SEND_TIMEOUT_S = 10.0   # a page that takes nothing for this long is closed
COMMANDS_PER_S = 20.0
SNDBUF = 128 * 1024     # [bytes] kernel send buffer of each connection


def _asset(name: str) -> bytes:
    return resources.files("hilsim.console").joinpath("static", name).read_bytes()


class Page:
    """One open page: its WebSocket, one slot per kind of message, and its sender task."""

    def __init__(self, ws: web.WebSocketResponse, peer: str, transport: asyncio.Transport | None = None) -> None:
        self.ws = ws
        self.peer = peer
        self.transport = transport
        self.slots: dict[str, str | bytes] = {}
        self.wake = asyncio.Event()
        self.show_camera = False
        self.sent = 0
        self.dropped = 0
        self.refused = 0
        self._budget = COMMANDS_PER_S
        self._budget_t = time.monotonic()

    def offer(self, kind: str, data: str | bytes) -> None:
        """Put ``data`` in its slot; an unsent older item there is dropped."""
        if kind in self.slots:
            self.dropped += 1
        self.slots[kind] = data
        self.wake.set()

    def allow_command(self) -> bool:
        now = time.monotonic()
        self._budget = min(COMMANDS_PER_S, self._budget + (now - self._budget_t) * COMMANDS_PER_S)
        self._budget_t = now
        if self._budget < 1.0:
            return False
        self._budget -= 1.0
        return True

    async def send_loop(self) -> None:
        while not self.ws.closed:
            await self.wake.wait()
            self.wake.clear()
            while self.slots and not self.ws.closed:
                kind = next(iter(self.slots))
                data = self.slots.pop(kind)
                coro = self.ws.send_str(data) if isinstance(data, str) else self.ws.send_bytes(data)
                try:
                    await asyncio.wait_for(coro, SEND_TIMEOUT_S)
                except asyncio.TimeoutError:  # it took nothing for that long: drop the page
                    log.warning("console: page %s took nothing for %.0f s; closed", self.peer, SEND_TIMEOUT_S)
                    if self.transport is not None:
                        self.transport.abort()
                    raise
                self.sent += 1


class Console:
    """The console of a running bridge: ``await start()`` -> endpoint, ``await close()``."""

    def __init__(self, bridge: Any, *, port: int = 0, host: str | None = None, max_pages: int = 8,
                 max_connections: int = 32, camera: Any | None = None) -> None:
        self.bridge = bridge
        self.host: str = str(host or getattr(bridge, "bind", "127.0.0.1"))
        self.port = int(port)
        self.max_pages = int(max_pages)
        self.max_connections = max(int(max_connections), self.max_pages + 1)
        self.refused_connections = 0
        self.sent_closed = 0      # messages sent to, and dropped for, pages since closed
        self.dropped_closed = 0
        self._server: asyncio.AbstractServer | None = None
        self.hub = Hub(bridge, camera)
        self.hub.extra_status["console"] = self.status
        self.refused_pages = 0
        self.bad_messages = 0
        self.last_error = ""
        self._refuse_logged = 0.0
        self._runner: web.AppRunner | None = None
        self._menu: list[dict[str, Any]] | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def app(self) -> web.Application:
        app = web.Application(client_max_size=4096, middlewares=[_headers])
        app.router.add_get("/", self._index)
        app.router.add_get("/static/{name}", self._static)
        app.router.add_get("/ws", self._websocket)
        return app

    async def start(self) -> str:
        """Listen; returns the URL (the port is picked free when 0)."""
        self.hub.start()
        self._runner = web.AppRunner(self.app(), access_log=None, keepalive_timeout=15.0)
        await self._runner.setup()
        loop = asyncio.get_running_loop()
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            # accepted sockets inherit it: a page that stops reading backs up here, not in megabytes of kernel buffer
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SNDBUF)
            sock.bind((self.host, self.port))
            sock.listen(32)
            sock.setblocking(False)
            self._server = await loop.create_server(self._accept(self._runner.server), sock=sock)
        except BaseException:
            sock.close()
            raise
        self.port = int(sock.getsockname()[1])
        log.info("console at %s", self.url)
        return self.url

    def _accept(self, server: Any) -> Callable[[], asyncio.BaseProtocol]:
        """aiohttp's protocol for each connection, up to ``max_connections`` at once; beyond, the
        connection is closed at once (and the refusal logged at most once a second). aiohttp
        closes a connection idle for 15 s, before or between requests."""
        loop = asyncio.get_running_loop()
        pending = [0]  # connections accepted in this burst, not yet in server.connections

        def settle() -> None:
            pending[0] = 0

        def factory() -> asyncio.BaseProtocol:
            # asyncio accepts a burst of connections before any of them is registered: count those too
            if len(server.connections) + pending[0] >= self.max_connections:
                return _Refuse(self)
            if not pending[0]:
                loop.call_soon(settle)  # runs after this burst's handlers, before the next accept
            pending[0] += 1
            return server()
        return factory

    def status(self) -> dict[str, Any]:
        pages = list(self.hub.pages)
        return {"clients": len(pages), "sent": self.sent_closed + sum(p.sent for p in pages),
                "dropped": self.dropped_closed + sum(p.dropped for p in pages),
                "refused": self.refused_pages + self.refused_connections,
                "bad_messages": self.bad_messages, "ticks": self.hub.ticks,
                "tick_ms": round(self.hub.tick_seconds * 1e3, 1),
                **({"last_error": self.last_error} if self.last_error else {})}

    # -- handlers -----------------------------------------------------------------
    async def _index(self, request: web.Request) -> web.Response:
        return web.Response(body=_asset("index.html"), content_type="text/html")

    async def _static(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name not in ASSETS or name == "index.html":
            raise web.HTTPNotFound(text="no such asset")
        return web.Response(body=_asset(name), content_type=ASSETS[name])

    def _origin_ok(self, request: web.Request) -> bool:
        origin = request.headers.get("Origin")
        if origin is None:  # not a browser (a script, a test client): allowed, it is on this machine
            return True
        return origin in (f"http://{request.host}", f"https://{request.host}")

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        if not self._origin_ok(request):
            self._refuse(f"WebSocket from another site ({request.headers.get('Origin', '')[:80]}) refused")
            raise web.HTTPForbidden(text="cross-site WebSocket refused")
        if len(self.hub.pages) >= self.max_pages:
            self._refuse(f"page refused: {self.max_pages} pages open (max_pages)")
            raise web.HTTPServiceUnavailable(text=f"at most {self.max_pages} pages at once")
        ws = web.WebSocketResponse(compress=False, max_msg_size=4096, heartbeat=20.0, writer_limit=65536)
        await ws.prepare(request)
        page = Page(ws, str(request.remote), request.transport)
        self.hub.add_page(page)
        sender = asyncio.ensure_future(page.send_loop())
        try:
            page.offer("hello", json.dumps(self.hello(), separators=(",", ":")))
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    await self._command(page, msg.data)
                elif msg.type == WSMsgType.BINARY:
                    self._reject(page, "only JSON text messages are accepted")
                elif msg.type == WSMsgType.ERROR:
                    break
                if sender.done():
                    break
        except Exception as exc:  # noqa: BLE001 - a page's trouble never reaches the bridge
            self.last_error = f"page {page.peer}: {type(exc).__name__}: {exc}"[:200]
            log.warning("console: %s", self.last_error)
        finally:
            self.hub.remove_page(page)
            self.sent_closed += page.sent
            self.dropped_closed += page.dropped
            sender.cancel()
            await asyncio.gather(sender, return_exceptions=True)
            if not ws.closed:
                await ws.close()
        return ws

    def hello(self) -> dict[str, Any]:
        if self._menu is None:
            self._menu = fault_menu(self.bridge)
        return {"type": "hello", **self.hub.scene(), "faults_menu": self._menu,
                "endpoints": [e.to_json() for e in self.bridge.endpoints],
                "cameras": self.hub.camera.mounts if self.hub.camera is not None else [],
                "sonars": [d.name for d in self.bridge.devices if getattr(d, "needs_renderer", False)],
                "track": list(self.hub.track), "tick_s": 0.1}

    async def _command(self, page: Page, data: str) -> None:
        if not page.allow_command():
            self._reject(page, f"too many commands (at most {COMMANDS_PER_S:g} a second)")
            return
        try:
            cmd = parse_command(data, self._menu or fault_menu(self.bridge))
        except Refused as exc:
            self._reject(page, str(exc))
            return
        if cmd.op == "camera":
            self.hub.show_camera(page, cmd.show)
            page.offer("ack", json.dumps({"type": "ack", "op": "camera", "show": cmd.show}))
            return
        try:
            if cmd.op == "fault":
                self.bridge.faults.inject(cmd.target, cmd.fault, dict(cmd.params))
            else:
                self.bridge.faults.clear(cmd.target, cmd.fault)
        except (ValueError, KeyError, LookupError) as exc:
            self._reject(page, f"{cmd.op} {cmd.fault} on {cmd.target}: {exc}")
            return
        log.warning("console (page %s): %s %s on %s", page.peer, cmd.op, cmd.fault, cmd.target)
        page.offer("ack", json.dumps({"type": "ack", "op": cmd.op, "target": cmd.target, "fault": cmd.fault}))

    def _reject(self, page: Page, message: str) -> None:
        self.bad_messages += 1
        page.refused += 1
        page.offer("error", json.dumps({"type": "error", "message": message[:300]}))

    def _refuse(self, why: str) -> None:
        self.refused_pages += 1
        now = time.monotonic()
        if now - self._refuse_logged >= 1.0:
            self._refuse_logged = now
            log.warning("console: %s (%d refused so far)", why, self.refused_pages)

    async def close(self) -> None:
        await self.hub.close()
        if self._server is not None:
            self._server.close()
        for p in list(self.hub.pages):
            await p.ws.close()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if self._server is not None:
            await self._server.wait_closed()
            self._server = None


class _Refuse(asyncio.Protocol):
    """A connection over the console's limit: closed at once."""

    def __init__(self, console: Console) -> None:
        self.console = console

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        c = self.console
        c.refused_connections += 1
        now = time.monotonic()
        if now - c._refuse_logged >= 1.0:
            c._refuse_logged = now
            peer = transport.get_extra_info("peername")
            who = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)
            log.warning("console: refused %s: client limit %d reached (%d refused so far)", who,
                        c.max_connections, c.refused_connections + c.refused_pages)
        transport.close()


@web.middleware
async def _headers(request: web.Request, handler: Any) -> web.StreamResponse:
    resp = await handler(request)
    if isinstance(resp, web.Response) or not getattr(resp, "prepared", False):
        resp.headers["Content-Security-Policy"] = CSP
        resp.headers["X-Content-Type-Options"] = "nosniff"
        resp.headers["Referrer-Policy"] = "no-referrer"
        resp.headers["Cache-Control"] = "no-store"
    return resp
