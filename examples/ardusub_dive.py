"""Fly the real ArduSub in hilsim's pool over MAVLink (pymavlink): arm, hold a depth in
ALT_HOLD, drive a square, surface. It knows hilsim only through ArduSub.

Start the two programs of README "Fly ArduSub in hilsim" first (``hilsim run
scenarios/ardusub_pool`` and ArduSub SITL with ``--model JSON:127.0.0.1 --home
55.7000,12.5500,0,0``), then::

    python examples/ardusub_dive.py --connect tcp:127.0.0.1:5760 [--depth 1.5] [--side 8]

Or let it start both: ``--sitl /path/to/ardusub`` (and ``--defaults sub.parm``)
starts the bridge and ArduSub, flies, and stops them.

Pilot input is MAVLink MANUAL_CONTROL from system id 255 (ArduSub's SYSID_MYGCS):
x forward, y right, r yaw in -1000..1000, z 0..1000 with 500 neutral (above 500 up).
In ALT_HOLD ArduSub holds the depth it has when z is neutral. Depth is read from
GLOBAL_POSITION_INT.relative_alt (negative below the surface), heading from VFR_HUD.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

try:
    from pymavlink import mavutil
except ImportError:  # pragma: no cover - told to the user
    sys.exit("examples/ardusub_dive.py needs pymavlink: pip install pymavlink")

MANUAL, STABILIZE, ALT_HOLD = 19, 0, 2
POOL_HOME = "55.7000,12.5500,0,0"  # scenarios/ardusub_pool: [world] origin, altitude 0 (the surface)
ROOT = Path(__file__).resolve().parents[1]


class Pilot:
    """A ground station's side of ArduSub: heartbeats, modes, arming, stick input, telemetry."""

    def __init__(self, url: str, timeout: float = 60.0) -> None:
        if url.startswith("tcp:"):  # wait for ArduSub's port: a link opened while it boots stays silent
            host, _, port = url[4:].rpartition(":")
            deadline = time.monotonic() + timeout
            while True:
                try:
                    socket.create_connection((host, int(port)), timeout=1.0).close()
                    break
                except OSError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.5)
            time.sleep(3.0)
        self.m = mavutil.mavlink_connection(url, source_system=255)
        if self.m.wait_heartbeat(timeout=timeout) is None:
            raise RuntimeError(f"no heartbeat from ArduSub on {url}")
        self.depth = 0.0      # [m] positive down
        self.heading = 0.0    # [deg]
        self.armed = False
        self._beat = 0.0
        self.m.mav.request_data_stream_send(self.m.target_system, self.m.target_component,
                                            mavutil.mavlink.MAV_DATA_STREAM_ALL, 10, 1)

    def param(self, name: str, value: float) -> None:
        self.m.mav.param_set_send(self.m.target_system, self.m.target_component, name.encode(), float(value),
                                  mavutil.mavlink.MAV_PARAM_TYPE_REAL32)

    def poll(self) -> None:
        """Read what arrived; send a GCS heartbeat once a second."""
        now = time.monotonic()
        if now - self._beat > 1.0:
            self.m.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            self._beat = now
        while (msg := self.m.recv_match(blocking=False)) is not None:
            kind = msg.get_type()
            if kind == "GLOBAL_POSITION_INT":
                self.depth = -msg.relative_alt / 1000.0
            elif kind == "VFR_HUD":
                self.heading = float(msg.heading)
            elif kind == "HEARTBEAT" and msg.get_srcSystem() == self.m.target_system:
                self.armed = bool(msg.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    def stick(self, x: int = 0, y: int = 0, z: int = 500, r: int = 0) -> None:
        self.m.mav.manual_control_send(self.m.target_system, x, y, z, r, 0)

    def fly(self, seconds: float, until: Any = None, **stick: int) -> bool:
        """Hold ``stick`` at 10 Hz for up to ``seconds``; True as soon as ``until()`` holds."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.stick(**stick)
            self.poll()
            if until is not None and until():
                return True
            time.sleep(0.1)
        return until is None

    def mode(self, mode: int) -> None:
        self.m.set_mode(mode)

    def arm(self, on: bool = True, timeout: float = 30.0) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.m.mav.command_long_send(self.m.target_system, self.m.target_component,
                                         mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1 if on else 0,
                                         0, 0, 0, 0, 0, 0)
            self.fly(1.0, until=lambda: self.armed == on)
            if self.armed == on:
                return
        raise RuntimeError(f"ArduSub did not {'arm' if on else 'disarm'}")


def turned(start: float, now: float, by: float) -> bool:
    """Whether the heading [deg] went clockwise from ``start`` by ``by`` or more (signed, -180..180)."""
    return (now - start + 540.0) % 360.0 - 180.0 >= by


def mission(p: Pilot, depth: float, side: float) -> None:
    print("setting parameters (absolute depth, no stick-input failsafe while we script)")
    p.param("BARO_SPEC_GRAV", 1.024)
    p.param("BARO1_GND_PRESS", 101325.0)
    p.mode(MANUAL)
    p.arm()
    print(f"armed; descending to {depth} m in ALT_HOLD")
    p.mode(ALT_HOLD)
    p.fly(60.0, until=lambda: p.depth >= depth, z=250)
    p.fly(3.0)  # neutral stick: ArduSub holds this depth
    print(f"holding {p.depth:.2f} m; a square of {side:.0f} s legs")
    for leg in range(4):
        p.fly(side, x=500)
        start = p.heading
        p.fly(20.0, until=lambda: turned(start, p.heading, 80.0), r=200)
        p.fly(2.0)
        print(f"  leg {leg + 1}: depth {p.depth:.2f} m, heading {p.heading:.0f} deg")
    print("surfacing")
    p.fly(90.0, until=lambda: p.depth < 0.15, z=900)
    p.mode(MANUAL)
    p.arm(False)
    print(f"disarmed at {p.depth:.2f} m")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", default="tcp:127.0.0.1:5760", help="ArduSub's MAVLink (default %(default)s)")
    ap.add_argument("--depth", type=float, default=1.5, help="[m] depth to hold")
    ap.add_argument("--side", type=float, default=8.0, help="[s] forward time per leg of the square")
    ap.add_argument("--sitl", help="start hilsim (scenarios/ardusub_pool) and this ArduSub SITL binary first")
    ap.add_argument("--defaults", help="ArduSub defaults file for --sitl (Tools/autotest/default_params/sub.parm)")
    args = ap.parse_args()
    procs: list[subprocess.Popen[bytes]] = []
    try:
        if args.sitl:
            procs.append(subprocess.Popen([sys.executable, "-m", "hilsim", "run",
                                           str(ROOT / "scenarios" / "ardusub_pool")], cwd=ROOT))
            time.sleep(5.0)
            cmd = [args.sitl, "-w", "--model", "JSON:127.0.0.1", "--home", POOL_HOME, "--serial0", "tcp:0"]
            if args.defaults:
                cmd += ["--defaults", args.defaults]
            procs.append(subprocess.Popen(cmd, cwd=os.environ.get("TMPDIR", "/tmp")))
        mission(Pilot(args.connect), args.depth, args.side)
    finally:
        for proc in reversed(procs):
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()


if __name__ == "__main__":
    main()
