"""The ardupilot-json device in a running bridge, driven by a client written from ArduPilot's
documented JSON backend protocol (servo packets packed here with ``struct``; replies read
by the SIM_JSON.cpp-like parser of tests/protocols/test_ardupilot_json.py, not by our
encoder): lockstep steps, repeats, restarts, bad datagrams, and the physics against
closed forms (buoyancy drift, descent under two vertical thrusters, rest, yaw sense,
the rangefinder). With ``ARDUSUB_SITL`` naming an ArduSub SITL binary, the real
autopilot arms in MANUAL over MAVLink and dives.
"""

from __future__ import annotations

import asyncio
import math
import os
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, AsyncIterator, Callable

import numpy as np
import pytest

from hilsim.runtime.bridge import Bridge
from hilsim.sim.scenario import load_scenario
from hilsim.sim.vehicle import load_vehicle_profile
from hilsim.sim.thrusters import load_thruster_profile
from tests.protocols.test_ardupilot_json import ardupilot_parse

ROOT = Path(__file__).resolve().parents[2]
POOL = ROOT / "scenarios" / "ardusub_pool" / "scenario.toml"
BLUEROV2 = ROOT / "devices" / "vehicles" / "bluerov2.toml"
T200 = ROOT / "devices" / "thrusters" / "t200.toml"
G = 9.80665
FLOOR = 3.0          # [m] the pool floor's top (scenario)
RNG_MOUNT_Z = load_scenario(POOL).sensor("altimeter").mount.position[2]  # [m] the altimeter under the CG
RATE = 400           # [Hz] frame_rate the client asks for (ArduPilot's SIM_RATE_HZ may be set so)
MAGIC16, MAGIC32 = 18458, 29569


def scenario(tmp: Path, start_depth: float = 1.0) -> Path:
    """The shipped pool (its sensors: sonar, DVL, altimeter) with only the ardupilot device (free port)."""
    text = POOL.read_text().split("# ---- devices")[0]
    text = text.replace("position_m = [0.0, 0.0, 0.5]", f"position_m = [0.0, 0.0, {start_depth}]")
    text += '''
[[devices]]
name = "ardupilot"
protocol = "ardupilot-json"
port = 0
'''
    folder = tmp / "pool"
    folder.mkdir(exist_ok=True)
    (folder / "scenario.toml").write_text(text)
    return folder / "scenario.toml"


def servo(count: int, pwm: list[int], rate: int = RATE, channels: int = 16) -> bytes:
    """A servo packet as the readme lays it out (little-endian, packed)."""
    values = pwm + [0] * (channels - len(pwm))
    return struct.pack("<HHI", MAGIC16 if channels == 16 else MAGIC32, rate, count) + \
        struct.pack(f"<{channels}H", *values)


class Client:
    """ArduPilot's side: one servo packet, then wait for the reply (as recv_fdm does)."""

    def __init__(self, port: int) -> None:
        self.addr = ("127.0.0.1", port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.count = 0

    async def exchange(self, data: bytes, timeout: float = 5.0) -> bytes:
        self.sock.sendto(data, self.addr)
        return await asyncio.wait_for(asyncio.get_running_loop().sock_recv(self.sock, 65536), timeout)

    async def silent(self, data: bytes, wait: float = 0.3) -> bool:
        """Send ``data``; True when no reply comes within ``wait`` [s]."""
        self.sock.sendto(data, self.addr)
        try:
            await asyncio.wait_for(asyncio.get_running_loop().sock_recv(self.sock, 65536), wait)
        except asyncio.TimeoutError:
            return True
        return False

    async def fly(self, pwm: list[int], seconds: float) -> dict[str, Any]:
        """Send new frames with ``pwm`` for ``seconds`` of ArduPilot's time; the last state."""
        state: dict[str, Any] | None = None
        for _ in range(int(round(seconds * RATE))):
            self.count += 1
            state = ardupilot_parse(await self.exchange(servo(self.count, pwm)))
            assert state is not None
        assert state is not None
        return state

    def close(self) -> None:
        self.sock.close()


async def session(path: Path, body: Callable[[Bridge, Client], Any], fast: bool = True) -> None:
    bridge = Bridge(path, fast=fast, run_dir=path.parent / "run")
    endpoints = await bridge.start()
    ep = next(e for e in endpoints if e.protocol == "ardupilot-json")
    assert ep.transport == "udp" and ep.address.startswith("127.0.0.1:")
    task = asyncio.ensure_future(bridge.run())
    client = Client(int(ep.address.rsplit(":", 1)[1]))
    try:
        await body(bridge, client)
    finally:
        client.close()
        bridge.stop()
        await asyncio.wait_for(task, 10)
        await bridge.close()


def run(path: Path, body: Callable[[Bridge, Client], Any], fast: bool = True) -> None:
    asyncio.run(asyncio.wait_for(session(path, body, fast), 60))


def heave_root(k: float, kq: float, f: float) -> float:
    """Speed w where k w + kq w|w| = f."""
    w = (-k + math.sqrt(k * k + 4 * kq * abs(f))) / (2 * kq)
    return math.copysign(w, f)


def device(bridge: Bridge) -> Any:
    return next(d for d in bridge.devices if d.protocol == "ardupilot-json")


# -- physics through the wire -------------------------------------------------------

def test_neutral_pwm_drifts_up_at_the_buoyancy_speed_and_reads_minus_g(tmp_path: Path) -> None:
    """All outputs at 1500 us (inside the dead band): only W - B drives the vehicle; it rises at
    the speed where heave damping balances it, level, and its accelerometer reads (0, 0, -g)."""
    prof = load_vehicle_profile(BLUEROV2)
    assert prof.hydrostatics is not None
    heave = prof.params["heave"]
    w_up = heave_root(heave.linear_damping, heave.quadratic_damping, prof.hydrostatics.net_down)
    assert w_up < 0  # positively buoyant

    async def body(bridge: Bridge, c: Client) -> None:
        first = await c.fly([1500] * 6, 1.0 / RATE)
        assert first["position"][2] == pytest.approx(1.0, abs=1e-3)
        s = await c.fly([1500] * 6, 4.0)
        assert s["velocity"][2] == pytest.approx(w_up, rel=0.01)
        assert abs(s["velocity"][0]) < 1e-6 and abs(s["velocity"][1]) < 1e-6
        assert s["quaternion"] == pytest.approx([1.0, 0.0, 0.0, 0.0], abs=1e-6)
        assert s["accel_body"] == pytest.approx([0.0, 0.0, -G], abs=2e-3)
        assert s["gyro"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-6)
        assert s["timestamp"] == pytest.approx(4.0 + 1.0 / RATE, abs=1e-6)
        assert s["no_time_sync"] is True  # the bridge runs --fast

    run(scenario(tmp_path), body)


def test_two_vertical_thrusters_at_1700us_descend_at_the_closed_form_speed(tmp_path: Path) -> None:
    """Servo 5 and 6 (the vertical thrusters of the vectored frame) at 1700 us: each pushes down
    T(s) with s = 0.5 x V / V_nominal on the T200 curve; the descent speed balances 2 T + W - B
    against the heave damping."""
    prof = load_vehicle_profile(BLUEROV2)
    t200 = load_thruster_profile(T200)
    s = 0.5 * (prof.supply_voltage or 0.0) / t200.nominal_voltage
    thrust = float(np.interp(s, t200.curve_speed, t200.curve_thrust))
    heave = prof.params["heave"]
    assert prof.hydrostatics is not None
    w_down = heave_root(heave.linear_damping, heave.quadratic_damping, 2 * thrust + prof.hydrostatics.net_down)

    async def body(bridge: Bridge, c: Client) -> None:
        st = await c.fly([1500, 1500, 1500, 1500, 1700, 1700], 3.0)
        assert st["velocity"][2] == pytest.approx(w_down, rel=0.01)
        assert w_down > 0.2
        assert st["quaternion"] == pytest.approx([1.0, 0.0, 0.0, 0.0], abs=1e-4)  # symmetric: no roll
        assert st["position"][2] > 1.0 + 0.5 * 3.0 * w_down
        # the rangefinder follows the floor: height of the altimeter above it
        assert st["rng_1"] == pytest.approx(FLOOR - st["position"][2] - RNG_MOUNT_Z, abs=1e-3)

    run(scenario(tmp_path), body)


def test_rng_1_is_the_height_above_the_pool_floor(tmp_path: Path) -> None:
    async def body(bridge: Bridge, c: Client) -> None:
        st = await c.fly([1500] * 6, 1.0 / RATE)
        assert st["rng_1"] == pytest.approx(FLOOR - 1.0 - RNG_MOUNT_Z, abs=1e-3)

    run(scenario(tmp_path), body)


@pytest.mark.parametrize("sense", [1, -1])
def test_the_vectored_yaw_pattern_turns_clockwise(tmp_path: Path, sense: int) -> None:
    """ArduSub's vectored frame: yaw factors +1, -1, -1, +1 on motors 1-4. PWM above 1500 us on
    the +1 motors and below on the -1 motors is a clockwise turn (seen from above: heading
    increases, gyro z > 0); the opposite pattern turns anticlockwise."""
    d = 150 * sense
    pwm = [1500 + d, 1500 - d, 1500 - d, 1500 + d, 1500, 1500]

    async def body(bridge: Bridge, c: Client) -> None:
        st = await c.fly(pwm, 2.0)
        w, x, y, z = st["quaternion"]
        yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        assert sense * st["gyro"][2] > 0.3
        assert sense * yaw > 0.3

    run(scenario(tmp_path), body)


def test_thirty_two_channel_packets_fly_the_same(tmp_path: Path) -> None:
    async def body(bridge: Bridge, c: Client) -> None:
        r16 = ardupilot_parse(await c.exchange(servo(1, [1500] * 4 + [1700, 1700])))
        r32 = ardupilot_parse(await c.exchange(servo(2, [1500] * 4 + [1700, 1700], channels=32)))
        assert r16 is not None and r32 is not None
        assert r32["timestamp"] == pytest.approx(r16["timestamp"] + 1.0 / RATE)
        assert device(bridge).status()["frames"] == 2

    run(scenario(tmp_path), body)


# -- lockstep ---------------------------------------------------------------------------

def test_a_repeated_frame_count_gets_the_same_reply_and_no_step(tmp_path: Path) -> None:
    async def body(bridge: Bridge, c: Client) -> None:
        await c.fly([1500] * 4 + [1700, 1700], 0.5)
        t_sim = bridge.vehicle.state.time
        again = servo(c.count, [1900] * 6)  # ArduPilot re-sends the same packet; even other PWM: no step
        first = await c.exchange(again)
        second = await c.exchange(again)
        assert first == second
        assert bridge.vehicle.state.time == t_sim
        st = device(bridge).status()
        assert st["repeats"] == 2 and st["frames"] == 0.5 * RATE
        nxt = ardupilot_parse(await c.exchange(servo(c.count + 1, [1500] * 6)))
        old = ardupilot_parse(first)
        assert nxt is not None and old is not None
        assert nxt["timestamp"] == pytest.approx(old["timestamp"] + 1.0 / RATE)

    run(scenario(tmp_path), body)


def test_the_simulation_waits_while_ardupilot_is_silent(tmp_path: Path) -> None:
    async def body(bridge: Bridge, c: Client) -> None:
        await c.fly([1500] * 6, 0.1)
        t_sim = bridge.vehicle.state.time
        await asyncio.sleep(0.5)
        assert bridge.vehicle.state.time == t_sim
        assert device(bridge).status()["frames"] == 0.1 * RATE

    run(scenario(tmp_path), body)


def test_a_restart_puts_the_vehicle_back_at_the_start(tmp_path: Path) -> None:
    async def body(bridge: Bridge, c: Client) -> None:
        moved = await c.fly([1500] * 4 + [1800, 1800], 2.0)
        assert moved["position"][2] > 1.5
        c.count = 0  # a new ArduPilot process counts from 0 again
        st = await c.fly([1500] * 6, 1.0 / RATE)
        assert st["position"][2] == pytest.approx(1.0, abs=1e-3)
        assert st["timestamp"] == pytest.approx(1.0 / RATE)  # its clock starts again too
        assert abs(st["velocity"][2]) < 0.01
        assert device(bridge).status()["restarts"] == 1

    run(scenario(tmp_path), body)


def test_garbage_and_short_packets_are_counted_and_never_answered(tmp_path: Path) -> None:
    async def body(bridge: Bridge, c: Client) -> None:
        await c.fly([1500] * 6, 0.05)
        bad = [b"hello", b"\x1a\x48", servo(99, [1500] * 6)[:30], struct.pack("<HHI16H", 1234, 400, 99, *[1500] * 16),
               servo(99, [1500] * 6) + b"x", struct.pack("<HHI16H", MAGIC16, 0, 99, *[1500] * 16)]
        t_sim = bridge.vehicle.state.time
        for data in bad:
            assert await c.silent(data, 0.2)
        assert bridge.vehicle.state.time == t_sim
        st = device(bridge).status()
        assert st["malformed"] == len(bad)
        good = await c.fly([1500] * 6, 1.0 / RATE)  # and it keeps serving
        assert good["timestamp"] == pytest.approx(0.05 + 1.0 / RATE)

    run(scenario(tmp_path), body)


def test_status_shows_frames_and_the_lockstep_rate(tmp_path: Path) -> None:
    async def body(bridge: Bridge, c: Client) -> None:
        await c.fly([1500] * 6, 0.5)
        st = bridge.status()["devices"]["ardupilot"]
        assert st["frames"] == 0.5 * RATE and st["restarts"] == 0 and st["rate_hz"] > 50

    run(scenario(tmp_path), body)


# -- the real ArduSub ---------------------------------------------------------------------

SITL = os.environ.get("ARDUSUB_SITL", "")


@pytest.mark.skipif(not SITL, reason="ARDUSUB_SITL does not name an ArduSub SITL binary "
                                     "(build one with shared/tools/ardusub-sitl-build)")
def test_real_ardusub_arms_in_manual_and_dives(tmp_path: Path) -> None:
    """ArduSub SITL flies the pool's BlueROV2, as a user runs it: ``hilsim run`` and ArduSub in
    their own processes, this test the ground station. Arm in MANUAL, command down for 8 s:
    ArduSub's own depth (its simulated water-pressure barometer, relative to where it booted)
    is what hilsim's vehicle did (truth.csv). ``ARDUSUB_DEFAULTS``: its defaults file
    (sub.parm), else the one in the binary's source tree."""
    import csv
    import json
    import signal

    mavutil = pytest.importorskip("pymavlink.mavutil")
    path = scenario(tmp_path, start_depth=0.5)
    defaults = os.environ.get("ARDUSUB_DEFAULTS") or str(
        Path(SITL).resolve().parents[3] / "Tools" / "autotest" / "default_params" / "sub.parm")
    endpoints, truth = tmp_path / "endpoints.json", tmp_path / "truth.csv"
    bridge = subprocess.Popen([sys.executable, "-m", "hilsim", "run", str(path), "--endpoints", str(endpoints),
                               "--truth", str(truth), "--pty-dir", str(tmp_path / "run")], cwd=ROOT,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sitl = None
    try:
        deadline = time.monotonic() + 60
        while not endpoints.exists():
            assert bridge.poll() is None and time.monotonic() < deadline, "hilsim run did not start"
            time.sleep(0.2)
        time.sleep(0.3)
        eps = json.loads(endpoints.read_text())
        eps = eps if isinstance(eps, list) else eps["endpoints"]
        port = next(e for e in eps if e["protocol"] == "ardupilot-json")["address"].rsplit(":", 1)[1]
        cmd = [SITL, "-w", "--model", "JSON:127.0.0.1", "--home", "55.7000,12.5500,0,0", "--sim-port-out",
               port, "--serial0", "tcp:0", "-I", "7"]
        if Path(defaults).exists():
            cmd += ["--defaults", defaults]
        sitl = subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        (t0, start_alt), (t1, end_alt) = _dive(mavutil, 5760 + 70)
    finally:
        if sitl is not None:
            sitl.terminate()
            try:
                sitl.wait(5)
            except subprocess.TimeoutExpired:
                sitl.kill()  # SITL may not stop on SIGTERM
                sitl.wait(5)
        bridge.send_signal(signal.SIGINT)
        bridge.wait(30)
    with open(truth, newline="") as f:
        rows = list(csv.DictReader(f))
    times = np.array([float(r["time_s"]) for r in rows])
    depths = np.array([float(r["down_m"]) for r in rows])
    dived = float(np.interp(t1, times, depths) - np.interp(t0, times, depths))
    assert dived > 0.5  # ArduSub's outputs pushed hilsim's vehicle down ...
    assert any(r["pwm_5"] not in ("0", "1500") for r in rows)  # ... through its servo outputs
    # ... and ArduSub saw it: its altitude (time_boot_ms = simulated time in lockstep) fell by the
    # depth gained; its simulated barometer reads 1024 kg/m^3 water with BARO_SPEC_GRAV 1 (default)
    assert start_alt - end_alt == pytest.approx(1.024 * dived, rel=0.05, abs=0.05)


def _dive(mavutil: Any, port: int) -> tuple[tuple[float, float], tuple[float, float]]:
    """As a ground station (system 255): arm in MANUAL, stick down (z 150 of 0..1000) for 8 s.
    ArduSub's (time since boot [s], relative altitude [m]) from GLOBAL_POSITION_INT when armed
    and at the end."""
    deadline = time.monotonic() + 60
    while True:  # wait for ArduSub's MAVLink port (a link opened while it boots stays silent)
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            assert time.monotonic() < deadline, "ArduSub's MAVLink port never opened"
            time.sleep(0.5)
    time.sleep(3.0)
    m = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255)
    assert m.wait_heartbeat(timeout=30) is not None, "no heartbeat from ArduSub"
    deadline = time.monotonic() + 60
    m.mav.request_data_stream_send(m.target_system, m.target_component, mavutil.mavlink.MAV_DATA_STREAM_ALL, 10, 1)
    for name, value in (("ARMING_CHECK", 0), ("FS_PILOT_INPUT", 0), ("FS_GCS_ENABLE", 0)):
        m.mav.param_set_send(m.target_system, m.target_component, name.encode(), value,
                             mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
    m.set_mode(19)  # MANUAL
    armed, beat = False, 0.0
    alt: tuple[float, float] | None = None
    start_alt: tuple[float, float] | None = None
    down_until: float | None = None
    while time.monotonic() < deadline:
        now = time.monotonic()
        if now - beat > 1.0:
            m.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            beat = now
            if not armed:
                m.mav.command_long_send(m.target_system, m.target_component,
                                        mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        m.mav.manual_control_send(m.target_system, 0, 0, 150 if armed else 500, 0, 0)
        msg = m.recv_match(blocking=True, timeout=0.1)
        while msg is not None:
            kind = msg.get_type()
            if kind == "HEARTBEAT" and msg.get_srcSystem() == m.target_system:
                armed = bool(msg.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            elif kind == "GLOBAL_POSITION_INT":
                alt = (msg.time_boot_ms / 1000.0, msg.relative_alt / 1000.0)
            msg = m.recv_match(blocking=False)
        if armed and alt is not None and start_alt is None:
            start_alt, down_until = alt, now + 8.0
        if down_until is not None and now > down_until:
            break
    m.close()
    assert start_alt is not None and alt is not None, f"ArduSub never armed ({armed}) or sent its position ({alt})"
    return start_alt, alt


def test_the_truth_record_carries_the_pwm_per_servo_output(tmp_path: Path) -> None:
    import csv

    path = scenario(tmp_path)

    async def body(bridge: Bridge, c: Client) -> None:
        await c.fly([1500, 1500, 1500, 1500, 1700, 1650], 1.0)

    run(path, body)
    with open(path.parent / "run" / "truth.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows and [f"pwm_{i}" for i in range(1, 7)] == [k for k in rows[0] if k.startswith("pwm_")]
    last = rows[-1]
    assert (last["pwm_1"], last["pwm_5"], last["pwm_6"]) == ("1500", "1700", "1650")
