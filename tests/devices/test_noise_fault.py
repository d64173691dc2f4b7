"""NoiseFault and SensorFaults: the faults the sensor devices share (hilsim.devices.base)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import pytest

from hilsim.devices.base import NoiseFault, SensorFaults


@dataclass(frozen=True)
class Profile:
    a_noise: float
    b_noise: float
    other_noise: float
    rate: float


class Sensor:
    def __init__(self) -> None:
        self.profile = Profile(1.0, 0.5, 2.0, 10.0)


def test_scales_the_named_figures_of_the_clean_profile_and_puts_it_back() -> None:
    s = Sensor()
    clean = s.profile
    fault = NoiseFault("a_noise", "b_noise")
    fault.inject(s, {"factor": 4.0})
    assert s.profile == Profile(4.0, 2.0, 2.0, 10.0)
    fault.inject(s, {"factor": 3.0})          # of the clean profile, not on top
    assert s.profile == Profile(3.0, 1.5, 2.0, 10.0)
    fault.inject(s, {})                        # default factor 10
    assert s.profile == Profile(10.0, 5.0, 2.0, 10.0)
    fault.clear(s)
    assert s.profile is clean
    fault.inject(s, {"factor": 0})
    assert s.profile == Profile(0.0, 0.0, 2.0, 10.0)
    fault.clear(s)
    assert s.profile is clean


def test_clear_without_inject_changes_nothing() -> None:
    s = Sensor()
    before = s.profile
    NoiseFault("a_noise").clear(s)
    assert s.profile is before


@pytest.mark.parametrize("factor", [-1.0, math.inf, math.nan])
def test_a_bad_factor_is_refused_and_changes_nothing(factor: float) -> None:
    s = Sensor()
    before = s.profile
    with pytest.raises(ValueError, match="noise factor"):
        NoiseFault("a_noise").inject(s, {"factor": factor})
    assert s.profile is before


class FakeDevice(SensorFaults):
    """A sensor device with the faults of SensorFaults and one of its own."""

    protocol = "fake"
    FAULTS = ("dropout", "stuck", "noise", "lamp")
    NOISE_FIELDS = ("a_noise",)

    def __init__(self) -> None:
        super().__init__("fake", {}, None)  # type: ignore[arg-type]
        self.sim = Sensor()
        self.log: list[str] = []

    async def start(self) -> list[Any]:
        return []

    def inject_fault(self, fault: str, params: Mapping[str, Any]) -> None:
        super().inject_fault(fault, params)
        self.log.append(f"+{fault}")

    def clear_fault(self, fault: str) -> None:
        super().clear_fault(fault)
        self.log.append(f"-{fault}")


def test_sensor_faults_keep_what_is_injected_until_cleared() -> None:
    d = FakeDevice()
    clean = d.sim.profile
    d.set_fault("stuck", True, {})
    d.set_fault("noise", True, {"factor": 2.0})
    d.set_fault("lamp", True, {"colour": "red"})
    assert d.faults == {"stuck": {}, "noise": {"factor": 2.0}, "lamp": {"colour": "red"}}
    assert d.sim.profile == Profile(2.0, 0.5, 2.0, 10.0)
    d.set_fault("noise", False, {})
    d.set_fault("lamp", False, {})
    assert d.faults == {"stuck": {}} and d.sim.profile is clean
    d.set_fault("stuck", False, {})
    assert d.faults == {}
    with pytest.raises(ValueError, match="has no fault"):
        d.inject_fault("lock_loss", {})
    assert d.faults == {}
    assert d.log == ["+stuck", "+noise", "+lamp", "-noise", "-lamp", "-stuck"]
