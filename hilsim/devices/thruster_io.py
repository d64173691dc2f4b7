"""What the thruster devices (VESC CAN/UART, DroneCAN, VRCSR) share: the id -> thruster
mapping from the scenario, the CAN bus they attach to, and the ESC's running counters.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping

from hilsim.devices.base import DeviceContext, OptionError
from hilsim.links.can import CanBus, bus_class
from hilsim.sim.thrusters import ThrusterSet, ThrusterTelemetry

KELVIN = 273.15
CAN_TRANSPORTS = ("socketcand", "slcan", "socketcan", "virtual")


def vehicle_thrusters(ctx: DeviceContext, device: str) -> ThrusterSet:
    """The vehicle's thruster set; ValueError if the vehicle has none."""
    t = ctx.vehicle.thrusters
    if t is None:
        raise ValueError(f"device {device!r}: the scenario's vehicle has no thrusters to drive")
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
            raise ValueError(f"device {device!r}: mapping must be a table {{{what} = thruster}}, got {option!r}")
        out = {}
        for key, target in option.items():
            try:
                ident = int(key)
            except (TypeError, ValueError):
                raise ValueError(f"device {device!r}: mapping key {key!r} is not a {what}") from None
            if isinstance(target, bool) or not isinstance(target, (int, str)):
                raise ValueError(f"device {device!r}: mapping {key} -> {target!r}: give a thruster name or index")
            if isinstance(target, str):
                try:
                    index = thrusters.index(target)
                except KeyError as exc:
                    raise ValueError(f"device {device!r}: mapping {key}: {exc.args[0]}") from None
            else:
                index = target
                if not 0 <= index < len(thrusters):
                    raise ValueError(f"device {device!r}: mapping {key} -> thruster index {index} out of range "
                                     f"0..{len(thrusters) - 1}")
            out[ident] = index
    for ident in out:
        if not lo <= ident <= hi:
            raise ValueError(f"device {device!r}: {what} {ident} out of range {lo}..{hi}")
    return out


def mapping_text(mapping: Mapping[int, int], thrusters: ThrusterSet) -> str:
    return ", ".join(f"{k}->{thrusters.names[v]}" for k, v in sorted(mapping.items()))


def check_can_options(device: str, options: Mapping[str, Any]) -> None:
    """ValueError for a CAN device's transport options that cannot work (at construction time)."""
    transport = options["transport"]
    if transport not in CAN_TRANSPORTS:
        raise ValueError(f"device {device!r}: transport {transport!r} is not one of {', '.join(CAN_TRANSPORTS)}")
    if not isinstance(options["channel"], str) or not options["channel"]:
        raise ValueError(f"device {device!r}: channel must be a bus name such as 'can0'")
    if transport == "socketcand" and not (isinstance(options["port"], int) and 0 <= options["port"] <= 65535):
        raise ValueError(f"device {device!r}: port {options['port']!r} outside 0..65535")
    bitrate = options.get("bitrate")
    if bitrate is not None and not (isinstance(bitrate, int) and bitrate > 0):
        raise ValueError(f"device {device!r}: bitrate must be a positive number of bit/s, got {bitrate!r}")


def bus_location(ctx: DeviceContext, options: Mapping[str, Any]) -> Any:
    """What tells one bus of a transport from another: the socketcand port, the slcan pty path
    (inside the run folder; OptionError "path" for one that leaves it), the interface name."""
    transport = str(options["transport"])
    channel = str(options["channel"])
    if transport == "socketcand":
        return int(options["port"])
    if transport == "slcan":
        try:
            return str(ctx.pty_path(options["path"], f"slcan-{channel}"))
        except (TypeError, ValueError) as exc:
            raise OptionError("path", str(exc)) from None
    return channel


async def acquire_bus(ctx: DeviceContext, device: str, options: Mapping[str, Any]) -> CanBus:
    """The CAN bus named by the device's options, shared with every device naming the same
    (transport, channel, port or path)."""
    check_can_options(device, options)
    transport = str(options["transport"])
    channel = str(options["channel"])
    bitrate = int(options["bitrate"]) if options.get("bitrate") else None
    where = bus_location(ctx, options)
    kw: dict[str, Any] = {"channel": channel}
    if transport == "socketcand":
        kw.update(host=ctx.bind, port=where, bitrate=bitrate, max_clients=int(options["max_clients"]))
    elif transport == "slcan":
        kw.update(path=where, bitrate=bitrate)
    cls = bus_class(transport)

    async def make() -> CanBus:
        bus = cls(f"{transport}:{channel}", **kw)
        await bus.start()
        return bus
    return await ctx.shared(("can", transport, channel, where), make)


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
