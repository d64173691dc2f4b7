"""Scenario files: the world, the vehicle, its sensor mounts, as TOML data.

A scenario is a folder holding ``scenario.toml`` and the meshes it names. The
file is data only; every path in it must stay inside the folder. Units are in
the key names (``position_m``, ``orientation_deg``, ``impedance_Pa_s_m``).
See ``scenarios/README.md`` for the format; :func:`load_scenario` refuses
unknown keys (suggesting the closest valid one), missing files and escaping
paths with a :class:`~hilsim.config.ConfigError` naming file, line and key.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import trimesh

from hilsim.config import ConfigError, Doc, check_keys, load_toml, number, require, safe_join, vector
from hilsim.resources import check_profile_ref
from hilsim.sim.geometry import Pose
from hilsim.sim.world import Material, Water, World, WorldObject

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".stl", ".ply", ".glb", ".gltf", ".off", ".dae")
PRIMITIVES = ("box", "cylinder", "sphere", "plane", "terrain")
SENSOR_KINDS = ("sonar", "camera", "depth", "imu", "dvl", "gnss", "echosounder")
# how a mesh file's axes map to NED (x north, y east, z down)
_UP_AXES: dict[str, np.ndarray] = {
    "z": np.diag([1.0, -1.0, -1.0]),                        # Z up (Blender, most OBJ/STL/PLY)
    "y": np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]),  # Y up (glTF convention)
    "-z": np.eye(3),                                         # already NED (z down)
}

_TOP_KEYS = ("name", "description", "seed", "water", "materials", "objects", "vehicle", "sensors",
             "positions", "devices", "links", "physics", "timeline", "world")
_WORLD_KEYS = ("origin", "description")
_ORIGIN_KEYS = ("lat_deg", "lon_deg", "alt_m")
_WATER_KEYS = ("impedance_Pa_s_m", "sound_speed_m_s", "density_kg_m3", "attenuation_per_m", "color")
_MATERIAL_KEYS = ("impedance_Pa_s_m", "color", "acoustic_absorption", "optical_absorption", "friction",
                  "description")
_OBJECT_KEYS = ("name", "material", "materials", "mesh", "primitive", "position_m", "orientation_deg",
                "scale", "up_axis", "size_m", "radius_m", "height_m", "sections", "subdivisions",
                "resolution_m", "relief_m", "seed", "watertight", "description")
_VEHICLE_KEYS = ("profile", "position_m", "orientation_deg", "description")
_SENSOR_KEYS = ("name", "kind", "profile", "position_m", "orientation_deg", "description")
_POSITION_KEYS = ("position_m", "yaw_deg", "description")


@dataclass(frozen=True)
class SensorMount:
    """A sensor on the vehicle: its profile and its pose in the body frame."""

    name: str
    kind: str           # sonar | camera | depth | imu
    profile: str        # profile reference, e.g. "sonars/didson_hf"
    mount: Pose         # sensor -> body


@dataclass(frozen=True)
class VehicleSpec:
    profile: str
    position: tuple[float, float, float]      # NED [m]
    attitude: tuple[float, float, float]      # roll, pitch, yaw [rad]


@dataclass(frozen=True)
class NamedPosition:
    """A named vehicle pose (``hilsim render --at A``)."""

    position: tuple[float, float, float]      # NED [m]
    yaw: float                                # [rad]
    description: str = ""


@dataclass(frozen=True)
class GeodeticOrigin:
    """Where the world frame's origin (NED x = y = z = 0, the water surface) is on the Earth:
    WGS84 latitude and longitude [deg], altitude above mean sea level [m]."""

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0


DEFAULT_ORIGIN = GeodeticOrigin(0.0, 0.0, 0.0)


@dataclass
class Scenario:
    """A loaded, validated scenario (the description; the World is built from it)."""

    path: Path
    name: str
    description: str
    seed: int
    water: Water
    objects: list[WorldObject]
    vehicle: VehicleSpec | None
    sensors: list[SensorMount]
    positions: dict[str, NamedPosition]
    raw: dict[str, Any] = field(repr=False, default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    origin: GeodeticOrigin | None = None   # [world] origin; None: not given (GNSS then uses 0 N 0 E)

    @property
    def folder(self) -> Path:
        return self.path.parent

    def build_world(self, **kwargs: Any) -> World:
        """A :class:`World` over this scenario's objects (kwargs go to World)."""
        return World([WorldObject(o.name, o.mesh.copy(), o.material, o.watertight) for o in self.objects],
                     self.water, **kwargs)

    def raw_object_names(self) -> list[str]:
        """The object names as written in the file (a multi-material mesh is one name)."""
        return [str(o.get("name")) for o in self.raw.get("objects", []) if isinstance(o, Mapping)]

    def object_placement(self, name: str) -> Pose:
        """The pose an object is placed at in the file (its ``position_m`` / ``orientation_deg``)."""
        for o in self.raw.get("objects", []):
            if isinstance(o, Mapping) and o.get("name") == name:
                xyz = [float(v) for v in o.get("position_m", (0.0, 0.0, 0.0))]
                rpy = [math.radians(float(a)) for a in o.get("orientation_deg", (0.0, 0.0, 0.0))]
                return Pose.from_xyz_rpy(xyz, rpy)
        raise KeyError(f"no object {name!r} in scenario {self.name!r}")

    def sensor(self, name_or_kind: str) -> SensorMount:
        """The sensor mount with this name, or the first of this kind."""
        for s in self.sensors:
            if s.name == name_or_kind:
                return s
        for s in self.sensors:
            if s.kind == name_or_kind:
                return s
        raise KeyError(f"scenario {self.name!r} has no sensor named or of kind {name_or_kind!r}; "
                       f"sensors: {', '.join(s.name for s in self.sensors) or 'none'}")


def _rgb(doc: Doc, table: Mapping[str, Any], key: str, where: str, default: tuple[float, float, float]) -> tuple[float, float, float]:
    v = vector(doc, table, key, 3, where, default)
    if any(c < 0.0 or c > 1.0 for c in v):
        raise doc.error(f"{where}.{key}", f"colour components must be in [0, 1], got {list(v)}")
    return (v[0], v[1], v[2])


def _pose(doc: Doc, table: Mapping[str, Any], where: str) -> Pose:
    xyz = vector(doc, table, "position_m", 3, where, (0.0, 0.0, 0.0))
    rpy = vector(doc, table, "orientation_deg", 3, where, (0.0, 0.0, 0.0))
    return Pose.from_xyz_rpy(xyz, tuple(math.radians(a) for a in rpy))


def _table(doc: Doc, value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise doc.error(where, f"expected a table, got {type(value).__name__}")
    return value


def _load_water(doc: Doc) -> Water:
    t = _table(doc, doc.data.get("water", {}), "water")
    check_keys(doc, t, _WATER_KEYS, "water")
    d = Water()
    att = vector(doc, t, "attenuation_per_m", 3, "water", d.attenuation)
    if any(a < 0 for a in att):
        raise doc.error("water.attenuation_per_m", "attenuation must be >= 0")
    return Water(
        impedance=number(doc, t, "impedance_Pa_s_m", "water", d.impedance, lo=1.0),
        sound_speed=number(doc, t, "sound_speed_m_s", "water", d.sound_speed, lo=1300.0, hi=1700.0),
        density=number(doc, t, "density_kg_m3", "water", d.density, lo=900.0, hi=1100.0),
        attenuation=(att[0], att[1], att[2]),
        color=_rgb(doc, t, "color", "water", d.color),
    )


def _load_materials(doc: Doc) -> dict[str, Material]:
    mats: dict[str, Material] = {}
    t = _table(doc, doc.data.get("materials", {}), "materials")
    for name, m in t.items():
        where = f"materials.{name}"
        m = _table(doc, m, where)
        check_keys(doc, m, _MATERIAL_KEYS, where)
        mats[name] = Material(
            name=name,
            impedance=number(doc, m, "impedance_Pa_s_m", where, lo=1.0),
            color=_rgb(doc, m, "color", where, (0.5, 0.5, 0.5)),
            acoustic_absorption=number(doc, m, "acoustic_absorption", where, 0.0, lo=0.0, hi=1.0),
            optical_absorption=number(doc, m, "optical_absorption", where, 0.0, lo=0.0, hi=1.0),
            friction=number(doc, m, "friction", where, Material.friction, lo=0.0, hi=10.0),
        )
    return mats


def _material_ref(doc: Doc, mats: Mapping[str, Material], name: Any, key: str) -> Material:
    if not isinstance(name, str) or name not in mats:
        import difflib

        close = difflib.get_close_matches(str(name), list(mats), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else f"; defined materials: {', '.join(mats) or 'none'}"
        raise doc.error(key, f"unknown material {name!r}{hint}")
    return mats[name]


def _terrain(doc: Doc, t: Mapping[str, Any], where: str) -> trimesh.Trimesh:
    """A seeded smooth random heightfield, centred on the origin, mean surface at z = 0 (NED)."""
    size = vector(doc, t, "size_m", 2, where)
    res = number(doc, t, "resolution_m", where, 0.25, lo=1e-3)
    relief = number(doc, t, "relief_m", where, 0.2, lo=0.0)
    seed = int(number(doc, t, "seed", where, 0.0))
    nx, ny = int(round(size[0] / res)) + 1, int(round(size[1] / res)) + 1
    if nx * ny > 4_000_000 or nx < 2 or ny < 2:
        raise doc.error(f"{where}.resolution_m", f"terrain grid {nx} x {ny} is out of range (2..4e6 points)")
    rng = np.random.default_rng(seed)
    x = np.linspace(-size[0] / 2, size[0] / 2, nx)
    y = np.linspace(-size[1] / 2, size[1] / 2, ny)
    xx, yy = np.meshgrid(x, y, indexing="ij")
    z = np.zeros_like(xx)
    # a few octaves of random sinusoids: smooth, seeded, cheap
    for octave in range(4):
        k = (2.0 ** octave) * 2.0 * np.pi / max(size)
        amp = relief / (2.0 ** octave)
        for _ in range(3):
            th = rng.uniform(0, 2 * np.pi)
            ph = rng.uniform(0, 2 * np.pi)
            z += amp / 3.0 * np.sin(k * (np.cos(th) * xx + np.sin(th) * yy) + ph)
    verts = np.column_stack([xx.ravel(), yy.ravel(), z.ravel()])
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    # winding so that face normals point up (-z in NED)
    faces = np.concatenate([np.column_stack([a, d, b]), np.column_stack([b, d, c])])
    return trimesh.Trimesh(verts, faces, process=False)


def _primitive(doc: Doc, t: Mapping[str, Any], kind: str, where: str) -> trimesh.Trimesh:
    if kind == "box":
        size = vector(doc, t, "size_m", 3, where)
        if min(size) <= 0:
            raise doc.error(f"{where}.size_m", "box sizes must be > 0")
        return trimesh.creation.box(extents=size)
    if kind == "sphere":
        r = number(doc, t, "radius_m", where, lo=1e-6)
        sub = int(number(doc, t, "subdivisions", where, 3.0, lo=0, hi=7))
        return trimesh.creation.icosphere(subdivisions=sub, radius=r)
    if kind == "cylinder":
        r = number(doc, t, "radius_m", where, lo=1e-6)
        h = number(doc, t, "height_m", where, lo=1e-6)
        sec = int(number(doc, t, "sections", where, 32.0, lo=3, hi=4096))
        return trimesh.creation.cylinder(radius=r, height=h, sections=sec)
    if kind == "plane":
        size = vector(doc, t, "size_m", 2, where)
        sx, sy = size[0] / 2, size[1] / 2
        v = np.array([[-sx, -sy, 0.0], [sx, -sy, 0.0], [sx, sy, 0.0], [-sx, sy, 0.0]])
        return trimesh.Trimesh(v, np.array([[0, 3, 1], [1, 3, 2]]), process=False)  # normal up (-z)
    if kind == "terrain":
        return _terrain(doc, t, where)
    raise doc.error(f"{where}.primitive", f"unknown primitive {kind!r}; one of {', '.join(PRIMITIVES)}")


def _part_material(geom: trimesh.Trimesh) -> str | None:
    mat = getattr(getattr(geom, "visual", None), "material", None)
    name = getattr(mat, "name", None)
    return str(name) if name else None


def _load_mesh_parts(doc: Doc, path: Path, where: str) -> list[tuple[str, str | None, trimesh.Trimesh]]:
    """Every (node name, material name, mesh in the file's frame) of a mesh file."""
    try:
        loaded: Any = trimesh.load(str(path), force="scene", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise doc.error(f"{where}.mesh", f"cannot load mesh {path.name}: {exc}") from None
    parts: list[tuple[str, str | None, trimesh.Trimesh]] = []
    for node in loaded.graph.nodes_geometry:
        transform, geom_name = loaded.graph[node]
        geom = loaded.geometry[geom_name]
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        g = geom.copy()
        g.apply_transform(transform)
        parts.append((str(node), _part_material(geom) or str(geom_name), g))
    if not parts:
        raise doc.error(f"{where}.mesh", f"mesh file {path.name} holds no triangles")
    return parts


def _load_objects(doc: Doc, mats: Mapping[str, Material], warnings: list[str]) -> list[WorldObject]:
    raw = doc.data.get("objects", [])
    if not isinstance(raw, list):
        raise doc.error("objects", "expected an array of tables: [[objects]]")
    out: list[WorldObject] = []
    names: set[str] = set()
    for i, t in enumerate(raw):
        where = f"objects.{i}"
        t = _table(doc, t, where)
        check_keys(doc, t, _OBJECT_KEYS, where)
        name = str(require(doc, t, "name", where))
        where = f"objects.{name}"
        if name in names:
            raise doc.error(where, f"duplicate object name {name!r}")
        names.add(name)
        if ("mesh" in t) == ("primitive" in t):
            raise doc.error(where, "an object needs exactly one of 'mesh' or 'primitive'")
        pose = _pose(doc, t, where)
        scale_raw = t.get("scale", 1.0)
        scale = np.asarray(scale_raw if isinstance(scale_raw, list) else [scale_raw] * 3, dtype=float)
        if scale.shape != (3,) or not np.all(np.isfinite(scale)) or np.any(scale <= 0):
            raise doc.error(f"{where}.scale", f"scale must be a positive number or 3 of them, got {scale_raw!r}")
        place = np.eye(4)
        place[:3, :3] = pose.rotation
        place[:3, 3] = pose.position
        if "primitive" in t:
            mesh = _primitive(doc, t, str(t["primitive"]), where)
            if not np.allclose(scale, 1):
                mesh.apply_scale(scale)
            mesh.apply_transform(place)
            material = _material_ref(doc, mats, require(doc, t, "material", where), f"{where}.material")
            out.append(WorldObject(name, mesh, material, bool(mesh.is_watertight)))
            continue
        path = safe_join(doc.path.parent, t["mesh"], doc, f"{where}.mesh")
        if path.suffix.lower() not in MESH_SUFFIXES:
            raise doc.error(f"{where}.mesh", f"unsupported mesh format {path.suffix!r}; one of {', '.join(MESH_SUFFIXES)}")
        up = str(t.get("up_axis", "y" if path.suffix.lower() in (".glb", ".gltf") else "z"))
        if up not in _UP_AXES:
            raise doc.error(f"{where}.up_axis", f"up_axis must be one of {', '.join(_UP_AXES)}, got {up!r}")
        to_ned = np.eye(4)
        to_ned[:3, :3] = _UP_AXES[up] @ np.diag(scale)
        mapping = t.get("materials")
        single = t.get("material")
        if mapping is None and single is None:
            raise doc.error(where, "a mesh object needs 'material' (one for all parts) or 'materials' "
                                   "(mesh material or node name -> scenario material, '*' for the rest)")
        if mapping is not None:
            mapping = _table(doc, mapping, f"{where}.materials")
        parts = _load_mesh_parts(doc, path, where)
        groups: dict[str, list[trimesh.Trimesh]] = {}
        for node, matname, g in parts:
            if mapping is not None:
                key = node if node in mapping else matname if matname in mapping else "*" if "*" in mapping else None
                if key is None:
                    raise doc.error(f"{where}.materials",
                                    f"mesh part node {node!r} (material {matname!r}) of {path.name} matches no entry; "
                                    f"entries: {', '.join(mapping)}; add it or a '*' entry")
                mat_name = mapping[key]
                key_where = f"{where}.materials"
            else:
                mat_name, key_where = single, f"{where}.material"
            _material_ref(doc, mats, mat_name, key_where)
            g.apply_transform(to_ned)
            groups.setdefault(str(mat_name), []).append(g)
        multi = len(groups) > 1
        for mat_name, meshes in groups.items():
            mesh = trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]  # type: ignore[assignment]
            if np.linalg.det(to_ned[:3, :3]) < 0:
                mesh.invert()  # a mirroring axis change flips the winding; restore outward normals
            mesh.apply_transform(place)
            watertight = bool(mesh.is_watertight)
            expect = bool(t.get("watertight", True))
            if expect and not watertight:
                msg = (f"{doc.path}: [{where}] mesh {path.name} part {mat_name!r} is not watertight; "
                       "its inside may show in sonar images (set watertight = false if that is intended)")
                warnings.append(msg)
                log.warning(msg)
            out.append(WorldObject(f"{name}/{mat_name}" if multi else name, mesh, mats[mat_name], watertight))
    if not out:
        raise doc.error("objects", "the scenario has no objects")
    return out


def _load_vehicle(doc: Doc) -> VehicleSpec | None:
    if "vehicle" not in doc.data:
        return None
    t = _table(doc, doc.data["vehicle"], "vehicle")
    check_keys(doc, t, _VEHICLE_KEYS, "vehicle")
    xyz = vector(doc, t, "position_m", 3, "vehicle", (0.0, 0.0, 0.0))
    rpy = vector(doc, t, "orientation_deg", 3, "vehicle", (0.0, 0.0, 0.0))
    profile = require(doc, t, "profile", "vehicle")
    check_profile_ref("vehicles", profile, doc.path.parent, doc=doc, key="vehicle.profile")
    return VehicleSpec(str(profile), (xyz[0], xyz[1], xyz[2]),
                       (math.radians(rpy[0]), math.radians(rpy[1]), math.radians(rpy[2])))


def _load_sensors(doc: Doc) -> list[SensorMount]:
    raw = doc.data.get("sensors", [])
    if not isinstance(raw, list):
        raise doc.error("sensors", "expected an array of tables: [[sensors]]")
    out: list[SensorMount] = []
    for i, t in enumerate(raw):
        where = f"sensors.{i}"
        t = _table(doc, t, where)
        check_keys(doc, t, _SENSOR_KEYS, where)
        name = str(require(doc, t, "name", where))
        kind = str(require(doc, t, "kind", where))
        if kind not in SENSOR_KINDS:
            raise doc.error(f"sensors.{name}.kind", f"unknown sensor kind {kind!r}; one of {', '.join(SENSOR_KINDS)}")
        if any(s.name == name for s in out):
            raise doc.error(f"sensors.{name}", f"duplicate sensor name {name!r}")
        profile = require(doc, t, "profile", where)
        check_profile_ref(None, profile, doc.path.parent, doc=doc, key=f"sensors.{name}.profile")
        out.append(SensorMount(name, kind, str(profile), _pose(doc, t, where)))
    return out


def _load_positions(doc: Doc) -> dict[str, NamedPosition]:
    t = _table(doc, doc.data.get("positions", {}), "positions")
    out: dict[str, NamedPosition] = {}
    for name, p in t.items():
        where = f"positions.{name}"
        p = _table(doc, p, where)
        check_keys(doc, p, _POSITION_KEYS, where)
        xyz = vector(doc, p, "position_m", 3, where)
        out[name] = NamedPosition((xyz[0], xyz[1], xyz[2]), math.radians(number(doc, p, "yaw_deg", where, 0.0)),
                                  str(p.get("description", "")))
    return out


def _load_origin(doc: Doc) -> GeodeticOrigin | None:
    """``[world] origin = {lat_deg = .., lon_deg = .., alt_m = ..}`` (alt_m optional, 0)."""
    if "world" not in doc.data:
        return None
    t = _table(doc, doc.data["world"], "world")
    check_keys(doc, t, _WORLD_KEYS, "world")
    if "origin" not in t:
        return None
    o = _table(doc, t["origin"], "world.origin")
    check_keys(doc, o, _ORIGIN_KEYS, "world.origin")
    return GeodeticOrigin(number(doc, o, "lat_deg", "world.origin", lo=-90.0, hi=90.0),
                          number(doc, o, "lon_deg", "world.origin", lo=-180.0, hi=180.0),
                          number(doc, o, "alt_m", "world.origin", 0.0, lo=-500.0, hi=9000.0))


def load_scenario(path: Path | str) -> Scenario:
    """Read and validate a scenario file; meshes are loaded and placed in NED.

    Raises :class:`ConfigError` (file, line, key, and the closest valid key for typos).
    """
    doc = load_toml(path)
    check_keys(doc, doc.data, _TOP_KEYS, "")
    warnings: list[str] = []
    water = _load_water(doc)
    mats = _load_materials(doc)
    objects = _load_objects(doc, mats, warnings)
    seed = number(doc, doc.data, "seed", "", 0.0, lo=0, hi=2**63 - 1)
    return Scenario(
        path=doc.path.resolve(),
        name=str(doc.data.get("name", doc.path.parent.name)),
        description=str(doc.data.get("description", "")),
        seed=int(seed),
        water=water,
        objects=objects,
        vehicle=_load_vehicle(doc),
        sensors=_load_sensors(doc),
        positions=_load_positions(doc),
        raw=doc.data,
        warnings=warnings,
        origin=_load_origin(doc),
    )


__all__ = ["ConfigError", "DEFAULT_ORIGIN", "GeodeticOrigin", "NamedPosition", "Scenario", "SensorMount", "VehicleSpec", "load_scenario"]
