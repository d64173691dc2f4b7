"""What the thruster devices (VESC CAN/UART, DroneCAN, VRCSR) share: the id -> thruster
mapping from the scenario, commanding a thruster (published for observers), and the ESC's
running counters.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping

from hilsim.devices.context import DeviceContext, OptionError
from hilsim.sim.thrusters import ThrusterSet, ThrusterTelemetry

KELVIN = 273.15


def vehicle_thrusters(ctx: DeviceContext, device: str) -> ThrusterSet:
    """The vehicle's thruster set; OptionError ("protocol") if the vehicle has none."""
    t = ctx.vehicle.thrusters
    if t is None:
        raise OptionError("protocol", f"device {device!r}: the scenario's vehicle has no thrusters to drive")
    return t


def resolve_mapping(device: str, option: Any, thrusters: ThrusterSet, default: Callable[[int], int],
                    id_range: tuple[int, int], what: str) -> dict[int, int]:
    """``{id: thruster}`` from the scenario (ids may be TOML string keys; thrusters a name or an
    index) -> ``{id: thruster index}``. Empty: ``default(i)`` is the id of thruster ``i``."""
    lo, hi = id_range
    if not option:
        out = {default(i): i for i in range(len(thrusters))}
    else:
        if not isinstance(option, Mapping):
            raise OptionError("mapping", f"device {device!r}: mapping must be a table {{{what} = thruster}}, got {option!r}")
        out = {}
        for key, target in option.items():
            try:
                ident = int(key)
            except (TypeError, ValueError):
                raise OptionError("mapping", f"device {device!r}: mapping key {key!r} is not a {what}") from None
            if isinstance(target, bool) or not isinstance(target, (int, str)):
                raise OptionError("mapping", f"device {device!r}: mapping {key} -> {target!r}: give a thruster name or index")
            if isinstance(target, str):
                try:
                    index = thrusters.index(target)
                except KeyError as exc:
                    raise OptionError("mapping", f"device {device!r}: mapping {key}: {exc.args[0]}") from None
            else:
                index = target
                if not 0 <= index < len(thrusters):
                    raise OptionError("mapping", f"device {device!r}: mapping {key} -> thruster index {index} out of range "
                                     f"0..{len(thrusters) - 1}")
            out[ident] = index
    for ident in out:
        if not lo <= ident <= hi:
            raise OptionError("mapping", f"device {device!r}: {what} {ident} out of range {lo}..{hi}")
    return out


def drive(device: Any, index: int, kind: str, value: float, now: float) -> None:
    """Command thruster ``index`` of ``device.thrusters`` (``kind``: duty, current, erpm, normalized ...)
    and publish it on the device's ``command`` topic for the console and recorders."""
    device.thrusters.command(index, kind, value, now)
    if device.observed("command"):
        device.publish("command", {"t": now, "thruster": index, "name": device.thrusters.names[index],
                                   "kind": kind, "value": float(value), "source": device.name})


def mapping_text(mapping: Mapping[int, int], thrusters: ThrusterSet) -> str:
    return ", ".join(f"{k}->{thrusters.names[v]}" for k, v in sorted(mapping.items()))


class EscCounters:
    """Running totals an ESC keeps: tachometer (6 steps per electrical revolution, signed and
    absolute), amp-hours and watt-hours drawn, advanced from the telemetry at each call."""

    def __init__(self) -> None:
        self.tachometer = 0.0
        self.tachometer_abs = 0.0
        self.amp_hours = 0.0
        self.watt_hours = 0.0
        self._t: float | None = None

    def advance(self, t: float, tel: ThrusterTelemetry) -> None:
        """Integrate up to time ``t`` [s] at the given telemetry."""
        if self._t is not None and t > self._t:
            dt = t - self._t
            steps = tel.erpm / 60.0 * 6.0 * dt
            self.tachometer += steps
            self.tachometer_abs += abs(steps)
            self.amp_hours += tel.input_current * dt / 3600.0
            self.watt_hours += tel.input_current * tel.voltage * dt / 3600.0
        self._t = t


def celsius(kelvin: float) -> float:
    return kelvin - KELVIN if math.isfinite(kelvin) else 0.0
