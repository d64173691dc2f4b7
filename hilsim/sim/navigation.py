"""Navigation sensors: pressure (depth) and IMU/AHRS, sampled from a VehicleState.

Stonefish style: :class:`Sensor` owns the update rate (:meth:`Sensor.update`
samples only when a sample is due, on an absolute grid ``offset + k / rate``)
and each sensor implements only :meth:`Sensor.sample`. A scheduler that runs
each sensor at its own period may call ``sample`` directly. Every sensor draws
its noise from its own ``numpy.random.Generator`` seeded from the scenario
seed and the sensor's name, so the same scenario and seed give the same
readings. Readings are SI and in hilsim's frames (NED world, body x forward,
y starboard, z down); device code converts at the wire (bar, degrees, the
sensor's own axes).

Profiles (``devices/sensors/*.toml``) name every value's unit and source and
are read by :func:`load_pressure_profile` and :func:`load_imu_profile`.
"""

from __future__ import annotations

import math
import zlib
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Generic, Sequence, TypeVar

import numpy as np

from hilsim.config import Doc, check_keys, load_toml, quantity, require
from hilsim.sim.geometry import F64, rpy_to_matrix, wrap_angle
from hilsim.sim.state import VehicleState

GRAVITY = 9.80665  # [m/s^2] standard gravity
ATMOSPHERE = 101325.0  # [Pa] standard atmosphere
R = TypeVar("R")


def sensor_rng(seed: int, name: str) -> np.random.Generator:
    """The noise stream of sensor ``name`` for scenario ``seed`` (stable across runs and platforms)."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode("utf-8"))])


def depth_from_pressure(pressure: float, density: float = 1025.0, gravity: float = GRAVITY,
                        atmosphere: float = ATMOSPHERE) -> float:
    """Depth [m] from absolute pressure [Pa], water density [kg/m^3], gravity [m/s^2], atmosphere [Pa]."""
    return (pressure - atmosphere) / (density * gravity)


class Sensor(ABC, Generic[R]):
    """Base of the navigation sensors: rate handling and the noise stream.

    rate [Hz]; offset [s] phase of the sampling grid; seed: scenario seed.
    """

    def __init__(self, name: str, rate: float, seed: int = 0, offset: float = 0.0):
        if not rate > 0:
            raise ValueError(f"{name}: rate must be > 0 Hz, got {rate}")
        self.name = name
        self.rate = float(rate)
        self.offset = float(offset)
        self.rng = sensor_rng(seed, name)
        self.last: R | None = None
        self._next = self.offset

    @property
    def period(self) -> float:
        """[s] time between samples."""
        return 1.0 / self.rate

    def update(self, state: VehicleState) -> R | None:
        """Sample if one is due at ``state.time`` [s] (then return it), else None.

        Deadlines stay on the grid ``offset + k * period``: a late call samples
        once and the next deadline is the next grid point after ``state.time``.
        """
        t = state.time
        if t + 1e-9 < self._next:
            return None
        self.last = self.sample(state)
        k = math.floor((t - self.offset) * self.rate + 1e-9) + 1
        self._next = self.offset + k * self.period
        return self.last

    @abstractmethod
    def sample(self, state: VehicleState) -> R:
        """One reading of ``state`` (draws noise)."""


def _load(path: Path | str, kind: str, spec: dict[str, tuple[str, float | None]]) -> tuple[Doc, dict[str, Any]]:
    """Read ``[sensor]`` of kind ``kind``: key -> (SI unit, default or None = required)."""
    doc = load_toml(path)
    check_keys(doc, doc.data, ("sensor",), "")
    s = require(doc, doc.data, "sensor", "")
    check_keys(doc, s, ("name", "kind", "description", *spec), "sensor")
    if s.get("kind") != kind:
        raise doc.error("sensor.kind", f"expected kind = {kind!r}, got {s.get('kind')!r}")
    vals: dict[str, Any] = {"name": str(s.get("name", Path(path).stem))}
    for key, (unit, default) in spec.items():
        if unit == "K" and isinstance(s.get(key), dict) and s[key].get("unit") == "degC":
            raise doc.error(f"sensor.{key}", "a temperature difference needs unit \"K\", not \"degC\"")
        v = float(quantity(doc, s, key, unit, "sensor", default=default))
        if v < 0 and key not in ("range_min", "offset", "temperature_offset"):
            raise doc.error(f"sensor.{key}", f"must be >= 0, got {v}")
        vals[key] = v
    if not vals["rate"] > 0:
        raise doc.error("sensor.rate", "rate must be > 0")
    vals["sources"] = {k: str(s[k]["source"]) for k in spec if isinstance(s.get(k), dict)}
    return doc, vals


@dataclass(frozen=True)
class PressureProfile:
    """A Keller-like pressure transmitter, SI: rate [Hz]; range_min/max [Pa]
    absolute; noise [Pa] std; offset [Pa]; resolution [Pa] (0: none);
    temperature_noise [K] std; temperature_resolution [K]."""

    name: str
    rate: float
    range_min: float
    range_max: float
    noise: float
    offset: float = 0.0
    resolution: float = 0.0
    temperature_noise: float = 0.0
    temperature_resolution: float = 0.0
    sources: dict[str, str] = field(default_factory=dict)


def load_pressure_profile(path: Path | str) -> PressureProfile:
    """Read a pressure sensor profile (``kind = "pressure"``) into SI units."""
    doc, v = _load(path, "pressure", {
        "rate": ("Hz", None), "range_min": ("Pa", None), "range_max": ("Pa", None), "noise": ("Pa", None),
        "offset": ("Pa", 0.0), "resolution": ("Pa", 0.0), "temperature_noise": ("K", 0.0),
        "temperature_resolution": ("K", 0.0)})
    if not v["range_max"] > v["range_min"]:
        raise doc.error("sensor.range_max", "range_max must exceed range_min")
    return PressureProfile(**v)


def _quantize(x: float, step: float) -> float:
    return round(x / step) * step if step > 0 else x


@dataclass(frozen=True)
class PressureReading:
    """time [s]; pressure [Pa] absolute (+inf / -inf over / under range, as the
    Keller protocol reports); temperature [K]."""

    time: float
    pressure: float
    temperature: float


class PressureSensor(Sensor[PressureReading]):
    """Absolute pressure ``P_atm + rho g depth`` at the sensor's mount, with
    offset, noise, resolution and range from the profile.

    water_density [kg/m^3] and water_temperature [K] from the scenario;
    gravity [m/s^2]; atmosphere [Pa]; mount (3,) [m] body-frame position.
    """

    def __init__(self, profile: PressureProfile, seed: int = 0, name: str = "pressure",
                 water_density: float = 1025.0, water_temperature: float = 288.15,
                 gravity: float = GRAVITY, atmosphere: float = ATMOSPHERE,
                 mount: Sequence[float] = (0.0, 0.0, 0.0), offset: float = 0.0):
        super().__init__(name, profile.rate, seed, offset)
        self.profile = profile
        self.water_density = float(water_density)
        self.water_temperature = float(water_temperature)
        self.gravity = float(gravity)
        self.atmosphere = float(atmosphere)
        self.mount = np.asarray(mount, dtype=float).reshape(3)

    def true_pressure(self, state: VehicleState) -> float:
        """[Pa] noise-free absolute pressure at the mount (0 m depth and above: atmosphere)."""
        depth = state.depth + float(rpy_to_matrix(*state.attitude)[2] @ self.mount)
        return self.atmosphere + self.water_density * self.gravity * max(depth, 0.0)

    def sample(self, state: VehicleState) -> PressureReading:
        p = self.profile
        noise_p, noise_t = self.rng.standard_normal(2)
        pressure = _quantize(self.true_pressure(state) + p.offset + p.noise * noise_p, p.resolution)
        if pressure > p.range_max:
            pressure = math.inf
        elif pressure < p.range_min:
            pressure = -math.inf
        temp = _quantize(self.water_temperature + p.temperature_noise * noise_t, p.temperature_resolution)
        return PressureReading(state.time, pressure, temp)


@dataclass(frozen=True)
class ImuProfile:
    """A WitMotion-like IMU/AHRS, SI. rate [Hz]; *_noise: white-noise std per
    sample; *_bias: std of the turn-on bias drawn once per run. accel [m/s^2],
    gyro [rad/s], angle (roll, pitch) and heading [rad], mag [T];
    accel_range [m/s^2], gyro_range [rad/s]: outputs clip there;
    temperature_noise [K]."""

    name: str
    rate: float
    accel_noise: float
    accel_bias: float
    gyro_noise: float
    gyro_bias: float
    angle_noise: float
    angle_bias: float
    heading_noise: float
    heading_bias: float
    mag_noise: float
    accel_range: float
    gyro_range: float
    temperature_noise: float = 0.0
    sources: dict[str, str] = field(default_factory=dict)


def load_imu_profile(path: Path | str) -> ImuProfile:
    """Read an IMU profile (``kind = "imu"``) into SI units."""
    units = {"accel_noise": "m/s^2", "accel_bias": "m/s^2", "gyro_noise": "rad/s", "gyro_bias": "rad/s",
             "angle_noise": "rad", "angle_bias": "rad", "heading_noise": "rad", "heading_bias": "rad",
             "mag_noise": "T", "accel_range": "m/s^2", "gyro_range": "rad/s"}
    spec: dict[str, tuple[str, float | None]] = {"rate": ("Hz", None)}
    spec.update({k: (u, None) for k, u in units.items()})
    spec["temperature_noise"] = ("K", 0.0)
    _, v = _load(path, "imu", spec)
    return ImuProfile(**v)


@dataclass(frozen=True)
class ImuReading:
    """time [s]; attitude (3,) roll, pitch, yaw [rad] (yaw from magnetic north);
    angular_velocity (3,) [rad/s] body; specific_force (3,) [m/s^2] body
    (acceleration minus gravity: (0, 0, -g) at rest, z down); magnetic_field
    (3,) [T] body; temperature [K]."""

    time: float
    attitude: F64
    angular_velocity: F64
    specific_force: F64
    magnetic_field: F64
    temperature: float

    @property
    def quaternion(self) -> F64:
        """(4,) unit quaternion (w, x, y, z) of :attr:`attitude` (Z-Y-X)."""
        r, p, y = (0.5 * a for a in self.attitude)
        cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
        return np.array([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                         cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy])


class Imu(Sensor[ImuReading]):
    """Attitude, rates, specific force and magnetic field at the vehicle's origin.

    The IMU is taken at the body origin, aligned with the body axes (no lever
    arm). magnetic_field (3,) [T] NED is the Earth's field (its east part sets
    the declination the reported yaw is measured from); gravity [m/s^2];
    temperature [K] of the housing.

    The accelerometer integrates over its output period, as a MEMS IMU's
    filter does: the body acceleration it reports is the mean over the
    physics steps since its previous sample, ``(v_now - v_prev) / (t_now - t_prev)``
    of the body velocity (each step's ``state.acceleration`` is that step's mean
    ``dv/dt``, so this is their time-weighted mean, at no cost per step), plus
    ``omega x v`` (mean of the two samples') and minus gravity at the current
    attitude. An impact that stops the vehicle within one physics tick shows
    as ``dv / period`` in exactly one sample, whatever the phase of the sampling
    grid, and the samples times their periods add up to the true velocity change.
    The first sample, a sample at the same time as the previous one, or one
    earlier than it (a state from another run) reports ``state.acceleration``
    (the last step's). A velocity the runtime sets outside the physics (a
    timeline ``teleport``: the vehicle at rest elsewhere) shows, like any
    velocity change, in the next sample. The gyro reports the state's rate
    as sampled: it is a state, not a derivative (contacts exert no torque, so
    it has no one-tick steps to miss).
    """

    def __init__(self, profile: ImuProfile, seed: int = 0, name: str = "imu",
                 magnetic_field: Sequence[float] = (2.0e-5, 0.0, 4.5e-5), gravity: float = GRAVITY,
                 temperature: float = 288.15, offset: float = 0.0):
        super().__init__(name, profile.rate, seed, offset)
        self.profile = profile
        self.field_ned = np.asarray(magnetic_field, dtype=float).reshape(3)
        self.declination = math.atan2(self.field_ned[1], self.field_ned[0])
        self.gravity = float(gravity)
        self.temperature = float(temperature)
        draw: Callable[[float, int], F64] = lambda s, n: s * self.rng.standard_normal(n)
        self.accel_bias_value = draw(profile.accel_bias, 3)
        self.gyro_bias_value = draw(profile.gyro_bias, 3)
        self.angle_bias_value = np.append(draw(profile.angle_bias, 2), draw(profile.heading_bias, 1))
        # the previous sample: time [s], body velocity (3,) [m/s], omega x v (3,) [m/s^2]
        self._prev: tuple[float, F64, F64] | None = None

    def body_acceleration(self, state: VehicleState) -> F64:
        """(3,) [m/s^2] the body origin's acceleration in body axes, ``dv/dt + omega x v``,
        averaged since the previous call (see the class); remembers ``state`` for the next."""
        omega = np.asarray(state.angular_velocity, dtype=float)
        velocity = np.array(state.velocity, dtype=float)
        coriolis = np.cross(omega, velocity)
        prev, t = self._prev, state.time
        if prev is not None and t - prev[0] > 1e-9:
            accel = (velocity - prev[1]) / (t - prev[0]) + 0.5 * (coriolis + prev[2])
        else:
            accel = np.asarray(state.acceleration, dtype=float) + coriolis
        self._prev = (t, velocity, coriolis)  # also when time went back: start again from here
        return accel

    def sample(self, state: VehicleState) -> ImuReading:
        p = self.profile
        n = self.rng.standard_normal(13)
        rot = rpy_to_matrix(*state.attitude)
        omega = np.asarray(state.angular_velocity, dtype=float)
        # acceleration of the body origin in body axes (mean over the period), minus gravity
        force = self.body_acceleration(state) - rot.T @ np.array([0.0, 0.0, self.gravity])
        force = np.clip(force + self.accel_bias_value + p.accel_noise * n[0:3], -p.accel_range, p.accel_range)
        gyro = np.clip(omega + self.gyro_bias_value + p.gyro_noise * n[3:6], -p.gyro_range, p.gyro_range)
        att = np.asarray(state.attitude, dtype=float) + self.angle_bias_value
        att = att + np.array([p.angle_noise * n[6], p.angle_noise * n[7], p.heading_noise * n[8]])
        att[2] = wrap_angle(att[2] - self.declination)
        att[0] = wrap_angle(att[0])
        mag = rot.T @ self.field_ned + p.mag_noise * n[9:12]
        temp = self.temperature + p.temperature_noise * n[12]
        return ImuReading(state.time, att, gyro, force, mag, float(temp))
