"""The optical camera: a pinhole model rendered by primary rays (paper, section 2.3).

The paper's optical model is a z-buffer: every pixel keeps the colour of the
closest surface. Here that result is computed by casting one primary ray per
pixel with the world's Embree caster, which gives the same picture and also the
depth of every pixel.

Camera frame and pixel grid
---------------------------
The camera frame is the sensor frame of its mount, like every body frame in
hilsim: x is the optical axis (forward), +y is image right (starboard), +z is
image down. A pixel is addressed (u, v): u the column (0 at the left), v the
row (0 at the top). Continuous pixel coordinates put the centre of pixel
(u, v) at (u + 0.5, v + 0.5); the principal point is the image centre
(cx, cy) = (width / 2, height / 2). Focal lengths [px]::

    fx = (width / 2) / tan(hfov / 2)
    fy = (height / 2) / tan(vfov / 2)   (= fx when vfov is derived: square pixels)

A point (x, y, z) in the camera frame (x > 0) projects to ``u = cx + fx y / x``,
``v = cy + fy z / x`` (:meth:`Camera.project`), and the ray of pixel (u, v)
leaves the camera along the unit vector of ``(1, (u + 0.5 - cx) / fx,
(v + 0.5 - cy) / fy)`` (:func:`pixel_directions`).

Shading (each effect a switch in the :class:`CameraProfile`)
------------------------------------------------------------
For a pixel whose ray hits an object with colour ``c`` (linear RGB reflectance
in [0, 1]) at distance ``t`` [m]::

    reflected = c * (1 - a) * (ambient + E)          a = optical_absorption if ``absorption`` else 0
    E         = I * cone * max(0, n.l) / r_l^2 * T(r_l)   (light on; 0 otherwise)
    pixel     = reflected * T(t) + water * (1 - T(t))     (``attenuation`` on)
    pixel     = reflected                                  (``attenuation`` off)
    T(d)      = exp(-k d) per channel,  k = Water.attenuation [1/m] (1 when attenuation is off)

``I`` is the light's intensity (the irradiance it gives a surface facing it at
1 m, relative to full white), ``r_l`` the light-to-surface distance [m], ``l``
the unit vector from the surface to the light, ``n`` the hit normal turned to
face the camera, and ``cone`` is 1 inside the light's cone (half-angle about the
camera's optical axis) and 0 outside. With the light off, ambient = 1 and the
other switches off (the defaults), the pixel is exactly the material colour:
the paper's model. Rays that hit nothing show the water colour. Values are
clipped to [0, 1] and stored as ``round(255 * value)`` (linear, no gamma curve).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from numpy.typing import NDArray

from hilsim.config import Doc, check_keys, load_toml, quantity
from hilsim.sim.geometry import F64, Pose
from hilsim.sim.state import VehicleState
from hilsim.sim.world import World

U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]
I16 = NDArray[np.int16]


@dataclass(frozen=True)
class CameraLight:
    """A point light carried by the vehicle, shining along the camera's optical axis.

    enabled: switch. intensity [1]: irradiance on a surface facing the light at
    1 m, relative to full white (falls off as 1 / r^2). offset: (3,) [m] light
    position in the camera frame. cone_half_angle [rad]: surfaces further than
    this from the optical axis (seen from the light) get no light.
    shadows: cast a shadow ray from each lit surface point to the light.
    """

    enabled: bool = False
    intensity: float = 1.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    cone_half_angle: float = math.radians(45.0)
    shadows: bool = False

    def __post_init__(self) -> None:
        if not (self.intensity >= 0.0 and math.isfinite(self.intensity)):
            raise ValueError(f"light intensity must be >= 0, got {self.intensity}")
        if not 0.0 < self.cone_half_angle <= math.pi:
            raise ValueError(f"light cone half-angle must be in (0, pi] rad, got {self.cone_half_angle}")
        if len(self.offset) != 3:
            raise ValueError(f"light offset must have 3 components, got {self.offset}")


@dataclass(frozen=True)
class CameraProfile:
    """What a camera is: resolution, field of view, rate and the optical effects it models.

    width, height [px]; hfov [rad] horizontal field of view; vfov [rad] vertical
    field of view, or None to derive it from square pixels; frame_rate [Hz];
    min_range, max_range [m] clipping distances along the ray; ambient [1]
    uniform illumination (1 = the material colour as is); attenuation: apply
    the scenario water's Beer-Lambert attenuation; absorption: scale reflected
    light by (1 - material optical_absorption); light: see :class:`CameraLight`.
    """

    name: str
    width: int
    height: int
    hfov: float
    vfov: float | None = None
    frame_rate: float = 10.0
    min_range: float = 0.0
    max_range: float = math.inf
    ambient: float = 1.0
    attenuation: bool = False
    absorption: bool = False
    light: CameraLight = field(default_factory=CameraLight)
    source: str = ""

    def __post_init__(self) -> None:
        for k in ("width", "height"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{k} must be a positive integer [px], got {v!r}")
        if not 0.0 < self.hfov < math.pi:
            raise ValueError(f"hfov must be in (0, pi) rad, got {self.hfov}")
        if self.vfov is not None and not 0.0 < self.vfov < math.pi:
            raise ValueError(f"vfov must be in (0, pi) rad, got {self.vfov}")
        if not (self.frame_rate > 0.0 and math.isfinite(self.frame_rate)):
            raise ValueError(f"frame_rate must be > 0 Hz, got {self.frame_rate}")
        if not 0.0 <= self.min_range < self.max_range:
            raise ValueError(f"need 0 <= min_range < max_range, got {self.min_range}, {self.max_range}")
        if not (self.ambient >= 0.0 and math.isfinite(self.ambient)):
            raise ValueError(f"ambient must be >= 0, got {self.ambient}")

    @property
    def fx(self) -> float:
        """Horizontal focal length [px]."""
        return (self.width / 2.0) / math.tan(self.hfov / 2.0)

    @property
    def fy(self) -> float:
        """Vertical focal length [px] (= fx unless vfov is given)."""
        if self.vfov is None:
            return self.fx
        return (self.height / 2.0) / math.tan(self.vfov / 2.0)

    @property
    def vertical_fov(self) -> float:
        """Vertical field of view [rad], given or derived from square pixels."""
        return 2.0 * math.atan((self.height / 2.0) / self.fy)

    @property
    def period(self) -> float:
        """Time between frames [s]."""
        return 1.0 / self.frame_rate

    @property
    def paper_model(self) -> bool:
        """True when every effect beyond the paper is off: pixel = material colour."""
        return not (self.attenuation or self.absorption or self.light.enabled) and self.ambient == 1.0


_TOP_KEYS = ("camera", "light")
_CAMERA_KEYS = ("name", "description", "width", "height", "horizontal_fov", "vertical_fov", "frame_rate",
                "min_range", "max_range", "ambient", "attenuation", "absorption")
_LIGHT_KEYS = ("enabled", "intensity", "offset", "cone_half_angle", "shadows", "description")


def _pixels(doc: Doc, table: Mapping[str, Any], key: str, where: str) -> int:
    """A pixel count written as ``{ value = 640, unit = "px", source = "..." }``."""
    dotted = f"{where}.{key}"
    if key not in table:
        raise doc.error(where, f"missing required key {key!r} (unit px)")
    q = table[key]
    if not isinstance(q, Mapping):
        raise doc.error(dotted, f"expected {{ value = ..., unit = \"px\", source = \"...\" }}, got {q!r}")
    check_keys(doc, q, ("value", "unit", "source", "note"), dotted)
    for k in ("value", "unit", "source"):
        if k not in q:
            raise doc.error(dotted, f"quantity needs {k!r}")
    if q["unit"] != "px":
        raise doc.error(dotted, f"unit {q['unit']!r} is not a unit of px")
    v = q["value"]
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise doc.error(dotted, f"expected a positive whole number of pixels, got {v!r}")
    return int(v)


def _flag(doc: Doc, table: Mapping[str, Any], key: str, where: str, default: bool) -> bool:
    if key not in table:
        return default
    v = table[key]
    if not isinstance(v, bool):
        raise doc.error(f"{where}.{key}", f"expected true or false, got {v!r}")
    return v


def _table(doc: Doc, key: str, required: bool) -> Mapping[str, Any]:
    t = doc.data.get(key)
    if t is None:
        if required:
            raise doc.error(key, f"missing required table [{key}]")
        return {}
    if not isinstance(t, Mapping):
        raise doc.error(key, f"[{key}] must be a table")
    return t


def load_camera_profile(path: Path | str) -> CameraProfile:
    """Read a camera profile (TOML, ``devices/cameras/*.toml``) into SI units.

    Physical values are quantity tables ``{ value, unit, source }``; unknown keys,
    wrong units and out-of-range values raise :class:`hilsim.config.ConfigError`
    naming the file, line and key.
    """
    doc = load_toml(path)
    check_keys(doc, doc.data, _TOP_KEYS, "")
    cam = _table(doc, "camera", True)
    check_keys(doc, cam, _CAMERA_KEYS, "camera")
    lt = _table(doc, "light", False)
    check_keys(doc, lt, _LIGHT_KEYS, "light")
    name = cam.get("name", doc.path.stem)
    if not isinstance(name, str) or not name:
        raise doc.error("camera.name", f"expected a non-empty string, got {name!r}")

    def q(table: Mapping[str, Any], key: str, unit: str, where: str, default: Any = None,
          lo: float | None = None, hi: float | None = None, lo_open: bool = False, length: int | None = None) -> Any:
        v = quantity(doc, table, key, unit, where, default=default, length=length)
        if lo is not None and isinstance(v, float) and (v < lo or (lo_open and v == lo)):
            raise doc.error(f"{where}.{key}", f"{v:g} {unit} must be {'>' if lo_open else '>='} {lo:g} {unit}")
        if hi is not None and isinstance(v, float) and v >= hi:
            raise doc.error(f"{where}.{key}", f"{v:g} {unit} must be < {hi:g} {unit}")
        return v

    width = _pixels(doc, cam, "width", "camera")
    height = _pixels(doc, cam, "height", "camera")
    hfov = q(cam, "horizontal_fov", "rad", "camera", lo=0.0, lo_open=True, hi=math.pi)
    vfov = q(cam, "vertical_fov", "rad", "camera", default=False, lo=0.0, lo_open=True, hi=math.pi)
    rate = q(cam, "frame_rate", "Hz", "camera", lo=0.0, lo_open=True)
    rmin = q(cam, "min_range", "m", "camera", default=0.0, lo=0.0)
    rmax = q(cam, "max_range", "m", "camera", default=math.inf, lo=0.0, lo_open=True)
    if rmax <= rmin:
        raise doc.error("camera.max_range", f"max_range {rmax:g} m must exceed min_range {rmin:g} m")
    ambient = q(cam, "ambient", "1", "camera", default=1.0, lo=0.0)

    enabled = _flag(doc, lt, "enabled", "light", False)
    if enabled:
        for k in ("intensity", "cone_half_angle"):
            if k not in lt:
                raise doc.error("light", f"a light that is enabled needs {k!r}")
    intensity = q(lt, "intensity", "1", "light", default=1.0, lo=0.0)
    cone = q(lt, "cone_half_angle", "rad", "light", default=math.radians(45.0), lo=0.0, lo_open=True,
             hi=math.pi + 1e-12)
    offset = q(lt, "offset", "m", "light", default=(0.0, 0.0, 0.0), length=3)
    light = CameraLight(enabled=enabled, intensity=intensity, offset=tuple(offset), cone_half_angle=cone,
                        shadows=_flag(doc, lt, "shadows", "light", False))
    return CameraProfile(
        name=name, width=width, height=height, hfov=hfov, vfov=None if vfov is False else vfov,
        frame_rate=rate, min_range=rmin, max_range=rmax, ambient=ambient,
        attenuation=_flag(doc, cam, "attenuation", "camera", False),
        absorption=_flag(doc, cam, "absorption", "camera", False),
        light=light, source=str(doc.path),
    )


def pixel_directions(width: int, height: int, fx: float, fy: float) -> F64:
    """Unit ray direction of every pixel centre, in the camera frame.

    width, height [px]; fx, fy [px] focal lengths; principal point at the image
    centre. Returns (height * width, 3) float, row-major: row ``v * width + u``
    is pixel (u, v), direction ∝ ``(1, (u + 0.5 - width/2) / fx, (v + 0.5 - height/2) / fy)``.
    """
    y = (np.arange(width, dtype=np.float64) + 0.5 - width / 2.0) / fx
    z = (np.arange(height, dtype=np.float64) + 0.5 - height / 2.0) / fy
    d = np.empty((height, width, 3))
    d[..., 0] = 1.0
    d[..., 1] = y[None, :]
    d[..., 2] = z[:, None]
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    return d.reshape(-1, 3)


@dataclass(frozen=True)
class CameraFrame:
    """One rendered picture.

    rgb: (h, w, 3) uint8; depth: (h, w) float32 [m] distance along each pixel's
    ray to the surface (inf where nothing is hit); object: (h, w) int16 index into
    ``object_names`` (-1 none); pose: sensor -> world; time [s]; counts: pixels
    per object name (objects that cover no pixel are left out).
    """

    rgb: U8
    depth: F32
    object: I16
    pose: Pose
    time: float
    object_names: tuple[str, ...]
    counts: dict[str, int]


@dataclass(frozen=True)
class _WorldTables:
    """Per-triangle lookups with one extra last row for a miss (triangle -1).

    tri_object: (m + 1,) int16 object index (-1 last); tri_normal_planar: (3, m + 1) float32.
    The source arrays are kept to notice a rebuilt world.
    """

    tri_object: I16
    tri_normal_planar: F32
    tri_object_src: NDArray[np.int64]
    tri_normal_src: F64

    @staticmethod
    def build(world: World) -> "_WorldTables":
        if len(world.objects) > np.iinfo(np.int16).max:
            raise ValueError(f"at most {np.iinfo(np.int16).max} objects, got {len(world.objects)}")
        ob = np.append(world.tri_object, -1).astype(np.int16)
        nrm = np.ascontiguousarray(np.vstack([world.tri_normal.reshape(-1, 3), np.zeros((1, 3))]).T,
                                   dtype=np.float32)
        return _WorldTables(ob, nrm, world.tri_object, world.tri_normal)


def _to_u8(x: NDArray[np.floating[Any]]) -> U8:
    """Values in [0, 1] (clipped) to uint8 ``round(255 x)``."""
    out: U8 = np.clip(x * 255.0 + 0.5, 0.0, 255.0).astype(np.uint8)
    return out


class Camera:
    """A pinhole camera rendering :class:`CameraFrame` s from a :class:`World`.

    The per-pixel ray directions (camera frame) are computed once here; each
    frame only rotates them into the world and casts them.
    """

    def __init__(self, profile: CameraProfile) -> None:
        self.profile = profile
        self.width = profile.width
        self.height = profile.height
        self.fx = profile.fx
        self.fy = profile.fy
        self.cx = profile.width / 2.0
        self.cy = profile.height / 2.0
        self._dirs_cam = pixel_directions(self.width, self.height, self.fx, self.fy)
        self._dirs_planar = np.ascontiguousarray(self._dirs_cam.T, dtype=np.float32)  # (3, n)
        self._tables: _WorldTables | None = None

    def _world_tables(self, world: World) -> "_WorldTables":
        """Per-triangle lookups for ``world``, rebuilt when the world is rebuilt."""
        tb = self._tables
        if tb is None or tb.tri_object_src is not world.tri_object or tb.tri_normal_src is not world.tri_normal:
            tb = _WorldTables.build(world)
            self._tables = tb
        return tb

    @property
    def ray_directions(self) -> F64:
        """(h, w, 3) unit ray directions in the camera frame."""
        return self._dirs_cam.reshape(self.height, self.width, 3)

    def project(self, points_world: F64, pose: Pose) -> F64:
        """Pixel coordinates of world points, by the same pinhole model as :meth:`render`.

        points_world: (n, 3) [m] NED; pose: sensor -> world. Returns (n, 2) float
        (u, v) in continuous pixel coordinates (the centre of pixel (i, j) is
        (i + 0.5, j + 0.5)); NaN for points not in front of the camera (x <= 0).
        Points may project outside [0, width) x [0, height).
        """
        p = pose.inverse().apply(np.asarray(points_world, dtype=float).reshape(-1, 3))
        out = np.full((p.shape[0], 2), np.nan)
        front = p[:, 0] > 0.0
        x = p[front, 0]
        out[front, 0] = self.cx + self.fx * p[front, 1] / x
        out[front, 1] = self.cy + self.fy * p[front, 2] / x
        return out

    def sample(self, world: World, state: VehicleState, mount: Pose) -> CameraFrame:
        """Render from a camera mounted on the vehicle: pose = state.pose @ mount (sensor -> body)."""
        return self.render(world, state.pose @ mount, time=float(state.time))

    def render(self, world: World, pose: Pose, time: float = 0.0) -> CameraFrame:
        """Render one frame from ``pose`` (sensor -> world, NED [m]); ``time`` [s] is stamped on it."""
        prof = self.profile
        h, w = self.height, self.width
        rot = np.asarray(pose.rotation, dtype=np.float64)
        origin = np.asarray(pose.position, dtype=np.float64)
        dirs = self._dirs_cam @ rot.T                           # (n, 3) world frame
        origins = np.broadcast_to(origin, dirs.shape)
        # The world's Embree caster answers the same query as world.cast; calling it
        # directly skips the per-ray object/normal lookups the paper model does not need.
        t, tri = world.caster.intersect(origins, dirs, prof.min_range, prof.max_range)
        tb = self._world_tables(world)
        # np.take rather than fancy indexing: several times faster on 300k rows;
        # mode="wrap" sends a miss (-1) to the tables' last row
        obj = np.take(tb.tri_object, tri, mode="wrap")
        hit = tri >= 0
        n_obj = len(world.objects)
        water = np.asarray(world.water.color, dtype=np.float64)

        if prof.paper_model:
            # the paper's z-buffer colour: a table lookup; the last row is the water
            table = _to_u8(np.vstack([world.obj_color[:n_obj], water[None, :]]))
            rgb = np.take(table, obj, axis=0, mode="wrap")
        else:
            m = int(np.count_nonzero(hit))
            shaded = np.empty((m + 1, 3), dtype=np.uint8)
            shaded[m] = _to_u8(water)
            if m:
                shaded[:m] = _to_u8(self._shade(
                    world, tb, pose, np.compress(hit, self._dirs_planar, axis=1), np.compress(hit, t),
                    np.compress(hit, tri), np.compress(hit, obj))).T
            pos = np.cumsum(hit) - 1                            # row of each hit in ``shaded``
            pos[~hit] = m
            rgb = np.take(shaded, pos, axis=0)

        depth = t.astype(np.float32).reshape(h, w)
        names = tuple(world.object_names)
        counts_arr = np.bincount(np.compress(hit, obj).astype(np.intp), minlength=n_obj)
        counts = {names[i]: int(c) for i, c in enumerate(counts_arr.tolist()) if c}
        return CameraFrame(rgb=rgb.reshape(h, w, 3), depth=depth, object=obj.reshape(h, w), pose=pose,
                           time=time, object_names=names, counts=counts)

    def _shade(self, world: World, tb: "_WorldTables", pose: Pose, d: F32, t64: F64,
               tri: NDArray[np.int64], ob: I16) -> F32:
        """Linear RGB of m hit pixels, planar: (3, m) float32 (see the module docstring).

        d: (3, m) unit ray directions in the camera frame; t64: (m,) hit distances
        [m]; tri, ob: (m,) triangle and object indices. The work is done in the
        camera frame (the normals are rotated there), in float32 and channel-planar
        so every numpy loop runs over m elements: this runs on every pixel of every frame.
        """
        prof = self.profile
        n_obj = len(world.objects)
        refl_obj = np.asarray(world.obj_color[:n_obj], dtype=np.float64)
        if prof.absorption:
            refl_obj = refl_obj * (1.0 - world.obj_optical_absorption[:n_obj])[:, None]
        refl = np.take(np.ascontiguousarray(refl_obj.T, dtype=np.float32), ob, axis=1)  # (3, m)
        t = t64.astype(np.float32)
        k = np.asarray(world.water.attenuation, dtype=np.float32)[:, None]             # (3, 1) [1/m]
        lt = prof.light
        if lt.enabled and lt.intensity > 0.0:
            rot = np.asarray(pose.rotation, dtype=np.float32)
            lpos = np.asarray(lt.offset, dtype=np.float32)[:, None]  # light, camera frame [m]
            to_l = lpos - d * t                                 # (3, m) surface -> light
            r2 = np.einsum("ij,ij->j", to_l, to_l)
            r_l = np.sqrt(r2)
            n = rot.T @ np.take(tb.tri_normal_planar, tri, axis=1)  # (3, m) normals, camera frame
            ndotl = np.einsum("ij,ij->j", n, to_l)              # = r_l cos(incidence)
            back = np.einsum("ij,ij->j", n, d) > 0.0            # normal turned away from the camera
            np.negative(ndotl, out=ndotl, where=back)
            # inside the cone when the angle between the axis (+x) and light -> surface is small
            in_cone = -to_l[0] >= np.float32(math.cos(lt.cone_half_angle) - 1e-6) * r_l
            r2 = np.maximum(r2, np.float32(1e-12))
            e = np.where(in_cone & (ndotl > 0.0),
                         np.float32(lt.intensity) * ndotl / (r2 * r_l), np.float32(0.0))
            if lt.shadows:
                np.negative(n, out=n, where=back[None, :])
                self._shadow(world, pose, e, d, t, n, lpos)
            if prof.attenuation:
                illum = np.float32(prof.ambient) + e * np.exp(-k * r_l)
            else:
                illum = (np.float32(prof.ambient) + e)[None, :]
            out: F32 = refl * illum
        else:
            out = refl * np.float32(prof.ambient)
        if prof.attenuation:
            tr = np.exp(-k * t)
            water = np.asarray(world.water.color, dtype=np.float32)[:, None]
            out = out * tr + water * (1.0 - tr)
        return out

    @staticmethod
    def _shadow(world: World, pose: Pose, e: F32, d: F32, t: F32, n: F32, lpos: F32) -> None:
        """Zero ``e`` (m,) in place where the segment from the surface to the light is blocked.

        d, n: (3, m) ray directions and camera-facing normals (camera frame);
        t: (m,) [m]; lpos: (3, 1) light position, camera frame [m].
        """
        lit = np.flatnonzero(e > 0.0)
        if not lit.size:
            return
        eps = 1e-4                                               # [m] lift off the surface
        start = (d[:, lit] * t[lit] + n[:, lit] * np.float32(eps)).T.astype(np.float64)  # (k, 3)
        seg = lpos[:, 0].astype(np.float64)[None, :] - start
        dist = np.linalg.norm(seg, axis=1)
        ok = dist > 2.0 * eps
        if not ok.any():
            return
        origins = pose.apply(start[ok])
        dirs = pose.apply_dirs(seg[ok] / dist[ok, None])
        # one cast reaching the farthest light; a hit counts only before the ray's own light
        tt, _ = world.caster.intersect(origins, dirs, 0.0, float(dist[ok].max()))
        blocked = np.zeros(lit.size, dtype=bool)
        blocked[np.flatnonzero(ok)] = tt < dist[ok] - eps
        e[lit[blocked]] = 0.0
