"""Keller and WitMotion devices: a real scheduler, vehicle and clock (a small context,
then the running bridge); pymodbus and Debian's mbpoll as clients over TCP and RTU
on the pty; depth against rho g depth while the vehicle dives under its thrusters."""

from __future__ import annotations

import asyncio
import dataclasses
import math
import re
import shutil
import struct
import time
import types
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any, AsyncIterator, Sequence

import numpy as np
import pytest
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException
from pymodbus.framer import FramerType

from hilsim.devices import device_class
from hilsim.devices.base import Device, Endpoint
from hilsim.resources import find_profile, find_scenario
from hilsim.runtime.clock import RealTimeClock
from hilsim.runtime.scheduler import Scheduler, VehicleLoop
from hilsim.sim.navigation import ATMOSPHERE, GRAVITY
from hilsim.sim.scenario import Scenario, load_scenario
from hilsim.sim.state import VehicleState
from hilsim.sim.vehicle import Vehicle, load_vehicle_profile

RHO = 998.0          # [kg/m^3] the water tank's fresh water
# depth tolerance [m]: noise 0.3 mbar (4 sigma), resolution 0.6 mbar, float32 of ~1.2 bar, over rho g
DEPTH_TOL = (4 * 30.0 + 60.0 / 2 + 0.02) / (RHO * GRAVITY) + 1e-3


def depth_of(bar: float) -> float:
    return (bar * 1e5 - ATMOSPHERE) / (RHO * GRAVITY)


class SmallContext:
    """A real DeviceContext without the bridge: the water-tank scenario, the Cyclops
    vehicle with its thrusters, a scheduler on the wall clock."""

    def __init__(self, run_dir: Path, seed: int = 3):
        self.scenario = load_scenario(find_scenario("water_tank"))
        profile = load_vehicle_profile(find_profile("vehicles", "cyclops"))
        self.scheduler = Scheduler(RealTimeClock())
        self.vehicle = VehicleLoop(Vehicle(profile), profile.thruster_set(),
                                   VehicleState(position=np.array([-3.0, 0.0, 1.5])))
        self.vehicle.attach(self.scheduler)
        self.bind = "127.0.0.1"
        self.broadcast = "127.0.0.1"
        self.run_dir = run_dir
        self.seed = seed
        self.fast = False


    def pty_path(self, option, default):
        from hilsim.runtime.bridge import path_inside

        return path_inside(self.run_dir, option or default)

    def now(self) -> float:
        return max(self.vehicle.state.time, self.scheduler.clock.now())

    def every(self, name, period, callback, *, offset=0.0, priority=20, tolerance=None):
        ev = self.scheduler.add(name, period, callback, offset=offset, priority=priority, tolerance=tolerance)
        return types.SimpleNamespace(cancel=lambda: self.scheduler.remove(ev))

    def observed(self, topic: str) -> bool:
        return False

    def publish(self, topic, message) -> None:
        pass

    async def shared(self, key, factory):
        return await factory()


@asynccontextmanager
async def running(ctx: SmallContext, *specs: tuple[str, str, dict[str, Any]]) -> AsyncIterator[
        tuple[list[Device], list[Endpoint]]]:
    devices = [device_class(proto)(name, opts, ctx) for name, proto, opts in specs]  # type: ignore[arg-type]
    endpoints: list[Endpoint] = []
    for d in devices:
        endpoints += await d.start()
    ctx.scheduler.clock.reset()  # type: ignore[attr-defined]
    task = asyncio.ensure_future(ctx.scheduler.run_async())
    try:
        yield devices, endpoints
    finally:
        ctx.scheduler.stop()
        await asyncio.wait_for(task, 5)
        for d in devices:
            await d.close()


def ep(endpoints: Sequence[Endpoint], device: str, transport: str) -> Endpoint:
    return next(e for e in endpoints if e.device == device and e.transport == transport)


async def tcp_client(e: Endpoint) -> AsyncModbusTcpClient:
    host, port = e.address.rsplit(":", 1)
    c = AsyncModbusTcpClient(host, port=int(port), timeout=1, retries=0)
    assert await c.connect()
    return c


async def rtu_client(e: Endpoint, timeout: float = 1.0) -> AsyncModbusSerialClient:
    c = AsyncModbusSerialClient(e.address, framer=FramerType.RTU, baudrate=e.extra["baudrate"], parity="N",
                                timeout=timeout, retries=0)
    assert await c.connect()
    return c


async def read_p1(c: Any, unit: int = 1, addr: int = 0x0002) -> float:
    rr = await c.read_holding_registers(addr, count=2, device_id=unit)
    assert not rr.isError(), rr
    return float(c.convert_from_registers(rr.registers, c.DATATYPE.FLOAT32, word_order="big"))


async def no_answer(c: Any, unit: int) -> bool:
    try:
        rr = await c.read_holding_registers(0x0002, count=2, device_id=unit)
    except ModbusException:
        return True
    return bool(rr.isError())


KELLER = ("depth", "modbus-keller", {"transport": ["tcp", "rtu"], "baudrate": 19200})
WIT = ("imu", "modbus-witmotion", {"transport": ["tcp", "rtu"]})


def test_options_are_checked(tmp_path: Path) -> None:
    ctx = SmallContext(tmp_path)
    cls = device_class("modbus-keller")
    for opts, match in [({"transprt": ["tcp"]}, "did you mean 'transport'"),
                        ({"transport": ["udp"]}, "transport must be"),
                        ({"parity": "X"}, "parity"),
                        ({"device_id": 300}, "device_id"),
                        ({"map": "no_such_map"}, "bundled maps: keller_serie30"),
                        ({"map": "witmotion_hwt905"}, "does not have"),
                        ({"map": "../etc/passwd"}, "not a path")]:
        with pytest.raises((ValueError, FileNotFoundError), match=match):
            cls("k", opts, ctx)  # type: ignore[arg-type]


def test_keller_one_state_on_tcp_and_rtu(tmp_path: Path) -> None:
    """TCP and RTU show the same live registers; an address write over TCP moves the
    device on RTU too; 250 answers on RTU; "set zero" and a channel error show on both."""
    async def main() -> None:
        ctx = SmallContext(tmp_path)
        async with running(ctx, KELLER) as (devices, endpoints):
            dev = devices[0]
            e_tcp, e_rtu = ep(endpoints, "depth", "tcp"), ep(endpoints, "depth", "pty")
            assert e_rtu.address == str(tmp_path / "depth.tty") and e_rtu.extra["baudrate"] == 19200
            tcp, rtu = await tcp_client(e_tcp), await rtu_client(e_rtu, timeout=0.3)
            await asyncio.sleep(0.1)
            # one state: with sampling paused, both transports show the very same words
            ev = next(e for e in ctx.scheduler.events if e.name == "depth.sample")
            ctx.scheduler.remove(ev)
            dev.sample()
            a, b = await read_p1(tcp), await read_p1(rtu)
            assert a == b and dev.tcp.target.image is dev.rtu.session.targets[0].image
            assert abs(depth_of(a) - ctx.vehicle.state.depth) < DEPTH_TOL + 0.01
            ctx.scheduler.add("depth", ev.period, dev.sample, priority=10)
            assert await read_p1(rtu, unit=250) == pytest.approx(a, abs=0.002)  # transparent address
            rr = await tcp.write_register(0x020D, 7, device_id=1)
            assert not rr.isError()
            assert await no_answer(rtu, 1)
            assert abs(await read_p1(rtu, unit=7) - a) < 0.002
            assert dev.status()["device_id"] == 7
            rr = await rtu.write_register(0xFF00, 0, device_id=7)       # set zero P1
            assert not rr.isError()
            assert abs(await read_p1(tcp, unit=7)) < 0.003               # bar: noise and resolution only
            assert abs(await read_p1(tcp, unit=7, addr=0x0100)) < 0.003
            dev.channel_error = True
            await asyncio.sleep(0.05)
            assert math.isnan(await read_p1(tcp, unit=7))
            rr = await tcp.write_register(0xFF00, 0, device_id=7)       # cannot zero a channel in error
            assert rr.isError() and rr.exception_code == 4
            rr = await rtu.write_register(0x0002, 1, device_id=7)
            assert rr.isError() and rr.exception_code == 2
            tcp.close()
            rtu.close()
            s = dev.status()
            assert s["samples"] > 5 and s["requests"] >= 10 and "internal_errors" not in s

    asyncio.run(main())


def test_witmotion_at_rest(tmp_path: Path) -> None:
    """Level, heading north, nearly at rest: AZ = +1 g, angles ~0, unit quaternion, 15 deg C,
    the field's down component negative in the sensor's Z-up axes; address 0x50."""
    async def main() -> None:
        ctx = SmallContext(tmp_path)
        async with running(ctx, WIT) as (devices, endpoints):
            await asyncio.sleep(0.1)
            for e in (ep(endpoints, "imu", "tcp"), ep(endpoints, "imu", "pty")):
                c = await (tcp_client(e) if e.transport == "tcp" else rtu_client(e))
                rr = await c.read_holding_registers(0x34, count=13, device_id=0x50)
                v = [x - 65536 if x >= 32768 else x for x in rr.registers]
                q = await c.read_holding_registers(0x51, count=4, device_id=0x50)
                c.close()
                assert abs(v[0]) < 150 and abs(v[1]) < 150 and abs(v[2] - 2048) < 150   # 16 g / 32768 per count
                assert all(abs(x) < 10 for x in v[3:6])                            # < 0.6 deg/s
                assert v[6] > 0 and v[8] < 0                                       # north and down (z up: negative)
                assert abs(v[9]) < 40 and abs(v[10]) < 40 and abs(v[11]) < 400     # deg * 32768 / 180
                assert abs(v[12] - 1500) < 60                                      # 15.00 deg C
                assert q.registers[0] > 32000                                      # w ~ 1

    asyncio.run(main())


# -- through the running bridge ------------------------------------------------

def bridge_scenario(devices: list[dict[str, Any]]) -> Scenario:
    """The water-tank scenario with exactly these devices."""
    sc = load_scenario(find_scenario("water_tank"))
    return dataclasses.replace(sc, raw={**sc.raw, "devices": devices})


DEVICES = [
    {"name": "depth", "protocol": "modbus-keller", "transport": ["tcp", "rtu"], "baudrate": 9600},
    {"name": "imu", "protocol": "modbus-witmotion", "transport": ["tcp", "rtu"], "baudrate": 115200},
]


@asynccontextmanager
async def bridge_running(tmp_path: Path, devices: list[dict[str, Any]] = DEVICES) -> AsyncIterator[Any]:
    from hilsim.runtime.bridge import Bridge

    bridge = Bridge(bridge_scenario(devices), run_dir=tmp_path, status_interval=0)
    await bridge.start()
    task = asyncio.ensure_future(bridge.run())
    try:
        yield bridge
    finally:
        bridge.stop()
        await asyncio.wait_for(task, 5)
        await bridge.close()


def test_bridge_depth_over_tcp_and_rtu_follows_a_dive(tmp_path: Path) -> None:
    """pymodbus over TCP and over RTU on the pty reads P1 and gets the simulated depth;
    commanding the vertical thrusters dives the vehicle and P1 follows."""
    async def main() -> None:
        async with bridge_running(tmp_path) as bridge:
            e_tcp, e_rtu = ep(bridge.endpoints, "depth", "tcp"), ep(bridge.endpoints, "depth", "pty")
            tcp, rtu = await tcp_client(e_tcp), await rtu_client(e_rtu)
            await asyncio.sleep(0.2)

            async def check() -> float:
                depths = []
                for c in (tcp, rtu):
                    for addr in (0x0002, 0x0100):
                        d_before = bridge.vehicle.state.depth
                        d = depth_of(await read_p1(c, addr=addr))
                        d_after = bridge.vehicle.state.depth
                        lo, hi = min(d_before, d_after), max(d_before, d_after)
                        assert lo - DEPTH_TOL - 0.01 < d < hi + DEPTH_TOL + 0.01, (d, d_before, d_after)
                        depths.append(d)
                rr = await tcp.read_holding_registers(0x0012, count=2, device_id=1)
                pa = struct.unpack(">i", struct.pack(">HH", *rr.registers))[0]  # 1/100 mbar
                assert abs(depth_of(pa / 1e5) - bridge.vehicle.state.depth) < DEPTH_TOL + 0.02
                return float(np.mean(depths))

            start = await check()
            assert start == pytest.approx(1.5, abs=0.05)
            ts = bridge.vehicle.thrusters
            vertical = [i for i, n in enumerate(ts.names) if n.startswith("vertical")]

            def dive(t: float) -> None:
                for i in vertical:
                    ts.command(i, "normalized", 0.8, bridge.now())

            ev = bridge.scheduler.add("test-dive", 0.05, dive)
            for _ in range(100):  # bounded: at most ~5 s
                await asyncio.sleep(0.05)
                if bridge.vehicle.state.depth > start + 0.3:
                    break
            bridge.scheduler.remove(ev)
            deeper = await check()
            assert deeper > start + 0.25
            tcp.close()
            rtu.close()

    asyncio.run(main())


async def _mbpoll(*args: str) -> str:
    proc = await asyncio.create_subprocess_exec("mbpoll", "-1", "-o", "1", "-0", *args,
                                                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    out, err = await asyncio.wait_for(proc.communicate(), 15)
    assert proc.returncode == 0, (out.decode(), err.decode())
    return out.decode()


def _values(out: str) -> dict[int, float]:
    return {int(a): float(b) for a, b in re.findall(r"^\[(\d+)\]:\s+(\S+)", out, re.M)}


@pytest.mark.skipif(shutil.which("mbpoll") is None, reason="Debian's mbpoll is not installed (.ci/run installs it)")
def test_bridge_mbpoll_tcp_and_rtu(tmp_path: Path) -> None:
    """An independent client (libmodbus): P1 as float (big-endian words) over TCP and
    RTU, and the WitMotion AZ over RTU at 115200 baud."""
    async def main() -> None:
        async with bridge_running(tmp_path) as bridge:
            e_tcp, e_rtu = ep(bridge.endpoints, "depth", "tcp"), ep(bridge.endpoints, "depth", "pty")
            host, port = e_tcp.address.rsplit(":", 1)
            await asyncio.sleep(0.2)
            outs = [await _mbpoll("-m", "tcp", "-a", "1", "-r", "2", "-c", "1", "-t", "4:float", "-B",
                                  "-p", port, host),
                    await _mbpoll("-m", "rtu", "-b", "9600", "-P", "none", "-a", "1", "-r", "0x100", "-c", "2",
                                  "-t", "4:float", "-B", e_rtu.address)]
            p_tcp = _values(outs[0])[2]
            p_rtu, tob1 = _values(outs[1])[256], _values(outs[1])[258]
            for p in (p_tcp, p_rtu):
                assert abs(depth_of(p) - bridge.vehicle.state.depth) < DEPTH_TOL + 0.02  # %g: 6 digits
            assert tob1 == pytest.approx(15.0, abs=0.2)
            e_imu = ep(bridge.endpoints, "imu", "pty")
            out = await _mbpoll("-m", "rtu", "-b", "115200", "-P", "none", "-a", "0x50", "-r", "0x36", "-c", "1",
                                e_imu.address)
            assert abs(_values(out)[0x36] - 2048) < 150
            # an address outside the map: mbpoll reports the device's exception
            proc = await asyncio.create_subprocess_exec(
                "mbpoll", "-1", "-o", "1", "-0", "-m", "tcp", "-a", "1", "-r", "0x0C00", "-p", port, host,
                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
            _, err = await asyncio.wait_for(proc.communicate(), 15)
            assert "Illegal data address" in err.decode()

    asyncio.run(main())


def test_bridge_16_tcp_clients_at_100hz(tmp_path: Path) -> None:
    """16 clients poll CH0..TOB2 (12 registers) every 10 ms for 1 s: every answer is
    consistent (T == TOB1 from the same sample, absent channels NaN, P1 at the vehicle's
    depth, the transaction id echoed); nobody is starved."""
    async def main() -> None:
        async with bridge_running(tmp_path) as bridge:
            host, port = ep(bridge.endpoints, "depth", "tcp").address.rsplit(":", 1)
            nan = [0x7FC0, 0x0000]

            async def poller(k: int) -> int:
                r, w = await asyncio.open_connection(host, int(port))
                ok = 0
                t_next = time.monotonic()
                for i in range(100):
                    tid = (k << 8) | i
                    w.write(struct.pack(">HHHBBHH", tid, 0, 6, 1, 3, 0x0000, 12))
                    head = await asyncio.wait_for(r.readexactly(9), 2)
                    body = await asyncio.wait_for(r.readexactly(24), 2)
                    t_id, _, length, unit, fc, nbytes = struct.unpack(">HHHBBB", head)
                    assert (t_id, length, unit, fc, nbytes) == (tid, 27, 1, 3, 24)
                    words = list(struct.unpack(">12H", body))
                    assert words[0:2] == nan and words[4:6] == nan and words[10:12] == nan
                    assert words[6:8] == words[8:10]                      # T and TOB1: one sample
                    p1 = struct.unpack(">f", body[4:8])[0]
                    assert abs(depth_of(p1) - bridge.vehicle.state.depth) < DEPTH_TOL + 0.02
                    ok += 1
                    t_next += 0.01
                    await asyncio.sleep(max(0.0, t_next - time.monotonic()))
                w.close()
                return ok

            results = await asyncio.gather(*(poller(k) for k in range(16)))
            assert results == [100] * 16
            dev = next(d for d in bridge.devices if d.name == "depth")
            assert dev.status()["requests"] >= 1600 and "internal_errors" not in dev.status()

    asyncio.run(main())


def test_bridge_two_sensors_on_one_rs485_line(tmp_path: Path) -> None:
    """Devices naming the same path share one line, as on an RS-485 bus: each answers
    its own address, an unknown address gets silence, and the line closes with the bridge."""
    devices = [{"name": "depth", "protocol": "modbus-keller", "transport": ["rtu"], "path": "bus.tty",
                "baudrate": 38400},
               {"name": "imu", "protocol": "modbus-witmotion", "transport": ["rtu"], "path": "bus.tty",
                "baudrate": 38400}]

    async def main() -> None:
        async with bridge_running(tmp_path, devices) as bridge:
            paths = {e.address for e in bridge.endpoints}
            assert paths == {str(tmp_path / "bus.tty")}
            c = await rtu_client(ep(bridge.endpoints, "imu", "pty"), timeout=0.3)
            await asyncio.sleep(0.1)
            assert abs(depth_of(await read_p1(c, unit=1)) - bridge.vehicle.state.depth) < DEPTH_TOL + 0.02
            rr = await c.read_holding_registers(0x36, count=1, device_id=0x50)
            assert abs(rr.registers[0] - 2048) < 150
            assert await no_answer(c, 9)
            c.close()
        assert not (tmp_path / "bus.tty").exists()

    asyncio.run(main())


def test_an_idle_modbus_tcp_client_is_disconnected_and_a_polling_one_kept(tmp_path: Path) -> None:
    """idle_timeout_s: a client that sends no request for that long is disconnected (its slot
    freed, as Modbus TCP gateways do); one polling well inside it keeps its connection."""
    async def main() -> None:
        ctx = SmallContext(tmp_path)
        spec = ("depth", "modbus-keller", {"transport": ["tcp"], "idle_timeout_s": 1.0})
        async with running(ctx, spec) as (devices, endpoints):
            e = ep(endpoints, "depth", "tcp")
            host, port = e.address.rsplit(":", 1)
            idle_r, idle_w = await asyncio.open_connection(host, int(port))
            poller = await tcp_client(e)
            loop = asyncio.get_running_loop()
            end = loop.time() + 3.0
            while loop.time() < end:
                await read_p1(poller)
                await asyncio.sleep(0.2)
            assert await asyncio.wait_for(idle_r.read(10), 2.0) == b""   # closed by the server
            await read_p1(poller)                                      # still served
            assert devices[0].tcp.link.stats.idle_drops == 1
            poller.close()
            idle_w.close()

    asyncio.run(main())


@pytest.mark.parametrize("spec", [KELLER, WIT], ids=["keller", "witmotion"])
def test_the_noise_fault_scales_every_noise_figure_of_the_clean_profile(tmp_path: Path, spec: tuple) -> None:
    """noise: each numeric '*noise*' figure of the sensor's profile times the factor (of the clean
    profile when injected again), nothing else; cleared, the clean profile is back; a bad factor
    is refused and changes nothing."""
    name, proto, opts = spec
    dev = device_class(proto)(name, opts, SmallContext(tmp_path))  # type: ignore[arg-type]
    sensor = dev.sensor  # type: ignore[attr-defined]
    clean = sensor.profile
    figures = {f.name: getattr(clean, f.name) for f in dataclasses.fields(clean)}
    noisy = [k for k, v in figures.items() if "noise" in k and isinstance(v, (int, float))]
    assert noisy and any(figures[k] > 0 for k in noisy)
    for factor in (5.0, 2.0):
        dev.inject_fault("noise", {"factor": factor})
        now = {f.name: getattr(sensor.profile, f.name) for f in dataclasses.fields(clean)}
        assert now == {k: v * factor if k in noisy else v for k, v in figures.items()}
    with pytest.raises(ValueError, match="noise factor"):
        dev.inject_fault("noise", {"factor": -1.0})
    assert getattr(sensor.profile, noisy[0]) == figures[noisy[0]] * 2.0
    dev.clear_fault("noise")
    assert sensor.profile is clean
