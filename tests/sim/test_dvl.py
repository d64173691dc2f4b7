"""The DVL model against the water tank's geometry (closed forms from the scenario file)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilsim.resources import find_scenario
from hilsim.sim.dvl import Dvl, figure_of_merit, load_dvl_profile, range_limits
from hilsim.sim.geometry import Pose, rpy_to_matrix
from hilsim.sim.rig import profile_path
from hilsim.sim.scenario import load_scenario
from hilsim.sim.state import VehicleState

FLOOR_Z = 3.0          # top of the floor box (scenario: centre 3.15, height 0.3)
CUBOID_TOP_Z = 2.70    # top of the cuboid (centre 2.85, height 0.30)


@pytest.fixture(scope="module")
def tank():
    s = load_scenario(find_scenario("water_tank"))
    mount = s.sensor("dvl")
    profile = load_dvl_profile(profile_path(s, mount))
    return s, s.build_world(), mount, profile


def _dvl(tank, mount: Pose | None = None, seed: int = 1) -> Dvl:
    s, world, m, profile = tank
    return Dvl(profile, world, m.mount if mount is None else mount, seed=seed, name="dvl",
               sound_speed_true=s.water.sound_speed)


def _state(x=-5.0, y=0.0, z=1.5, yaw=0.0, v=(0.0, 0.0, 0.0), w=(0.0, 0.0, 0.0), t=0.0) -> VehicleState:
    return VehicleState(t, np.array([x, y, z]), np.array([0.0, 0.0, yaw]), np.array(v, float), np.array(w, float))


def test_scenario_mount_matches_the_file(tank) -> None:
    _, _, m, profile = tank
    assert np.allclose(m.mount.position, [-0.2, 0.0, 0.35])
    assert profile.beam_tilt == pytest.approx(math.radians(22.5))
    assert sorted(round(math.degrees(a)) for a in profile.beam_azimuths) == [45, 135, 225, 315]


def test_altitude_over_the_floor_with_the_lever_arm(tank) -> None:
    dvl = _dvl(tank)
    expect = FLOOR_Z - (1.5 + 0.35)            # body origin 1.5 m above the floor, DVL 0.35 m below it
    alts, dists = [], []
    for k in range(50):
        p = dvl.ping(_state(t=0.1 * k))
        assert p.valid and p.beam_valid.all()
        alts.append(p.altitude)
        dists.append(p.distance)
    assert np.mean(alts) == pytest.approx(expect, abs=0.002)
    assert np.std(alts) < 0.01
    # each beam reaches the floor along its 22.5 deg slant
    assert np.mean(dists, axis=0) == pytest.approx([expect / math.cos(math.radians(22.5))] * 4, abs=0.003)


@pytest.mark.parametrize("yaw_deg,mount_yaw_deg", [(0.0, 0.0), (90.0, 0.0), (30.0, 45.0), (-120.0, 180.0)])
def test_velocity_north_rotated_into_the_dvl_frame(tank, yaw_deg, mount_yaw_deg) -> None:
    _, _, m, _ = tank
    mount = Pose(m.mount.position, rpy_to_matrix(0.0, 0.0, math.radians(mount_yaw_deg)))
    dvl = _dvl(tank, mount)
    yaw = math.radians(yaw_deg)
    v_world = np.array([0.3, 0.0, 0.0])                       # 0.3 m/s north
    v_body = rpy_to_matrix(0.0, 0.0, yaw).T @ v_world
    expect = (rpy_to_matrix(0.0, 0.0, yaw) @ mount.rotation).T @ v_world
    vs = np.array([dvl.ping(_state(yaw=yaw, v=v_body, t=0.1 * k)).velocity for k in range(40)])
    assert np.mean(vs, axis=0) == pytest.approx(expect, abs=0.002)
    assert np.linalg.norm(np.mean(vs, axis=0)) == pytest.approx(0.3, abs=0.002)
    # with the mounting rotation offset set to the mount's yaw, the output is back in the vehicle frame
    dvl.mounting_rotation_offset = math.radians(mount_yaw_deg)
    vs = np.array([dvl.ping(_state(yaw=yaw, v=v_body, t=0.1 * k)).velocity for k in range(40)])
    assert np.mean(vs, axis=0) == pytest.approx(v_body, abs=0.002)


def test_lever_arm_of_a_yaw_rate(tank) -> None:
    dvl = _dvl(tank)
    r = 0.5                                              # [rad/s] yaw rate, vehicle not translating
    expect = np.cross([0.0, 0.0, r], [-0.2, 0.0, 0.35])  # omega x r_mount = (0, -0.1, 0)
    vs = np.array([dvl.ping(_state(w=(0.0, 0.0, r), t=0.1 * k)).velocity for k in range(40)])
    assert np.mean(vs, axis=0) == pytest.approx(expect, abs=0.002)


def test_altitude_drops_by_the_cuboid_height(tank) -> None:
    """Low enough that all four beams land on the 0.55 x 0.40 m top (footprint +-0.14 m at 0.5 m)."""
    dvl = _dvl(tank)
    z = CUBOID_TOP_Z - 0.5 - 0.35                        # DVL 0.5 m above the cuboid's top
    x_over = 0.275 + 0.2                                 # DVL (0.2 m aft of the body origin) over the centre
    over = np.mean([dvl.ping(_state(x=x_over, z=z, t=0.1 * k)).altitude for k in range(30)])
    away = np.mean([dvl.ping(_state(x=-3.0, z=z, t=0.1 * k)).altitude for k in range(30)])
    assert over == pytest.approx(0.5, abs=0.005)
    assert away == pytest.approx(0.8, abs=0.005)
    assert away - over == pytest.approx(0.30, abs=0.006)


def test_lock_lost_past_the_range_and_when_beams_miss(tank) -> None:
    dvl = _dvl(tank)
    assert dvl.ping(_state()).valid
    dvl.range_mode = "=0"                                # 0.05-0.6 m: the floor at 1.15 m is out of range
    assert range_limits("=0", dvl.profile) == (0.05, 0.6)
    p = dvl.ping(_state())
    assert not p.valid and not p.beam_valid.any() and p.altitude == -1.0 and (p.distance == -1.0).all()
    dvl.range_mode = "auto"
    p = dvl.ping(_state(x=60.0))                        # outside the tank: nothing below
    assert not p.valid and p.interval == pytest.approx(1.0 / dvl.profile.search_rate)
    p = dvl.ping(_state(x=-5.0, z=-60.0))               # 63 m above the floor: past 50 m
    assert not p.valid


def test_rate_as_the_device(tank) -> None:
    dvl = _dvl(tank)
    assert dvl.ping(_state()).interval == pytest.approx(1 / 10.0)            # 1.15 m: range mode 1, 10 Hz
    assert dvl.ping(_state(z=2.3)).interval == pytest.approx(1 / 15.0)       # 0.35 m: range mode 0, 15 Hz
    dvl.range_mode = "wt"
    assert dvl.ping(_state()).interval == pytest.approx(1 / 2.0)


def test_figure_of_merit_of_the_vendor_example() -> None:
    """The example velocity report of Water Linked's JSON API document: its fom from its covariance."""
    cov = [[2.4471841442164077e-08, -3.3937477272871774e-09, -1.6659699175747278e-09],
           [-3.3937477272871774e-09, 1.4654466085062268e-08, 4.0409570134514183e-10],
           [-1.6659699175747278e-09, 4.0409570134514183e-10, 1.5971971523143225e-09]]
    assert figure_of_merit(np.array(cov)) == pytest.approx(0.00016016385052353144, rel=1e-6)


def test_speed_of_sound_setting_scales_distances(tank) -> None:
    s = tank[0]
    dvl = _dvl(tank)
    dvl.speed_of_sound = s.water.sound_speed * 1.1
    alt = np.mean([dvl.ping(_state(t=0.1 * k)).altitude for k in range(20)])
    assert alt == pytest.approx(1.1 * 1.15, abs=0.005)


def test_dead_reckoning_integrates_in_the_reset_frame(tank) -> None:
    dvl = _dvl(tank)
    yaw = math.radians(90.0)                     # heading east, moving forward at 0.3 m/s
    t, x = 0.0, -5.0
    dvl.reset_dead_reckoning(_state(x=x, yaw=yaw, t=t))
    while t < 10.0 - 1e-9:
        st = VehicleState(t, np.array([-5.0, 0.3 * t, 1.5]), np.array([0.0, 0.0, yaw]), np.array([0.3, 0.0, 0.0]))
        p = dvl.ping(st)
        dvl.integrate(p, st)
        t += p.interval
    dr = dvl.dead_reckoning(VehicleState(t, np.array([-5.0, 0.3 * t, 1.5]), np.array([0.0, 0.0, yaw])))
    travelled = 0.3 * (t - p.interval)           # integrated up to the last ping
    assert dr.position[0] == pytest.approx(travelled, rel=0.01)
    assert abs(dr.position[1]) < 0.03 and abs(dr.position[2]) < 0.01
    assert abs(dr.attitude[2]) < math.radians(1.0)   # yaw relative to the reset (drift only)
    dvl.reset_dead_reckoning(st)
    assert np.allclose(dvl.dead_reckoning(st).position, 0.0)


def test_same_seed_same_pings(tank) -> None:
    a, b = _dvl(tank, seed=7), _dvl(tank, seed=7)
    for k in range(5):
        pa, pb = a.ping(_state(t=0.1 * k, v=(0.2, 0.1, 0.0))), b.ping(_state(t=0.1 * k, v=(0.2, 0.1, 0.0)))
        assert np.array_equal(pa.velocity, pb.velocity) and pa.altitude == pb.altitude
    assert not np.array_equal(_dvl(tank, seed=8).ping(_state()).distance, _dvl(tank, seed=7).ping(_state()).distance)


def test_three_beams_keep_lock_two_do_not(tank) -> None:
    """Heading 45 deg, 0.5 m above the cuboid's top, the four footprints form a diamond 0.21 m around the DVL.
    With range mode 0 (0.05-0.6 m) the beams landing on the floor (0.8 m down) are out of range: three beams
    on the top keep bottom lock (the velocity and the 0.5 m altitude are still right), two do not."""
    dvl = _dvl(tank)
    dvl.range_mode = "=0"
    yaw = math.radians(45.0)
    r = rpy_to_matrix(0.0, 0.0, yaw)
    z = CUBOID_TOP_Z - 0.5 - 0.35
    v_body = r.T @ np.array([0.1, 0.0, 0.0])

    def at(dvl_x: float, dvl_y: float, k: int):
        pos = np.array([dvl_x, dvl_y, 0.0]) - r @ np.array([-0.2, 0.0, 0.0])
        return dvl.ping(VehicleState(0.1 * k, np.array([pos[0], pos[1], z]), np.array([0.0, 0.0, yaw]), v_body))

    # footprints at (0.51, 0.05), (0.09, 0.05), (0.30, -0.16) on the 0.55 x 0.40 top; (0.30, 0.26) off it
    pings = [at(0.3, 0.05, k) for k in range(20)]
    assert all(p.valid and int(p.beam_valid.sum()) == 3 for p in pings)
    assert np.mean([p.altitude for p in pings]) == pytest.approx(0.5, abs=0.005)
    assert np.mean([p.velocity for p in pings], axis=0) == pytest.approx(v_body, abs=0.002)
    # at (0.45, 0.12): (0.66, 0.12) and (0.45, 0.33) fall off the top, (0.24, 0.12) and (0.45, -0.09) on it: no lock
    p = at(0.45, 0.12, 0)
    assert int(p.beam_valid.sum()) == 2 and not p.valid and p.altitude == -1.0
