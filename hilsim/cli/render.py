"""``hilsim render``: sonar and camera frames of a scenario at given poses, to files.

For each pose it writes into ``OUT/<label>/``: ``sonar.raw`` (uint8,
n_samples rows of n_beams, beam fastest, beam 0 = port), ``sonar.png`` (the
fan in Cartesian space with range rings and bearings), ``camera.png``,
``depth.png`` and ``render.json`` (pose, timings, hit counts per object and
facet). With several poses it also writes ``OUT/figure.png``, the sonar fans
above the camera images side by side like the paper's Fig. 4.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from hilsim import viz
from hilsim.resources import find_scenario
from hilsim.sim.rig import build_camera, build_sonar, profile_path
from hilsim.sim.scenario import Scenario, load_scenario
from hilsim.sim.state import VehicleState


@dataclass(frozen=True)
class Where:
    label: str
    position: tuple[float, float, float]
    yaw: float  # [rad]
    description: str = ""


def parse_at(at: str | None, scenario: Scenario) -> list[Where]:
    """``A,B,C`` (named positions) or ``x,y,z,yaw`` (metres NED, degrees) -> poses."""
    if at is None:
        if scenario.positions:
            return [Where(k, p.position, p.yaw, p.description) for k, p in scenario.positions.items()]
        if scenario.vehicle is None:
            raise ValueError("the scenario has no vehicle and no named positions: give --at x,y,z,yaw")
        v = scenario.vehicle
        return [Where("initial", v.position, v.attitude[2], "the vehicle's initial pose")]
    parts = [p.strip() for p in at.split(",") if p.strip()]
    try:
        nums = [float(p) for p in parts]
    except ValueError:
        nums = []
    if len(nums) == 4 and all(math.isfinite(x) for x in nums):
        x, y, z, yaw = nums
        return [Where(f"x{x:g}_y{y:g}_z{z:g}_yaw{yaw:g}", (x, y, z), math.radians(yaw))]
    out = []
    for p in parts:
        if p not in scenario.positions:
            known = ", ".join(scenario.positions) or "none"
            raise ValueError(f"--at {p!r} is not a named position of scenario {scenario.name!r} "
                             f"(named: {known}) nor a pose 'x,y,z,yaw'")
        n = scenario.positions[p]
        out.append(Where(p, n.position, n.yaw, n.description))
    if not out:
        raise ValueError("--at is empty")
    return out


def _pose_json(pose: Any) -> dict[str, Any]:
    r, p, y = pose.rpy()
    return {"position_m": [round(float(v), 6) for v in pose.position],
            "orientation_deg": [round(math.degrees(a), 4) for a in (r, p, y)]}


def render_command(args: argparse.Namespace, stream: TextIO | None = None) -> int:
    stream = stream if stream is not None else sys.stderr
    scenario = load_scenario(find_scenario(args.scenario))
    wheres = parse_at(args.at, scenario)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)

    def say(msg: str) -> None:
        print(msg, file=stream, flush=True)

    t0 = time.perf_counter()
    world = scenario.build_world()
    say(f"scenario {scenario.name}: {len(world.objects)} objects, {len(world.triangles)} triangles "
        f"({(time.perf_counter() - t0) * 1e3:.0f} ms)")
    sonar_mount = scenario.sensor(args.sonar or "sonar")
    sonar = build_sonar(scenario, sonar_mount, seed=args.seed)
    settings = sonar.settings
    if args.elevation_rays is not None:
        settings = settings.replace(elevation_rays=args.elevation_rays)
    if args.paper_sampling:
        settings = settings.replace(spread=False)
    if args.gain is not None:
        settings = settings.replace(gain_mode=args.gain)
    camera_mount = None
    try:
        camera_mount = scenario.sensor(args.camera or "camera")
    except KeyError:
        if args.camera:
            raise
    camera = build_camera(scenario, camera_mount) if camera_mount is not None else None
    if camera_mount is not None and camera_mount.kind != "camera":
        camera = None

    panels = []
    for i, w in enumerate(wheres, 1):
        state = VehicleState(position=np.array(w.position, dtype=float), attitude=np.array([0.0, 0.0, w.yaw]))
        n_rays = sonar.profile.n_beams * settings.elevation_rays
        say(f"[{i}/{len(wheres)}] {w.label}: sonar {sonar.profile.name}, {sonar.profile.n_beams} x "
            f"{settings.elevation_rays} rays ({n_rays:,}) ...")
        ts = time.perf_counter()
        frame = sonar.render(world, state.pose @ sonar_mount.mount, settings, time=0.0, frame_index=0)
        sonar_ms = (time.perf_counter() - ts) * 1e3
        folder = out / w.label
        folder.mkdir(parents=True, exist_ok=True)
        viz.save_raw(frame.image, folder / "sonar.raw")
        fan = viz.sonar_fan_image(frame.image, frame.azimuths, frame.range_min, frame.range_max,
                                  title=f"{w.label}: {sonar.profile.name}")
        viz.save_png(fan, folder / "sonar.png")
        report: dict[str, Any] = {
            "scenario": {"name": scenario.name, "path": str(scenario.path), "seed": scenario.seed},
            "label": w.label, "description": w.description,
            "vehicle": {"position_m": list(w.position), "yaw_deg": math.degrees(w.yaw)},
            "sonar": {
                "sensor": sonar_mount.name, "profile": str(profile_path(scenario, sonar_mount)),
                "pose": _pose_json(frame.pose), "n_beams": int(frame.image.shape[1]),
                "n_samples": int(frame.image.shape[0]), "range_min_m": frame.range_min,
                "range_max_m": frame.range_max, "elevation_rays": settings.elevation_rays,
                "spread": settings.spread, "gain_mode": settings.gain_mode,
                "rays": frame.n_rays, "hits": frame.n_hits, "hit_counts": frame.hit_counts,
                "render_ms": round(sonar_ms, 2),
                "raw": {"file": "sonar.raw", "dtype": "uint8", "shape": list(frame.image.shape),
                        "order": "n_samples rows of n_beams, beam fastest; beam 0 = port (most negative azimuth)"},
            },
        }
        cam_img = None
        if camera is not None and camera_mount is not None:
            tc = time.perf_counter()
            cf = camera.sample(world, state, camera_mount.mount)
            cam_ms = (time.perf_counter() - tc) * 1e3
            cam_img = viz.camera_image(cf.rgb)
            viz.save_png(cam_img, folder / "camera.png")
            finite = cf.depth[np.isfinite(cf.depth)]
            viz.save_png(viz.depth_image(cf.depth, near=float(finite.min()) if finite.size else 0.0,
                                         far=float(finite.max()) if finite.size else 1.0), folder / "depth.png")
            report["camera"] = {"sensor": camera_mount.name, "pose": _pose_json(cf.pose),
                                "size_px": [int(cf.rgb.shape[1]), int(cf.rgb.shape[0])],
                                "pixel_counts": cf.counts, "render_ms": round(cam_ms, 2)}
            say(f"      sonar {sonar_ms:.0f} ms ({frame.n_hits:,} hits), camera {cam_ms:.0f} ms")
        else:
            say(f"      sonar {sonar_ms:.0f} ms ({frame.n_hits:,} hits)")
        faces = {k: {f: n for f, n in v.items() if f != "total"} for k, v in frame.hit_counts.items()}
        say(f"      sonar hits per object/face: {json.dumps(faces)}")
        (folder / "render.json").write_text(json.dumps(report, indent=2) + "\n")
        panels.append((w.label, fan, cam_img if cam_img is not None else fan))
    if len(panels) > 1:
        fig = viz.figure_positions(panels, title=f"{scenario.name}: sonar (top) and camera (bottom)")
        viz.save_png(fig, out / "figure.png")
        say(f"figure: {out / 'figure.png'}")
    say(f"done in {time.perf_counter() - t0:.1f} s -> {out}")
    return 0
