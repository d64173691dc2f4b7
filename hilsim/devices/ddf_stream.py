"""The DIDSON-like sonar: its frames as a DDF version 4 file over TCP.

See ``protocols/ddf-stream.md``. On connect a client gets the file header,
then every frame the sonar pings while it is connected; command lines it
sends (``RATE``, ``WINDOW``, ``GAIN``, ``PING``) change the sonar for every
client and are answered in the reply area of the next frame header sent to
that client. The sonar renders only while it has a client or a recording.
A slow client loses whole frames (its queue holds ``queue_frames``), never
half frames, and never slows the others.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, BinaryIO

from hilsim.devices.base import DeviceContext, Endpoint, Periodic, RenderedFrame, RenderFailed, TcpServerDevice
from hilsim.devices.sonar_pinger import publish_frame
from hilsim.links.tcp import Client
from hilsim.protocols import ddf
from hilsim.protocols.codec import drain
from hilsim.protocols.ddf_commands import (BadCommand, CommandDecoder, Ping, SetGain, SetRate, SetWindow,
                                           command_text, encode_reply, pack_replies)

log = logging.getLogger(__name__)

MAX_PENDING_REPLIES = 16


class DdfStreamDevice(TcpServerDevice):
    protocol = "ddf-stream"
    needs_renderer = True
    records = (".ddf",)
    OPTIONS = {
        **TcpServerDevice.OPTIONS,
        "sensor": "sonar",          # the sensor mount whose pose pings
        "profile": None,            # sonar profile (default: the mount's)
        "frame_rate_hz": None,      # default: the profile's
        "gain_db": 20,              # receiver gain [dB] 0..40 (fixed-gain mode)
        "idle_timeout_s": 0,        # drop a client with no traffic either way this long (0: never; a
                                    # stream client only listens, and the frames stop in a sonar dropout)
        "queue_frames": 2,          # per-client queue [frames]
        "serial_number": 1,
    }
    COUNTERS = ("frames", "render_failures", "late_skips", "bad_commands")
    COMMAND_CHANNEL = False  # its clients only listen: only one that stops reading is evictable

    def __init__(self, name: str, options: dict[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.mount = self.sonar_mount()
        self.profile_ref = str(self.options["profile"] or ctx.scenario.sensor(self.mount).profile)
        try:
            self.profile = ctx.sonar_profile(self.profile_ref)
        except (KeyError, ValueError, OSError) as exc:
            raise self.option_error("profile" if self.options["profile"] else "sensor",
                                    str(exc.args[0] if exc.args else exc)) from None
        self.high_freq = self.profile.frequency >= 1.5e6
        if self.options["frame_rate_hz"] is not None:
            self.rate = self.option_number("frame_rate_hz", 0.1, 30.0)
        else:
            self.rate = float(self.profile.frame_rate)
        self.start_code, self.length_code = ddf.codes_for_window(
            self.profile.range_min, self.profile.range_max - self.profile.range_min, self.high_freq)
        self.gain_db = self.option_int("gain_db", 0, 40)
        self.option_int("queue_frames", 1, 1000)
        self.settings = self._settings()
        self.record_path: Path | None = None
        self._record: BinaryIO | None = None
        self.frame_number = 0
        self._event: Periodic | None = None
        self._rendering = False

    def record_to(self, path: Path) -> None:
        self.record_path = Path(path)

    @property
    def frames_recorded(self) -> int:
        return self.counters["recorded"]

    # -- settings ----------------------------------------------------------------

    def _settings(self) -> Any:
        start, length = ddf.window_from_codes(self.start_code, self.length_code, self.high_freq)
        return self.profile.default_settings().replace(range_min=start, range_max=start + length,
                                                       gain_mode="fixed", gain_db=float(self.gain_db))

    def file_header(self) -> ddf.FileHeader:
        start, length = ddf.window_from_codes(self.start_code, self.length_code, self.high_freq)
        c = self.ctx.scenario.water.sound_speed
        now = datetime.fromtimestamp(self.ctx.wall_time(self.ctx.now()), timezone.utc)
        return ddf.FileHeader(
            numframes=0, framerate=max(1, round(self.rate)), resolution=1 if self.high_freq else 0,
            numbeams=self.profile.n_beams, samplerate=float(self.profile.n_samples * c / (2 * length)),
            samplesperchannel=self.settings.n_samples, receivergain=self.gain_db,
            windowstart=self.start_code, windowlength=self.length_code,
            serialnumber=int(self.options["serial_number"]), date=now.strftime("%Y-%m-%d_%H%M%S"),
            idstring=f"hilsim {self.ctx.scenario.name} {self.name}"[:255], sspd=round(c))

    # -- lifecycle ---------------------------------------------------------------

    async def start(self) -> list[Endpoint]:
        frame = ddf.FRAME_HEADER_SIZE + self.profile.n_beams * self.settings.n_samples
        host, port = await self.serve(queue_len=int(self.options["queue_frames"]), write_buffer=frame,
                                      sndbuf=2 * frame)
        try:  # warm the worker up (profile load, first allocations) so the first pings keep pace
            await self.ctx.render(self.mount, self.profile_ref, self.settings, frame_index=0)
        except RenderFailed as exc:
            log.warning("%s: warm-up render failed: %s", self.name, exc)
        if self.record_path is not None:
            self._record = open(self.record_path, "wb")
            self._record.write(ddf.encode_file_header(self.file_header()))
        self._schedule()
        return [Endpoint(self.name, self.protocol, "tcp", f"{host}:{port}",
                         {"beams": self.profile.n_beams, "samples": self.settings.n_samples,
                          "frame_rate_hz": self.rate})]

    def _schedule(self) -> None:
        if self._event is not None:
            self._event.cancel()
        self._event = self.every("ping", 1.0 / self.rate, self._ping, priority=20, tolerance=0.5 / self.rate)

    async def on_close(self) -> None:
        if self._record is not None:
            f, self._record = self._record, None
            f.flush()
            f.seek(ddf.NUMFRAMES_OFFSET)  # a seekable recording knows its length
            f.write(self.frames_recorded.to_bytes(4, "little"))
            f.close()
            log.info("%s: recorded %d frames to %s", self.name, self.frames_recorded, self.record_path)

    # -- clients -----------------------------------------------------------------

    def on_connect(self, client: Client) -> None:
        client.state["decoder"] = CommandDecoder()
        client.state["replies"] = deque()
        self.server.send(client, ddf.encode_file_header(self.file_header()))

    def on_data(self, client: Client, data: bytes) -> None:
        dec: CommandDecoder = client.state["decoder"]
        replies: deque[bytes] = client.state["replies"]
        for ev in drain(dec, data):
            ok, text = self._apply(ev)
            if len(replies) < MAX_PENDING_REPLIES:
                replies.append(encode_reply(ok, text))

    def _apply(self, ev: Any) -> tuple[bool, str]:
        if isinstance(ev, BadCommand):
            self.counters["bad_commands"] += 1
            return False, ev.reason
        if isinstance(ev, SetRate):
            # re-adding the ping event moves its next tick to the next grid point: do it only
            # when the rate really changes (a client repeating RATE must not stop the frames)
            if float(ev.rate_hz) != self.rate:
                self.rate = float(ev.rate_hz)
                self._schedule()
        elif isinstance(ev, SetWindow):
            self.start_code, self.length_code = ev.start_code, ev.length_code
            self.settings = self._settings()
        elif isinstance(ev, SetGain):
            self.gain_db = int(ev.gain_db)
            self.settings = self._settings()
        elif not isinstance(ev, Ping):
            return False, "unsupported"
        return True, command_text(ev)

    # -- pinging -----------------------------------------------------------------

    # fault injection: "dropout" -- the sonar head stops pinging (clients stay connected,
    # no frames arrive; the frame numbering resumes without a gap: no ping was fired)
    FAULTS = ("dropout",)
    dropout = False

    def inject_fault(self, fault: str, params: Any) -> None:
        if fault != "dropout":
            super().inject_fault(fault, params)
        self.dropout = True

    def clear_fault(self, fault: str) -> None:
        if fault == "dropout":
            self.dropout = False

    def _wanted(self) -> bool:
        if self.dropout:
            return False
        return self._record is not None or (self.server is not None and self.server.stats.connected > 0)

    def _ping(self, t: float) -> Any:
        if not self._wanted():
            return None
        if self._rendering:
            # the previous frame is still rendering: the sonar cannot ping this fast, so this
            # ping never happens (counted; the frame rate drops, the numbering has no gap).
            # A ping that was fired and then lost (worker crash) does leave a gap.
            self.counters["late_skips"] += 1
            return None
        self._rendering = True
        return self.ctx.defer(self._render_and_send(self.frame_number))

    async def _render_and_send(self, number: int) -> None:
        self.frame_number = number + 1
        try:
            r = await self.ctx.render(self.mount, self.profile_ref, self.settings, frame_index=number,
                                      budget_s=1.0 / self.rate)
        except RenderFailed as exc:
            self.counters["render_failures"] += 1
            log.warning("%s: frame %d lost: %s", self.name, number, exc)
            return
        finally:
            self._rendering = False
        self.counters["frames"] += 1
        self.counters["rays"] = r.rays  # elevation rays per beam of the last frame (status line)
        publish_frame(self, r, number)
        header = self._frame_header(number, r)
        plain = ddf.encode_frame(header, r.frame.image)
        if self._record is not None:
            self._record.write(plain)
            self.counters["recorded"] += 1
        if self.server is None:
            return
        for c in list(self.server.clients.values()):
            replies: deque[bytes] = c.state.get("replies", deque())
            if replies:
                packed, n = pack_replies(list(replies))
                for _ in range(n):
                    replies.popleft()
                hdr = ddf.encode_frame_header(_with_replies(header, packed))
                self.server.send(c, hdr + plain[ddf.FRAME_HEADER_SIZE:])
            else:
                self.server.send(c, plain)

    def _frame_header(self, number: int, r: RenderedFrame) -> ddf.FrameHeader:
        s = r.state
        roll, pitch, yaw = (math.degrees(a) for a in s.attitude)
        p, q, rr = (math.degrees(a) for a in s.angular_velocity)
        mroll, mpitch, myaw = (math.degrees(a) for a in self.ctx.scenario.sensor(self.mount).mount.rpy())
        alt = r.altitude if math.isfinite(r.altitude) else 0.0
        return ddf.FrameHeader(
            framenumber=number, time=self.ctx.wall_time(s.time),
            transmit=ddf.transmit_flags(self.high_freq), windowstart=self.start_code,
            windowlength=self.length_code, receivergain=self.gain_db,
            velocity=float(math.sqrt(sum(float(v) ** 2 for v in s.velocity))), depth=s.depth, altitude=alt,
            pitch=pitch, pitchrate=q, roll=roll, rollrate=p, heading=yaw % 360.0, headingrate=rr,
            sonarpan=myaw, sonartilt=mpitch, sonarroll=mroll, rays=r.rays)


def _with_replies(h: ddf.FrameHeader, replies: bytes) -> ddf.FrameHeader:
    from dataclasses import replace

    return replace(h, replies=replies)
