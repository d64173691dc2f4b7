"""Vehicle dynamics against physics: analytic steady states (paper eq. 11,
Table 1) and a tight-tolerance scipy reference of the same equations."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from hilsim.config import ConfigError
from hilsim.sim.state import VehicleState
from hilsim.sim.vehicle import Current, Vehicle, load_vehicle_profile

ROOT = Path(__file__).resolve().parents[2]
CYCLOPS = ROOT / "devices" / "vehicles" / "cyclops.toml"
BLUEROV = ROOT / "devices" / "vehicles" / "bluerov2_heavy.toml"

# The paper's Table 1 (SI): mass incl. added mass, linear and quadratic damping.
TABLE1 = {"surge": (391.5, 16.0, 229.4), "sway": (639.6, 131.8, 328.3), "heave": (639.6, 65.6, 296.8)}
W_W = -2.5  # [N] buoyancy force in heave


def root(k: float, kq: float, f: float) -> float:
    """Speed where k x + kq x|x| = f."""
    x = (-k + math.sqrt(k * k + 4 * kq * abs(f))) / (2 * kq)
    return math.copysign(x, f)


@pytest.fixture(scope="module")
def cyclops() -> Vehicle:
    return Vehicle.from_file(CYCLOPS)


def run(vehicle: Vehicle, wrench: list[float], seconds: float, dt: float,
        state: VehicleState | None = None, current: Current | None = None) -> VehicleState:
    s = state or VehicleState()
    for _ in range(int(round(seconds / dt))):
        s = vehicle.step(s, dt, wrench, current)
    return s


def test_profile_carries_table1_with_sources() -> None:
    p = load_vehicle_profile(CYCLOPS)
    assert p.dofs == ("surge", "sway", "heave", "yaw")
    for dof, (m, k, kq) in TABLE1.items():
        got = p.params[dof]
        assert (got.mass, got.linear_damping, got.quadratic_damping) == (m, k, kq)
        for key in ("mass", "linear_damping", "quadratic_damping"):
            assert p.sources[f"dynamics.{dof}.{key}"].startswith("paper Table 1")
    assert p.params["heave"].constant_force == W_W
    for key in ("mass", "linear_damping", "quadratic_damping"):
        assert p.sources[f"dynamics.yaw.{key}"].startswith("estimate")
    assert len(p.thrusters) == 8


def test_steady_surge_under_100N_is_the_damping_root(cyclops: Vehicle) -> None:
    m, k, kq = TABLE1["surge"]
    expected = root(k, kq, 100.0)
    assert expected == pytest.approx(0.626, rel=1e-3)  # the figure
    s = run(cyclops, [100.0, 0, 0, 0, 0, 0], 40.0, 0.02)
    assert s.velocity[0] == pytest.approx(expected, rel=0.005)
    assert s.velocity[0] == pytest.approx(expected, rel=1e-6)  # converged: 30 time constants
    assert abs(s.velocity[1]) < 1e-12 and s.angular_velocity[2] == 0.0
    assert s.acceleration[0] == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("dof,axis", [("sway", 1), ("heave", 2)])
def test_steady_sway_and_heave_under_100N(cyclops: Vehicle, dof: str, axis: int) -> None:
    m, k, kq = TABLE1[dof]
    force = 100.0
    expected = root(k, kq, force + (W_W if dof == "heave" else 0.0))
    wrench = [0.0] * 6
    wrench[axis] = force
    s = run(cyclops, wrench, 40.0, 0.02)
    assert s.velocity[axis] == pytest.approx(expected, rel=0.005)
    assert s.velocity[axis] == pytest.approx(expected, rel=1e-6)


def test_zero_thrust_gives_buoyancy_driven_heave(cyclops: Vehicle) -> None:
    m, k, kq = TABLE1["heave"]
    expected = root(k, kq, W_W)
    assert expected < 0  # net buoyancy: the vehicle rises (z down)
    s = run(cyclops, [0.0] * 6, 120.0, 0.05, VehicleState(position=np.array([0.0, 0.0, 5.0])))
    assert s.velocity[2] == pytest.approx(expected, rel=1e-4)
    assert s.position[2] < 5.0
    assert cyclops.steady_speed("heave", 0.0) == pytest.approx(expected, rel=1e-12)


def test_steady_yaw_rate_from_the_estimated_yaw_terms(cyclops: Vehicle) -> None:
    p = cyclops.profile.params["yaw"]
    expected = root(p.linear_damping, p.quadratic_damping, 30.0)
    s = run(cyclops, [0, 0, 0, 0, 0, 30.0], 30.0, 0.01)
    assert s.angular_velocity[2] == pytest.approx(expected, rel=1e-6)


def test_heading_rotates_body_velocity_into_ned(cyclops: Vehicle) -> None:
    # heading east (90 deg): pure surge moves the vehicle east, not north
    s0 = VehicleState(attitude=np.array([0.0, 0.0, math.pi / 2]), velocity=np.array([0.5, 0.0, 0.0]))
    s = run(cyclops, [0.0] * 6, 2.0, 0.01, s0)
    assert s.position[1] > 0.5 and abs(s.position[0]) < 1e-12


def reference(vehicle: Vehicle, y0: np.ndarray, wrench_at, t_end: float, current: Current | None = None,
              t_eval: np.ndarray | None = None):
    """solve_ivp of eq. 11 (+ yaw) with heading kinematics, written out independently."""
    prm = vehicle.profile.params
    dofs = ("surge", "sway", "heave", "yaw")
    m = np.array([prm[d].mass for d in dofs])
    k = np.array([prm[d].linear_damping for d in dofs])
    kq = np.array([prm[d].quadratic_damping for d in dofs])
    c = np.array([prm[d].constant_force for d in dofs])

    def f(t: float, y: np.ndarray) -> np.ndarray:
        x, yy, z, psi, u, v, w, r = y
        cn, ce, cd = current.velocity(z, t) if current else (0.0, 0.0, 0.0)
        rel = np.array([u - (math.cos(psi) * cn + math.sin(psi) * ce),
                        v - (-math.sin(psi) * cn + math.cos(psi) * ce), w - cd, r])
        tau = np.asarray(wrench_at(t), dtype=float)[[0, 1, 2, 5]]
        acc = (tau + c - k * rel - kq * rel * np.abs(rel)) / m
        return np.array([math.cos(psi) * u - math.sin(psi) * v, math.sin(psi) * u + math.cos(psi) * v,
                         w, r, *acc])

    return solve_ivp(f, (0.0, t_end), y0, method="DOP853", rtol=1e-11, atol=1e-12, t_eval=t_eval,
                     max_step=0.05)


def to_vec(s: VehicleState) -> np.ndarray:
    return np.array([*s.position, s.attitude[2], *s.velocity, s.angular_velocity[2]])


@pytest.mark.parametrize("dt", [0.001, 0.01, 0.05])
def test_integrator_matches_reference_for_a_thrust_step(cyclops: Vehicle, dt: float) -> None:
    """A thrust step at t = 2 s (surge, sway, heave and yaw together), 6 s total."""
    on = [120.0, -60.0, 80.0, 0.0, 0.0, 40.0]

    def wrench_at(t: float) -> list[float]:
        return on if t >= 2.0 else [0.0] * 6

    s = VehicleState(attitude=np.array([0.0, 0.0, 0.3]), velocity=np.array([0.1, 0.0, 0.0]))
    y0 = to_vec(s)
    ref1 = reference(cyclops, y0, lambda t: [0.0] * 6, 2.0)
    ref = reference(cyclops, ref1.y[:, -1], lambda t: on, 4.0)
    for _ in range(int(round(2.0 / dt))):
        s = cyclops.step(s, dt, wrench_at(s.time + 1e-9))
    for _ in range(int(round(4.0 / dt))):
        s = cyclops.step(s, dt, wrench_at(s.time + 1e-9))
    assert s.time == pytest.approx(6.0)
    got, want = to_vec(s), ref.y[:, -1]
    got[3] = want[3] + math.remainder(got[3] - want[3], 2 * math.pi)
    scale = {0.001: 1e-9, 0.01: 1e-9, 0.05: 1e-7}[dt]  # RK4: error ~ dt^4 (measured 2e-9 at 50 ms)
    np.testing.assert_allclose(got[:4], want[:4], atol=scale * 10)   # position [m], heading [rad]
    np.testing.assert_allclose(got[4:], want[4:], atol=scale)        # velocities


def test_current_damps_relative_velocity_and_matches_reference(cyclops: Vehicle) -> None:
    # a sheared, tidal current; the vehicle turns and dives through it
    cur = Current(velocities=(((0.2, 0.0, 0.0), (0.0, 0.1, 0.0)), ((0.3, 0.1, 0.0), (0.1, 0.2, 0.01))),
                  times=(0.0, 20.0), depths=(0.0, 10.0))
    wrench = [50.0, 0.0, 60.0, 0.0, 0.0, 10.0]
    s = VehicleState(position=np.array([0.0, 0.0, 1.0]))
    ref = reference(cyclops, to_vec(s), lambda t: wrench, 10.0, cur)
    s = run(cyclops, wrench, 10.0, 0.02, s, cur)
    got, want = to_vec(s), ref.y[:, -1]
    got[3] = want[3] + math.remainder(got[3] - want[3], 2 * math.pi)
    np.testing.assert_allclose(got, want, atol=1e-7)


def test_no_thrust_drifts_with_a_constant_current(cyclops: Vehicle) -> None:
    cur = Current.constant((0.2, -0.1, 0.0))
    heading = 0.7
    s = run(cyclops, [0, 0, -W_W, 0, 0, 0], 400.0, 0.05,  # 16 surge time constants
            VehicleState(attitude=np.array([0.0, 0.0, heading])), cur)
    # over ground the vehicle moves with the water: body velocity = R^T current
    c, sn = math.cos(heading), math.sin(heading)
    np.testing.assert_allclose(s.velocity[:2], [c * 0.2 + sn * -0.1, -sn * 0.2 + c * -0.1], atol=1e-6)
    assert abs(s.velocity[2]) < 1e-9


def test_current_profile_interpolates_and_clamps() -> None:
    cur = Current.over_depth([0.0, 10.0], [[0.0, 0.0, 0.0], [1.0, 2.0, 0.0]])
    assert cur.velocity(5.0, 0.0) == pytest.approx((0.5, 1.0, 0.0))
    assert cur.velocity(50.0, 0.0) == pytest.approx((1.0, 2.0, 0.0))
    tide = Current.over_time([0.0, 100.0], [[0.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    assert tide.velocity(3.0, 25.0) == pytest.approx((0.0, -0.25, 0.0))
    assert Current.constant((0, 0, 0)).is_zero and not tide.is_zero


def test_bluerov_is_a_new_file_and_stable_at_50ms() -> None:
    rov = Vehicle.from_file(BLUEROV)
    wrench = [60.0, 20.0, -30.0, 0.0, 0.0, 8.0]
    fine = run(rov, wrench, 5.0, 0.001)
    coarse = run(rov, wrench, 5.0, 0.05)
    assert np.all(np.isfinite(to_vec(coarse)))
    par = rov.profile.params
    yaw = par["yaw"]
    # 6-DOF profile: at the steady turn the yaw moment also balances the Munk moment
    # (m_v - m_u) u v and the gyroscopic (I_q - I_p) p q
    u, v = coarse.velocity[:2]
    p, q = coarse.angular_velocity[:2]
    n = 8.0 - (par["sway"].mass - par["surge"].mass) * u * v - (par["pitch"].mass - par["roll"].mass) * p * q
    assert coarse.angular_velocity[2] == pytest.approx(root(1e-12 + yaw.linear_damping, yaw.quadratic_damping, n),
                                                       rel=1e-4)
    np.testing.assert_allclose(to_vec(coarse)[4:], to_vec(fine)[4:], atol=1e-4)


def test_profile_errors_name_the_key(tmp_path: Path) -> None:
    text = CYCLOPS.read_text().replace("linear_damping = { value = 16.0", "linear_dampin = { value = 16.0")
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(ConfigError, match="did you mean 'linear_damping'"):
        load_vehicle_profile(bad)
    text = CYCLOPS.read_text().replace('unit = "N*s/m", source = "paper Table 1 (k_u)"',
                                       'unit = "kg", source = "paper Table 1 (k_u)"')
    bad.write_text(text)
    with pytest.raises(ConfigError, match="not a unit of"):
        load_vehicle_profile(bad)


def test_roll_pitch_are_held_not_modelled(tmp_path: Path) -> None:
    text = CYCLOPS.read_text().replace('dofs = ["surge", "sway", "heave", "yaw"]',
                                       'dofs = ["surge", "sway", "heave", "roll", "yaw"]')
    text += '\n[dynamics.roll]\nmass = { value = 20, unit = "kg*m^2", source = "x" }\n' \
            'linear_damping = { value = 1, unit = "N*m*s/rad", source = "x" }\n' \
            'quadratic_damping = { value = 1, unit = "N*m*s^2/rad^2", source = "x" }\n'
    f = tmp_path / "six.toml"
    f.write_text(text)
    profile = load_vehicle_profile(f)  # the format names the DOF...
    assert "roll" in profile.dofs
    with pytest.raises(ValueError, match="held"):  # ...the 4-DOF model refuses it
        Vehicle(profile)
    s = Vehicle.from_file(CYCLOPS).step(VehicleState(attitude=np.array([0.01, -0.02, 0.0])), 0.1,
                                        [0, 0, 0, 5.0, 5.0, 0])
    np.testing.assert_array_equal(s.attitude[:2], [0.01, -0.02])  # carried through, moments ignored


@pytest.mark.parametrize("dt", [0.001, 0.01, 0.05])
def test_no_turn_and_idle_dofs_match_reference(cyclops: Vehicle, dt: float) -> None:
    """Surge and heave only, from rest at a heading: yaw and sway stay exactly at rest
    (their integration is skipped) and the track follows the heading."""
    wrench = [90.0, 0.0, 40.0, 0.0, 0.0, 0.0]
    s = VehicleState(position=np.array([3.0, -1.0, 2.0]), attitude=np.array([0.0, 0.0, 2.2]))
    ref = reference(cyclops, to_vec(s), lambda t: wrench, 6.0)
    s = run(cyclops, wrench, 6.0, dt, s)
    assert s.velocity[1] == 0.0 and s.angular_velocity[2] == 0.0
    got, want = to_vec(s), ref.y[:, -1]
    got[3] = want[3] + math.remainder(got[3] - want[3], 2 * math.pi)
    scale = {0.001: 1e-9, 0.01: 1e-9, 0.05: 1e-7}[dt]
    np.testing.assert_allclose(got[:4], want[:4], atol=scale * 10)
    np.testing.assert_allclose(got[4:], want[4:], atol=scale)


def test_step_states_build_their_arrays_on_demand(cyclops: Vehicle) -> None:
    """A stepped state holds its numbers and builds the arrays when read; whether or not
    they were read, and however the state was made, the next step is the same."""
    import dataclasses
    import pickle

    wrench = [60.0, -20.0, 30.0, 0.0, 0.0, 12.0]
    s0 = run(cyclops, wrench, 1.0, 0.01, VehicleState(attitude=np.array([0.0, 0.0, 0.4])))
    copy = pickle.loads(pickle.dumps(s0))
    rebuilt = VehicleState(s0.time, np.array(s0.position), np.array(s0.attitude), np.array(s0.velocity),
                           np.array(s0.angular_velocity), np.array(s0.acceleration))
    flat = s0.flat()
    assert len(flat) == 15 and flat == rebuilt.flat() == copy.flat()
    np.testing.assert_array_equal(np.concatenate([s0.position, s0.attitude, s0.velocity,
                                                  s0.angular_velocity, s0.acceleration]), flat)
    assert s0.depth == flat[2] and s0.heading == flat[5]
    nexts = [cyclops.step(s, 0.01, wrench).flat() for s in (s0, copy, rebuilt, VehicleState.from_flat(s0.time, flat))]
    assert all(n == nexts[0] for n in nexts)
    moved = dataclasses.replace(s0, position=np.array([1.0, 2.0, 3.0]))
    assert moved.flat()[:3] == (1.0, 2.0, 3.0) and moved.flat()[3:] == flat[3:]
    with pytest.raises(AttributeError):
        s0.no_such_field  # noqa: B018
    with pytest.raises(ValueError, match="15 values"):
        VehicleState.from_flat(0.0, [0.0] * 14)


def test_step_with_thrusters_is_wrench_held_then_advance() -> None:
    """step_with_thrusters = the set's wrench at the step's start, held over the step,
    then the rotors advanced to its end (the documented order), with a current."""
    profile = load_vehicle_profile(CYCLOPS)
    vehicle, ts, twin = Vehicle(profile), profile.thruster_set(), profile.thruster_set()
    cur = Current.constant((0.1, -0.05, 0.0))
    s = s2 = VehicleState()
    for k in range(400):
        if k % 20 == 0:
            cmds = [0.4 * math.sin(0.3 * k + i) for i in range(8)]
            ts.command_all("normalized", cmds, s.time)
            twin.command_all("normalized", cmds, s2.time)
        s = vehicle.step_with_thrusters(s, 0.005, ts, cur)
        w = twin.wrench()
        twin.advance(0.005, s2.time + 0.005)
        s2 = vehicle.step(s2, 0.005, w, cur)
    np.testing.assert_allclose(s.flat(), s2.flat(), rtol=1e-12, atol=1e-14)
    assert s.time == s2.time
    with pytest.raises(ValueError, match="dt must be > 0"):
        vehicle.step_with_thrusters(s, 0.0, ts)
    np.testing.assert_array_equal(ts.speeds, twin.speeds)  # a refused step does not advance the rotors
