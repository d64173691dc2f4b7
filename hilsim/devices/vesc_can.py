"""VESC ESCs on a CAN bus: SET_* commands in, STATUS_1/4/5 out, one ESC per mapped thruster.

Each mapped controller id behaves as a VESC with that id (``protocols/vesc_can.dbc``):

    SET_DUTY           -> the thruster's "duty" command
    SET_CURRENT        -> "current" [A]
    SET_CURRENT_BRAKE  -> brake: a zero duty (the rotor slows to a stop with the model's lag)
    SET_RPM            -> "erpm" (electrical rev/min; the profile's pole pairs convert)
    SET_CURRENT_REL    -> "current" = fraction x the profile's max current

Every ``1 / status_rate_hz`` each ESC sends STATUS_1 (ERPM, motor current, duty),
STATUS_4 (FET and motor temperature [degC], input current) and STATUS_5
(tachometer, input voltage), from the thruster model's telemetry, never
echoing the command. The watchdog is the thruster model's (a command older
than the profile's ``watchdog_timeout`` lets the rotor stop). The FET
temperature is the water's (the model has no FET thermal model).

Options: transport (socketcand | slcan | socketcan | virtual), channel (bus
name, e.g. can0), port (socketcand; 0 picks one), path (slcan pty symlink;
inside the run folder, default ``slcan-<channel>``), bitrate [bit/s], status_rate_hz,
mapping (``{controller_id = thruster}``; default controller i+1 drives thruster i),
max_clients (socketcand).
"""

from __future__ import annotations

import logging
from typing import Any, Callable

from hilsim.devices.base import Device, DeviceContext, Endpoint
from hilsim.devices.thruster_io import (EscCounters, acquire_bus, bus_location, celsius, check_can_options,
                                       mapping_text, resolve_mapping, vehicle_thrusters)
from hilsim.links.can import CanBus
from hilsim.protocols import vesc_can as vc
from hilsim.protocols.can import CanFrame

log = logging.getLogger(__name__)


class VescCanDevice(Device):
    protocol = "vesc-can"
    OPTIONS = {
        "transport": "socketcand",
        "channel": "can0",
        "port": 0,
        "path": None,
        "bitrate": 1_000_000,
        "status_rate_hz": 50.0,
        "mapping": {},
        "max_clients": 8,
    }

    def __init__(self, name: str, options: dict[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        check_can_options(name, self.options)
        bus_location(ctx, self.options)  # a pty path that leaves the run folder fails here, with the scenario line
        self.thrusters = vehicle_thrusters(ctx, name)
        self.mapping = resolve_mapping(name, self.options["mapping"], self.thrusters, lambda i: i + 1, (0, 255),
                                       "controller id")
        rate = float(self.options["status_rate_hz"])
        if not 0 < rate <= 1000:
            raise ValueError(f"device {name!r}: status_rate_hz {rate} outside (0, 1000]")
        self.period = 1.0 / rate
        self.bus: CanBus | None = None
        self.counters = {cid: EscCounters() for cid in self.mapping}
        self.commands = 0
        self.bad_frames = 0
        self.other_ids = 0
        self.status_frames = 0
        self._unsubscribe: Callable[[], None] | None = None
        self._event: Any = None

    async def start(self) -> list[Endpoint]:
        self.bus = await acquire_bus(self.ctx, self.name, self.options)
        self._unsubscribe = self.bus.subscribe(self._on_frame)
        self._event = self.ctx.scheduler.add(f"{self.name}.status", self.period, self._send_status, priority=20)
        log.info("%s: VESC CAN on %s %s, controllers %s", self.name, self.bus.transport, self.bus.address,
                 mapping_text(self.mapping, self.thrusters))
        return [Endpoint(self.name, self.protocol, self.bus.transport, self.bus.address,
                         {**self.bus.extra, "controller_ids": sorted(self.mapping)})]

    async def close(self) -> None:
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        if self._event is not None:
            self.ctx.scheduler.remove(self._event)
            self._event = None

    def status(self) -> dict[str, float]:
        out = {"commands": float(self.commands), "bad_frames": float(self.bad_frames),
               "status_frames": float(self.status_frames)}
        if self.bus is not None:
            bs = self.bus.status()
            out.update(clients=bs["clients"], frames_in=bs["frames_in"], dropped_in=bs["dropped_in"],
                       dropped_out=bs["dropped_out"])
        return out

    # -- commands ----------------------------------------------------------------

    def _on_frame(self, frame: CanFrame) -> None:
        msg = vc.decode(frame)
        if msg is None:
            return
        if isinstance(msg, vc.BadFrame):
            self.bad_frames += 1
            return
        if not isinstance(msg, vc.VescCommand):
            return  # another ESC's status on the bus
        index = self.mapping.get(msg.controller_id)
        if index is None:
            self.other_ids += 1
            return
        kind, value = self._command(index, msg)
        self.thrusters.command(index, kind, value, self.ctx.now())
        self.commands += 1

    def _command(self, index: int, msg: vc.VescCommand) -> tuple[str, float]:
        if msg.command == "SET_DUTY":
            return "duty", msg.value
        if msg.command == "SET_CURRENT":
            return "current", msg.value
        if msg.command == "SET_CURRENT_BRAKE":
            return "duty", 0.0
        if msg.command == "SET_RPM":
            return "erpm", msg.value
        profile = self.thrusters.thrusters[index].profile
        return "current", max(-1.0, min(1.0, msg.value)) * profile.max_current  # SET_CURRENT_REL

    # -- telemetry -----------------------------------------------------------------

    def _send_status(self, t: float) -> None:
        bus = self.bus
        if bus is None:
            return
        water = celsius(self.thrusters.water_temperature)
        listening = bus.has_listeners
        for cid, index in self.mapping.items():
            tel = self.thrusters.telemetry(index)
            c = self.counters[cid]
            c.advance(t, tel)
            if not listening:
                continue  # nobody could hear it: skip the encoding, keep the counters going
            for msg in (vc.Status1(cid, round(tel.erpm), tel.motor_current, tel.duty),
                        vc.Status4(cid, water, celsius(tel.temperature), tel.input_current, 0.0),
                        vc.Status5(cid, int(c.tachometer), tel.voltage)):
                bus.send(vc.encode(msg))
                self.status_frames += 1
