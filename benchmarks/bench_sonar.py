"""Imaging-sonar rendering speed: prints figures, never pass/fail.

Run: ``.venv/bin/python benchmarks/bench_sonar.py``. Pins itself to one CPU
core (``os.sched_setaffinity(0, {0})``) and sets the BLAS/OpenMP thread counts
to 1 *before* numpy and Embree start any thread, so the figures are
single-core ones. Frame rates are given from the median frame time and from
the best one: on a shared machine the best is the closer estimate of the
code's own speed, the median of what a loaded machine delivers.

Frames are 96 beams x 512 samples from 96 x 1000 rays (DIDSON HF profile,
the paper's ray count), on two scenes built here:

(a) water tank: a floor slab and a 0.5 m (wide) x 0.35 m (deep) x 0.3 m (tall)
    cuboid, sonar 1.2 m above the floor, tilted 45 deg down, the cuboid's
    front face 0.9 m ahead (24 triangles);
(b) terrain: a seeded noisy heightfield of 2 x 255 x 255 = 130,050 triangles.

For each scene: frames/s with Embree for the paper's literal model, the
artifact-free model (range spreading, realism off) and the full model
(spreading + beam pattern + speckle + noise + absorption); then the same
frame's ray casting with the paper's method (ReferenceCaster, every ray
against every polygon) and trimesh's default engine (TrimeshCaster). Those two
are timed on an evenly spaced subset of the frame's rays when a full frame
would take too long, and extrapolated linearly per ray (their cost is linear
in the ray count); the output says when it did so. Ratios are against Embree
measured in the same run. The full-model frame is also given as a ratio to the
raw cast of its rays (``EmbreeCaster.intersect`` alone), measured interleaved
(cast, frame, cast, frame, ...) so that a load change on a shared machine hits
both alike: best to best, and the median of the per-pair ratios.

``--quick``: only the tuned-allocator Embree rates and the full-frame ratio
(no default-allocator pass, no reference casters), for repeated runs.
"""

from __future__ import annotations

import os

# single core, before anything can start a thread
os.sched_setaffinity(0, {0})
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import ctypes  # noqa: E402
import functools  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Callable  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from hilsim.sim.geometry import Pose  # noqa: E402
from hilsim.sim.raycast_ref import ReferenceCaster, TrimeshCaster  # noqa: E402
from hilsim.sim.sonar import ImagingSonar, SonarSettings, load_sonar_profile  # noqa: E402
from hilsim.sim.world import Material, Water, World, WorldObject  # noqa: E402

CONCRETE = Material("concrete", 8.0e6)
PLASTIC = Material("plastic", 3.5e6)


def tank_scene() -> tuple[list[WorldObject], Pose]:
    """Sensor at the origin; floor top 1.2 m below; cuboid front face 0.9 m ahead."""
    floor = trimesh.creation.box(extents=(10.0, 10.0, 0.1))
    floor.apply_translation((0.0, 0.0, 1.2 + 0.05))
    cuboid = trimesh.creation.box(extents=(0.35, 0.5, 0.3))
    cuboid.apply_translation((0.9 + 0.175, 0.0, 1.2 - 0.15))
    objects = [WorldObject("floor", floor, CONCRETE), WorldObject("cuboid", cuboid, PLASTIC)]
    return objects, Pose.from_xyz_rpy((0.0, 0.0, 0.0), (0.0, math.radians(-45.0), 0.0))


def terrain_scene(n: int = 256) -> tuple[list[WorldObject], Pose]:
    """Seeded rough seabed, 8 m x 8 m, 1.5 m below the sensor (tilted 30 deg down)."""
    rng = np.random.default_rng(0)
    xs = np.linspace(-1.0, 7.0, n)
    ys = np.linspace(-4.0, 4.0, n)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    z = 1.5 + 0.15 * np.sin(1.7 * gx) * np.cos(1.3 * gy) + rng.normal(0.0, 0.01, gx.shape)
    verts = np.stack([gx.ravel(), gy.ravel(), z.ravel()], axis=1)
    i = np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]
    a, b, c, d = i.ravel(), (i + 1).ravel(), (i + n).ravel(), (i + n + 1).ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])  # normals up (-z)
    mesh = trimesh.Trimesh(vertices=verts, faces=faces, process=False)
    return [WorldObject("seabed", mesh, CONCRETE)], Pose.from_xyz_rpy((0.0, 0.0, 0.0), (0.0, math.radians(-30.0), 0.0))


def frame_times(render: Callable[[], object], budget: float = 2.0, min_frames: int = 5) -> tuple[float, float, int]:
    """Median and best seconds per frame over about ``budget`` seconds, and the frame count."""
    render()  # warm up caches
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < min_frames or time.perf_counter() - start < budget:
        t0 = time.perf_counter()
        render()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), min(times), len(times)


def time_call(fn: Callable[[], object], repeat: int = 3) -> float:
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def cast_time(caster_cls: type, tris: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
              s: SonarSettings, max_seconds: float) -> tuple[float, float, int]:
    """Seconds to cast all rays (extrapolated from a subset if needed), set-up seconds, rays timed."""
    t0 = time.perf_counter()
    caster = caster_cls(tris)
    caster.intersect(origins[:1], dirs[:1], s.range_min, s.range_max)  # lazy set-up (trimesh's rtree)
    build = time.perf_counter() - t0
    n = len(origins)
    k = min(n, 96)
    while True:
        step = max(1, n // k)
        sub = slice(0, n, step)
        m = len(origins[sub])
        t0 = time.perf_counter()
        caster.intersect(origins[sub], dirs[sub], s.range_min, s.range_max)
        spent = time.perf_counter() - t0
        if m == n or spent * min(4.0, n / m) > max_seconds / 4:
            return spent * n / m, build, m
        k = min(n, k * 4)


def tune_allocator() -> bool:
    """Ask glibc to keep freed memory instead of unmapping/trimming it after every frame.

    A frame allocates a few dozen 0.8-2.3 MB temporaries. With glibc's default
    thresholds they are returned to the kernel when freed and page-faulted in
    again on the next frame, which on some virtual machines costs more system
    time than the frame's computation. Returns False where mallopt is unavailable.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        return bool(libc.mallopt(m_mmap_threshold, 64 << 20)) and bool(libc.mallopt(m_trim_threshold, 256 << 20))
    except (OSError, AttributeError):
        return False


class Scene:
    """A world, the sensor pose and the sonar with its three settings."""

    def __init__(self, label: str, objects: list[WorldObject], pose: Pose) -> None:
        self.label = label
        self.pose = pose
        self.n_tri = sum(len(o.mesh.faces) for o in objects)
        t0 = time.perf_counter()
        self.world = World(objects, Water())
        self.build = time.perf_counter() - t0
        profile = load_sonar_profile(ROOT / "devices" / "sonars" / "didson_hf.toml")
        full = profile.default_settings().replace(elevation_rays=1000, n_samples=512)
        clean = full.realism_off()
        self.settings = {
            "paper's model (no spreading, realism off)": clean.replace(spread=False),
            ARTIFACT_FREE: clean,
            FULL: full,
        }
        self.sonar = ImagingSonar(profile, full, seed=0)
        self.best: dict[str, float] = {}

    def embree_rates(self) -> None:
        print(f"({self.label}) {self.n_tri} triangles; Embree scene build {self.build * 1e3:.1f} ms")
        for name, s in self.settings.items():
            med, self.best[name], n = frame_times(functools.partial(self.sonar.render, self.world, self.pose, s))
            print(f"  Embree  {name:70s} {1 / self.best[name]:6.1f} frames/s best, {1 / med:6.1f} median "
                  f"({self.best[name] * 1e3:.1f} / {med * 1e3:.1f} ms, {n} frames)")

    def cast_ratio(self, pairs: int = 60) -> None:
        """Full-model frame time over the raw cast of the same rays, interleaved."""
        full = self.settings[FULL]
        dirs_s, _ = self.sonar.rays(full)
        dirs = self.pose.apply_dirs(dirs_s)
        origins = np.broadcast_to(self.pose.position, dirs.shape).copy()
        caster = self.world.caster
        self.sonar.render(self.world, self.pose, full)
        cast, frame = [], []
        for i in range(pairs):
            t0 = time.perf_counter()
            caster.intersect(origins, dirs, full.range_min, full.range_max)
            t1 = time.perf_counter()
            self.sonar.render(self.world, self.pose, full, frame_index=i)
            t2 = time.perf_counter()
            cast.append(t1 - t0)
            frame.append(t2 - t1)
        c, f = np.array(cast), np.array(frame)
        print(f"  full frame / raw cast (EmbreeCaster.intersect of its {len(dirs)} rays), {pairs} interleaved pairs: "
              f"{f.min() / c.min():.2f}x best to best ({f.min() * 1e3:.1f} / {c.min() * 1e3:.1f} ms), "
              f"{np.median(f / c):.2f}x median of pair ratios; load average {os.getloadavg()[0]:.2f}")

    def other_casters(self, ref_seconds: float) -> None:
        clean = self.settings[ARTIFACT_FREE]
        frame = self.sonar.render(self.world, self.pose, clean)
        print(f"({self.label}) rays hitting: {frame.n_hits} of {frame.n_rays}; {frame.hit_counts}")
        # the frame's rays, cast alone with each backend
        dirs_s, _ = self.sonar.rays(clean)
        dirs = self.pose.apply_dirs(dirs_s)
        origins = np.broadcast_to(self.pose.position, dirs.shape).copy()
        caster = self.world.caster
        embree_cast = time_call(lambda: caster.intersect(origins, dirs, clean.range_min, clean.range_max), 10)
        world_cast = time_call(lambda: self.world.cast(origins, dirs, clean.range_min, clean.range_max), 10)
        hits = self.world.cast(origins, dirs, clean.range_min, clean.range_max)
        counting = time_call(lambda: self.world.hit_counts(hits), 10)
        frame_s = self.best[ARTIFACT_FREE]
        print(f"  of the {frame_s * 1e3:.1f} ms artifact-free frame (best of 10 each): "
              f"EmbreeCaster.intersect {embree_cast * 1e3:.1f} ms, World.cast {world_cast * 1e3:.1f} ms "
              f"(incl. intersect), World.hit_counts {counting * 1e3:.1f} ms")
        for cls in (ReferenceCaster, TrimeshCaster):
            try:
                cast, cbuild, m = cast_time(cls, self.world.triangles, origins, dirs, clean, ref_seconds)
            except ImportError as exc:
                print(f"  {cls.__name__}: not available ({exc})")
                continue
            est = frame_s - embree_cast + cast
            how = "all rays measured" if m == len(dirs) else f"timed on {m} of {len(dirs)} rays, extrapolated per ray"
            print(f"  {cls.__name__:15s} cast {cast:9.3f} s/frame = {cast / embree_cast:7.0f} x Embree's cast; "
                  f"frame {1.0 / est:8.3f} frames/s, {est / frame_s:6.0f} x the Embree frame time\n"
                  f"                  ({how}; set-up {cbuild:.2f} s)")


ARTIFACT_FREE = "artifact-free (spreading, realism off)"
FULL = "full model (spreading + beam pattern + speckle + noise + absorption)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="tuned-allocator rates and the full-frame ratio only")
    args = ap.parse_args()
    cpu = "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    print("hilsim imaging-sonar benchmark: 96 beams x 512 samples, 96 x 1000 rays (DIDSON HF)")
    print(f"pinned to CPU core {sorted(os.sched_getaffinity(0))} (os.sched_setaffinity), BLAS threads 1; {cpu}; "
          f"Python {platform.python_version()}, numpy {np.__version__}, trimesh {trimesh.__version__}; "
          f"load average {os.getloadavg()[0]:.2f}")
    t0 = time.perf_counter()
    scenes = [Scene("a: water tank", *tank_scene()), Scene("b: terrain heightfield", *terrain_scene())]
    if not args.quick:
        print("\n-- Embree, glibc's default allocator")
        for sc in scenes:
            sc.embree_rates()
    tuned = tune_allocator()  # as the render worker does
    print(f"\n-- Embree, allocator tuned with mallopt (keep freed memory): {'on' if tuned else 'unavailable'}")
    for sc in scenes:
        sc.embree_rates()
        sc.cast_ratio()
    if args.quick:
        print(f"\ntotal benchmark time {time.perf_counter() - t0:.0f} s")
        return
    print("\n-- the same frame's ray casting with the paper's method and trimesh's default engine")
    for sc, budget in zip(scenes, (6.0, 12.0)):
        sc.other_casters(budget)
    print(f"\ntotal benchmark time {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
