"""Per-cell labels of a sonar frame: which object and material each cell's strongest echo came from,
and the acoustic shadow.

The rays are the sonar's own (``hilsim.sim.sonar``'s fan: beam ``b`` at the
centre of the b-th of ``n_beams`` equal parts of the azimuth field, rays at the
centres of equal parts of the elevation aperture, beam-major), cast through the
same :class:`~hilsim.sim.world.World` with the same window, and each hit's echo
(eq. 9 per ray) is binned the way the sonar bins it: spread uniformly over
``R +- |dR/dphi| dphi / 2`` (capped at ``spread_max_bins``), split across range
bins by overlap, or all in one bin without spreading. Here every (ray, bin)
share is kept apart, so each cell knows its strongest contributor; their sum
per cell is the sonar's pre-gain intensity (before beam pattern, speckle and
noise), which the tests hold equal to :class:`~hilsim.sim.sonar.ImagingSonar`'s.

Shadow: a cell is in the shadow when no echo lands in it but some ray of its
beam, continued through the object it first hit, would have echoed there from
the next object behind (the floor behind a target, say).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from hilsim.sim.geometry import Pose
from hilsim.sim.sonar import ImagingSonar, SonarSettings
from hilsim.sim.world import World

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
_CONTINUE_STEP = 1e-4   # [m] past a surface before casting on
_MAX_CROSSINGS = 8      # surfaces of the first object a continued ray may cross


@dataclass(frozen=True)
class SonarLabels:
    """Labels of one frame, arrays (n_samples, n_beams) like the frame's image.

    object: int16 index into ``object_names`` of the strongest echo (-1: no echo);
    material: int16 index into ``material_names`` (-1: no echo); shadow: bool;
    intensity: float, the summed echoes (the sonar's pre-gain intensity without realism);
    hits: rays whose first hit in the window is each object (objects hit by none left out);
    cells: cells each object labels.
    """

    object: NDArray[np.int16]
    material: NDArray[np.int16]
    shadow: NDArray[np.bool_]
    intensity: F64
    object_names: tuple[str, ...]
    material_names: tuple[str, ...]
    hits: dict[str, int]
    cells: dict[str, int]


def ray_fan(sonar: ImagingSonar, s: SonarSettings) -> tuple[F64, F64, I64, float]:
    """Sensor-frame directions (n, 3), d(dir)/d(phi) (n, 3), beam index (n,), elevation step [rad]."""
    p = sonar.profile
    return _fan(tuple(p.azimuth_limits), tuple(p.elevation_limits), p.n_beams, s.elevation_rays)


@lru_cache(maxsize=8)
def _fan(az: tuple[float, float], el: tuple[float, float], nb: int, ne: int) -> tuple[F64, F64, I64, float]:
    (az_lo, az_hi), (el_lo, el_hi) = az, el
    theta = az_lo + (np.arange(nb) + 0.5) * (az_hi - az_lo) / nb
    dphi = (el_hi - el_lo) / ne
    phi = el_lo + (np.arange(ne) + 0.5) * dphi
    th, ph = (a.ravel() for a in np.meshgrid(theta, phi, indexing="ij"))
    cp, sp, ct, st = np.cos(ph), np.sin(ph), np.cos(th), np.sin(th)
    dirs = np.stack([cp * ct, cp * st, -sp], axis=1)
    ddphi = np.stack([-sp * ct, -sp * st, -cp], axis=1)
    beam = np.repeat(np.arange(nb, dtype=np.int64), ne)
    for a in (dirs, ddphi, beam):
        a.setflags(write=False)
    return dirs, ddphi, beam, dphi


def _rotate(v: F64, rot: F64) -> F64:
    """(n, 3) vectors times a 3x3 rotation, ``v @ rot.T``, without BLAS threads."""
    return v[:, 0:1] * rot[:, 0] + v[:, 1:2] * rot[:, 1] + v[:, 2:3] * rot[:, 2]


def _shares(sonar: ImagingSonar, s: SonarSettings, world: World, rot: F64, dirs_s: F64, ddphi_s: F64,
            dphi: float, t: F64, obj: I64, normal: F64) -> tuple[I64, I64, F64]:
    """(ray, range bin, energy) of every part of every echo that lands inside the window.

    t, obj, normal: (h,) hits of the rays ``dirs_s`` (h, 3) (sensor frame; normals in the world)."""
    p = sonar.profile
    ns = s.n_samples
    nrm = _rotate(normal, rot.T)
    n_dot_d = np.einsum("ij,ij->i", nrm, dirs_s)
    refl = np.abs(world.obj_reflection)[obj]
    energy = (p.k * p.k * p.source_intensity / s.elevation_rays) * refl * n_dot_d * n_dot_d / t ** 4
    if s.absorption:
        energy *= 10.0 ** (-0.2 * p.absorption_db_per_m * t)
    dr = s.range_resolution
    u = np.clip((t - s.range_min) / dr, 0.0, ns * (1.0 - 1e-12))
    if s.spread:
        with np.errstate(divide="ignore", invalid="ignore"):
            width = np.abs(t * np.einsum("ij,ij->i", nrm, ddphi_s) / n_dot_d) * (dphi / dr)
        width = np.fmin(width, s.spread_max_bins)
        width[~np.isfinite(width)] = s.spread_max_bins
    else:
        width = np.zeros_like(u)
    a, b = u - 0.5 * width, u + 0.5 * width
    i0, i1 = np.floor(a).astype(np.int64), np.floor(b).astype(np.int64)
    nk = i1 - i0 + 1
    ray = np.repeat(np.arange(t.size), nk)
    k = i0[ray] + (np.arange(int(nk.sum())) - np.repeat(np.cumsum(nk) - nk, nk))
    single = (nk == 1)[ray]
    with np.errstate(divide="ignore", invalid="ignore"):
        part = (np.minimum(b[ray], k + 1) - np.maximum(a[ray], k)) * (energy / width)[ray]
    share = np.where(single, energy[ray], part)
    keep = (k >= 0) & (k < ns)
    return ray[keep], k[keep], share[keep]


def sonar_labels(world: World, sonar: ImagingSonar, pose: Pose, settings: SonarSettings | None = None) -> SonarLabels:
    """Labels of the frame ``sonar.render(world, pose, settings)`` would give (pose: sensor -> world)."""
    s = settings or sonar.settings
    nb, ns = sonar.profile.n_beams, s.n_samples
    dirs_s, ddphi_s, beam, dphi = ray_fan(sonar, s)
    rot = np.asarray(pose.rotation, dtype=float)
    dirs = _rotate(dirs_s, rot)
    origin = np.asarray(pose.position, dtype=float)
    n = dirs.shape[0]
    hits = world.cast(np.broadcast_to(origin, (n, 3)), dirs, t_min=s.range_min, t_max=s.range_max)
    hit = np.flatnonzero(hits.tri >= 0)
    names = tuple(world.object_names)
    mats = tuple(dict.fromkeys(o.material.name for o in world.objects))
    mat_of_obj = np.array([mats.index(o.material.name) for o in world.objects] + [-1], dtype=np.int16)

    first_obj = hits.obj[hit]
    dirs_hit = dirs[hit]
    ray, k, share = _shares(sonar, s, world, rot, dirs_s[hit], ddphi_s[hit], dphi, hits.t[hit], first_obj,
                            hits.normal[hit])
    cell = k * nb + beam[hit][ray]
    intensity: F64 = np.bincount(cell, weights=share, minlength=ns * nb).astype(np.float64).reshape(ns, nb)
    flat = np.full(ns * nb, -1, dtype=np.int16)
    if cell.size:
        strongest = np.zeros(ns * nb)
        np.maximum.at(strongest, cell, share)
        win = share == strongest[cell]            # the strongest share of its cell (ties: any of them)
        flat[cell[win]] = first_obj[ray[win]]
    label = flat.reshape(ns, nb)
    material = np.where(label >= 0, mat_of_obj[label], -1).astype(np.int16)

    # the shadow: continue each ray through the object it hit first, to the next object behind it
    first = first_obj
    t_now = hits.t[hit].copy()
    obj_now = first.copy()
    tri_now = hits.tri[hit].copy()
    nrm_now = hits.normal[hit].copy()
    active = np.ones(hit.size, dtype=bool)
    for _ in range(_MAX_CROSSINGS):
        idx = np.flatnonzero(active & (obj_now == first))
        if idx.size == 0:
            break
        start = t_now[idx] + _CONTINUE_STEP
        room = s.range_max - start
        go = room > 0
        idx, start, room = idx[go], start[go], room[go]
        active[np.flatnonzero(active & (obj_now == first))] = False
        if idx.size == 0:
            break
        d = dirs_hit[idx]
        h2 = world.cast(origin + d * start[:, None], d, t_min=0.0, t_max=float(room.max()))
        ok = (h2.tri >= 0) & (h2.t <= room)   # beyond the window is no echo
        sel = idx[ok]
        t_now[sel] = start[ok] + h2.t[ok]
        obj_now[sel], tri_now[sel], nrm_now[sel] = h2.obj[ok], h2.tri[ok], h2.normal[ok]
        active[sel] = True
    behind = np.flatnonzero(active & (obj_now != first) & (t_now >= s.range_min) & (t_now <= s.range_max))
    shadow = np.zeros(ns * nb, dtype=bool)
    if behind.size:
        sub = hit[behind]
        r2, k2, _ = _shares(sonar, s, world, rot, dirs_s[sub], ddphi_s[sub], dphi, t_now[behind],
                            obj_now[behind], nrm_now[behind])
        shadow[k2 * nb + beam[sub][r2]] = True
    shadow &= intensity.ravel() <= 0.0
    counts = np.bincount(first, minlength=len(names))
    cells = np.bincount(label[label >= 0].astype(np.int64), minlength=len(names))
    return SonarLabels(object=label, material=material, shadow=shadow.reshape(ns, nb), intensity=intensity,
                       object_names=names, material_names=mats,
                       hits={names[i]: int(c) for i, c in enumerate(counts) if c},
                       cells={names[i]: int(c) for i, c in enumerate(cells) if c})
