"""Live bridge benchmark: DIDSON-like stream frame rate and ping-to-client latency.

Starts ``hilsim run`` on the water tank (real-time clock), connects 1 and then
8 plain socket clients, and for each measures over ``--seconds``:
  * the sustained frame rate every client receives [frames/s];
  * the ping-to-client latency: arrival (wall clock) of a frame's last byte minus
    the frame time in its header (the simulation time of the ping on the wall
    clock) [ms], p50 / p99 / max over all clients' frames;
  * the elevation rays per beam each frame was rendered with (frame header offset
    732, protocols/ddf-stream.md: the bridge lowers them when frames would miss
    their period), min / median / max.
``--hog N`` runs N CPU-burning processes beside the bridge while it measures (a busy
machine: the user's own stack and tools), each bounded in time; the load average is
printed with the figures. ``--fixed-rays``: the same with the sonar profile's
``adaptive_rays = false`` (a copy of the scenario and of the DIDSON profile in a
temporary folder), to compare with the adaptive ray count under the same load.
Prints figures; never passes or fails.
Usage: python benchmarks/bench_bridge.py [--seconds 10] [--hog N] [--fixed-rays]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import tempfile
import time
from pathlib import Path

from _common import ROOT, ddf_clients, host_port, start_bridge


def hog(seconds: float) -> None:
    """Burn one CPU for ``seconds`` (a child process)."""
    end = time.monotonic() + seconds
    x = 0
    while time.monotonic() < end:
        for _ in range(10000):
            x += 1


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--hog", type=int, default=0, metavar="N", help="N CPU-burning processes beside the bridge")
    ap.add_argument("--fixed-rays", action="store_true", help="the sonar profile with adaptive_rays = false")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp())
    scenario: list[str] = []
    if args.fixed_rays:  # a scenario's own profile comes before the bundled one of the same name
        (tmp / "sonars").mkdir()
        text = (ROOT / "devices" / "sonars" / "didson_hf.toml").read_text()
        assert "adaptive_rays      = true" in text
        (tmp / "sonars" / "didson_hf.toml").write_text(text.replace("adaptive_rays      = true",
                                                                    "adaptive_rays      = false"))
        (tmp / "scenario.toml").write_text((ROOT / "scenarios" / "water_tank" / "scenario.toml").read_text())
        scenario = [str(tmp / "scenario.toml")]
    bridge = start_bridge(tmp, *scenario, "--log-level", "WARNING", "--status-interval", "0", "--no-console")
    hogs: list = []
    try:
        e = bridge.endpoint("ddf-stream")
        addr = host_port(e["address"])
        print(f"DIDSON-like stream, water tank, profile rate {e['frame_rate_hz']} Hz, 96 x 512 samples, "
              f"96 x 1000 rays; {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f} before"
              + (f"; {args.hog} CPU hog(s) beside the bridge" if args.hog else "")
              + ("; fixed ray count (adaptive_rays = false)" if args.fixed_rays else "; adaptive ray count"))
        if args.hog:  # bounded: they stop by themselves after the measurements, and are killed at the end
            ctx = mp.get_context("spawn")
            hogs = [ctx.Process(target=hog, args=(2 * args.seconds + 20,), daemon=True) for _ in range(args.hog)]
            for h in hogs:
                h.start()
            time.sleep(2.0)  # let the bridge feel them before measuring
        for n in (1, 8):
            r = ddf_clients(addr, n, args.seconds)
            lo, med, hi = r["rays"]
            rays = f"{lo}/{med:.0f}/{hi}" if hi else "not stated in the header"
            print(f"  {n} client(s): {r['rate_mean']:.1f} frames/s per client (slowest {r['rate_min']:.1f}); "
                  f"ping-to-client latency p50 {r['p50']:.1f} ms, p99 {r['p99']:.1f} ms, max {r['max']:.1f} ms "
                  f"({r['frames']} frames); elevation rays per beam min/median/max {rays}; "
                  f"load {os.getloadavg()[0]:.2f}")
            if n > 1:
                print(f"    per client [frames/s]: {' '.join(f'{x:.1f}' for x in r['rates'])}")
        period_ms = 1000.0 / float(e["frame_rate_hz"])
        print(f"  (one frame period: {period_ms:.1f} ms)")
    finally:
        for h in hogs:
            h.kill()
            h.join(5)
        bridge.stop()


if __name__ == "__main__":
    main()
