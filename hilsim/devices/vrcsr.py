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

from hilsim.devices.base import Device, DeviceContext, Endpoint
from hilsim.devices.thruster_io import celsius, mapping_text, resolve_mapping, vehicle_thrusters
from hilsim.links.pty import PtyLink
from hilsim.protocols import vrcsr

log = logging.getLogger(__name__)


class VrcsrDevice(Device):
    protocol = "vrcsr"
    OPTIONS = {
        "path": None,
        "baudrate": 115200,
        "group_id": vrcsr.THRUSTER_GROUP_ID,
        "mapping": {},
        "node_ids": {},
        "device_type": 2,
    }

    def __init__(self, name: str, options: dict[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.thrusters = vehicle_thrusters(ctx, name)
        self.path = self.option_pty_path("path", name)  # inside the run folder
        self.mapping = resolve_mapping(name, self.options["mapping"], self.thrusters, lambda i: i, (0, 62),
                                       "motor id")
        node_ids = self.options["node_ids"]
        if not isinstance(node_ids, Mapping):
            raise ValueError(f"device {name!r}: node_ids must be a table {{motor_id = node_id}}")
        given = {int(k): int(v) for k, v in node_ids.items()}
        self.node_of = {m: given.get(m, m + 1) for m in self.mapping}
        self.group_id = int(self.options["group_id"])
        nodes = list(self.node_of.values())
        if len(set(nodes)) != len(nodes) or any(not 1 <= n <= 255 or n == self.group_id for n in nodes):
            raise ValueError(f"device {name!r}: node ids {nodes} must be distinct, 1..255 and not the group id")
        self.motor_of = {n: m for m, n in self.node_of.items()}
        self.device_type = int(self.options["device_type"]) & 0xFF
        self.decoder = vrcsr.PacketDecoder()
        self.link: PtyLink | None = None
        self.commands = 0
        self.replies = 0
        self.not_emulated = 0
        self.bad_payloads = 0

    async def start(self) -> list[Endpoint]:
        self.link = PtyLink(self.name, self.path, baudrate=int(self.options["baudrate"]), on_data=self._on_data)
        await self.link.start()
        log.info("%s: VRCSR on %s (%d baud), group 0x%02X, motors %s", self.name, self.link.path,
                 self.link.baudrate, self.group_id, mapping_text(self.mapping, self.thrusters))
        return [Endpoint(self.name, self.protocol, "pty", self.link.path,
                         {"baudrate": self.link.baudrate, "group_id": self.group_id,
                          "node_ids": {str(m): n for m, n in sorted(self.node_of.items())}})]

    async def close(self) -> None:
        if self.link is not None:
            await self.link.close()
            self.link = None

    def status(self) -> dict[str, float]:
        st = self.decoder.stats
        return {"commands": float(self.commands), "replies": float(self.replies),
                "crc_errors": float(st.header_crc_errors + st.payload_crc_errors),
                "bytes_skipped": float(st.bytes_skipped), "not_emulated": float(self.not_emulated)}

    def _on_data(self, data: bytes) -> None:
        self.decoder.receive_data(data)
        for _ in range(10_000):
            pkt = self.decoder.next_event()
            if pkt is vrcsr.NEED_DATA:
                break
            self._handle(pkt)

    def _handle(self, pkt: vrcsr.Packet) -> None:
        if pkt.node_id != self.group_id and pkt.node_id not in self.motor_of:
            return  # for another device on the RS-485 line
        if pkt.address != vrcsr.ADDR_CUSTOM_COMMAND or not pkt.payload or pkt.payload[0] != vrcsr.PROPULSION_COMMAND:
            self.not_emulated += 1
            return
        cmd = vrcsr.PropulsionCommand.decode(pkt.payload)
        if cmd is None:
            self.bad_payloads += 1
            return
        now = self.ctx.now()
        if pkt.node_id == self.group_id:
            targets = list(self.mapping)
        else:
            targets = [self.motor_of[pkt.node_id]]
        for motor in targets:
            if motor < len(cmd.powers):
                self.thrusters.command(self.mapping[motor], "normalized", cmd.powers[motor], now)
        self.commands += 1
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
        self.replies += 1
