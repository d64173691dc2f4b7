"""A single-beam echosounder / altimeter (Blue Robotics Ping-like), cast with Embree.

The transducer looks along its sensor frame's +z axis (:data:`BEAM_AXIS`): a sensor
mounted with ``orientation_deg = [0, 0, 0]`` looks straight down. Its beam is a cone of half-power full width ``beam_width``;
:func:`cone_directions` samples it with rings of rays (centre, then rings out to
the first null, about 1.5 x the half-power half-angle). Each ray's echo has the
strength ``gain(angle) * |cos(incidence)| * R(object)`` (a Gaussian beam
pattern fitted to the half-power width, Lambert-like incidence, the object's
reflection coefficient from the world) and spreads over the pulse length
``c * transmit_duration / 2``.

* distance: the nearest echo inside the half-power cone (the first surface
  the beam meets), scaled by configured / true speed of sound, plus noise;
* confidence [%]: the share of the half-power cone's rays that return an echo
  within the scan window, lowered towards the end of the range;
* profile: ``samples`` bins over [scan_start, scan_start + scan_length], the sum
  of the echoes' pulses plus a seeded noise floor, amplified by the gain
  setting and clipped to 0-255;
* auto mode picks the scan window (the distance in the middle third) and the
  gain; manual mode keeps what was set.
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
from hilsim.sim.state import VehicleState
from hilsim.sim.world import World

BEAM_AXIS = np.array([0.0, 0.0, 1.0])   # the beam axis in the sensor frame: +z (down when mounted level)
GAINS = (0.6, 1.8, 5.5, 12.9, 30.2, 66.1, 144.0)   # ping-protocol gain_setting 0-6 (ping1d.json)


@dataclass(frozen=True)
class EchosounderProfile:
    """An echosounder, SI. beam_width [rad] half-power full width; range_min/max [m];
    frequency [Hz]; ping_interval [s] default; transmit_duration [s]; distance_noise_fraction [1]
    of the distance (std); samples: profile length; rings, rays_per_ring: the cone sampling."""

    name: str
    beam_width: float
    range_min: float
    range_max: float
    frequency: float
    ping_interval: float
    transmit_duration: float
    distance_noise_fraction: float
    samples: int = 200
    rings: int = 3
    rays_per_ring: int = 12
    sources: dict[str, str] = field(default_factory=dict)


_UNITS = {"beam_width": "rad", "range_min": "m", "range_max": "m", "frequency": "Hz", "ping_interval": "s",
          "transmit_duration": "s", "distance_noise_fraction": "1", "samples": "1", "rings": "1",
          "rays_per_ring": "1"}


def load_echosounder_profile(path: Path | str) -> EchosounderProfile:
    """Read an echosounder profile (``[sensor] kind = "echosounder"``) into SI units."""
    doc = load_toml(path)
    check_keys(doc, doc.data, ("sensor",), "")
    s = require(doc, doc.data, "sensor", "")
    check_keys(doc, s, ("name", "kind", "description", *_UNITS), "sensor")
    if s.get("kind") != "echosounder":
        raise doc.error("sensor.kind", f"expected kind = 'echosounder', got {s.get('kind')!r}")
    v: dict[str, Any] = {}
    for k, unit in _UNITS.items():
        if k in ("samples", "rings", "rays_per_ring") and k not in s:
            continue
        v[k] = float(quantity(doc, s, k, unit, "sensor"))
    for k in ("samples", "rings", "rays_per_ring"):
        if k in v:
            v[k] = int(v[k])
            if v[k] < 1:
                raise doc.error(f"sensor.{k}", f"{k} must be >= 1")
    if not 0 < v["range_min"] < v["range_max"]:
        raise doc.error("sensor.range_max", "need 0 < range_min < range_max")
    v["sources"] = {k: str(s[k]["source"]) for k in s if isinstance(s.get(k), dict)}
    return EchosounderProfile(name=str(s.get("name", Path(path).stem)), **v)


def cone_directions(beam_width: float, rings: int, per_ring: int) -> tuple[F64, F64]:
    """Rays sampling a cone around +z: ((n, 3) unit directions, (n,) off-axis angles [rad]).
    The centre ray, then ``rings`` rings out to 1.5 x the half-power half-angle."""
    half = 0.5 * beam_width
    dirs, angles = [np.array([0.0, 0.0, 1.0])], [0.0]
    for k in range(1, rings + 1):
        a = 1.5 * half * k / rings
        phis = 2 * math.pi * (np.arange(per_ring) + 0.5 * (k % 2)) / per_ring
        for phi in phis:
            dirs.append(np.array([math.sin(a) * math.cos(phi), math.sin(a) * math.sin(phi), math.cos(a)]))
            angles.append(a)
    return np.array(dirs), np.array(angles)


@dataclass(frozen=True)
class EchoPing:
    """One ping. time [s]; distance [m] (NaN: no echo); confidence [%] 0-100; scan_start,
    scan_length [m]; transmit_duration [s]; gain_setting 0-6; profile (samples,) uint8;
    ping_number."""

    time: float
    distance: float
    confidence: int
    scan_start: float
    scan_length: float
    transmit_duration: float
    gain_setting: int
    profile: np.ndarray
    ping_number: int


class Echosounder:
    """The echosounder model. mount: sensor -> body (beam along the sensor's +z); seed: scenario
    seed. Device settings: speed_of_sound [m/s], mode_auto, scan_start/scan_length [m] (manual),
    gain_setting (manual), sound_speed_true [m/s] of the water."""

    def __init__(self, profile: EchosounderProfile, world: World, mount: Pose = Pose(), seed: int = 0,
                 name: str = "echosounder", sound_speed_true: float = 1500.0) -> None:
        self.profile = profile
        self.world = world
        self.mount = mount
        self.name = name
        self.rng = sensor_rng(seed, name)
        self.sound_speed_true = float(sound_speed_true)
        self.speed_of_sound = float(sound_speed_true)
        self.mode_auto = True
        self.scan_start = 0.0
        self.scan_length = min(profile.range_max, 10.0)
        self.gain_setting = 3
        self.ping_number = 0
        self.dirs, self.angles = cone_directions(profile.beam_width, profile.rings, profile.rays_per_ring)
        sigma = 0.5 * profile.beam_width / math.sqrt(2.0 * math.log(2.0))   # Gaussian: -3 dB at half width
        self.pattern = np.exp(-0.5 * (self.angles / sigma) ** 2)
        self.in_main = self.angles <= 0.5 * profile.beam_width + 1e-12

    def cast(self, state: VehicleState) -> tuple[F64, F64]:
        """((n,) true distance [m] (inf miss), (n,) echo strength [0, 1]) of the cone's rays."""
        r_ws = rpy_to_matrix(*state.attitude) @ self.mount.rotation
        origin = np.asarray(state.position, float) + rpy_to_matrix(*state.attitude) @ self.mount.position
        dirs = self.dirs @ r_ws.T
        hits = self.world.cast(np.repeat(origin[None, :], len(dirs), axis=0), dirs, 0.0, self.profile.range_max)
        t = np.where(hits.hit, hits.t, np.inf)
        cos_inc = np.abs(np.sum(hits.normal * dirs, axis=1))
        refl = np.abs(self.world.obj_reflection[np.maximum(hits.obj, 0)]) if len(self.world.objects) else 0.0
        strength = np.where(hits.hit, self.pattern * cos_inc * refl, 0.0)
        return t, strength

    def ping(self, state: VehicleState) -> EchoPing:
        """One measurement at ``state`` (draws noise, advances ping_number)."""
        p = self.profile
        self.ping_number += 1
        scale = self.speed_of_sound / self.sound_speed_true
        t, strength = self.cast(state)
        d_all = t * scale
        main = self.in_main & np.isfinite(t) & (d_all >= p.range_min)
        distance = math.nan
        if main.any():
            distance = float(d_all[main].min()) * (1.0 + p.distance_noise_fraction * float(self.rng.standard_normal()))
        if self.mode_auto:
            self._auto_window(distance)
        lo, hi = self.scan_start, self.scan_start + self.scan_length
        inside = main & (d_all >= lo) & (d_all <= hi)
        confidence = 0
        if math.isfinite(distance) and lo <= distance <= hi:
            share = float(inside.sum()) / float(self.in_main.sum())
            fade = min(1.0, max(0.0, (p.range_max - distance) / (0.2 * p.range_max)))
            confidence = int(round(100.0 * share * fade))
        else:
            distance = distance if math.isfinite(distance) else math.nan
        prof = self._profile(d_all, strength, lo, hi)
        return EchoPing(state.time, distance, confidence, lo, self.scan_length, p.transmit_duration, self.gain_setting,
                        prof, self.ping_number)

    def _auto_window(self, distance: float) -> None:
        """Auto mode: a window starting at 0 whose length holds the target in its middle (>= 1 m)."""
        p = self.profile
        self.scan_start = 0.0
        if math.isfinite(distance):
            self.scan_length = float(min(p.range_max, max(1.0, math.ceil(1.5 * distance))))
        else:
            self.scan_length = float(p.range_max)
        self.gain_setting = int(min(6, max(0, round(math.log2(max(self.scan_length, 1.0))))))

    def _profile(self, d: F64, strength: F64, lo: float, hi: float) -> np.ndarray:
        p = self.profile
        n = p.samples
        centres = lo + (np.arange(n) + 0.5) * (hi - lo) / n
        pulse = max(0.5 * self.speed_of_sound * p.transmit_duration, (hi - lo) / n)
        ok = np.isfinite(d) & (strength > 0)
        echo = np.zeros(n)
        if ok.any():
            dist = d[ok][:, None]
            spread = np.maximum(dist, 0.1) ** 2          # two-way spreading, normalised at 1 m
            echo = np.sum(strength[ok][:, None] / spread * np.exp(-0.5 * ((centres[None, :] - dist) / pulse) ** 2),
                          axis=0)
        gain = GAINS[self.gain_setting]
        noise = 2.0 + 1.0 * np.abs(self.rng.standard_normal(n))
        level = 40.0 * gain * echo / max(1, int(self.in_main.sum())) + noise
        return np.clip(np.round(level), 0, 255).astype(np.uint8)


__all__ = ["BEAM_AXIS", "EchoPing", "Echosounder", "EchosounderProfile", "GAINS", "cone_directions",
           "load_echosounder_profile"]
