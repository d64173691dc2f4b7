"""``hilsim experiment water-tank``: the paper's water-tank experiment and its figures.

Runs :func:`hilsim.experiments.water_tank.run` (the vehicle driven forward
1.5 m above the floor through positions A, B and C on the virtual clock) and
writes into ``--out``:

- ``A/``, ``B/``, ``C/``: ``sonar.raw`` (uint8, n_samples rows of n_beams,
  beam fastest, beam 0 = port), ``sonar.png`` (the fan) and ``camera.png``,
  rendered from the vehicle's actual state when it passed the position;
- ``figure_fig4.png``: the sonar fans above the camera images, columns A, B,
  C, as the paper's Fig. 4;
- ``figure_sampling.png``: at each position the paper's 96 x 1000 sampling
  beside the artifact-free one, as mounted and, because the paper's sampling
  leaves no empty bins at this geometry, in the first variant geometry of
  :data:`hilsim.experiments.sampling.VARIANTS` where it does (labelled so);
- ``trajectory.csv``: the vehicle's state at 10 Hz;
- ``experiment.json``: per position the actual pose, the sonar's distance
  ``d`` to the cuboid's front face and height ``H`` above the floor, the hit
  counts per object and face from the frame, the faces predicted from the
  geometry (closed form and analytic ray grid, see
  :mod:`hilsim.experiments.tank_geometry`), the sampling comparison (empty
  range bins inside the surfaces' footprint for each sampling) and a summary
  of the trajectory (depth, altitude, heading and speed errors).

Lengths [m], times [s], speeds [m/s], angles [deg] in the files.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from PIL import Image

from hilsim import viz
from hilsim.experiments import sampling
from hilsim.experiments.tank_geometry import closed_form_faces, ray_grid_faces
from hilsim.experiments.water_tank import (
    CONTROL_RATE,
    PHYSICS_RATE,
    POSITIONS,
    TRAJECTORY_FIELDS,
    Capture,
    Rig,
    RunResult,
    run,
)
from hilsim.sim.geometry import Pose

EXPERIMENTS = ("water-tank",)


def _r(x: float, nd: int = 6) -> float:
    return round(float(x), nd)


def _pose_json(pose: Pose) -> dict[str, Any]:
    return {"position_m": [_r(v) for v in pose.position],
            "orientation_deg": [_r(math.degrees(a), 4) for a in pose.rpy()]}


def _faces(hit_counts: dict[str, dict[str, int]], obj: str = "cuboid") -> list[str]:
    return sorted(k for k, v in hit_counts.get(obj, {}).items() if k != "total" and v > 0)


def position_report(rig: Rig, res: RunResult, cap: Capture) -> dict[str, Any]:
    """The JSON entry of one capture (see the module doc)."""
    s, frame = cap.state, cap.sonar
    prof, settings = rig.sonar.profile, frame.settings
    closed = closed_form_faces(frame.pose, rig.geometry, prof.azimuth_limits, prof.elevation_limits)
    grid = ray_grid_faces(frame.pose, rig.geometry, prof.azimuths, prof.elevation_limits,
                          settings.range_min, settings.range_max, settings.elevation_rays)
    observed = _faces(frame.hit_counts)
    nominal = rig.scenario.positions[cap.label]
    return {
        "description": nominal.description,
        "nominal_position_m": list(nominal.position),
        "time_s": _r(s.time),
        "vehicle": {
            "position_m": [_r(v) for v in s.position],
            "orientation_deg": [_r(math.degrees(a), 4) for a in s.attitude],
            "velocity_m_s": [_r(v) for v in s.velocity],
            "altitude_m": _r(cap.altitude),
            "depth_error_m": _r(s.depth - res.target_depth),
            "speed_error_m_s": _r(float(s.velocity[0]) - res.speed),
        },
        "sonar": {
            "sensor": rig.sonar_mount.name, "profile": prof.name, "pose": _pose_json(frame.pose),
            "d_m": _r(closed["d_m"]), "H_m": _r(closed["H_m"]),
            "settings": {"elevation_rays": settings.elevation_rays, "n_samples": settings.n_samples,
                         "spread": settings.spread, "gain_mode": settings.gain_mode,
                         "speckle": settings.speckle, "noise": settings.noise,
                         "beam_pattern": settings.beam_pattern, "absorption": settings.absorption},
            "range_min_m": frame.range_min, "range_max_m": frame.range_max,
            "n_rays": frame.n_rays, "n_hits": frame.n_hits, "hit_counts": frame.hit_counts,
            "raw": {"file": f"{cap.label}/sonar.raw", "dtype": "uint8", "shape": list(frame.image.shape),
                    "order": "n_samples rows of n_beams, beam fastest; beam 0 = port"},
            "fan": f"{cap.label}/sonar.png",
        },
        "camera": {"sensor": rig.camera_mount.name, "file": f"{cap.label}/camera.png",
                   "pose": _pose_json(cap.camera.pose), "pixel_counts": cap.camera.counts},
        "faces": {"observed": observed, "closed_form": closed["faces"], "ray_grid": grid["faces"],
                  "agree": observed == sorted(closed["faces"]) == grid["faces"]},
        "prediction": {"closed_form": closed, "ray_grid": grid},
    }


def trajectory_report(res: RunResult) -> dict[str, Any]:
    """Errors over the whole run and the speed between the first and last capture."""
    a = np.asarray(res.trajectory, dtype=float)
    col = {k: a[:, i] for i, k in enumerate(TRAJECTORY_FIELDS)}
    t0, t1 = res.captures[POSITIONS[0]].state.time, res.captures[POSITIONS[-1]].state.time
    window = (col["t_s"] >= t0) & (col["t_s"] <= t1)
    u = col["u_m_s"][window] if window.any() else col["u_m_s"][-1:]
    heading_err = [abs(math.remainder(math.radians(h) - res.heading, 2 * math.pi)) for h in col["heading_deg"]]
    return {
        "file": "trajectory.csv", "rows": len(a), "duration_s": _r(res.duration),
        "max_abs_depth_error_m": _r(np.abs(col["z_m"] - res.target_depth).max()),
        "altitude_m": {"min": _r(col["altitude_m"].min()), "max": _r(col["altitude_m"].max())},
        "max_abs_cross_track_m": _r(np.abs(col["cross_track_m"]).max()),
        "max_abs_heading_error_deg": _r(math.degrees(max(heading_err)), 4),
        "speed_from_A_to_C_m_s": {"mean": _r(u.mean()), "min": _r(u.min()), "max": _r(u.max())},
    }


def sampling_report(rig: Rig, res: RunResult, say: Callable[[str], None]) -> tuple[dict[str, Any], Image.Image]:
    """Both samplings at each capture, as mounted and (when needed) in a variant; the figure."""
    mount = rig.sonar_mount.mount
    bodies = {k: res.captures[k].state.pose for k in POSITIONS}
    mounted = {k: sampling.compare(rig.world, rig.sonar, bodies[k], mount, sampling.AS_MOUNTED)
               for k in POSITIONS}
    report: dict[str, Any] = {"as_mounted": {k: r.summary() for k, r in mounted.items()}, "variant": None}
    variant = None
    if all(r.empty_paper == 0 for r in mounted.values()):
        variant = sampling.choose_variant(rig.world, rig.sonar, bodies[POSITIONS[0]], mount)
    headers = ["paper 96 x 1000 (no spreading)\nas mounted", "artifact-free (spreading)\nas mounted"]
    rows = {k: sampling.result_panels(k, r, 300, mask=False) for k, r in mounted.items()}
    notes = [("paper gain, realism off, each display pixel shows its nearest cell; empty bin = a cell inside "
              "a surface's footprint that no echo reached")]
    for k, r in mounted.items():
        say(f"sampling {k} as mounted: empty bins paper {r.empty_paper}, artifact-free {r.empty_free} "
            f"(footprint {int(r.footprint.sum())} cells)")
    if variant is not None:
        spacing = max(r.ray_spacing[1] for r in mounted.values())
        bin_mm = mounted[POSITIONS[0]].paper.settings.range_resolution * 1e3
        why = (f"as mounted the paper's sampling leaves no empty bins (rays adjacent in elevation land at most "
               f"{spacing * 1e3:.2f} mm apart in range, with {bin_mm:.2f} mm range bins); the first variant "
               f"where it does: {variant.label.replace('variant: ', '')}")
        var = {k: sampling.compare(rig.world, rig.sonar, bodies[k], mount, variant) for k in POSITIONS}
        report["variant"] = {"case": variant.key, "label": variant.label, "why": why,
                             **{k: r.summary() for k, r in var.items()}}
        tag = variant.label.replace("variant: ", "")
        headers += [f"paper 96 x 1000\n{tag}", f"artifact-free\n{tag}", f"paper's empty bins\n{tag}"]
        for k, r in var.items():
            rows[k] += sampling.result_panels(k, r, 300, mask=True)
            say(f"sampling {k} {variant.label}: empty bins paper {r.empty_paper}, "
                f"artifact-free {r.empty_free} (footprint {int(r.footprint.sum())} cells)")
        notes.append("VARIANT (not the paper's geometry): " + why)
    fig = sampling.grid_figure([(k, rows[k]) for k in POSITIONS], headers,
                               "The paper's 96 x 1000 sampling vs the artifact-free sampling", notes)
    return report, fig


def run_water_tank(args: argparse.Namespace, stream: TextIO) -> int:
    def say(msg: str) -> None:
        print(msg, file=stream, flush=True)

    t_wall = time.perf_counter()
    rig = Rig.load(args.scenario, args.seed)
    res = run(rig, float(args.speed), stream)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    panels = []
    positions: dict[str, Any] = {}
    for label in POSITIONS:
        cap = res.captures[label]
        folder = out / label
        folder.mkdir(parents=True, exist_ok=True)
        viz.save_raw(cap.sonar.image, folder / "sonar.raw")
        entry = position_report(rig, res, cap)
        positions[label] = entry
        faces = entry["faces"]["observed"]
        fan = viz.sonar_fan_image(cap.sonar.image, cap.sonar.azimuths, cap.sonar.range_min, cap.sonar.range_max,
                                  title=f"{label}: d = {entry['sonar']['d_m']:.2f} m, cuboid: "
                                        f"{' + '.join(faces) or 'not seen'}")
        cam = viz.camera_image(cap.camera.rgb)
        viz.save_png(fan, folder / "sonar.png")
        viz.save_png(cam, folder / "camera.png")
        panels.append((label, fan, cam))
        if not entry["faces"]["agree"]:
            say(f"warning: {label}: observed faces {faces} differ from the predicted "
                f"{entry['faces']['closed_form']} / {entry['faces']['ray_grid']}")
    fig4 = viz.figure_positions(panels, title=f"{rig.scenario.name}: sonar (top) and camera (bottom) at A, B, C; "
                                              f"{res.speed:g} m/s, "
                                              f"{rig.geometry.floor_z - res.target_depth:.2f} m above the floor")
    viz.save_png(fig4, out / "figure_fig4.png")
    with open(out / "trajectory.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(TRAJECTORY_FIELDS)
        w.writerows([[f"{v:.6f}" for v in row] for row in res.trajectory])
    samp, fig_s = sampling_report(rig, res, say)
    viz.save_png(fig_s, out / "figure_sampling.png")
    c = res.controller
    report = {
        "experiment": "water-tank",
        "paper": "Kim, Sung, Yu: AUV simulator with image sonar and optical vision, sections 3-4, Fig. 4",
        "scenario": {"name": rig.scenario.name, "path": str(rig.scenario.path), "seed": rig.sonar.seed},
        "run": {"speed_set_m_s": res.speed, "target_depth_m": res.target_depth,
                "floor_z_m": rig.geometry.floor_z,
                "target_altitude_m": _r(rig.geometry.floor_z - res.target_depth),
                "heading_deg": _r(math.degrees(res.heading), 4), "start_position_m": [_r(v) for v in res.start],
                "physics_rate_hz": PHYSICS_RATE, "control_rate_hz": CONTROL_RATE, "vehicle": rig.profile.name,
                "controller": {"surge": {"kp": _r(c.kp_u, 3), "ki": _r(c.ki_u, 3), "feed_forward_N": _r(c.feed_forward, 3)},
                               "heave": {"kp": _r(c.kp_z, 3), "kd": _r(c.kd_z, 3), "ki": _r(c.ki_z, 3)},
                               "yaw": {"kp": _r(c.kp_psi, 3), "kd": _r(c.kd_psi, 3)},
                               "sway": {"kp": _r(c.kp_y, 3), "kd": _r(c.kd_y, 3)}}},
        "cuboid": {"box_lo_m": rig.geometry.box_lo.tolist(), "box_hi_m": rig.geometry.box_hi.tolist(),
                   "height_m": rig.geometry.height, "length_m": rig.geometry.length},
        "trajectory": trajectory_report(res),
        "positions": positions,
        "sampling": samp,
        "figures": {"fig4": "figure_fig4.png", "sampling": "figure_sampling.png"},
    }
    (out / "experiment.json").write_text(json.dumps(report, indent=2) + "\n")
    say("faces seen: " + ", ".join(f"{k}: {' + '.join(positions[k]['faces']['observed']) or 'none'}"
                                    for k in POSITIONS))
    say(f"wrote {out / 'figure_fig4.png'}, {out / 'figure_sampling.png'}, {out / 'experiment.json'} "
        f"({time.perf_counter() - t_wall:.1f} s)")
    return 0


def experiment_command(args: argparse.Namespace, stream: TextIO | None = None) -> int:
    """Entry point of ``hilsim experiment NAME``: args.name, args.scenario, args.out (Path),
    args.speed [m/s], args.seed. Errors raise ValueError/KeyError/ConfigError."""
    if args.name not in EXPERIMENTS:
        raise ValueError(f"unknown experiment {args.name!r}; one of {', '.join(EXPERIMENTS)}")
    return run_water_tank(args, stream if stream is not None else sys.stderr)
