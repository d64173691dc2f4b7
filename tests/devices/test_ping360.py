"""The Ping360 scanning sonar through a running bridge, with Blue Robotics' own client
(``brping.Ping360`` from PyPI bluerobotics-ping) over the pty and over UDP: a sweep of the water
tank shows its walls at the scenario's distances within one sample and the cuboid at its
bearing; a ``device_data`` answer takes the time its samples take; bad input gets a NACK or
nothing, never a stop."""

from __future__ import annotations

import math
import re
import socket
import struct
import time

import numpy as np
import pytest

from tests.runtime.bridge_helpers import ROOT, start_bridge

brping = pytest.importorskip("brping", reason="bluerobotics-ping (brping) is a test peer: pip install -e '.[test]'")

X0, Y0, Z0 = -3.0, 0.5, 2.5         # the vehicle, heading north, 0.5 m above the floor (z = 3.0)
MOUNT_UP = 0.25                     # the ping360 mount sits 0.25 m above the body origin
C = 1482.0                          # the water tank's sound speed [m/s]
PERIOD = 888                        # sample period [25 ns ticks]: 1200 samples cover 19.7 m
DR = PERIOD * 25e-9 * C / 2         # [m] per sample


@pytest.fixture(scope="module")
def bridge(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ping360")
    text = (ROOT / "scenarios" / "water_tank" / "scenario.toml").read_text().split("\n[[devices]]")[0]
    text = re.sub(r"(\[vehicle\]\nprofile = )\"cyclops\"(\nposition_m = )\[[^\]]*\]",
                  rf'\1"neutral"\2[{X0}, {Y0}, {Z0}]', text)
    # Cyclops made neutrally buoyant (W_w = 0): with no thrust the vehicle stays where the geometry
    # below puts it, however long the sweeps take on a loaded machine
    (tmp / "vehicles").mkdir()
    cyclops = (ROOT / "devices" / "vehicles" / "cyclops.toml").read_text()
    assert 'constant_force = { value = -2.5,' in cyclops
    (tmp / "vehicles" / "neutral.toml").write_text(
        cyclops.replace('constant_force = { value = -2.5,', 'constant_force = { value = 0.0,'))
    text += ('\n[[devices]]\nname = "ping360"\nprotocol = "ping360"\nsensor = "ping360"\nudp_port = 0\n')
    (tmp / "scenario.toml").write_text(text)
    b = start_bridge(tmp, str(tmp / "scenario.toml"), "--status-interval", "0")
    yield b
    assert b.stop() == 0, b.log()[-2000:]


def endpoint(bridge, transport: str) -> dict:
    return next(e for e in bridge.endpoints if e["device"] == "ping360" and e["transport"] == transport)


@pytest.fixture(scope="module")
def serial_sonar(bridge):
    p = brping.Ping360()
    p.connect_serial(endpoint(bridge, "pty")["address"], 115200)
    assert p.initialize()  # protocol_version, then device_data
    p.set_number_of_samples(1200)
    p.set_sample_period(PERIOD)
    p.set_transmit_frequency(750)
    p.set_gain_setting(0)
    yield p
    p.iodev.close()


def wall_distance(angle_grad: int) -> float:
    """[m] from the head (x0, y0) to the tank wall along bearing ``angle`` (north 0, east 100)."""
    th = 2 * math.pi * angle_grad / 400
    c, s = math.cos(th), math.sin(th)
    out = []
    if c > 1e-9:
        out.append((10.0 - X0) / c)
    if c < -1e-9:
        out.append((-10.0 - X0) / c)
    if s > 1e-9:
        out.append((5.0 - Y0) / s)
    if s < -1e-9:
        out.append((-5.0 - Y0) / s)
    return min(out)


def onset(data: bytes, levels: int = 30) -> int:
    """The first sample within ``levels`` of the ping's brightest: the leading edge of the
    strongest echo (a surface at near-normal incidence, above the floor's grazing returns)."""
    d = np.frombuffer(bytes(data), np.uint8).astype(int)
    return int(np.argmax(d >= d.max() - levels))


def test_identity_over_the_serial_line(serial_sonar):
    info = serial_sonar.request(4)  # device_information
    assert info is not None and serial_sonar._device_type == 2  # a Ping360
    v = serial_sonar.request(5)
    assert v is not None and serial_sonar._version_major == 1


def test_a_sweep_shows_the_walls_within_one_sample(serial_sonar):
    errors = {}
    for angle in range(0, 400, 25):
        m = serial_sonar.transmitAngle(angle)
        assert m is not None and m.message_id == 2300 and serial_sonar._angle == angle
        assert serial_sonar._number_of_samples == 1200 and len(serial_sonar._data) == 1200
        errors[angle] = onset(serial_sonar._data) - wall_distance(angle) / DR
    # sample i covers [i, i + 1) x dr: the wall's leading edge falls in the sample that holds it
    assert all(-1.0 < e < 1.0 for e in errors.values()), errors


def test_the_cuboid_shows_at_its_bearing(serial_sonar):
    # the cuboid's south face (x = 0, y in [-0.2, 0.2], top at z = 2.70) is 3 m north of the head
    # (z = 2.25): the nearest point the beam (+-12.5 deg) finds on it is its top edge, 0.45 m below
    bearing = round(math.degrees(math.atan2(0.0 - Y0, 0.0 - X0)) / 0.9) % 400
    along = abs(X0) / math.cos(2 * math.pi * bearing / 400)
    face = math.hypot(along, 2.70 - (Z0 - MOUNT_UP)) / DR
    m = serial_sonar.transmitAngle(bearing)
    assert m is not None
    assert -1.0 < onset(serial_sonar._data) - face < 1.0, (onset(serial_sonar._data), face)
    # 30 gradians (27 deg) away the beam misses it: nothing that bright there
    at = np.frombuffer(bytes(serial_sonar._data), np.uint8)
    serial_sonar.transmitAngle((bearing + 30) % 400)
    off = np.frombuffer(bytes(serial_sonar._data), np.uint8)
    k = int(face)
    assert int(at[k - 2:k + 3].max()) > int(off[k - 2:k + 3].max()) + 40


def test_device_data_takes_the_time_its_samples_take(serial_sonar):
    serial_sonar.transmitAngle(0)
    times = {}
    for period in (200, 2000):
        serial_sonar.set_sample_period(period)
        t0 = time.monotonic()
        assert serial_sonar.transmitAngle(0) is not None
        times[period] = time.monotonic() - t0
    serial_sonar.set_sample_period(PERIOD)
    listen = 1200 * (2000 - 200) * 25e-9  # 54 ms more listening at the longer period
    assert times[2000] - times[200] > 0.8 * listen, times
    assert times[200] > 0.018  # the head's own overhead per ping (18 ms, from the device's sweep times)


def test_bad_input_gets_a_nack_or_nothing_and_the_sonar_keeps_answering(bridge, serial_sonar):
    path = endpoint(bridge, "pty")["address"]
    import serial as pyserial

    # an unknown id with a good checksum: NACK naming it
    head = b"BR" + struct.pack("<HHBB", 0, 4321, 0, 1)
    pkt = head + struct.pack("<H", sum(head) & 0xFFFF)
    serial_sonar.write(pkt)
    m = serial_sonar.wait_message([2], 1.0)
    assert m is not None and serial_sonar._nacked_id == 4321
    # a bad checksum: NACK; garbage: nothing
    serial_sonar.write(pkt[:-2] + b"\x00\x00")
    assert serial_sonar.wait_message([2], 1.0) is not None
    serial_sonar.write(bytes(range(256)) * 4)
    # a transducer command out of range: NACK; then it still answers
    serial_sonar.control_transducer(1, 0, 0, 11, 10, 750, 5000, 1, 0)
    assert serial_sonar.wait_message([2], 1.0) is not None
    assert serial_sonar.transmitAngle(100) is not None
    del pyserial, path


def test_udp_client_and_auto_transmit(bridge):
    host, port = endpoint(bridge, "udp")["address"].rsplit(":", 1)
    p = brping.Ping360()
    p.connect_udp(host, int(port))
    assert p.initialize()
    # a sector sweep 0..20 gradians in steps of 5: auto_device_data back and forth
    p.control_auto_transmit(1, 0, 11, 200, 750, 300, 0, 20, 5, 0)
    angles = []
    deadline = time.monotonic() + 5
    while len(angles) < 8 and time.monotonic() < deadline:
        m = p.wait_message([2301], 1.0)
        if m is not None:
            angles.append(m.angle)
            assert len(m.data) == 300
    assert angles[:8] == [0, 5, 10, 15, 20, 15, 10, 5], angles
    p.control_motor_off()
    assert p.wait_message([1], 1.0) is not None  # ack
    time.sleep(0.3)
    while p.read() is not None:  # drain what was in flight
        pass
    assert p.wait_message([2301], 0.5) is None  # stopped
    # UDP garbage is ignored; the sonar still answers
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.sendto(b"\x00" * 100, (host, int(port)))
    s.close()
    assert p.request(2300) is not None
    p.iodev.close()
