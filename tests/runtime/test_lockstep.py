"""Lockstep: a device that declares ``clock_master`` drives the simulated time through
``ctx.advance(dt)`` (ArduPilot's JSON backend does); time stands still between its steps while
the event loop keeps serving, and each step runs physics and every device's schedule."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from hilsim.devices import REGISTRY
from hilsim.devices.base import Device, Endpoint
from hilsim.resources import find_scenario
from hilsim.runtime.bridge import Bridge
from hilsim.sim.scenario import load_scenario


class StepMaster(Device):
    """A clock master with no link: the test calls its ``step``; it counts its own 10 Hz ticks."""

    protocol = "test-step-master"
    clock_master = True

    async def start(self) -> list[Endpoint]:
        self.ticks: list[float] = []
        self.every("tick", 0.1, self.ticks.append, priority=20)
        return []

    async def step(self, dt: float) -> float:
        await self.ctx.advance(dt)
        return self.ctx.vehicle.state.time


@pytest.fixture
def scenario(tmp_path):
    src = load_scenario(find_scenario("water_tank")).path.read_text()
    head = src.split("# ---- devices")[0]  # the world and the vehicle, none of the default devices
    path = tmp_path / "scenario.toml"
    # the water tank has only primitives (no mesh files), so the copy stands alone
    path.write_text(head + '\n[[devices]]\nname = "master"\nprotocol = "test-step-master"\n')
    REGISTRY["test-step-master"] = f"{__name__}:StepMaster"
    yield path
    REGISTRY.pop("test-step-master", None)


def test_time_moves_only_by_the_masters_steps(scenario):
    async def main() -> None:
        bridge = Bridge(scenario, status_interval=0)
        await bridge.start()
        master = bridge.devices[0]
        assert bridge.lockstep and isinstance(master, StepMaster)
        runner = asyncio.ensure_future(bridge.run())
        try:
            await asyncio.sleep(0.2)  # no steps: simulated time stands still, the loop runs
            assert bridge.now() == 0.0 and master.ticks == [0.0]
            dt = 1.0 / 1200.0
            times = [await master.step(dt) for _ in range(1200)]
            # each step ends with the vehicle exactly at the granted time (physics included)
            assert all(math.isclose(t, (i + 1) * dt, abs_tol=1e-9) for i, t in enumerate(times))
            assert len(master.ticks) == 11 and math.isclose(master.ticks[-1], 1.0, abs_tol=1e-9)
            # the physics ran: the buoyant Cyclops (W_w = -2.5 N) has started to rise
            assert bridge.vehicle.state.velocity[2] < 0.0
            await asyncio.sleep(0.1)
            assert math.isclose(bridge.now(), 1.0, abs_tol=1e-9)  # and stood still again
        finally:
            bridge.stop()  # wakes the scheduler's wait for a step
            await asyncio.wait_for(runner, 5)
            await bridge.close()

    asyncio.run(main())


def test_advance_without_a_clock_master_is_refused(tmp_path):
    async def main() -> None:
        bridge = Bridge(find_scenario("water_tank"), fast=True, status_interval=0, run_dir=tmp_path / "run")
        with pytest.raises(RuntimeError, match="clock_master"):
            await bridge.advance(0.01)
        await bridge.close()

    asyncio.run(main())


def test_the_sonar_pings_at_every_simulated_period_however_fast_the_master_steps(tmp_path):
    """A sonar in lockstep renders at its simulated times: the master's step waits for a frame
    that falls in it. 2 s of 10 ms steps taken as fast as the loop allows (far faster than
    real time, and than the renderer) still give the DDF client the 30 frames of 15 Hz, numbered
    in a row, 1/15 s apart in the frames' own time (to the 5 ms physics step)."""
    from tests.runtime.bridge_helpers import FRAME_HDR, parse_frame

    src = load_scenario(find_scenario("water_tank")).path.read_text()
    path = tmp_path / "scenario.toml"
    path.write_text(src.split("# ---- devices")[0]
                    + '\n[[devices]]\nname = "master"\nprotocol = "test-step-master"\n'
                    + '\n[[devices]]\nname = "sonar_ddf"\nprotocol = "ddf-stream"\nsensor = "sonar"\nport = 0\n')
    REGISTRY["test-step-master"] = f"{__name__}:StepMaster"

    async def main() -> None:
        bridge = Bridge(path, status_interval=0, run_dir=tmp_path / "run")
        endpoints = await bridge.start()
        master = bridge.devices[0]
        host, port = next(e for e in endpoints if e.protocol == "ddf-stream").address.rsplit(":", 1)
        runner = asyncio.ensure_future(bridge.run())
        writer = None
        try:
            reader, writer = await asyncio.open_connection(host, int(port))
            head = await reader.readexactly(1024)
            beams, samples = int.from_bytes(head[16:20], "little"), int.from_bytes(head[24:28], "little")
            frames = []

            async def read() -> None:  # the client reads all along (its queue is bounded)
                while True:
                    try:
                        raw = await asyncio.wait_for(reader.readexactly(FRAME_HDR + beams * samples), 3.0)
                    except asyncio.TimeoutError:
                        return
                    frames.append(parse_frame(raw, beams))

            client = asyncio.ensure_future(read())
            await asyncio.sleep(0.3)  # the client is registered before time moves
            for _ in range(200):
                await master.step(0.01)
            assert math.isclose(bridge.now(), 2.0, abs_tol=1e-9)
            await client
        finally:
            if writer is not None:
                writer.close()
            bridge.stop()
            await asyncio.wait_for(runner, 5)
            await bridge.close()
        numbers = [f.number for f in frames]
        assert numbers == list(range(numbers[0], numbers[0] + len(numbers))), numbers
        assert len(frames) >= 30, numbers  # t = 1/15 .. 2 s (and t = 0 if it reached the client)
        # a frame carries the vehicle's state time: the ping's time on the 5 ms physics grid
        times = np.array([f.time_us for f in frames]) * 1e-6
        assert np.all(np.abs(np.diff(times) - 1.0 / 15.0) <= 0.005 + 1e-6), np.diff(times)
        assert abs(times[-1] - times[0] - (len(times) - 1) / 15.0) <= 0.005 + 1e-6

    try:
        asyncio.run(main())
    finally:
        REGISTRY.pop("test-step-master", None)
