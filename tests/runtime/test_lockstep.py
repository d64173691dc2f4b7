"""Lockstep: a device that declares ``clock_master`` drives the simulated time through
``ctx.advance(dt)`` (ArduPilot's JSON backend does); time stands still between its steps while
the event loop keeps serving, and each step runs physics and every device's schedule."""

from __future__ import annotations

import asyncio
import math

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
