"""Imaging sonar (DIDSON-like) by ray casting: the seed paper's eqs. 2-9, fixed.

Sensor frame: x along the boresight, y to starboard, z down (the body
convention). A ray at azimuth ``theta`` (positive toward starboard, +y) and
elevation ``phi`` (positive *up*, toward -z) has the direction::

    d = (cos phi cos theta, cos phi sin theta, -sin phi)

Beams are ordered by ascending azimuth in every array here: beam 0 is the most
negative azimuth (port). Wire codecs reorder as their formats require (a
DIDSON puts its starboard-most beam first). Beam ``b`` points at the centre of
the ``b``-th of ``n_beams`` equal parts of the azimuth field of view; each beam
casts ``elevation_rays`` rays at the centres of equal parts of the elevation
aperture (paper: 96 x 1000 rays).

Each ray keeps only its *first* hit with range in ``[range_min, range_max]``
(the paper's eqs. 2-5 semantics: a hit outside the window is no echo, and a
surface behind the first one is shadowed). Its echo (eq. 9, per ray)::

    I_M = k^2 |(Z - Z0)/(Z + Z0)| (1 - absorption) I0 / R^4 cos^2(alpha) / elevation_rays

with ``cos alpha = |d . n|``: alpha is the angle between the ray and the
surface normal (0 at normal incidence), read from "the angle between the
intersecting ray and polygon" of eq. 7 as the usual Lambert incidence angle.
The reflection factor comes from ``World.obj_reflection`` (its magnitude, so a
softer-than-water surface still echoes). Dividing by ``elevation_rays`` makes
the image independent of the ray count (energy per ray). Echoes are summed
into (range bin, beam) cells: ``SonarFrame.intensity``, the pre-gain quantity.

The paper's defect ("circular patterns": empty range bins where adjacent
rays land more than a bin apart) is fixed by *spreading*: a ray hitting a
surface of normal n at range R covers, over its elevation step ``dphi``, the
range interval ``R +- |dR/dphi| dphi / 2`` with ``dR/dphi = -R (n . dd/dphi) / (n . d)``
(exact to first order for a plane). The echo is spread uniformly over that
interval and split across range bins by overlap; the width is capped at
``spread_max_bins`` (grazing incidence). ``spread=False`` is the paper's
literal one-bin deposit. The gaps appear wherever ``|dR/dphi| dphi`` exceeds a
range bin: at grazing incidence and long range (a floor seen by a sonar
tilted 10 deg down from 0.5 m, far half of the window), or with range bins
finer than the ray spacing. A floor 1.2 m below a sonar tilted 45 deg down
is sampled every < 1 mm by 1000 rays and shows none with 9.8 mm bins.

Gain (see :func:`fixed_gain_levels`): ``"paper"`` maps the brightest cell to
255 and the others *linearly* in proportion to it; ``"fixed"`` applies a gain
in dB plus time-varied gain and maps a fixed dB range to 8 bits.

Realism beyond the paper (each switchable, seeded): azimuth beam pattern
with side lobes, speckle, additive noise floor, water absorption.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from hilsim.sim.geometry import F64, Pose
from hilsim.sim.sonar_profile import (
    GAIN_MODES,
    SonarProfile,
    SonarSettings,
    load_sonar_profile,
    pure_water_absorption,
)
from hilsim.sim.state import VehicleState
from hilsim.sim.world import World

U8 = NDArray[np.uint8]
I64 = NDArray[np.int64]

# -3 dB point of sinc^2(x) = sin^2(pi x) / (pi x)^2: sinc^2(0.4429) = 1/2
_SINC2_HALF_POWER_X = 0.44295


@dataclass(frozen=True)
class SonarFrame:
    """One rendered sonar frame.

    intensity: (n_samples, n_beams) float, accumulated linear I_M (eq. 9 per
        ray, summed per cell; after beam pattern, speckle and noise when on;
        before any gain). Units of k^2 I0 (I0 at 1 m).
    image: (n_samples, n_beams) uint8, the gain-mapped image.
    ranges: (n_samples,) float [m], bin centres; azimuths: (n_beams,) float [rad], ascending.
    range_min, range_max: [m] the window.
    pose: sensor -> world pose the frame was rendered from.
    hit_counts: rays that hit, per object and facet direction (``World.hit_counts``).
    n_rays: rays cast; n_hits: rays with a hit inside the window.
    time: [s] sample time if known; frame_index: the index the RNG was keyed with.
    settings: the settings used.
    gain_db_at_range: (n_samples,) float [dB], gain_db + TVG applied per range
        row in "fixed" mode (empty in "paper" mode).
    """

    intensity: F64
    image: U8
    ranges: F64
    azimuths: F64
    range_min: float
    range_max: float
    pose: Pose
    hit_counts: dict[str, dict[str, int]]
    n_rays: int
    n_hits: int
    settings: SonarSettings
    time: float | None = None
    frame_index: int = 0
    gain_db_at_range: F64 = field(default_factory=lambda: np.zeros(0))


def tvg_db(ranges: F64, settings: SonarSettings, absorption_db_per_m: float) -> F64:
    """Time-varied gain [dB] at ``ranges`` (n,) [m].

    ``N log10(R / 1 m) + 2 alpha R`` with N = ``settings.tvg_spreading_db``
    (40 undoes eq. 9's R^-4) and the absorption term only with
    ``settings.tvg_absorption``; zeros when ``settings.tvg`` is off.
    """
    r = np.maximum(np.asarray(ranges, dtype=float), 1e-6)
    if not settings.tvg:
        return np.zeros_like(r)
    g = settings.tvg_spreading_db * np.log10(r)
    if settings.tvg_absorption:
        g = g + 2.0 * absorption_db_per_m * r
    return g


def fixed_gain_levels(intensity: F64, ranges: F64, settings: SonarSettings, reference: float,
                      absorption_db_per_m: float) -> U8:
    """The "fixed" gain law: (n_samples, n_beams) intensity -> uint8 image.

    ``level = 10 log10(I / reference) + TVG(R) + gain_db`` [dB], then
    ``pixel = round(255 (level + DR) / DR)`` clipped to 0..255, with DR =
    ``settings.dynamic_range_db``: 0 dB is full scale (255), ``-DR`` dB and
    below (and empty cells) are 0. ``reference`` is k^2 I0, the eq. 9 echo of
    a perfect reflector at 1 m and normal incidence filling the beam.
    """
    dr = settings.dynamic_range_db
    with np.errstate(divide="ignore"):
        level = 10.0 * np.log10(intensity / reference)
    level += (tvg_db(ranges, settings, absorption_db_per_m) + settings.gain_db)[:, None]
    px = np.rint((level + dr) * (255.0 / dr))
    return np.clip(np.nan_to_num(px, nan=0.0, neginf=0.0), 0.0, 255.0).astype(np.uint8)


def paper_gain_levels(intensity: F64) -> U8:
    """The paper's gain: the brightest cell is 255, the others linear in I / I_max (rounded)."""
    top = float(intensity.max()) if intensity.size else 0.0
    if top <= 0.0:
        return np.zeros(intensity.shape, dtype=np.uint8)
    return np.clip(np.rint(intensity * (255.0 / top)), 0, 255).astype(np.uint8)


@lru_cache(maxsize=8)
def _ray_fan(az_lo: float, az_hi: float, n_beams: int, el_lo: float, el_hi: float,
             n_el: int) -> tuple[F64, F64, I64, float]:
    """Sensor-frame rays: dirs (n, 3), d(dirs)/d(phi) (n, 3), beam index (n,), dphi [rad].

    Ray ``i`` belongs to beam ``i // n_el`` (beam-major).
    """
    theta = az_lo + (np.arange(n_beams) + 0.5) * (az_hi - az_lo) / n_beams
    dphi = (el_hi - el_lo) / n_el
    phi = el_lo + (np.arange(n_el) + 0.5) * dphi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    th, ph = th.ravel(), ph.ravel()
    cp, sp, ct, st = np.cos(ph), np.sin(ph), np.cos(th), np.sin(th)
    dirs = np.stack([cp * ct, cp * st, -sp], axis=1)
    ddphi = np.stack([-sp * ct, -sp * st, -cp], axis=1)
    beam = np.repeat(np.arange(n_beams, dtype=np.int64), n_el)
    for a in (dirs, ddphi, beam):
        a.setflags(write=False)
    return dirs, ddphi, beam, dphi


@lru_cache(maxsize=8)
def beam_pattern_matrix(azimuths: tuple[float, ...], beam_width: float) -> F64:
    """(n_beams, n_beams) leakage matrix K: ``out = intensity @ K``.

    ``K[j, b] = sinc^2(x)``, ``x = 0.443 (theta_b - theta_j) / (beam_width / 2)``:
    the power pattern of a uniform line aperture whose -3 dB full width is
    ``beam_width`` [rad], normalised to 1 on its axis, with side lobes at -13 dB
    and below, sampled at the other beams' azimuths.
    """
    th = np.asarray(azimuths, dtype=float)
    x = _SINC2_HALF_POWER_X * (th[None, :] - th[:, None]) / (0.5 * beam_width)
    k = np.sinc(x) ** 2
    k.setflags(write=False)
    return k


def _weighted_count(index: I64, weights: F64, size: int) -> F64:
    """Sum of ``weights`` per ``index`` into a (size,) float array (np.bincount, no np.add.at)."""
    return np.bincount(index, weights=weights, minlength=size).astype(np.float64, copy=False)


def spread_deposit(u: F64, width: F64, energy: F64, beam: I64, n_samples: int, n_beams: int) -> F64:
    """Accumulate echoes spread uniformly over range intervals into cells.

    u: (h,) float in [0, n_samples), hit range in bin units (``(R - range_min) / dr``);
    width: (h,) finite float >= 0, interval width [bins] centred on ``u``;
    energy: (h,) float, echo of each ray; beam: (h,) int beam index.
    Returns (n_samples, n_beams) float: each ray's energy split across the bins
    its interval overlaps, in proportion to the overlap (all of it in one bin
    for a zero width); parts outside the window are lost. O(h + cells): the
    partial first and last bins are deposited directly and fully covered
    interior bins through a running sum (cells where no interval is open are
    exactly zero).
    """
    ns, nb = n_samples, n_beams
    # pad bins on both sides take what falls outside the window; indices are shifted by +pad
    pad = int(np.ceil(0.5 * float(width.max(initial=0.0)))) + 1
    rows = ns + 2 * pad
    half = 0.5 * width
    a = u - half
    a += pad
    b = u + half
    b += pad
    i0 = a.astype(np.int64)  # floor: a >= 1
    i1 = b.astype(np.int64)
    single = i1 == i0
    with np.errstate(divide="ignore", invalid="ignore"):
        density = energy / width  # inf/nan only where width == 0, which is always single
        lead = i0 + 1 - a
        lead *= density
    first = np.where(single, energy, lead)
    total: F64 = _weighted_count(i0 * nb + beam, first, rows * nb)
    multi = np.flatnonzero(~single)
    if multi.size:
        m0, m1, mb, md = i0[multi], i1[multi], beam[multi], density[multi]
        last = md * (b[multi] - m1)
        total += _weighted_count(m1 * nb + mb, last, rows * nb)
        inner = m1 > m0 + 1
        if inner.any():
            bi, dens = mb[inner], md[inner]
            start = (m0[inner] + 1) * nb + bi
            stop = m1[inner] * nb + bi
            size = rows * nb
            run = _weighted_count(start, dens, size) - _weighted_count(stop, dens, size)
            cnt = np.bincount(start, minlength=size) - np.bincount(stop, minlength=size)
            run = np.cumsum(run.reshape(rows, nb), axis=0)
            is_open = np.cumsum(cnt.reshape(rows, nb), axis=0) > 0
            total += np.where(is_open, run, 0.0).ravel()
    return total.reshape(rows, nb)[pad:pad + ns]


class ImagingSonar:
    """A forward-looking imaging sonar rendered by ray casting.

    profile: what the sonar is; settings: runtime settings (default
    ``profile.default_settings()``); seed: realism RNG seed (default ``profile.seed``).
    Frames are a pure function of (world, pose, settings, seed, frame_index):
    the random numbers of frame ``i`` come from ``default_rng([seed, i])``;
    :meth:`render` without ``frame_index`` uses and advances an internal
    counter. With speckle and noise off the output is deterministic.
    """

    def __init__(self, profile: SonarProfile, settings: SonarSettings | None = None,
                 seed: int | None = None) -> None:
        self.profile = profile
        self.settings = settings if settings is not None else profile.default_settings()
        self.seed = int(profile.seed if seed is None else seed)
        self.frame_counter = 0

    @property
    def azimuths(self) -> F64:
        """(n_beams,) float [rad], ascending."""
        return self.profile.azimuths

    def rays(self, settings: SonarSettings | None = None) -> tuple[F64, I64]:
        """Sensor-frame ray directions (n, 3) and their beam index (n,), n = n_beams x elevation_rays."""
        s = settings or self.settings
        p = self.profile
        dirs, _, beam, _ = _ray_fan(p.azimuth_limits[0], p.azimuth_limits[1], p.n_beams,
                                    p.elevation_limits[0], p.elevation_limits[1], s.elevation_rays)
        return dirs, beam

    def render(self, world: World, pose: Pose, settings: SonarSettings | None = None, *,
               time: float | None = None, frame_index: int | None = None,
               rng: np.random.Generator | None = None) -> SonarFrame:
        """Render one frame from ``pose`` (sensor -> world, NED [m]).

        settings: overrides ``self.settings`` for this frame. rng: explicit
        random source for speckle/noise (else ``default_rng([seed, frame_index])``).
        Returns a :class:`SonarFrame` of (n_samples, n_beams) arrays.
        """
        s = settings or self.settings
        p = self.profile
        if frame_index is None:
            frame_index = self.frame_counter
            self.frame_counter += 1
        nb, ns = p.n_beams, s.n_samples
        dirs_s, ddphi_s, beam_all, dphi = _ray_fan(p.azimuth_limits[0], p.azimuth_limits[1], nb,
                                                   p.elevation_limits[0], p.elevation_limits[1],
                                                   s.elevation_rays)
        rot = np.asarray(pose.rotation, dtype=float)
        dirs = dirs_s @ rot.T
        n = dirs.shape[0]
        origins = np.broadcast_to(np.asarray(pose.position, dtype=float), (n, 3))
        hits = world.cast(origins, dirs, t_min=s.range_min, t_max=s.range_max)
        hit = hits.tri >= 0
        n_hits = int(np.count_nonzero(hit))

        # Work on every ray in the sensor frame, column by column (1-D ops,
        # no gathers of the hits). A miss has t = inf and a zero
        # normal, so its echo comes out exactly 0.
        nrm = hits.normal @ rot  # (n, 3) normals in the sensor frame
        n0, n1, n2 = nrm[:, 0], nrm[:, 1], nrm[:, 2]
        dx, dy, dz = dirs_s[:, 0], dirs_s[:, 1], dirs_s[:, 2]
        n_dot_d = n0 * dx + n1 * dy + n2 * dz
        r = hits.t
        refl = np.abs(world.obj_reflection)[hits.obj]
        r2 = r * r
        energy = (p.k * p.k * p.source_intensity / s.elevation_rays) * refl * (n_dot_d * n_dot_d) / (r2 * r2)
        if s.absorption:
            energy *= 10.0 ** (-0.2 * p.absorption_db_per_m * np.where(hit, r, 0.0))
        dr = s.range_resolution
        u = np.clip((r - s.range_min) * (1.0 / dr), 0.0, ns * (1.0 - 1e-12))
        if s.spread:
            n_dot_dd = n0 * ddphi_s[:, 0] + n1 * ddphi_s[:, 1] + n2 * ddphi_s[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                width = r * n_dot_dd
                width /= n_dot_d
            np.abs(width, out=width)
            width *= dphi / dr
            # grazing incidence (n . d -> 0, inf or nan) is capped; misses get no width
            np.fmin(width, s.spread_max_bins, out=width)
            width[~hit] = 0.0
            intensity = spread_deposit(u, width, energy, beam_all, ns, nb)
        else:
            cell = u.astype(np.int64) * nb + beam_all
            intensity = _weighted_count(cell, energy, ns * nb).reshape(ns, nb)

        if s.beam_pattern:
            intensity = intensity @ beam_pattern_matrix(tuple(p.azimuths.tolist()), p.beam_width_azimuth)
        if s.speckle or s.noise:
            g = rng if rng is not None else np.random.default_rng([self.seed, frame_index])
            if s.speckle:
                # fully developed speckle: Rayleigh amplitude, so intensity x Exp(1)
                intensity = intensity * g.exponential(1.0, intensity.shape)
            if s.noise:
                # receiver noise: complex Gaussian, so its intensity is Exp(mean)
                mean = p.k * p.k * p.source_intensity * 10.0 ** (s.noise_level_db / 10.0)
                intensity = intensity + g.exponential(mean, intensity.shape)

        ranges = s.ranges
        if s.gain_mode == "paper":
            image = paper_gain_levels(intensity)
            gain = np.zeros(0)
        else:
            ref = p.k * p.k * p.source_intensity
            image = fixed_gain_levels(intensity, ranges, s, ref, p.absorption_db_per_m)
            gain = tvg_db(ranges, s, p.absorption_db_per_m) + s.gain_db
        return SonarFrame(
            intensity=intensity, image=image, ranges=ranges, azimuths=p.azimuths,
            range_min=s.range_min, range_max=s.range_max, pose=pose,
            hit_counts=world.hit_counts(hits), n_rays=n, n_hits=n_hits, settings=s,
            time=time, frame_index=frame_index, gain_db_at_range=gain,
        )

    def sample(self, world: World, state: VehicleState, mount: Pose,
               settings: SonarSettings | None = None) -> SonarFrame:
        """Render from the vehicle: pose = ``state.pose @ mount`` (mount: sensor -> body)."""
        return self.render(world, state.pose @ mount, settings, time=state.time)


__all__ = [
    "GAIN_MODES", "ImagingSonar", "SonarFrame", "SonarProfile", "SonarSettings", "beam_pattern_matrix",
    "fixed_gain_levels", "load_sonar_profile", "paper_gain_levels", "pure_water_absorption",
    "spread_deposit", "tvg_db",
]
