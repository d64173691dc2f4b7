"""What the console's top and side views draw: the scenario's objects as outlines, the hull.

Pure functions of the scenario (no I/O): each object's mesh projected on the
horizontal plane (top view: north up, east right) and on the north-down plane
(side view: north right, depth down), as convex hulls in metres; the vehicle's
hull as a box around its thrusters. Sent to each page in its ``hello``, and the
objects again when one moves (a timeline ``move``: a ``scene`` message).
"""

from __future__ import annotations

from typing import Any, Iterable, Sequence

import numpy as np


def convex_hull_2d(points: np.ndarray) -> np.ndarray:
    """(k, 2) counter-clockwise convex hull of (n, 2) points (Andrew's monotone chain)."""
    pts = np.unique(np.round(np.asarray(points, dtype=float).reshape(-1, 2), 4), axis=0)
    if len(pts) <= 2:
        return pts

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    lower: list[np.ndarray] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list[np.ndarray] = []
    for p in pts[::-1]:
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1])


def _rgb_hex(color: Sequence[float]) -> str:
    r, g, b = (max(0, min(255, int(round(float(c) * 255)))) for c in color[:3])
    return f"#{r:02x}{g:02x}{b:02x}"


def object_outlines(objects: Iterable[Any], max_vertices: int = 20000) -> list[dict[str, Any]]:
    """Each world object as ``{"name", "color", "top": [[north, east], ...], "side": [[north,
    down], ...], "bounds": [[min xyz], [max xyz]]}`` [m]; a large mesh is subsampled to
    ``max_vertices`` vertices before its hull is taken (an outline, not a survey)."""
    out = []
    for o in objects:
        v = np.asarray(o.mesh.vertices, dtype=float)
        if len(v) == 0:
            continue
        if len(v) > max_vertices:
            v = v[np.linspace(0, len(v) - 1, max_vertices).astype(int)]
        out.append({
            "name": o.name,
            "color": _rgb_hex(o.material.color),
            "top": np.round(convex_hull_2d(v[:, [0, 1]]), 3).tolist(),
            "side": np.round(convex_hull_2d(v[:, [0, 2]]), 3).tolist(),
            "bounds": [np.round(v.min(axis=0), 3).tolist(), np.round(v.max(axis=0), 3).tolist()],
        })
    return out


def hull_box(thruster_positions: Sequence[Sequence[float]] | None, margin: float = 0.1,
             default: tuple[float, float, float] = (0.9, 0.6, 0.4)) -> dict[str, list[float]]:
    """The vehicle drawn as a box in the body frame (x forward, y starboard, z down) [m]: the
    thrusters' extent plus ``margin``; ``default`` (length, width, height) without thrusters."""
    if thruster_positions:
        p = np.asarray(thruster_positions, dtype=float).reshape(-1, 3)
        lo, hi = p.min(axis=0) - margin, p.max(axis=0) + margin
        # a flat layout (all thrusters in one plane) still gets a body height
        for i, size in enumerate(default):
            if hi[i] - lo[i] < size / 2:
                c = (hi[i] + lo[i]) / 2
                lo[i], hi[i] = c - size / 4, c + size / 4
    else:
        lo = -np.asarray(default) / 2
        hi = np.asarray(default) / 2
    return {"min": np.round(lo, 3).tolist(), "max": np.round(hi, 3).tolist()}


def world_objects(bridge: Any, name: str | None = None) -> list[Any]:
    """The bridge's world objects where they are now (its main-process scene, which the timeline's
    moves place; the scenario's objects if it has none); ``name``: only that object and its
    parts (``name/...``)."""
    world = getattr(bridge, "world", None)
    objects = list(world.objects) if world is not None else list(bridge.scenario.objects)
    if name is not None:
        objects = [o for o in objects if o.name == name or o.name.startswith(name + "/")]
    return objects


def scene_description(bridge: Any) -> dict[str, Any]:
    """The scene part of a page's ``hello``: objects (where they are now), hull, thruster and
    sensor names."""
    scenario = bridge.scenario
    ts = bridge.vehicle.thrusters
    positions = [list(map(float, t.position)) for t in ts.thrusters] if ts is not None else None
    return {
        "scenario": scenario.name,
        "objects": object_outlines(world_objects(bridge)),
        "hull": hull_box(positions),
        "thrusters": list(ts.names) if ts is not None else [],
        "sensors": [{"name": s.name, "kind": s.kind} for s in scenario.sensors],
    }
