"""Imaging-sonar description (profile) and runtime settings.

A :class:`SonarProfile` is what a sonar *is* (beams, field of view, frequency,
beam widths, source level): it is read from a TOML file in
``devices/sonars/`` by :func:`load_sonar_profile`. A :class:`SonarSettings` is
what a client may change while it runs (range window, sample count, gain,
time-varied gain, the realism switches); ``profile.default_settings()`` gives
the profile's defaults, and protocols derive new settings with
:meth:`SonarSettings.replace`. Both are frozen values.

Angles are in radians, ranges in metres, frequencies in hertz, levels in dB.
The sonar frame and ray layout are documented in :mod:`hilsim.sim.sonar`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from hilsim.config import ConfigError, Doc, check_keys, load_toml, quantity
from hilsim.sim.geometry import F64

GAIN_MODES = ("paper", "fixed")


@dataclass(frozen=True)
class SonarSettings:
    """Runtime-changeable sonar settings (validated on construction).

    range_min, range_max: the range window [m], 0 <= range_min < range_max.
    n_samples: range bins across the window (bin ``i`` covers
        ``[range_min + i dr, range_min + (i + 1) dr)``, ``dr = (range_max - range_min) / n_samples``).
    elevation_rays: rays per beam across the elevation aperture (paper: 1000).
    gain_mode: ``"paper"`` (brightest cell = 255, the others linear in their
        intensity relative to it) or ``"fixed"`` (dB gain + TVG, log-mapped to
        8 bits; see :func:`hilsim.sim.sonar.fixed_gain_levels`).
    gain_db: receiver gain [dB] ("fixed" mode).
    tvg: apply time-varied gain ("fixed" mode).
    tvg_spreading_db: N in the TVG term ``N log10(R / 1 m)`` [dB]; 40 undoes
        the two-way R^-4 of eq. 9.
    tvg_absorption: add ``2 alpha R`` [dB] to the TVG (alpha: the profile's water absorption).
    dynamic_range_db: levels from ``-dynamic_range_db`` to 0 dB map to pixels 0..255 [dB].
    spread: spread each ray's echo over the range interval its elevation
        footprint covers (the fix of the paper's empty bins); False = the paper's
        single-bin deposit.
    spread_max_bins: cap of that interval's width [range bins] (grazing incidence).
    speckle: multiply each cell by fully developed speckle (Rayleigh amplitude).
    noise: add a noise floor with mean ``noise_level_db`` [dB re k^2 I0] per cell.
    beam_pattern: leak each beam's echo into the others by the azimuth
        beam pattern (sinc^2 with the profile's -3 dB beam width; side lobes).
    absorption: attenuate each echo by the two-way water absorption ``2 alpha R`` [dB].
    """

    range_min: float
    range_max: float
    n_samples: int
    elevation_rays: int = 1000
    gain_mode: str = "fixed"
    gain_db: float = 0.0
    tvg: bool = True
    tvg_spreading_db: float = 40.0
    tvg_absorption: bool = True
    dynamic_range_db: float = 80.0
    spread: bool = True
    spread_max_bins: float = 8.0
    speckle: bool = False
    noise: bool = False
    noise_level_db: float = -100.0
    beam_pattern: bool = False
    absorption: bool = False

    def __post_init__(self) -> None:
        for name in ("range_min", "range_max", "gain_db", "tvg_spreading_db", "dynamic_range_db",
                     "spread_max_bins", "noise_level_db"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{name} must be a finite number, got {v!r}")
        for name in ("n_samples", "elevation_rays"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        for name in ("tvg", "tvg_absorption", "spread", "speckle", "noise", "beam_pattern", "absorption"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")
        if self.range_min < 0.0:
            raise ValueError(f"range_min must be >= 0 m, got {self.range_min}")
        if not self.range_min < self.range_max:
            raise ValueError(f"range_min ({self.range_min} m) must be < range_max ({self.range_max} m)")
        if self.gain_mode not in GAIN_MODES:
            raise ValueError(f"gain_mode must be one of {GAIN_MODES}, got {self.gain_mode!r}")
        if self.dynamic_range_db <= 0.0:
            raise ValueError(f"dynamic_range_db must be > 0 dB, got {self.dynamic_range_db}")
        if self.spread_max_bins <= 0.0:
            raise ValueError(f"spread_max_bins must be > 0, got {self.spread_max_bins}")

    @property
    def range_resolution(self) -> float:
        """Width of one range bin [m]."""
        return (self.range_max - self.range_min) / self.n_samples

    @property
    def ranges(self) -> F64:
        """(n_samples,) float [m]: range-bin centres."""
        return np.asarray(self.range_min + (np.arange(self.n_samples) + 0.5) * self.range_resolution, dtype=np.float64)

    def replace(self, **changes: Any) -> "SonarSettings":
        """A copy with ``changes`` applied (validated again)."""
        return dataclasses.replace(self, **changes)

    def realism_off(self) -> "SonarSettings":
        """A copy with speckle, noise, beam pattern and absorption off (deterministic output)."""
        return self.replace(speckle=False, noise=False, beam_pattern=False, absorption=False)

    def paper_model(self) -> "SonarSettings":
        """The seed paper's model literally: realism off, no spreading, relative ("paper") gain."""
        return self.realism_off().replace(spread=False, gain_mode="paper")


def pure_water_absorption(frequency: float, temperature: float = 293.15) -> float:
    """Sound absorption of fresh water [dB/m] at ``frequency`` [Hz], ``temperature`` [K].

    The pure-water (viscous) term of Francois & Garrison (1982), at shallow
    depth: ``alpha = A3 f^2`` with f in kHz, A3 in dB/(km kHz^2). It dominates
    above about 500 kHz; at 1.8 MHz and 20 degC it is about 0.72 dB/m. Sea
    water adds the MgSO4 relaxation (about +0.1 dB/m at these frequencies):
    give ``absorption`` explicitly in the profile for that.
    """
    t = temperature - 273.15
    if t <= 20.0:
        a3 = 4.937e-4 - 2.59e-5 * t + 9.11e-7 * t**2 - 1.50e-8 * t**3
    else:
        a3 = 3.964e-4 - 1.146e-5 * t + 1.45e-7 * t**2 - 6.5e-10 * t**3
    f_khz = frequency / 1e3
    return a3 * f_khz**2 / 1e3


@dataclass(frozen=True)
class SonarProfile:
    """What an imaging sonar is. All values SI (angles [rad]).

    n_beams: beams, ordered by ascending azimuth (beam 0 = most negative = port).
    azimuth_limits: (2,) edges of the horizontal field of view [rad]; beam
        ``b`` points at the centre of the ``b``-th of ``n_beams`` equal parts.
    elevation_limits: (2,) edges of the vertical aperture [rad], positive up.
    beam_width_azimuth, beam_width_elevation: -3 dB beam widths [rad].
    frequency [Hz]; frame_rate: nominal ping rate [Hz].
    source_intensity: I0 of eq. 6, intensity at 1 m [arbitrary linear unit].
    k: the unit-conversion constant of eqs. 6 and 8 [1].
    absorption_db_per_m: one-way water absorption alpha at ``frequency`` [dB/m].
    defaults: the default :class:`SonarSettings`.
    min_elevation_rays: the fewest elevation rays per beam the live bridge may cast when a
        frame would miss its period (deadline-aware rendering; the range spreading keeps the
        image free of empty bins); adaptive_rays: whether it may (False: always
        ``elevation_rays``, fixed quality).
    seed: default seed of the realism random numbers.
    sources: where each value came from, by dotted profile key.
    """

    name: str
    model: str
    n_beams: int
    azimuth_limits: tuple[float, float]
    elevation_limits: tuple[float, float]
    beam_width_azimuth: float
    beam_width_elevation: float
    frequency: float
    frame_rate: float
    source_intensity: float
    k: float
    absorption_db_per_m: float
    defaults: SonarSettings
    seed: int = 0
    min_elevation_rays: int = 100
    adaptive_rays: bool = True
    sources: Mapping[str, str] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.n_beams < 1:
            raise ValueError(f"n_beams must be >= 1, got {self.n_beams}")
        for name in ("azimuth_limits", "elevation_limits"):
            lo, hi = getattr(self, name)
            if not lo < hi:
                raise ValueError(f"{name}: lower limit {lo} must be < upper limit {hi}")
            if not (-math.pi / 2 < lo and hi < math.pi / 2):
                raise ValueError(f"{name} must lie inside (-90, 90) deg, got ({lo}, {hi}) rad")
        for name in ("beam_width_azimuth", "beam_width_elevation", "frequency", "frame_rate",
                     "source_intensity", "k"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.absorption_db_per_m < 0.0:
            raise ValueError(f"absorption_db_per_m must be >= 0, got {self.absorption_db_per_m}")
        if isinstance(self.min_elevation_rays, bool) or not isinstance(self.min_elevation_rays, int) \
                or not 1 <= self.min_elevation_rays <= self.defaults.elevation_rays:
            raise ValueError(f"min_elevation_rays must be a whole number in 1..elevation_rays "
                             f"({self.defaults.elevation_rays}), got {self.min_elevation_rays!r}")

    def default_settings(self) -> SonarSettings:
        return self.defaults

    @property
    def beam_spacing(self) -> float:
        """Azimuth step between adjacent beams [rad]."""
        return (self.azimuth_limits[1] - self.azimuth_limits[0]) / self.n_beams

    @property
    def azimuths(self) -> F64:
        """(n_beams,) float [rad]: beam centre azimuths, ascending (positive = starboard)."""
        return np.asarray(self.azimuth_limits[0] + (np.arange(self.n_beams) + 0.5) * self.beam_spacing, dtype=np.float64)

    @property
    def range_min(self) -> float:
        return self.defaults.range_min

    @property
    def range_max(self) -> float:
        return self.defaults.range_max

    @property
    def n_samples(self) -> int:
        return self.defaults.n_samples


# ---------------------------------------------------------------- loading

_TOP = ("name", "model", "beams", "window", "acoustics", "gain", "spreading", "realism")
_SECTIONS: dict[str, tuple[str, ...]] = {
    "beams": ("count", "azimuth_limits", "elevation_limits", "width_azimuth", "width_elevation", "elevation_rays",
              "min_elevation_rays", "adaptive_rays"),
    "window": ("range_min", "range_max", "samples"),
    "acoustics": ("frequency", "frame_rate", "source_intensity", "k", "water_temperature", "absorption"),
    "gain": ("mode", "gain", "tvg", "tvg_spreading", "tvg_absorption", "dynamic_range"),
    "spreading": ("enabled", "max_width"),
    "realism": ("speckle", "noise", "noise_level", "beam_pattern", "absorption", "seed"),
}


def _section(doc: Doc, name: str, required: bool = True) -> Mapping[str, Any]:
    t = doc.data.get(name)
    if t is None:
        if required:
            raise doc.error(name, f"missing section [{name}]")
        return {}
    if not isinstance(t, Mapping):
        raise doc.error(name, f"[{name}] must be a table")
    check_keys(doc, t, _SECTIONS[name], name)
    return t


def _count(doc: Doc, t: Mapping[str, Any], key: str, where: str, sources: dict[str, str],
           default: int | None = None) -> int:
    dotted = f"{where}.{key}"
    if key not in t and default is not None:
        return default
    v = quantity(doc, t, key, "1", where)
    raw = t[key]["value"]
    if isinstance(raw, bool) or not isinstance(raw, int) or raw < 1:
        raise doc.error(dotted, f"expected a whole number >= 1, got {raw!r}")
    sources[dotted] = str(t[key]["source"])
    return int(v)


def _qty(doc: Doc, t: Mapping[str, Any], key: str, si: str, where: str, sources: dict[str, str],
         default: Any = None, length: int | None = None) -> Any:
    v = quantity(doc, t, key, si, where, default=default, length=length)
    if key in t:
        sources[f"{where}.{key}"] = str(t[key]["source"])
    return v


def _flag(doc: Doc, t: Mapping[str, Any], key: str, where: str, default: bool) -> bool:
    v = t.get(key, default)
    if not isinstance(v, bool):
        raise doc.error(f"{where}.{key}", f"expected true or false, got {v!r}")
    return v


def _text(doc: Doc, key: str) -> str:
    v = doc.data.get(key)
    if not isinstance(v, str) or not v:
        raise doc.error(key, f"missing or empty string {key!r}")
    return v


# dataclass field -> profile key, to point validation errors at the right line
_KEY_OF_FIELD = {
    "range_min": "window.range_min", "range_max": "window.range_max", "n_samples": "window.samples",
    "elevation_rays": "beams.elevation_rays", "gain_db": "gain.gain", "tvg_spreading_db": "gain.tvg_spreading",
    "dynamic_range_db": "gain.dynamic_range", "spread_max_bins": "spreading.max_width",
    "noise_level_db": "realism.noise_level", "n_beams": "beams.count",
    "azimuth_limits": "beams.azimuth_limits", "elevation_limits": "beams.elevation_limits",
    "beam_width_azimuth": "beams.width_azimuth", "beam_width_elevation": "beams.width_elevation",
    "frequency": "acoustics.frequency", "frame_rate": "acoustics.frame_rate",
    "source_intensity": "acoustics.source_intensity", "k": "acoustics.k",
    "absorption_db_per_m": "acoustics.absorption", "min_elevation_rays": "beams.min_elevation_rays",
}


def _key_of(message: str) -> str | None:
    field = message.split(" ", 1)[0].rstrip(":")
    return _KEY_OF_FIELD.get(field)


def load_sonar_profile(path: Path | str) -> SonarProfile:
    """Read a sonar profile TOML (``devices/sonars/*.toml``).

    Every physical value is a quantity table ``{ value, unit, source }``
    converted to SI; counts use unit ``"1"``; switches are bare booleans.
    Unknown keys, wrong units and inconsistent values raise
    :class:`hilsim.config.ConfigError` naming the file, line and key.
    """
    doc = load_toml(path)
    check_keys(doc, doc.data, _TOP, "")
    src: dict[str, str] = {}
    name, model = _text(doc, "name"), _text(doc, "model")

    b = _section(doc, "beams")
    n_beams = _count(doc, b, "count", "beams", src)
    az = _qty(doc, b, "azimuth_limits", "rad", "beams", src, length=2)
    el = _qty(doc, b, "elevation_limits", "rad", "beams", src, length=2)
    bw_az = _qty(doc, b, "width_azimuth", "rad", "beams", src)
    bw_el = _qty(doc, b, "width_elevation", "rad", "beams", src)
    rays = _count(doc, b, "elevation_rays", "beams", src, default=1000)
    min_rays = _count(doc, b, "min_elevation_rays", "beams", src, default=min(100, rays))
    adaptive = _flag(doc, b, "adaptive_rays", "beams", True)

    w = _section(doc, "window")
    r_min = _qty(doc, w, "range_min", "m", "window", src)
    r_max = _qty(doc, w, "range_max", "m", "window", src)
    n_samples = _count(doc, w, "samples", "window", src)

    a = _section(doc, "acoustics")
    freq = _qty(doc, a, "frequency", "Hz", "acoustics", src)
    frame_rate = _qty(doc, a, "frame_rate", "Hz", "acoustics", src)
    i0 = _qty(doc, a, "source_intensity", "1", "acoustics", src, default=1.0)
    k = _qty(doc, a, "k", "1", "acoustics", src, default=1.0)
    temp = _qty(doc, a, "water_temperature", "K", "acoustics", src, default=293.15)
    if "absorption" in a:
        alpha = _qty(doc, a, "absorption", "dB/m", "acoustics", src)
    else:
        alpha = pure_water_absorption(freq, temp)
        src["acoustics.absorption"] = "computed: pure_water_absorption(frequency, water_temperature)"

    g = _section(doc, "gain", required=False)
    mode = g.get("mode", "fixed")
    if mode not in GAIN_MODES:
        raise doc.error("gain.mode", f"mode must be one of {GAIN_MODES}, got {mode!r}")
    s = _section(doc, "spreading", required=False)
    r = _section(doc, "realism", required=False)
    seed = r.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise doc.error("realism.seed", f"seed must be a whole number >= 0, got {seed!r}")

    try:
        settings = SonarSettings(
            range_min=r_min, range_max=r_max, n_samples=n_samples, elevation_rays=rays,
            gain_mode=mode,
            gain_db=_qty(doc, g, "gain", "dB", "gain", src, default=0.0),
            tvg=_flag(doc, g, "tvg", "gain", True),
            tvg_spreading_db=_qty(doc, g, "tvg_spreading", "dB", "gain", src, default=40.0),
            tvg_absorption=_flag(doc, g, "tvg_absorption", "gain", True),
            dynamic_range_db=_qty(doc, g, "dynamic_range", "dB", "gain", src, default=80.0),
            spread=_flag(doc, s, "enabled", "spreading", True),
            spread_max_bins=_qty(doc, s, "max_width", "1", "spreading", src, default=8.0),
            speckle=_flag(doc, r, "speckle", "realism", False),
            noise=_flag(doc, r, "noise", "realism", False),
            noise_level_db=_qty(doc, r, "noise_level", "dB", "realism", src, default=-100.0),
            beam_pattern=_flag(doc, r, "beam_pattern", "realism", False),
            absorption=_flag(doc, r, "absorption", "realism", False),
        )
    except ConfigError:
        raise
    except ValueError as exc:
        raise doc.error(_key_of(str(exc)), str(exc)) from None
    try:
        return SonarProfile(
            name=name, model=model, n_beams=n_beams,
            azimuth_limits=(az[0], az[1]), elevation_limits=(el[0], el[1]),
            beam_width_azimuth=bw_az, beam_width_elevation=bw_el,
            frequency=freq, frame_rate=frame_rate, source_intensity=i0, k=k,
            absorption_db_per_m=alpha, defaults=settings, seed=seed, sources=src,
            min_elevation_rays=min_rays, adaptive_rays=adaptive,
        )
    except ConfigError:
        raise
    except ValueError as exc:
        raise doc.error(_key_of(str(exc)), str(exc)) from None


__all__ = ["ConfigError", "GAIN_MODES", "SonarProfile", "SonarSettings", "load_sonar_profile",
           "pure_water_absorption"]
