"""Ray casting against a triangle soup: the Embree backend.

A caster is built once from ``triangles`` ((m, 3, 3) float [m], world frame)
and answers :meth:`intersect` for batches of rays. Every backend (Embree here,
the paper's literal method in :mod:`hilsim.sim.raycast_ref`, trimesh's default
engine for benchmarks) answers the same query, so tests can hold them equal.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class RayCaster(Protocol):
    """What every ray-casting backend answers."""

    n_triangles: int

    def intersect(self, origins: F64, dirs: F64, t_min: float = 0.0,
                  t_max: float | F64 = np.inf) -> tuple[F64, I64]:
        """First hit of each ray with distance in [t_min, t_max].

        origins: (n, 3) float [m]; dirs: (n, 3) float, unit length.
        Returns ``t`` (n,) float [m] (``inf`` where nothing is hit) and
        ``tri`` (n,) int, the index of the triangle hit (``-1`` for a miss).
        """
        ...


class EmbreeCaster:
    """Embree (via embreex) over one triangle geometry holding every triangle.

    The triangle index Embree returns (``primID``) is the row of ``triangles``.
    Embree works in float32: distances carry about 1e-6 relative error.
    """

    def __init__(self, triangles: F64) -> None:
        from embreex import mesh_construction, rtcore_scene

        tris = np.ascontiguousarray(triangles, dtype=np.float32)
        if tris.ndim != 3 or tris.shape[1:] != (3, 3):
            raise ValueError(f"triangles must be (m, 3, 3), got {tris.shape}")
        self.n_triangles = int(tris.shape[0])
        self._scene = rtcore_scene.EmbreeScene()
        if self.n_triangles:
            # keep a reference: Embree shares the buffer
            self._mesh = mesh_construction.TriangleMesh(self._scene, tris)
            self._tris = tris

    def intersect(self, origins: F64, dirs: F64, t_min: float = 0.0,
                  t_max: float | F64 = np.inf) -> tuple[F64, I64]:
        """See :class:`RayCaster`; ``t_max`` may also be an (n,) array (per-ray limit [m])."""
        o = np.asarray(origins)
        d = np.asarray(dirs)
        n = o.shape[0]
        t = np.full(n, np.inf)
        tri = np.full(n, -1, dtype=np.int64)
        if n == 0 or self.n_triangles == 0:
            return t, tri
        span = np.minimum(np.asarray(t_max, dtype=np.float64) - t_min, 3.0e38)
        if np.all(span <= 0):
            return t, tri
        # Embree has no t_near in this binding: start the rays at t_min instead.
        start = o + d * t_min if t_min > 0.0 else o
        res = self._scene.run(
            np.ascontiguousarray(start, dtype=np.float32),
            np.ascontiguousarray(d, dtype=np.float32),
            dists=np.ascontiguousarray(np.broadcast_to(np.maximum(span, 0.0), (n,)), dtype=np.float32),
            output=1,
        )
        prim = np.asarray(res["primID"], dtype=np.int64)
        hit = prim >= 0
        tri[hit] = prim[hit]
        t[hit] = np.asarray(res["tfar"], dtype=np.float64)[hit] + t_min
        return t, tri
