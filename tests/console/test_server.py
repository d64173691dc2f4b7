"""The console's server from the outside: what it serves, what it refuses, floods and bad input.

Against a running ``hilsim run`` (the shared subprocess), with aiohttp's client: a page's
WebSocket gets the hello, states and sonar frames; anything but the page's commands is
answered with an error message (never a traceback), other sites and other files are refused,
a flood of WebSockets is bounded and the bridge keeps serving through it all.
"""

from __future__ import annotations

import asyncio
import json
import struct

import aiohttp
import pytest

from tests.console.conftest import console_url


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 60))


async def _next_text(ws, kind: str, timeout: float = 5.0) -> dict:
    async def go() -> dict:
        while True:
            msg = await ws.receive()
            if msg.type == aiohttp.WSMsgType.TEXT:
                m = json.loads(msg.data)
                if m.get("type") == kind:
                    return m
            elif msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR):
                raise AssertionError(f"closed while waiting for {kind}")
    return await asyncio.wait_for(go(), timeout)


def test_the_page_and_its_assets_and_nothing_else(console_bridge):
    url = console_url(console_bridge)

    async def go():
        async with aiohttp.ClientSession() as s:
            async with s.get(url) as r:
                body = await r.text()
                assert r.status == 200 and "console.js" in body
                csp = r.headers["Content-Security-Policy"]
                assert "connect-src 'self'" in csp and "default-src 'none'" in csp
                assert "http" not in body.replace('href="/', "").split("<body>")[0].lower().replace("http-equiv", "")
            for asset in ("console.js", "console.css"):
                async with s.get(url + "static/" + asset) as r:
                    assert r.status == 200
                    text = await r.text()
                    assert "//cdn" not in text and "https://" not in text   # offline: nothing from elsewhere
            for bad in ("static/../../pyproject.toml", "static/%2e%2e%2fpyproject.toml", "static/index.html.bak",
                        "static/__init__.py", "../etc/passwd", "static/..%2f..%2f__init__.py"):
                async with s.get(url + bad) as r:
                    assert r.status in (400, 403, 404), bad
            async with s.post(url + "ws", data=b"x" * 10000) as r:
                assert r.status in (405, 413)
    run(go())


def test_a_page_websocket_gets_hello_state_and_sonar_frames(console_bridge):
    url = console_url(console_bridge)

    async def go():
        async with aiohttp.ClientSession() as s, s.ws_connect(url + "ws") as ws:
            hello = await _next_text(ws, "hello")
            assert hello["thrusters"][0] == "front_left" and any(o["name"] == "cuboid" for o in hello["objects"])
            assert {m["fault"] for m in hello["faults_menu"]} >= {"dropout", "stuck", "noise", "silent", "fail"}
            state = await _next_text(ws, "state")
            assert 0.0 <= state["vehicle"]["depth_m"] <= 3.0 and "console" in state["devices"]   # in the tank
            while True:
                msg = await asyncio.wait_for(ws.receive(), 5)
                if msg.type == aiohttp.WSMsgType.BINARY:
                    (n,) = struct.unpack(">I", msg.data[:4])
                    h = json.loads(msg.data[4:4 + n])
                    if h["type"] == "sonar":
                        assert len(msg.data) - 4 - n == h["shape"][0] * h["shape"][1]
                        break
    run(go())


@pytest.mark.parametrize("payload, needle", [
    ("{", "not JSON"),
    ('{"op": "eval", "code": "import os"}', "unknown op"),
    ('{"op": "fault", "target": "depth", "fault": "dropout", "path": "/etc/passwd"}', "takes no path"),
    ('{"op": "fault", "target": "nosuch", "fault": "dropout"}', "menu"),
    (b"\x00\x01binary", "JSON text"),
])
def test_bad_messages_get_an_error_message_and_the_page_stays(console_bridge, payload, needle):
    url = console_url(console_bridge)

    async def go():
        async with aiohttp.ClientSession() as s, s.ws_connect(url + "ws") as ws:
            await _next_text(ws, "hello")
            await (ws.send_bytes(payload) if isinstance(payload, bytes) else ws.send_str(payload))
            err = await _next_text(ws, "error")
            assert needle in err["message"] and "Traceback" not in err["message"]
            await _next_text(ws, "state")                     # still served
    run(go())


def test_oversize_messages_close_only_that_page_and_a_command_flood_is_throttled(console_bridge):
    url = console_url(console_bridge)

    async def go():
        async with aiohttp.ClientSession() as s:
            async with s.ws_connect(url + "ws") as ws:
                await _next_text(ws, "hello")
                await ws.send_str("x" * 100_000)
                msg = await asyncio.wait_for(ws.receive(), 5)
                while msg.type not in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED):
                    msg = await asyncio.wait_for(ws.receive(), 5)
            async with s.ws_connect(url + "ws") as ws:
                await _next_text(ws, "hello")
                for _ in range(200):
                    await ws.send_str('{"op": "camera", "show": false}')
                err = await _next_text(ws, "error")
                assert "too many commands" in err["message"]
    run(go())


def test_other_sites_cannot_open_the_websocket(console_bridge):
    url = console_url(console_bridge)

    async def go():
        async with aiohttp.ClientSession() as s:
            with pytest.raises(aiohttp.WSServerHandshakeError) as exc:
                await s.ws_connect(url + "ws", headers={"Origin": "http://evil.example"})
            assert exc.value.status == 403
            host = url.split("//", 1)[1].rstrip("/")
            async with s.ws_connect(url + "ws", headers={"Origin": f"http://{host}"}) as ws:  # the page's own
                await _next_text(ws, "hello")
    run(go())


def test_a_flood_of_websockets_is_bounded_and_the_bridge_keeps_serving(console_bridge):
    url = console_url(console_bridge)

    async def go():
        async with aiohttp.ClientSession() as s:
            opened, refused = [], 0
            for _ in range(20):
                try:
                    opened.append(await s.ws_connect(url + "ws"))
                except aiohttp.WSServerHandshakeError as exc:
                    assert exc.status == 503
                    refused += 1
            assert len(opened) == 8 and refused == 12           # max_pages = 8
            for ws in opened:                                   # they never read: frames are dropped, not queued
                pass
            await asyncio.sleep(1.5)
            for ws in opened:
                await ws.close()
            await asyncio.sleep(0.3)
            async with s.ws_connect(url + "ws") as ws:          # a slot is free again
                state = await _next_text(ws, "state")
                assert state["devices"]["console"]["refused"] >= 12
    run(go())
    assert console_bridge.proc.poll() is None
    assert "Traceback" not in console_bridge.log()


def test_a_connection_flood_is_bounded_and_idle_connections_do_not_hold_the_console(console_bridge):
    import socket
    import time

    host, port = console_url(console_bridge).split("//", 1)[1].rstrip("/").rsplit(":", 1)
    socks = []
    for _ in range(60):                                      # more than the console's 32 connections
        s = socket.create_connection((host, int(port)), timeout=5)
        socks.append(s)
    time.sleep(0.5)
    closed = 0
    for s in socks:
        s.setblocking(False)
        try:
            closed += s.recv(1, socket.MSG_PEEK) == b""
        except BlockingIOError:
            pass
        except OSError:
            closed += 1
    assert 60 - closed <= 32 and closed >= 28, closed       # beyond the limit: closed at once
    for s in socks:
        s.close()
    time.sleep(0.3)

    async def still_served():
        async with aiohttp.ClientSession() as s, s.ws_connect(console_url(console_bridge) + "ws") as ws:
            state = await _next_text(ws, "state")
            # the endpoints table's last error line: what the log said last about the device
            assert "client limit 32 reached" in state["devices"]["console"]["last_error"]
    run(still_served())
    assert "console: refused" in console_bridge.log() and "client limit 32 reached" in console_bridge.log()


def test_a_page_that_stops_reading_loses_frames_instead_of_queueing_them(console_bridge):
    import socket
    import time

    url = console_url(console_bridge)
    host, port = url.split("//", 1)[1].rstrip("/").rsplit(":", 1)

    async def dropped() -> float:
        async with aiohttp.ClientSession() as s, s.ws_connect(url + "ws") as ws:
            return (await _next_text(ws, "state"))["devices"]["console"]["dropped"]

    before = run(dropped())
    stalled = socket.socket()
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)     # a page that reads nothing
    stalled.connect((host, int(port)))
    stalled.sendall(f"GET /ws HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                    "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
    try:
        time.sleep(4.0)                                                  # states and sonar frames keep coming
        after = run(dropped())
    finally:
        stalled.close()
    assert after - before >= 10, (before, after)                        # newer updates replaced unsent ones
    assert console_bridge.proc.poll() is None
