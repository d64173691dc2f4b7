"""Two more ray casters answering :class:`hilsim.sim.raycast.RayCaster`.

:class:`ReferenceCaster` is the seed paper's method taken literally (eqs. 1-5):
every ray is tested against the plane of every polygon, the intersection point
is found with eq. 4, and eq. 5's three cross products decide whether that
point is inside the polygon. It is O(rays x triangles), in float64, and is the
ground truth the Embree backend is tested against.

:class:`TrimeshCaster` wraps trimesh's default (non-Embree) engine,
``trimesh.ray.ray_triangle.RayMeshIntersector``, for the benchmark. It needs
the ``rtree`` package.

Both follow the protocol's semantics: the first hit whose distance lies in
``[t_min, t_max]``; both faces of a triangle are hit (no back-face culling).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hilsim.sim.raycast import F64, I64


def _check_triangles(triangles: F64) -> F64:
    tris = np.ascontiguousarray(triangles, dtype=np.float64)
    if tris.ndim != 3 or tris.shape[1:] != (3, 3):
        raise ValueError(f"triangles must be (m, 3, 3), got {tris.shape}")
    return tris


def _check_rays(origins: F64, dirs: F64, t_max: float | F64) -> tuple[F64, F64, F64]:
    """Rays as float64 (n, 3) arrays and ``t_max`` as an (n,) array."""
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise ValueError(f"origins and dirs must both be (n, 3), got {o.shape} and {d.shape}")
    limit = np.broadcast_to(np.asarray(t_max, dtype=np.float64), (o.shape[0],))
    return o, d, limit


class ReferenceCaster:
    """The paper's ray-polygon test, every ray against every triangle.

    triangles: (m, 3, 3) float [m], rows ``(p1, p2, p3)`` in the world frame.
    chunk_pairs: bound on rays x triangles handled at once; memory is about
    ``12 * 8 * chunk_pairs`` bytes (a dozen float64 work arrays of that size).

    For a ray ``p = o + t v`` (eq. 2 with the ray's origin ``o`` made explicit;
    the paper puts the sensor at the origin) and the plane ``N . (p - p1) = 0``
    (eq. 3) with ``N = (p2 - p1) x (p3 - p1)`` (eq. 1), eq. 4 gives
    ``t = N . (p1 - o) / (N . v)``. The point is inside the triangle when the
    three vectors of eq. 5, ``(p2 - p1) x (p - p1)``, ``(p3 - p2) x (p - p2)``,
    ``(p1 - p3) x (p - p3)``, point the same way as ``N`` (their dot products
    with ``N`` are all >= 0; a point on an edge counts as inside). Rays parallel
    to a plane and degenerate triangles (``N = 0``) never hit.
    """

    def __init__(self, triangles: F64, chunk_pairs: int = 1 << 16) -> None:
        tris = _check_triangles(triangles)
        if chunk_pairs < 1:
            raise ValueError(f"chunk_pairs must be >= 1, got {chunk_pairs}")
        self.n_triangles = int(tris.shape[0])
        self.chunk_pairs = int(chunk_pairs)
        self._p1 = tris[:, 0, :].copy()
        self._p2 = tris[:, 1, :].copy()
        self._p3 = tris[:, 2, :].copy()
        # eq. 1, unnormalised as in the paper
        self._normal = np.cross(self._p2 - self._p1, self._p3 - self._p1)
        # edge vectors of eq. 5
        self._e12 = self._p2 - self._p1
        self._e23 = self._p3 - self._p2
        self._e31 = self._p1 - self._p3
        # N . p1, the plane constant of eq. 3
        self._n_p1 = np.einsum("ij,ij->i", self._normal, self._p1)
        self._valid = np.einsum("ij,ij->i", self._normal, self._normal) > 0.0

    def intersect(self, origins: F64, dirs: F64, t_min: float = 0.0,
                  t_max: float | F64 = np.inf) -> tuple[F64, I64]:
        """First hit of each ray with distance in [t_min, t_max].

        origins: (n, 3) float [m]; dirs: (n, 3) float, unit length; t_max: a
        float or an (n,) array (per-ray limit) [m].
        Returns t (n,) float [m] (inf on a miss) and tri (n,) int (-1 on a miss).
        Among equal distances the lowest triangle index wins.
        """
        o, d, limit = _check_rays(origins, dirs, t_max)
        n = o.shape[0]
        t_out = np.full(n, np.inf)
        tri_out = np.full(n, -1, dtype=np.int64)
        m = self.n_triangles
        if n == 0 or m == 0 or not np.any(limit >= t_min):
            return t_out, tri_out
        tri_chunk = min(m, self.chunk_pairs)
        ray_chunk = max(1, self.chunk_pairs // tri_chunk)
        for r0 in range(0, n, ray_chunk):
            r1 = min(n, r0 + ray_chunk)
            best_t = np.full(r1 - r0, np.inf)
            best_i = np.full(r1 - r0, -1, dtype=np.int64)
            for k0 in range(0, m, tri_chunk):
                k1 = min(m, k0 + tri_chunk)
                t, idx = self._chunk(o[r0:r1], d[r0:r1], k0, k1, t_min, limit[r0:r1])
                better = t < best_t
                best_t[better] = t[better]
                best_i[better] = idx[better]
            t_out[r0:r1] = best_t
            tri_out[r0:r1] = best_i
        return t_out, tri_out

    def _chunk(self, o: F64, d: F64, k0: int, k1: int, t_min: float, t_max: F64) -> tuple[F64, I64]:
        """Rays (r, 3) with limits t_max (r,) against triangles k0:k1; nearest valid hit per ray."""
        nrm = self._normal[k0:k1]
        # eq. 4: t = N . (p1 - o) / (N . v), as (r, k) arrays
        n_dot_v = d @ nrm.T
        n_dot_o = o @ nrm.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self._n_p1[k0:k1][None, :] - n_dot_o) / n_dot_v
        ok = np.isfinite(t) & (t >= t_min) & (t <= t_max[:, None]) & self._valid[k0:k1][None, :]
        # the intersection point p = o + t v, one (r, k) array per component
        px = o[:, 0:1] + t * d[:, 0:1]
        py = o[:, 1:2] + t * d[:, 1:2]
        pz = o[:, 2:3] + t * d[:, 2:3]
        for edge, start in ((self._e12, self._p1), (self._e23, self._p2), (self._e31, self._p3)):
            ex, ey, ez = (edge[k0:k1, j][None, :] for j in range(3))
            qx = px - start[k0:k1, 0][None, :]
            qy = py - start[k0:k1, 1][None, :]
            qz = pz - start[k0:k1, 2][None, :]
            # eq. 5: c = edge x (p - start), then its direction against N
            cx = ey * qz - ez * qy
            cy = ez * qx - ex * qz
            cz = ex * qy - ey * qx
            same = cx * nrm[:, 0][None, :] + cy * nrm[:, 1][None, :] + cz * nrm[:, 2][None, :]
            ok &= same >= 0.0
        t = np.where(ok, t, np.inf)
        j = np.argmin(t, axis=1)
        rows = np.arange(t.shape[0])
        best = t[rows, j]
        idx = np.where(np.isfinite(best), j + k0, -1).astype(np.int64)
        return best, idx


class TrimeshCaster:
    """trimesh's default ray engine (``RayMeshIntersector``, rtree + numpy).

    triangles: (m, 3, 3) float [m]. The triangle index returned is the row of
    ``triangles`` (the mesh is built with ``process=False`` so nothing is merged
    or reordered). Requires the ``rtree`` package.
    """

    def __init__(self, triangles: F64) -> None:
        import trimesh
        from trimesh.ray.ray_triangle import RayMeshIntersector

        tris = _check_triangles(triangles)
        self.n_triangles = int(tris.shape[0])
        self._engine: Any = None
        if self.n_triangles:
            mesh = trimesh.Trimesh(
                vertices=tris.reshape(-1, 3),
                faces=np.arange(3 * self.n_triangles).reshape(-1, 3),
                process=False,
            )
            self._engine = RayMeshIntersector(mesh)

    def intersect(self, origins: F64, dirs: F64, t_min: float = 0.0,
                  t_max: float | F64 = np.inf) -> tuple[F64, I64]:
        """First hit of each ray with distance in [t_min, t_max].

        origins: (n, 3) float [m]; dirs: (n, 3) float, unit length; t_max: a
        float or an (n,) array (per-ray limit) [m].
        Returns t (n,) float [m] (inf on a miss) and tri (n,) int (-1 on a miss).
        """
        o, d, limit = _check_rays(origins, dirs, t_max)
        n = o.shape[0]
        t_out = np.full(n, np.inf)
        tri_out = np.full(n, -1, dtype=np.int64)
        if n == 0 or self._engine is None or not np.any(limit >= t_min):
            return t_out, tri_out
        o = np.ascontiguousarray(o)
        # every hit along each ray, then the nearest one inside the window
        tri, ray, loc = self._engine.intersects_id(o, d, multiple_hits=True, return_locations=True)
        tri = np.asarray(tri, dtype=np.int64)
        ray = np.asarray(ray, dtype=np.int64)
        if tri.size == 0:
            return t_out, tri_out
        t = np.einsum("ij,ij->i", np.asarray(loc) - o[ray], d[ray])
        keep = (t >= t_min) & (t <= limit[ray])
        tri, ray, t = tri[keep], ray[keep], t[keep]
        # sort by (ray, t); the first row of each ray is its nearest hit
        order = np.lexsort((tri, t, ray))
        tri, ray, t = tri[order], ray[order], t[order]
        first = np.ones(ray.size, dtype=bool)
        first[1:] = ray[1:] != ray[:-1]
        t_out[ray[first]] = t[first]
        tri_out[ray[first]] = tri[first]
        return t_out, tri_out
