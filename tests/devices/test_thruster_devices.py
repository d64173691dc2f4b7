"""The thruster devices through the running bridge, with unmodified clients.

One bridge (the water tank scenario with every thruster interface at once: VESC CAN on
the socketcand server, DroneCAN on the slcan pty, VESC UART and VRCSR on their ptys)
runs in an asyncio loop on a background thread. The clients are the real libraries
in the test thread: python-can (socketcand and slcan interfaces), dronecan over slcan,
pyserial. What they receive is decoded with cantools from the DBC file, with
dronecan's own DSDL code, or with struct at the documented offsets. Each test looks
at the simulation too (thruster speeds, thrust, depth).
"""

from __future__ import annotations

import asyncio
import os
import struct
import time
import zlib
from pathlib import Path
from typing import Any

import can
import cantools
import pytest
import serial

from hilsim.protocols.vesc_can import dbc_path
from hilsim.runtime.bridge import Bridge
from tests.links.test_can import LoopThread, wait_for

ROOT = Path(__file__).resolve().parents[2]
THRUSTER_DEVICES = """
[[devices]]
name = "vesc_can"
protocol = "vesc-can"
transport = "socketcand"
channel = "can0"
port = 0
status_rate_hz = 50

[[devices]]
name = "dronecan_esc"
protocol = "dronecan"
transport = "slcan"
channel = "can1"
node_id = 20

[[devices]]
name = "vesc_uart"
protocol = "vesc-uart"
baudrate = 115200
controller_id = 1

[[devices]]
name = "vrcsr"
protocol = "vrcsr"
baudrate = 115200
"""


def scenario_with_thrusters(tmp: Path) -> Path:
    text = (ROOT / "scenarios" / "water_tank" / "scenario.toml").read_text()
    cut = text.find("[[devices]]")
    if cut >= 0:  # drop the sonar stream: these tests need no render worker
        text = text[:cut]
    path = tmp / "scenario.toml"
    path.write_text(text + THRUSTER_DEVICES)
    return path


class RunningBridge:
    def __init__(self, tmp: Path) -> None:
        self.lt = LoopThread()
        self.bridge = Bridge(scenario_with_thrusters(tmp), run_dir=tmp / "run", status_interval=0)
        self.endpoints = {e.device: e for e in self.lt.run(self.bridge.start(), 60)}
        self.future = asyncio.run_coroutine_threadsafe(self.bridge.run(None), self.lt.loop)

    @property
    def thrusters(self) -> Any:
        return self.bridge.vehicle.thrusters

    def speed(self, index: int) -> float:
        return float(self.thrusters.speeds[index])

    def status(self, device: str) -> dict[str, float]:
        dev = next(d for d in self.bridge.devices if d.name == device)
        return self.lt.call(dev.status)  # type: ignore[no-any-return]

    def close(self) -> None:
        self.lt.call(self.bridge.stop)
        try:
            self.future.result(20)
        finally:
            self.lt.run(self.bridge.close(), 30)
            self.lt.close()


@pytest.fixture(scope="module")
def bridge(tmp_path_factory):
    b = RunningBridge(tmp_path_factory.mktemp("thrusters"))
    yield b
    b.close()


@pytest.fixture(scope="module")
def dbc():
    return cantools.database.load_file(str(dbc_path()))


def wait_stopped(bridge: RunningBridge, indexes, timeout: float = 5.0) -> None:
    """Let earlier tests' commands time out (watchdog) so each test starts from rest."""
    assert wait_for(lambda: all(abs(bridge.speed(i)) < 1e-9 for i in indexes), timeout)


def socketcand_client(bridge: RunningBridge) -> can.BusABC:
    e = bridge.endpoints["vesc_can"]
    return can.Bus(interface="socketcand", channel=e.extra["channel"], host=e.extra["host"], port=e.extra["port"])


def test_endpoints_describe_every_interface(bridge):
    e = bridge.endpoints
    assert set(e) == {"vesc_can", "dronecan_esc", "vesc_uart", "vrcsr"}
    assert e["vesc_can"].transport == "socketcand" and e["vesc_can"].extra["channel"] == "can0"
    assert e["vesc_can"].address == f"127.0.0.1:{e['vesc_can'].extra['port']}"
    assert e["vesc_can"].extra["controller_ids"] == list(range(1, 9))
    assert e["dronecan_esc"].transport == "slcan" and os.path.islink(e["dronecan_esc"].address)
    assert e["dronecan_esc"].extra["esc_indexes"] == list(range(8))
    for name in ("vesc_uart", "vrcsr"):
        assert e[name].transport == "pty" and os.path.islink(e[name].address)
        assert e[name].extra["baudrate"] == 115200


def test_vesc_can_set_rpm_over_socketcand_moves_the_thruster_and_status_follows_with_lag(bridge, dbc):
    index, cid = 1, 2  # front_right
    wait_stopped(bridge, [index])
    profile = bridge.thrusters.thrusters[index].profile
    target = round(0.6 * profile.max_rpm * profile.pole_pairs)  # ERPM
    set_rpm = dbc.get_message_by_name(f"VESC{cid}_SET_RPM")
    status1 = dbc.get_message_by_name(f"VESC{cid}_STATUS_1")
    client = socketcand_client(bridge)
    erpms: list[float] = []
    try:
        assert wait_for(lambda: bridge.status("vesc_can")["clients"] >= 1)
        time.sleep(0.3)  # past the server's raw-mode grace
        deadline = time.monotonic() + 1.5
        next_cmd = 0.0
        while time.monotonic() < deadline:
            if time.monotonic() >= next_cmd:  # 20 Hz, as a controller would
                client.send(can.Message(arbitration_id=set_rpm.frame_id, data=set_rpm.encode({"erpm": target}),
                                        is_extended_id=True))
                next_cmd = time.monotonic() + 0.05
            msg = client.recv(0.02)
            if msg is not None and msg.arbitration_id == status1.frame_id:
                erpms.append(status1.decode(msg.data)["erpm"])
        assert bridge.thrusters.telemetry(index).thrust > 0.5  # [N] the simulated thruster pushes
    finally:
        client.shutdown()
    assert erpms and abs(erpms[-1] - target) <= 0.03 * target          # settled at the command
    # the rotor's lag (0.04 s) takes 0.18 s from 2 % to 99 %: about 9 status periods, so a status
    # tick or two the loaded bridge runs late cannot hide the rise (an echo of the command would)
    rising = [e for e in erpms if 0.02 * target < e < 0.99 * target]
    assert rising, "no STATUS_1 caught the rotor on its way up: telemetry echoes the command?"
    assert all(b >= a - 0.01 * target for a, b in zip(erpms, erpms[1:]))  # monotone first-order rise


def test_vertical_thrusters_commanded_down_over_can_increase_depth(bridge, dbc):
    client = socketcand_client(bridge)
    try:
        time.sleep(0.3)
        depth0 = bridge.bridge.vehicle.state.depth
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            for cid in (5, 6, 7, 8):  # the four vertical thrusters push the vehicle down (+z)
                m = dbc.get_message_by_name(f"VESC{cid}_SET_DUTY")
                client.send(can.Message(arbitration_id=m.frame_id, data=m.encode({"duty": 0.8}), is_extended_id=True))
            time.sleep(0.05)
        depth1 = bridge.bridge.vehicle.state.depth
    finally:
        client.shutdown()
    assert depth1 - depth0 > 0.05, (depth0, depth1)


def test_watchdog_through_the_wire(bridge, dbc):
    index, cid = 2, 3  # rear_left
    wait_stopped(bridge, [index])
    m = dbc.get_message_by_name(f"VESC{cid}_SET_CURRENT")
    st = dbc.get_message_by_name(f"VESC{cid}_STATUS_1")
    client = socketcand_client(bridge)
    try:
        time.sleep(0.3)
        for _ in range(10):
            client.send(can.Message(arbitration_id=m.frame_id, data=m.encode({"current": 12.0}), is_extended_id=True))
            time.sleep(0.05)
        assert abs(bridge.speed(index)) > 0.3 and not bridge.thrusters.telemetry(index).timed_out
        t_last = time.monotonic()
        timeout = bridge.thrusters.thrusters[index].profile.watchdog_timeout
        # no more commands: within the ESC's timeout (+ the spin-down) STATUS_1 reads 0 again
        stopped_at, spinning = None, False
        while time.monotonic() < t_last + timeout + 3.0:
            msg = client.recv(0.05)
            if msg is None or msg.arbitration_id != st.frame_id:
                continue
            erpm = st.decode(msg.data)["erpm"]
            spinning = spinning or erpm > 0  # skip status frames queued from before the command
            if spinning and erpm == 0:
                stopped_at = time.monotonic()
                break
        assert stopped_at is not None and stopped_at - t_last >= 0.9 * timeout
        assert bridge.thrusters.telemetry(index).timed_out and bridge.thrusters.telemetry(index).thrust == 0.0
    finally:
        client.shutdown()


def test_most_recent_command_from_any_interface_wins(bridge, dbc):
    index = 0  # front_left: VESC CAN controller 1, VRCSR motor 0
    m = dbc.get_message_by_name("VESC1_SET_DUTY")
    client = socketcand_client(bridge)
    port = serial.Serial(bridge.endpoints["vrcsr"].address, 115200, timeout=1)
    try:
        time.sleep(0.3)
        client.send(can.Message(arbitration_id=m.frame_id, data=m.encode({"duty": 0.5}), is_extended_id=True))
        assert wait_for(lambda: bridge.speed(index) > 0.2, 3)
        port.write(vrcsr_request([-0.5], reply_node=1, flags=0))
        assert wait_for(lambda: bridge.speed(index) < -0.2, 3)
        client.send(can.Message(arbitration_id=m.frame_id, data=m.encode({"duty": 0.5}), is_extended_id=True))
        assert wait_for(lambda: bridge.speed(index) > 0.2, 3)
    finally:
        client.shutdown()
        port.close()


# ---------------------------------------------------------------- DroneCAN on the slcan pty


def test_dronecan_node_over_slcan_drives_an_esc_and_reads_status(bridge):
    dronecan = pytest.importorskip("dronecan")
    index = 3  # rear_right = esc index 3
    wait_stopped(bridge, [index])
    path = bridge.endpoints["dronecan_esc"].address
    node = dronecan.make_node("slcan:" + path, node_id=10, bitrate=1_000_000)
    statuses: list[Any] = []
    heartbeats: list[Any] = []
    node.add_handler(dronecan.uavcan.equipment.esc.Status,
                     lambda e: statuses.append((e.transfer.source_node_id, e.message)))
    node.add_handler(dronecan.uavcan.protocol.NodeStatus, lambda e: heartbeats.append(e.transfer.source_node_id))
    try:
        cmd = [0, 0, 0, 4000]  # about 49 % power on ESC 3, others 0
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            node.broadcast(dronecan.uavcan.equipment.esc.RawCommand(cmd=cmd))
            node.spin(0.05)
        assert bridge.speed(index) > 0.3
        mine = [m for src, m in statuses if src == 20 and m.esc_index == 3]
        assert mine, f"no esc.Status for index 3 (got {len(statuses)} statuses)"
        assert mine[-1].rpm > 0.3 * bridge.thrusters.thrusters[index].profile.max_rpm
        assert 15.0 < mine[-1].voltage <= 16.0 and mine[-1].temperature > 270.0
        assert 20 in heartbeats
        assert {m.esc_index for _, m in statuses} == set(range(8))
    finally:
        node.close()


def test_python_can_over_slcan_sends_raw_command_frames(bridge):
    dronecan = pytest.importorskip("dronecan")
    from dronecan.transport import Frame, Transfer

    index = 4  # vertical_front_left = esc index 4: 5 values -> a 2-frame transfer with CRC
    wait_stopped(bridge, [index])
    path = bridge.endpoints["dronecan_esc"].address
    client = can.Bus(interface="slcan", channel=path, bitrate=1_000_000, sleep_after_open=0)
    try:
        got: list[Frame] = []
        for tid in range(30):
            t = Transfer(payload=dronecan.uavcan.equipment.esc.RawCommand(cmd=[0, 0, 0, 0, -6000]),
                         source_node_id=11, transfer_id=tid, transfer_priority=20)
            for f in t.to_frames():
                client.send(can.Message(arbitration_id=f.message_id, data=bytes(f.bytes), is_extended_id=True))
            end = time.monotonic() + 0.05
            while time.monotonic() < end:
                msg = client.recv(0.01)
                if msg is not None and (msg.arbitration_id >> 8) & 0xFFFF == 1034:
                    got.append(Frame(msg.arbitration_id, msg.data))
        assert bridge.speed(index) < -0.3
        # reassemble the ESC status transfers with dronecan's own code
        done = []
        for i, f in enumerate(got):
            if f.start_of_transfer and i + 2 < len(got) and got[i + 2].end_of_transfer:
                tr = Transfer()
                tr.from_frames(got[i:i + 3])
                done.append(tr.payload)
        st4 = [p for p in done if p.esc_index == 4]
        assert st4 and st4[-1].rpm < 0
    finally:
        client.shutdown()


# ---------------------------------------------------------------- serial: VESC UART and VRCSR


def vesc_packet(payload: bytes) -> bytes:
    crc = 0  # CRC-16/XMODEM, written out here rather than taken from hilsim
    for b in payload:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return bytes([2, len(payload)]) + payload + struct.pack(">H", crc) + b"\x03"


def read_vesc_reply(port: serial.Serial, timeout: float = 2.0) -> bytes:
    end = time.monotonic() + timeout
    buf = b""
    while time.monotonic() < end:
        buf += port.read(max(1, port.in_waiting))
        if len(buf) >= 2 and buf[0] == 2 and len(buf) >= buf[1] + 5:
            return buf[2:2 + buf[1]]
    raise AssertionError(f"no VESC reply (got {buf!r})")


def test_vesc_uart_with_pyserial(bridge):
    index = 0  # front_left: the local controller 1
    e = bridge.endpoints["vesc_uart"]
    port = serial.Serial(e.address, e.extra["baudrate"], timeout=0.05)
    try:
        wait_stopped(bridge, [index])
        before = bridge.status("vesc_uart")
        # the pyvesc SetRPM(5000) packet, after garbage and a packet with a bad CRC
        bad = bytearray(vesc_packet(b"\x08\x00\x00\x27\x10"))
        bad[-2] ^= 0x55
        port.write(b"\x00\xff garbage \x02\x03" + bytes(bad) + bytes.fromhex("02050800001388448d03"))
        assert wait_for(lambda: bridge.speed(index) > 0.1, 3)
        rpms = []
        for _ in range(8):
            port.write(bytes.fromhex("02050800001388448d03"))
            port.reset_input_buffer()
            t0 = time.monotonic()
            port.write(vesc_packet(b"\x04"))  # COMM_GET_VALUES
            reply = read_vesc_reply(port)
            took = time.monotonic() - t0
            assert reply[0] == 4 and len(reply) == 74
            # a real-shaped reply: rpm (ERPM) at offset 23, v_in at 27, controller id at 58
            rpms.append(struct.unpack_from(">i", reply, 23)[0])
            assert 15.0 < struct.unpack_from(">h", reply, 27)[0] / 10 <= 16.0 and reply[58] == 1
            assert took >= 0.9 * (len(reply) + 5) * 10 / e.extra["baudrate"]  # not faster than the line
            time.sleep(0.05)
        assert abs(rpms[-1] - 5000) <= 150
        after = bridge.status("vesc_uart")
        assert after["crc_errors"] > before["crc_errors"] and after["bytes_skipped"] > before["bytes_skipped"]
        # COMM_FORWARD_CAN to controller 4 (rear_right)
        wait_stopped(bridge, [3])
        port.write(vesc_packet(b"\x22\x04\x05" + struct.pack(">i", 50000)))  # SET_DUTY 0.5
        assert wait_for(lambda: bridge.speed(3) > 0.2, 3)
    finally:
        port.close()


def vrcsr_request(powers, reply_node: int, flags: int = 2, node: int = 0x81) -> bytes:
    header = struct.pack("<HBBBB", 0x5FF5, node, flags, 0xF0, 2 + 4 * len(powers))
    payload = struct.pack("<BB", 0xAA, reply_node) + b"".join(struct.pack("<f", p) for p in powers)
    return header + struct.pack("<I", zlib.crc32(header)) + payload + struct.pack("<I", zlib.crc32(payload))


def test_vrcsr_with_pyserial(bridge):
    index = 5  # vertical_front_right: motor id 5, node id 6
    e = bridge.endpoints["vrcsr"]
    port = serial.Serial(e.address, e.extra["baudrate"], timeout=1)
    try:
        wait_stopped(bridge, [index])
        powers = [0.0, 0.0, 0.0, 0.0, 0.0, 0.7]
        port.write(b"\xf5\x5f\x00garbage" + vrcsr_request(powers, 6)[:-2])  # truncated: dropped
        port.reset_input_buffer()
        rpm = []
        for _ in range(10):
            port.write(vrcsr_request(powers, reply_node=6))
            resp = port.read(6 + 4 + 18 + 4)
            f = struct.unpack("=HBBBBIBffffBI", resp)
            assert f[0] == 0x0FF0 and f[1] == 6 and f[4] == 18 and f[12] == zlib.crc32(resp[10:28])
            rpm.append(f[7])
            assert 15.0 < f[8] <= 16.0 and f[11] == 0
            time.sleep(0.05)
        assert rpm[-1] > 0.5 * bridge.thrusters.thrusters[index].profile.max_rpm and rpm[0] < rpm[-1]
        assert bridge.thrusters.telemetry(index).thrust > 1.0
        assert bridge.status("vrcsr")["bytes_skipped"] > 0
        # a command to a single thruster's node id; flags 0: no reply
        port.write(vrcsr_request([0.0] * 5 + [-0.7], reply_node=6, flags=0, node=6))
        assert wait_for(lambda: bridge.speed(index) < -0.3, 3)
        assert port.read(1) == b""
    finally:
        port.close()


# ---------------------------------------------------------------- configuration errors


@pytest.mark.parametrize("protocol, options, match", [
    ("vesc-can", {"mapping": {"1": "propeller"}}, "no thruster 'propeller'"),
    ("vesc-can", {"mapping": {"300": 0}}, "controller id 300 out of range"),
    ("vesc-can", {"transport": "udp"}, "transport 'udp' is not one of"),
    ("vesc-can", {"status_rate_hz": 0}, "status_rate_hz"),
    ("vesc-can", {"mapping": {"1": 8}}, "thruster index 8 out of range"),
    ("dronecan", {"node_id": 0}, "node_id 0 outside"),
    ("dronecan", {"mapping": {"20": 0}}, "esc index 20 out of range"),
    ("vesc-uart", {"controller_id": 9}, "controller_id 9 is not in the mapping"),
    ("vrcsr", {"node_ids": {"0": 129}}, "not the group id"),
    ("vesc-can", {"statusrate": 5}, "did you mean 'status_rate_hz'"),
    ("dronecan", {"path": "../outside"}, "leaves"),
    ("vesc-uart", {"path": "/dev/ttyUSB0"}, "absolute"),
    ("vrcsr", {"path": "../../x"}, "leaves"),
])
def test_bad_options_are_refused_with_a_clear_message(tmp_path, protocol, options, match):
    from hilsim.devices import device_class

    ctx = Bridge(scenario_with_thrusters(tmp_path), run_dir=tmp_path / "run")  # built, not started
    with pytest.raises(ValueError, match=match):
        device_class(protocol)("dev", options, ctx)


def test_mapping_by_name_and_index(tmp_path):
    from hilsim.devices.vesc_can import VescCanDevice

    ctx = Bridge(scenario_with_thrusters(tmp_path), run_dir=tmp_path / "run")
    dev = VescCanDevice("dev", {"mapping": {"23": "vertical_rear_right", "7": 0}}, ctx)
    assert dev.mapping == {23: 7, 7: 0}
