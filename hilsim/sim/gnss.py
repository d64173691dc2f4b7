"""A GNSS receiver on the vehicle's mast: geodetic fixes from the NED position, none under water.

The scenario's ``[world] origin`` (:class:`~hilsim.sim.scenario.GeodeticOrigin`)
ties NED (0, 0, 0) to a WGS84 latitude, longitude and altitude; positions
around it are converted with the local radii of curvature (exact to millimetres
over the few kilometres a vehicle covers from its origin). The antenna is the
sensor's mount point (a mast: negative body z). Radio does not reach through
water: while the antenna is below ``submerged_depth`` the receiver has no fix;
after it surfaces the fix returns ``time_to_fix`` later (the profile's
reacquisition time). Position noise is white per fix, per horizontal axis
``horizontal_noise`` and vertically ``vertical_noise``; a dual-antenna unit
also gives true heading (``heading_noise``). Pure and deterministic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hilsim.config import check_keys, load_toml, quantity, require
from hilsim.sim.geometry import F64, Pose, rpy_to_matrix
from hilsim.sim.navigation import sensor_rng
from hilsim.sim.scenario import DEFAULT_ORIGIN, GeodeticOrigin
from hilsim.sim.state import VehicleState

WGS84_A = 6378137.0                 # [m] semi-major axis
WGS84_F = 1.0 / 298.257223563       # flattening
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


def radii(lat_rad: float) -> tuple[float, float]:
    """(meridian, prime-vertical) radii of curvature [m] of WGS84 at latitude [rad]."""
    s2 = math.sin(lat_rad) ** 2
    w = math.sqrt(1.0 - WGS84_E2 * s2)
    return WGS84_A * (1.0 - WGS84_E2) / w ** 3, WGS84_A / w


def ned_to_geodetic(ned: F64, origin: GeodeticOrigin) -> F64:
    """(n, 3) NED positions [m] -> (n, 3) latitude [deg], longitude [deg], altitude [m] (MSL)."""
    p = np.atleast_2d(np.asarray(ned, dtype=float))
    lat0 = math.radians(origin.lat_deg)
    rm, rn = radii(lat0)
    lat = origin.lat_deg + np.degrees(p[:, 0] / (rm + origin.alt_m))
    lon = origin.lon_deg + np.degrees(p[:, 1] / ((rn + origin.alt_m) * math.cos(lat0)))
    lon = (lon + 180.0) % 360.0 - 180.0
    return np.column_stack([lat, lon, origin.alt_m - p[:, 2]])


def geodetic_to_ned(lat_deg: float, lon_deg: float, alt_m: float, origin: GeodeticOrigin) -> F64:
    """(3,) NED [m] of a geodetic point (inverse of :func:`ned_to_geodetic`)."""
    lat0 = math.radians(origin.lat_deg)
    rm, rn = radii(lat0)
    dlon = (lon_deg - origin.lon_deg + 180.0) % 360.0 - 180.0
    return np.array([math.radians(lat_deg - origin.lat_deg) * (rm + origin.alt_m),
                     math.radians(dlon) * (rn + origin.alt_m) * math.cos(lat0), origin.alt_m - alt_m])


@dataclass(frozen=True)
class GnssProfile:
    """A GNSS receiver, SI. rate [Hz] default output rate; time_to_fix [s] after surfacing;
    horizontal_noise (per axis), vertical_noise [m] std; velocity_noise [m/s] std; satellites,
    hdop, fix_quality (GGA 1 GPS, 2 DGPS, 4 RTK) as counts; geoid_separation [m];
    submerged_depth [m] antenna depth beyond which there is no signal; dual_antenna: gives true
    heading (HDT) with heading_noise [rad]; talker: NMEA talker id ("GP", "GN")."""

    name: str
    rate: float
    time_to_fix: float
    horizontal_noise: float
    vertical_noise: float
    velocity_noise: float
    satellites: int
    hdop: float
    fix_quality: int
    geoid_separation: float
    submerged_depth: float
    dual_antenna: bool = False
    heading_noise: float = 0.0
    talker: str = "GP"
    sources: dict[str, str] = field(default_factory=dict)


_UNITS = {"rate": "Hz", "time_to_fix": "s", "horizontal_noise": "m", "vertical_noise": "m",
          "velocity_noise": "m/s", "satellites": "1", "hdop": "1", "fix_quality": "1", "geoid_separation": "m",
          "submerged_depth": "m", "heading_noise": "rad"}


def load_gnss_profile(path: Path | str) -> GnssProfile:
    """Read a GNSS profile (``[sensor] kind = "gnss"``) into SI units."""
    doc = load_toml(path)
    check_keys(doc, doc.data, ("sensor",), "")
    s = require(doc, doc.data, "sensor", "")
    check_keys(doc, s, ("name", "kind", "description", "dual_antenna", "talker", *_UNITS), "sensor")
    if s.get("kind") != "gnss":
        raise doc.error("sensor.kind", f"expected kind = 'gnss', got {s.get('kind')!r}")
    v: dict[str, Any] = {}
    for k, unit in _UNITS.items():
        if k == "heading_noise" and k not in s:
            continue
        v[k] = float(quantity(doc, s, k, unit, "sensor"))
    if not 1.0 <= v["rate"] <= 10.0:
        raise doc.error("sensor.rate", "rate must be 1-10 Hz")
    if int(v["fix_quality"]) not in (1, 2, 4, 5):
        raise doc.error("sensor.fix_quality", "fix_quality must be 1, 2, 4 or 5 (GGA)")
    v["satellites"], v["fix_quality"] = int(v["satellites"]), int(v["fix_quality"])
    dual = s.get("dual_antenna", False)
    if not isinstance(dual, bool):
        raise doc.error("sensor.dual_antenna", "dual_antenna must be true or false")
    talker = s.get("talker", "GP")
    if not (isinstance(talker, str) and len(talker) == 2 and talker.isalpha() and talker.isupper()):
        raise doc.error("sensor.talker", "talker must be two upper-case letters (GP, GN, ...)")
    v["sources"] = {k: str(s[k]["source"]) for k in s if isinstance(s.get(k), dict)}
    return GnssProfile(name=str(s.get("name", Path(path).stem)), dual_antenna=dual, talker=talker, **v)


@dataclass(frozen=True)
class GnssFix:
    """One output epoch. time [s] sim time; fix: a position solution; quality (GGA, 0 none);
    lat_deg, lon_deg [deg], alt_m [m] MSL (NaN without fix); satellites used; hdop;
    speed [m/s] and course [rad, from north] over ground; heading [rad] true (NaN unless a
    dual-antenna fix); antenna_ned (3,) [m] true antenna position; submerged: antenna under water."""

    time: float
    fix: bool
    quality: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    satellites: int
    hdop: float
    speed: float
    course: float
    heading: float
    antenna_ned: F64
    submerged: bool


class Gnss:
    """The receiver model. mount: antenna pose on the body (its position is the mast top);
    origin: the scenario's geodetic origin; seed: scenario seed."""

    def __init__(self, profile: GnssProfile, mount: Pose = Pose(), origin: GeodeticOrigin | None = None,
                 seed: int = 0, name: str = "gnss") -> None:
        self.profile = profile
        self.mount = mount
        self.origin = origin or DEFAULT_ORIGIN
        self.name = name
        self.rng = sensor_rng(seed, name)
        self._surfaced_at: float | None = None
        self.outage = False   # a timeline fault: no fix whatever the antenna sees

    def antenna(self, state: VehicleState) -> F64:
        """(3,) [m] NED position of the antenna."""
        return np.asarray(state.position, float) + rpy_to_matrix(*state.attitude) @ self.mount.position

    def sample(self, state: VehicleState) -> GnssFix:
        """The receiver's output at ``state`` (draws noise). Call it at the output rate: the fix
        returns ``time_to_fix`` after the first call that finds the antenna out of the water."""
        p = self.profile
        ant = self.antenna(state)
        n = self.rng.standard_normal(7)
        submerged = bool(ant[2] > p.submerged_depth)
        if submerged or self.outage:
            self._surfaced_at = None
        elif self._surfaced_at is None:
            self._surfaced_at = state.time
        fix = self._surfaced_at is not None and state.time - self._surfaced_at >= p.time_to_fix - 1e-9
        if not fix:
            acquiring = self._surfaced_at is not None
            sats = int(min(p.satellites, 3 * (state.time - self._surfaced_at) / max(p.time_to_fix, 1e-3))) \
                if acquiring and self._surfaced_at is not None else 0
            nan = math.nan
            return GnssFix(state.time, False, 0, nan, nan, nan, sats, 99.99, nan, nan, nan, ant, submerged)
        noisy = ant + np.array([p.horizontal_noise * n[0], p.horizontal_noise * n[1], p.vertical_noise * n[2]])
        lat, lon, alt = ned_to_geodetic(noisy, self.origin)[0]
        v_ned = rpy_to_matrix(*state.attitude) @ (np.asarray(state.velocity, float)
                                                  + np.cross(np.asarray(state.angular_velocity, float),
                                                             self.mount.position))
        vn, ve = v_ned[0] + p.velocity_noise * n[3], v_ned[1] + p.velocity_noise * n[4]
        speed = math.hypot(vn, ve)
        course = math.atan2(ve, vn) % (2 * math.pi)
        heading = (state.heading + p.heading_noise * n[5]) % (2 * math.pi) if p.dual_antenna else math.nan
        sats = max(4, p.satellites + int(round(n[6])))
        hdop = max(0.5, p.hdop * math.sqrt(p.satellites / sats))
        return GnssFix(state.time, True, p.fix_quality, float(lat), float(lon), float(alt), sats, round(hdop, 2),
                       speed, course, heading, ant, False)


__all__ = ["Gnss", "GnssFix", "GnssProfile", "geodetic_to_ned", "load_gnss_profile", "ned_to_geodetic", "radii"]
