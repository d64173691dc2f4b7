"""Scripted events and injected faults, seen through real clients on a running bridge.

The expected effects on the wire come from the devices' documented behaviour
(Keller: NaN on a channel error; VESC CAN frames packed here with struct per
the reference layout; VESC UART packets checked here with CRC16-XMODEM).
"""

from __future__ import annotations

import asyncio
import binascii
import math
import re
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import serial

from hilsim.config import ConfigError
from hilsim.resources import find_scenario
from hilsim.runtime.bridge import Bridge

BASE = find_scenario("water_tank").read_text()
HEAD = BASE[: BASE.index("# ---- devices")]
DEVICES = '''
[[devices]]
name = "sonar_ddf"
protocol = "ddf-stream"
sensor = "sonar"

[[devices]]
name = "depth"
protocol = "modbus-keller"
transport = ["tcp"]

[[devices]]
name = "vesc_can"
protocol = "vesc-can"
transport = "socketcand"
channel = "can0"
status_rate_hz = 10               # 240 frames/s: python-can's socketcand reader keeps up on a busy CI box

[[devices]]
name = "vesc_uart"
protocol = "vesc-uart"
baudrate = 115200
'''
TIMELINE = '''
[[timeline]]
at_s = 0.5
action = "current"
velocity_m_s = [0.3, 0.0, 0.0]

[[timeline]]
at_s = 1.0
action = "fault"
target = "depth"
fault = "dropout"
duration_s = 1.5

[[timeline]]
at_s = 1.0
action = "fault"
target = "thruster:vertical_front_left"
fault = "fail"

[[timeline]]
at_s = 1.0
action = "fault"
target = "vesc_can"
fault = "silent"
duration_s = 1.0

[[timeline]]
at_s = 1.0
action = "fault"
target = "vesc_uart"
fault = "bit_errors"
rate = 0.02
duration_s = 1.5

[[timeline]]
at_s = 3.0
action = "move"
object = "cuboid"
position_m = [1.775, 0.0, 2.85]

[[timeline]]
at_s = 3.5
action = "teleport"
position_m = [-5.0, 0.0, 1.5]
'''


def write_scenario(tmp: Path, extra: str) -> Path:
    p = tmp / "scenario.toml"
    p.write_text(HEAD + DEVICES + extra)
    return p


def vesc_uart_packet(payload: bytes) -> bytes:
    return bytes([2, len(payload)]) + payload + binascii.crc_hqx(payload, 0).to_bytes(2, "big") + b"\x03"


def valid_vesc_uart(reply: bytes) -> bool:
    if len(reply) < 5 or reply[0] != 2 or reply[-1] != 3:
        return False
    n = reply[1]
    payload = reply[2:2 + n]
    return len(reply) == n + 5 and binascii.crc_hqx(payload, 0).to_bytes(2, "big") == reply[2 + n:4 + n]


def test_timeline_faults_show_on_the_wire(tmp_path):
    import can
    from pymodbus.client import AsyncModbusTcpClient

    scn = write_scenario(tmp_path, TIMELINE)

    async def main():
        bridge = Bridge(scn, status_interval=0)
        eps = await bridge.start()
        ep = {e.device: e for e in eps}
        cuboid_before = (await bridge.render("sonar", "didson_hf")).frame.hit_counts.get("cuboid", {}).get("total", 0)
        stop = threading.Event()
        can_status: list[tuple[float, int, int]] = []
        uart: list[tuple[float, bool]] = []

        def can_client() -> None:
            host, port = ep["vesc_can"].address.rsplit(":", 1)
            bus = can.Bus(interface="socketcand", host=host, port=int(port), channel="can0")
            try:
                next_send = 0.0
                while not stop.is_set():
                    if time.monotonic() >= next_send:
                        for cid in (5, 6):  # SET_RPM (3) 3000 ERPM, big-endian int32
                            bus.send(can.Message(arbitration_id=(3 << 8) | cid, is_extended_id=True,
                                                 data=struct.pack(">i", 3000)))
                        next_send = time.monotonic() + 0.05
                    msg = bus.recv(0.01)
                    if msg is not None and msg.arbitration_id >> 8 == 9:  # STATUS_1
                        erpm = struct.unpack_from(">i", msg.data, 0)[0]
                        can_status.append((bridge.now(), msg.arbitration_id & 0xFF, erpm))
            finally:
                bus.shutdown()

        def uart_client() -> None:
            with serial.Serial(ep["vesc_uart"].address, 115200, timeout=0.3) as s:
                while not stop.is_set():
                    s.reset_input_buffer()
                    sent = bridge.now()
                    s.write(vesc_uart_packet(b"\x04"))  # COMM_GET_VALUES
                    head = s.read(2)  # start byte, length: then the rest of this packet
                    reply = head + (s.read(head[1] + 3) if len(head) == 2 else b"")
                    whole = len(reply) >= 2 and len(reply) >= reply[1] + 5
                    if not whole and not (1.0 < sent < 2.6):
                        continue  # no whole reply within the timeout (a loaded machine): not a corruption
                    # in the bit-error window a request may arrive corrupted and get no reply at all
                    uart.append((sent, whole and valid_vesc_uart(reply)))
                    time.sleep(0.05)

        threads = [threading.Thread(target=can_client), threading.Thread(target=uart_client)]
        for th in threads:
            th.start()
        host, port = ep["depth"].address.rsplit(":", 1)
        mb = AsyncModbusTcpClient(host, port=int(port))
        await mb.connect()
        depth: list[tuple[float, float]] = []
        xs: list[tuple[float, float, float]] = []
        run = asyncio.ensure_future(bridge.run(5.0))
        cuboid_after = None
        while not run.done():
            rr = await mb.read_holding_registers(0x0002, count=2, device_id=1)
            p1 = struct.unpack(">f", struct.pack(">HH", *rr.registers))[0]
            depth.append((bridge.now(), p1))
            st = bridge.vehicle.state
            xs.append((st.time, float(st.position[0]), float(st.velocity[0])))
            if cuboid_after is None and bridge.now() > 3.2:
                r = await bridge.render("sonar", "didson_hf")
                cuboid_after = r.frame.hit_counts.get("cuboid", {}).get("total", 0)
            await asyncio.sleep(0.05)
        await run
        stop.set()
        for th in threads:
            th.join(10)
        mb.close()
        await bridge.close()
        return depth, can_status, uart, xs, cuboid_before, cuboid_after, bridge

    depth, can_status, uart, xs, before, after, bridge = asyncio.run(asyncio.wait_for(main(), 120))

    # depth sensor dropout 1.0-2.5 s: the Keller reports its channel error as NaN, then recovers
    inside = [v for t, v in depth if 1.15 < t < 2.35]
    outside = [v for t, v in depth if t < 0.85 or 2.7 < t < 3.4]
    assert inside and all(math.isnan(v) for v in inside)
    assert outside and all(1.0 < v < 1.3 for v in outside)  # ~1.15 bar at 1.5 m

    # CAN bus silent 1.0-2.0 s: no STATUS frame at all; they come back after
    assert not [s for s in can_status if 1.1 < s[0] < 1.9]
    assert [s for s in can_status if s[0] > 2.2]
    # thruster vertical_front_left (controller 5) failed at 1.0 s: its rotor stays stopped
    # while controller 6, commanded the same, spins
    late = [(cid, e) for t, cid, e in can_status if t > 2.6]
    assert late and all(abs(e) < 50 for cid, e in late if cid == 5)
    assert any(e > 1000 for cid, e in late if cid == 6)
    assert any(e > 1000 for t, cid, e in can_status if cid == 5 and t < 0.95)

    # VESC UART bit errors 1.0-2.5 s: corrupted replies; clean before and after
    during = [ok for t, ok in uart if 1.1 < t < 2.4]
    clean = [ok for t, ok in uart if t < 0.9 or t > 2.7]
    assert during and not all(during)
    assert clean and all(clean)

    # current 0.3 m/s north from 0.5 s: the vehicle drifts north; teleport at 3.5 s
    u_before = [u for t, x, u in xs if 0.2 < t < 0.45]
    u_after = [u for t, x, u in xs if 2.5 < t < 3.4]
    assert max(abs(u) for u in u_before) < 0.02 and min(u_after) > 0.05  # 391 kg accelerate slowly
    assert [x for t, x, u in xs if t > 3.7][-1] < -4.5
    # the cuboid moved 1.5 m north at 3.0 s: out of the sonar's view
    assert before > 1000 and after == 0
    assert [a for _, a in bridge.timeline.fired] == ["current", "fault", "fault", "fault", "fault", "move", "teleport"]


@pytest.mark.parametrize("entry,key,needle", [
    ('at_s = 1\naction = "explode"', "timeline.0.action", "unknown action 'explode'"),
    ('at_s = 1\naction = "fault"\ntarget = "nobody"\nfault = "dropout"', "timeline.0.target", "no device 'nobody'"),
    ('at_s = 1\naction = "fault"\ntarget = "depth"\nfault = "melt"', "timeline.0.fault", "has no fault 'melt'"),
    ('at_s = 1\naction = "fault"\ntarget = "thruster:nope"\nfault = "fail"', "timeline.0.target", "no thruster 'nope'"),
    ('at_s = -1\naction = "current"\nvelocity_m_s = [0,0,0]', "timeline.0.at_s", "outside"),
    ('at_s = 1\naction = "move"\nobject = "ghost"\nposition_m = [0,0,0]', "timeline.0.object", "no object 'ghost'"),
])
def test_broken_timelines_give_clear_errors(tmp_path, entry, key, needle):
    scn = write_scenario(tmp_path, "\n[[timeline]]\n" + entry + "\n")

    async def main():
        b = Bridge(scn, status_interval=0)
        try:
            await b.start()
        finally:
            await b.close()

    with pytest.raises(ConfigError) as ei:
        asyncio.run(main())
    assert needle in str(ei.value) and ei.value.key == key and "scenario.toml" in str(ei.value)
