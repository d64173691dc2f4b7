"""The BlueROV2 of the ArduSub pool carries a Ping360: the shipped scenario run by ``hilsim run``
(its listening ports made free ones), its lockstep clock driven by a client playing ArduPilot's
side of the JSON backend (servo packets packed with ``struct``, all outputs at 1500 us), and Blue
Robotics' own client (``brping.Ping360``) reading scan lines over the pty and over UDP: the echo
starts at the pool wall's distance from the head, computed here from the scenario file's numbers
(walls, mount, water) read with tomllib, within one sample."""

from __future__ import annotations

import math
import re
import socket
import threading
import time
import tomllib

import numpy as np
import pytest

from tests.devices.test_ardupilot import servo
from tests.devices.test_ping360 import onset
from tests.runtime.bridge_helpers import ROOT, start_bridge

brping = pytest.importorskip("brping", reason="bluerobotics-ping (brping) is a test peer: pip install -e '.[test]'")

POOL = ROOT / "scenarios" / "ardusub_pool" / "scenario.toml"
TANK = ROOT / "scenarios" / "water_tank" / "scenario.toml"
SCN = tomllib.loads(POOL.read_text())
MOUNT = next(s for s in SCN["sensors"] if s["name"] == "ping360")
START = SCN["vehicle"]["position_m"]
C = SCN["water"]["sound_speed_m_s"]
PERIOD = 888                            # sample period [25 ns ticks]: 1200 samples cover 19.7 m
DR = PERIOD * 25e-9 * C / 2             # [m] per sample


def wall_distance(angle_grad: int) -> float:
    """[m] from the head to the first pool wall along head angle ``angle`` (0 ahead = north, the
    vehicle heading north; 100 = east), from the walls' boxes in the scenario file."""
    x0, y0 = START[0] + MOUNT["position_m"][0], START[1] + MOUNT["position_m"][1]
    th = 2 * math.pi * angle_grad / 400
    c, s = math.cos(th), math.sin(th)
    out = []
    for o in SCN["objects"]:
        if not o["name"].startswith("wall_"):
            continue
        (px, py, _), (sx, sy, _) = o["position_m"], o["size_m"]
        if sx < sy:   # a north or south wall: its face towards the centre at x = px -+ sx / 2
            face = px - math.copysign(sx / 2, px)
            if abs(c) > 1e-9 and (face - x0) / c > 0:
                out.append((face - x0) / c)
        else:
            face = py - math.copysign(sy / 2, py)
            if abs(s) > 1e-9 and (face - y0) / s > 0:
                out.append((face - y0) / s)
    return min(out)


def free_ports(text: str) -> str:
    """The scenario with every listening port (``port``, ``udp_port``) 0: free ones."""
    return re.sub(r"(?m)^(port|udp_port) = \d+", r"\1 = 0", text)


class ArduPilot(threading.Thread):
    """ArduPilot's side of the JSON backend: a servo packet (all outputs 1500 us: thrusters off),
    wait for the state, about 400 frames per wall second (the simulation's clock in lockstep)."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.settimeout(1.0)
        self.addr = ("127.0.0.1", port)
        self.stop = threading.Event()
        self.frames = 0

    def run(self) -> None:
        while not self.stop.is_set():
            self.sock.sendto(servo(self.frames + 1, [1500] * 6), self.addr)
            try:
                self.sock.recv(65536)
            except socket.timeout:
                continue
            self.frames += 1
            time.sleep(0.002)


@pytest.fixture(scope="module")
def bridge(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pool360")
    (tmp / "scenario.toml").write_text(free_ports(POOL.read_text()))
    b = start_bridge(tmp, str(tmp / "scenario.toml"), "--no-console", "--status-interval", "0")
    ap = None
    try:
        ep = next(e for e in b.endpoints if e["protocol"] == "ardupilot-json")
        ap = ArduPilot(int(ep["address"].rsplit(":", 1)[1]))
        ap.start()
        yield b
    finally:
        if ap is not None:
            ap.stop.set()
            ap.join(5)
            ap.sock.close()
        assert b.stop() == 0, b.log()[-2000:]
    assert ap.frames > 0


def endpoint(bridge, transport: str) -> dict:
    return next(e for e in bridge.endpoints if e["device"] == "ping360" and e["transport"] == transport)


def setup(p) -> None:
    assert p.initialize()  # protocol_version, then device_data
    p.set_number_of_samples(1200)
    p.set_sample_period(PERIOD)
    p.set_transmit_frequency(750)
    p.set_gain_setting(0)


def test_the_shipped_scenario_mounts_a_ping360_on_top_looking_ahead_on_its_own_udp_port():
    assert MOUNT["kind"] == "sonar" and MOUNT["profile"] == "ping360"
    assert MOUNT["orientation_deg"] == [0.0, 0.0, 0.0] and MOUNT["position_m"][0] > 0   # level, at the front
    hull_top = -0.254 / 2                                   # the BlueROV2's 254 mm frame about its centre
    assert MOUNT["position_m"][2] < hull_top                # above the frame (z down)
    dev = next(d for d in SCN["devices"] if d["protocol"] == "ping360")
    tank = next(d for d in tomllib.loads(TANK.read_text())["devices"] if d["protocol"] == "ping360")
    assert dev["sensor"] == "ping360" and dev["udp_port"] != tank["udp_port"]   # both bridges can run at once


@pytest.mark.parametrize("transport", ["pty", "udp"])
def test_scan_lines_show_the_pool_walls_at_their_distance(bridge, transport):
    p = brping.Ping360()
    e = endpoint(bridge, transport)
    if transport == "pty":
        p.connect_serial(e["address"], 115200)
    else:
        host, port = e["address"].rsplit(":", 1)
        p.connect_udp(host, int(port))
    try:
        setup(p)
        errors = {}
        # the side walls (6 m abeam) and the diagonals to them; ahead and astern the 12.4 m to the
        # end walls meets the floor's grazing echoes (the beam's lower edge reaches the floor at 12 m)
        for angle in (50, 100, 150, 250, 300, 350):
            m = p.transmitAngle(angle)
            assert m is not None and m.message_id == 2300 and p._angle == angle
            assert p._number_of_samples == 1200 and len(p._data) == 1200
            errors[angle] = onset(p._data) - wall_distance(angle) / DR
        # sample i covers [i, i + 1) x dr: the wall's leading edge falls in the sample that holds it
        assert all(-1.0 < err < 1.0 for err in errors.values()), errors
        assert wall_distance(100) == pytest.approx(6.0)          # the east wall, abeam
        d = np.frombuffer(bytes(p._data), np.uint8)
        k = round(wall_distance(350) / DR)
        assert int(d[k:k + 5].max()) > int(d[: k - 20].max()) + 40   # the wall stands out of the water before it
    finally:
        p.iodev.close()
