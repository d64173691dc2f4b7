"""Thruster model, set wrench, allocation and watchdog, checked against physics."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from hilsim.sim.thrusters import ThrusterSet, load_thruster_profile, target_speed
from hilsim.sim.vehicle import load_vehicle_profile

ROOT = Path(__file__).resolve().parents[2]
T200 = ROOT / "devices" / "thrusters" / "t200.toml"
CYCLOPS = ROOT / "devices" / "vehicles" / "cyclops.toml"
KGF = 9.80665


@pytest.fixture()
def cyclops_set() -> ThrusterSet:
    return load_vehicle_profile(CYCLOPS).thruster_set()


def settle(ts: ThrusterSet, seconds: float, dt: float = 0.005, t0: float = 0.0, keep: bool = True,
           kind: str = "normalized", values: list[float] | None = None) -> float:
    """Advance ``seconds``; re-send ``values`` every step when ``keep``. Returns the end time."""
    t = t0
    for _ in range(int(round(seconds / dt))):
        t += dt
        if keep and values is not None:
            ts.command_all(kind, values, t)
        ts.advance(dt, t)
    return t


def test_t200_curve_is_asymmetric_with_the_published_maxima() -> None:
    p = load_thruster_profile(T200)
    assert float(p.thrust(1.0)) == pytest.approx(5.1 * KGF)
    assert float(p.thrust(-1.0)) == pytest.approx(-4.1 * KGF)
    # close to quadratic in speed: half speed gives a quarter of the thrust
    assert float(p.thrust(0.5)) == pytest.approx(0.25 * 5.1 * KGF, rel=1e-3)
    assert float(p.speed_for_thrust(p.thrust(0.37))) == pytest.approx(0.37, abs=1e-3)
    assert p.sources["time_constant"].startswith("estimate")


@pytest.mark.parametrize("dt", [0.001, 0.02])
def test_speed_follows_a_first_order_lag(dt: float) -> None:
    p = load_thruster_profile(T200)
    ts = ThrusterSet([_single(p)])
    ts.command(0, "normalized", 1.0, 0.0)
    n = int(round(p.time_constant / dt))
    for k in range(n):
        ts.advance(dt, (k + 1) * dt)
    # exact discretisation: after one time constant, 1 - 1/e of the step, at any dt
    assert ts.speeds[0] == pytest.approx(1.0 - math.exp(-n * dt / p.time_constant), rel=1e-12)
    tel = ts.telemetry(0)
    assert tel.rpm == pytest.approx(ts.speeds[0] * p.max_rpm)  # from the rotor, not the command
    assert tel.rpm < 0.7 * p.max_rpm


def _single(p):  # one thruster on the x axis
    from hilsim.sim.thrusters import Thruster
    return Thruster("t", np.zeros(3), np.array([1.0, 0.0, 0.0]), p)


@pytest.mark.parametrize("kind,value", [
    ("normalized", 0.5), ("duty", 0.5), ("rpm", 1800.0), ("erpm", 1800.0 * 7), ("current", 24.0 * 0.25)])
def test_command_kinds_map_to_the_same_half_speed(kind: str, value: float) -> None:
    p = load_thruster_profile(T200)
    assert p.max_rpm == pytest.approx(3600.0) and p.pole_pairs == 7 and p.max_current == 24.0
    ts = ThrusterSet([_single(p)])
    settle(ts, 1.0, values=[value], kind=kind)  # 25 time constants
    assert ts.speeds[0] == pytest.approx(0.5, rel=1e-9)
    # current command: thrust proportional to current (load torque ~ speed^2)
    assert ts.thrusts()[0] == pytest.approx(0.25 * 5.1 * KGF, rel=2e-3)
    tel = ts.telemetry(0)
    assert tel.motor_current == pytest.approx(6.0) and tel.duty == pytest.approx(0.5)
    assert 0 < tel.input_current <= tel.motor_current and tel.voltage < 16.0


def test_dead_band_and_saturation() -> None:
    p = load_thruster_profile(T200)
    assert target_speed(p, "normalized", 0.5 * p.dead_band, 16.0) == 0.0
    assert target_speed(p, "normalized", -2.0, 16.0) == -1.0
    assert target_speed(p, "rpm", 10_000.0, 16.0) == 1.0
    assert target_speed(p, "current", 1000.0, 16.0) == 1.0
    with pytest.raises(ValueError, match="unknown command kind"):
        target_speed(p, "pwm", 1500, 16.0)
    ts = ThrusterSet([_single(p)])
    settle(ts, 1.0, values=[0.5 * p.dead_band])
    assert ts.thrusts()[0] == 0.0
    settle(ts, 1.0, values=[5.0])
    assert ts.thrusts()[0] == pytest.approx(5.1 * KGF)  # saturated at the curve's end


def test_open_loop_commands_scale_with_supply_voltage() -> None:
    p = load_thruster_profile(T200)
    ts = ThrusterSet([_single(p)], supply_voltage=12.0)
    settle(ts, 1.0, values=[1.0])
    assert ts.speeds[0] == pytest.approx(0.75)  # speed ~ duty x voltage
    assert ts.max_thrust[0] == pytest.approx(0.75 ** 2 * 5.1 * KGF, rel=2e-3)


def test_watchdog_zeroes_thrust_after_the_timeout(cyclops_set: ThrusterSet) -> None:
    ts = cyclops_set
    p = ts.thrusters[0].profile
    t = settle(ts, 0.3, values=[0.8] * 8)
    assert np.all(ts.thrusts() > 0) and not ts.telemetry(0).timed_out
    # commands stop at t: thrust holds until the timeout...
    last = t
    t = settle(ts, p.watchdog_timeout - 0.05, t0=t, keep=False)
    assert np.all(ts.thrusts() > 0.5 * float(p.thrust(0.8)))
    # ...then the target drops to zero and the rotor spins down to a stop
    t = settle(ts, 0.05 + 10 * p.time_constant, t0=t, keep=False)
    assert np.all(ts.thrusts() == 0.0) and np.all(ts.wrench() == 0.0)
    tel = ts.telemetry(3)
    assert tel.timed_out and tel.rpm == 0.0 and tel.command_age == pytest.approx(t - last)
    # a new command restarts the thruster
    ts.command(3, "normalized", 0.5, t)
    settle(ts, 0.3, t0=t, keep=False)
    assert ts.thrusts()[3] > 0 and ts.thrusts()[2] == 0.0 and not ts.telemetry(3).timed_out


def test_winding_temperature_rises_under_load(cyclops_set: ThrusterSet) -> None:
    ts = cyclops_set
    settle(ts, 5.0, dt=0.01, values=[1.0] * 4 + [0.0] * 4)
    assert ts.telemetry(0).temperature > ts.water_temperature + 0.1
    assert ts.telemetry(5).temperature == pytest.approx(ts.water_temperature)


def test_set_wrench_is_force_and_moment_of_the_placed_thrusters(cyclops_set: ThrusterSet) -> None:
    ts = cyclops_set
    f = float(ts.thrusters[0].profile.thrust(0.6))
    settle(ts, 1.0, values=[0.6] * 4 + [0.0] * 4)
    w = ts.wrench()
    np.testing.assert_allclose(w, [4 * f * math.cos(math.pi / 4), 0, 0, 0, 0, 0], atol=1e-9)
    settle(ts, 1.0, values=[0.6, -0.6, 0.6, -0.6, 0, 0, 0, 0])  # yaw pattern
    w = ts.wrench()
    assert abs(w[0]) > 0 and abs(w[1]) < 1e-9 and w[5] > 0  # asymmetric curve leaves some surge
    r = np.array([t.position for t in ts.thrusters])
    d = np.array([t.direction for t in ts.thrusters])
    thrust = ts.thrusts()
    np.testing.assert_allclose(w[3:], np.sum(np.cross(r, d * thrust[:, None]), axis=0), atol=1e-9)


def test_allocation_reproduces_a_feasible_wrench_exactly(cyclops_set: ThrusterSet) -> None:
    ts = cyclops_set
    rng = np.random.default_rng(5)
    for _ in range(20):
        f = rng.uniform(0.4 * ts.min_thrust, 0.4 * ts.max_thrust)
        wrench = ts.matrix @ f
        a = ts.allocate(wrench)
        assert not a.saturated and a.scale == 1.0
        np.testing.assert_allclose(ts.matrix @ a.thrusts, wrench, atol=1e-9)
        assert np.all(a.thrusts <= ts.max_thrust) and np.all(a.thrusts >= ts.min_thrust)


def test_allocation_of_an_infeasible_surge_is_the_analytic_maximum(cyclops_set: ThrusterSet) -> None:
    ts = cyclops_set
    a = ts.allocate([1000.0, 0, 0, 0, 0, 0])
    # Fy = Mz = 0 force equal horizontal thrusts; best is all four at full forward thrust
    best = 4 * math.cos(math.pi / 4) * ts.max_thrust[0]
    assert a.saturated and a.wrench[0] == pytest.approx(best, rel=1e-6)
    np.testing.assert_allclose(a.wrench[1:], 0.0, atol=1e-6)
    np.testing.assert_allclose(a.thrusts[4:], 0.0, atol=1e-9)  # verticals not used


def test_allocation_saturates_along_the_requested_direction(cyclops_set: ThrusterSet) -> None:
    ts = cyclops_set
    rng = np.random.default_rng(11)
    improved = 0
    for _ in range(10):
        wrench = rng.normal(size=6) * np.array([300, 300, 300, 60, 60, 80])
        a = ts.allocate(wrench)
        assert a.saturated and 0 < a.scale < 1
        assert np.all(a.thrusts <= ts.max_thrust + 1e-9) and np.all(a.thrusts >= ts.min_thrust - 1e-9)
        # direction unchanged: the achieved wrench is the requested one scaled
        np.testing.assert_allclose(a.wrench, a.scale * wrench, atol=1e-6 * np.abs(wrench).max())
        # at least as large as scaling the minimum-norm solution into the limits
        f = np.linalg.pinv(ts.matrix) @ wrench
        naive = min(1.0, *(ts.max_thrust[f > 0] / f[f > 0]), *(ts.min_thrust[f < 0] / f[f < 0]))
        assert a.scale >= naive - 1e-9
        improved += a.scale > 1.05 * naive  # the redundant thrusters' null space is used
        # and maximal: 1 % more along the same direction is out of reach (bounded least squares)
        more = lsq_linear(ts.matrix, 1.01 * a.scale * wrench, bounds=(ts.min_thrust, ts.max_thrust),
                          tol=1e-12, lsmr_tol="auto")
        assert np.linalg.norm(ts.matrix @ more.x - 1.01 * a.scale * wrench) > 1e-3
    assert improved >= 3


def test_allocated_commands_produce_the_allocated_thrusts(cyclops_set: ThrusterSet) -> None:
    ts = cyclops_set
    wrench = np.array([60.0, -20.0, 40.0, 0.0, 0.0, 10.0])
    a = ts.allocate(wrench)
    for kind in ("normalized", "rpm", "current"):
        cmds = [ts.command_for_thrust(i, f, kind) for i, f in enumerate(a.thrusts)]
        settle(ts, 1.0, values=cmds, kind=kind)
        np.testing.assert_allclose(ts.wrench(), wrench, atol=0.05)


def test_allocation_over_a_subset_of_dofs_leaves_the_others_free(cyclops_set: ThrusterSet) -> None:
    ts = cyclops_set
    a = ts.allocate([50.0, -10.0, 999.0, 0.0, 0.0, 5.0], dofs=(0, 1, 5))  # heave not controlled
    assert not a.saturated
    np.testing.assert_allclose(a.wrench[[0, 1, 5]], [50.0, -10.0, 5.0], atol=1e-9)
    np.testing.assert_allclose(a.thrusts[4:], 0.0, atol=1e-12)  # minimum norm: verticals idle


class SteppedRotors:
    """The thruster model stepped rotor by rotor, every tick: the exact first-order lag,
    the dead band stop, the watchdog, the winding temperature and np.interp thrust."""

    def __init__(self, ts: ThrusterSet):
        self.ts = ts
        self.n = len(ts)
        self.speed = [0.0] * self.n
        self.target = [0.0] * self.n
        self.cmd_time = [-math.inf] * self.n
        self.timed_out = [True] * self.n
        self.temp = [ts.water_temperature] * self.n
        self.thermal_dt = 0.0

    def command(self, i: int, kind: str, value: float, now: float) -> None:
        self.target[i] = target_speed(self.ts.thrusters[i].profile, kind, value, self.ts.supply_voltage)
        self.cmd_time[i] = now
        self.timed_out[i] = False

    def wrench(self) -> np.ndarray:
        thrust = [np.interp(s, t.profile.curve_speed, t.profile.curve_thrust)
                  for t, s in zip(self.ts.thrusters, self.speed)]
        return self.ts.matrix @ np.array(thrust)

    def advance(self, dt: float, now: float) -> None:
        for i, t in enumerate(self.ts.thrusters):
            p = t.profile
            if now - self.cmd_time[i] > p.watchdog_timeout:
                self.timed_out[i] = True
                self.target[i] = 0.0
            s = self.speed[i] + (self.target[i] - self.speed[i]) * -math.expm1(-dt / p.time_constant)
            self.speed[i] = 0.0 if self.target[i] == 0.0 and abs(s) < p.dead_band else s
        self.thermal_dt += dt
        if self.thermal_dt >= 0.05:
            for i, t in enumerate(self.ts.thrusters):
                p = t.profile
                loss = (p.max_current * self.speed[i] ** 2) ** 2 * p.winding_resistance
                steady = self.ts.water_temperature + p.thermal_resistance * loss
                self.temp[i] += (steady - self.temp[i]) * -math.expm1(-self.thermal_dt / p.thermal_time_constant)
            self.thermal_dt = 0.0


def _random_run(ts: ThrusterSet, seed: int, ticks: int, check_every: int = 1) -> None:
    """Drive ``ts`` and a :class:`SteppedRotors` with the same random commands and
    clock (rounding-jittered dt, stalls, bursts, silences for the watchdog); compare."""
    ref = SteppedRotors(ts)
    rng = np.random.default_rng(seed)
    scale = {"normalized": 1.0, "duty": 1.0, "rpm": 3600.0, "current": 24.0}
    values = [0.0, 0.03, -0.05, 0.0626, 0.5, 0.55, -0.6, 1.0, -1.0, 1.7]
    t, silent_until = 0.0, -1.0
    for k in range(ticks):
        if t > silent_until and rng.random() < 0.06:
            if rng.random() < 0.1:
                silent_until = t + rng.uniform(0.3, 1.5)  # commands stop: the watchdog may trip
            kind = str(rng.choice(list(scale)))
            for i in range(len(ts)):
                if rng.random() < 0.6:
                    v = float(rng.choice(values)) if rng.random() < 0.5 else float(rng.uniform(-1.1, 1.1))
                    ts.command(i, kind, v * scale[kind], t)
                    ref.command(i, kind, v * scale[kind], t)
        dt = float(rng.choice([0.005, 0.005, 0.005, 0.001, 0.01, 0.0173])) * (1.0 + 1e-15 * rng.normal())
        t += dt
        want = ref.wrench()
        got = ts.tick(dt, t)
        np.testing.assert_allclose(got, want[[0, 1, 2, 5]], rtol=0, atol=1e-11)
        ref.advance(dt, t)
        speeds = ts.speeds
        np.testing.assert_allclose(speeds, ref.speed, rtol=0, atol=1e-13)
        assert [s == 0.0 for s in speeds] == [s == 0.0 for s in ref.speed], k  # stopped on the same tick
        if k % check_every == 0:
            np.testing.assert_allclose(ts.wrench(), ref.wrench(), rtol=0, atol=1e-11)
            for i in range(len(ts)):
                tel = ts.telemetry(i)
                assert tel.timed_out == ref.timed_out[i]
                assert tel.temperature == pytest.approx(ref.temp[i], rel=1e-13)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_closed_form_rotor_state_equals_stepping_every_rotor(cyclops_set: ThrusterSet, seed: int) -> None:
    """The set keeps its rotors in closed form between events (pieces of the thrust curve,
    dead band, commands, watchdog): the same speeds, stops and wrench as stepping each rotor."""
    _random_run(cyclops_set, seed, 2500)


def test_closed_form_with_two_time_constants_and_a_long_run() -> None:
    """Thrusters of two time constants (two decay factors), over a long run that
    renormalises the decay factors and refreshes the sums many times."""
    from dataclasses import replace

    profile = load_vehicle_profile(CYCLOPS)
    slow = replace(profile.thrusters[0].profile, time_constant=0.11, thermal_time_constant=30.0)
    units = [replace(u, profile=slow) if i % 3 == 0 else u for i, u in enumerate(profile.thrusters)]
    _random_run(ThrusterSet(units, 16.0), 7, 12000, check_every=50)


def test_tick_is_the_wrench_then_advance(cyclops_set: ThrusterSet) -> None:
    ts, twin = cyclops_set, load_vehicle_profile(CYCLOPS).thruster_set()
    for t in (0.0, 0.3):
        for s in (ts, twin):
            s.command_all("normalized", [0.7, -0.4, 0.2, 0.9, -0.1, 0.3, 0.0, -0.8], t)
        for k in range(60):
            now = t + (k + 1) * 0.005
            w = twin.wrench()
            twin.advance(0.005, now)
            if k % 2:  # tick: the 4-DOF rows; tick6: all six (roll and pitch moments too)
                np.testing.assert_allclose(ts.tick(0.005, now), w[[0, 1, 2, 5]], atol=1e-12)
            else:
                np.testing.assert_allclose(ts.tick6(0.005, now), w, atol=1e-12)
            np.testing.assert_allclose(ts.speeds, twin.speeds, atol=1e-15)


def test_a_nan_command_is_a_zero_target() -> None:
    p = load_thruster_profile(T200)
    for kind in ("normalized", "duty", "rpm", "erpm", "current"):
        assert target_speed(p, kind, math.nan, 16.0) == 0.0
    assert target_speed(p, "normalized", math.inf, 16.0) == 1.0  # saturates, as before


def test_stopped_rotors_give_an_exactly_zero_tick_wrench(cyclops_set: ThrusterSet) -> None:
    ts = cyclops_set
    t = 0.0
    for k in range(200):  # an uneven history, then silence: the watchdog stops every rotor
        t += 0.005
        if k % 20 == 0:
            ts.command_all("normalized", [0.9, -0.3, 0.5, 0.1, -0.7, 0.2, 0.65, -0.45], t)
        ts.tick(0.005, t)
    while not np.all(ts.speeds == 0.0):
        t += 0.005
        ts.tick(0.005, t)
    assert ts.tick(0.005, t + 0.005) == (0.0, 0.0, 0.0, 0.0)
