"""A Doppler velocity log (Water Linked DVL A50-like): four Janus beams cast with Embree.

Geometry (Water Linked docs, ``axes.md``, ``dvl-a50.md``): the DVL frame is x
forward, y right (starboard), z down towards the transducers; its origin is
where the beam axes meet. Beam ``i`` (transducer ``id`` i) points
``b_i = (sin t cos a_i, sin t sin a_i, cos t)`` in that frame, tilted ``t``
(22.5 deg) from z at azimuth ``a_i`` (from x towards y); the profile gives the
azimuths. The DVL sits on the vehicle at ``mount`` (DVL -> body).

Each ping (:meth:`Dvl.ping`):

* every beam is one ray from the DVL's origin; its distance is the first hit
  (scaled by configured / true speed of sound, plus seeded noise); a beam is
  valid when it hits and its vertical reach ``d cos t`` lies in the range
  (the profile's 0.05-50 m, narrowed by the range mode);
* the velocity of the DVL over ground is ``v_body + omega x r_mount`` rotated
  into the DVL frame; each beam measures its projection ``b_i . v`` with noise
  ``sigma_i = velocity_noise + velocity_noise_fraction |b_i . v|``;
* bottom lock needs >= 3 valid beams; the velocity is the weighted least-squares
  solution, its covariance ``(B^T W B)^-1`` and the figure of merit the square
  root of its largest eigenvalue (which reproduces the example report of the
  JSON API document from its covariance);
* altitude: the plane through the valid beams' echo points, intersected with
  the DVL's z axis (the mean vertical reach over a flat bottom);
* the velocity is reported in the vehicle frame: the DVL frame turned by the
  mounting rotation offset about z (``v_out = Rz(offset) v_dvl``);
* the next ping follows after ``1 / rate``, the rate from the range-mode table
  of the altitude (faster close to the bottom), the search rate without lock.

Dead reckoning (:meth:`Dvl.dead_reckoning`, ``dead-reckoning.md``): position is
the integral of the *measured* velocity rotated by the DVL's own orientation
relative to the frame of the last reset (its gyro drifts in yaw); without lock
it holds position and its std grows. Pure and deterministic: the noise comes
from ``sensor_rng(seed, name)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hilsim.config import check_keys, load_toml, quantity, require
from hilsim.sim.geometry import F64, Pose, matrix_to_rpy, rot_z, rpy_to_matrix
from hilsim.sim.navigation import sensor_rng
from hilsim.sim.state import VehicleState
from hilsim.sim.world import World

# Water Linked range modes (docs/dvl/range-mode.md): (lower, upper altitude [m]) per mode 0-4
RANGE_MODES: tuple[tuple[float, float], ...] = ((0.05, 0.6), (0.3, 3.0), (1.5, 14.0), (7.7, 36.0), (15.0, math.inf))


@dataclass(frozen=True)
class DvlProfile:
    """A DVL, SI units. beam_tilt, beam_azimuths (4,), beam_width [rad]; range_min/max: altitude
    [m]; rate_altitudes (k,) [m] upper altitude of each rate band and rates (k + 1,) [Hz];
    search_rate, water_tracking_rate, dead_reckoning_rate [Hz]; max_velocity [m/s];
    velocity_noise [m/s] per beam std, velocity_noise_fraction [1] of the beam's speed;
    distance_noise [m] std; rssi_at_1m, nsd [dBm], nsd_noise [dB]; yaw_drift,
    yaw_drift_calibrated [rad/s] std of the gyro's yaw drift before / after calibrate_gyro."""

    name: str
    beam_tilt: float
    beam_azimuths: tuple[float, ...]
    beam_width: float
    range_min: float
    range_max: float
    rate_altitudes: tuple[float, ...]
    rates: tuple[float, ...]
    search_rate: float
    water_tracking_rate: float
    dead_reckoning_rate: float
    max_velocity: float
    velocity_noise: float
    velocity_noise_fraction: float
    distance_noise: float
    rssi_at_1m: float
    nsd: float
    nsd_noise: float
    yaw_drift: float
    yaw_drift_calibrated: float
    sources: dict[str, str] = field(default_factory=dict)

    def rate_at(self, altitude: float) -> float:
        """[Hz] ping rate at ``altitude`` [m]."""
        for upper, rate in zip(self.rate_altitudes, self.rates):
            if altitude < upper:
                return rate
        return self.rates[-1]


_SCALARS = {"beam_tilt": "rad", "beam_width": "rad", "range_min": "m", "range_max": "m", "search_rate": "Hz",
            "water_tracking_rate": "Hz", "dead_reckoning_rate": "Hz", "max_velocity": "m/s",
            "velocity_noise": "m/s", "velocity_noise_fraction": "1", "distance_noise": "m", "rssi_at_1m": "dB",
            "nsd": "dB", "nsd_noise": "dB", "yaw_drift": "rad/s", "yaw_drift_calibrated": "rad/s"}


def load_dvl_profile(path: Path | str) -> DvlProfile:
    """Read a DVL profile (``[sensor] kind = "dvl"``) into SI units (dBm written as unit ``dB``)."""
    doc = load_toml(path)
    check_keys(doc, doc.data, ("sensor",), "")
    s = require(doc, doc.data, "sensor", "")
    keys = ("name", "kind", "description", "beam_azimuths", "rate_altitudes", "rates", *_SCALARS)
    check_keys(doc, s, keys, "sensor")
    if s.get("kind") != "dvl":
        raise doc.error("sensor.kind", f"expected kind = 'dvl', got {s.get('kind')!r}")
    v: dict[str, Any] = {k: float(quantity(doc, s, k, u, "sensor")) for k, u in _SCALARS.items()}
    v["beam_azimuths"] = tuple(quantity(doc, s, "beam_azimuths", "rad", "sensor", length=4))
    v["rate_altitudes"] = tuple(quantity(doc, s, "rate_altitudes", "m", "sensor"))
    v["rates"] = tuple(quantity(doc, s, "rates", "Hz", "sensor"))
    if len(v["rates"]) != len(v["rate_altitudes"]) + 1 or min(v["rates"]) <= 0:
        raise doc.error("sensor.rates", "rates needs one positive rate more than rate_altitudes")
    if not 0 < v["range_min"] < v["range_max"]:
        raise doc.error("sensor.range_max", "need 0 < range_min < range_max")
    if not 0 < v["beam_tilt"] < math.pi / 2:
        raise doc.error("sensor.beam_tilt", "beam_tilt must be in (0, 90) deg")
    v["sources"] = {k: str(s[k]["source"]) for k in s if isinstance(s.get(k), dict)}
    return DvlProfile(name=str(s.get("name", Path(path).stem)), **v)


def range_limits(range_mode: str, profile: DvlProfile) -> tuple[float, float]:
    """[m] (lower, upper) altitude searched in ``range_mode`` (``auto``, ``=a``, ``a<=b``, ``wt``)."""
    lo, hi = profile.range_min, profile.range_max
    if range_mode.startswith("="):
        a = int(range_mode[1:])
        lo, hi = RANGE_MODES[a]
    elif "<=" in range_mode:
        a, b = (int(x) for x in range_mode.split("<="))
        lo, hi = RANGE_MODES[min(a, b)][0], RANGE_MODES[max(a, b)][1]
    return max(lo, profile.range_min), min(hi, profile.range_max)


def beam_directions(profile: DvlProfile) -> F64:
    """(4, 3) unit beam vectors in the DVL frame."""
    t = profile.beam_tilt
    a = np.asarray(profile.beam_azimuths)
    return np.column_stack([math.sin(t) * np.cos(a), math.sin(t) * np.sin(a), np.full(len(a), math.cos(t))])


def figure_of_merit(covariance: F64) -> float:
    """[m/s] square root of the largest eigenvalue of a (3, 3) velocity covariance [(m/s)^2]
    (NaN for a covariance that is not finite: no figure of merit, not an exception)."""
    cov = np.asarray(covariance, dtype=float)
    if not np.all(np.isfinite(cov)):
        return float("nan")
    return float(math.sqrt(max(0.0, float(np.linalg.eigvalsh(cov)[-1]))))


@dataclass(frozen=True)
class DvlPing:
    """One ping. time [s]; distance (4,) [m] along each beam (-1 invalid); beam_valid (4,);
    beam_velocity (4,) [m/s] (0 invalid); rssi, nsd (4,) [dBm]; velocity (3,) [m/s] vehicle frame;
    covariance (3, 3) [(m/s)^2]; fom [m/s]; altitude [m] (-1 without lock); valid: bottom lock;
    interval [s] to the next ping; water_tracking: velocity relative to the water."""

    time: float
    distance: F64
    beam_valid: np.ndarray
    beam_velocity: F64
    rssi: F64
    nsd: F64
    velocity: F64
    covariance: F64
    fom: float
    altitude: float
    valid: bool
    interval: float
    water_tracking: bool = False


@dataclass(frozen=True)
class DvlPosition:
    """Dead reckoning. time [s]; position (3,) [m] x, y, z (down) in the frame of the last reset;
    std [m]; attitude (3,) roll, pitch, yaw [rad] relative to that frame; status 0 ok / 1."""

    time: float
    position: F64
    std: float
    attitude: F64
    status: int


class Dvl:
    """The DVL model (see the module docstring). world: the scene its beams see; mount: DVL -> body
    pose; seed: scenario seed. Configuration the device changes: speed_of_sound [m/s],
    mounting_rotation_offset [rad], range_mode (str), sound_speed_true [m/s] of the water."""

    def __init__(self, profile: DvlProfile, world: World, mount: Pose = Pose(), seed: int = 0, name: str = "dvl",
                 sound_speed_true: float = 1500.0) -> None:
        self.profile = profile
        self.world = world
        self.mount = mount
        self.name = name
        self.rng = sensor_rng(seed, name)
        self.beams = beam_directions(profile)
        self.sound_speed_true = float(sound_speed_true)
        self.speed_of_sound = float(sound_speed_true)
        self.mounting_rotation_offset = 0.0
        self.range_mode = "auto"
        self._yaw_drift_rate = float(profile.yaw_drift * self.rng.standard_normal())
        self._dr_pos = np.zeros(3)
        self._dr_std = 0.0
        self._dr_ref: F64 = np.eye(3)
        self._dr_t0 = 0.0
        self._last_ping: float | None = None
        self._reset_pending = True

    # ---- frames ---------------------------------------------------------------------------------
    def _dvl_rotation(self, state: VehicleState) -> F64:
        """(3, 3) DVL -> world."""
        return rpy_to_matrix(*state.attitude) @ self.mount.rotation

    def _vehicle_frame_rotation(self, state: VehicleState) -> F64:
        """(3, 3) output (vehicle) frame -> world: the DVL frame turned back by the mounting offset."""
        return self._dvl_rotation(state) @ rot_z(self.mounting_rotation_offset).T

    def true_velocity(self, state: VehicleState) -> F64:
        """(3,) [m/s] velocity over ground of the DVL's origin in the DVL frame (lever arm included)."""
        v = np.asarray(state.velocity, float) + np.cross(np.asarray(state.angular_velocity, float), self.mount.position)
        return np.asarray(self.mount.rotation.T @ v)

    # ---- one ping ---------------------------------------------------------------------------------
    def ping(self, state: VehicleState) -> DvlPing:
        """Cast the four beams at ``state`` and compute what the DVL reports (draws noise)."""
        p = self.profile
        scale = self.speed_of_sound / self.sound_speed_true
        r_wd = self._dvl_rotation(state)
        origin = np.asarray(state.position, float) + rpy_to_matrix(*state.attitude) @ self.mount.position
        dirs = self.beams @ r_wd.T
        cos_t = math.cos(p.beam_tilt)
        hits = self.world.cast(np.repeat(origin[None, :], 4, axis=0), dirs, 0.0, 1.05 * p.range_max / cos_t)
        n = self.rng.standard_normal(12)
        water = self.range_mode == "wt"
        lo, hi = range_limits(self.range_mode, p)
        true_d = np.where(hits.hit, hits.t, np.inf)
        vertical = true_d * cos_t
        in_range = hits.hit & (vertical >= lo) & (vertical <= hi)
        v_dvl = self.true_velocity(state)
        vb_true = self.beams @ v_dvl * scale
        sigma = p.velocity_noise + p.velocity_noise_fraction * np.abs(vb_true)
        vb = vb_true + sigma * n[0:4]
        dist = np.where(in_range, true_d * scale + p.distance_noise * n[4:8], -1.0)
        nsd = p.nsd + p.nsd_noise * n[8:12]
        rssi = np.where(hits.hit, p.rssi_at_1m - 40.0 * np.log10(np.maximum(true_d, 0.05)), nsd + 3.0)
        fast = float(np.linalg.norm(v_dvl)) > p.max_velocity
        valid_beam = np.asarray(in_range, dtype=bool) & (not fast)
        if water:
            valid_beam = np.full(4, not fast, dtype=bool)
        ok = int(valid_beam.sum()) >= 3
        velocity, cov, fom, altitude = np.zeros(3), np.eye(3), 10.0, -1.0
        if ok:
            b = self.beams[valid_beam]
            w = 1.0 / sigma[valid_beam] ** 2
            info = b.T @ (w[:, None] * b)
            cov_dvl = np.linalg.inv(info)
            v_est = cov_dvl @ (b.T @ (w * vb[valid_beam]))
            rz = rot_z(self.mounting_rotation_offset)
            velocity = rz @ v_est
            cov = rz @ cov_dvl @ rz.T
            fom = figure_of_merit(cov)
            if not water:
                pts = dist[valid_beam, None] * b
                a = np.column_stack([np.ones(len(pts)), pts[:, 0], pts[:, 1]])
                altitude = float(np.linalg.lstsq(a, pts[:, 2], rcond=None)[0][0])
        if water:
            rate = p.water_tracking_rate
        elif ok:
            rate = p.rate_at(altitude)
        else:
            rate = p.search_rate
        return DvlPing(state.time, dist, valid_beam, np.where(valid_beam, vb, 0.0), rssi, nsd, velocity, cov,
                       fom, altitude, ok, 1.0 / rate, water)

    # ---- dead reckoning ---------------------------------------------------------------------------
    def reset_dead_reckoning(self, state: VehicleState) -> None:
        """Start a new run at ``state``: position and angles zero, the frame is the vehicle frame now."""
        self._dr_ref = self._vehicle_frame_rotation(state)
        self._dr_pos = np.zeros(3)
        self._dr_std = 0.0
        self._dr_t0 = state.time
        self._last_ping = None
        self._reset_pending = False

    def calibrate_gyro(self) -> None:
        """Calibrate the gyro (the vehicle still): the yaw drift drops to the calibrated figure."""
        self._yaw_drift_rate = float(self.profile.yaw_drift_calibrated * self.rng.standard_normal())

    def _relative_rotation(self, state: VehicleState) -> F64:
        drift = rot_z(self._yaw_drift_rate * (state.time - self._dr_t0))
        return np.asarray(drift @ self._dr_ref.T @ self._vehicle_frame_rotation(state))

    def integrate(self, ping: DvlPing, state: VehicleState) -> None:
        """Advance dead reckoning with a ping's measured velocity (the device does it at each ping)."""
        if self._reset_pending:
            self.reset_dead_reckoning(state)
        dt = 0.0 if self._last_ping is None else max(0.0, ping.time - self._last_ping)
        self._last_ping = ping.time
        if ping.valid and not ping.water_tracking:
            self._dr_pos = self._dr_pos + self._relative_rotation(state) @ ping.velocity * dt
            self._dr_std = math.hypot(self._dr_std, ping.fom * dt)
        else:
            self._dr_std += 0.1 * dt   # [m/s] growth without velocity (estimate: IMU-only prediction)

    def dead_reckoning(self, state: VehicleState) -> DvlPosition:
        """The dead-reckoning report at ``state`` (about 5 Hz on the device)."""
        if self._reset_pending:
            self.reset_dead_reckoning(state)
        roll, pitch, yaw = matrix_to_rpy(self._relative_rotation(state))
        return DvlPosition(state.time, self._dr_pos.copy(), self._dr_std, np.array([roll, pitch, yaw]), 0)


__all__ = ["Dvl", "DvlPing", "DvlPosition", "DvlProfile", "RANGE_MODES", "beam_directions", "figure_of_merit",
           "load_dvl_profile", "range_limits"]
