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

from hilsim.devices.base import Device, DeviceContext, Endpoint
from hilsim.devices.thruster_io import EscCounters, celsius, mapping_text, resolve_mapping, vehicle_thrusters
from hilsim.links.pty import PtyLink
from hilsim.protocols import vesc_uart as vu

log = logging.getLogger(__name__)

COUNTER_PERIOD = 0.02  # [s] how often the tachometer and Ah/Wh counters are integrated


class VescUartDevice(Device):
    protocol = "vesc-uart"
    OPTIONS = {
        "path": None,
        "baudrate": 115200,
        "controller_id": 1,
        "mapping": {},
    }

    def __init__(self, name: str, options: dict[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.thrusters = vehicle_thrusters(ctx, name)
        self.path = self.option_pty_path("path", name)  # inside the run folder
        self.mapping = resolve_mapping(name, self.options["mapping"], self.thrusters, lambda i: i + 1, (0, 255),
                                       "controller id")
        self.controller_id = int(self.options["controller_id"])
        if self.controller_id not in self.mapping:
            raise ValueError(f"device {name!r}: controller_id {self.controller_id} is not in the mapping "
                             f"({mapping_text(self.mapping, self.thrusters)})")
        self.decoder = vu.PacketDecoder()
        self.counters = {cid: EscCounters() for cid in self.mapping}
        self.last: dict[int, tuple[str, float]] = {}
        self.link: PtyLink | None = None
        self._event: Any = None
        self.commands = 0
        self.replies = 0
        self.unsupported = 0
        self.unknown_ids = 0

    async def start(self) -> list[Endpoint]:
        self.link = PtyLink(self.name, self.path, baudrate=int(self.options["baudrate"]), on_data=self._on_data)
        await self.link.start()
        self._event = self.ctx.scheduler.add(f"{self.name}.counters", COUNTER_PERIOD, self._count, priority=20)
        log.info("%s: VESC UART on %s (%d baud), controller %d, CAN ids %s", self.name, self.link.path,
                 self.link.baudrate, self.controller_id, mapping_text(self.mapping, self.thrusters))
        return [Endpoint(self.name, self.protocol, "pty", self.link.path,
                         {"baudrate": self.link.baudrate, "controller_id": self.controller_id,
                          "controller_ids": sorted(self.mapping)})]

    async def close(self) -> None:
        if self._event is not None:
            self.ctx.scheduler.remove(self._event)
            self._event = None
        if self.link is not None:
            await self.link.close()
            self.link = None

    def status(self) -> dict[str, float]:
        st = self.decoder.stats
        return {"commands": float(self.commands), "replies": float(self.replies),
                "crc_errors": float(st.crc_errors), "framing_errors": float(st.framing_errors),
                "bytes_skipped": float(st.bytes_skipped), "unsupported": float(self.unsupported)}

    def _on_data(self, data: bytes) -> None:
        self.decoder.receive_data(data)
        for _ in range(10_000):
            payload = self.decoder.next_event()
            if payload is vu.NEED_DATA:
                break
            self._handle(vu.decode_command(payload), self.controller_id)

    def _reply(self, payload: bytes) -> None:
        if self.link is not None:
            self.link.write(vu.frame(payload))
            self.replies += 1

    def _handle(self, cmd: vu.Command | vu.Unsupported, cid: int) -> None:
        if isinstance(cmd, vu.Unsupported):
            self.unsupported += 1
            return
        if isinstance(cmd, vu.ForwardCan):
            if cmd.controller_id not in self.mapping:
                self.unknown_ids += 1  # nobody on the CAN bus answers
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
                self.thrusters.command(index, *self.last[index], now)
            return
        if isinstance(cmd, vu.SetDuty):
            kind, value = "duty", cmd.duty
        elif isinstance(cmd, vu.SetCurrent):
            kind, value = "current", cmd.current
        elif isinstance(cmd, vu.SetCurrentBrake):
            kind, value = "duty", 0.0
        else:
            kind, value = "erpm", cmd.erpm
        self.thrusters.command(index, kind, value, now)
        self.last[index] = (kind, value)
        self.commands += 1

    def _count(self, t: float) -> None:
        for cid, index in self.mapping.items():
            self.counters[cid].advance(t, self.thrusters.telemetry(index))

    def _values(self, cid: int, index: int) -> vu.Values:
        tel = self.thrusters.telemetry(index)
        c = self.counters[cid]
        water = celsius(self.thrusters.water_temperature)
        return vu.Values(
            temp_fet=water, temp_motor=celsius(tel.temperature), avg_motor_current=tel.motor_current,
            avg_input_current=tel.input_current, avg_id=0.0, avg_iq=tel.motor_current, duty_now=tel.duty,
            rpm=tel.erpm, v_in=tel.voltage, amp_hours=c.amp_hours, watt_hours=c.watt_hours,
            tachometer=int(c.tachometer), tachometer_abs=int(c.tachometer_abs), fault_code=0, pid_pos=0.0,
            controller_id=cid, temp_mos1=water, temp_mos2=water, temp_mos3=water, avg_vd=0.0,
            avg_vq=tel.duty * tel.voltage, status=1 if tel.timed_out else 0)
