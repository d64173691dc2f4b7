"""Ray casters: the paper's literal method, Embree and trimesh answer the same queries.

Rays are aimed at points well inside a triangle (barycentric coordinates
>= 0.05), so no ray grazes an edge within float32 precision: then Embree
(float32) and the float64 reference must agree on hit/miss and triangle, and
on distance to ~1e-6 relative (1e-4 asserted). The reference is itself checked
against distances computed here from the construction of the rays.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from hilsim.sim.raycast import EmbreeCaster
from hilsim.sim.raycast_ref import ReferenceCaster, TrimeshCaster
from hilsim.sim.world import Material, World, WorldObject

TRI = np.array([[[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.0]]])
DOWN = np.array([[0.0, 0.0, 1.0]])


def casters() -> list[type]:
    out: list[type] = [EmbreeCaster, ReferenceCaster]
    try:
        import rtree  # noqa: F401  (TrimeshCaster needs it)
    except ImportError:
        pass
    else:
        out.append(TrimeshCaster)
    return out


# ------------------------------------------------- the reference, by hand


def test_reference_single_triangle_by_hand() -> None:
    c = ReferenceCaster(TRI)
    o = np.array([[0.25, 0.25, 0.0], [0.75, 0.75, 0.0], [0.25, 0.25, 5.0], [0.2, 0.3, 0.0]])
    d = np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 0, -1.0], [0, 0, -1.0]])
    t, tri = c.intersect(o, d)
    # inside from above; outside the hypotenuse; from below (back face); pointing away
    np.testing.assert_array_equal(tri, [0, -1, 0, -1])
    np.testing.assert_allclose(t, [2.0, np.inf, 3.0, np.inf])


def test_reference_window_and_nearest() -> None:
    two = np.concatenate([TRI, TRI + [0.0, 0.0, 1.5]])  # planes z = 2 and z = 3.5
    c = ReferenceCaster(two, chunk_pairs=1)  # the smallest chunks exercise the loop
    o = np.tile([[0.3, 0.3, 0.0]], (4, 1))
    d = np.tile(DOWN, (4, 1))
    for (lo, hi), want_t, want_tri in [((0.0, np.inf), 2.0, 0), ((2.5, 10.0), 3.5, 1),
                                       ((0.0, 1.9), np.inf, -1), ((2.1, 3.4), np.inf, -1)]:
        t, tri = c.intersect(o, d, lo, hi)
        assert np.all(tri == want_tri) and np.all(t == want_t), (lo, hi, t, tri)


def test_reference_parallel_and_degenerate_never_hit() -> None:
    degenerate = np.array([[[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [2.0, 0.0, 2.0]]])
    c = ReferenceCaster(np.concatenate([TRI, degenerate]))
    o = np.array([[1.5, 0.0, 0.0], [-1.0, 0.2, 2.0]])
    d = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # onto the degenerate one; in the plane of TRI
    t, tri = c.intersect(o, d)
    np.testing.assert_array_equal(tri, [-1, -1])
    assert np.all(np.isinf(t))


@settings(max_examples=60, deadline=None)
@given(
    tri=st.lists(st.floats(-5, 5, allow_nan=False), min_size=9, max_size=9),
    bary=st.tuples(st.floats(0.05, 1.0), st.floats(0.05, 1.0), st.floats(0.05, 1.0)),
    origin=st.lists(st.floats(-5, 5, allow_nan=False), min_size=3, max_size=3),
)
def test_reference_hits_a_point_inside_at_its_distance(tri: list[float], bary: tuple[float, float, float],
                                                       origin: list[float]) -> None:
    v = np.array(tri).reshape(1, 3, 3)
    e1, e2 = v[0, 1] - v[0, 0], v[0, 2] - v[0, 0]
    n = np.cross(e1, e2)
    area2 = np.linalg.norm(n)
    if area2 < 0.5 or area2 < 0.02 * np.linalg.norm(e1) * np.linalg.norm(e2):
        return  # skip slivers: "inside" would be within rounding of an edge
    w = np.array(bary) / sum(bary)
    target = w @ v[0]
    o = np.array(origin)
    to = target - o
    dist = np.linalg.norm(to)
    if dist < 1e-3 or abs(np.dot(n / area2, to / dist)) < 0.05:
        return  # origin on the plane or ray nearly parallel to it
    t, idx = ReferenceCaster(v).intersect(o[None], (to / dist)[None])
    assert idx[0] == 0
    assert t[0] == pytest.approx(dist, rel=1e-9, abs=1e-9)


# -------------------------------------------- random scenes, all backends


def aimed_rays(tris: np.ndarray, n: int, rng: np.random.Generator, spread: float) -> tuple[np.ndarray, np.ndarray]:
    """n rays from random origins toward random points well inside random triangles."""
    pick = rng.integers(0, len(tris), n)
    w = rng.uniform(0.05, 1.0, (n, 3))
    w /= w.sum(axis=1, keepdims=True)
    target = np.einsum("ij,ijk->ik", w, tris[pick])
    o = rng.uniform(-spread, spread, (n, 3))
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d


def random_soup(rng: np.random.Generator, m: int) -> np.ndarray:
    """m random triangles in a 4 m cube, slivers replaced."""
    tris = rng.uniform(-2, 2, (m, 3, 3))
    for _ in range(10):
        n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        bad = np.linalg.norm(n, axis=1) < 0.1
        if not bad.any():
            break
        tris[bad] = rng.uniform(-2, 2, (int(bad.sum()), 3, 3))
    return tris


def random_boxes(rng: np.random.Generator, k: int) -> np.ndarray:
    parts = []
    for _ in range(k):
        box = trimesh.creation.box(extents=rng.uniform(0.2, 1.5, 3))
        box.apply_transform(trimesh.transformations.random_rotation_matrix(rng.uniform(0, 1, 3)))
        box.apply_translation(rng.uniform(-3, 3, 3))
        parts.append(np.asarray(box.triangles))
    return np.concatenate(parts)


def all_backends(tris: np.ndarray, o: np.ndarray, d: np.ndarray, t_min: float, t_max: float) -> dict[str, tuple]:
    return {cls.__name__: cls(tris).intersect(o, d, t_min, t_max) for cls in casters()}


def assert_agree(results: dict[str, tuple]) -> None:
    t_ref, tri_ref = results["ReferenceCaster"]
    assert (tri_ref >= 0).sum() > 0 and (tri_ref < 0).sum() > 0, "scene should give both hits and misses"
    for name, (t, tri) in results.items():
        hit = tri_ref >= 0
        np.testing.assert_array_equal(tri >= 0, hit, err_msg=f"{name}: hit/miss differs")
        np.testing.assert_array_equal(tri[hit], tri_ref[hit], err_msg=f"{name}: triangle differs")
        np.testing.assert_allclose(t[hit], t_ref[hit], rtol=1e-4, err_msg=name)
        assert np.all(np.isinf(t[~hit])), name


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_backends_agree_on_random_soup(seed: int) -> None:
    rng = np.random.default_rng(seed)
    tris = random_soup(rng, 150)
    o, d = aimed_rays(tris, 1500, rng, spread=6.0)
    # plus rays in random directions, mostly misses
    o2 = rng.uniform(-6, 6, (500, 3))
    d2 = rng.normal(size=(500, 3))
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    o, d = np.concatenate([o, o2]), np.concatenate([d, d2])
    assert_agree(all_backends(tris, o, d, 0.0, np.inf))


@pytest.mark.parametrize("seed", [3, 4])
def test_backends_agree_on_random_boxes_with_window(seed: int) -> None:
    rng = np.random.default_rng(seed)
    tris = random_boxes(rng, 8)
    o, d = aimed_rays(tris, 2000, rng, spread=8.0)
    full_t, _ = ReferenceCaster(tris).intersect(o, d)
    lo, hi = np.quantile(full_t[np.isfinite(full_t)], [0.25, 0.75])
    results = all_backends(tris, o, d, float(lo), float(hi))
    assert_agree(results)
    t_ref, tri_ref = results["ReferenceCaster"]
    hit = tri_ref >= 0
    assert np.all((t_ref[hit] >= lo) & (t_ref[hit] <= hi))
    # hits nearer than the window's start are skipped: some rays now hit a farther face
    assert np.any(hit & (t_ref > full_t + 1e-6))


def test_backends_agree_with_per_ray_limits() -> None:
    rng = np.random.default_rng(8)
    tris = random_boxes(rng, 8)
    o, d = aimed_rays(tris, 1500, rng, spread=8.0)
    first, _ = ReferenceCaster(tris).intersect(o, d)
    assert np.all(np.isfinite(first))  # every ray is aimed at a triangle
    # each ray's limit is 2 % or more away from its first hit: short of it (a miss) or past it (that hit)
    factor = np.where(rng.uniform(size=len(o)) < 0.5, rng.uniform(0.3, 0.98, len(o)), rng.uniform(1.02, 2.0, len(o)))
    limit = first * factor
    results = {cls.__name__: cls(tris).intersect(o, d, 0.0, limit) for cls in casters()}
    assert_agree(results)
    t_ref, tri_ref = results["ReferenceCaster"]
    np.testing.assert_array_equal(tri_ref >= 0, factor > 1.0)
    np.testing.assert_allclose(t_ref[factor > 1.0], first[factor > 1.0], rtol=1e-12)


def test_world_normals_agree_with_every_backend() -> None:
    rng = np.random.default_rng(5)
    tris = random_boxes(rng, 6)
    mesh = trimesh.Trimesh(vertices=tris.reshape(-1, 3), faces=np.arange(len(tris) * 3).reshape(-1, 3), process=False)
    o, d = aimed_rays(tris, 1000, rng, spread=8.0)
    hits = {}
    for cls in casters():
        world = World([WorldObject("boxes", mesh, Material("m", 3e6))], caster_factory=cls)
        hits[cls.__name__] = world.cast(o, d, 0.1, 20.0)
    ref = hits["ReferenceCaster"]
    assert ref.hit.sum() > 500
    for name, h in hits.items():
        np.testing.assert_array_equal(h.hit, ref.hit, err_msg=name)
        np.testing.assert_allclose(h.normal, ref.normal, atol=1e-12, err_msg=name)
        # the normal is the unit normal of the triangle that was hit (eq. 1, normalised)
        v = tris[h.tri[h.hit]]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        np.testing.assert_allclose(h.normal[h.hit], n / np.linalg.norm(n, axis=1, keepdims=True), atol=1e-9)


def test_reference_memory_chunking_gives_same_answer() -> None:
    rng = np.random.default_rng(6)
    tris = random_soup(rng, 97)
    o, d = aimed_rays(tris, 301, rng, spread=5.0)
    a = ReferenceCaster(tris).intersect(o, d, 0.2, 9.0)
    for chunk in (40, 500, 5000, 97 * 301):
        b = ReferenceCaster(tris, chunk_pairs=chunk).intersect(o, d, 0.2, 9.0)
        np.testing.assert_array_equal(a[1], b[1])
        np.testing.assert_allclose(a[0], b[0], rtol=1e-12)  # BLAS blocking may change the last bit


def test_empty_inputs() -> None:
    for cls in casters():
        t, tri = cls(np.zeros((0, 3, 3))).intersect(np.zeros((2, 3)), np.tile(DOWN, (2, 1)))
        assert np.all(tri == -1) and np.all(np.isinf(t))
        t, tri = cls(TRI).intersect(np.zeros((0, 3)), np.zeros((0, 3)))
        assert t.shape == (0,) and tri.shape == (0,)
