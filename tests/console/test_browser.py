"""The console in a real browser against a running bridge (``hilsim run`` in a subprocess).

Debian's chromium, driven by Playwright for Python (no browser is ever downloaded: the
executable is /usr/bin/chromium). The page is loaded once; the tests then check what a person
would see: no JavaScript errors, a sonar fan that changes frame to frame and whose bright
region moves when the vehicle moves, a thruster bar that follows a command sent over CAN, the
fault button that silences the Keller on Modbus and the clear button that restores it, and a
screenshot (``HILSIM_CONSOLE_SHOT=path`` keeps a copy, e.g. docs/console.png).
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np
import pytest

from tests.console.conftest import console_url

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--no-first-run"]

if not os.path.exists(CHROMIUM):
    pytest.skip(f"{CHROMIUM} is missing (apt-get install chromium; .ci/run installs it)", allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (the test extra)")
can = pytest.importorskip("can")
cantools = pytest.importorskip("cantools")


def wait_for(cond, timeout: float = 10.0, step: float = 0.1):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = cond()
        if v:
            return v
        time.sleep(step)
    return cond()


@pytest.fixture(scope="module")
def bridge(console_bridge):
    return console_bridge


@pytest.fixture(scope="module")
def page(bridge):
    url = console_url(bridge)
    problems: list[str] = []
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            pg = browser.new_page(viewport={"width": 1400, "height": 1250})
            pg.on("pageerror", lambda e: problems.append(f"pageerror: {e}"))
            pg.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
            pg.goto(url)
            pg.problems = problems  # type: ignore[attr-defined]
            pg.wait_for_selector("#thr-0", timeout=15000)
            yield pg
        finally:
            browser.close()


def stats(pg) -> dict:
    return pg.evaluate("window.hilsimConsole")


SONAR = "sonar_ddf"
BRIGHT_JS = """(id) => {
  const c = document.getElementById(id), d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  let n = 0, sy = 0, sx = 0, h = 0;
  for (let i = 0; i < d.length; i += 4) {
    h = (h * 31 + d[i] + 7 * d[i + 1]) % 1000000007;
    if (d[i] > 200 && d[i + 1] > 120) { const p = i / 4; n++; sy += Math.floor(p / c.width); sx += p % c.width; }
  }
  return {n, y: n ? sy / n : null, x: n ? sx / n : null, hash: h, frame: Number(c.dataset.frameIndex || -1)};
}"""


def test_the_page_shows_the_bridge_live_without_javascript_errors(page, bridge):
    assert wait_for(lambda: stats(page)["sonarFrames"].get(SONAR, 0) >= 5, 20), stats(page)
    heads = {e["device"] for e in bridge.endpoints if e["protocol"] in ("ddf-stream", "oculus", "aris")}
    assert wait_for(lambda: all(stats(page)["sonarFrames"].get(h, 0) >= 2 for h in heads), 20), stats(page)
    s = stats(page)
    assert s["states"] >= 5 and not s["errors"] and not s["serverErrors"]
    rows = page.eval_on_selector_all("#endpoints tbody tr", "rs => rs.map(r => r.dataset.device)")
    assert set(rows) >= {e["device"] for e in bridge.endpoints} and "console" in rows
    # live counts: the DDF server counts frames it served (this page's own sonar view is not a DDF client)
    assert page.eval_on_selector_all("#thrusters tbody tr", "rs => rs.length") == 8
    assert float(page.text_content("#nav-depth")) == pytest.approx(1.5, abs=0.3)
    assert page.eval_on_selector_all("#faults button.inject", "bs => bs.length") >= 5
    assert not page.problems, page.problems


def test_a_screenshot(page, tmp_path):
    shot = tmp_path / "console.png"
    page.evaluate("window.scrollTo(0, 0)")  # taken before the tests below move the vehicle
    assert wait_for(lambda: stats(page)["sonarFrames"].get(SONAR, 0) > 0 and stats(page)["cameraFrames"] > 0, 10)
    page.screenshot(path=str(shot), full_page=False)
    from PIL import Image

    with Image.open(shot) as im:
        assert im.size == (1400, 1250)
        assert len(np.unique(np.asarray(im.convert("L").resize((64, 64))))) > 20   # not a blank page
    keep = os.environ.get("HILSIM_CONSOLE_SHOT")
    if keep:  # a palette PNG: small enough for the README
        Path(keep).parent.mkdir(parents=True, exist_ok=True)
        with Image.open(shot) as im:
            im.convert("RGB").quantize(128).save(keep, optimize=True)


def test_the_sonar_fan_changes_frame_to_frame(page):
    a = page.evaluate(BRIGHT_JS, f"sonar-{SONAR}")
    b = wait_for(lambda: (x := page.evaluate(BRIGHT_JS, f"sonar-{SONAR}"))["frame"] > a["frame"] and x, 5)
    assert b, "no new frame drawn"
    assert b["hash"] != a["hash"], "the canvas did not change with a new frame"
    assert a["n"] > 20, "no bright echo in the fan"


def _send_duty(client, dbc, cids, duty: float, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for cid in cids:
            m = dbc.get_message_by_name(f"VESC{cid}_SET_DUTY")
            client.send(can.Message(arbitration_id=m.frame_id, data=m.encode({"duty": duty}), is_extended_id=True))
        time.sleep(0.05)


@pytest.fixture(scope="module")
def can_client(bridge):
    from hilsim.protocols.vesc_can import dbc_path

    e = next(x for x in bridge.endpoints if x["device"] == "vesc_can")
    client = can.Bus(interface="socketcand", channel=e["channel"], host=e["host"], port=e["port"])
    time.sleep(0.3)  # past the server's raw-mode grace
    yield client, cantools.database.load_file(str(dbc_path()))
    client.shutdown()


def test_a_thruster_bar_follows_a_command_sent_over_can(page, can_client):
    client, dbc = can_client
    assert abs(float(page.get_attribute("#thr-1-rpm", "data-value"))) < 0.05
    _send_duty(client, dbc, [2], 0.6, 1.5)                  # front_right = VESC controller 2
    rpm = float(page.get_attribute("#thr-1-rpm", "data-value"))
    cmd = float(page.get_attribute("#thr-1-cmd", "data-value"))
    assert rpm > 0.3 and cmd == pytest.approx(0.6, abs=0.01), (rpm, cmd)
    assert "vesc_can" in page.text_content("#thr-1-src")
    assert abs(float(page.get_attribute("#thr-0-rpm", "data-value"))) < 0.05   # the others stay at rest
    # no more commands: the watchdog stops the thruster and the bar follows it down
    assert wait_for(lambda: abs(float(page.get_attribute("#thr-1-rpm", "data-value"))) < 0.05, 5)


def test_the_bright_region_moves_when_the_vehicle_moves(page, can_client):
    client, dbc = can_client
    before = page.evaluate(BRIGHT_JS, f"sonar-{SONAR}")
    depth0 = float(page.text_content("#nav-depth"))
    _send_duty(client, dbc, [5, 6, 7, 8], 0.8, 3.0)         # the four vertical thrusters push it down
    moved = wait_for(lambda: (x := page.evaluate(BRIGHT_JS, f"sonar-{SONAR}"))["n"] > 20
                     and x["y"] - before["y"] > 8 and x, 5)
    assert moved, (before, page.evaluate(BRIGHT_JS, f"sonar-{SONAR}"))
    assert float(page.text_content("#nav-depth")) > depth0 + 0.1
    # down, closer to the floor and the cuboid: their echoes move towards the fan's apex (the bottom)


def _keller_p1(bridge) -> float:
    from pymodbus.client import ModbusTcpClient

    e = next(x for x in bridge.endpoints if x["device"] == "depth" and x["transport"] == "tcp")
    host, port = e["address"].rsplit(":", 1)
    c = ModbusTcpClient(host, port=int(port), timeout=1)
    try:
        c.connect()
        rr = c.read_holding_registers(0x0002, count=2, device_id=1)
        if rr.isError():
            return math.nan
        return float(c.convert_from_registers(rr.registers, c.DATATYPE.FLOAT32))
    finally:
        c.close()


def test_the_fault_button_silences_the_keller_and_clear_restores_it(page, bridge):
    assert math.isfinite(_keller_p1(bridge))
    page.click("#faults button.inject[data-target='depth'][data-fault='dropout']")
    assert wait_for(lambda: not math.isfinite(_keller_p1(bridge)), 5), "P1 still reads a value"
    assert wait_for(lambda: "dropout on depth" in page.text_content("#active-faults"), 3)
    page.click("#faults button.clear[data-target='depth'][data-fault='dropout']")
    assert wait_for(lambda: math.isfinite(_keller_p1(bridge)), 5), "P1 did not come back"
    assert wait_for(lambda: "dropout" not in page.text_content("#active-faults"), 3)
    assert "fault dropout on depth injected" in bridge.log() or "dropout" in bridge.log()
    assert not page.problems, page.problems
