"""Navigation sensors against physics: hydrostatic pressure, gravity and
turning in the specific force, the heading of an integrated yaw, seeded noise."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from hilsim.config import ConfigError
from hilsim.sim.navigation import (
    ATMOSPHERE, GRAVITY, Imu, PressureSensor, depth_from_pressure, load_imu_profile, load_pressure_profile)
from hilsim.sim.state import VehicleState
from hilsim.sim.vehicle import Vehicle

ROOT = Path(__file__).resolve().parents[2]
KELLER = ROOT / "devices" / "sensors" / "keller_serie30.toml"
HWT905 = ROOT / "devices" / "sensors" / "witmotion_hwt905.toml"
CYCLOPS = ROOT / "devices" / "vehicles" / "cyclops.toml"


def at_depth(depth: float, t: float = 0.0) -> VehicleState:
    return VehicleState(time=t, position=np.array([1.0, 2.0, depth]))


def test_profiles_load_in_si_with_sources() -> None:
    k = load_pressure_profile(KELLER)
    assert k.range_max == pytest.approx(30e5) and k.noise == pytest.approx(30.0) and k.rate == 50.0
    w = load_imu_profile(HWT905)
    assert w.accel_range == pytest.approx(16 * GRAVITY) and w.gyro_range == pytest.approx(math.radians(2000))
    assert all(src for src in w.sources.values())


@pytest.mark.parametrize("density", [998.0, 1025.0])
@pytest.mark.parametrize("depth", [0.5, 10.0, 100.0])
def test_pressure_is_atmosphere_plus_rho_g_depth_within_noise(density: float, depth: float) -> None:
    prof = load_pressure_profile(KELLER)
    sensor = PressureSensor(prof, seed=3, water_density=density)
    truth = ATMOSPHERE + density * GRAVITY * depth
    samples = np.array([sensor.sample(at_depth(depth)).pressure for _ in range(400)])
    bound = 5 * prof.noise + prof.resolution / 2
    assert np.all(np.abs(samples - truth) <= bound)
    assert abs(samples.mean() - truth) <= 4 * prof.noise / math.sqrt(len(samples)) + prof.resolution / 2
    assert samples.std() > 0.5 * prof.noise  # the noise is there
    np.testing.assert_allclose(np.remainder(samples, prof.resolution), 0.0, atol=1e-6)  # quantised
    depths = [depth_from_pressure(p, density) for p in samples]
    assert np.mean(depths) == pytest.approx(depth, abs=0.01)


def test_pressure_offset_mount_range_and_temperature() -> None:
    prof = load_pressure_profile(KELLER)
    quiet = type(prof)(**{**prof.__dict__, "noise": 0.0, "resolution": 0.0, "offset": 500.0})
    # mounted 0.3 m below the origin, pitched level: sees 0.3 m more water
    s = PressureSensor(quiet, mount=(0.0, 0.0, 0.3), water_density=1000.0, water_temperature=283.15)
    r = s.sample(at_depth(2.0))
    assert r.pressure == pytest.approx(ATMOSPHERE + 1000.0 * GRAVITY * 2.3 + 500.0)
    assert r.temperature == pytest.approx(283.15, abs=0.05)
    assert s.sample(at_depth(400.0)).pressure == math.inf  # beyond 30 bar: overflow as Keller reports


def test_update_samples_at_the_profile_rate() -> None:
    sensor = PressureSensor(load_pressure_profile(KELLER), seed=1)
    readings = [sensor.update(at_depth(5.0, k * 0.005)) for k in range(200)]  # 1 s at 200 Hz
    times = [r.time for r in readings if r is not None]
    assert len(times) == 50
    np.testing.assert_allclose(np.diff(times), 0.02, atol=1e-9)


def test_same_seed_same_readings_other_seed_other_readings() -> None:
    prof, imu_prof = load_pressure_profile(KELLER), load_imu_profile(HWT905)
    state = VehicleState(time=1.0, position=np.array([0, 0, 7.0]), velocity=np.array([0.3, 0, 0]),
                         angular_velocity=np.array([0, 0, 0.1]))

    def run(seed: int) -> list[float]:
        p, i = PressureSensor(prof, seed=seed), Imu(imu_prof, seed=seed)
        out: list[float] = []
        for _ in range(5):
            out.append(p.sample(state).pressure)
            r = i.sample(state)
            out += [*r.attitude, *r.angular_velocity, *r.specific_force, *r.magnetic_field]
        return out

    assert run(42) == run(42)
    assert run(42) != run(43)


def test_specific_force_at_rest_is_minus_gravity_in_body_axes() -> None:
    prof = load_imu_profile(HWT905)
    imu = Imu(prof, seed=2)
    f = np.mean([imu.sample(VehicleState()).specific_force for _ in range(400)], axis=0)
    tol = 5 * prof.accel_bias + 5 * prof.accel_noise / 20
    np.testing.assert_allclose(f, [0.0, 0.0, -GRAVITY], atol=tol)
    # pitched nose up 30 deg: gravity shows on x (the held attitude's small values work the same way)
    pitched = VehicleState(attitude=np.array([0.0, math.radians(30), 0.0]))
    f = np.mean([imu.sample(pitched).specific_force for _ in range(400)], axis=0)
    np.testing.assert_allclose(f, [GRAVITY * 0.5, 0.0, -GRAVITY * math.cos(math.radians(30))], atol=tol)


def test_specific_force_in_a_steady_turn_is_centripetal() -> None:
    prof = load_imu_profile(HWT905)
    imu = Imu(prof, seed=4)
    u, r = 0.6, 0.25
    turning = VehicleState(velocity=np.array([u, 0.0, 0.0]), angular_velocity=np.array([0.0, 0.0, r]))
    f = np.mean([imu.sample(turning).specific_force for _ in range(400)], axis=0)
    assert f[1] == pytest.approx(r * u, abs=5 * prof.accel_bias + prof.accel_noise)  # omega x v


def test_imu_heading_and_rate_follow_the_integrated_yaw() -> None:
    vehicle = Vehicle.from_file(CYCLOPS)
    prof = load_imu_profile(HWT905)
    imu = Imu(prof, seed=9)
    s = VehicleState()
    dt, yaw, prev_r = 0.01, 0.0, 0.0
    errors, rate_errors = [], []
    for k in range(2000):  # 20 s: spin up under a constant yaw moment, more than one full turn
        s = vehicle.step(s, dt, [40.0, 0, 0, 0, 0, 25.0])
        r = s.angular_velocity[2]
        yaw += 0.5 * (prev_r + r) * dt  # trapezoid of the rate: the integrated yaw
        prev_r = r
        reading = imu.sample(s)
        errors.append(math.remainder(reading.attitude[2] - yaw, 2 * math.pi))
        rate_errors.append(reading.angular_velocity[2] - r)
    assert yaw > 2 * math.pi
    bound = 5 * prof.heading_bias + 5 * prof.heading_noise + 1e-4  # 1e-4: trapezoid vs RK4
    assert np.max(np.abs(errors)) < bound
    assert np.max(np.abs(rate_errors)) < 5 * prof.gyro_bias + 5 * prof.gyro_noise
    assert np.std(errors) > 0.3 * prof.heading_noise


def test_magnetometer_and_declination() -> None:
    prof = load_imu_profile(HWT905)
    quiet = type(prof)(**{**prof.__dict__, **{k: 0.0 for k in prof.__dict__ if k.endswith(("_noise", "_bias"))}})
    field = (20e-6, 5e-6, 40e-6)
    imu = Imu(quiet, magnetic_field=field)
    east = VehicleState(attitude=np.array([0.0, 0.0, math.pi / 2]))
    r = imu.sample(east)
    # facing east, north lies to port (-y), east ahead (+x)
    np.testing.assert_allclose(r.magnetic_field, [5e-6, -20e-6, 40e-6], atol=1e-12)
    assert r.attitude[2] == pytest.approx(math.pi / 2 - math.atan2(5e-6, 20e-6))
    q = r.quaternion
    assert np.linalg.norm(q) == pytest.approx(1.0)


def test_bad_temperature_unit_is_refused(tmp_path: Path) -> None:
    text = KELLER.read_text().replace('temperature_noise = { value = 0.02, unit = "K"',
                                      'temperature_noise = { value = 0.02, unit = "degC"')
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(ConfigError, match="temperature difference"):
        load_pressure_profile(bad)


# -- the accelerometer integrates over its output period ------------------------------------

def quiet_imu(rate: float, offset: float = 0.0) -> Imu:
    """A noise-free, bias-free HWT905 at ``rate`` [Hz], sampling grid at ``offset`` [s]."""
    prof = load_imu_profile(HWT905)
    zero = {k: 0.0 for k in prof.__dict__ if k.endswith(("_noise", "_bias"))}
    return Imu(type(prof)(**{**prof.__dict__, **zero, "rate": rate}), offset=offset)


PHYSICS = 200.0  # [Hz]


@pytest.mark.parametrize("imu_rate", [100.0, 50.0])
def test_a_one_tick_velocity_change_shows_in_exactly_one_sample_at_every_phase(imu_rate: float) -> None:
    """Physics at 200 Hz; the body velocity drops from 0.5 m/s to 0 within tick k (its state's
    acceleration is -0.5 m/s / 5 ms there, 0 elsewhere). Whatever the phase of tick k against
    the IMU's grid, one sample reads -0.5 m/s / period, the others 0, and the samples times the
    period add up to -0.5 m/s. (Reading the last step's acceleration only, the IMU at 100 Hz
    missed it at every other phase.)"""
    dv, dt = -0.5, 1.0 / PHYSICS
    every = int(PHYSICS / imu_rate)
    for k in range(20, 20 + 2 * every):  # every phase of the impact against the sampling grid, twice
        imu = quiet_imu(imu_rate)
        seen = []
        for i in range(60):
            t = i * dt
            u = 0.5 if i < k else 0.0
            a = dv / dt if i == k else 0.0
            state = VehicleState(time=t, velocity=np.array([u, 0.0, 0.0]), acceleration=np.array([a, 0.0, 0.0]))
            if i % every == 0:
                seen.append(imu.sample(state).specific_force)
        f = np.array(seen)
        period = 1.0 / imu_rate
        hit = np.flatnonzero(np.abs(f[:, 0]) > 1e-9)
        assert len(hit) == 1, (k, f[:, 0])
        assert f[hit[0], 0] == pytest.approx(dv / period, rel=1e-12)
        assert hit[0] == -(-k // every)  # the first sample at or after tick k's end
        assert f[:, 0].sum() * period == pytest.approx(dv, rel=1e-12)
        np.testing.assert_allclose(f[:, 2], -GRAVITY, rtol=1e-15)
        np.testing.assert_allclose(f[:, 1], 0.0, atol=1e-15)


def test_steady_states_read_as_before() -> None:
    """At rest (0, 0, -g) and in a steady turn the centripetal ``r u``, sample after sample;
    under a constant acceleration, that acceleration."""
    imu = quiet_imu(100.0)
    for i in range(10):
        f = imu.sample(VehicleState(time=i * 0.01)).specific_force
        np.testing.assert_allclose(f, [0.0, 0.0, -GRAVITY], atol=1e-12)
    imu = quiet_imu(100.0)
    u, r = 0.6, 0.25
    for i in range(10):
        f = imu.sample(VehicleState(time=i * 0.01, velocity=np.array([u, 0.0, 0.0]),
                                    angular_velocity=np.array([0.0, 0.0, r]))).specific_force
        np.testing.assert_allclose(f, [0.0, r * u, -GRAVITY], atol=1e-12)
    imu = quiet_imu(100.0)
    for i in range(10):
        t = i * 0.01
        f = imu.sample(VehicleState(time=t, velocity=np.array([0.0, 0.0, 0.3 * t]),
                                    acceleration=np.array([0.0, 0.0, 0.3]))).specific_force
        np.testing.assert_allclose(f, [0.0, 0.0, 0.3 - GRAVITY], atol=1e-12)


@pytest.mark.parametrize("imu_rate", [100.0, 50.0])
def test_the_imu_feels_a_wall_impact_whatever_its_phase(imu_rate: float) -> None:
    """The physics (VehicleLoop at 200 Hz, contacts) coasts Cyclops at 0.3 m/s into a wall, which
    stops it within one tick; the IMU runs on the same scheduler at ``imu_rate`` with its grid at
    several phases. The samples times the period add up to the ground truth's velocity change,
    and the impact (the speed the truth had just before it, lost) shows in one sample, or two
    adjacent ones, whatever the phase."""
    import trimesh

    from hilsim.runtime.scheduler import Scheduler, VehicleLoop
    from hilsim.sim.world import Material, World, WorldObject

    mesh = trimesh.creation.box(extents=[1.0, 40.0, 11.0])
    mesh.apply_translation([10.5, 0.0, 4.5])
    world = World([WorldObject("wall", mesh, Material("wall", 3e6))])
    period = 1.0 / imu_rate
    for offset in np.arange(0.0, period, 0.25 / PHYSICS):
        vehicle = Vehicle.from_file(CYCLOPS)
        start = VehicleState(position=np.array([9.3, 0.0, 2.0]), velocity=np.array([0.3, 0.0, 0.0]))
        loop = VehicleLoop(vehicle, None, start, physics_rate=PHYSICS, world=world)
        truth: dict[float, tuple[float, bool]] = {}
        loop.tick_listeners.append(lambda s, info: truth.__setitem__(round(s.time, 9), (s.velocity[0], info.touching)))
        samples: list[tuple[float, float]] = []
        imu = quiet_imu(imu_rate, offset=float(offset))
        sched = Scheduler()
        loop.attach(sched, [imu], on_reading=lambda s, r: samples.append((loop.state.time, r.specific_force[0])))
        sched.run(1.5)
        times = sorted(truth)
        k = next(i for i, t in enumerate(times) if truth[t][1])  # the impact tick
        u_before, u_after = truth[times[k - 1]][0], truth[times[k]][0]
        assert u_before > 0.2 and abs(u_after) < 1e-6  # no restitution: the wall took it all
        t_imp = times[k]
        # each sample (after the first, which has no previous one) times the time it covers (the
        # period; a physics tick less or more where a float tie put the sample before that
        # instant's physics) adds up to the truth's velocity change
        t_s = np.array([t for t, _ in samples])
        f_s = np.array([f for _, f in samples])
        span = np.diff(t_s)
        assert np.all(np.abs(span - period) <= 1.0 / PHYSICS + 1e-9)
        u = [truth[round(t, 9)][0] if t > 0 else 0.3 for t in t_s]
        assert float(f_s[1:] @ span) == pytest.approx(u[-1] - u[0], abs=1e-12)
        # the impact: the sample whose window holds its tick, or that and the next
        at = int(np.searchsorted(t_s, t_imp - 1e-9))
        near = f_s[at:at + 2] * span[at - 1:at + 1]
        assert near.sum() == pytest.approx(-u_before, rel=0.02), offset
        assert near[0] == pytest.approx(-u_before, rel=0.02) or near[1] < -0.45 * u_before
        rest = np.delete(f_s[1:] * span, [at - 1, at])
        assert np.max(np.abs(rest)) < 0.01 * u_before  # elsewhere only the drag's slow deceleration
