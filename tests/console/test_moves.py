"""A timeline ``move`` reaches the viewers: the MCAP recording's ``/world`` (read back with the
independent ``mcap`` reader, the SceneUpdate decoded with protobuf from the schema inside the
file) and the console's pages (their WebSocket messages, and the page itself in Chromium).

One in-process bridge in real time on the water tank with a console and an MCAP recording; at
``MOVE_S`` the timeline moves the cuboid and turns it. Where it must be comes from the scenario
file's numbers (its size, the timeline's position and heading), not from the code that moved it.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

mcap_reader = pytest.importorskip("mcap.reader")
aiohttp = pytest.importorskip("aiohttp")

from hilsim.resources import find_scenario  # noqa: E402
from hilsim.runtime.bridge import Bridge  # noqa: E402
from tests.test_mcap import message_class, read  # noqa: E402

MOVE_S, RUN_S = 1.0, 2.2
SIZE = np.array([0.55, 0.40, 0.30])          # the scenario's cuboid, size_m
BEFORE = np.array([0.275, 0.0, 2.85])        # its position_m
AFTER, YAW_DEG = np.array([1.5, -0.8, 2.85]), 30.0
BASE = find_scenario("water_tank").read_text()
SCENARIO = BASE[: BASE.index("# ---- devices")] + f'''
[[devices]]
name = "depth"
protocol = "modbus-keller"
transport = ["tcp"]
port = 0

[[timeline]]
at_s = {MOVE_S}
action = "move"
object = "cuboid"
position_m = [{AFTER[0]}, {AFTER[1]}, {AFTER[2]}]
orientation_deg = [0.0, 0.0, {YAW_DEG}]
'''


def corners(position: np.ndarray, yaw_deg: float) -> np.ndarray:
    """(8, 3) [m] NED corners of the cuboid at ``position`` turned ``yaw_deg`` about down."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    return position + (signs * SIZE / 2) @ rz.T


def same_points(a, b, tol: float = 1e-3) -> bool:
    """Whether the point sets ``a`` and ``b`` (any order, repeats allowed) are the same."""
    a, b = np.unique(np.round(np.asarray(a, float), 4), axis=0), np.asarray(b, float)
    return len(a) == len(b) and all(np.min(np.linalg.norm(b - p, axis=1)) < tol for p in a)


def outline(obj: dict, key: str, cols: list[int], position, yaw) -> bool:
    """Whether the console's outline ``obj[key]`` is the convex hull of the corners' ``cols``
    (a box's projection: its 4 extreme corners in the top view, 4 or 6 in the side view)."""
    from scipy.spatial import ConvexHull

    pts = corners(position, yaw)[:, cols]
    hull = pts[ConvexHull(pts).vertices]
    return same_points(obj[key], hull)


async def _page(url: str, got: list, stop: asyncio.Event) -> None:
    async with aiohttp.ClientSession() as s, s.ws_connect(url.replace("http", "ws") + "ws") as ws:
        while not stop.is_set():
            try:
                msg = await asyncio.wait_for(ws.receive(), 0.2)
            except asyncio.TimeoutError:
                continue
            if msg.type == aiohttp.WSMsgType.TEXT:
                m = json.loads(msg.data)
                if m["type"] in ("hello", "scene"):
                    got.append(m)
            elif msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR):
                return


@pytest.fixture(scope="module")
def moved(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("moves")
    scn = tmp / "scenario.toml"
    scn.write_text(SCENARIO)
    out: dict = {"mcap": tmp / "run.mcap", "early": [], "late": [], "browser": None}

    async def go() -> None:
        b = Bridge(scn, console=0, record_mcap=out["mcap"], status_interval=0)
        await b.start()
        stop, ready = asyncio.Event(), threading.Event()
        try:
            url = b.attached.url
            early = asyncio.ensure_future(_page(url, out["early"], stop))   # open before the move
            browser = asyncio.get_running_loop().run_in_executor(None, browser_objects, url, ready)
            while not ready.is_set() and not browser.done():   # the browser's page has its hello
                await asyncio.sleep(0.05)
            run = asyncio.ensure_future(b.run(RUN_S))
            while b.now() < MOVE_S + 0.4:
                await asyncio.sleep(0.05)
            late = asyncio.ensure_future(_page(url, out["late"], stop))     # opened after it
            await run
            out["browser"] = await browser
            stop.set()
            await asyncio.gather(early, late)
            out["fired"] = list(b.timeline.fired)
        finally:
            stop.set()
            await b.close()

    asyncio.run(asyncio.wait_for(go(), 120))
    return out


CHROMIUM = "/usr/bin/chromium"


def poll(cond, timeout: float) -> None:
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, "the page did not get there"
        time.sleep(0.05)


def browser_objects(url: str, ready: threading.Event) -> tuple[list, list] | None:
    """The objects the page (Debian's Chromium, through Playwright) draws with its hello (then sets
    ``ready``) and after its first ``scene`` message; None where there is no browser."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    if not os.path.exists(CHROMIUM):
        return None
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--headless", "--no-sandbox", "--disable-gpu"])
        try:
            pg = browser.new_page()
            errors: list[str] = []
            pg.on("pageerror", lambda e: errors.append(str(e)))
            pg.goto(url)
            stats = lambda: pg.evaluate("window.hilsimConsole || {}")  # noqa: E731 (the CSP allows no eval)
            poll(lambda: stats().get("objects"), 20)
            before = stats()["objects"]
            ready.set()
            poll(lambda: stats().get("scenes", 0) > 0, 30)
            pg.wait_for_timeout(300)   # a state after the scene: the views drawn with it
            after = stats()
            assert not errors and not after["errors"], (errors, after["errors"])
            return list(before), list(after["objects"])
        finally:
            ready.set()
            browser.close()


def test_the_recording_shows_the_cuboid_where_it_moved_from_the_move_on(moved):
    assert [a for _, a in moved["fired"]] == ["move"]
    topics, meta = read(moved["mcap"])
    epoch = float(meta["hilsim"]["epoch_s"])
    schema = topics["/world"][0][0]
    SceneUpdate = message_class(schema.name, schema.data)
    scenes = [(m.log_time / 1e9 - epoch, SceneUpdate.FromString(m.data)) for _, _, m in topics["/world"]]
    assert len(scenes) == 2
    (t0, first), (t1, second) = scenes
    assert t0 == pytest.approx(0.0, abs=1e-6) and t1 == pytest.approx(MOVE_S, abs=0.05)

    def cuboid(scene):
        e = next(e for e in scene.entities if e.id == "cuboid")
        assert e.frame_id == "ned"
        return np.array([[p.x, p.y, p.z] for p in e.triangles[0].points])

    assert same_points(cuboid(first), corners(BEFORE, 0.0))
    assert same_points(cuboid(second), corners(AFTER, YAW_DEG))
    # the whole scene again (a viewer seeking past the move reads only the last /world): the rest as it was
    assert [e.id for e in second.entities] == [e.id for e in first.entities]
    floor = [next(e for e in s.entities if e.id == "floor").triangles[0].points for s in (first, second)]
    assert [(p.x, p.y, p.z) for p in floor[0]] == [(p.x, p.y, p.z) for p in floor[1]]


def test_open_pages_get_the_moved_outline_and_new_pages_see_it_in_their_hello(moved):
    early, late = moved["early"], moved["late"]
    assert [m["type"] for m in early] == ["hello", "scene"]
    hello, scene = early
    assert scene["object"] == "cuboid" and scene["t"] == pytest.approx(MOVE_S, abs=0.05)
    old = next(o for o in hello["objects"] if o["name"] == "cuboid")
    new = next(o for o in scene["objects"] if o["name"] == "cuboid")
    assert outline(old, "top", [0, 1], BEFORE, 0.0) and outline(old, "side", [0, 2], BEFORE, 0.0)
    assert outline(new, "top", [0, 1], AFTER, YAW_DEG) and outline(new, "side", [0, 2], AFTER, YAW_DEG)
    lo, hi = corners(AFTER, YAW_DEG).min(axis=0), corners(AFTER, YAW_DEG).max(axis=0)
    np.testing.assert_allclose(new["bounds"], [lo, hi], atol=1e-3)
    others = lambda objs: [o for o in objs if o["name"] != "cuboid"]  # noqa: E731
    assert others(scene["objects"]) == others(hello["objects"])
    assert [m["type"] for m in late] == ["hello"]
    assert next(o for o in late[0]["objects"] if o["name"] == "cuboid") == new


def test_the_page_in_a_browser_draws_the_cuboid_where_it_is_now(moved):
    if moved["browser"] is None:
        pytest.skip("no Chromium / Playwright here")
    before, after = (next(o for o in objs if o["name"] == "cuboid") for objs in moved["browser"])
    assert outline(before, "top", [0, 1], BEFORE, 0.0)
    assert outline(after, "top", [0, 1], AFTER, YAW_DEG) and outline(after, "side", [0, 2], AFTER, YAW_DEG)
