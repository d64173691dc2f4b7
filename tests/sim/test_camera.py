"""The camera model against geometry computed here, independently of hilsim.sim.camera.

Every expected pixel, distance and colour below comes from the pinhole and
shading formulas written out in this file (the module docstring of
hilsim.sim.camera states them), not from calling the code under test.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings, strategies as st
from scipy.spatial import ConvexHull

from hilsim.config import ConfigError
from hilsim.sim.camera import Camera, CameraLight, CameraProfile, load_camera_profile
from hilsim.sim.geometry import Pose
from hilsim.sim.state import VehicleState
from hilsim.sim.world import Material, Water, World, WorldObject

ROOT = Path(__file__).resolve().parents[2]
BLACK_WATER = Water(attenuation=(0.35, 0.07, 0.05), color=(0.0, 0.0, 0.0))


# ---- independent helpers -------------------------------------------------------------------

def rot_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """body -> world rotation, written out element by element (Z-Y-X, NED)."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def pinhole(points: np.ndarray, origin: np.ndarray, r: np.ndarray, w: int, h: int, hfov: float,
            vfov: float | None = None) -> np.ndarray:
    """(n, 2) continuous pixel coordinates: u = w/2 + fx y/x, v = h/2 + fy z/x in the camera frame."""
    fx = (w / 2) / math.tan(hfov / 2)
    fy = fx if vfov is None else (h / 2) / math.tan(vfov / 2)
    pc = (points - origin) @ r          # rows: R^T (p - o)
    assert np.all(pc[:, 0] > 0)
    return np.column_stack([w / 2 + fx * pc[:, 1] / pc[:, 0], h / 2 + fy * pc[:, 2] / pc[:, 0]])


def ray_dir_cam(u: np.ndarray, v: np.ndarray, w: int, h: int, hfov: float) -> np.ndarray:
    """Unit camera-frame direction through the centre of pixel (u, v) (integer indices)."""
    f = (w / 2) / math.tan(hfov / 2)
    d = np.stack([np.ones_like(u, dtype=float), (u + 0.5 - w / 2) / f, (v + 0.5 - h / 2) / f], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def box_corners(centre, size, r_box=np.eye(3)) -> np.ndarray:
    s = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * np.asarray(size) / 2
    return s @ np.asarray(r_box).T + np.asarray(centre)


def box(name, centre, size, color=(0.5, 0.5, 0.5), absorption=0.0, r_box=np.eye(3)) -> WorldObject:
    m = trimesh.creation.box(extents=size)
    tf = np.eye(4)
    tf[:3, :3] = r_box
    tf[:3, 3] = centre
    m.apply_transform(tf)
    return WorldObject(name, m, Material(name, 3.5e6, color, optical_absorption=absorption))


def wall(name, x, color, half=20.0) -> WorldObject:
    """A thick wall whose near face is the plane x = ``x`` (facing -x, towards the origin)."""
    return box(name, (x + 0.5, 0.0, 0.0), (1.0, 2 * half, 2 * half), color)


def u8(x) -> np.ndarray:
    return np.floor(np.clip(np.asarray(x, dtype=float), 0, 1) * 255 + 0.5).astype(np.uint8)


def profile(**kw) -> CameraProfile:
    base = dict(name="test", width=160, height=120, hfov=math.radians(60))
    base.update(kw)
    return CameraProfile(**base)  # type: ignore[arg-type]


# ---- 1. pinhole footprint and colour ---------------------------------------------------------

@pytest.mark.parametrize("vfov_deg", [None, 40.0])
def test_box_lands_where_the_pinhole_projection_predicts(vfov_deg):
    w_px, h_px, hfov = 200, 150, math.radians(60)
    vfov = None if vfov_deg is None else math.radians(vfov_deg)
    origin = np.array([1.0, -0.5, 0.3])
    rpy = (0.1, -0.2, 0.3)
    r_cam = rot_zyx(*rpy)
    # a tilted box about 4 m ahead, a little right and below the axis
    centre = origin + r_cam @ np.array([4.0, 0.4, 0.3])
    size = (0.6, 0.9, 0.5)
    r_box = rot_zyx(0.2, 0.3, -0.5)
    color = (0.8, 0.25, 0.1)
    water = Water(color=(0.0, 0.1, 0.2))
    world = World([box("cuboid", centre, size, color, r_box=r_box)], water=water)
    cam = Camera(profile(width=w_px, height=h_px, hfov=hfov, vfov=vfov))
    pose = Pose(origin, r_cam)
    frame = cam.render(world, pose)

    uv = pinhole(box_corners(centre, size, r_box), origin, r_cam, w_px, h_px, hfov, vfov)
    mask = frame.object == 0
    rows, cols = np.nonzero(mask)
    # pixel i is inside when its centre i + 0.5 is inside the footprint
    exp_cols = (math.ceil(uv[:, 0].min() - 0.5), math.floor(uv[:, 0].max() - 0.5))
    exp_rows = (math.ceil(uv[:, 1].min() - 0.5), math.floor(uv[:, 1].max() - 0.5))
    assert abs(cols.min() - exp_cols[0]) <= 1 and abs(cols.max() - exp_cols[1]) <= 1
    assert abs(rows.min() - exp_rows[0]) <= 1 and abs(rows.max() - exp_rows[1]) <= 1
    # the footprint is the convex hull of the corners: its area in pixels, within a 1 px rim
    hull = ConvexHull(uv)
    assert abs(mask.sum() - hull.volume) <= hull.area + 4   # volume = area, area = perimeter in 2-D
    # the paper's model: the material colour exactly, the water colour elsewhere
    assert np.all(frame.rgb[mask] == u8(color))
    assert np.all(frame.rgb[~mask] == u8(water.color))
    assert frame.counts == {"cuboid": int(mask.sum())}
    # Camera.project is the same model
    np.testing.assert_allclose(cam.project(box_corners(centre, size, r_box), pose), uv, atol=1e-9)


def test_project_marks_points_behind_the_camera():
    cam = Camera(profile())
    uv = cam.project(np.array([[-1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]), Pose())
    assert np.all(np.isnan(uv[0]))
    np.testing.assert_allclose(uv[1], [80.0, 60.0])


def test_starboard_is_image_right_and_down_is_image_bottom():
    """Vehicle heading east: a box to the south (starboard) appears right, a deeper box lower."""
    state = VehicleState(position=np.array([0.0, 0.0, 2.0]), attitude=np.array([0.0, 0.0, math.pi / 2]))
    world = World([box("stbd", (-1.0, 5.0, 2.0), (0.3, 0.3, 0.3)),     # south of the east-going vehicle
                   box("deep", (0.0, 5.0, 3.0), (0.3, 0.3, 0.3))])      # below the axis
    frame = Camera(profile()).sample(world, state, Pose())
    cols_s = np.nonzero(frame.object == 0)[1]
    rows_d = np.nonzero(frame.object == 1)[0]
    assert cols_s.min() > 80 and rows_d.min() > 60


def test_mount_tilted_45_deg_down_looks_at_the_point_45_deg_below_ahead():
    state = VehicleState(time=3.5, position=np.array([0.0, 0.0, 1.0]), attitude=np.zeros(3))
    mount = Pose.from_xyz_rpy((0.2, 0.0, 0.1), (0.0, math.radians(-45.0), 0.0))
    # the camera sits at (0.2, 0, 1.1); 1 m ahead and 1 m down of it is (1.2, 0, 2.1)
    world = World([box("target", (1.2, 0.0, 2.1), (0.1, 0.1, 0.1))])
    cam = Camera(profile())
    frame = cam.sample(world, state, mount)
    rows, cols = np.nonzero(frame.object == 0)
    assert abs(rows.mean() + 0.5 - 60) < 1.0 and abs(cols.mean() + 0.5 - 80) < 1.0
    assert frame.time == 3.5
    np.testing.assert_allclose(frame.pose.position, [0.2, 0.0, 1.1])


# ---- 2. occlusion and depth ------------------------------------------------------------------

@pytest.mark.parametrize("order", [("near", "far"), ("far", "near")])
def test_nearer_object_hides_a_farther_one_whatever_the_object_order(order):
    objs = {"near": box("near", (3.0, 0.0, 0.0), (0.4, 0.6, 0.6), (1.0, 0.0, 0.0)),
            "far": box("far", (6.0, 0.3, 0.0), (0.4, 1.2, 1.2), (0.0, 0.0, 1.0))}
    world = World([objs[n] for n in order])
    cam = Camera(profile())
    frame = cam.render(world, Pose())
    near, far = order.index("near"), order.index("far")
    # pixels whose centres fall well inside the near box's front face are all the near box
    uv = pinhole(box_corners((3.0, 0.0, 0.0), (0.4, 0.6, 0.6))[[0, 1, 2, 3]], np.zeros(3), np.eye(3),
                 160, 120, math.radians(60))
    u0, u1 = math.ceil(uv[:, 0].min() - 0.5) + 1, math.floor(uv[:, 0].max() - 0.5) - 1
    v0, v1 = math.ceil(uv[:, 1].min() - 0.5) + 1, math.floor(uv[:, 1].max() - 0.5) - 1
    inner = frame.object[v0:v1 + 1, u0:u1 + 1]
    assert inner.size > 100 and np.all(inner == near)
    assert np.all(frame.rgb[v0:v1 + 1, u0:u1 + 1] == (255, 0, 0))
    # the far box shows around the near one, never inside its footprint
    assert frame.counts["far"] > 0 and np.all(frame.object[frame.object == far] == far)
    assert np.all(frame.depth[frame.object == near] < 3.0) and np.all(frame.depth[frame.object == far] > 5.7)


def test_depth_is_the_distance_along_each_pixel_ray():
    d = 2.5
    world = World([wall("wall", d, (0.5, 0.5, 0.5))])
    w_px, h_px, hfov = 160, 120, math.radians(60)
    frame = Camera(profile(width=w_px, height=h_px, hfov=hfov)).render(world, Pose())
    v, u = np.mgrid[0:h_px, 0:w_px]
    cos_angle = ray_dir_cam(u, v, w_px, h_px, hfov)[..., 0]      # angle to the optical axis
    np.testing.assert_allclose(frame.depth, d / cos_angle, rtol=2e-6)
    assert frame.depth.dtype == np.float32
    # near the centre the four middle pixels are within half a pixel's angle of d
    assert np.all(np.abs(frame.depth[59:61, 79:81] - d) < 1e-3)


def test_misses_are_inf_and_minus_one_and_match_world_cast():
    world = World([box("b", (3.0, 0.0, 0.0), (0.5, 0.5, 0.5))])
    pose = Pose.from_xyz_rpy((0.0, 0.1, -0.1), (0.0, 0.05, -0.02))
    cam = Camera(profile(width=64, height=48))
    frame = cam.render(world, pose)
    dirs = cam.ray_directions.reshape(-1, 3) @ pose.rotation.T
    hits = world.cast(np.tile(pose.position, (dirs.shape[0], 1)), dirs)
    np.testing.assert_array_equal(frame.object.ravel(), hits.obj)
    np.testing.assert_allclose(frame.depth.ravel(), hits.t, rtol=1e-6)
    assert np.all(np.isinf(frame.depth[frame.object == -1]))
    assert 0 < (frame.object == 0).sum() < frame.object.size


def test_range_clipping():
    world = World([wall("wall", 2.0, (1.0, 1.0, 1.0))])
    frame = Camera(profile(max_range=1.5)).render(world, Pose())
    assert np.all(frame.object == -1) and np.all(np.isinf(frame.depth))
    frame = Camera(profile(min_range=5.0)).render(world, Pose())   # beyond the 1 m thick wall
    assert np.all(frame.object == -1)
    # a near clip in front of the wall changes nothing: depth is still from the camera
    clipped, full = Camera(profile(min_range=1.0)).render(world, Pose()), Camera(profile()).render(world, Pose())
    np.testing.assert_allclose(clipped.depth, full.depth, rtol=1e-5)


# ---- 3. Beer-Lambert, absorption, the light --------------------------------------------------

def test_beer_lambert_scales_each_channel_by_exp_minus_c_d():
    color = np.array([0.9, 0.8, 0.7])
    k = np.array(BLACK_WATER.attenuation)
    cam_on = Camera(profile(attenuation=True))
    cam_off = Camera(profile())
    v, u = np.mgrid[0:120, 0:160]
    cos_angle = ray_dir_cam(u, v, 160, 120, math.radians(60))[..., 0]
    centre = {}
    for d in (1.0, 4.0):
        world = World([wall("wall", d, tuple(color))], water=BLACK_WATER)
        on, off = cam_on.render(world, Pose()), cam_off.render(world, Pose())
        assert np.all(off.rgb == u8(color))
        dist = d / cos_angle
        expected = color[None, None, :] * np.exp(-k[None, None, :] * dist[..., None])
        assert np.abs(on.rgb.astype(int) - u8(expected).astype(int)).max() <= 1
        centre[d] = on.rgb[60, 80].astype(float)
    # between two distances the ratio is exp(-c (d2 - d1)) per channel (centre pixel, 1 LSB)
    ratio = centre[4.0] / centre[1.0]
    assert np.all(np.abs(ratio - np.exp(-k * 3.0)) <= 2.0 / centre[1.0])


def test_attenuation_blends_toward_the_water_colour():
    color, water = np.array([1.0, 0.2, 0.0]), Water(attenuation=(0.5, 0.2, 0.1), color=(0.0, 0.3, 0.6))
    world = World([wall("wall", 3.0, tuple(color))], water=water)
    frame = Camera(profile(attenuation=True)).render(world, Pose())
    v, u = np.mgrid[0:120, 0:160]
    dist = 3.0 / ray_dir_cam(u, v, 160, 120, math.radians(60))[..., 0]
    tr = np.exp(-np.array(water.attenuation)[None, None, :] * dist[..., None])
    expected = color * tr + np.array(water.color) * (1 - tr)
    assert np.abs(frame.rgb.astype(int) - u8(expected).astype(int)).max() <= 1
    # far away the picture tends to the water colour; where nothing is hit it is the water colour
    far = Camera(profile(attenuation=True)).render(World([wall("wall", 200.0, tuple(color))], water=water),
                                                   Pose())
    assert np.abs(far.rgb.astype(int) - u8(water.color).astype(int)).max() <= 1


def test_absorption_and_ambient_scale_the_reflected_colour():
    color, a = (0.8, 0.6, 0.4), 0.25
    world = World([wall("wall", 2.0, color)])
    world.objects[0] = WorldObject("wall", world.objects[0].mesh, Material("m", 3e6, color, optical_absorption=a))
    world.rebuild()
    off = Camera(profile()).render(world, Pose())
    assert np.all(off.rgb == u8(color))                       # absorption is off by default
    on = Camera(profile(absorption=True, ambient=0.5)).render(world, Pose())
    assert np.all(np.abs(on.rgb.astype(int) - u8(np.array(color) * (1 - a) * 0.5).astype(int)) <= 1)


def lit_profile(**kw) -> CameraProfile:
    light = kw.pop("light", CameraLight(enabled=True, intensity=0.8, cone_half_angle=math.radians(60)))
    return profile(ambient=0.0, light=light, **kw)


def test_light_inverse_square_lambert_and_cone():
    color = np.array([1.0, 0.9, 0.5])
    w_px, h_px, hfov = 160, 120, math.radians(60)
    v, u = np.mgrid[0:h_px, 0:w_px]
    dcam = ray_dir_cam(u, v, w_px, h_px, hfov)
    cone = math.radians(20)
    cam = Camera(lit_profile(light=CameraLight(True, 0.8, (0.0, 0.0, 0.0), cone)))
    centre = {}
    for d in (1.0, 1.7):
        frame = cam.render(World([wall("wall", d, tuple(color))]), Pose())
        # light at the camera, surface facing it: E = I cos / r^2 with cos = d_x, r = d / d_x
        ux = dcam[..., 0]
        e = 0.8 * ux ** 3 / d ** 2
        in_cone = np.arccos(ux) <= cone
        expected = color[None, None, :] * (e * in_cone)[..., None]
        assert np.abs(frame.rgb.astype(int) - u8(expected).astype(int)).max() <= 1
        assert np.all(frame.rgb[~in_cone] == 0) and np.all(frame.rgb[in_cone].max(axis=1) > 0)
        centre[d] = frame.rgb[60, 80].astype(float)
    # inverse square between the two distances (red channel, 1 LSB of quantisation each)
    assert abs(centre[1.7][0] / centre[1.0][0] - (1.0 / 1.7) ** 2) < 2.0 / centre[1.0][0]


def test_lighting_is_two_sided():
    """A quad wound so its normal points away from the camera is lit like one facing it."""
    verts = np.array([[1.5, -5.0, -5.0], [1.5, 5.0, -5.0], [1.5, 5.0, 5.0], [1.5, -5.0, 5.0]])
    away = trimesh.Trimesh(verts, [[0, 1, 2], [0, 2, 3]], process=False)
    toward = trimesh.Trimesh(verts, [[0, 2, 1], [0, 3, 2]], process=False)
    assert away.face_normals[0, 0] > 0.9 and toward.face_normals[0, 0] < -0.9
    cam = Camera(lit_profile(light=CameraLight(True, 1.0, (0.0, 0.2, 0.1), math.radians(60))))
    frames = [cam.render(World([WorldObject("q", m, Material("m", 3e6, (1.0, 1.0, 1.0)))]), Pose())
              for m in (away, toward)]
    assert frames[0].rgb.max() > 100
    assert np.array_equal(frames[0].rgb, frames[1].rgb)


def test_offset_light_on_a_tilted_plane_with_attenuation():
    """The full shading formula, evaluated here for a plane at 30 deg and a light off the axis."""
    color = np.array([0.9, 0.9, 0.9])
    water = Water(attenuation=(0.3, 0.1, 0.05), color=(0.05, 0.1, 0.15))
    r_plane = rot_zyx(0.0, 0.0, math.radians(30))               # plane turned about the vertical
    n_plane = r_plane @ np.array([-1.0, 0.0, 0.0])
    p0 = np.array([2.0, 0.0, 0.0])
    world = World([box("plane", p0 + r_plane @ np.array([0.25, 0.0, 0.0]), (0.5, 8.0, 8.0), tuple(color),
                       r_box=r_plane)], water=water)
    offset = np.array([0.0, 0.3, -0.2])
    prof = profile(ambient=0.1, attenuation=True,
                   light=CameraLight(True, 1.5, tuple(offset), math.radians(50)))
    frame = Camera(prof).render(world, Pose())
    v, u = np.mgrid[0:120, 0:160]
    dcam = ray_dir_cam(u, v, 160, 120, math.radians(60))
    t = ((p0 @ n_plane) / (dcam @ n_plane))                     # ray-plane distance
    p = dcam * t[..., None]
    to_l = offset - p
    r_l = np.linalg.norm(to_l, axis=-1)
    cos_i = np.clip((to_l @ n_plane) / r_l, 0, None)
    in_cone = (-to_l[..., 0] / r_l) >= math.cos(math.radians(50))
    k = np.array(water.attenuation)
    e = 1.5 * cos_i * in_cone / r_l ** 2
    refl = color * (0.1 + e[..., None] * np.exp(-k * r_l[..., None]))
    tr = np.exp(-k * t[..., None])
    expected = refl * tr + np.array(water.color) * (1 - tr)
    np.testing.assert_allclose(frame.depth, t, rtol=1e-5)
    assert np.abs(frame.rgb.astype(int) - u8(expected).astype(int)).max() <= 1


def test_shadows_block_the_light():
    light = CameraLight(True, 2.0, (0.0, 0.5, 0.0), math.radians(80), shadows=True)
    objs = [wall("wall", 3.0, (1.0, 1.0, 1.0)), box("blocker", (1.5, 0.0, 0.0), (0.2, 0.2, 0.2))]
    target = np.array([[3.0, -0.5, 0.0]])       # segment to the light crosses (1.5, 0, 0)
    cam = Camera(lit_profile(light=light))
    u, v = (np.floor(cam.project(target, Pose())[0])).astype(int)
    shadowed = cam.render(World(objs), Pose())
    assert shadowed.object[v, u] == 0 and np.all(shadowed.rgb[v, u] == 0)
    lit = Camera(lit_profile(light=CameraLight(True, 2.0, (0.0, 0.5, 0.0), math.radians(80)))).render(
        World(objs), Pose())
    assert lit.rgb[v, u].min() > 20
    # away from the blocker's shadow both agree
    assert np.array_equal(shadowed.rgb[5, 5], lit.rgb[5, 5])


# ---- 5. profiles -----------------------------------------------------------------------------

def test_bundled_profiles_load_in_si():
    tank = load_camera_profile(ROOT / "devices/cameras/tank_camera.toml")
    assert (tank.width, tank.height) == (640, 480)
    assert tank.hfov == pytest.approx(math.radians(60))
    assert tank.paper_model and not tank.light.enabled
    # square pixels: vfov from the aspect ratio
    assert math.tan(tank.vertical_fov / 2) == pytest.approx(math.tan(tank.hfov / 2) * 480 / 640)
    low = load_camera_profile(ROOT / "devices/cameras/low_light.toml")
    assert low.light.enabled and low.attenuation and not low.paper_model
    assert low.light.cone_half_angle == pytest.approx(math.radians(40))
    assert len(low.light.offset) == 3


GOOD = """
[camera]
name = "t"
width = { value = 64, unit = "px", source = "test" }
height = { value = 48, unit = "px", source = "test" }
horizontal_fov = { value = 90, unit = "deg", source = "test" }
frame_rate = { value = 5, unit = "Hz", source = "test" }
"""


def test_profile_minimal_and_vertical_fov(tmp_path):
    p = tmp_path / "cam.toml"
    p.write_text(GOOD + 'vertical_fov = { value = 1.0, unit = "rad", source = "test" }\n')
    prof = load_camera_profile(p)
    assert prof.hfov == pytest.approx(math.pi / 2) and prof.vfov == 1.0 and prof.frame_rate == 5.0
    assert prof.fy == pytest.approx(24 / math.tan(0.5))


@pytest.mark.parametrize("text, key", [
    (GOOD + 'horizontal_fv = { value = 1, unit = "rad", source = "x" }\n', "camera.horizontal_fv"),
    (GOOD.replace('unit = "px", source = "test" }\nheight', 'unit = "m", source = "test" }\nheight'),
     "camera.width"),
    (GOOD.replace("value = 64", "value = 64.5"), "camera.width"),
    (GOOD.replace('horizontal_fov = { value = 90, unit = "deg"', 'horizontal_fov = { value = 90, unit = "m"'),
     "camera.horizontal_fov"),
    (GOOD.replace("value = 90", "value = 180"), "camera.horizontal_fov"),
    (GOOD.replace("value = 5,", "value = 0,"), "camera.frame_rate"),
    (GOOD + "attenuation = 1\n", "camera.attenuation"),
    (GOOD + "[light]\nenabled = true\n", "light"),
    (GOOD + '[light]\nenabled = true\nintensity = { value = 1, unit = "1", source = "x" }\n'
            'cone_half_angle = { value = 30, unit = "deg", source = "x" }\n'
            'offset = { value = [0, 1], unit = "m", source = "x" }\n', "light.offset"),
    (GOOD + "[lamp]\nenabled = true\n", "lamp"),
])
def test_broken_profile_names_the_key(tmp_path, text, key):
    p = tmp_path / "broken.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_camera_profile(p)
    assert exc.value.key == key
    assert str(p) in str(exc.value) and f"[{key}]" in str(exc.value)
    assert exc.value.line is not None


def test_profile_dataclass_refuses_nonsense():
    with pytest.raises(ValueError):
        profile(width=0)
    with pytest.raises(ValueError):
        profile(hfov=math.pi)
    with pytest.raises(ValueError):
        CameraLight(True, -1.0)


# ---- the rays and the projection are one model -----------------------------------------------


@settings(max_examples=60, deadline=None)
@given(u=st.integers(0, 63), v=st.integers(0, 47), dist=st.floats(0.1, 50.0),
       rpy=st.tuples(*[st.floats(-3.0, 3.0)] * 3), xyz=st.tuples(*[st.floats(-10.0, 10.0)] * 3),
       vfov=st.one_of(st.none(), st.floats(0.3, 2.0)))
def test_a_point_on_a_pixel_ray_projects_to_that_pixel_centre(u, v, dist, rpy, xyz, vfov):
    cam = Camera(profile(width=64, height=48, hfov=math.radians(75), vfov=vfov))
    pose = Pose(np.array(xyz), rot_zyx(*rpy))
    d = cam.ray_directions[v, u]
    assert abs(np.linalg.norm(d) - 1.0) < 1e-12
    point = pose.position + rot_zyx(*rpy) @ (d * dist)
    np.testing.assert_allclose(cam.project(point[None, :], pose)[0], [u + 0.5, v + 0.5], atol=1e-6)
