"""Ping1D-like echosounder against the water tank's geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilsim.resources import find_scenario
from hilsim.sim.echosounder import Echosounder, cone_directions, load_echosounder_profile
from hilsim.sim.rig import profile_path
from hilsim.sim.scenario import load_scenario
from hilsim.sim.state import VehicleState

FLOOR_Z, CUBOID_TOP_Z = 3.0, 2.70
MOUNT = np.array([0.2, 0.0, 0.3])       # the scenario's altimeter mount


@pytest.fixture(scope="module")
def tank():
    s = load_scenario(find_scenario("water_tank"))
    m = s.sensor("altimeter")
    return s, s.build_world(), m, load_echosounder_profile(profile_path(s, m))


def _sounder(tank, seed: int = 1) -> Echosounder:
    s, world, m, p = tank
    return Echosounder(p, world, m.mount, seed=seed, name="altimeter", sound_speed_true=s.water.sound_speed)


def _at(x_sensor: float, z_body: float = 1.5, t: float = 0.0) -> VehicleState:
    """The vehicle placed so that the altimeter is at north ``x_sensor``."""
    return VehicleState(t, np.array([x_sensor - MOUNT[0], 0.0, z_body]))


def test_mount_and_profile(tank) -> None:
    _, _, m, p = tank
    assert np.allclose(m.mount.position, MOUNT)
    assert math.degrees(p.beam_width) == pytest.approx(25.0) and p.samples == 200
    dirs, ang = cone_directions(p.beam_width, 3, 12)
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0) and ang.max() == pytest.approx(1.5 * p.beam_width / 2)


def test_distance_to_the_floor_and_over_the_cuboid(tank) -> None:
    e = _sounder(tank)
    floor = [e.ping(_at(-5.0, t=0.1 * k)) for k in range(40)]
    over = [e.ping(_at(0.275, t=0.1 * k)) for k in range(40)]
    h = FLOOR_Z - (1.5 + MOUNT[2])                       # 1.2 m
    assert np.mean([p.distance for p in floor]) == pytest.approx(h, rel=0.003)
    assert np.mean([p.distance for p in over]) == pytest.approx(h - 0.30, rel=0.003)
    assert min(p.confidence for p in floor) == 100
    # the echo's peak sits in the profile bin of the distance
    for p in floor[:5] + over[:5]:
        assert len(p.profile) == 200 and p.profile.dtype == np.uint8
        peak = (int(np.argmax(p.profile)) + 0.5) * p.scan_length / 200 + p.scan_start
        assert peak == pytest.approx(p.distance, abs=p.scan_length / 200 + 0.03)
        assert np.median(p.profile) < 0.2 * p.profile.max()
        assert p.scan_start <= p.distance <= p.scan_start + p.scan_length


def test_the_beam_width_sees_the_cuboid_edge(tank) -> None:
    """0.15 m before the cuboid's front face, 0.9 m above its top: the 12.5 deg half-width reaches
    0.9 tan(12.5 deg) = 0.20 m ahead, so the first echo is the top's edge (slant 0.9-0.92 m), not the
    floor 1.2 m below; 0.3 m before the face the cone misses the cuboid."""
    e = _sounder(tank)
    near = np.mean([e.ping(_at(-0.15, t=0.1 * k)).distance for k in range(20)])
    assert 0.9 * 0.995 <= near <= 0.9 / math.cos(math.radians(12.5)) * 1.005
    far = np.mean([e.ping(_at(-0.3, t=0.1 * k)).distance for k in range(20)])
    assert far == pytest.approx(1.2, rel=0.003)


def test_no_echo_outside_the_tank(tank) -> None:
    p = _sounder(tank).ping(_at(60.0))
    assert math.isnan(p.distance) and p.confidence == 0


def test_speed_of_sound_and_manual_window(tank) -> None:
    s = tank[0]
    e = _sounder(tank)
    e.speed_of_sound = s.water.sound_speed * 1.05
    assert np.mean([e.ping(_at(-5.0, t=k)).distance for k in range(20)]) == pytest.approx(1.26, rel=0.004)
    e.speed_of_sound = s.water.sound_speed
    e.mode_auto = False
    e.scan_start, e.scan_length, e.gain_setting = 2.0, 3.0, 2
    p = e.ping(_at(-5.0))
    assert p.confidence == 0 and (p.scan_start, p.scan_length, p.gain_setting) == (2.0, 3.0, 2)
    assert p.ping_number == 21


def test_deterministic(tank) -> None:
    a, b = _sounder(tank, 5).ping(_at(-5.0)), _sounder(tank, 5).ping(_at(-5.0))
    assert a.distance == b.distance and np.array_equal(a.profile, b.profile)
