"""The world's objects as contact shapes: bounding boxes, convex polyhedra, triangle grids.

Built once per :class:`~hilsim.sim.world.World` triangle set (again after the
world is rebuilt, e.g. when the timeline moves an object). A closed convex
object with few edge directions (a box, a cylinder) is kept as a convex
polyhedron (tested whole); anything else (terrain, planes, imported meshes,
spheres with many edges) as triangles, binned into a grid when there are many.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hilsim.sim.collide import TriangleGrid
from hilsim.sim.geometry import F64

_MAX_CONVEX_EDGES = 64     # more edge directions: test triangle by triangle instead
_GRID_MIN_TRIANGLES = 256  # fewer: test every triangle's bounding box
_QUERY_MARGIN = 0.5        # [m] how far around the hull a grid query looks


def unique_directions(v: F64) -> F64:
    """(k, 3) unit directions of the rows of ``v`` (n, 3), each once up to sign (zeros dropped)."""
    n = np.linalg.norm(v, axis=1)
    v = v[n > 1e-12] / n[n > 1e-12, None]
    if len(v) == 0:
        return np.zeros((0, 3))
    first = np.argmax(np.abs(v) > 1e-9, axis=1)
    v = v * np.sign(v[np.arange(len(v)), first])[:, None]
    _, keep = np.unique(np.round(v, 6), axis=0, return_index=True)
    return v[np.sort(keep)]


class WorldShapes:
    """Per object of ``world``: name, friction [1], bounding box, and its contact shape.

    names (N,); friction (N,) (the material's ``friction``, else ``default_friction``);
    lo, hi (N, 3) [m] bounding boxes; convex[i]: (vertices (V, 3), face normals (F, 3),
    edge directions (E, 3)) or None for a triangle-tested object."""

    def __init__(self, world: Any, default_friction: float):
        objs = world.objects
        self.names: list[str] = [o.name for o in objs]
        self.friction: list[float] = [float(getattr(o.material, "friction", default_friction)) for o in objs]
        n = len(objs)
        owner = np.asarray(world.tri_object)
        self._tris: F64 = np.asarray(world.triangles, dtype=float)
        self._normals: F64 = np.asarray(world.tri_normal, dtype=float)
        self._start = np.searchsorted(owner, np.arange(n), side="left")
        self._stop = np.searchsorted(owner, np.arange(n), side="right")
        self.lo = np.zeros((n, 3))
        self.hi = np.zeros((n, 3))
        self.convex: list[tuple[F64, F64, F64] | None] = []
        self._tri_lo: list[F64] = []
        self._tri_hi: list[F64] = []
        self._grid: list[TriangleGrid | None] = []
        self._near: dict[int, tuple[F64, F64, np.ndarray]] = {}  # object -> last query box and its triangles
        for i, ob in enumerate(objs):
            tris = self._tris[self._start[i]:self._stop[i]]
            tlo, thi = tris.min(axis=1), tris.max(axis=1)
            self.lo[i] = tlo.min(axis=0) if len(tris) else np.inf
            self.hi[i] = thi.max(axis=0) if len(tris) else -np.inf
            self._tri_lo.append(tlo)
            self._tri_hi.append(thi)
            self.convex.append(self._convex(ob.mesh))
            grid = None
            if self.convex[i] is None and len(tris) >= _GRID_MIN_TRIANGLES:
                ext = np.median(np.max(thi[:, :2] - tlo[:, :2], axis=1))
                grid = TriangleGrid(tlo, thi, max(0.5, 2.0 * float(ext)))
            self._grid.append(grid)
        finite = np.isfinite(self.lo).all(axis=1)
        span = (self.hi[finite].max(axis=0) - self.lo[finite].min(axis=0)) if finite.any() else np.zeros(3)
        self.extent = float(np.linalg.norm(span)) + 1.0  # [m] no distance in this world is larger

    @staticmethod
    def _convex(mesh: Any) -> tuple[F64, F64, F64] | None:
        try:
            if not (mesh.is_watertight and mesh.is_convex):
                return None
        except Exception:  # noqa: BLE001 - trimesh on odd meshes: test by triangles
            return None
        verts = np.asarray(mesh.vertices, dtype=float)
        edges = unique_directions(np.asarray(mesh.vertices)[mesh.edges_unique[:, 1]]
                                  - np.asarray(mesh.vertices)[mesh.edges_unique[:, 0]])
        if len(edges) > _MAX_CONVEX_EDGES:
            return None
        return verts, unique_directions(np.asarray(mesh.face_normals, dtype=float)), edges

    def aabb_gaps(self, lo: F64, hi: F64) -> F64:
        """(N,) [m] distance from the box [lo, hi] (3,) to each object's bounding box (0: overlap)."""
        g = np.maximum(np.maximum(self.lo - hi, lo - self.hi), 0.0)
        return np.sqrt((g * g).sum(axis=1))

    def triangles_within(self, i: int, lo: F64, hi: F64) -> np.ndarray:
        """Indices (into object ``i``'s triangles) of those whose bounding box meets [lo, hi]."""
        grid = self._grid[i]
        if grid is not None:
            return grid.query(lo, hi)
        ok = np.all((self._tri_lo[i] <= hi) & (self._tri_hi[i] >= lo), axis=1)
        return np.flatnonzero(ok)

    def near_triangles(self, i: int, lo: F64, hi: F64) -> tuple[np.ndarray, float]:
        """Triangles of object ``i`` whose bounding box meets [lo, hi], and a lower bound [m] of
        the distance from [lo, hi] to the object's other triangles."""
        m = _QUERY_MARGIN
        cached = self._near.get(i)
        if cached is not None and np.all(lo - 0.5 * m >= cached[0]) and np.all(hi + 0.5 * m <= cached[1]):
            idx = cached[2]  # still well inside the last query's box: its triangles are a superset
        else:
            qlo, qhi = lo - m, hi + m
            idx = self.triangles_within(i, qlo, qhi)
            self._near[i] = (qlo, qhi, idx)
        if len(idx) == 0:
            return idx, 0.5 * m
        g = np.maximum(np.maximum(self._tri_lo[i][idx] - hi, lo - self._tri_hi[i][idx]), 0.0)
        gap = np.linalg.norm(g, axis=1)
        near = gap <= 0.0
        sep = float(min(0.5 * m, gap[~near].min())) if np.any(~near) else 0.5 * m
        return idx[near], sep

    def all_within(self, lo: F64, hi: F64) -> np.ndarray:
        """Indices into the world's triangles of those whose bounding box meets [lo, hi] (3,) [m]."""
        near = np.flatnonzero(np.all((self.lo <= hi) & (self.hi >= lo), axis=1))
        found = [self._start[i] + self.triangles_within(int(i), lo, hi) for i in near.tolist()]
        return np.concatenate(found) if found else np.zeros(0, dtype=np.int64)

    def all_triangles(self, idx: np.ndarray) -> tuple[F64, F64]:
        """The world's triangles ``idx``: (k, 3, 3) vertices [m], (k, 3) unit normals."""
        return self._tris[idx], self._normals[idx]

    def owner(self, k: int) -> int:
        """The object of the world's triangle ``k``."""
        return int(np.searchsorted(self._stop, k, side="right"))

    def triangles(self, i: int, idx: np.ndarray) -> tuple[F64, F64]:
        """Object ``i``'s triangles ``idx``: (k, 3, 3) vertices [m] and (k, 3) unit normals."""
        s = self._start[i]
        return self._tris[s + idx], self._normals[s + idx]
