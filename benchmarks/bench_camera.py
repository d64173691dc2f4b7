"""Camera frames/s at 640 x 480 on one core, and the sonar fan picture's rendering time.

Scenes: the paper's water tank (a floor and a 0.5 x 0.35 x 0.3 m cuboid, the
camera 1.2 m above the floor tilted 45 deg down) and a seabed heightfield of
more than 100k triangles. Prints figures; never passes or fails.

    .venv/bin/python benchmarks/bench_camera.py
"""

from __future__ import annotations

import math
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})   # one core, before Embree starts

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from hilsim import viz  # noqa: E402
from hilsim.sim.camera import Camera, CameraLight, CameraProfile, load_camera_profile  # noqa: E402
from hilsim.sim.geometry import Pose  # noqa: E402
from hilsim.sim.world import Material, Water, World, WorldObject  # noqa: E402

CONCRETE = Material("concrete", 8.0e6, (0.55, 0.55, 0.5), optical_absorption=0.2)
PLASTIC = Material("plastic", 3.5e6, (0.85, 0.35, 0.1), optical_absorption=0.1)
WATER = Water(attenuation=(0.35, 0.07, 0.05), color=(0.0, 0.12, 0.18))
FLOOR_Z = 3.0            # [m] NED depth of the tank floor


def tank_world() -> World:
    floor = trimesh.creation.box(extents=(12.0, 8.0, 0.2))
    floor.apply_translation((0.0, 0.0, FLOOR_Z + 0.1))
    cuboid = trimesh.creation.box(extents=(0.5, 0.35, 0.3))
    cuboid.apply_translation((1.2, 0.0, FLOOR_Z - 0.15))
    return World([WorldObject("floor", floor, CONCRETE), WorldObject("cuboid", cuboid, PLASTIC)], water=WATER)


def seabed_world(n: int = 226) -> World:
    """A rolling heightfield of 2 (n - 1)^2 triangles (226 -> 100,450) plus the cuboid."""
    x = np.linspace(-10.0, 10.0, n)
    gx, gy = np.meshgrid(x, x, indexing="ij")
    rng = np.random.default_rng(7)
    gz = FLOOR_Z + 0.3 * np.sin(gx * 0.9) * np.cos(gy * 0.7) + 0.03 * rng.standard_normal(gx.shape)
    verts = np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).ravel()
    faces = np.concatenate([np.column_stack([a, a + n, a + 1]), np.column_stack([a + 1, a + n, a + n + 1])])
    seabed = trimesh.Trimesh(verts, faces, process=False)
    cuboid = trimesh.creation.box(extents=(0.5, 0.35, 0.3))
    cuboid.apply_translation((1.2, 0.0, FLOOR_Z - 0.5))
    return World([WorldObject("seabed", seabed, CONCRETE, watertight=False),
                  WorldObject("cuboid", cuboid, PLASTIC)], water=WATER)


def time_it(fn, seconds: float = 2.0, min_runs: int = 5) -> list[float]:
    fn()                                                          # warm up (tables, caches)
    out: list[float] = []
    t_end = time.perf_counter() + seconds
    while len(out) < min_runs or time.perf_counter() < t_end:
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def report(label: str, ts: list[float]) -> None:
    med = statistics.median(ts)
    print(f"  {label:<46s} {1.0 / med:6.1f} frames/s  (median {med * 1e3:6.1f} ms, best {min(ts) * 1e3:6.1f} ms,"
          f" {len(ts)} runs)")


def main() -> None:
    print(f"camera benchmark, 640 x 480, one core (affinity {sorted(os.sched_getaffinity(0))})")
    pose = Pose.from_xyz_rpy((0.0, 0.0, FLOOR_Z - 1.2), (0.0, math.radians(-45.0), 0.0))
    tank = load_camera_profile(ROOT / "devices/cameras/tank_camera.toml")
    low = load_camera_profile(ROOT / "devices/cameras/low_light.toml")
    shadows = CameraProfile(**{**low.__dict__, "name": "low_light+shadows",
                               "light": CameraLight(**{**low.light.__dict__, "shadows": True})})
    worlds = {"tank": tank_world(), "seabed": seabed_world()}
    for wname, world in worlds.items():
        print(f"scene {wname}: {world.triangles.shape[0]:,} triangles")
        for prof in (tank, low, shadows):
            cam = Camera(prof)
            frame = cam.render(world, pose)
            report(f"{prof.name} ({'paper model' if prof.paper_model else 'lit, attenuated'})",
                   time_it(lambda: cam.render(world, pose)))
        print(f"  pixels per object: {frame.counts}")

    print("sonar fan picture (DIDSON HF: 512 samples x 96 beams, 29 deg, 0.83-5.83 m)")
    az = np.radians(-14.5 + (np.arange(96) + 0.5) * 29.0 / 96)
    img = np.random.default_rng(1).integers(0, 256, (512, 96), dtype=np.uint8)
    for interp in ("bilinear", "nearest"):
        t0 = time.perf_counter()
        first = viz.sonar_fan_image(img, az, 0.83, 5.83, size_px=480, interpolation=interp)
        t_first = time.perf_counter() - t0
        ts = time_it(lambda: viz.sonar_fan_image(img, az, 0.83, 5.83, size_px=480, interpolation=interp), 1.0)
        print(f"  {interp:<9s} {first.size[0]} x {first.size[1]} px: first (builds the table) "
              f"{t_first * 1e3:6.1f} ms, then median {statistics.median(ts) * 1e3:5.2f} ms")


if __name__ == "__main__":
    main()
