"""Blueprint Subsea Oculus M-series sonar: UDP status + TCP fire/ping channel.

See ``protocols/oculus.md``. The device

* sends the 142-byte status datagram every ``status_interval_s`` to
  ``ctx.broadcast:status_port`` (loopback unless the scenario or the command
  line names a LAN address), with the address clients must connect to in
  ``ipAddr`` (``status_ip``, default the bind address, 127.0.0.1 for a
  wildcard bind);
* serves the TCP data channel (``port``, 52100 on a real sonar): every
  client fires SimpleFire v1 or v2 messages and gets SimplePingResults of the
  same version at the fired ping rate, rendered with the fired mode (LF ->
  ``profile_lf``, HF -> ``profile_hf``), range and gain. Standby (ping rate 5)
  stops a client's pings; repeated fire messages just update its
  configuration; junk bytes and malformed messages are counted and skipped.

A client renders only while it is connected and firing. Clients with the same
configuration share one render per ping.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
from typing import Any

import numpy as np

from hilsim.devices.base import DeviceContext, Endpoint, RenderedFrame, TcpServerDevice
from hilsim.devices.sonar_pinger import ClientPinger, PingEntry, publish_frame
from hilsim.links.tcp import Client
from hilsim.links.udp import open_udp
from hilsim.protocols import oculus as oc
from hilsim.protocols.codec import drain

log = logging.getLogger(__name__)

MAX_RANGE_M = {oc.MODE_LF: 120.0, oc.MODE_HF: 40.0}  # datasheet (M750d)
MIN_RANGE_M = 0.1  # estimate
MIN_RESOLUTION_M = {oc.MODE_LF: 0.004, oc.MODE_HF: 0.0025}  # estimate (datasheet-like range resolution)


def gain_db_from_percent(percent: float) -> float:
    """Fire gain [%] -> receiver gain [dB]: 100 % = 0 dB, 20 log10(p / 100), floored at 1 %."""
    return 20.0 * math.log10(min(max(percent, 1.0), 100.0) / 100.0)


def effective_gain_percent(requested: float, mode: int, hf_floor: float) -> float:
    """The gain [%] an M-series applies (and echoes in the ping's fire message) for a requested one:
    in HF (master mode 2) it forces the gain into [hf_floor, 100] as ``hf_floor + (1 - hf_floor/100) x
    requested`` (40 + 0.6 x requested on the real sonar; ``protocols/oculus.md``); in LF as requested.
    ``hf_floor`` 0 turns the law off."""
    g = min(max(float(requested), 0.0), 100.0)
    if mode == oc.MODE_HF and hf_floor > 0:
        return hf_floor + (100.0 - hf_floor) / 100.0 * g
    return g


class OculusDevice(TcpServerDevice):
    protocol = "oculus"
    needs_renderer = True
    OPTIONS = {
        **TcpServerDevice.OPTIONS,
        "sensor": "sonar",                  # the sensor mount whose pose pings
        "profile_lf": "oculus_m750d",       # masterMode 1
        "profile_hf": "oculus_m750d_hf",    # masterMode 2
        "port": oc.DATA_PORT,               # TCP data channel; 0 picks a free one
        "status_port": oc.STATUS_PORT,      # UDP destination port of the status
        "status_interval_s": 1.0,
        "status_ip": None,                  # ipAddr in the status (default: the bind address)
        "device_id": 1,                     # srcDeviceId / deviceId
        "part_number": oc.PART_M750D,
        "max_rows": 1024,                   # cap on nRanges per ping
        "max_clients": 8,
        "idle_timeout_s": 0,      # drop a client with no traffic either way this long (0: never: standby is legal)
        "queue_frames": 2,                  # per-client queue [pings]
        "hf_gain_floor_percent": 40.0,      # HF gain law (40 + 0.6 x requested, as the sonar); 0: off
        "dummy_interval_s": 1.0,            # dummy messages to a connection that gets no pings
    }

    COUNTERS = ("pings", "fires", "bad_messages", "junk_bytes", "dummies")

    def __init__(self, name: str, options: dict[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.mount = self.sonar_mount()
        self.profile_refs = {oc.MODE_LF: str(self.options["profile_lf"]), oc.MODE_HF: str(self.options["profile_hf"])}
        self.profiles = {}
        for m, ref in self.profile_refs.items():
            try:
                self.profiles[m] = ctx.sonar_profile(ref)
            except (KeyError, ValueError, OSError) as exc:
                raise self.option_error("profile_lf" if m == oc.MODE_LF else "profile_hf",
                                        str(exc.args[0] if exc.args else exc)) from None
        self.max_rows = self.option_int("max_rows", 16, 8192)
        self.option_int("status_port", 0, 65535)
        self.option_number("status_interval_s", 0.0, 60.0, lo_open=True)
        self.device_id = self.option_int("device_id", 0, 65535)
        self.hf_floor = self.option_number("hf_gain_floor_percent", 0.0, 99.0)
        self.option_number("dummy_interval_s", 0.0, 9.0, lo_open=True)
        self.pinger = ClientPinger(ctx, name, self.mount, self._send_pings)
        self._udp: asyncio.DatagramTransport | None = None
        self.status_ip = "127.0.0.1"
        self.status_sent = 0

    # -- lifecycle -----------------------------------------------------------------

    async def start(self) -> list[Endpoint]:
        frame = oc.PING_V2_SIZE + 4 * 512 * (self.max_rows + 1)
        host, port = await self.serve(vendor_port=True, queue_len=int(self.options["queue_frames"]),
                                      write_buffer=frame, sndbuf=2 * frame)
        self.status_ip = str(self.options["status_ip"] or (host if host not in ("0.0.0.0", "") else "127.0.0.1"))
        self._udp = self.own(await open_udp(self.ctx.bind))
        interval = float(self.options["status_interval_s"])
        self._send_status(0.0)
        self.every("status", interval, self._send_status, priority=30, tolerance=interval)
        dummy = float(self.options["dummy_interval_s"])
        self.every("dummy", dummy, self._send_dummies, priority=30, tolerance=dummy)
        return [Endpoint(self.name, self.protocol, "tcp", f"{host}:{port}",
                         {"status": f"udp {self.ctx.broadcast}:{self.options['status_port']}",
                          "beams": 512, "modes": "LF,HF"})]

    async def on_close(self) -> None:
        await self.pinger.close()

    def status(self) -> dict[str, float]:
        return {**super().status(), "renders": float(self.pinger.renders), "busy_skips": float(self.pinger.busy_skips),
                "render_failures": float(self.pinger.failures), "rays": float(self.pinger.rays)}

    # -- status datagram ---------------------------------------------------------------

    def status_message(self) -> oc.Status:
        connected = "0.0.0.0"
        if self.server is not None and self.server.clients:
            connected = next(iter(self.server.clients.values())).peer.rsplit(":", 1)[0]
            if connected.count(".") != 3:
                connected = "0.0.0.0"
        loopback = self.status_ip.startswith("127.")
        return oc.Status(device_id=int(self.options["device_id"]), part_number=int(self.options["part_number"]),
                         status=oc.STATUS_MAIN_RUN, ip=self.status_ip,
                         ip_mask="255.0.0.0" if loopback else "255.255.255.0", connected_ip=connected,
                         temperatures=(20.0,) * 8, pressure=self._pressure_bar(),
                         src_device_id=int(self.options["device_id"]))

    def _pressure_bar(self) -> float:
        depth = float(self.ctx.vehicle.state.depth)
        return max(depth, 0.0) * 998.0 * 9.81 / 1e5

    def _send_status(self, t: float) -> None:
        if self._udp is None:
            return
        try:
            self._udp.sendto(oc.encode_status(self.status_message()),
                             (self.ctx.broadcast, int(self.options["status_port"])))
            self.status_sent += 1
        except OSError as exc:  # a network without that destination: keep serving TCP
            log.warning("%s: status datagram not sent: %s", self.name, exc)

    # -- TCP clients ---------------------------------------------------------------------

    def on_connect(self, client: Client) -> None:
        client.state["reader"] = oc.OculusReader(oc.MAX_SERVER_PAYLOAD)

    def on_disconnect(self, client: Client) -> None:
        self.pinger.set(client.id, None)

    def on_data(self, client: Client, data: bytes) -> None:
        reader: oc.OculusReader = client.state["reader"]
        for ev in drain(reader, data, limit=10_000):  # bounded: at most a few thousand events per read
            if isinstance(ev, oc.Fire):
                self._fire(client, ev)
            elif isinstance(ev, oc.Junk):
                self.counters["junk_bytes"] += ev.n_bytes
            elif isinstance(ev, (oc.BadMessage, oc.Oversize)):
                self.counters["bad_messages"] += 1
                log.debug("%s: %s sent a bad message: %s", self.name, client, ev)
            # dummy keep-alives and other messages: nothing to do

    def _fire(self, client: Client, fire: oc.Fire) -> None:
        self.counters["fires"] += 1
        if fire.master_mode not in self.profiles:
            self.counters["bad_messages"] += 1
            log.debug("%s: %s fired master mode %d (only 1 and 2 exist)", self.name, client, fire.master_mode)
            return
        if fire.ping_rate == oc.PING_RATE_STANDBY:
            self.pinger.set(client.id, None)
            client.state["fire"] = fire
            self._send_dummy(client)  # the sonar acknowledges standby with a dummy message
            return
        mode = fire.master_mode
        profile = self.profiles[mode]
        max_range = MAX_RANGE_M[mode]
        rng = fire.range if fire.range_in_metres else fire.range / 100.0 * max_range
        rng = min(max(rng, MIN_RANGE_M), max_range)
        rows = int(min(self.max_rows, max(16, math.ceil(rng / MIN_RESOLUTION_M[mode]))))
        settings = profile.default_settings().replace(range_min=0.0, range_max=rng, n_samples=rows,
                                                      gain_mode="fixed",
                                                      gain_db=profile.defaults.gain_db + gain_db_from_percent(
                                                          effective_gain_percent(fire.gain, mode, self.hf_floor)))
        entry = PingEntry(client, self.profile_refs[mode], settings, 1.0 / fire.ping_rate_hz,
                          extra={"fire": fire, "mode": mode})
        client.state["fire"] = fire
        self.pinger.set(client.id, entry)

    # -- dummy messages ----------------------------------------------------------------

    def _send_dummy(self, client: Client) -> None:
        """A dummy message (header only, id 0xFF, from the sonar's device id) to one client."""
        fire: oc.Fire | None = client.state.get("fire")
        msg = oc.encode_message(oc.MSG_DUMMY, b"", src_device_id=self.device_id,
                                dst_device_id=fire.src_device_id if fire is not None else 0)
        # a keep-alive: taking it does not make a client that never fires less idle (eviction)
        if not client.closed and self.server.send(client, msg, progress=False):
            self.counters["dummies"] += 1

    def _send_dummies(self, t: float) -> None:
        """Every connection that receives no pings (never fired, or in standby) gets a dummy message,
        as the sonar keeps an idle TCP connection alive (drivers reset a silent one)."""
        if self.server is None:
            return
        for c in list(self.server.clients.values()):
            if c.id not in self.pinger.entries:
                self._send_dummy(c)

    # -- pings -------------------------------------------------------------------------

    def _send_pings(self, entries: list[PingEntry], r: RenderedFrame, index: int) -> None:
        if self.server is None:
            return
        publish_frame(self, r, index)
        cache: dict[oc.Fire, bytes] = {}  # clients that fired the same get the same bytes
        for e in entries:
            fire: oc.Fire = e.extra["fire"]
            msg = cache.get(fire)
            if msg is None:
                msg = cache[fire] = oc.encode_ping_result(self.ping_result(fire, e.extra["mode"], r, index))
            client: Client = e.owner
            if not client.closed and self.server.send(client, msg):
                self.counters["pings"] += 1

    def ping_result(self, fire: oc.Fire, mode: int, r: RenderedFrame, index: int) -> oc.PingResult:
        """The SimplePingResult answering ``fire`` with the rendered frame ``r``."""
        frame = r.frame
        image, az = frame.image, frame.azimuths
        if fire.n_beams_requested < image.shape[1]:
            image, az = oc.halve_beams(image, az)
        gains = None
        if fire.send_gain:
            g = np.asarray(frame.gain_db_at_range, dtype=np.float64)
            if g.shape != (image.shape[0],):
                g = np.zeros(image.shape[0])
            gains = (10.0 ** (g / 20.0)).astype(np.float32)
        s = r.state
        roll, pitch, yaw = (math.degrees(a) for a in s.attitude)
        sos = fire.speed_of_sound if fire.speed_of_sound > 0 else float(self.ctx.scenario.water.sound_speed)
        start = float(s.time) if fire.version == 2 else float(int(s.time * 1000.0) & 0xFFFFFFFF)
        echoed = effective_gain_percent(fire.gain, mode, self.hf_floor)
        if echoed != fire.gain:
            fire = dataclasses.replace(fire, gain=echoed)
        return oc.PingResult(
            fire=fire, image=oc.widen_samples(image, fire.data_size), bearings=oc.bearings_from_azimuths(az),
            range_resolution=(frame.range_max - frame.range_min) / image.shape[0], gains=gains,
            ping_id=index, status=0, frequency=self.profiles[mode].frequency, temperature=20.0,
            pressure=self._pressure_bar(), heading=yaw % 360.0, pitch=pitch, roll=roll,
            speed_of_sound_used=sos, ping_start_time=start, src_device_id=int(self.options["device_id"]),
            dst_device_id=fire.src_device_id, rays=r.rays)
