"""The console's and the recorder's pure parts: command validation, frame encoding, fan mapping,
outlines, JSON conversion."""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest

from hilsim.console.commands import MAX_COMMAND_BYTES, Refused, parse_command
from hilsim.console.hub import MAX_BEAMS, MAX_ROWS, encode_sonar
from hilsim.console.scene import convex_hull_2d, hull_box
from hilsim.record.convert import FanMapper, jsonable, time_ns

MENU = [{"target": "depth", "fault": "dropout", "label": "depth: dropout"},
        {"target": "depth", "fault": "noise", "label": "depth: noise"},
        {"target": "thruster:front_left", "fault": "fail", "label": "thruster front_left: fail"}]


def test_the_page_commands_are_accepted():
    c = parse_command('{"op": "fault", "target": "depth", "fault": "dropout"}', MENU)
    assert (c.op, c.target, c.fault, dict(c.params)) == ("fault", "depth", "dropout", {})
    c = parse_command('{"op": "fault", "target": "depth", "fault": "noise"}', MENU)
    assert dict(c.params) == {"factor": 10.0}  # the menu's parameters, never the page's
    c = parse_command('{"op": "clear", "target": "thruster:front_left", "fault": "fail"}', MENU)
    assert (c.op, c.target) == ("clear", "thruster:front_left")
    assert parse_command('{"op": "camera", "show": false}', MENU).show is False


@pytest.mark.parametrize("data, needle", [
    (b'{"op": "camera", "show": true}', "JSON text"),
    ("x" * (MAX_COMMAND_BYTES + 1), "longer than"),
    ("{not json", "not JSON"),
    ("[" * 5000 + "]" * 5000, ""),                      # nesting: refused, never a RecursionError
    ('["fault"]', "JSON object"),
    ('{"op": "read_file", "path": "/etc/passwd"}', "unknown op"),
    ('{"op": "fault", "target": "depth", "fault": "dropout", "factor": 1e9}', "takes no factor"),
    ('{"op": "fault", "target": "depth", "fault": 3}', "needs a target and a fault"),
    ('{"op": "fault", "target": "depth", "fault": "stuck"}', "menu"),
    ('{"op": "fault", "target": "../../etc", "fault": "dropout"}', "menu"),
    ('{"op": "camera", "show": "yes"}', "show"),
    ('{"op": null}', "unknown op"),
])
def test_anything_else_is_refused_with_a_message(data, needle):
    with pytest.raises(Refused) as exc:
        parse_command(data, MENU)
    assert needle in str(exc.value)
    assert "Traceback" not in str(exc.value)


def _decode(blob: bytes) -> tuple[dict, bytes]:
    (n,) = struct.unpack(">I", blob[:4])
    return json.loads(blob[4:4 + n]), blob[4 + n:]


def test_a_sonar_frame_for_a_page_keeps_its_bright_echoes():
    ns, nb = 1000, 512
    img = np.zeros((ns, nb), np.uint8)
    img[777, 301] = 250                                  # one bright cell must survive pooling
    az = np.linspace(-0.6, 0.6, nb)
    header, payload = _decode(encode_sonar("oculus", {"t": 1.5, "image": img, "azimuths": az, "range_min": 0.1,
                                                      "range_max": 40.0, "gain_db": 12.0, "frame_index": 7}))
    rows, beams = header["shape"]
    assert rows <= MAX_ROWS and beams <= MAX_BEAMS and len(payload) == rows * beams
    out = np.frombuffer(payload, np.uint8).reshape(rows, beams)
    r, b = np.unravel_index(int(out.argmax()), out.shape)
    assert out.max() == 250 and r == 777 // math.ceil(ns / MAX_ROWS) and b == 301 // math.ceil(nb / MAX_BEAMS)
    assert len(header["azimuths"]) == beams and header["azimuths"] == sorted(header["azimuths"])
    assert abs(header["azimuths"][0] - az[:2].mean()) < 1e-4
    assert (header["device"], header["frame_index"], header["gain_db"]) == ("oculus", 7, 12.0)


def test_a_small_frame_is_sent_as_served():
    img = np.arange(96 * 64, dtype=np.uint32).astype(np.uint8).reshape(64, 96)
    header, payload = _decode(encode_sonar("ddf", {"image": img, "azimuths": np.linspace(-0.25, 0.25, 96),
                                                   "range_min": 1.0, "range_max": 5.0}))
    assert header["shape"] == [64, 96] and payload == img.tobytes() and header["gain_db"] is None


def test_fan_mapper_puts_an_echo_at_its_range_and_bearing():
    ns, nb, rmin, rmax = 200, 48, 1.0, 11.0
    az = np.linspace(math.radians(-14), math.radians(14), nb)
    fan = FanMapper(ns, az, rmin, rmax, height=300)
    img = np.zeros((ns, nb), np.uint8)
    img[100, 40] = 255                                   # range 6.0 m, starboard of centre
    out = fan(img)
    assert out.shape == fan.shape and out.dtype == np.uint8
    ys, xs = np.nonzero(out)
    assert len(ys) > 0 and out.max() == 255
    h, w = out.shape
    scale = h / rmax
    x = (xs.mean() + 0.5 - w / 2) / scale
    y = (h - ys.mean() - 0.5) / scale
    assert abs(math.hypot(x, y) - (rmin + 100.5 * (rmax - rmin) / ns)) < 0.1
    assert abs(math.atan2(x, y) - az[40]) < math.radians(0.7)
    assert out[0, 0] == 0 and out[h - 1, w // 2] == 0    # outside the fan, inside range_min


def test_outlines_and_hull():
    box = np.array([[x, y] for x in (0, 2) for y in (-1, 1)] + [[1, 0]], float)
    hull = convex_hull_2d(box)
    assert sorted(map(tuple, hull.tolist())) == [(0, -1), (0, 1), (2, -1), (2, 1)]
    hb = hull_box([[0.35, -0.25, 0.0], [-0.35, 0.25, 0.1]], margin=0.1)
    assert hb["min"][:2] == [-0.45, -0.35] and hb["max"][:2] == [0.45, 0.35]
    assert hb["max"][2] - hb["min"][2] >= 0.2             # a flat layout still gets a body height
    assert hull_box(None)["max"] == [0.45, 0.3, 0.2]


def test_jsonable_and_log_time():
    out = jsonable({"a": np.float32(1.5), "b": np.array([1, 2]), "c": float("nan"), "d": b"raw", "e": (np.int64(3),)})
    assert out == {"a": 1.5, "b": [1, 2], "c": None, "e": [3]}
    json.dumps(out, allow_nan=False)
    assert time_ns(1_700_000_000.0, 2.5) == 1_700_000_002_500_000_000


def test_a_frame_the_console_cannot_draw_is_skipped_and_said_once(caplog):
    from hilsim.console.hub import Hub
    from hilsim.runtime.observe import Observers

    class Page:
        show_camera = False

        def __init__(self):
            self.got = []

        def offer(self, kind, data):
            self.got.append(kind)

    hub = Hub.__new__(Hub)                     # only the frame path: no bridge, no loop
    hub.pages, hub.sonar, hub._sonar_sent, hub._sonar_seq, hub._bad_sonar = set(), {}, {}, {}, set()
    hub.ticks, hub.state = 0, lambda: {"type": "state"}
    obs = Observers()
    obs.subscribe("sonar/*", hub._on_sonar)
    page = Page()
    hub.pages.add(page)
    for _ in range(3):
        obs.publish("sonar/odd", {"t": 0.0, "image": np.zeros((4, 4), np.uint8)})   # no azimuths, no range
        hub.tick()
    obs.publish("sonar/good", {"t": 0.0, "image": np.zeros((4, 2), np.uint8), "azimuths": [-0.1, 0.1],
                               "range_min": 1.0, "range_max": 2.0})
    hub.tick()
    assert page.got.count("sonar:odd") == 0 and page.got.count("sonar:good") == 1
    assert sum("cannot show the frames of odd" in r.message for r in caplog.records) == 1
