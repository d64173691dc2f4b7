"""Blue Robotics Ping1D echosounder/altimeter: ping-protocol on a pty (115200 8N1).

The sounder pings every ``ping_interval`` while enabled
(:class:`hilsim.sim.echosounder.Echosounder`: the beam cone cast with Embree);
requests are answered from the latest ping. Packets (protocols/ping-protocol.md):

* a request (``general_request`` with ``requested_id``, or an empty packet of a
  get id, as brping's ``Ping1D`` sends it) -> that message;
* a set message -> applied and acknowledged (``ack``), or ``nack`` with the reason
  when a value is refused;
* ``continuous_start`` / ``continuous_stop`` with id 1300 (profile), 1211 or 1212
  -> that message after every ping, until stopped;
* an unknown id, a payload that does not fit, a bad checksum -> ``nack`` with the
  id; bytes outside packets are skipped and counted.

Options: path, baudrate, sensor (the scenario's echosounder mount, default
``altimeter``), device_id (1). Faults: dropout (silent), stuck (the last ping
repeated), noise (``factor`` x the distance noise).
"""

from __future__ import annotations

import logging
import math
from typing import Any, Mapping

from hilsim.devices.base import DeviceContext, Endpoint, PtyDevice, SensorFaults
from hilsim.protocols import ping_protocol as pp
from hilsim.protocols.codec import drain

log = logging.getLogger(__name__)

FIRMWARE = (3, 29, 0)                    # reported firmware version (major, minor, patch)
STREAMABLE = frozenset({1211, 1212, 1300})
MIN_PING_INTERVAL_MS = 50


class Ping1dDevice(SensorFaults, PtyDevice):
    protocol = "ping1d"
    OPTIONS = {**PtyDevice.OPTIONS, "sensor": "altimeter", "device_id": 1}
    FAULTS = ("dropout", "stuck", "noise")
    NOISE_FIELDS = ("distance_noise_fraction",)
    COUNTERS = ("pings", "requests", "sets", "nacks", "streamed")

    def __init__(self, name: str, options: Mapping[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.mount = self.sensor_mount("echosounder")
        self.device_id = self.option_int("device_id", 0, 254)
        self.decoder = pp.PingDecoder()
        self.sim: Any = None
        self.last: Any = None
        self.streams: set[int] = set()
        self.ping_enabled = True
        self.ping_interval_ms = 100
        self._next_ping = 0.0

    async def start(self) -> list[Endpoint]:
        from hilsim.sim.echosounder import Echosounder, load_echosounder_profile
        from hilsim.sim.rig import profile_path

        profile = load_echosounder_profile(profile_path(self.ctx.scenario, self.mount))
        self.sim = Echosounder(profile, self.ctx.world, self.mount.mount, seed=self.ctx.seed, name=self.name,
                               sound_speed_true=float(self.ctx.scenario.water.sound_speed))
        self.ping_interval_ms = max(MIN_PING_INTERVAL_MS, int(round(profile.ping_interval * 1000)))
        self.last = self.sim.ping(self.ctx.vehicle.state)
        link = await self.open_pty(self._on_data)
        self.every("tick", MIN_PING_INTERVAL_MS / 1000.0, self._tick, priority=10)
        log.info("%s: Ping1D on %s (%d baud)", self.name, link.path, link.baudrate)
        return [Endpoint(self.name, self.protocol, "pty", link.path,
                         {"connect": f"uart://{link.path}:{link.baudrate}", "baudrate": link.baudrate,
                          "device_id": self.device_id})]

    # -- pinging -------------------------------------------------------------------
    def _tick(self, t: float) -> None:
        if not self.ping_enabled or t + 1e-9 < self._next_ping:
            return
        self._next_ping = t + self.ping_interval_ms / 1000.0
        if "stuck" not in self.faults or self.last is None:
            self.last = self.sim.ping(self.ctx.vehicle.state)
        self.counters["pings"] += 1
        if self.observed("reading"):
            self.publish("reading", {"t": float(t), "distance_m": float(self.last.distance),
                                     "confidence_pct": int(self.last.confidence)})
        for mid in sorted(self.streams):
            self._send(mid, 0)
            self.counters["streamed"] += 1

    # -- messages ------------------------------------------------------------------
    def _values(self, mid: int) -> dict[str, Any] | None:
        """The fields of get message ``mid`` now, None if this device does not answer it."""
        s, last = self.sim, self.last
        dist_mm = int(round(last.distance * 1000)) if math.isfinite(last.distance) else 0
        common = {"distance": dist_mm, "confidence": int(last.confidence),
                  "transmit_duration": int(round(last.transmit_duration * 1e6)), "ping_number": int(last.ping_number),
                  "scan_start": int(round(last.scan_start * 1000)), "scan_length": int(round(last.scan_length * 1000)),
                  "gain_setting": int(last.gain_setting)}
        major, minor, patch = FIRMWARE
        table: dict[int, dict[str, Any]] = {
            4: {"device_type": 1, "device_revision": 1, "firmware_version_major": major,
                "firmware_version_minor": minor, "firmware_version_patch": patch, "reserved": 0},
            5: {"version_major": 1, "version_minor": 0, "version_patch": 0, "reserved": 0},
            1200: {"device_type": 1, "device_model": 1, "firmware_version_major": major,
                   "firmware_version_minor": minor},
            1201: {"device_id": self.device_id},
            1202: {"voltage_5": 5000},
            1203: {"speed_of_sound": int(round(s.speed_of_sound * 1000))},
            1204: {"scan_start": common["scan_start"], "scan_length": common["scan_length"]},
            1205: {"mode_auto": int(s.mode_auto)},
            1206: {"ping_interval": self.ping_interval_ms},
            1207: {"gain_setting": int(s.gain_setting)},
            1208: {"transmit_duration": common["transmit_duration"]},
            1210: {"firmware_version_major": major, "firmware_version_minor": minor, "voltage_5": 5000,
                   "ping_interval": self.ping_interval_ms, "gain_setting": int(s.gain_setting),
                   "mode_auto": int(s.mode_auto)},
            1211: {"distance": dist_mm, "confidence": min(255, int(last.confidence))},
            1212: common,
            1213: {"processor_temperature": 4500},
            1214: {"pcb_temperature": 3500},
            1215: {"ping_enabled": int(self.ping_enabled)},
            1300: {**common, "profile_data": bytes(last.profile)},
            1301: {"number_of_points": len(last.profile), "normalization_enabled": 0, "enhance_enabled": 0},
        }
        return table.get(mid)

    def _send(self, mid: int, dst: int) -> None:
        values = self._values(mid)
        if values is None or self.link is None or "dropout" in self.faults:
            return
        self.link.write(pp.encode(mid, values, src=self.device_id, dst=dst))

    def _ack(self, mid: int, dst: int) -> None:
        if self.link is not None and "dropout" not in self.faults:
            self.link.write(pp.encode("ack", {"acked_id": mid}, src=self.device_id, dst=dst))

    def _nack(self, mid: int, dst: int, why: str) -> None:
        self.counters["nacks"] += 1
        if self.link is not None and "dropout" not in self.faults:
            self.link.write(pp.encode("nack", {"nacked_id": mid, "nack_message": why[:64]}, src=self.device_id,
                                      dst=dst))

    def _on_data(self, data: bytes) -> None:
        for ev in drain(self.decoder, data, limit=10_000):
            if isinstance(ev, pp.Message):
                self._handle(ev)
            elif isinstance(ev, (pp.BadChecksum, pp.UnknownMessage, pp.BadPayload)):
                self._nack(ev.message_id, 0, ev.reason)
            else:
                self.counters["bytes_skipped"] += getattr(ev, "n_bytes", 0) or 1

    def _handle(self, m: pp.Message) -> None:
        mid, src, f = m.message_id, m.src, m.fields
        if m.is_request:
            want = int(f["requested_id"]) if mid == 6 and m.payload else mid
            self.counters["requests"] += 1
            if want in pp.PING1D_GET_IDS:
                self._send(want, src)
            else:
                self._nack(want, src, "not a message this device sends")
            return
        s = self.sim
        err = ""
        if mid in (100, 1000):
            self.device_id = int(f["device_id"]) if f["device_id"] < 255 else self.device_id
        elif mid == 1001:
            if f["scan_length"] < 1000 or f["scan_start"] + f["scan_length"] > s.profile.range_max * 1000:
                err = "scan range out of bounds"
            else:
                s.mode_auto = False
                s.scan_start, s.scan_length = f["scan_start"] / 1000.0, f["scan_length"] / 1000.0
        elif mid == 1002:
            if not 1_000_000 <= f["speed_of_sound"] <= 2_000_000:
                err = "speed of sound out of bounds (1000-2000 m/s)"
            else:
                s.speed_of_sound = f["speed_of_sound"] / 1000.0
        elif mid == 1003:
            s.mode_auto = bool(f["mode_auto"])
        elif mid == 1004:
            if not MIN_PING_INTERVAL_MS <= f["ping_interval"] <= 65535:
                err = f"ping interval below {MIN_PING_INTERVAL_MS} ms"
            else:
                self.ping_interval_ms = int(f["ping_interval"])
        elif mid == 1005:
            if f["gain_setting"] > 6:
                err = "gain setting must be 0-6"
            else:
                s.mode_auto, s.gain_setting = False, int(f["gain_setting"])
        elif mid == 1006:
            self.ping_enabled = bool(f["ping_enabled"])
        elif mid in (1400, 1401):
            if f["id"] not in STREAMABLE:
                err = f"cannot stream message {f['id']}"
            elif mid == 1400:
                self.streams.add(int(f["id"]))
            else:
                self.streams.discard(int(f["id"]))
        else:
            err = "not a command this device accepts"
        if err:
            self._nack(mid, src, err)
        else:
            self.counters["sets"] += 1
            self._ack(mid, src)
