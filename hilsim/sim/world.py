"""The world: triangle meshes with materials, and the ray queries sensors make.

A :class:`World` holds every object's mesh already placed in the world frame
(NED [m]), flattens them into one triangle array for the ray caster, and keeps
per-triangle lookups (object, material, normal) so that a hit's triangle index
answers every question a sensor model asks. Sensors get the world passed in;
nothing reaches it through a global.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import trimesh

from hilsim.sim.geometry import F64
from hilsim.sim.raycast import EmbreeCaster, I64, RayCaster


@dataclass(frozen=True)
class Material:
    """Surface properties of an object.

    impedance: acoustic impedance Z [Pa s/m] (water is about 1.5e6).
    color: (3,) linear RGB reflectance in [0, 1].
    acoustic_absorption: fraction [0, 1] of incident acoustic intensity absorbed at the surface.
    optical_absorption: fraction [0, 1] of incident light absorbed at the surface.
    friction: Coulomb friction coefficient [1] of the vehicle's hull sliding on it (contacts).
    """

    name: str
    impedance: float
    color: tuple[float, float, float] = (0.5, 0.5, 0.5)
    acoustic_absorption: float = 0.0
    optical_absorption: float = 0.0
    friction: float = 0.5  # hilsim.sim.contact.DEFAULT_FRICTION


@dataclass(frozen=True)
class Water:
    """The medium.

    impedance: Z0 [Pa s/m]; sound_speed [m/s]; density [kg/m^3];
    attenuation: (3,) Beer-Lambert optical attenuation per RGB channel [1/m];
    color: (3,) RGB of the water seen where no surface is hit.
    """

    impedance: float = 1.5e6
    sound_speed: float = 1500.0
    density: float = 1000.0
    attenuation: tuple[float, float, float] = (0.35, 0.07, 0.05)
    color: tuple[float, float, float] = (0.0, 0.12, 0.18)


@dataclass
class WorldObject:
    """One named object: its mesh in the world frame and its material."""

    name: str
    mesh: trimesh.Trimesh
    material: Material
    watertight: bool = True


_LABELS = ("north", "south", "east", "west", "down", "up")


def facet_codes(normals: F64) -> I64:
    """(m,) index into ``("north", "south", "east", "west", "down", "up")`` of (m, 3) normals."""
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    axis = np.argmax(np.abs(n), axis=1)
    negative = n[np.arange(len(n)), axis] < 0
    return (2 * axis + negative).astype(np.int64)


def facet_label(normal: F64) -> str:
    """Name of the dominant direction of a unit normal in NED words.

    ``north``/``south`` (+x/-x), ``east``/``west`` (+y/-y), ``down``/``up`` (+z/-z).
    The top face of a box has an ``up`` normal.
    """
    axis = int(np.argmax(np.abs(normal)))
    positive = normal[axis] >= 0
    return (("north", "south"), ("east", "west"), ("down", "up"))[axis][0 if positive else 1]


@dataclass
class Hits:
    """Result of casting n rays.

    t: (n,) [m] hit distance (inf for a miss); tri: (n,) triangle index (-1 miss);
    obj: (n,) object index (-1 miss); normal: (n, 3) unit geometric normal of the
    triangle hit (zeros for a miss), oriented as the mesh winding gives it.
    """

    t: F64
    tri: I64
    obj: I64
    normal: F64

    @property
    def hit(self) -> np.ndarray:
        return self.tri >= 0


@dataclass
class World:
    """Objects, the water, and a ray caster over all their triangles."""

    objects: list[WorldObject]
    water: Water = field(default_factory=Water)
    caster_factory: Callable[[F64], RayCaster] = EmbreeCaster

    def __post_init__(self) -> None:
        self._placed: dict[str, F64] = {}  # object name -> its current placement (4, 4), once moved
        self.rebuild()

    def place(self, name: str, pose: F64, initial: F64) -> None:
        """Move object ``name`` (with its parts ``name/...``) to the (4, 4) world pose ``pose``;
        ``initial`` is the (4, 4) pose it was built at (the scenario's), used the first time it
        moves. The scene is rebuilt: the next query sees it there."""
        parts = [o for o in self.objects if o.name == name or o.name.startswith(name + "/")]
        if not parts:
            raise KeyError(f"no object {name!r}; objects: {', '.join(self.object_names)}")
        old = self._placed.get(name, np.asarray(initial, dtype=float))
        delta = np.asarray(pose, dtype=float) @ np.linalg.inv(old)
        for o in parts:
            o.mesh.apply_transform(delta)
        self._placed[name] = np.asarray(pose, dtype=float)
        self.rebuild()

    def rebuild(self) -> None:
        """(Re)flatten the objects into triangle arrays and build the caster."""
        tris, normals, owner = [], [], []
        for i, ob in enumerate(self.objects):
            m = ob.mesh
            tris.append(np.asarray(m.triangles, dtype=np.float64))
            normals.append(np.asarray(m.face_normals, dtype=np.float64))
            owner.append(np.full(len(m.faces), i, dtype=np.int64))
        self.triangles: F64 = np.concatenate(tris) if tris else np.zeros((0, 3, 3))
        self.tri_normal: F64 = np.concatenate(normals) if normals else np.zeros((0, 3))
        self.tri_object: I64 = np.concatenate(owner) if owner else np.zeros(0, dtype=np.int64)
        self.tri_facet: I64 = facet_codes(self.tri_normal)
        n_obj = len(self.objects)
        self.obj_impedance: F64 = np.array([o.material.impedance for o in self.objects] or [0.0])
        self.obj_color: F64 = np.array([o.material.color for o in self.objects] or [(0.0, 0.0, 0.0)], dtype=float)
        self.obj_acoustic_absorption: F64 = np.array([o.material.acoustic_absorption for o in self.objects] or [0.0])
        self.obj_optical_absorption: F64 = np.array([o.material.optical_absorption for o in self.objects] or [0.0])
        # reflection coefficient of eq. 7, (Z - Z0) / (Z + Z0), per object, after absorption
        z0 = self.water.impedance
        z = self.obj_impedance[:n_obj] if n_obj else np.zeros(0)
        refl = (z - z0) / (z + z0) if n_obj else np.zeros(0)
        self.obj_reflection: F64 = refl * (1.0 - self.obj_acoustic_absorption[:n_obj]) if n_obj else np.zeros(1)
        self.caster: RayCaster = self.caster_factory(self.triangles)

    @property
    def object_names(self) -> list[str]:
        return [o.name for o in self.objects]

    def object_index(self, name: str) -> int:
        for i, o in enumerate(self.objects):
            if o.name == name:
                return i
        raise KeyError(f"no object named {name!r}; objects: {', '.join(self.object_names)}")

    def cast(self, origins: F64, dirs: F64, t_min: float = 0.0, t_max: float = np.inf) -> Hits:
        """Cast (n, 3) rays from ``origins`` along unit ``dirs``; first hit in [t_min, t_max] [m]."""
        t, tri = self.caster.intersect(origins, dirs, t_min, t_max)
        hit = tri >= 0
        obj = np.full(tri.shape, -1, dtype=np.int64)
        obj[hit] = self.tri_object[tri[hit]]
        normal = np.zeros((tri.shape[0], 3))
        normal[hit] = self.tri_normal[tri[hit]]
        return Hits(t=t, tri=tri, obj=obj, normal=normal)

    def facet_labels(self, tri: I64) -> list[str]:
        """Direction label (see :func:`facet_label`) of each triangle index."""
        return [facet_label(self.tri_normal[i]) for i in np.asarray(tri).tolist()]

    def hit_counts(self, hits: Hits) -> dict[str, dict[str, int]]:
        """Per object, the number of rays that hit each of its facet directions.

        ``{"cuboid": {"south": 120, "up": 40, "total": 160}, ...}``
        """
        out: dict[str, dict[str, int]] = {}
        tri = hits.tri[hits.tri >= 0]
        if tri.size == 0:
            return out
        n_lab = len(_LABELS)
        counts = np.bincount(self.tri_object[tri] * n_lab + self.tri_facet[tri],
                             minlength=len(self.objects) * n_lab).reshape(-1, n_lab)
        for i, row in enumerate(counts.tolist()):
            total = sum(row)
            if total:
                d = {"total": total}
                d.update({_LABELS[k]: c for k, c in enumerate(row) if c})
                out[self.objects[i].name] = d
        return out
