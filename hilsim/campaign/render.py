"""Render campaigns (``kind = "render"``): labelled sonar (and camera) frames at sampled poses.

Each case of the matrix (a seed, a scenario variant) renders ``[render] count``
poses sampled in the scenario (uniform in a box, evenly along a path, or
listed), in chunks of ``chunk`` poses per task so a worker builds the world
once per chunk. Per frame it writes ``frames/<case>/<frame>.npz`` with the
image, the labels of :mod:`hilsim.campaign.labels` and the pose, plus a
``.png`` of the fan and a ``_labels.png`` of the label grid; one index row per
frame (pose, scenario, seed, rays and cells per object, shadow cells, files).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from hilsim.campaign.matrix import Case
from hilsim.campaign.spec import Campaign, Poses

PoseRow = tuple[int, float, float, float, float, float, float]   # frame, x, y, z, roll, pitch, yaw [m, deg]

# label colours: one per object index (cycled), no echo black, shadow grey
_PALETTE = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                     [140, 86, 75], [227, 119, 194], [188, 189, 34], [23, 190, 207], [255, 255, 255]], dtype=np.uint8)
_SHADOW = np.array([80, 80, 80], dtype=np.uint8)


def sample_poses(p: Poses, count: int, seed: int) -> list[PoseRow]:
    """``count`` vehicle poses (frame index, x, y, z [m], roll, pitch, yaw [deg]), reproducible from ``seed``."""
    rng = np.random.default_rng([seed, 0x5EED])
    if p.mode == "list":
        return [(i, *row) for i, row in enumerate(p.listed)]  # type: ignore[misc]

    def angles(n: int) -> np.ndarray:
        return np.stack([rng.uniform(*p.roll_deg, n), rng.uniform(*p.pitch_deg, n), rng.uniform(*p.yaw_deg, n)], 1)

    if p.mode == "box":
        xyz = rng.uniform(p.min_m, p.max_m, size=(count, 3))
        ang = angles(count)
    else:
        wp = np.asarray(p.waypoints_m, dtype=float)
        seg = np.diff(wp, axis=0)
        length = np.linalg.norm(seg, axis=1)
        cum = np.r_[0.0, np.cumsum(length)]
        s = np.linspace(0.0, cum[-1], count) if count > 1 else np.array([0.0])
        j = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
        f = np.where(length[j] > 0, (s - cum[j]) / np.where(length[j] > 0, length[j], 1.0), 0.0)
        xyz = wp[j] + seg[j] * f[:, None]
        ang = angles(count)
        if p.path_yaw:
            ang[:, 2] = np.degrees(np.arctan2(seg[j, 1], seg[j, 0]))
    return [(i, *map(float, xyz[i]), *map(float, ang[i])) for i in range(count)]  # type: ignore[misc]


def label_png(labels: Any, path: Path) -> None:
    from PIL import Image

    obj = labels.object
    rgb = np.zeros(obj.shape + (3,), dtype=np.uint8)
    on = obj >= 0
    rgb[on] = _PALETTE[obj[on] % len(_PALETTE)]
    rgb[labels.shadow] = _SHADOW
    Image.fromarray(rgb[::-1].copy(), "RGB").save(path, compress_level=1)   # far ranges at the top, like the fan


def render_chunk(c: Campaign, case: Case, scenario: Path, poses: list[PoseRow], out: Path) -> list[dict[str, Any]]:
    """Render ``poses`` of one case into ``out/frames/<case>/``; one index row per frame."""
    from hilsim import viz
    from hilsim.campaign.labels import sonar_labels
    from hilsim.sim.rig import build_camera, build_sonar
    from hilsim.sim.scenario import load_scenario
    from hilsim.sim.state import VehicleState

    assert c.render is not None
    r = c.render
    scen = load_scenario(scenario)
    world = scen.build_world()
    mount = scen.sensor(r.sonar)
    seed = case.seed if case.seed is not None else scen.seed
    sonar = build_sonar(scen, mount, seed=seed)
    s = sonar.settings
    if r.elevation_rays is not None:
        s = s.replace(elevation_rays=r.elevation_rays)
    if not r.realism:
        s = s.replace(speckle=False, noise=False, beam_pattern=False)
    cam_mount = scen.sensor(r.camera) if r.camera else None
    camera = build_camera(scen, cam_mount) if cam_mount is not None else None
    folder = out / "frames" / case.id
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    for frame, x, y, z, roll, pitch, yaw in poses:
        t0 = time.perf_counter()
        state = VehicleState(position=np.array([x, y, z]), attitude=np.radians([roll, pitch, yaw]))
        pose = state.pose @ mount.mount
        f = sonar.render(world, pose, s, time=0.0, frame_index=frame)
        t_render = time.perf_counter() - t0
        lab = sonar_labels(world, sonar, pose, s)
        stem = f"{frame:05d}"
        arrays: dict[str, Any] = dict(
            image=f.image, intensity=f.intensity.astype(np.float32), label_object=lab.object,
            label_material=lab.material, shadow=lab.shadow, object_names=np.array(lab.object_names),
            material_names=np.array(lab.material_names), ranges_m=f.ranges, azimuths_rad=f.azimuths,
            vehicle_pose=np.array([x, y, z, roll, pitch, yaw]), sensor_position_m=np.asarray(pose.position),
            sensor_rotation=np.asarray(pose.rotation))
        files = {"npz": f"frames/{case.id}/{stem}.npz"}
        if camera is not None and cam_mount is not None:
            cf = camera.sample(world, state, cam_mount.mount)
            arrays.update(camera_rgb=cf.rgb, camera_depth=cf.depth, camera_object=cf.object)
        np.savez_compressed(folder / f"{stem}.npz", **arrays)
        if r.png:
            viz.sonar_fan_image(f.image, f.azimuths, f.range_min, f.range_max,
                                title=f"{case.id} frame {frame}").save(folder / f"{stem}.png", compress_level=1)
            label_png(lab, folder / f"{stem}_labels.png")
            files.update(png=f"frames/{case.id}/{stem}.png", labels_png=f"frames/{case.id}/{stem}_labels.png")
            if camera is not None:
                viz.camera_image(arrays["camera_rgb"]).save(folder / f"{stem}_camera.png", compress_level=1)
                files["camera_png"] = f"frames/{case.id}/{stem}_camera.png"
        rows.append({
            "case": case.id, "index": case.index, "key": f"{case.key}-{frame:05d}", "frame": frame,
            "params": dict(case.params), "scenario": scen.name, "seed": seed, "status": "done",
            "x_m": x, "y_m": y, "z_m": z, "roll_deg": roll, "pitch_deg": pitch, "yaw_deg": yaw,
            "rays": f.n_rays, "rays_hit": f.n_hits,
            "hits": {k: lab.hits.get(k, 0) for k in lab.object_names},
            "cells": {k: lab.cells.get(k, 0) for k in lab.object_names}, "shadow_cells": int(lab.shadow.sum()),
            "render_ms": round(t_render * 1e3, 2), "wall_s": round(time.perf_counter() - t0, 4),
            "files": files,
        })
    return rows


def chunks(c: Campaign, case: Case, done: set[str]) -> list[list[PoseRow]]:
    """The case's poses not yet rendered (``done``: index keys), in chunks of ``[render] chunk``."""
    assert c.render is not None
    seed = case.seed if case.seed is not None else int(c.scenario_data.get("seed", 0) or 0)
    todo = [p for p in sample_poses(c.render.poses, c.render.count, seed) if f"{case.key}-{p[0]:05d}" not in done]
    n = max(1, c.render.chunk)
    return [todo[i:i + n] for i in range(0, len(todo), n)]
