"""Sound Metrics ARIS sonar: availability beacon, protobuf command channel, UDP frame stream.

See ``protocols/aris.md``. The device

* sends the ``Availability`` beacon every ``beacon_interval_s`` to
  ``ctx.broadcast:beacon_port`` (BUSY while a client is connected);
* serves the command channel on TCP ``port`` (56888 on a real sonar):
  length-prefixed ``Command`` messages. Acoustic settings are checked as the
  sonar does (:func:`hilsim.protocols.aris.check_settings`): valid ones apply
  (their cookie in AppliedSettings of the following frame headers), out of
  range ones are constrained (cookie also in ConstrainedSettings) or rejected
  (cookie in InvalidSettings, the previous settings stay). No frame flows
  before valid settings and a frame stream receiver. A client that sends no
  command for ``keepalive_timeout_s`` is dropped;
* streams frames as FramePart datagrams (<= 1500 bytes) to the receiver,
  which must be in 127.0.0.0/8 unless ``allow_lan`` is true;
* records to an ``.aris`` file when ``record`` names one (the recording pings
  with the first settings a client applies, or the profile's defaults).

Settings -> render: the window is ``[delay, delay + samples x period] x c / 2``
(c: the scenario's sound speed), ``samplesPerBeam`` range samples, the
profile by beam count (96 -> ``profile_hf``, 48 -> ``profile_lf``), the frame
rate as applied, receiver gain added to the profile's gain.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import math
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, BinaryIO

from hilsim.devices.base import DeviceContext, Endpoint, RenderedFrame, TcpServerDevice
from hilsim.devices.sonar_pinger import ClientPinger, PingEntry, publish_frame
from hilsim.links.tcp import Client
from hilsim.links.udp import open_udp
from hilsim.protocols import aris as ar
from hilsim.protocols.aris_file import ArisWriter
from hilsim.protocols.codec import drain
from hilsim.sim.sonar_profile import SonarSettings

log = logging.getLogger(__name__)

RECORDER = -1  # the pinger key of the recording


class ArisDevice(TcpServerDevice):
    protocol = "aris"
    needs_renderer = True
    records = (".aris",)
    OPTIONS = {
        **TcpServerDevice.OPTIONS,
        "sensor": "sonar",
        "profile_hf": "aris1800_hf",    # 96-beam ping modes
        "profile_lf": "aris1800_lf",    # 48-beam ping modes
        "port": ar.COMMAND_PORT,        # TCP command channel; 0 picks a free one
        "beacon_port": ar.BEACON_PORT,  # UDP destination port of the beacon
        "beacon_interval_s": 1.0,
        "serial_number": 1800,
        "system_type": ar.SYSTEM_1800,
        "keepalive_timeout_s": 3.0,     # drop a client silent this long
        "allow_lan": False,             # send frames outside 127.0.0.0/8
        "record": None,                 # path of an .aris recording
        "max_clients": 4,
        "max_datagram": ar.MAX_DATAGRAM,
    }
    COUNTERS = ("frames", "datagrams", "bad_commands", "invalid_settings", "refused_receivers", "dropped_silent",
                "recorded")

    def __init__(self, name: str, options: dict[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.mount = self.sonar_mount()
        self.profile_refs = {96: str(self.options["profile_hf"]), 48: str(self.options["profile_lf"])}
        self.profiles = {}
        for n, ref in self.profile_refs.items():
            key = "profile_hf" if n == 96 else "profile_lf"
            try:
                self.profiles[n] = p = ctx.sonar_profile(ref)
            except (KeyError, ValueError, OSError) as exc:
                raise self.option_error(key, str(exc.args[0] if exc.args else exc)) from None
            if p.n_beams != n:
                raise self.option_error(key, f"profile {p.name!r} has {p.n_beams} beams, expected {n}")
        self.system_type = self.option_int("system_type", 0, 255)
        self.option_int("beacon_port", 1, 65535)
        self.option_number("beacon_interval_s", 0.0, 60.0, lo_open=True)
        self.option_number("keepalive_timeout_s", 0.0, lo_open=True)
        self.sound_speed = float(ctx.scenario.water.sound_speed)
        self.max_datagram = self.option_int("max_datagram", 256, 65507)
        self.pinger = ClientPinger(ctx, name, self.mount, self._send_frames)
        self._udp: asyncio.DatagramTransport | None = None
        self._writer: ArisWriter | None = None
        self._record_file: BinaryIO | None = None  # the writer is sans-I/O: the file is ours
        self.record_path = self.option_output_path("record") if self.options["record"] else None

    def record_to(self, path: Path) -> None:
        self.record_path = Path(path)

    # -- lifecycle -----------------------------------------------------------------

    async def start(self) -> list[Endpoint]:
        host, port = await self.serve(vendor_port=True, queue_len=4, write_buffer=64 * 1024)
        self._udp = self.own(await open_udp(self.ctx.bind))
        interval = float(self.options["beacon_interval_s"])
        self._beacon(0.0)
        self.every("beacon", interval, self._beacon, priority=30, tolerance=interval)
        self.every("keepalive", 0.25, self._check_keepalive, priority=30, tolerance=0.25)
        if self.record_path is not None:
            self._record_file = open(self.record_path, "wb")
            self._writer = ArisWriter(self._record_file, {"SN": int(self.options["serial_number"]),
                                                          "strHeaderID": f"hilsim {self.name}".encode()[:255]})
            self._set_recording(None)
        return [Endpoint(self.name, self.protocol, "tcp", f"{host}:{port}",
                         {"beacon": f"udp {self.ctx.broadcast}:{self.options['beacon_port']}",
                          "beams": "96 (HF) / 48 (LF)"})]

    async def on_close(self) -> None:
        await self.pinger.close()
        if self._writer is not None:
            self._writer.close()
            log.info("%s: recorded %d frames to %s", self.name, self.counters["recorded"], self.record_path)
            self._writer = None
        if self._record_file is not None:
            self._record_file.close()
            self._record_file = None

    def status(self) -> dict[str, float]:
        return {**super().status(), "renders": float(self.pinger.renders), "busy_skips": float(self.pinger.busy_skips),
                "render_failures": float(self.pinger.failures), "rays": float(self.pinger.rays)}

    # -- beacon and keep-alive ------------------------------------------------------------

    def _beacon(self, t: float) -> None:
        if self._udp is None:
            return
        busy = 1 if self.server is not None and self.server.clients else 0
        msg = ar.encode_availability(ar.Availability(int(self.options["serial_number"]), self.system_type,
                                                     connection_state=busy))
        try:
            self._udp.sendto(msg, (self.ctx.broadcast, int(self.options["beacon_port"])))
        except OSError as exc:
            log.warning("%s: beacon not sent: %s", self.name, exc)

    def _check_keepalive(self, t: float) -> None:
        if self.server is None:
            return
        limit = float(self.options["keepalive_timeout_s"])
        now = time.monotonic()
        for c in list(self.server.clients.values()):
            if now - c.state.get("last_seen", now) > limit:
                log.info("%s: %s sent nothing for %.1f s: dropped", self.name, c, limit)
                self.counters["dropped_silent"] += 1
                self.pinger.set(c.id, None)
                self.server.disconnect(c)

    # -- commands ----------------------------------------------------------------------

    def on_connect(self, client: Client) -> None:
        client.state.update(reader=ar.CommandReader(), last_seen=time.monotonic(), receiver=None, settings=None,
                            applied=0, constrained=0, invalid=0, salinity=0, focus=0.0, frame_index=0)

    def on_disconnect(self, client: Client) -> None:
        self.pinger.set(client.id, None)

    def on_data(self, client: Client, data: bytes) -> None:
        reader: ar.CommandReader = client.state["reader"]
        for ev in drain(reader, data, limit=10_000):
            if isinstance(ev, (ar.BadCommand, ar.Oversize)):
                self.counters["bad_commands"] += 1
                continue
            if isinstance(ev, ar.Junk):
                continue
            client.state["last_seen"] = time.monotonic()
            self._apply(client, ev)

    def _apply(self, client: Client, ev: ar.CommandEvent) -> None:
        st = client.state
        if isinstance(ev, ar.SetFrameStreamReceiver):
            ip = ev.ip if ev.ip else client.peer.rsplit(":", 1)[0]
            st["receiver"] = None if ip == "0.0.0.0" else (ip, int(ev.port))
            if st["receiver"] is not None and not self._receiver_allowed(ip):
                self.counters["refused_receivers"] += 1
                log.warning("%s: frame stream receiver %s refused: outside 127.0.0.0/8 (set allow_lan)",
                            self.name, ip)
                st["receiver"] = None
        elif isinstance(ev, ar.SetAcoustics):
            check = ar.check_settings(ev.settings, self.system_type)
            if check.outcome == "invalid":
                self.counters["invalid_settings"] += 1
                st["invalid"] = ev.settings.cookie
                log.info("%s: invalid settings (cookie %d): %s", self.name, ev.settings.cookie,
                         "; ".join(check.reasons))
            else:
                st["settings"] = check.settings
                st["applied"] = ev.settings.cookie
                if check.outcome == "constrained":
                    st["constrained"] = ev.settings.cookie
                if self._writer is not None and self.pinger.entries.get(RECORDER) is not None \
                        and not self.pinger.entries[RECORDER].extra.get("from_client"):
                    self._set_recording(check.settings)
        elif isinstance(ev, ar.SetSalinity):
            st["salinity"] = ev.salinity
        elif isinstance(ev, ar.SetFocus):
            st["focus"] = ev.focus_range or 0.0
        self._update(client)

    def _receiver_allowed(self, ip: str) -> bool:
        if self.options["allow_lan"]:
            return True
        try:
            return ipaddress.ip_address(ip) in ipaddress.ip_network("127.0.0.0/8")
        except ValueError:
            return False

    def sonar_settings(self, s: ar.AcousticSettings) -> tuple[str, SonarSettings]:
        """(profile reference, render settings) for applied acoustic settings."""
        beams = ar.beams_for_ping_mode(s.ping_mode)
        profile = self.profiles.get(beams, self.profiles[96])
        start, end = s.window(self.sound_speed)
        settings = profile.default_settings().replace(range_min=start, range_max=end,
                                                      n_samples=int(s.samples_per_beam), gain_mode="fixed",
                                                      gain_db=profile.defaults.gain_db + float(s.receiver_gain))
        return self.profile_refs.get(beams, self.profile_refs[96]), settings

    def _update(self, client: Client) -> None:
        st = client.state
        s: ar.AcousticSettings | None = st["settings"]
        if s is None or st["receiver"] is None:
            self.pinger.set(client.id, None)
            return
        ref, settings = self.sonar_settings(s)
        old = self.pinger.entries.get(client.id)
        if old is not None and old.extra["acoustic"] == s and old.settings == settings:
            old.extra["client_state"] = st
            return
        self.pinger.set(client.id, PingEntry(client, ref, settings, 1.0 / s.frame_rate,
                                             extra={"acoustic": s, "client_state": st}))

    def _set_recording(self, s: ar.AcousticSettings | None) -> None:
        from_client = s is not None
        if s is None:
            p = self.profiles[96]
            s = ar.AcousticSettings.for_window(p.range_min, p.range_max, p.n_samples, self.sound_speed,
                                               frame_rate=p.frame_rate, cookie=0)
            s = ar.check_settings(s, self.system_type).settings
        ref, settings = self.sonar_settings(s)
        state = {"applied": s.cookie, "constrained": 0, "invalid": 0, "salinity": 0, "focus": 0.0, "frame_index": 0}
        self.pinger.set(RECORDER, PingEntry(None, ref, settings, 1.0 / s.frame_rate,
                                            extra={"acoustic": s, "client_state": state, "from_client": from_client}))

    # -- frames ------------------------------------------------------------------------

    def frame_header(self, s: ar.AcousticSettings, st: dict[str, Any], r: RenderedFrame,
                     frame_index: int) -> dict[str, ar.HeaderValue]:
        """The frame-header fields of one frame (every field we know written; the rest 0)."""
        state = r.state
        wall = self.ctx.wall_time(float(state.time))
        d = datetime.fromtimestamp(wall, timezone.utc)
        roll, pitch, yaw = (math.degrees(a) for a in state.attitude)
        start, end = s.window(self.sound_speed)
        alt = r.altitude if math.isfinite(r.altitude) else 0.0
        return {
            "FrameIndex": frame_index, "FrameTime": int(wall * 1e6), "Version": ar.FILE_VERSION,
            "sonarTimeStamp": int(wall * 1e6), "TS_Day": d.day, "TS_Hour": d.hour, "TS_Minute": d.minute,
            "TS_Second": d.second, "TS_Hsecond": d.microsecond // 10000,
            "WindowStart": start, "WindowLength": end - start, "ReceiverGain": int(round(s.receiver_gain)),
            "DegC1": 30, "DegC2": 30, "Focus": int(min(max(st.get("focus", 0.0), 0.0), 40.0) * 25),
            "Velocity": float(math.sqrt(sum(float(v) ** 2 for v in state.velocity))),
            "Depth": float(state.depth), "Altitude": alt, "Pitch": pitch, "Roll": roll, "Heading": yaw % 360.0,
            "CompassHeading": yaw % 360.0, "CompassPitch": pitch, "CompassRoll": roll,
            "WaterTemp": 20.0, "SampleRate": 1e6 / s.sample_period,
            "PingMode": s.ping_mode, "FrequencyHiLow": s.frequency, "PulseWidth": s.pulse_width,
            "CyclePeriod": s.cycle_period, "SamplePeriod": s.sample_period,
            "TransmitEnable": int(s.enable_transmit), "FrameRate": s.frame_rate, "SoundSpeed": self.sound_speed,
            "SamplesPerBeam": s.samples_per_beam, "Enable150V": int(s.enable_150_volts),
            "SampleStartDelay": s.sample_start_delay, "LargeLens": 0, "TheSystemType": self.system_type,
            "SonarSerialNumber": int(self.options["serial_number"]), "ReorderedSamples": 1,
            "Salinity": int(st.get("salinity", 0)), "Pressure": max(float(state.depth), 0.0) * 1.4223,
            "AppliedSettings": int(st.get("applied", 0)), "ConstrainedSettings": int(st.get("constrained", 0)),
            "InvalidSettings": int(st.get("invalid", 0)), "ArisAppVersionMajor": 2, "ArisAppVersionMinor": 8,
            "FocusCurrentPosition": int(min(max(st.get("focus", 0.0), 0.0), 40.0) * 25),
        }

    def _send_frames(self, entries: list[PingEntry], r: RenderedFrame, index: int) -> None:
        samples = ar.samples_to_wire(r.frame.image)
        publish_frame(self, r, index)
        for e in entries:
            s: ar.AcousticSettings = e.extra["acoustic"]
            st: dict[str, Any] = e.extra["client_state"]
            if e.owner is None:
                if self._writer is not None:
                    fields = self.frame_header(s, st, r, self.counters["recorded"])
                    self._writer.write_frame(fields, r.frame.image)
                    self.counters["recorded"] += 1
                continue
            client: Client = e.owner
            if client.closed or st.get("receiver") is None or self._udp is None:
                continue
            st["frame_index"] = st.get("frame_index", 0) + 1  # FramePart.frame_index is 1-based
            header = ar.encode_frame_header(self.frame_header(s, st, r, st["frame_index"] - 1))
            if _buffered(self._udp) > 4 * len(samples):  # the kernel is not keeping up: drop the frame
                continue
            for dgram in ar.split_frame(st["frame_index"], header, samples, self.max_datagram):
                try:
                    self._udp.sendto(dgram, st["receiver"])
                except OSError as exc:
                    log.debug("%s: frame part not sent: %s", self.name, exc)
                    break
                self.counters["datagrams"] += 1
            self.counters["frames"] += 1


def _buffered(transport: asyncio.DatagramTransport) -> int:
    """Bytes asyncio holds for a UDP transport the kernel would not take yet."""
    size = getattr(transport, "get_write_buffer_size", None)
    return int(size()) if size is not None else 0
