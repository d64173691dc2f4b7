"""What the console costs while nobody looks: nothing is encoded, no camera picture rendered, no
sonar topic listened to; a page turns them on, and closing it turns them off again.

An in-process bridge (the default scenario, real time) with its console, and a page-like
WebSocket client (aiohttp)."""

from __future__ import annotations

import asyncio
import json

import aiohttp

from hilsim.resources import find_scenario
from hilsim.runtime.bridge import Bridge


def test_nothing_is_built_for_no_page_and_a_page_turns_it_on_and_off():
    async def go() -> dict:
        b = Bridge(find_scenario(None), console=0, status_interval=0)
        await b.start()
        out: dict = {}
        try:
            att = b.attached
            hub, camera = att.console.hub, att.camera
            await b.run(1.0)
            out["idle"] = (hub.ticks, camera.frames, b.observers.observed("sonar/sonar_ddf"),
                           b.observers.observed("reading/depth"))
            async with aiohttp.ClientSession() as s, s.ws_connect(att.url + "ws") as ws:
                await ws.send_str(json.dumps({"op": "camera", "show": True}))
                run = asyncio.ensure_future(b.run(b.vehicle.state.time + 2.0))
                kinds: dict[str, int] = {}
                while not run.done():
                    try:
                        msg = await asyncio.wait_for(ws.receive(), 0.5)
                    except asyncio.TimeoutError:
                        continue
                    if msg.type == aiohttp.WSMsgType.TEXT:
                        k = json.loads(msg.data)["type"]
                    elif msg.type == aiohttp.WSMsgType.BINARY:
                        k = json.loads(msg.data[4:4 + int.from_bytes(msg.data[:4], "big")])["type"]
                    else:
                        break
                    kinds[k] = kinds.get(k, 0) + 1
                await run
                out["open"] = (hub.ticks, camera.frames, b.observers.observed("sonar/sonar_ddf"),
                               b.observers.observed("reading/depth"), kinds)
            await asyncio.sleep(0.3)                         # the server sees the page go
            ticks, frames = hub.ticks, camera.frames
            await b.run(b.vehicle.state.time + 1.0)
            out["closed"] = (hub.ticks - ticks, camera.frames - frames, b.observers.observed("sonar/sonar_ddf"),
                             b.observers.observed("reading/depth"))
        finally:
            await b.close()
        return out

    out = asyncio.run(asyncio.wait_for(go(), 60))
    assert out["idle"] == (0, 0, False, False), out
    ticks, frames, sonar, reading, kinds = out["open"]
    assert ticks >= 10 and frames >= 2 and sonar and reading, out
    assert kinds.get("state", 0) >= 10 and kinds.get("camera", 0) >= 2 and kinds.get("hello") == 1, kinds
    assert kinds["state"] <= 25                              # at most 10 updates a second
    assert out["closed"][0] <= 1 and out["closed"][1] <= 1 and out["closed"][2:] == (False, False), out


def test_the_camera_keeps_its_rate_when_its_first_picture_starts_the_render_worker(tmp_path):
    """A scenario without a sonar device starts the render worker for the console's first camera
    picture (about 1 s): that start is not a render's cost, so the feed does not stretch its period
    to it (at SHARE 0.1 it waited over 10 s for the second picture)."""
    src = find_scenario(None).read_text()
    scn = tmp_path / "scenario.toml"
    scn.write_text(src[: src.index("# ---- devices")]
                   + '\n[[devices]]\nname = "depth"\nprotocol = "modbus-keller"\ntransport = ["tcp"]\nport = 0\n')

    async def go() -> int:
        b = Bridge(scn, console=0, status_interval=0, run_dir=tmp_path / "run")
        await b.start()
        try:
            assert b.worker.pid is None  # no device renders: the worker is not running
            camera = b.attached.camera
            run = asyncio.ensure_future(b.run(None))
            camera.want("page", 4.0)
            loop = asyncio.get_running_loop()
            end = loop.time() + 15.0
            while camera.frames < 1 and loop.time() < end:   # the first picture, the worker's start
                await asyncio.sleep(0.05)
            first = camera.frames
            await asyncio.sleep(3.0)
            camera.unwant("page")
            b.stop()
            await run
            return camera.frames - first
        finally:
            await b.close()

    more = asyncio.run(asyncio.wait_for(go(), 60))
    assert more >= 3, more  # 4 Hz asked: at least 3 pictures in the 3 s after the first
