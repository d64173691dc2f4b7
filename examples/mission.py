#!/usr/bin/env python3
"""A reference AUV control stack: dive, turn, find the target on the sonar, approach it, hold station.

A separate program that talks to the vehicle only through its wire protocols
and public client libraries, so it runs unchanged against ``hilsim run`` or a
real vehicle exposing the same devices (see ``examples/README.md``):

- depth: Keller Series 30 on Modbus TCP (pymodbus), P1 [bar abs] float32 at 0x0002;
- heading: WitMotion HWT905 on Modbus TCP, yaw at 0x3F and rate GZ at 0x39 (int16,
  the sensor's Z-up frame: NED heading = -yaw, NED yaw rate = -GZ);
- thrusters: 8 VESCs on CAN through socketcand (python-can), SET_DUTY / SET_RPM /
  SET_CURRENT encoded with cantools from ``protocols/vesc_can.dbc`` (or packed by
  hand per the DBC when the file is absent); STATUS_1 read back (ERPM);
- sonar: the DIDSON-like DDF stream over a plain TCP socket;
- DVL: Water Linked DVL A50 over its TCP JSON API (velocity reports: surge speed for the approach and
  the hold, altitude for the floor's depth);
- GNSS: NMEA 0183 on a serial port (pyserial), GGA fixes logged in a surfacing phase at the end.

Timing: the stack runs on the simulation's clock, read from the sonar frame
headers (frame time, microseconds since the epoch, offset 4). It estimates
the rate of that clock against its own monotonic clock from the arrivals, so
the same code works in real time and under ``hilsim run --time-scale K``; the
control loop ticks at a fixed rate of that clock, far more often than the
ESC watchdog (0.5 s) needs.

Usage::

    python examples/mission.py ENDPOINTS.json [--out out/mission] [--depth 1.8] ...

Exit status: 0 mission completed, 1 mission failed or aborted, 2 bad usage.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:  # the stack's modules live next to this file
    sys.path.insert(0, str(HERE))

from auv_control import Mission, Params, wrap180  # noqa: E402
from auv_io import (VESC_COMMANDS, DvlClient, EscHealth, GnssReader, ModbusSensors, VescCan, host_port,  # noqa: E402
                    load_endpoints)
from auv_sonar import DdfSonar, Detection, SimClock, TargetDetector  # noqa: E402
from auv_vehicle import THRUSTERS  # noqa: E402
from mission_report import write_outputs  # noqa: E402

DEFAULT_DBC = HERE.parent / "protocols" / "vesc_can.dbc"


@dataclass
class Log:
    """Per-tick records (columns) for the summary, the CSV and the plots."""
    columns: dict[str, list[float]] = field(default_factory=dict)

    def add(self, **row: float) -> None:
        for k, v in row.items():
            self.columns.setdefault(k, []).append(v)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("endpoints", type=Path, help="endpoints JSON written by `hilsim run --endpoints FILE`")
    ap.add_argument("--out", type=Path, default=Path("out/mission"), help="output folder (default out/mission)")
    ap.add_argument("--rho", type=float, default=998.0, help="water density [kg/m^3] for depth (default 998)")
    ap.add_argument("--depth", type=float, default=Params.depth, help="depth to dive to and hold [m] (1.8)")
    ap.add_argument("--headings", default="20,0",
                    help="headings [deg] to turn to in order before the approach (default 20,0; '' for none)")
    ap.add_argument("--hold-range", type=float, default=Params.hold_range,
                    help="sonar range of the target's shadow edge to approach to and hold [m] (1.25)")
    ap.add_argument("--hold-time", type=float, default=Params.hold_time, help="station keeping [s] (20)")
    ap.add_argument("--approach-speed", type=float, default=Params.approach_speed, help="[m/s] (0.05)")
    ap.add_argument("--control-rate", type=float, default=Params.control_rate,
                    help="control ticks per second of simulation time (10)")
    ap.add_argument("--sonar-rate", type=float, default=5.0,
                    help="sonar frame rate to ask for [Hz] (RATE command; 0: leave it; default 5)")
    ap.add_argument("--esc", choices=sorted(VESC_COMMANDS), default="duty",
                    help="VESC command: duty (SET_DUTY, default), rpm (SET_RPM, electrical rpm) or current "
                         "(SET_CURRENT; thrusts below its wide dead band are dithered)")
    ap.add_argument("--dbc", type=Path, default=DEFAULT_DBC,
                    help="VESC DBC for cantools (default protocols/vesc_can.dbc; missing: packed by hand)")
    ap.add_argument("--timeout", type=float, default=Params.timeout, help="mission limit [s of sim time] (240)")
    ap.add_argument("--surface", action="store_true",
                    help="after the hold, surface and wait for GNSS fixes (needs the bridge's nmea-gnss endpoint)")
    ap.add_argument("--surface-depth", type=float, default=Params.surface_depth,
                    help="[m] body depth of the surfacing phase (0.2: the GNSS mast out of the water)")
    ap.add_argument("--gnss-fixes", type=int, default=Params.gnss_fixes,
                    help="GNSS fixes to log at the surface before the mission completes (3)")
    ap.add_argument("--status-every", type=float, default=1.0, help="status line period [s of sim time] (1)")
    ap.add_argument("--no-plots", action="store_true", help="summary JSON and CSV only")
    ap.add_argument("--quiet", action="store_true", help="no live status lines")
    a = ap.parse_args(argv)
    try:
        a.headings = tuple(float(h) for h in a.headings.split(",") if h.strip())
    except ValueError:
        ap.error(f"--headings: expected numbers separated by commas, got {a.headings!r}")
    if not (a.control_rate >= 2.5):
        ap.error("--control-rate must be at least 2.5 Hz (the ESC watchdog is 0.5 s)")
    return a


def status_line(t: float, m: Mission, depth: float, heading: float, det: Detection | None,
                thrusts: np.ndarray, cmds: list[float], kind: str, stale: str) -> str:
    fx, _, fz, mz = m.force
    rng = f"{det.shadow_edge:4.2f} m" if det is not None and det.found else " -- m "
    alt = f"  alt {m.dvl_altitude:4.2f} m" if math.isfinite(m.dvl_altitude) else ""
    gnss = f"  gnss fixes {len(m.gnss_fixes)}" if m.phase == "surface" else ""
    unit = {"duty": "", "rpm": " [erpm]", "current": " [A]"}[kind]
    fmt = (lambda v: f"{v:+.0f}") if kind == "rpm" else (lambda v: f"{v:+.2f}")
    h = " ".join(fmt(c) for c in cmds[:4])
    v = " ".join(fmt(c) for c in cmds[4:])
    return (f"t={t:6.1f}s {m.phase:<9} depth {depth:4.2f} m  hdg {wrap180(heading):+6.1f} deg  "
            f"target {rng}{alt}{gnss}  F x{fx:+5.1f} z{fz:+5.1f} N  Mz{mz:+5.1f} Nm  {kind}{unit} h[{h}] v[{v}]{stale}")


def run(a: argparse.Namespace) -> int:
    ep = load_endpoints(a.endpoints)
    if a.surface and "nmea-gnss" not in ep:
        raise ValueError(f"{a.endpoints}: --surface needs a GNSS (no nmea-gnss endpoint)")
    p = Params(depth=a.depth, headings=a.headings, hold_range=a.hold_range, hold_time=a.hold_time,
               approach_speed=a.approach_speed, control_rate=a.control_rate, timeout=a.timeout,
               surface=a.surface, surface_depth=a.surface_depth, gnss_fixes=a.gnss_fixes)
    clock = SimClock()
    wall_start = time.monotonic()
    sonar = DdfSonar(*host_port(ep["ddf-stream"]["address"]), a.sonar_rate or None, clock, TargetDetector)
    sensors = ModbusSensors(host_port(ep["modbus-keller"]["address"]), int(ep["modbus-keller"].get("device_id", 1)),
                            host_port(ep["modbus-witmotion"]["address"]),
                            int(ep["modbus-witmotion"].get("device_id", 0x50)), a.rho)
    vc = ep["vesc-can"]
    vesc = VescCan(vc.get("host") or host_port(vc["address"])[0], int(vc.get("port") or host_port(vc["address"])[1]),
                   vc.get("channel", "can0"), a.esc, a.dbc)
    dvl = DvlClient(*host_port(ep["dvl-json"]["address"])) if "dvl-json" in ep else None
    gnss = GnssReader(ep["nmea-gnss"]["address"], int(ep["nmea-gnss"].get("baudrate", 9600))) if p.surface else None
    if dvl is None:
        print("mission: no DVL endpoint; surge speed from the model, floor from the sonar", flush=True)
    mission = Mission(p, esc=a.esc)
    thr = mission.thr
    health = EscHealth([n for n, _, _, _ in THRUSTERS])
    log = Log()
    frames_log = Log()
    gnss_log = Log()
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):   # stop cleanly: thrusters to zero, summary written
        signal.signal(sig, lambda *_: stop.set())
    dt = 1.0 / p.control_rate
    zero = [0.0] * len(THRUSTERS)
    t0 = math.nan
    last_depth, last_heading, last_depth_t = math.nan, math.nan, -math.inf
    last_det: Detection | None = None
    late = 0
    last_step: float | None = None
    next_status = -math.inf
    try:
        while not clock.ready() and not stop.is_set():   # three frames: the clock's rate
            if sonar.error or time.monotonic() - wall_start > 30.0:
                raise ConnectionError(f"no sonar frames from the DDF stream ({sonar.error or 'timeout'})")
            time.sleep(0.01)
        t_tick = clock.now()
        t0 = t_tick
        while not mission.done and not stop.is_set():
            # -- pace: wait for the next tick of simulation time --------------------------------
            t_tick += dt
            while True:
                delay = clock.wall_at(t_tick) - time.monotonic()
                if delay <= 0:
                    break
                time.sleep(min(delay, 0.05))
            t_now = clock.now()
            if t_now - t_tick > dt:          # fell behind: skip ticks, never send a burst
                late += int((t_now - t_tick) / dt)
                t_tick = t_now
            t = t_tick - t0
            if sonar.error:
                mission.fail(t, f"sonar stream: {sonar.error}")
                break
            # -- sense ---------------------------------------------------------------------------
            depth = sensors.depth()
            depth_ok = math.isfinite(depth)
            heading, yaw_rate = sensors.attitude()
            if math.isfinite(depth):
                last_depth, last_depth_t = depth, t
            elif t - last_depth_t > 2.0:
                mission.fail(t, "no depth for 2 s")
                break
            if math.isfinite(heading):
                last_heading = heading
            else:
                heading, yaw_rate = last_heading, 0.0
            if not (math.isfinite(heading) and math.isfinite(last_depth)):
                continue  # nothing to steer by yet
            if not mission.phases:
                mission.start(t, heading)
            for f in sonar.take():
                tf = f.time - t0
                mission.sonar(tf, f.detection)
                last_det = f.detection
                d = f.detection
                frames_log.add(t=tf, number=f.number, found=float(d.found), shadow_edge=d.shadow_edge,
                               near_edge=d.near_edge, floor_far=d.floor_far, floor_near=d.floor_near,
                               hdr_depth=f.depth, hdr_heading=f.heading)
            report = dvl.latest() if dvl is not None else None
            mission.dvl(report, last_depth)
            for fix in (gnss.take() if gnss is not None else []):
                mission.gnss(t, fix)
                if fix["quality"] > 0:
                    gnss_log.add(t=t, quality=fix["quality"], lat_deg=fix["lat_deg"], lon_deg=fix["lon_deg"],
                                 alt_m=fix["alt_m"], satellites=fix["satellites"], hdop=fix["hdop"])
            stale_age = clock.last_frame_age()
            # -- act -----------------------------------------------------------------------------
            step_dt = dt if last_step is None else min(max(t - last_step, 1e-3), 1.0)  # the real interval
            last_step = t
            thrusts = mission.step(t, step_dt, last_depth, heading, yaw_rate)
            cmds = [thr.command(a.esc, float(x)) for x in thrusts]
            vesc.send(cmds)
            erpm = [float(vesc.erpm.get(cid, math.nan)) for _, cid, _, _ in THRUSTERS]
            for name in health.update(t, step_dt, [float(x) for x in thrusts], erpm):
                print(f"t={t:6.1f}s WARNING thruster {name}: its ESC reports a stopped rotor while commanded; "
                      "flying on the others", flush=True)
            if t > p.timeout and not mission.done:
                mission.fail(t, f"timeout {p.timeout:g} s")
            fx, fy, fz, mz = mission.force
            rng = mission.target_range(t)
            log.add(t=t, depth=last_depth, depth_est=mission.depth_obs.x, heave_rate=mission.depth_obs.v,
                    heading=heading, yaw_rate=yaw_rate, heading_ref=mission.heading_ref, depth_ref=mission.depth_ref,
                    range=rng, distance=mission.track.d if mission.track.valid(t) else math.nan,
                    sonar_height=mission.track.h, speed_bias=mission.track.speed_bias,
                    surge_speed=mission.surge_obs.v, fx=fx, fz=fz, mz=mz,
                    dvl_vx=mission.dvl_u, dvl_altitude=mission.dvl_altitude,
                    floor_depth=mission.track.floor_depth,
                    phase=float(mission.plan.index(mission.phase)) if mission.phases else -1.0,
                    **{f"cmd{i}": c for i, c in enumerate(cmds)},
                    depth_ok=float(depth_ok),
                    **{f"thrust{i}": float(x) for i, x in enumerate(thrusts)},
                    **{f"erpm{i}": e for i, e in enumerate(erpm)})
            if not a.quiet and t >= next_status:
                next_status = (math.floor(t / a.status_every) + 1) * a.status_every
                stale = f"  (no sonar frame for {stale_age:.1f} s)" if stale_age > 1.0 else ""
                print(status_line(t, mission, last_depth, heading, last_det, thrusts, cmds, a.esc, stale), flush=True)
        if stop.is_set() and not mission.done:
            mission.fail(clock.now() - t0 if math.isfinite(t0) else 0.0, "stopped by a signal")
    finally:
        try:
            vesc.send(zero)   # leave the thrusters stopped (the ESC watchdog would too)
        except Exception:  # noqa: BLE001 - the bus may be gone already
            pass
        wall = time.monotonic() - wall_start
        sonar.close()
        sensors.close()
        vesc.close()
        if dvl is not None:
            dvl.close()
        if gnss is not None:
            gnss.close()
    info = {"time_scale_estimate": clock.rate, "wall_s": wall, "t0_unix": t0, "late_ticks": late,
            "frames_received": sonar.received, "frames_lost": sonar.lost, "sonar_replies": sonar.replies,
            "modbus_errors": sensors.errors, "can_frames_sent": vesc.sent, "esc_status_frames": vesc.status_frames,
            "esc_erpm_last": {str(k): v for k, v in sorted(vesc.erpm.items())}, "esc_command": a.esc,
            "dbc": str(a.dbc) if vesc.db is not None else None, "thruster_faults": health.faults,
            "dvl_reports": dvl.reports if dvl is not None else 0, "dvl_valid": dvl.valid if dvl is not None else 0,
            "gnss_sentences": gnss.sentences if gnss is not None else 0, "gnss_log": gnss_log.columns}
    summary = write_outputs(a.out, p, mission, log.columns, frames_log.columns, info, plots=not a.no_plots,
                            thruster_names=[n for n, _, _, _ in THRUSTERS])
    print(summary["text"], flush=True)
    return 0 if mission.failure is None else 1


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    try:
        return run(a)
    except (OSError, ValueError, ConnectionError) as e:
        print(f"mission: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
