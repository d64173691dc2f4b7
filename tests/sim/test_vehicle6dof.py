"""The 6-DOF model against physics: the righting moment of the centres of gravity and
buoyancy (period and decay linearised about level, closed form), thrusters off the
centre roll and pitch the vehicle the right way, energy is conserved by the Coriolis
terms, steady speeds are the damping roots, and the ArduSub layouts of the profiles
match ArduSub's motor factors (AP_Motors6DOF.cpp)."""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import numpy as np
import pytest

from hilsim.config import ConfigError
from hilsim.sim.ardupilot_frames import FRAMES, check_layout, motor_wrench
from hilsim.sim.state import VehicleState
from hilsim.sim.vehicle import DofParameters, Vehicle, VehicleProfile, load_vehicle_profile
from hilsim.sim.vehicle6dof import GRAVITY, Vehicle6DOF, specific_force

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ROOT / "devices" / "vehicles" / "bluerov2_heavy.toml"
BLUEROV2 = ROOT / "devices" / "vehicles" / "bluerov2.toml"
CYCLOPS = ROOT / "devices" / "vehicles" / "cyclops.toml"


@pytest.fixture(scope="module")
def heavy() -> VehicleProfile:
    return load_vehicle_profile(HEAVY)


def run(vehicle: Vehicle6DOF, state: VehicleState, seconds: float, dt: float,
        wrench: tuple[float, ...] = (0.0,) * 6) -> tuple[np.ndarray, list[VehicleState]]:
    out = [state]
    for _ in range(int(round(seconds / dt))):
        state = vehicle.step(state, dt, wrench)
        out.append(state)
    return np.array([s.time for s in out]), out


def tilted(roll: float = 0.0, pitch: float = 0.0) -> VehicleState:
    return VehicleState(position=np.array([0.0, 0.0, 5.0]), attitude=np.array([roll, pitch, 0.0]))


def test_profiles_are_six_dof_with_sources_and_cyclops_is_not(heavy: VehicleProfile) -> None:
    assert heavy.six_dof and isinstance(Vehicle(heavy), Vehicle6DOF)
    assert heavy.dofs == ("surge", "sway", "heave", "roll", "pitch", "yaw")
    for dof in heavy.dofs:
        for key in ("mass", "linear_damping", "quadratic_damping"):
            assert "vB2022" in heavy.sources[f"dynamics.{dof}.{key}"]
    assert heavy.hydrostatics is not None and heavy.hydrostatics.centre_of_buoyancy[2] < 0
    assert load_vehicle_profile(BLUEROV2).six_dof
    cyclops = load_vehicle_profile(CYCLOPS)
    assert not cyclops.six_dof and type(Vehicle(cyclops)) is Vehicle


def zero_crossings(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    i = np.nonzero(np.sign(x[:-1]) * np.sign(x[1:]) < 0)[0]
    return t[i] - x[i] * (t[i + 1] - t[i]) / (x[i + 1] - x[i])


def test_roll_swings_back_with_the_righting_period_and_quadratic_decay(heavy: VehicleProfile) -> None:
    """Roll: I_p phi'' + K_p|p| phi'|phi'| + B |z_b| phi = 0 (K_p = 0). Linearised:
    omega_n = sqrt(B |z_b| / I_p); quadratic damping, averaged over a cycle, gives
    1/A(t) = 1/A0 + 4 c omega t / (3 pi), c = K_p|p| / I_p."""
    hs, roll = heavy.hydrostatics, heavy.params["roll"]
    assert hs is not None and roll.linear_damping == 0.0
    omega = math.sqrt(hs.buoyancy * -hs.centre_of_buoyancy[2] / roll.mass)
    t, states = run(Vehicle6DOF(heavy), tilted(roll=0.1), 18.0, 0.01)
    phi = np.array([s.attitude[0] for s in states])
    zc = zero_crossings(t, phi)
    period = 2.0 * float(np.mean(np.diff(zc)))
    assert period == pytest.approx(2.0 * math.pi / omega, rel=0.01)
    # amplitude of each half swing against the averaged decay law
    c = roll.quadratic_damping / roll.mass
    for a, b in zip(zc[:-1], zc[1:]):
        sel = (t > a) & (t < b)
        peak = float(np.max(np.abs(phi[sel])))
        tp = float(t[sel][np.argmax(np.abs(phi[sel]))])
        expect = 1.0 / (1.0 / 0.1 + 4.0 * c * omega * tp / (3.0 * math.pi))
        assert peak == pytest.approx(expect, rel=0.06)
    assert abs(phi[-1]) < 0.03  # swung back towards level


def test_pitch_is_a_damped_oscillator_with_the_profiles_numbers(heavy: VehicleProfile) -> None:
    """Pitch at small amplitude: I_q theta'' + M_q theta' + B |z_b| theta = 0, the
    closed-form underdamped solution (the quadratic term is < 1 % at 0.01 rad)."""
    hs, pitch = heavy.hydrostatics, heavy.params["pitch"]
    assert hs is not None
    k = hs.buoyancy * -hs.centre_of_buoyancy[2]
    wn = math.sqrt(k / pitch.mass)
    zeta = pitch.linear_damping / (2.0 * pitch.mass * wn)
    assert 0.0 < zeta < 1.0
    wd = wn * math.sqrt(1.0 - zeta * zeta)
    a0 = 0.01
    t, states = run(Vehicle6DOF(heavy), tilted(pitch=a0), 4.0, 0.005)
    theta = np.array([s.attitude[1] for s in states])
    exact = a0 * np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta * zeta) * np.sin(wd * t))
    np.testing.assert_allclose(theta, exact, atol=0.02 * a0)
    # the first zero crossing, tan(wd t) = -sqrt(1 - zeta^2) / zeta, and the first overshoot
    zc = zero_crossings(t, theta)
    assert zc[0] == pytest.approx((math.pi - math.atan(math.sqrt(1 - zeta ** 2) / zeta)) / wd, rel=0.01)
    overshoot = -float(np.min(theta)) / a0
    assert overshoot == pytest.approx(math.exp(-math.pi * zeta / math.sqrt(1 - zeta * zeta)), rel=0.05)


def test_off_centre_thrusters_roll_and_pitch_the_right_way(heavy: VehicleProfile) -> None:
    vehicle = Vehicle6DOF(heavy)
    thrusters = heavy.thruster_set()
    i = thrusters.index("vertical_front_right")  # at +x, +y; positive thrust pushes down
    state = tilted()
    for _ in range(50):
        thrusters.command(i, "normalized", 0.5, state.time)
        state = vehicle.step_with_thrusters(state, 0.01, thrusters)
    roll, pitch, _ = state.attitude
    assert roll > 0.005 and pitch < -0.005  # starboard side down, nose down
    assert state.velocity[2] > 0  # and it pushes the vehicle down
    # horizontal thrusters mounted 5 cm below the CG: surging forward raises the nose
    low = tuple(dataclasses.replace(t, position=t.position + np.array([0.0, 0.0, 0.05]))
                if t.direction[2] == 0 else t for t in heavy.thrusters)
    variant = dataclasses.replace(heavy, thrusters=low)
    thrusters = variant.thruster_set()
    state = tilted()
    fwd = [thrusters.index(n) for n in ("front_right", "front_left", "rear_right", "rear_left")]
    for _ in range(50):
        for j in fwd:
            thrusters.command(j, "normalized", 0.5, state.time)
        state = Vehicle6DOF(variant).step_with_thrusters(state, 0.01, thrusters)
    assert state.velocity[0] > 0.05 and state.attitude[1] > 0.005 and abs(state.attitude[0]) < 1e-9


def test_a_vehicle_pitched_over_the_top_stays_finite_and_canonical(heavy: VehicleProfile) -> None:
    """A strong pitch moment turns the vehicle over: the state passes pitch 90 deg without a
    blow-up, keeps |pitch| <= 90 deg, and its rotation follows the integrated body rates."""
    vehicle = Vehicle6DOF(heavy)
    state = tilted()
    pitches = []
    for _ in range(400):
        state = vehicle.step(state, 0.005, (0.0, 0.0, 0.0, 0.0, 3.0, 0.0))
        pitches.append(state.attitude[1])
    assert np.all(np.isfinite(state.flat()))
    assert max(abs(p) for p in pitches) <= math.pi / 2 + 1e-12
    # it went over: the body's x axis points backwards and up at some time
    assert abs(state.attitude[0]) > 3.0 or max(pitches) > 1.5


@pytest.mark.parametrize("two_lags", [False, True])
def test_thruster_wrench_matches_the_full_matrix(heavy: VehicleProfile, two_lags: bool) -> None:
    """The wrench the 6-DOF step gets (tick6, and roll_pitch_moments) is the allocation
    matrix times the thrusts, while the rotors spin up and down (one or two time constants)."""
    units = heavy.thrusters
    if two_lags:
        slow = dataclasses.replace(units[0].profile, time_constant=0.2)
        units = tuple(dataclasses.replace(u, profile=slow) if i % 2 else u for i, u in enumerate(units))
    thrusters = dataclasses.replace(heavy, thrusters=units).thruster_set()
    now, biggest = 0.0, np.zeros(2)
    for cmds in ([0.3, -0.2, 0.5, 0.1, 0.4, -0.6, 0.2, 0.7], [-0.5, 0.6, 0.0, 0.9, -0.3, 0.1, -0.8, 0.2]):
        thrusters.command_all("normalized", cmds, now)
        for _ in range(12):
            full = thrusters.wrench()
            mx, my = thrusters.roll_pitch_moments()
            got = thrusters.tick6(0.01, now + 0.01)
            now += 0.01
            np.testing.assert_allclose(got, full, atol=1e-9)
            np.testing.assert_allclose([mx, my], full[3:5], atol=1e-9)
            biggest = np.maximum(biggest, np.abs(full[3:5]))
    assert biggest.min() > 0.5, biggest  # roll and pitch moments really exercised [N m]


def energy(profile: VehicleProfile, s: VehicleState) -> float:
    """Kinetic energy (with added mass) + potential of the weight at the CG and the
    buoyancy at the CB: U = -W z + B z_CB (NED z down)."""
    hs = profile.hydrostatics
    assert hs is not None
    masses = [profile.params[d].mass for d in profile.dofs]
    nu = np.concatenate([s.velocity, s.angular_velocity])
    r = s.pose.rotation
    z_cb = float(s.position[2] + (r @ np.array(hs.centre_of_buoyancy))[2])
    return 0.5 * float(np.sum(np.array(masses) * nu * nu)) - hs.weight * float(s.position[2]) + hs.buoyancy * z_cb


def test_coriolis_and_restoring_terms_conserve_energy(heavy: VehicleProfile) -> None:
    """Without damping and thrust the total energy stays constant whatever the motion:
    the Coriolis terms only move energy between DOFs (a sign error would not)."""
    params = {d: DofParameters(p.mass, 0.0, 0.0) for d, p in heavy.params.items()}
    hs = dataclasses.replace(heavy.hydrostatics, centre_of_buoyancy=(0.01, -0.02, -0.03))  # type: ignore[arg-type]
    free = dataclasses.replace(heavy, params=params, hydrostatics=hs)
    vehicle = Vehicle6DOF(free)
    state = VehicleState(position=np.array([0.0, 0.0, 3.0]), attitude=np.array([0.3, -0.2, 1.0]),
                         velocity=np.array([0.4, -0.3, 0.2]), angular_velocity=np.array([0.5, -0.4, 0.8]))
    e0 = energy(free, state)
    _, states = run(vehicle, state, 5.0, 0.002)
    drift = max(abs(energy(free, s) - e0) for s in states)
    moving = 0.5 * sum(p.mass * v * v for p, v in zip(params.values(), [0.4, -0.3, 0.2, 0.5, -0.4, 0.8]))
    assert drift < 1e-6 * moving
    assert abs(states[-1].angular_velocity[0] - 0.5) > 0.01  # and the motion did couple


def test_steady_surge_and_heave_drift_are_the_damping_roots(heavy: VehicleProfile) -> None:
    """Surge with the net weight held by the vertical force (w = 0: no Munk moment
    tilts the vehicle), then the sinking drift of W - B with the thrusters off."""
    vehicle = Vehicle6DOF(heavy)
    hs = heavy.hydrostatics
    assert hs is not None
    _, states = run(vehicle, tilted(), 25.0, 0.02, (20.0, 0.0, -hs.net_down, 0.0, 0.0, 0.0))
    s = states[-1]
    assert s.velocity[0] == pytest.approx(vehicle.steady_speed("surge", 20.0), rel=1e-6)
    assert abs(s.velocity[2]) < 1e-9 and abs(s.attitude[1]) < 1e-9
    w = vehicle.steady_speed("heave", 0.0)  # W - B alone
    heave = heavy.params["heave"]
    assert heave.linear_damping * w + heave.quadratic_damping * w * abs(w) == pytest.approx(hs.net_down)
    assert w > 0  # vB2022's W > B: it sinks
    _, states = run(vehicle, tilted(), 20.0, 0.02)
    assert states[-1].velocity[2] == pytest.approx(w, rel=1e-6)


def test_fifty_ms_steps_agree_with_one_ms(heavy: VehicleProfile) -> None:
    vehicle = Vehicle6DOF(heavy)
    wrench = (30.0, 10.0, -15.0, 0.3, -0.2, 1.5)
    start = tilted(roll=0.1, pitch=-0.05)
    fine = run(vehicle, start, 3.0, 0.001, wrench)[1][-1]
    coarse = run(vehicle, start, 3.0, 0.05, wrench)[1][-1]
    np.testing.assert_allclose(np.array(coarse.flat()[:12]), np.array(fine.flat()[:12]), atol=2e-4)


def test_specific_force_is_minus_gravity_at_rest_and_tilts_with_the_body() -> None:
    assert specific_force(VehicleState()) == pytest.approx((0.0, 0.0, -GRAVITY))
    roll, pitch = 0.2, -0.1
    got = specific_force(tilted(roll, pitch))
    want = (GRAVITY * math.sin(pitch), -GRAVITY * math.cos(pitch) * math.sin(roll),
            -GRAVITY * math.cos(pitch) * math.cos(roll))
    assert got == pytest.approx(want)
    # a steady turn: the centripetal term omega x v shows (r u in y)
    s = VehicleState(velocity=np.array([0.5, 0.0, 0.0]), angular_velocity=np.array([0.0, 0.0, 0.4]))
    assert specific_force(s)[1] == pytest.approx(0.4 * 0.5)


@pytest.mark.parametrize("path", [HEAVY, BLUEROV2])
def test_ardupilot_tables_match_ardusubs_motor_factors(path: Path) -> None:
    profile = load_vehicle_profile(path)
    table = profile.ardupilot
    assert table is not None and len(table.motors) == len(FRAMES[table.frame]) == len(profile.thrusters)
    assert check_layout(table, profile.thrusters) == []
    # ArduSub's yaw pattern (motors with yaw factor +1 above 1500 us, -1 below) turns clockwise
    mz = sum(FRAMES[table.frame][m.servo - 1][2] * motor_wrench(profile.thrusters[m.thruster], m.direction)[5]
             for m in table.motors)
    assert mz > 0
    # all vertical motors' throttle factor (-1) pattern pushes the vehicle up
    fz = sum(-FRAMES[table.frame][m.servo - 1][3] * motor_wrench(profile.thrusters[m.thruster], m.direction)[2]
             for m in table.motors)
    assert fz > 0  # PWM above 1500 on motors with throttle factor -1: down (+z)


def test_a_reversed_motor_is_refused_naming_the_key(tmp_path: Path) -> None:
    text = HEAVY.read_text()
    marker = 'servo = 3\nthruster = "rear_right"\ndirection = 1'
    assert marker in text
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace(marker, marker.replace("direction = 1", "direction = -1")))
    with pytest.raises(ConfigError, match=r"ardupilot.*servo 3"):
        load_vehicle_profile(bad)


def test_a_uniform_current_carries_the_vehicle_along(heavy: VehicleProfile) -> None:
    """Damping acts on the velocity relative to the water: at steady state the vehicle drifts
    with a uniform current (NED), plus its own sinking drift, and stays level."""
    from hilsim.sim.vehicle import Current

    vehicle = Vehicle6DOF(heavy)
    current = Current.constant((0.2, -0.1, 0.0))
    state = VehicleState(position=np.array([0.0, 0.0, 5.0]), attitude=np.array([0.0, 0.0, 0.7]))
    for _ in range(1500):
        state = vehicle.step(state, 0.02, (0.0,) * 6, current)
    # the relative speed left decays no faster than sway's quadratic-only damping allows,
    # v0 / (1 + k_q v0 t / m) < m / (k_q t), plus the slow turn of the Munk moment
    sway = heavy.params["sway"]
    ned = state.pose.rotation @ state.velocity
    assert ned[:2] == pytest.approx([0.2, -0.1], abs=1.5 * sway.mass / (sway.quadratic_damping * 30.0))
    assert ned[2] == pytest.approx(vehicle.steady_speed("heave", 0.0), rel=0.02)
    assert abs(state.attitude[0]) < 0.01 and abs(state.attitude[1]) < 0.01  # Munk moments tilt it a little


def reference_rhs(profile: VehicleProfile, current: "Current | None", wrench: np.ndarray):  # type: ignore[no-untyped-def]
    """The module doc's equations in matrix form (numpy cross products, scipy's rotation),
    written apart from the kernel's expanded scalar arithmetic: the right-hand side of the
    12 states for solve_ivp."""
    from scipy.spatial.transform import Rotation

    hs = profile.hydrostatics
    assert hs is not None and profile.rigid_mass is not None
    m = profile.rigid_mass
    masses = np.array([profile.params[d].mass for d in profile.dofs])
    lin = np.array([profile.params[d].linear_damping for d in profile.dofs])
    quad = np.array([profile.params[d].quadratic_damping for d in profile.dofs])
    added = np.diag(masses[:3] - m)
    inertia = np.diag(masses[3:])
    r_b = np.array(hs.centre_of_buoyancy)

    def rhs(t: float, x: np.ndarray) -> np.ndarray:
        phi, theta, psi = x[3:6]
        v, omega = x[6:9], x[9:12]
        rot = Rotation.from_euler("ZYX", [psi, theta, phi]).as_matrix()  # body -> NED
        c_ned = np.zeros(3) if current is None else np.array(current.velocity(x[2], t))
        v_r = v - rot.T @ c_ned
        g_b = rot.T @ np.array([0.0, 0.0, 1.0])
        p1 = m * v + added @ v_r
        coriolis = np.concatenate([np.cross(omega, p1), np.cross(omega, inertia @ omega) + np.cross(v_r, added @ v_r)])
        nu_r = np.concatenate([v_r, omega])
        damping = (lin + quad * np.abs(nu_r)) * nu_r
        restoring = np.concatenate([-(hs.weight - hs.buoyancy) * g_b, hs.buoyancy * np.cross(r_b, g_b)])
        nu_dot = (wrench - coriolis - damping - restoring) / masses
        euler_rates = np.array([[1.0, math.sin(phi) * math.tan(theta), math.cos(phi) * math.tan(theta)],
                                [0.0, math.cos(phi), -math.sin(phi)],
                                [0.0, math.sin(phi) / math.cos(theta), math.cos(phi) / math.cos(theta)]]) @ omega
        return np.concatenate([rot @ v, euler_rates, nu_dot])

    return rhs


@pytest.mark.parametrize("water", ["still", "uniform", "over depth and time"])
def test_the_kernel_integrates_the_documented_equations(heavy: VehicleProfile, water: str) -> None:
    """A manoeuvre on every DOF (a wrench with all six components, a tilted, moving start),
    RK4 at 10 ms against solve_ivp at 1e-11 on the matrix form of the equations, with the
    current at each stage's depth and time (hilsim.sim.vehicle.Current's own interpolation)."""
    from scipy.integrate import solve_ivp

    from hilsim.sim.vehicle import Current

    current = {"still": None, "uniform": Current.constant((0.3, -0.2, 0.05)),
               "over depth and time": Current((((0.1, 0.0, 0.0), (0.4, 0.2, 0.0)),
                                               ((-0.2, 0.3, 0.02), (0.0, -0.1, 0.0))),
                                              times=(0.5, 2.5), depths=(4.9, 5.6))}[water]
    wrench = np.array([30.0, -12.0, 18.0, 2.5, -3.0, 4.0])
    start = VehicleState(position=np.array([1.0, -2.0, 5.0]), attitude=np.array([0.2, -0.15, 2.9]),
                         velocity=np.array([0.3, -0.1, 0.05]), angular_velocity=np.array([0.1, -0.2, 0.3]))
    vehicle, state, dt, seconds = Vehicle6DOF(heavy), start, 0.01, 3.0
    for _ in range(int(round(seconds / dt))):
        state = vehicle.step(state, dt, wrench, current)
    x0 = np.array(start.flat()[:12])
    ref = solve_ivp(reference_rhs(heavy, current, wrench), (0.0, seconds), x0, method="DOP853",
                    rtol=1e-11, atol=1e-12).y[:, -1]
    got = np.array(state.flat()[:12])
    wrap = (got[3:6] - ref[3:6] + math.pi) % (2 * math.pi) - math.pi  # yaw crossed +-pi
    assert abs(state.time - seconds) < 1e-9
    assert np.abs(got[:3] - ref[:3]).max() < 1e-6  # [m]
    assert np.abs(wrap).max() < 1e-6  # [rad]
    assert np.abs(got[6:] - ref[6:]).max() < 1e-6  # [m/s, rad/s]
    assert np.abs(got[:3] - x0[:3]).max() > 0.5 and abs(ref[5] - x0[5]) > 0.3  # it really moved and turned


def test_the_kernel_is_compiled_and_cpython_runs_the_same_source() -> None:
    """numba compiles the step (the benchmark's figure depends on it); with HILSIM_JIT=0
    CPython runs the same functions and gets the same numbers to rounding."""
    import json
    import subprocess
    import sys

    from hilsim.sim import vehicle6dof_kernel

    assert vehicle6dof_kernel.COMPILED, vehicle6dof_kernel.WHY_NOT_COMPILED
    code = """if True:
        import json, sys
        import numpy as np
        from hilsim.sim import vehicle6dof_kernel
        from hilsim.sim.state import VehicleState
        from hilsim.sim.vehicle import Current, Vehicle, load_vehicle_profile
        vehicle = Vehicle(load_vehicle_profile(sys.argv[1]))
        current = Current.over_depth((4.0, 6.0), ((0.2, 0.0, 0.0), (-0.1, 0.3, 0.0)))
        state = VehicleState(position=np.array([0.0, 0.0, 5.0]), attitude=np.array([0.1, 0.2, -3.0]))
        for k in range(400):
            state = vehicle.step(state, 0.005, (20.0, 5.0, -8.0, 1.0, -2.0, 3.0), current if k % 2 else None)
        print(json.dumps([vehicle6dof_kernel.COMPILED, vehicle6dof_kernel.WHY_NOT_COMPILED, state.flat()]))
    """
    runs = {}
    for jit in ("1", "0"):
        env = {**os.environ, "HILSIM_JIT": jit}
        out = subprocess.run([sys.executable, "-c", code, str(HEAVY)], env=env, capture_output=True, text=True,
                             timeout=120, check=True, cwd=ROOT)
        runs[jit] = json.loads(out.stdout)
    assert runs["1"][:2] == [True, ""] and runs["0"][:2] == [False, "HILSIM_JIT=0"]
    np.testing.assert_allclose(runs["0"][2], runs["1"][2], rtol=1e-12, atol=1e-12)
