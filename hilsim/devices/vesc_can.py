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
from typing import Any

from hilsim.devices.base import CanDevice, DeviceContext, Endpoint
from hilsim.devices.thruster_io import EscCounters, celsius, drive, mapping_text, resolve_mapping, vehicle_thrusters
from hilsim.protocols import vesc_can as vc
from hilsim.protocols.can import CanFrame

log = logging.getLogger(__name__)


class VescCanDevice(CanDevice):
    protocol = "vesc-can"
    OPTIONS = {
        **CanDevice.OPTIONS,
        "status_rate_hz": 50.0,
        "mapping": {},
    }
    COUNTERS = ("commands", "bad_frames", "status_frames")

    def __init__(self, name: str, options: dict[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.thrusters = vehicle_thrusters(ctx, name)
        self.mapping = resolve_mapping(name, self.options["mapping"], self.thrusters, lambda i: i + 1, (0, 255),
                                       "controller id")
        self.period = 1.0 / self.option_number("status_rate_hz", 0.0, 1000.0, lo_open=True)
        self.esc_counters = {cid: EscCounters() for cid in self.mapping}

    async def start(self) -> list[Endpoint]:
        bus = await self.attach(self._on_frame)
        self.every("status", self.period, self._send_status)
        log.info("%s: VESC CAN on %s %s, controllers %s", self.name, bus.transport, bus.address,
                 mapping_text(self.mapping, self.thrusters))
        return [self.endpoint(controller_ids=sorted(self.mapping))]

    # -- commands ----------------------------------------------------------------

    def _on_frame(self, frame: CanFrame) -> None:
        msg = vc.decode(frame)
        if msg is None:
            return
        if isinstance(msg, vc.BadFrame):
            self.counters["bad_frames"] += 1
            return
        if not isinstance(msg, vc.VescCommand):
            return  # another ESC's status on the bus
        index = self.mapping.get(msg.controller_id)
        if index is None:
            self.counters["other_ids"] += 1
            return
        kind, value = self._command(index, msg)
        drive(self, index, kind, value, self.ctx.now())
        self.counters["commands"] += 1

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
            c = self.esc_counters[cid]
            c.advance(t, tel)
            if not listening:
                continue  # nobody could hear it: skip the encoding, keep the counters going
            for msg in (vc.Status1(cid, round(tel.erpm), tel.motor_current, tel.duty),
                        vc.Status4(cid, water, celsius(tel.temperature), tel.input_current, 0.0),
                        vc.Status5(cid, int(c.tachometer), tel.voltage)):
                bus.send(vc.encode(msg))
                self.counters["status_frames"] += 1
