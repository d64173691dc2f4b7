"""GNSS model: geodetic conversion against the standard series, no fix under water, fix after surfacing."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from hilsim.config import ConfigError
from hilsim.resources import find_scenario
from hilsim.sim.gnss import Gnss, geodetic_to_ned, load_gnss_profile, ned_to_geodetic
from hilsim.sim.rig import profile_path
from hilsim.sim.scenario import GeodeticOrigin, load_scenario
from hilsim.sim.state import VehicleState


@pytest.fixture(scope="module")
def tank():
    s = load_scenario(find_scenario("water_tank"))
    m = s.sensor("gnss")
    return s, m, load_gnss_profile(profile_path(s, m))


def _state(t: float, z: float, x: float = 0.0, v=(0.0, 0.0, 0.0), yaw: float = 0.0) -> VehicleState:
    return VehicleState(t, np.array([x, 0.0, z]), np.array([0.0, 0.0, yaw]), np.array(v, float))


def test_degree_lengths_match_the_standard_series() -> None:
    """Length of a degree of latitude / longitude on WGS84 (the usual cosine series)."""
    for lat in (0.0, 36.0106, 59.9, -45.0):
        phi = math.radians(lat)
        m_lat = 111132.954 - 559.822 * math.cos(2 * phi) + 1.175 * math.cos(4 * phi)
        m_lon = 111412.84 * math.cos(phi) - 93.5 * math.cos(3 * phi) + 0.118 * math.cos(5 * phi)
        o = GeodeticOrigin(lat, 10.0, 0.0)
        lat1, lon1, alt1 = ned_to_geodetic(np.array([[m_lat, m_lon, -2.0]]), o)[0]
        assert lat1 - lat == pytest.approx(1.0, abs=2e-4)       # flat-earth over 111 km: ~1e-4 deg
        assert lon1 - 10.0 == pytest.approx(1.0, abs=2e-4)
        assert alt1 == 2.0
        small = ned_to_geodetic(np.array([[m_lat / 1000, m_lon / 1000, 0.0]]), o)[0]   # 111 m: exact to 1e-8
        assert small[0] - lat == pytest.approx(1e-3, abs=1e-8) and small[1] - 10.0 == pytest.approx(1e-3, abs=1e-8)
        assert geodetic_to_ned(small[0], small[1], 0.0, o) == pytest.approx([m_lat / 1000, m_lon / 1000, 0.0], abs=1e-6)


def test_tank_origin_and_mast(tank) -> None:
    s, m, profile = tank
    assert s.origin == GeodeticOrigin(36.0106, 129.3230, 5.0)
    assert m.mount.position[2] < 0                              # the antenna is above the body origin


def test_no_fix_under_water_fix_after_surfacing(tank) -> None:
    s, m, p = tank
    g = Gnss(p, m.mount, s.origin, seed=s.seed, name="gnss")
    rate = 1.0 / p.rate
    t = 0.0
    for _ in range(5):                                          # 1.5 m deep: antenna at 0.9 m
        f = g.sample(_state(t, 1.5))
        assert not f.fix and f.quality == 0 and f.submerged and math.isnan(f.lat_deg)
        t += rate
    surfaced = t
    first_fix = None
    while t < surfaced + p.time_to_fix + 3:                     # body at 0.1 m: antenna 0.5 m out of the water
        f = g.sample(_state(t, 0.1))
        assert not f.submerged
        if f.fix and first_fix is None:
            first_fix = t
        t += rate
    assert first_fix == pytest.approx(surfaced + p.time_to_fix, abs=1e-6)
    f = g.sample(_state(t, 1.0))                                # dives again (antenna at 0.4 m): fix lost at once
    assert not f.fix


def test_fix_statistics_follow_the_profile(tank) -> None:
    s, m, p = tank
    g = Gnss(p, m.mount, s.origin, seed=3, name="gnss")
    g.sample(_state(0.0, 0.0, x=4.0))
    fixes = [g.sample(_state(p.time_to_fix + k, 0.0, x=4.0, v=(0.5, 0.0, 0.0))) for k in range(400)]
    assert all(f.fix and f.quality == p.fix_quality for f in fixes)
    ned = np.array([geodetic_to_ned(f.lat_deg, f.lon_deg, f.alt_m, s.origin) for f in fixes])
    antenna = np.array([4.0, 0.0, 0.0]) + m.mount.position
    assert np.mean(ned, axis=0) == pytest.approx(antenna, abs=4 * p.horizontal_noise / math.sqrt(400) + 0.5)
    assert np.std(ned[:, 0]) == pytest.approx(p.horizontal_noise, rel=0.15)
    assert np.std(ned[:, 1]) == pytest.approx(p.horizontal_noise, rel=0.15)
    assert np.mean([f.speed for f in fixes]) == pytest.approx(0.5, abs=0.02)
    course = [f.course for f in fixes]
    assert math.degrees(math.atan2(np.mean(np.sin(course)), np.mean(np.cos(course)))) == pytest.approx(0.0, abs=3.0)
    assert all(4 <= f.satellites <= p.satellites + 4 and f.hdop > 0 for f in fixes)
    assert all(math.isnan(f.heading) for f in fixes)            # single antenna: no heading


def test_dual_antenna_heading(repo_root: Path) -> None:
    p = load_gnss_profile(repo_root / "devices/sensors/gnss_dual.toml")
    g = Gnss(p, origin=GeodeticOrigin(10.0, 20.0), seed=1)
    g.sample(_state(0.0, -1.0, yaw=math.radians(100.0)))
    f = g.sample(_state(p.time_to_fix, -1.0, yaw=math.radians(100.0)))
    assert f.fix and f.quality == 4
    assert math.degrees(f.heading) == pytest.approx(100.0, abs=2.0)


def test_outage_fault(tank) -> None:
    s, m, p = tank
    g = Gnss(p, m.mount, s.origin, seed=1)
    g.sample(_state(0.0, 0.0))
    assert g.sample(_state(p.time_to_fix, 0.0)).fix
    g.outage = True
    assert not g.sample(_state(p.time_to_fix + 1, 0.0)).fix
    g.outage = False
    assert not g.sample(_state(p.time_to_fix + 2, 0.0)).fix         # reacquiring
    assert g.sample(_state(2 * p.time_to_fix + 2, 0.0)).fix


@pytest.mark.parametrize("text,key", [
    ("[world]\norigin = { lat_deg = 95.0, lon_deg = 0.0 }\n", "world.origin.lat_deg"),
    ("[world]\norigin = { lat_deg = 10.0 }\n", "world.origin"),
    ("[world]\norigin = { lat_deg = 10.0, lon_deg = 1.0, altitude = 3 }\n", "world.origin.altitude"),
    ("[world]\norign = { lat_deg = 10.0, lon_deg = 1.0 }\n", "world.orign"),
])
def test_origin_errors_name_file_line_and_key(tmp_path: Path, text: str, key: str) -> None:
    f = tmp_path / "scenario.toml"
    f.write_text('name = "x"\n' + text + '\n[[objects]]\nname = "floor"\nprimitive = "plane"\nsize_m = [1.0, 1.0]\n'
                 'material = "m"\n[materials.m]\nimpedance_Pa_s_m = 8e6\n')
    with pytest.raises(ConfigError) as e:
        load_scenario(f)
    assert e.value.key == key and e.value.path == f and e.value.line in (2, 3)
