"""VideoRay thrusters on an RS-485 line (pty), VRCSR protocol: propulsion commands, standard responses.

Each mapped thruster is a VideoRay thruster with a motor id (its index in
the command's power array) and a node id. A propulsion command (custom
command 0xAA at CSR address 0xF0) to the group id (default 0x81) sets every
mapped thruster whose motor id the array reaches ("normalized" power in
[-1, 1]); one sent to a thruster's own node id sets that thruster only. The
thruster named by the command's reply node id answers when the header's
flags ask: 0x02 the standard response (device type, rpm, bus voltage [V],
bus current [A], temperature [degC], fault 0), 0x01 an ACK (device type
only). Other CSR reads/writes are not emulated (counted, no reply). Replies
leave at the baud rate; garbage and bad CRCs are counted and skipped.

Options: path (pty symlink in the run folder; default the device name), baudrate,
group_id, mapping (``{motor_id = thruster}``; default motor id i drives
thruster i), node_ids (``{motor_id = node_id}``; default motor id + 1),
device_type (the byte the responses carry).
"""

from __future__ import annotations

import logging
from typing import Any, Mapping

from hilsim.devices.base import DeviceContext, Endpoint, PtyDevice
from hilsim.devices.thruster_io import celsius, drive, mapping_text, resolve_mapping, vehicle_thrusters
from hilsim.protocols import vrcsr
from hilsim.protocols.codec import drain

log = logging.getLogger(__name__)


class VrcsrDevice(PtyDevice):
    protocol = "vrcsr"
    OPTIONS = {
        **PtyDevice.OPTIONS,
        "group_id": vrcsr.THRUSTER_GROUP_ID,
        "mapping": {},
        "node_ids": {},
        "device_type": 2,
    }
    COUNTERS = ("commands", "replies", "not_emulated")

    def __init__(self, name: str, options: dict[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.thrusters = vehicle_thrusters(ctx, name)
        self.mapping = resolve_mapping(name, self.options["mapping"], self.thrusters, lambda i: i, (0, 62),
                                       "motor id")
        node_ids = self.options["node_ids"]
        if not isinstance(node_ids, Mapping):
            raise self.option_error("node_ids", "node_ids must be a table {motor_id = node_id}")
        try:
            given = {int(k): int(v) for k, v in node_ids.items()}
        except (TypeError, ValueError):
            raise self.option_error("node_ids", f"node_ids must map motor ids to node ids, got {node_ids!r}") from None
        self.node_of = {m: given.get(m, m + 1) for m in self.mapping}
        self.group_id = self.option_int("group_id", 1, 255)
        nodes = list(self.node_of.values())
        if len(set(nodes)) != len(nodes) or any(not 1 <= n <= 255 or n == self.group_id for n in nodes):
            raise self.option_error("node_ids", f"node ids {nodes} must be distinct, 1..255 and not the group id")
        self.motor_of = {n: m for m, n in self.node_of.items()}
        self.device_type = self.option_int("device_type", 0, 255)
        self.decoder = vrcsr.PacketDecoder()

    async def start(self) -> list[Endpoint]:
        link = await self.open_pty(self._on_data)
        log.info("%s: VRCSR on %s (%d baud), group 0x%02X, motors %s", self.name, link.path,
                 link.baudrate, self.group_id, mapping_text(self.mapping, self.thrusters))
        return [Endpoint(self.name, self.protocol, "pty", link.path,
                         {"baudrate": link.baudrate, "group_id": self.group_id,
                          "node_ids": {str(m): n for m, n in sorted(self.node_of.items())}})]

    def status(self) -> dict[str, float]:
        st = self.decoder.stats
        return {**super().status(), "crc_errors": float(st.header_crc_errors + st.payload_crc_errors),
                "bytes_skipped": float(st.bytes_skipped)}

    def _on_data(self, data: bytes) -> None:
        for pkt in drain(self.decoder, data, limit=10_000):
            self._handle(pkt)

    def _handle(self, pkt: vrcsr.Packet) -> None:
        if pkt.node_id != self.group_id and pkt.node_id not in self.motor_of:
            return  # for another device on the RS-485 line
        if pkt.address != vrcsr.ADDR_CUSTOM_COMMAND or not pkt.payload or pkt.payload[0] != vrcsr.PROPULSION_COMMAND:
            self.counters["not_emulated"] += 1
            return
        cmd = vrcsr.PropulsionCommand.decode(pkt.payload)
        if cmd is None:
            self.counters["bad_payloads"] += 1
            return
        now = self.ctx.now()
        if pkt.node_id == self.group_id:
            targets = list(self.mapping)
        else:
            targets = [self.motor_of[pkt.node_id]]
        for motor in targets:
            if motor < len(cmd.powers):
                drive(self, self.mapping[motor], "normalized", cmd.powers[motor], now)
        self.counters["commands"] += 1
        replier = self.motor_of.get(cmd.reply_node_id)
        if replier is None or pkt.flags not in (vrcsr.FLAG_ACK, vrcsr.FLAG_STANDARD) or self.link is None:
            return
        if pkt.flags == vrcsr.FLAG_ACK:
            body = bytes([self.device_type])
        else:
            tel = self.thrusters.telemetry(self.mapping[replier])
            body = vrcsr.StandardResponse(self.device_type, tel.rpm, tel.voltage, tel.input_current,
                                          celsius(tel.temperature), 0).payload()
        self.link.write(vrcsr.response(cmd.reply_node_id, pkt.flags, pkt.address, body))
        self.counters["replies"] += 1
