"""Campaign throughput: prints figures, never pass/fail.

Run: ``.venv/bin/python benchmarks/bench_campaign.py [--runs 4] [--frames 60] [--skip-missions] [--skip-ray]``.

1. Mission runs per hour: the same campaign of ``--runs`` short reference missions
   (examples/mission.py: dive, turns, approach, 2 s hold; time scale 4) on the local
   executor (a pool sized from the cores: cores / 2 CPUs per run) and on Ray's
   local mode (each run a task asking for 2 CPUs). Ray's rate includes its own
   start (paid once per campaign), also timed alone.
2. Render campaign: ``--frames`` labelled sonar frames (water tank, DIDSON HF,
   96 x 1000 rays, realism on; labels, .npz and PNGs written) with the local
   executor on every core, against the same frames rendered in one process by
   ``ImagingSonar.render`` alone (what bench_sonar measures, here on this
   machine, same poses, same settings): the ratio is the campaign machinery's
   cost (labels, files, processes) over the bare render.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from hilsim.campaign.runner import run_campaign  # noqa: E402

MISSIONS = """name = "bench_missions"
scenario = "water_tank"
time_scale = 4.0
duration_s = 130.0
[stack]
command = "{{python}} {mission} {{endpoints}} --out {{out}} --quiet --no-plots --hold-time 2 --timeout 90"
timeout_s = 90.0
[matrix]
seed = {seeds}
[pass]
exit = "exit_code == 0"
"""

RENDERS = """name = "bench_renders"
kind = "render"
scenario = "water_tank"
seed = 3
[render]
count = {n}
chunk = {chunk}
png = {png}
[render.poses]
mode = "box"
min_m = [-2.2, -0.6, 1.3]
max_m = [-0.6, 0.6, 1.7]
yaw_deg = [-20.0, 20.0]
"""


def load() -> str:
    a, b, c = os.getloadavg()
    return f"load average {a:.2f} {b:.2f} {c:.2f} on {os.cpu_count()} cores"


def missions(tmp: Path, runs: int, ray: bool) -> None:
    f = tmp / "missions.toml"
    f.write_text(MISSIONS.format(mission=ROOT / "examples" / "mission.py", seeds=list(range(1, runs + 1))))
    print(f"missions: {runs} runs, {load()}")
    t0 = time.perf_counter()
    o = run_campaign(f, out=tmp / "local", stream=open(os.devnull, "w"))
    wall = time.perf_counter() - t0
    ok = sum(r["status"] == "pass" for r in o.rows)
    print(f"  local pool : {runs / wall * 3600:7.0f} runs/hour ({wall:.1f} s for {runs}, {ok} passed)")
    if not ray:
        return
    try:
        from hilsim.campaign import executors
        t0 = time.perf_counter()
        executors.ray_init(None)
        init = time.perf_counter() - t0
        executors.ray_shutdown()   # the campaign starts its own (timed apart here: its start-up)
    except RuntimeError as exc:
        print(f"  ray local  : skipped ({exc})")
        return
    t0 = time.perf_counter()
    o = run_campaign(f, out=tmp / "ray", ray="local", stream=open(os.devnull, "w"))
    wall = time.perf_counter() - t0
    ok = sum(r["status"] == "pass" for r in o.rows)
    print(f"  ray local  : {runs / wall * 3600:7.0f} runs/hour ({wall:.1f} s for {runs}, {ok} passed; "
          f"includes Ray's start, {init:.1f} s when timed alone)")


def renders(tmp: Path, n: int) -> None:
    from hilsim.campaign.render import sample_poses
    from hilsim.campaign.spec import load_campaign
    from hilsim.resources import find_scenario
    from hilsim.sim.rig import build_sonar
    from hilsim.sim.scenario import load_scenario
    from hilsim.sim.state import VehicleState

    cores = len(os.sched_getaffinity(0))
    print(f"renders: {n} frames, {load()}")
    f = tmp / "renders.toml"
    f.write_text(RENDERS.format(n=n, chunk=max(1, n // (2 * cores)), png="false"))
    c = load_campaign(f)
    assert c.render is not None
    sc = load_scenario(find_scenario("water_tank"))
    world = sc.build_world()
    mount = sc.sensor("sonar")
    sonar = build_sonar(sc, mount, seed=3)
    poses = sample_poses(c.render.poses, n, 3)
    sonar.render(world, VehicleState(position=np.array(poses[0][1:4])).pose @ mount.mount, frame_index=0)
    t0 = time.perf_counter()
    for i, x, y, z, r, p, yaw in poses:
        st = VehicleState(position=np.array([x, y, z]), attitude=np.radians([r, p, yaw]))
        sonar.render(world, st.pose @ mount.mount, frame_index=i)
    bare = n / (time.perf_counter() - t0)
    print(f"  one process, ImagingSonar.render only  : {bare:6.1f} frames/s")
    for png in ("false", "true"):
        f.write_text(RENDERS.format(n=n, chunk=max(1, n // (2 * cores)), png=png))
        out = tmp / f"renders_{png}"
        t0 = time.perf_counter()
        run_campaign(f, out=out, workers=cores, stream=open(os.devnull, "w"))
        rate = n / (time.perf_counter() - t0)
        what = "labels + .npz + PNGs" if png == "true" else "labels + .npz"
        print(f"  campaign, {cores} processes, {what:<20}: {rate:6.1f} frames/s "
              f"(x{rate / bare:.2f} of one bare process)")
        shutil.rmtree(out, ignore_errors=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=4, help="missions per executor (default 4)")
    ap.add_argument("--frames", type=int, default=200, help="frames of the render campaign (default 200)")
    ap.add_argument("--skip-missions", action="store_true")
    ap.add_argument("--skip-ray", action="store_true")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-campaign-"))
    try:
        renders(tmp, a.frames)
        if not a.skip_missions:
            missions(tmp, a.runs, not a.skip_ray)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
