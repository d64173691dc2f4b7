"""DroneCAN (UAVCAN v0) ESCs: esc.RawCommand in, esc.Status and the NodeStatus heartbeat out.

One emulated node (``node_id``) carries every mapped ESC index, as a
multi-channel ESC does. A RawCommand from any node sets, for each mapped
index present in its array, the thruster's "normalized" command
(value / 8191, clipped to [-1, 1]); indexes the array does not reach keep
their last command (and the model's watchdog). Every ``1 / status_rate_hz``
each ESC sends an esc.Status (a 3-frame transfer): voltage [V], input current
[A], winding temperature [K], mechanical rpm, power rating = |duty| [%], its
esc_index; every ``1 / node_status_rate_hz`` the node sends NodeStatus
(uptime = simulation seconds, health OK, mode OPERATIONAL). Transfer ids
count per data type.

Options: transport (default slcan), channel, port, path, bitrate (as for
vesc-can), node_id 1..127, priority (of Status; NodeStatus goes at 24),
status_rate_hz, node_status_rate_hz, mapping (``{esc_index = thruster}``;
default esc index i drives thruster i).
"""

from __future__ import annotations

import logging
from typing import Any

from hilsim.devices.base import CanDevice, DeviceContext, Endpoint
from hilsim.devices.thruster_io import drive, mapping_text, resolve_mapping, vehicle_thrusters
from hilsim.protocols import dronecan as dc
from hilsim.protocols.can import CanFrame

log = logging.getLogger(__name__)

NODE_STATUS_PRIORITY = 24


class DroneCanEscDevice(CanDevice):
    protocol = "dronecan"
    OPTIONS = {
        **CanDevice.OPTIONS,
        "transport": "slcan",
        "node_id": 20,
        "priority": 16,
        "status_rate_hz": 20.0,
        "node_status_rate_hz": 1.0,
        "mapping": {},
    }
    COUNTERS = ("commands", "status_transfers")

    def __init__(self, name: str, options: dict[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.thrusters = vehicle_thrusters(ctx, name)
        self.mapping = resolve_mapping(name, self.options["mapping"], self.thrusters, lambda i: i,
                                       (0, dc.RAW_COMMAND_LEN_MAX - 1), "esc index")
        self.node_id = self.option_int("node_id", 1, 127)
        self.priority = self.option_int("priority", 0, 31)
        self.rates = {k: self.option_number(k, 0.0, 1000.0, lo_open=True)
                      for k in ("status_rate_hz", "node_status_rate_hz")}
        self.receiver = dc.TransferReceiver(signatures={dc.RAW_COMMAND_DTID: dc.RAW_COMMAND_SIGNATURE})
        self.transfer_ids = dc.TransferIds()

    async def start(self) -> list[Endpoint]:
        bus = await self.attach(self._on_frame)
        self.every("status", 1.0 / self.rates["status_rate_hz"], self._send_status)
        self.every("node_status", 1.0 / self.rates["node_status_rate_hz"], self._send_node_status)
        log.info("%s: DroneCAN node %d on %s %s, ESCs %s", self.name, self.node_id, bus.transport,
                 bus.address, mapping_text(self.mapping, self.thrusters))
        return [self.endpoint(node_id=self.node_id, esc_indexes=sorted(self.mapping))]

    def status(self) -> dict[str, float]:
        st = self.receiver.stats
        bad = st.bad_frames + st.crc_errors + st.too_long + self.counters["bad_transfers"]
        return {**super().status(), "bad_frames": float(bad)}

    def _on_frame(self, frame: CanFrame) -> None:
        now = self.ctx.now()
        transfer = self.receiver.receive(frame, now)
        if transfer is None or transfer.dtid != dc.RAW_COMMAND_DTID:
            return
        if transfer.source_node == self.node_id:
            self.counters["own_id_seen"] += 1  # another node uses our id: a configuration error on the bus
        rc = dc.RawCommand.decode(transfer.payload)
        if rc is None:
            self.counters["bad_transfers"] += 1
            return
        for esc, index in self.mapping.items():
            value = rc.normalized(esc)
            if value is not None:
                drive(self, index, "normalized", value, now)
        self.counters["commands"] += 1

    def _send(self, message: dc.Message, priority: int) -> None:
        if self.bus is None:
            return
        dtid = dc.ESC_STATUS_DTID if isinstance(message, dc.EscStatus) else dc.NODE_STATUS_DTID
        for frame in dc.encode_message(message, self.node_id, self.transfer_ids.next(dtid, self.node_id), priority):
            self.bus.send(frame)

    def _send_status(self, t: float) -> None:
        if self.bus is None or not self.bus.has_listeners:
            return
        for esc, index in self.mapping.items():
            tel = self.thrusters.telemetry(index)
            self._send(dc.EscStatus(error_count=0, voltage=tel.voltage, current=tel.input_current,
                                    temperature=tel.temperature, rpm=round(tel.rpm),
                                    power_rating_pct=round(abs(tel.duty) * 100), esc_index=esc), self.priority)
            self.counters["status_transfers"] += 1

    def _send_node_status(self, t: float) -> None:
        self._send(dc.NodeStatus(uptime_sec=int(max(0.0, t))), NODE_STATUS_PRIORITY)
