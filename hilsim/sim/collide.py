"""Narrow-phase geometry of contacts: an oriented box against convex polyhedra and triangles.

Pure numpy, no state. The box is the vehicle's hull: centre ``c`` (3,) [m] in
the world (NED), rotation ``rot`` (3, 3) body -> world (its columns are the
box's axes), half extents ``half`` (3,) [m].

Separating-axis test (SAT). For a candidate axis ``a`` (unit, world frame) the
box projects to ``[a.c - r, a.c + r]`` with ``r = sum_i h_i |a . R_i|`` and the
other shape to ``[o_min, o_max]``. Two numbers per axis say everything:

* ``op = o_max - (a.c - r)``: how far the box must move along ``+a`` to leave,
* ``om = (a.c + r) - o_min``: how far it must move along ``-a``.

Both >= 0 on every axis: the shapes intersect (the smallest of them is the
penetration depth and its axis the contact normal). One of them < 0 on some
axis: that axis separates them, by ``-min(op, om)`` [m]. Axes: the box's 3
face normals, the other shape's face normals, and the cross products of the
box's edge directions with the other shape's edge directions (for a triangle:
3 + 1 + 9 = 13). A degenerate cross product (parallel edges) gets ``op = om =
inf``, so arrays stay aligned between two poses of the box.

Distances (:func:`box_triangle_distance`) are exact: the closest pair of two
disjoint convex polytopes is a vertex of one and a face of the other, or two
edges, and all of those are tried.
"""

from __future__ import annotations

import numpy as np

from hilsim.sim.geometry import F64

_INF = np.inf
# box corners and edges in half-extent units
CORNERS: F64 = np.array([[sx, sy, sz] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0) for sz in (-1.0, 1.0)])
_EDGES = np.array([(i, j) for i in range(8) for j in range(i + 1, 8)
                   if np.count_nonzero(CORNERS[i] != CORNERS[j]) == 1])  # (12, 2)


def box_corners(c: F64, rot: F64, half: F64) -> F64:
    """(8, 3) [m] world corners of the box."""
    return np.asarray(c) + (CORNERS * half) @ rot.T


def _cross(a: F64, b: F64) -> F64:
    """Cross products of (..., 3) arrays, broadcast (np.cross without its overhead)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _dot(a: F64, b: F64) -> F64:
    """Dot products over the last axis, broadcast."""
    return (a * b).sum(axis=-1)


def _unit_rows(v: F64) -> tuple[F64, np.ndarray]:
    """Rows of ``v`` (..., 3) normalised, and the mask of rows too short to normalise."""
    n = np.sqrt(np.einsum("...d,...d->...", v, v))
    bad = n < 1e-9
    out = v / np.where(bad, 1.0, n)[..., None]
    return out, bad


def convex_axes(rot: F64, half: F64, verts: F64, face_normals: F64, edge_dirs: F64
                ) -> tuple[F64, F64, F64, F64]:
    """The part of :func:`sat_convex` that does not depend on the box's centre: ``axes``
    (A, 3), the box's radius ``r`` (A,) [m] and the polyhedron's ``o_min``, ``o_max`` (A,) [m]
    on them (degenerate axes: r = inf, so that op = om = inf). Then for a centre c:
    ``op = o_max - (axes @ c - r)``, ``om = (axes @ c + r) - o_min``."""
    box_axes = rot.T
    cross, bad = _unit_rows(_cross(box_axes[:, None, :], edge_dirs[None, :, :]).reshape(-1, 3))
    axes = np.concatenate([box_axes, face_normals, cross])
    r = np.abs(axes @ rot) @ half
    proj = verts @ axes.T
    r[3 + len(face_normals):][bad] = _INF
    return axes, r, proj.min(axis=0), proj.max(axis=0)


def sat_convex(c: F64, rot: F64, half: F64, verts: F64, face_normals: F64, edge_dirs: F64
               ) -> tuple[F64, F64, F64]:
    """SAT of the box against a convex polyhedron.

    verts (V, 3) [m]; face_normals (F, 3) and edge_dirs (E, 3) unit, each
    direction once (up to sign). Returns ``axes`` (A, 3), ``op`` (A,), ``om``
    (A,) [m] (module docstring), A = 3 + F + 3 E."""
    box_axes = rot.T
    cross, bad = _unit_rows(_cross(box_axes[:, None, :], edge_dirs[None, :, :]).reshape(-1, 3))
    axes = np.concatenate([box_axes, face_normals, cross])
    pc = axes @ c
    r = np.abs(axes @ rot) @ half
    proj = verts @ axes.T
    op = proj.max(axis=0) - (pc - r)
    om = (pc + r) - proj.min(axis=0)
    k = 3 + len(face_normals)
    op[k:][bad] = _INF
    om[k:][bad] = _INF
    return axes, op, om


def sat_triangles(c: F64, rot: F64, half: F64, tris: F64, normals: F64) -> tuple[F64, F64, F64]:
    """SAT of the box against each of ``tris`` (T, 3, 3) [m] with unit ``normals`` (T, 3).

    Returns ``axes`` (T, 13, 3), ``op``, ``om`` (T, 13) [m]; axis 3 is the
    triangle's normal (as the mesh winding gives it)."""
    t = len(tris)
    box_axes = rot.T
    edges = tris[:, [1, 2, 0]] - tris                                   # (T, 3, 3)
    cross, bad = _unit_rows(_cross(box_axes[None, :, None, :], edges[:, None, :, :]).reshape(t, 9, 3))
    axes = np.concatenate([np.broadcast_to(box_axes, (t, 3, 3)), normals[:, None, :], cross], axis=1)
    pc = axes @ c                                                        # (T, 13)
    r = np.abs(axes @ rot) @ half
    proj = np.einsum("tad,tvd->tav", axes, tris)                         # (T, 13, 3)
    op = proj.max(axis=2) - (pc - r)
    om = (pc + r) - proj.min(axis=2)
    op[:, 4:][bad] = _INF
    om[:, 4:][bad] = _INF
    return axes, op, om


def choose_normal(axes: F64, op: F64, om: F64, pop: F64, pom: F64, one_sided: int | None = None,
                  prefer_eps: float = 0.0) -> tuple[np.ndarray, F64, F64]:
    """The contact normal and depth of N candidates from their SAT now and at the previous pose.

    axes (N, A, 3); op, om (N, A) now; pop, pom (N, A) at the previous pose of the
    box (same axis order). ``one_sided``: index of an axis (a triangle's outward
    normal) along which the box is only ever pushed out to the normal's side.

    Rule: a candidate is in contact if it intersects now. If some axis separated
    the two at the previous pose, the box crossed it during the step: the normal
    is that axis, on the side the box was on, with the current overlap on that side
    as the depth (the smallest, if several did). Otherwise (resting contact) the
    axis of least penetration, except that the one-sided axis is preferred when
    its depth is within ``prefer_eps`` [m] of the least (a mesh's internal edges
    then never push sideways). Returns ``hit`` (N,) bool, ``depth`` (N,) [m] and
    ``normal`` (N, 3) unit, pointing from the object to the box."""
    plus, minus = op.copy(), om.copy()
    if one_sided is not None:
        minus[:, one_sided] = _INF
    hit = np.all((op >= 0.0) & (om >= 0.0), axis=1)
    sep_plus, sep_minus = pop < 0.0, pom < 0.0
    if one_sided is not None:
        sep_minus[:, one_sided] = False
    crossed = np.where(sep_plus, plus, _INF), np.where(sep_minus, minus, _INF)
    have_prev = np.any(sep_plus | sep_minus, axis=1)
    # previous-pose rule
    cp = np.minimum(crossed[0], crossed[1])
    kp = np.argmin(cp, axis=1)
    rows = np.arange(len(op))
    sign_p = np.where(crossed[0][rows, kp] <= crossed[1][rows, kp], 1.0, -1.0)
    depth_p = cp[rows, kp]
    # resting rule
    least = np.minimum(plus, minus)
    kr = np.argmin(least, axis=1)
    depth_r = least[rows, kr]
    sign_r = np.where(plus[rows, kr] <= minus[rows, kr], 1.0, -1.0)
    if one_sided is not None:
        face = plus[:, one_sided]
        use_face = face <= depth_r + prefer_eps
        kr = np.where(use_face, one_sided, kr)
        depth_r = np.where(use_face, face, depth_r)
        sign_r = np.where(use_face, 1.0, sign_r)
    k = np.where(have_prev, kp, kr)
    depth = np.where(have_prev, depth_p, depth_r)
    sign = np.where(have_prev, sign_p, sign_r)
    normal = axes[rows, k] * sign[:, None]
    hit &= np.isfinite(depth)
    return hit, depth, normal


# -- distances ------------------------------------------------------------------------


def _point_segment(p: F64, a: F64, b: F64) -> F64:
    """Distances (broadcast shape) [m] from points ``p`` (..., 3) to segments ``a``-``b`` (..., 3)."""
    ab = b - a
    den = _dot(ab, ab)
    t = np.clip(_dot(p - a, ab) / np.where(den > 0, den, 1.0), 0.0, 1.0)
    d = p - (a + t[..., None] * ab)
    return np.sqrt(_dot(d, d))


def point_triangle_distance(p: F64, tris: F64) -> F64:
    """(P, T) [m] distances from points (P, 3) to triangles (T, 3, 3)."""
    a, b, c = (tris[None, :, i, :] for i in range(3))
    q = p[:, None, :]
    n = _cross(b - a, c - a)
    nn = np.sqrt(_dot(n, n))
    nn_safe = np.where(nn > 0, nn, 1.0)
    inside = ((_dot(_cross(b - a, q - a), n) >= 0) & (_dot(_cross(c - b, q - b), n) >= 0)
              & (_dot(_cross(a - c, q - c), n) >= 0) & (nn > 0))
    plane = np.abs(_dot(q - a, n)) / nn_safe
    edge = np.minimum(np.minimum(_point_segment(q, a, b), _point_segment(q, b, c)), _point_segment(q, c, a))
    return np.where(inside, plane, edge)


def segment_segment_distance(p1: F64, q1: F64, p2: F64, q2: F64) -> F64:
    """Distances [m] between segments p1-q1 and p2-q2 (arrays (..., 3), broadcast)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = np.einsum("...d,...d->...", d1, d1)
    e = np.einsum("...d,...d->...", d2, d2)
    f = np.einsum("...d,...d->...", d2, r)
    c = np.einsum("...d,...d->...", d1, r)
    b = np.einsum("...d,...d->...", d1, d2)
    den = a * e - b * b
    eps = 1e-12
    s = np.where(den > eps * np.maximum(a * e, eps), np.clip((b * f - c * e) / np.where(den > 0, den, 1.0), 0, 1), 0.0)
    s = np.where(a <= eps, 0.0, s)
    t = np.where(e > eps, (b * s + f) / np.where(e > eps, e, 1.0), 0.0)
    # t outside [0, 1]: clamp it and recompute s for the clamped t
    t_lo, t_hi = t < 0.0, t > 1.0
    t = np.clip(t, 0.0, 1.0)
    s_re = np.clip(np.where(a > eps, (t * b - c) / np.where(a > eps, a, 1.0), 0.0), 0.0, 1.0)
    s = np.where(t_lo | t_hi, s_re, s)
    c1 = p1 + s[..., None] * d1
    c2 = p2 + t[..., None] * d2
    return np.linalg.norm(c1 - c2, axis=-1)


def box_triangle_distance(c: F64, rot: F64, half: F64, tris: F64) -> F64:
    """(T,) [m] exact distances from the box to triangles (T, 3, 3); 0 where they intersect."""
    if len(tris) == 0:
        return np.zeros(0)
    q = (tris - c) @ rot                      # triangles in the box frame (T, 3, 3)
    corners = CORNERS * half                  # (8, 3)
    d_vf = point_triangle_distance(corners, q).min(axis=0)
    d_fv = np.linalg.norm(np.maximum(np.abs(q) - half, 0.0), axis=-1).min(axis=1)
    e0, e1 = corners[_EDGES[:, 0]], corners[_EDGES[:, 1]]   # (12, 3)
    t0, t1 = q, q[:, [1, 2, 0]]
    d_ee = segment_segment_distance(e0[None, :, None, :], e1[None, :, None, :],
                                    t0[:, None, :, :], t1[:, None, :, :]).reshape(len(q), -1).min(axis=1)
    d = np.minimum(np.minimum(d_vf, d_fv), d_ee)
    # a triangle can only cut through the box if the box straddles its plane: test those by SAT
    normals, _ = _unit_rows(_cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]))
    straddle = np.abs(_dot(normals, c - tris[:, 0])) <= np.abs(normals @ rot) @ half
    if np.any(straddle):
        _, op, om = sat_triangles(c, rot, half, tris[straddle], normals[straddle])
        d[straddle] = np.where(np.all((op >= 0.0) & (om >= 0.0), axis=1), 0.0, d[straddle])
    return d


class TriangleGrid:
    """Triangles binned into square cells over (north, east): the triangles near a box.

    lo, hi (T, 3) [m]: each triangle's bounding box. ``cell`` [m] side of a cell.
    """

    def __init__(self, lo: F64, hi: F64, cell: float, max_pairs: int = 4_000_000):
        self.lo, self.hi = lo, hi
        while True:
            ilo = np.floor(lo[:, :2] / cell).astype(np.int64)
            ihi = np.floor(hi[:, :2] / cell).astype(np.int64)
            span = ihi - ilo + 1
            counts = span[:, 0] * span[:, 1]
            if counts.sum() <= max_pairs:
                break
            cell *= 2.0
        self.cell = cell
        tri = np.repeat(np.arange(len(lo)), counts)
        start = np.repeat(np.cumsum(counts) - counts, counts)
        local = np.arange(int(counts.sum())) - start
        sy = span[tri, 1]
        ix = ilo[tri, 0] + local // sy
        iy = ilo[tri, 1] + local % sy
        self._oy = int(iy.min()) if len(iy) else 0
        self._ny = int(iy.max() - self._oy + 1) if len(iy) else 1
        keys = ix * self._ny + (iy - self._oy)
        order = np.argsort(keys, kind="stable")
        self._keys, self._tris = keys[order], tri[order]
        self._ukeys, self._start = np.unique(self._keys, return_index=True)
        self._end = np.append(self._start[1:], len(self._keys))

    def query(self, lo: F64, hi: F64) -> np.ndarray:
        """Indices of the triangles whose bounding box meets the box [lo, hi] (3,) [m]."""
        ilo = np.floor(np.asarray(lo[:2]) / self.cell).astype(np.int64)
        ihi = np.floor(np.asarray(hi[:2]) / self.cell).astype(np.int64)
        iy0 = max(int(ilo[1]), self._oy)
        iy1 = min(int(ihi[1]), self._oy + self._ny - 1)
        if iy1 < iy0:
            return np.zeros(0, dtype=np.int64)
        found = []
        for ix in range(int(ilo[0]), int(ihi[0]) + 1):
            k0, k1 = ix * self._ny + iy0 - self._oy, ix * self._ny + iy1 - self._oy
            a, b = np.searchsorted(self._ukeys, (k0, k1 + 1))
            if b > a:
                found.append(self._tris[self._start[a]:self._end[b - 1]])
        if not found:
            return np.zeros(0, dtype=np.int64)
        idx = np.unique(np.concatenate(found))
        ok = np.all((self.lo[idx] <= hi) & (self.hi[idx] >= lo), axis=1)
        return idx[ok]
