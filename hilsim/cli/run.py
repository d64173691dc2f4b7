"""``hilsim run`` and ``hilsim record``: the bridge from the command line."""

from __future__ import annotations

import argparse
import asyncio
import logging
import math
import signal
import sys

from hilsim.resources import find_scenario
from hilsim.runtime.bridge import Bridge, endpoints_table, write_endpoints

log = logging.getLogger("hilsim.run")


async def _serve(bridge: Bridge, duration: float | None, endpoints_file: object) -> None:
    loop = asyncio.get_running_loop()
    stop_reason: list[str] = []

    def on_signal(name: str) -> None:
        if not stop_reason:
            stop_reason.append(name)
            log.info("%s: shutting down", name)
        bridge.stop()

    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, on_signal, sig.name)
    try:
        endpoints = await bridge.start()
        print(endpoints_table(endpoints), flush=True)
        if bridge.attached is not None and bridge.attached.url:
            print(f"console: {bridge.attached.url}", flush=True)
        if endpoints_file is not None:
            write_endpoints(endpoints_file, endpoints)  # type: ignore[arg-type]
        mode = ("fast (virtual clock)" if bridge.fast else "real time" if bridge.time_scale == 1.0
                else f"real time x {bridge.time_scale:g}")
        log.info("bridge running in %s%s", mode, f" for {duration:g} s" if duration else "; Ctrl-C to stop")
        if not stop_reason:
            await bridge.run(duration)
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        await bridge.close()
        log.info("bridge stopped at t=%.2f s\n%s", bridge.vehicle.state.time, bridge.scheduler.report())


def run_command(args: argparse.Namespace) -> int:
    if args.duration is not None and not (args.duration > 0 and math.isfinite(args.duration)):
        raise ValueError(f"--duration must be a positive number of seconds, got {args.duration}")
    bridge = Bridge(find_scenario(args.scenario), fast=args.fast, bind=args.bind, broadcast=args.broadcast,
                    seed=args.seed, record=args.record, physics_rate=args.physics_rate,
                    epoch=args.epoch, status_interval=args.status_interval,
                    worker_timeout=args.render_timeout, run_dir=args.pty_dir, time_scale=args.time_scale,
                    console=args.console, record_mcap=args.record_mcap, foxglove=args.foxglove)
    beside = args.endpoints.parent if args.endpoints is not None else None  # else: the run folder
    bridge.truth_path = args.truth or (beside / "truth.csv" if beside is not None else None)
    bridge.summary_path = args.summary or (beside / "summary.json" if beside is not None else None)
    bridge.truth_rate = args.truth_rate
    asyncio.run(_serve(bridge, args.duration, args.endpoints))
    return 0


def record_command(args: argparse.Namespace) -> int:
    if args.frames <= 0:
        raise ValueError("--frames must be positive")
    bridge = Bridge(find_scenario(args.scenario), fast=True, seed=args.seed, record=args.out,
                    epoch=args.epoch, status_interval=0)

    async def go() -> None:
        await bridge.start()
        dev = next(d for d in bridge.devices if args.out.suffix.lower() in d.records)
        try:
            while (done := int(dev.status().get("recorded", 0))) < args.frames:
                await bridge.run(bridge.vehicle.state.time + 0.01)  # below one frame period
                print(f"\rrecorded {done}/{args.frames} frames", end="", file=sys.stderr)
            print(f"\rrecorded {done}/{args.frames} frames", file=sys.stderr)
        finally:
            await bridge.close()

    asyncio.run(go())
    return 0
