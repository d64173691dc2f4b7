"""Contacts: the vehicle's hull against the world's meshes and the water surface.

A constraint step after the dynamics step, whatever the vehicle model: the
dynamics move the vehicle freely over ``dt``, then :meth:`ContactModel.step`
looks for overlaps of the hull (a box in the body frame, ``[hull]`` of the
vehicle profile) with every object of the :class:`~hilsim.sim.world.World`
and with the water surface (NED z = 0: a buoyant vehicle floats with the
hull's top there), and

1. removes the inward normal velocity with impulses through the vehicle's
   inverse mass (no restitution: nothing bounces, kinetic energy never grows);
2. applies Coulomb friction, ``|J_t| <= mu J_n`` per contact, with the
   material's ``friction`` (none at the water surface);
3. moves the hull back by what the removed velocity moved it during the step
   (along the contact: a resting vehicle does not creep) and pushes it out along
   each normal down to a resting overlap of ``slop`` (1 mm), never further (it
   stays touching, so a resting contact stays a contact);
4. shows the velocity change in ``state.acceleration`` (the IMU feels the
   impact) and returns the new state.

Pressed against a wall by a force F, the impulse that cancels each step's
inward velocity is ``F dt``, so the contact force is F and a sliding vehicle
decelerates by ``mu F / m_t`` (m_t the mass along the slide): Coulomb's law.
A vehicle driven into a wall sees its penetration undone every step, so the
state the sensors see overlaps by at most ``slop`` whatever the thrust.
Angular velocities are not changed (the hull's corners may rotate away from a
wall; no contact torque).

Contact normals (see :func:`hilsim.sim.collide.choose_normal`): the axis
that separated the hull from the object at the previous step's pose, i.e. the
face it crossed; for a resting contact the axis of least penetration. Convex
objects (boxes, cylinders) are tested whole; other meshes (terrain, imported
scenes) triangle by triangle, with the triangle's outward normal preferred.

Cost: a cached "safe sphere" (how far the hull may move before it could touch
anything, from bounding boxes) makes a tick without anything near a handful
of float operations; the narrow phase runs only near an object.

Limits: the hull is rigid, so an impact's force is its momentum stopped within
one step (it scales with the physics rate; the impact speed does not); an object
the timeline moves jumps to its new pose (its velocity is not passed on: it
pushes the hull out, it does not throw it); contacts exert no torque.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from hilsim.config import Doc, check_keys, quantity
from hilsim.sim.collide import CORNERS, box_triangle_distance, choose_normal, convex_axes, sat_convex, sat_triangles
from hilsim.sim.contact_shapes import WorldShapes
from hilsim.sim.geometry import F64
from hilsim.sim.state import VehicleState
from hilsim.sim.world import Material

DEFAULT_FRICTION = Material.friction  # [1] Coulomb coefficient of a material without ``friction`` (0.5)
SLOP = 1e-3              # [m] overlap left in a resting contact
_ATT_TOL = 0.05          # [rad] roll/pitch change the cached safe sphere allows
_PREFER_FACE = 1e-3      # [m] see collide.choose_normal (a resting overlap: the slop)
_ITERATIONS = 8


@dataclass(frozen=True)
class Hull:
    """The vehicle's collision hull: a box along the body axes.

    size (3,) [m] full extents along body x, y, z; centre (3,) [m] of the box in
    the body frame; sources: key -> where its value comes from."""

    size: tuple[float, float, float]
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    shape: str = "box"
    sources: dict[str, str] = field(default_factory=dict, compare=False)

    @property
    def half(self) -> F64:
        """(3,) [m] half extents."""
        return np.asarray(self.size, dtype=float) / 2.0

    @property
    def top(self) -> float:
        """[m] body z of the hull's top face (negative: above the body origin)."""
        return self.centre[2] - self.size[2] / 2.0


POINT_HULL = Hull((0.0, 0.0, 0.0))


def load_hull(doc: Doc, where: str = "hull") -> Hull | None:
    """The ``[hull]`` table of a vehicle profile (None if absent)::

        [hull]
        shape = "box"
        size = { value = [0.9, 0.8, 0.6], unit = "m", source = "..." }
        centre = { value = [0.0, 0.0, 0.0], unit = "m", source = "..." }   # optional
    """
    t = doc.data.get(where)
    if t is None:
        return None
    if not isinstance(t, dict):
        raise doc.error(where, "expected a table")
    check_keys(doc, t, ("shape", "size", "centre", "description"), where)
    shape = t.get("shape", "box")
    if shape != "box":
        raise doc.error(f"{where}.shape", f"hull shape {shape!r} is not supported; use \"box\"")
    size = quantity(doc, t, "size", "m", where, length=3)
    if min(size) < 0.0:
        raise doc.error(f"{where}.size", "sizes must be >= 0")
    centre = quantity(doc, t, "centre", "m", where, default=(0.0, 0.0, 0.0), length=3)
    sources = {f"{where}.{k}": str(t[k]["source"]) for k in ("size", "centre") if k in t}
    return Hull(tuple(size), tuple(centre), "box", sources)


def inverse_mass(profile: Any) -> F64:
    """(3, 3) [1/kg] body-frame translational inverse mass of a vehicle profile.

    A profile with a 6 x 6 ``mass_matrix`` (rigid body + added mass) gives the
    inverse of its translational block; one with per-DOF ``params`` (the
    diagonal model) gives diag(1/m_u, 1/m_v, 1/m_w), 0 for a held DOF (it cannot move)."""
    mm = getattr(profile, "mass_matrix", None)
    if mm is not None:
        return np.linalg.inv(np.asarray(mm, dtype=float)[:3, :3])
    params = getattr(profile, "params", {})
    diag = []
    for dof in ("surge", "sway", "heave"):
        p = params.get(dof)
        diag.append(1.0 / p.mass if p is not None else 0.0)
    return np.diag(diag)


@dataclass(frozen=True)
class ContactInfo:
    """What the contact step found at one tick.

    objects: names of the solid objects the hull overlapped (before the push-out);
    forces (per object) [N]: normal contact force (normal impulse / dt);
    speeds (per object) [m/s]: normal approach speed before the response;
    depths (per object) [m]: overlap before the push-out;
    penetration [m]: largest overlap left after the push-out (<= slop when resolved);
    surfaced: the hull touches the water surface.
    """

    objects: tuple[str, ...] = ()
    forces: tuple[float, ...] = ()
    speeds: tuple[float, ...] = ()
    depths: tuple[float, ...] = ()
    penetration: float = 0.0
    surfaced: bool = False

    @property
    def touching(self) -> bool:
        return bool(self.objects)

    @property
    def force(self) -> float:
        """[N] total normal force from the solid objects."""
        return float(sum(self.forces))


NO_CONTACT = ContactInfo()


def _rpy(roll: float, pitch: float, yaw: float) -> F64:
    """(3, 3) body -> world rotation, as :func:`hilsim.sim.geometry.rpy_to_matrix` (in floats)."""
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), \
        math.cos(yaw), math.sin(yaw)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _dot(a: Sequence[float], b: Sequence[float]) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _mv(m: Sequence[Sequence[float]], a: Sequence[float]) -> tuple[float, float, float]:
    """m @ a for a 3 x 3 ``m`` and a 3-vector ``a`` in Python floats."""
    return (m[0][0] * a[0] + m[0][1] * a[1] + m[0][2] * a[2], m[1][0] * a[0] + m[1][1] * a[1] + m[1][2] * a[2],
            m[2][0] * a[0] + m[2][1] * a[1] + m[2][2] * a[2])


def _mtv(m: Sequence[Sequence[float]], a: Sequence[float]) -> tuple[float, float, float]:
    """m.T @ a."""
    return (m[0][0] * a[0] + m[1][0] * a[1] + m[2][0] * a[2], m[0][1] * a[0] + m[1][1] * a[1] + m[2][1] * a[2],
            m[0][2] * a[0] + m[1][2] * a[1] + m[2][2] * a[2])


@dataclass
class _Contact:
    obj: int            # object index, -1 for the surface
    normal: F64         # (3,) world, from the object to the hull
    depth: float        # [m] before the push-out
    friction: float


class ContactModel:
    """The contact step of one vehicle.

    hull: its :class:`Hull`; inv_mass: (3, 3) [1/kg] body-frame inverse mass
    (:func:`inverse_mass`); world: the scene (None: the water surface only);
    surface: whether the water surface (z = 0) holds the hull under it;
    slop [m]: overlap left in a resting contact."""

    def __init__(self, hull: Hull = POINT_HULL, inv_mass: F64 | None = None, world: Any = None,
                 surface: bool = True, slop: float = SLOP):
        self.hull = hull
        self.half = hull.half
        self.offset = np.asarray(hull.centre, dtype=float)
        self.inv_mass = np.eye(3) if inv_mass is None else np.asarray(inv_mass, dtype=float)
        self.surface = surface
        self.slop = float(slop)
        self.last: ContactInfo = NO_CONTACT
        self._shapes: WorldShapes | None = None
        self._tris: Any = None
        self._world: Any = None
        self.world = world
        self._safe: tuple[float, ...] | None = None
        self._box = CORNERS * self.half                 # (8, 3) body-frame corners about the hull centre
        corners = self.offset + self._box
        self._corners = corners
        self._radius = float(np.linalg.norm(corners, axis=1).max())
        self._bounds_cache: tuple[Any, tuple[float, float, float]] = (None, (0.0, 0.0, 0.0))

    @staticmethod
    def for_profile(profile: Any, world: Any = None, surface: bool = True) -> "ContactModel":
        """The contact step of a vehicle profile (its ``hull``; a point if it has none)."""
        hull = getattr(profile, "hull", None) or POINT_HULL
        return ContactModel(hull, inverse_mass(profile), world, surface)

    @property
    def surface(self) -> bool:
        """Whether the water surface (z = 0) holds the hull under it."""
        return self._surface

    @surface.setter
    def surface(self, on: bool) -> None:
        self._surface = bool(on)
        self._safe = None

    @property
    def world(self) -> Any:
        return self._world

    @world.setter
    def world(self, world: Any) -> None:
        self._world = world
        self._shapes = None
        self._tris = None
        self._safe = None
        self._axes: dict[int, tuple[Any, ...]] = {}  # object -> (hull rotation, its SAT axes...)

    def _current_shapes(self) -> WorldShapes | None:
        w = self._world
        if w is None:
            return None
        if self._shapes is None or w.triangles is not self._tris:  # built, or rebuilt (an object moved)
            self._shapes = WorldShapes(w, DEFAULT_FRICTION)
            self._tris = w.triangles
            self._safe = None
            self._axes = {}
        return self._shapes

    # -- the step ------------------------------------------------------------------

    def step(self, before: VehicleState, after: VehicleState, dt: float) -> VehicleState:
        """The state ``after`` a dynamics step of ``dt`` [s] from ``before``, with the
        contacts resolved; :attr:`last` tells what was found."""
        f = after.flat()
        safe = self._safe
        if safe is not None and (self._world is None or self._world.triangles is self._tris):
            dx, dy, dz = f[0] - safe[0], f[1] - safe[1], f[2] - safe[2]
            if (dx * dx + dy * dy + dz * dz < safe[3] and abs(f[3] - safe[4]) < _ATT_TOL
                    and abs(f[4] - safe[5]) < _ATT_TOL and abs(f[5] - safe[6]) < _ATT_TOL):
                self.last = NO_CONTACT
                return after
        return self._slow(before, after, f, dt)

    def _bounds(self, roll: float, pitch: float) -> tuple[float, float, float]:
        """Horizontal radius and vertical extent (z min, z max) [m] of the hull around the body
        origin for any yaw, at this roll and pitch, grown for a roll/pitch change of _ATT_TOL."""
        key = (roll, pitch)
        if self._bounds_cache[0] != key:
            c = self._corners @ _rpy(roll, pitch, 0.0).T
            grow = self._radius * _ATT_TOL
            rho = float(np.hypot(c[:, 0], c[:, 1]).max()) + grow
            self._bounds_cache = (key, (rho, float(c[:, 2].min()) - grow, float(c[:, 2].max()) + grow))
        return self._bounds_cache[1]

    def _slow(self, before: VehicleState, after: VehicleState, f: tuple[float, ...], dt: float) -> VehicleState:
        x, y, z, roll, pitch, yaw = f[0], f[1], f[2], f[3], f[4], f[5]
        rho, zmin, zmax = self._bounds(roll, pitch)
        lo = np.array([x - rho, y - rho, z + zmin])
        hi = np.array([x + rho, y + rho, z + zmax])
        safe = (z + zmin) if self.surface else math.inf
        shapes = self._current_shapes()
        rot = _rpy(roll, pitch, yaw)
        centre = np.array([x, y, z]) + rot @ self.offset
        contacts: list[_Contact] = []
        if self.surface and z + zmin <= 0.0:
            top = float((centre + self._box_world_corners(rot))[:, 2].min())
            if top < 0.0:
                contacts.append(_Contact(-1, np.array([0.0, 0.0, 1.0]), -top, 0.0))
        if shapes is not None:
            pf = before.flat()
            prot = _rpy(pf[3], pf[4], pf[5])
            pcentre = np.array(pf[0:3]) + prot @ self.offset
            gaps = shapes.aabb_gaps(lo, hi)
            for i in np.flatnonzero(gaps <= 0.0).tolist():
                found, sep = self._narrow(shapes, i, centre, rot, pcentre, prot, lo, hi)
                contacts.extend(found)
                if not found:  # exact for this yaw: allow for the rotation the cache lets pass
                    safe = min(safe, sep - 3.0 * _ATT_TOL * self._radius)
            if len(gaps):
                safe = min(safe, float(gaps[gaps > 0.0].min()) if np.any(gaps > 0.0) else math.inf)
        if not contacts:
            self.last = NO_CONTACT
            self._safe = (x, y, z, safe * safe, roll, pitch, yaw) if safe > 1e-6 else None
            return after
        self._safe = None
        return self._respond(after, f, dt, rot, contacts, shapes)

    def _box_world_corners(self, rot: F64) -> F64:
        return self._box @ rot.T

    def _narrow(self, shapes: WorldShapes, i: int, c: F64, rot: F64, pc: F64, prot: F64, lo: F64, hi: F64
                ) -> tuple[list[_Contact], float]:
        """Contacts of the hull with object ``i``; if none, a lower bound [m] of its distance."""
        half = self.half
        mu = shapes.friction[i]
        conv = shapes.convex[i]
        if conv is not None:
            key = rot.tobytes()
            cached = self._axes.get(i)
            if cached is None or cached[0] != key:  # the axes turn with the hull only
                cached = self._axes[i] = (key, *convex_axes(rot, half, *conv))
            _, axes, r, omin, omax = cached
            p = axes @ c
            op, om = omax - (p - r), (p + r) - omin
            if min(float(op.min()), float(om.min())) < 0.0:
                return [], float(np.max(-np.minimum(op, om)))
            if np.array_equal(rot, prot):  # same axes: the previous projections are a shift
                shift = axes @ (c - pc)
                pop, pom = op + shift, om - shift
            else:
                _, pop, pom = sat_convex(pc, prot, half, *conv)
            sp, sm = pop < 0.0, pom < 0.0
            if sp.any() or sm.any():  # the face it crossed during the step
                cp, cm = np.where(sp, op, np.inf), np.where(sm, om, np.inf)
            else:  # resting: least penetration
                cp, cm = op, om
            kp, km = int(np.argmin(cp)), int(np.argmin(cm))
            if cp[kp] <= cm[km]:
                return [_Contact(i, axes[kp], float(cp[kp]), mu)], 0.0
            return [_Contact(i, -axes[km], float(cm[km]), mu)], 0.0
        idx, sep = shapes.near_triangles(i, lo, hi)
        if len(idx) == 0:
            return [], sep
        tris, normals = shapes.triangles(i, idx)
        # only a triangle whose plane the hull straddles can touch it; the others are at least
        # their plane's distance away
        plane = np.abs((normals * (c - tris[:, 0])).sum(axis=1)) - np.abs(normals @ rot) @ half
        # ... and whose vertices reach into the hull's slab along each of its axes (box frame)
        q = (tris - c) @ rot
        slab = np.max(np.maximum(q.min(axis=1) - half, -half - q.max(axis=1)), axis=1)
        plane = np.maximum(plane, slab)
        cut = plane <= 0.0
        if not np.all(cut):
            sep = min(sep, float(plane[~cut].min()))
            if not np.any(cut):
                return [], sep
            tris, normals = tris[cut], normals[cut]
        axes, op, om = sat_triangles(c, rot, half, tris, normals)
        if np.array_equal(rot, prot):  # same axes: the previous projections are a shift
            shift = axes @ (c - pc)
            pop, pom = op + shift, om - shift
        else:
            _, pop, pom = sat_triangles(pc, prot, half, tris, normals)
        hit, depth, normal = choose_normal(axes, op, om, pop, pom, one_sided=3, prefer_eps=_PREFER_FACE)
        if not np.any(hit):
            gap = np.max(-np.minimum(op, om), axis=1)
            return [], float(min(sep, gap.min()))
        out: list[_Contact] = []
        for k in np.argsort(-depth[hit]).tolist():  # deepest first; one contact per direction
            n = normal[hit][k]
            if all(float(n @ o.normal) < 0.99 for o in out):
                out.append(_Contact(i, n, float(depth[hit][k]), mu))
            if len(out) >= 6:
                break
        return out, 0.0

    def _respond(self, after: VehicleState, f: tuple[float, ...], dt: float, rot: F64,
                 contacts: list[_Contact], shapes: WorldShapes | None) -> VehicleState:
        # 2-3. impulses: normal (>= 0, no restitution) and Coulomb friction, accumulated and clamped
        normals = [tuple(ct.normal.tolist()) for ct in contacts]
        vb0 = f[6:9]
        rl = rot.tolist()
        v = _mv(rl, vb0)
        w = (rot @ self.inv_mass @ rot.T).tolist()
        jn = [0.0] * len(contacts)
        jt = [(0.0, 0.0, 0.0)] * len(contacts)
        speeds = [max(0.0, -_dot(n, v)) for n in normals]
        for _ in range(_ITERATIONS):
            change = 0.0
            for k, (ct, n) in enumerate(zip(contacts, normals)):
                wn = _mv(w, n)
                kn = _dot(n, wn)
                if kn <= 1e-15:
                    continue
                new = max(jn[k] - _dot(n, v) / kn, 0.0)
                d = new - jn[k]
                if d:
                    v = (v[0] + wn[0] * d, v[1] + wn[1] * d, v[2] + wn[2] * d)
                    change = max(change, abs(d) * kn)
                jn[k] = new
                if ct.friction <= 0.0 or new <= 0.0:
                    continue
                vn = _dot(n, v)
                vt = (v[0] - n[0] * vn, v[1] - n[1] * vn, v[2] - n[2] * vn)
                sp = math.sqrt(_dot(vt, vt))
                if sp < 1e-12:
                    continue
                t = (vt[0] / sp, vt[1] / sp, vt[2] / sp)
                kt = _dot(t, _mv(w, t))
                if kt <= 1e-15:
                    continue
                old = jt[k]
                c = (old[0] - t[0] * sp / kt, old[1] - t[1] * sp / kt, old[2] - t[2] * sp / kt)
                lim = ct.friction * jn[k]
                mag = math.sqrt(_dot(c, c))
                if mag > lim:
                    c = (c[0] * lim / mag, c[1] * lim / mag, c[2] * lim / mag)
                dj = _mv(w, (c[0] - old[0], c[1] - old[1], c[2] - old[2]))
                v = (v[0] + dj[0], v[1] + dj[1], v[2] + dj[2])
                change = max(change, math.sqrt(_dot(dj, dj)))
                jt[k] = c
            if change < 1e-10:  # [m/s]
                break
        # 4. positions: undo what the removed velocity moved during the step (its mean over the
        # step, for a velocity that grew steadily: the step's change / 2) along the contact (so a
        # resting contact does not creep); along each normal, push out what overlaps beyond the
        # slop and no further (never lift off: the hull stays touching)
        vf = _mv(rl, vb0)
        h = 0.5 * dt
        dp = [(v[0] - vf[0]) * h, (v[1] - vf[1]) * h, (v[2] - vf[2]) * h]
        for _ in range(_ITERATIONS):
            moved = False
            for ct, n in zip(contacts, normals):
                r = max(ct.depth - self.slop, 0.0) - _dot(n, dp)
                if abs(r) > 1e-12:
                    dp = [dp[0] + n[0] * r, dp[1] + n[1] * r, dp[2] + n[2] * r]
                    moved = True
            if not moved:
                break
        residual = max(ct.depth - _dot(n, dp) for ct, n in zip(contacts, normals))
        vb = _mtv(rl, v)
        out = list(f)
        out[0] += dp[0]
        out[1] += dp[1]
        out[2] += dp[2]
        out[6:9] = list(vb)
        for j in range(3):
            out[12 + j] += (vb[j] - vb0[j]) / dt
        names = shapes.names if shapes is not None else []
        objs: dict[int, list[float]] = {}
        for k, ct in enumerate(contacts):
            if ct.obj < 0:
                continue
            e = objs.setdefault(ct.obj, [0.0, 0.0, 0.0])
            e[0] += jn[k] / dt
            e[1] = max(e[1], speeds[k])
            e[2] = max(e[2], ct.depth)
        order = sorted(objs, key=lambda o: -objs[o][0])
        self.last = ContactInfo(tuple(names[o] for o in order), tuple(objs[o][0] for o in order),
                                tuple(objs[o][1] for o in order), tuple(objs[o][2] for o in order),
                                max(0.0, residual), any(ct.obj < 0 for ct in contacts))
        return VehicleState.from_flat(after.time, out)

    # -- queries for the ground truth ---------------------------------------------------

    def clearance(self, state: VehicleState) -> tuple[float, str]:
        """[m] distance from the hull to the nearest object, and that object's name
        (inf and "" in an empty world). Exact (box against every nearby triangle)."""
        shapes = self._current_shapes()
        if shapes is None or not shapes.names:
            return math.inf, ""
        f = state.flat()
        rot = _rpy(f[3], f[4], f[5])
        c = np.array(f[0:3]) + rot @ self.offset
        corners = c + self._box_world_corners(rot)
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        gaps = shapes.aabb_gaps(lo, hi)
        reach = max(float(gaps.min()), 0.25)
        while True:  # the triangles within reach; the nearest of them is the nearest of all if within reach
            idx = shapes.all_within(lo - reach, hi + reach)
            d, k = self._nearest(shapes, c, rot, lo, hi, idx) if len(idx) else (math.inf, -1)
            if d <= reach or reach >= shapes.extent:
                return d, (shapes.names[shapes.owner(k)] if k >= 0 else "")
            reach = min(max(2.0 * reach, d), shapes.extent)

    def _nearest(self, shapes: WorldShapes, c: F64, rot: F64, lo: F64, hi: F64, idx: np.ndarray
                 ) -> tuple[float, int]:
        """The exact distance [m] from the hull to the nearest of the world's triangles ``idx``, and
        its index: triangles in order of a cheap lower bound (their bounding box's and their plane's
        distance), exactly only while the bound is below the best so far."""
        tris, normals = shapes.all_triangles(idx)
        tlo, thi = tris.min(axis=1), tris.max(axis=1)
        g = np.maximum(np.maximum(tlo - hi, lo - thi), 0.0)
        plane = np.abs(np.einsum("td,td->t", normals, c - tris[:, 0])) - np.abs(normals @ rot) @ self.half
        lb = np.maximum(np.sqrt((g * g).sum(axis=1)), plane)
        order = np.argsort(lb)
        best, at = math.inf, -1
        for chunk in (order[:8], order[8:]):
            chunk = chunk[lb[chunk] < best]
            if len(chunk):
                d = box_triangle_distance(c, rot, self.half, tris[chunk])
                j = int(np.argmin(d))
                if d[j] < best:
                    best, at = float(d[j]), int(idx[chunk[j]])
        return best, at

    def altitude(self, state: VehicleState) -> float:
        """[m] from the body origin straight down (NED +z) to the first surface; inf if none."""
        w = self._world
        if w is None:
            return math.inf
        hits = w.cast(np.array([state.flat()[0:3]]), np.array([[0.0, 0.0, 1.0]]))
        return float(hits.t[0])
