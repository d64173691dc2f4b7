"""A VESC on a serial port (pty): COMM_* packets in, GET_VALUES / FW_VERSION replies out.

The local VESC has ``controller_id`` and drives the thruster ``mapping`` gives
it; COMM_FORWARD_CAN reaches the other mapped ids, as a VESC forwards to the
ESCs on its CAN bus. Commands: SET_DUTY ("duty"), SET_CURRENT ("current" [A]),
SET_CURRENT_BRAKE (a zero duty: the rotor slows to a stop), SET_RPM ("erpm"),
ALIVE (re-issues this interface's last command for that thruster, as the
firmware's timeout reset keeps the last set-point), GET_VALUES and
GET_VALUES_SELECTIVE (the firmware's reply layout, values from the thruster
model; FET temperature = the water's), FW_VERSION. Other packets are counted
and get no reply. Replies leave at the baud rate (the pty link paces them).
Garbage, truncated packets and bad CRCs are counted and skipped.

Options: path (pty symlink in the run folder; default the device name), baudrate,
controller_id, mapping (``{controller_id = thruster}``; default i+1 -> thruster i).
"""

from __future__ import annotations

import logging
from typing import Any

from hilsim.devices.base import DeviceContext, Endpoint, PtyDevice
from hilsim.devices.thruster_io import (EscCounters, celsius, drive, mapping_text, resolve_mapping,
                                       vehicle_thrusters)
from hilsim.protocols import vesc_uart as vu
from hilsim.protocols.codec import drain

log = logging.getLogger(__name__)

COUNTER_PERIOD = 0.02  # [s] how often the tachometer and Ah/Wh counters are integrated


class VescUartDevice(PtyDevice):
    protocol = "vesc-uart"
    OPTIONS = {
        **PtyDevice.OPTIONS,
        "controller_id": 1,
        "mapping": {},
    }
    COUNTERS = ("commands", "replies", "unsupported")

    def __init__(self, name: str, options: dict[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.thrusters = vehicle_thrusters(ctx, name)
        self.mapping = resolve_mapping(name, self.options["mapping"], self.thrusters, lambda i: i + 1, (0, 255),
                                       "controller id")
        self.controller_id = self.option_int("controller_id", 0, 255)
        if self.controller_id not in self.mapping:
            raise self.option_error("controller_id", f"controller_id {self.controller_id} is not in the mapping "
                                    f"({mapping_text(self.mapping, self.thrusters)})")
        self.decoder = vu.PacketDecoder()
        self.esc_counters = {cid: EscCounters() for cid in self.mapping}
        self.last: dict[int, tuple[str, float]] = {}

    async def start(self) -> list[Endpoint]:
        link = await self.open_pty(self._on_data)
        self.every("counters", COUNTER_PERIOD, self._count)
        log.info("%s: VESC UART on %s (%d baud), controller %d, CAN ids %s", self.name, link.path,
                 link.baudrate, self.controller_id, mapping_text(self.mapping, self.thrusters))
        return [Endpoint(self.name, self.protocol, "pty", link.path,
                         {"baudrate": link.baudrate, "controller_id": self.controller_id,
                          "controller_ids": sorted(self.mapping)})]

    def status(self) -> dict[str, float]:
        st = self.decoder.stats
        return {**super().status(), "crc_errors": float(st.crc_errors), "framing_errors": float(st.framing_errors),
                "bytes_skipped": float(st.bytes_skipped)}

    def _on_data(self, data: bytes) -> None:
        for payload in drain(self.decoder, data, limit=10_000):
            self._handle(vu.decode_command(payload), self.controller_id)

    def _reply(self, payload: bytes) -> None:
        if self.link is not None:
            self.link.write(vu.frame(payload))
            self.counters["replies"] += 1

    def _handle(self, cmd: vu.Command | vu.Unsupported, cid: int) -> None:
        if isinstance(cmd, vu.Unsupported):
            self.counters["unsupported"] += 1
            return
        if isinstance(cmd, vu.ForwardCan):
            if cmd.controller_id not in self.mapping:
                self.counters["unknown_ids"] += 1  # nobody on the CAN bus answers
                return
            self._handle(cmd.inner, cmd.controller_id)
            return
        index = self.mapping[cid]
        now = self.ctx.now()
        if isinstance(cmd, vu.GetValues):
            self._reply(vu.encode_values(self._values(cid, index), cmd.mask))
            return
        if isinstance(cmd, vu.GetFwVersion):
            self._reply(vu.encode_fw_version(vu.FwVersion(hw_name="hilsim")))
            return
        if isinstance(cmd, vu.Alive):
            if index in self.last:
                drive(self, index, *self.last[index], now)
            return
        if isinstance(cmd, vu.SetDuty):
            kind, value = "duty", cmd.duty
        elif isinstance(cmd, vu.SetCurrent):
            kind, value = "current", cmd.current
        elif isinstance(cmd, vu.SetCurrentBrake):
            kind, value = "duty", 0.0
        else:
            kind, value = "erpm", cmd.erpm
        drive(self, index, kind, value, now)
        self.last[index] = (kind, value)
        self.counters["commands"] += 1

    def _count(self, t: float) -> None:
        for cid, index in self.mapping.items():
            self.esc_counters[cid].advance(t, self.thrusters.telemetry(index))

    def _values(self, cid: int, index: int) -> vu.Values:
        tel = self.thrusters.telemetry(index)
        c = self.esc_counters[cid]
        water = celsius(self.thrusters.water_temperature)
        return vu.Values(
            temp_fet=water, temp_motor=celsius(tel.temperature), avg_motor_current=tel.motor_current,
            avg_input_current=tel.input_current, avg_id=0.0, avg_iq=tel.motor_current, duty_now=tel.duty,
            rpm=tel.erpm, v_in=tel.voltage, amp_hours=c.amp_hours, watt_hours=c.watt_hours,
            tachometer=int(c.tachometer), tachometer_abs=int(c.tachometer_abs), fault_code=0, pid_pos=0.0,
            controller_id=cid, temp_mos1=water, temp_mos2=water, temp_mos3=water, avg_vd=0.0,
            avg_vq=tel.duty * tel.voltage, status=1 if tel.timed_out else 0)
