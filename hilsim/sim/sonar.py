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
from typing import Any

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
F32 = NDArray[np.float32]
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
    with np.errstate(divide="ignore", invalid="ignore"):
        level = np.log10(intensity / reference)
    level *= 10.0
    level += (tvg_db(ranges, settings, absorption_db_per_m) + settings.gain_db)[:, None]
    level += dr
    level *= 255.0 / dr
    px = np.rint(level, out=level)
    np.fmax(px, 0.0, out=px)    # -inf (an empty cell) and nan -> 0
    np.fmin(px, 255.0, out=px)
    return px.astype(np.uint8)


def paper_gain_levels(intensity: F64) -> U8:
    """The paper's gain: the brightest cell is 255, the others linear in I / I_max (rounded)."""
    top = float(intensity.max()) if intensity.size else 0.0
    if top <= 0.0:
        return np.zeros(intensity.shape, dtype=np.uint8)
    return np.clip(np.rint(intensity * (255.0 / top)), 0, 255).astype(np.uint8)


@lru_cache(maxsize=32)
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


@dataclass(frozen=True)
class _Fan:
    """A ray fan's per-ray columns, contiguous (1-D ops on them run at memory speed).

    dirs_t: (3, n) float directions, rows contiguous; d: 3 x (n,) float32 direction
    components; e: 3 x (n,) float32 components of d(d)/d(phi); beam: (n,) beam index;
    dphi [rad] the elevation step.
    """

    dirs_t: F64
    d: tuple[F32, F32, F32]
    e: tuple[F32, F32, F32]
    beam: I64
    dphi: float


@lru_cache(maxsize=32)
def _fan(az_lo: float, az_hi: float, n_beams: int, el_lo: float, el_hi: float, n_el: int) -> _Fan:
    # not through _ray_fan's cache: a live bridge that adapts its ray count keeps several fans
    dirs, ddphi, beam, dphi = _ray_fan.__wrapped__(az_lo, az_hi, n_beams, el_lo, el_hi, n_el)
    dirs_t = np.ascontiguousarray(dirs.T)
    d = dirs_t.astype(np.float32)
    e = np.ascontiguousarray(ddphi.T, dtype=np.float32)
    for a in (dirs_t, d, e):
        a.setflags(write=False)
    return _Fan(dirs_t, (d[0], d[1], d[2]), (e[0], e[1], e[2]), beam, dphi)


# facet direction codes of World.tri_facet (hilsim.sim.world.facet_codes)
_FACETS = ("north", "south", "east", "west", "down", "up")


class _TriangleTables:
    """Per-triangle values a frame gathers per ray, with one extra row at the end for a miss
    (triangle index -1): ``refl`` (m + 1,) |reflection| (0 for a miss) and the world-frame
    normal components ``n`` 3 x (m + 1,) (0 for a miss). Rebuilt when the world is."""

    def __init__(self, world: World) -> None:
        self.normals = world.tri_normal  # identity: World.rebuild makes new arrays
        self.tri_object = world.tri_object
        self.reflection = world.obj_reflection
        m = len(world.tri_object)
        self.refl = np.zeros(m + 1, dtype=np.float32)
        if m:
            self.refl[:m] = np.abs(world.obj_reflection)[world.tri_object]
        self.normal = np.zeros((m + 1, 3))
        self.normal[:m] = world.tri_normal
        self.code = world.tri_object * len(_FACETS) + world.tri_facet

    def current(self, world: World) -> bool:
        return (self.normals is world.tri_normal and self.tri_object is world.tri_object
                and self.reflection is world.obj_reflection)


def _hit_counts(world: World, tables: _TriangleTables, tri: I64) -> dict[str, dict[str, int]]:
    """``World.hit_counts`` from the triangle indices (n,) alone (one bincount per frame)."""
    m = len(tables.code)
    per_tri = np.bincount(tri + 1, minlength=m + 1)[1:]
    seen = np.flatnonzero(per_tri)
    out: dict[str, dict[str, int]] = {}
    if seen.size == 0:
        return out
    counts = np.bincount(tables.code[seen], weights=per_tri[seen])
    for code in np.flatnonzero(counts).tolist():
        obj, facet = divmod(code, len(_FACETS))
        d = out.setdefault(world.objects[obj].name, {"total": 0})
        d["total"] += int(counts[code])
        d[_FACETS[facet]] = int(counts[code])
    return out


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


FLT = NDArray[np.floating[Any]]


@lru_cache(maxsize=8)
def _beam_pattern32(azimuths: tuple[float, ...], beam_width: float) -> F32:
    k = beam_pattern_matrix(azimuths, beam_width).astype(np.float32)
    k.setflags(write=False)
    return k


def _weighted_count(index: I64, weights: FLT, size: int) -> F64:
    """Sum of ``weights`` per ``index`` into a (size,) float array (np.bincount, no np.add.at)."""
    return np.bincount(index, weights=weights, minlength=size).astype(np.float64, copy=False)


def spread_deposit(u: F64, width: FLT, energy: FLT, beam: I64, n_samples: int, n_beams: int) -> F64:
    """Accumulate echoes spread uniformly over range intervals into cells.

    u: (h,) float in [0, n_samples), hit range in bin units (``(R - range_min) / dr``);
    width: (h,) finite float >= 0 (float32 or float64), interval width [bins] centred on ``u``;
    energy: (h,) float (float32 or float64), echo of each ray; beam: (h,) int beam index.
    Returns (n_samples, n_beams) float: each ray's energy split across the bins
    its interval overlaps, in proportion to the overlap (all of it in one bin
    for a zero width); parts outside the window are lost. O(h + cells): the
    partial first and last bins are deposited directly and fully covered
    interior bins through a running sum (cells where no interval is open are
    exactly zero). Cells are numbered beam-major inside (a beam's rays land in
    neighbouring cells: the sums run at cache speed); the result is (n_samples, n_beams).
    """
    ns, nb = n_samples, n_beams
    # pad bins on both sides take what falls outside the window; indices are shifted by +pad
    pad = int(np.ceil(0.5 * float(width.max(initial=0.0)))) + 1
    rows = ns + 2 * pad
    size = rows * nb
    half = 0.5 * width
    # most intervals lie inside one bin (the bin of u): their whole energy goes there
    iu = u.astype(np.int64)  # floor: u >= 0
    frac = u - iu
    lo = frac - half
    hi = frac + half
    single = lo >= 0.0
    single &= hi < 1.0
    base = beam * rows  # cell of (row i, beam b): b * rows + i
    base += pad
    iu += base
    total: F64 = _weighted_count(iu, np.where(single, energy, 0.0), size)
    multi = np.flatnonzero(~single)
    if multi.size:
        # the others: a partial first bin, a partial last bin and fully covered ones between
        um, hm, mb = u[multi], half[multi], base[multi]
        with np.errstate(divide="ignore", invalid="ignore"):
            md = energy[multi] / (2.0 * hm)
        a = um - hm
        b = um + hm
        m0 = np.floor(a).astype(np.int64)
        m1 = np.floor(b).astype(np.int64)
        same = m1 == m0  # (rounding at a bin edge: inside one bin after all)
        total += _weighted_count(mb + m0, np.where(same, energy[multi], (m0 + 1 - a) * md), size)
        total += _weighted_count(mb + m1, np.where(same, 0.0, md * (b - m1)), size)
        inner = m1 > m0 + 1
        if inner.any():
            bi, dens = mb[inner], md[inner]
            start = bi + m0[inner] + 1
            stop = bi + m1[inner]
            run = _weighted_count(start, dens, size) - _weighted_count(stop, dens, size)
            cnt = np.bincount(start, minlength=size) - np.bincount(stop, minlength=size)
            run = np.cumsum(run.reshape(nb, rows), axis=1)
            is_open = np.cumsum(cnt.reshape(nb, rows), axis=1) > 0
            total += np.where(is_open, run, 0.0).ravel()
    return np.ascontiguousarray(total.reshape(nb, rows)[:, pad:pad + ns].T)


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
        self._tables: _TriangleTables | None = None

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
        fan = _fan(p.azimuth_limits[0], p.azimuth_limits[1], nb, p.elevation_limits[0], p.elevation_limits[1],
                   s.elevation_rays)
        rot = np.asarray(pose.rotation, dtype=float)
        dirs = (rot @ fan.dirs_t).T  # (n, 3) world-frame directions (a transposed view)
        n = dirs.shape[0]
        origins = np.broadcast_to(np.asarray(pose.position, dtype=float), (n, 3))
        r, tri = world.caster.intersect(origins, dirs, s.range_min, s.range_max)
        hit = tri >= 0
        n_hits = int(np.count_nonzero(hit))
        tables = self._tables
        if tables is None or not tables.current(world):
            tables = self._tables = _TriangleTables(world)

        # Per ray, in the sensor frame, as 1-D float32 columns (Embree's ranges are float32
        # already; range bins are found from the float64 range): the normal of the triangle
        # hit (a miss, index -1, takes the tables' last row: zero normal, zero reflection, so
        # its echo is exactly 0; its range is inf).
        nrm = (rot.T @ tables.normal.T).astype(np.float32)  # (3, m + 1) sensor-frame normals
        n0, n1, n2 = np.take(nrm[0], tri), np.take(nrm[1], tri), np.take(nrm[2], tri)
        dx, dy, dz = fan.d
        n_dot_d = n0 * dx
        n_dot_d += n1 * dy
        n_dot_d += n2 * dz
        r32 = r.astype(np.float32)
        r4 = r32 * r32
        r4 *= r4
        energy = n_dot_d * n_dot_d
        energy *= np.take(tables.refl, tri)
        energy *= np.float32(p.k * p.k * p.source_intensity / s.elevation_rays)
        energy /= r4
        if s.absorption and p.absorption_db_per_m > 0.0:
            # 10^(-0.2 alpha R); a miss (R = inf) gets 0, its echo is 0 already
            energy *= np.exp(r32 * np.float32(-0.2 * np.log(10.0) * p.absorption_db_per_m))
        dr = s.range_resolution
        u = r - s.range_min
        u *= 1.0 / dr
        np.clip(u, 0.0, ns * (1.0 - 1e-12), out=u)
        if s.spread:
            ex, ey, ez = fan.e
            width = n0 * ex
            width += n1 * ey
            width += n2 * ez
            with np.errstate(divide="ignore", invalid="ignore"):
                width *= r32
                # misses get no width (0, not the 0 x inf / 0 of their columns)
                width = np.divide(width, n_dot_d, out=np.zeros_like(width), where=hit)
            np.abs(width, out=width)
            width *= np.float32(fan.dphi / dr)
            # grazing incidence (n . d -> 0, inf or nan) is capped
            np.fmin(width, np.float32(s.spread_max_bins), out=width)
            intensity = spread_deposit(u, width, energy, fan.beam, ns, nb)
        else:
            cell = u.astype(np.int64)
            cell *= nb
            cell += fan.beam
            intensity = _weighted_count(cell, energy, ns * nb).reshape(ns, nb)

        if s.beam_pattern:
            k32 = _beam_pattern32(tuple(p.azimuths.tolist()), p.beam_width_azimuth)
            intensity = (intensity.astype(np.float32) @ k32).astype(np.float64)
        if s.speckle or s.noise:
            g = rng if rng is not None else np.random.default_rng([self.seed, frame_index])
            # fully developed speckle: Rayleigh amplitude, so intensity x Exp(1); receiver
            # noise: complex Gaussian, so its intensity is Exp(mean). Exp(1) = -ln(1 - U)
            # (inverse CDF) from float32 uniforms: the tail is cut at 16.6 (P = 6e-8)
            ln = g.random((int(s.speckle) + int(s.noise), *intensity.shape), dtype=np.float32)
            np.subtract(np.float32(1.0), ln, out=ln)
            np.log(ln, out=ln)  # -Exp(1) each
            if s.speckle:
                intensity *= ln[0]
                np.negative(intensity, out=intensity)
            if s.noise:
                mean = p.k * p.k * p.source_intensity * 10.0 ** (s.noise_level_db / 10.0)
                ln[-1] *= np.float32(-mean)
                intensity += ln[-1]

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
            hit_counts=_hit_counts(world, tables, tri), n_rays=n, n_hits=n_hits, settings=s,
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
