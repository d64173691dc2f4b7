"""Physics throughput and real-time tick jitter. Prints figures; never pass/fail.

1. Physics steps per second in fast mode: Cyclops (8 T200-like thrusters with
   lag and watchdog, RK4 dynamics) at the default 200 Hz, called directly
   (steady surge + heave commands, as the issue's figure; and a manoeuvre
   whose commands change every 0.1 s on every DOF) and through the scheduler
   on a virtual clock; the real-time ratio is simulated seconds per
   wall-clock second (goal >= 1000x).
2. Real-time tick lateness p50/p99/max at 200 Hz and 1 kHz (the physics
   running in the callback), with a busy-loop process on the other core
   (bounded in time, killed at the end). Goal: p99 <= 1 ms at 200 Hz.

3. The 6-DOF BlueROV2 model (Heavy, 8 thrusters) at 200, 50 and 1200 Hz (ArduPilot's
   lockstep rate), and the 6-thruster BlueROV2 (``report_6dof``; ``--6dof`` runs only it).

Run: ``.venv/bin/python benchmarks/bench_dynamics.py`` (under a minute).
"""

from __future__ import annotations

import asyncio
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hilsim.runtime import RealTimeClock, Scheduler, VehicleLoop, VirtualClock  # noqa: E402
from hilsim.sim.state import VehicleState  # noqa: E402
from hilsim.sim.vehicle import Current, Vehicle, load_vehicle_profile  # noqa: E402

PROFILE = load_vehicle_profile(ROOT / "devices" / "vehicles" / "cyclops.toml")
RATE = 200.0


def physics_direct(seconds: float, current: Current | None = None, rate: float = RATE) -> float:
    """Steps/s of thrusters + vehicle called in a plain loop (commands at 10 Hz)."""
    vehicle, thrusters = Vehicle(PROFILE), PROFILE.thruster_set()
    state, dt = VehicleState(), 1.0 / rate
    cmds = [0.6, 0.6, 0.6, 0.6, 0.3, 0.3, 0.3, 0.3]
    n = int(seconds * rate)
    every = max(1, int(rate / 10))
    start = time.perf_counter()
    for k in range(n):
        if k % every == 0:
            thrusters.command_all("normalized", cmds, state.time)
        state = vehicle.step_with_thrusters(state, dt, thrusters, current)
    return n / (time.perf_counter() - start)


def physics_manoeuvre(seconds: float, rate: float = RATE) -> float:
    """Steps/s as :func:`physics_direct`, but every DOF moving: each thruster's command
    changes at every 10 Hz control tick (smooth, different per thruster), so the rotors
    are always spinning up or down and surge, sway, heave and yaw are all driven."""
    return _manoeuvre(PROFILE, VehicleState(), seconds, rate)


def _manoeuvre(profile: Any, state: VehicleState, seconds: float, rate: float) -> float:
    """Steps/s of ``Vehicle(profile)`` from ``state`` with the commands of :func:`physics_manoeuvre`."""
    vehicle, thrusters = Vehicle(profile), profile.thruster_set()
    dt, n_th = 1.0 / rate, len(profile.thrusters)
    n = int(seconds * rate)
    every = max(1, int(rate / 10))
    plan = [[0.15 + 0.45 * math.sin(0.9 * k * dt + 1.3 * i) for i in range(n_th)] for k in range(0, n, every)]
    start = time.perf_counter()
    for k in range(n):
        if k % every == 0:
            thrusters.command_all("normalized", plan[k // every], state.time)
        state = vehicle.step_with_thrusters(state, dt, thrusters)
    return n / (time.perf_counter() - start)


def vehicle_only(seconds: float) -> float:
    """Steps/s of the rigid-body step alone (a fixed wrench, no thruster model)."""
    vehicle, state, dt = Vehicle(PROFILE), VehicleState(), 1.0 / RATE
    wrench = np.array([80.0, 10.0, 20.0, 0.0, 0.0, 5.0])
    n = int(seconds * RATE)
    start = time.perf_counter()
    for _ in range(n):
        state = vehicle.step(state, dt, wrench)
    return n / (time.perf_counter() - start)


def physics_scheduled(seconds: float) -> float:
    """Steps/s of the same physics as a scheduler event on a virtual clock."""
    thrusters = PROFILE.thruster_set()
    loop = VehicleLoop(Vehicle(PROFILE), thrusters, VehicleState(), physics_rate=RATE)
    sched = Scheduler(VirtualClock())
    sched.add("control", 0.1, lambda t: thrusters.command_all("normalized", [0.6] * 4 + [0.3] * 4, t), priority=-1)
    loop.attach(sched)
    start = time.perf_counter()
    sched.run(until=seconds)
    return seconds * RATE / (time.perf_counter() - start)


def scheduler_only(seconds: float) -> float:
    """Ticks/s of the same two events with empty callbacks: the scheduler's own cost."""
    sched = Scheduler(VirtualClock())
    sched.add("control", 0.1, lambda t: None, priority=-1)
    sched.add("physics", 1.0 / RATE, lambda t: None)
    start = time.perf_counter()
    sched.run(until=seconds)
    return seconds * RATE / (time.perf_counter() - start)


def physics_6dof(seconds: float, rate: float = RATE, profile: str = "bluerov2_heavy") -> float:
    """Steps/s of the 6-DOF model (a BlueROV2 profile, all thrusters with lag and watchdog,
    RK4 on 12 states) with the commands of :func:`physics_manoeuvre`: every DOF moving."""
    prof = load_vehicle_profile(ROOT / "devices" / "vehicles" / f"{profile}.toml")
    return _manoeuvre(prof, VehicleState(position=np.array([0.0, 0.0, 5.0])), seconds, rate)


def report_6dof() -> None:
    """The 6-DOF BlueROV2 lines (issue #19; goal: Heavy with 8 thrusters >= 1000x real time)."""
    physics_6dof(2.0)  # warm up
    print("physics, 6-DOF BlueROV2 Heavy + 8 thrusters, all DOFs moving:")
    for rate in (RATE, 50.0, 1200.0):
        sps = max(physics_6dof(10.0 if rate < 1000 else 4.0, rate) for _ in range(2))
        print(f"  at {rate:6.0f} Hz {sps:9.0f} steps/s = {sps / rate:6.0f}x real time   ({1e6 / sps:.1f} us/step)")
    sps = max(physics_6dof(10.0, RATE, "bluerov2") for _ in range(2))
    print(f"  BlueROV2 (6 thrusters) at {RATE:g} Hz {sps:9.0f} steps/s = {sps / RATE:6.0f}x real time")


def start_busy(seconds: float) -> subprocess.Popen[bytes]:
    """A busy-loop process pinned to the other core, ending by itself after ``seconds``."""
    code = f"import time\nend = time.monotonic() + {seconds}\nwhile time.monotonic() < end:\n    pass\n"
    proc = subprocess.Popen([sys.executable, "-c", code])
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) >= 2:
        os.sched_setaffinity(proc.pid, {cpus[-1]})
        os.sched_setaffinity(0, {cpus[0]})
    return proc


def jitter(rate: float, seconds: float, use_async: bool = False) -> tuple[np.ndarray, int, int]:
    """Lateness samples [s], late count and skipped count of a physics event at ``rate``."""
    thrusters = PROFILE.thruster_set()
    clock = RealTimeClock()
    loop = VehicleLoop(Vehicle(PROFILE), thrusters, VehicleState(), physics_rate=rate)
    sched = Scheduler(clock, record_lateness=True)
    sched.add("control", 0.1, lambda t: thrusters.command_all("normalized", [0.5] * 8, t), priority=-1)
    ev = loop.attach(sched)[0]
    clock.reset()
    if use_async:
        asyncio.run(sched.run_async(until=seconds))
    else:
        sched.run(until=seconds)
    return np.array(ev.stats.lateness or [0.0]), ev.stats.late, ev.stats.skipped


def contact_loop(seconds: float, start: tuple[float, float, float], cmds: list[float], world: object,
                 rate: float = RATE) -> tuple[float, int]:
    """Steps/s of thrusters + vehicle + the contact step (hilsim.sim.contact) in a plain loop,
    and how many steps were in contact."""
    from hilsim.sim.contact import ContactModel

    vehicle, thrusters = Vehicle(PROFILE), PROFILE.thruster_set()
    contacts = ContactModel.for_profile(PROFILE, world)
    state, dt = VehicleState(position=np.array(start)), 1.0 / rate
    n, every, touching = int(seconds * rate), max(1, int(rate / 10)), 0
    for k in range(int(2 * rate)):  # settle (onto the floor) before timing
        if k % every == 0:
            thrusters.command_all("normalized", cmds, state.time)
        state = contacts.step(state, vehicle.step_with_thrusters(state, dt, thrusters), dt)
    start_t, cpu = time.perf_counter(), time.process_time()
    for k in range(n):
        if k % every == 0:
            thrusters.command_all("normalized", cmds, state.time)
        state = contacts.step(state, vehicle.step_with_thrusters(state, dt, thrusters), dt)
        touching += contacts.last.touching
    _CPU.append((time.process_time() - cpu) / n)
    return n / (time.perf_counter() - start_t), touching


_CPU: list[float] = []  # [s] CPU time per step of the last contact_loop runs (steady under load)


def report_contacts() -> None:
    """Physics x real time with and without a contact (issue #12): Cyclops in the water tank."""
    from hilsim.sim.scenario import load_scenario
    from hilsim.sim.world import Material, World, WorldObject

    tank = load_scenario(ROOT / "scenarios" / "water_tank" / "scenario.toml").build_world()
    from hilsim.config import Doc
    from hilsim.sim.scenario import _terrain

    mesh = _terrain(Doc(ROOT / "x.toml", "", {}), {"size_m": [90.0, 90.0], "resolution_m": 0.25,
                                                   "relief_m": 1.0, "seed": 1}, "t")
    mesh.apply_translation([0.0, 0.0, 20.0])
    seabed = World([WorldObject("seabed", mesh, Material("sand", 2e6), watertight=False)])
    free_cmd, down, corner = [0.6] * 4 + [0.0] * 4, [0.0] * 4 + [1.0] * 4, [1.0] * 8
    print(f"physics with contacts (Cyclops + 8 thrusters + the contact step, {RATE:g} Hz; "
          f"load average {os.getloadavg()[0]:.2f}):")
    rows = [("no contact step (as above)", None),
            ("mid-water, tank world", (tank, (-5.0, 0.0, 1.5), free_cmd, RATE)),
            ("resting on the floor", (tank, (-3.0, 2.0, 2.6), down, RATE)),
            ("in the floor/wall corner", (tank, (9.3, 0.0, 2.6), corner, RATE)),
            ("resting, 50 Hz physics", (tank, (-3.0, 2.0, 2.6), down, 50.0)),
            (f"on a {len(mesh.faces) // 1000}k-triangle terrain", (seabed, (3.0, -2.0, 19.0), down, RATE))]
    for label, args in rows:
        if args is None:
            sps, rate, touching = max(physics_direct(10.0) for _ in range(2)), RATE, 0
        else:
            world, start, cmds, rate = args
            _CPU.clear()
            sps, touching = max((contact_loop(10.0, start, cmds, world, rate) for _ in range(2)),
                                key=lambda r: r[0])
        share = (f"{100.0 * touching / (10.0 * rate):3.0f}% of steps in contact, {1e6 * min(_CPU):6.1f} us CPU/step"
                 if args else "")
        print(f"  {label:30s}{sps:9.0f} steps/s = {sps / rate:6.0f}x real time   ({1e6 / sps:6.1f} us/step) {share}")


def main() -> None:
    print(f"hilsim dynamics benchmark (python {sys.version.split()[0]}, {os.cpu_count()} cpus)")
    physics_direct(2.0)  # warm up
    direct = max(physics_direct(20.0) for _ in range(2))
    with_current = physics_direct(10.0, Current.constant((0.2, 0.1, 0.0)))
    moving = max(physics_manoeuvre(20.0) for _ in range(2))
    scheduled = max(physics_scheduled(20.0) for _ in range(2))
    empty = max(scheduler_only(20.0) for _ in range(2))
    body = max(vehicle_only(20.0) for _ in range(2))
    coarse = max(physics_direct(40.0, rate=50.0) for _ in range(2))
    print(f"physics, Cyclops + 8 thrusters, {RATE:g} Hz steps:")
    print(f"  direct loop      {direct:9.0f} steps/s = {direct / RATE:6.0f}x real time"
          f"   ({1e6 / direct:.1f} us/step)")
    print(f"  with a current   {with_current:9.0f} steps/s = {with_current / RATE:6.0f}x real time")
    print(f"  all DOFs moving  {moving:9.0f} steps/s = {moving / RATE:6.0f}x real time"
          f"   ({1e6 / moving:.1f} us/step; commands change every 0.1 s)")
    print(f"  via scheduler    {scheduled:9.0f} steps/s = {scheduled / RATE:6.0f}x real time"
          f"   ({1e6 / scheduled:.1f} us/step, of which the scheduler's own {1e6 / empty:.1f} us)")
    print(f"  vehicle.step only{body:9.0f} steps/s = {body / RATE:6.0f}x real time   ({1e6 / body:.1f} us/step)")
    print(f"  at 50 Hz physics {coarse:9.0f} steps/s = {coarse / 50.0:6.0f}x real time"
          "   (20 ms steps: RK4 error vs reference < 1e-7)")
    report_6dof()
    report_contacts()
    print(f"  load average {os.getloadavg()[0]:.2f} (other processes share these cores)")
    busy = start_busy(45.0)
    try:
        time.sleep(0.2)
        print("real-time tick lateness, other core busy (physics in the callback):")
        for rate, secs, use_async in ((200.0, 5.0, False), (1000.0, 5.0, False), (200.0, 4.0, True)):
            lat, late, skipped = jitter(rate, secs, use_async)
            p50, p99 = np.percentile(lat, [50, 99]) * 1e3
            mode = "asyncio" if use_async else "sync"
            print(f"  {rate:6.0f} Hz {mode:7s} ticks {lat.size:5d}  p50 {p50:6.3f} ms  p99 {p99:6.3f} ms  "
                  f"max {lat.max() * 1e3:6.3f} ms  late {late}  skipped {skipped}")
    finally:
        busy.kill()
        busy.wait()


if __name__ == "__main__":
    if "--6dof" in sys.argv:
        report_6dof()
    elif "--contacts" in sys.argv:
        report_contacts()
    else:
        main()
