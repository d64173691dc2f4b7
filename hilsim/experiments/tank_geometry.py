"""Which faces of the water tank's cuboid a sonar pose should see, computed without the renderer.

Two independent predictions, both from the scenario's geometry (the floor's
top surface and the cuboid's axis-aligned box) and the sonar's aperture:

:func:`closed_form_faces` is the derivation in the header of
``scenarios/water_tank/scenario.toml``. With ``H`` the sonar's height above
the floor, ``h`` the cuboid's height, ``L`` its length and ``d`` the
horizontal distance (north) from the sonar to its front (south) face: a ray
descending with slope ``tan b`` (metres down per metre north) is ``z``
metres below the sonar after ``z / tan b`` metres north, so

- the front face is ensonified iff ``d`` lies in ``[(H - h) / tan b_max, H / tan b_min]``;
- the top face iff the distances ``(H - h) / tan b`` at which the rays reach
  the cuboid's height, ``[(H - h) / tan b_max, (H - h) / tan b_min]``,
  overlap ``[d, d + L]``.

``tan b`` ranges over the whole aperture (every azimuth and elevation), so
the edge beams, which descend a little more steeply per metre north, widen
the interval. Only the north-bound run of the paper is handled.

:func:`ray_grid_faces` intersects the sonar's own rays (every beam's centre
azimuth, ``n_el`` elevations at the centres of equal steps, as the renderer
casts them) analytically with the floor plane and the box (slab method),
keeps each ray's first surface inside the range window and counts the rays
per cuboid face. It does not see the tank's walls (out of range here).
Face names are the world's (:func:`hilsim.sim.world.facet_label`): the
front is ``south`` (normal -x), the top ``up`` (normal -z).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hilsim.sim.geometry import F64, Pose
from hilsim.sim.world import World

# the face a ray enters a box through, by (axis, ray direction positive): its outward normal's name
_ENTRY_FACE = {(0, True): "south", (0, False): "north", (1, True): "west", (1, False): "east",
               (2, True): "up", (2, False): "down"}


@dataclass(frozen=True)
class TankGeometry:
    """floor_z: [m] NED z of the floor's top surface; box_lo, box_hi: (3,) [m]
    the cuboid's axis-aligned bounds (NED, so box_lo[2] is its top)."""

    floor_z: float
    box_lo: F64
    box_hi: F64

    @staticmethod
    def from_world(world: World, target: str = "cuboid", floor: str = "floor") -> TankGeometry:
        names = world.object_names
        for name in (target, floor):
            if name not in names:
                raise ValueError(f"the water-tank experiment needs objects {target!r} and {floor!r}; "
                                 f"the scenario has: {', '.join(names)}")
        lo, hi = world.objects[world.object_index(target)].mesh.bounds
        floor_top = float(world.objects[world.object_index(floor)].mesh.bounds[0][2])
        return TankGeometry(floor_top, np.asarray(lo, dtype=float), np.asarray(hi, dtype=float))

    @property
    def front_x(self) -> float:
        """[m] north coordinate of the cuboid's front (south) face."""
        return float(self.box_lo[0])

    @property
    def height(self) -> float:
        """[m] h: the cuboid's top above the floor."""
        return self.floor_z - float(self.box_lo[2])

    @property
    def length(self) -> float:
        """[m] L: the cuboid's extent north."""
        return float(self.box_hi[0] - self.box_lo[0])


def aperture_directions(rotation: F64, azimuths: F64, elevations: F64) -> F64:
    """(n_az * n_el, 3) world directions of rays at ``azimuths`` x ``elevations`` [rad]
    (sensor frame: x boresight, y starboard, z down, elevation positive up)."""
    th, ph = np.meshgrid(np.asarray(azimuths, float), np.asarray(elevations, float), indexing="ij")
    th, ph = th.ravel(), ph.ravel()
    d = np.stack([np.cos(ph) * np.cos(th), np.cos(ph) * np.sin(th), -np.sin(ph)], axis=1)
    return np.asarray(d @ np.asarray(rotation, float).T, dtype=np.float64)


def slope_range(rotation: F64, az_limits: tuple[float, float], el_limits: tuple[float, float],
                n: int = 65) -> tuple[float, float]:
    """(tan b_min, tan b_max) [1]: metres down per metre north over the whole aperture."""
    d = aperture_directions(rotation, np.linspace(*az_limits, n), np.linspace(*el_limits, n))
    if np.any(d[:, 0] <= 0) or np.any(d[:, 2] <= 0):
        raise ValueError("the closed-form prediction needs every ray heading north and down")
    s = d[:, 2] / d[:, 0]
    return float(s.min()), float(s.max())


def closed_form_faces(sonar: Pose, geom: TankGeometry, az_limits: tuple[float, float],
                      el_limits: tuple[float, float]) -> dict[str, Any]:
    """The scenario comment's intervals at this sonar pose (see the module doc)."""
    lo, hi = slope_range(sonar.rotation, az_limits, el_limits)
    big_h = geom.floor_z - float(sonar.position[2])
    h, length = geom.height, geom.length
    d = geom.front_x - float(sonar.position[0])
    front = ((big_h - h) / hi, big_h / lo)
    reach = ((big_h - h) / hi, (big_h - h) / lo)
    faces = []
    if front[0] <= d <= front[1]:
        faces.append("south")
    if reach[0] <= d + length and d <= reach[1]:
        faces.append("up")
    return {"d_m": d, "H_m": big_h, "h_m": h, "L_m": length,
            "tan_b": [lo, hi], "b_deg": [math.degrees(math.atan(lo)), math.degrees(math.atan(hi))],
            "front_interval_m": list(front), "top_reach_m": list(reach), "faces": faces}


def ray_grid_faces(sonar: Pose, geom: TankGeometry, azimuths: F64, el_limits: tuple[float, float],
                   range_min: float, range_max: float, n_el: int = 1000) -> dict[str, Any]:
    """Rays per cuboid face (first surface inside ``[range_min, range_max]`` [m]); see the module doc."""
    step = (el_limits[1] - el_limits[0]) / n_el
    elev: F64 = el_limits[0] + (np.arange(n_el, dtype=np.float64) + 0.5) * step
    d = aperture_directions(sonar.rotation, azimuths, elev)
    o = np.asarray(sonar.position, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (geom.box_lo - o) / d
        t2 = (geom.box_hi - o) / d
        near = np.fmin(t1, t2)
        far = np.fmax(t1, t2)
        t_floor = np.where(d[:, 2] > 0, (geom.floor_z - o[2]) / d[:, 2], np.inf)
    t_in = near.max(axis=1)
    t_out = far.min(axis=1)
    axis = near.argmax(axis=1)
    on_box = np.isfinite(t_in) & (t_in <= t_out) & (t_in >= range_min)
    t_box = np.where(on_box, t_in, np.inf)
    first = np.minimum(t_box, np.where(t_floor >= range_min, t_floor, np.inf))
    seen = (first <= range_max) & (t_box <= first)
    counts: dict[str, int] = {}
    positive = d[np.arange(len(d)), axis] > 0
    for (ax, pos), name in _ENTRY_FACE.items():
        n = int(np.count_nonzero(seen & (axis == ax) & (positive == pos)))
        if n:
            counts[name] = n
    return {"rays": len(d), "counts": counts, "faces": sorted(counts)}
