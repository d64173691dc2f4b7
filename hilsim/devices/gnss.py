"""A GNSS receiver writing NMEA 0183 on a pty (GGA, RMC, VTG, ZDA; HDT on a dual-antenna unit).

Each output epoch (1-10 Hz) samples :class:`hilsim.sim.gnss.Gnss` at the vehicle's
state and writes the sentences in that order (protocols/nmea0183.md). Under water
the receiver has no fix (GGA quality 0 with empty fields, RMC status V); the fix
comes back ``time_to_fix`` after the antenna surfaces. UTC is the bridge's wall
time for the simulation time. Input from the host (configuration sentences) is
read and ignored, as a receiver that does not understand it does.

Options: path (pty symlink, default the device name), baudrate (4800, 9600 or
115200), sensor (the scenario's GNSS mount, default ``gnss``), rate [Hz] (1-10;
default the profile's). A rate whose sentences do not fit the baud rate is
refused. Faults: dropout (silent), stuck (the last epoch repeated), noise
(``factor`` x the position noise), outage (no fix, as under a bridge or in a
jammed area; the fix returns ``time_to_fix`` after it ends).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import logging
import math
from typing import Any, Mapping

from hilsim.devices.base import DeviceContext, Endpoint, PtyDevice, SensorFaults
from hilsim.protocols import nmea

log = logging.getLogger(__name__)

SENTENCE_BYTES = 80        # [bytes] a full sentence, about (the worst case is 82)


class GnssDevice(SensorFaults, PtyDevice):
    protocol = "nmea-gnss"
    OPTIONS = {**PtyDevice.OPTIONS, "baudrate": 9600, "sensor": "gnss", "rate": None}
    BAUDRATES = (4800, 9600, 115200)
    FAULTS = ("dropout", "stuck", "noise", "outage")
    NOISE_FIELDS = ("horizontal_noise", "vertical_noise", "velocity_noise")
    COUNTERS = ("epochs", "fixes")

    def __init__(self, name: str, options: Mapping[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        from hilsim.sim.gnss import Gnss, load_gnss_profile
        from hilsim.sim.rig import profile_path

        self.mount = self.sensor_mount("gnss")
        profile = load_gnss_profile(profile_path(ctx.scenario, self.mount))
        if self.options["rate"] is not None:
            profile = dataclasses.replace(profile, rate=self.option_number("rate", 1.0, 10.0))
        self.sim = Gnss(profile, self.mount.mount, ctx.scenario.origin, seed=ctx.seed, name=name)
        n = 5 if profile.dual_antenna else 4
        need = profile.rate * n * SENTENCE_BYTES * 10
        if need > int(self.options["baudrate"]):
            raise self.option_error("baudrate", f"{n} sentences at {profile.rate:g} Hz need about {need:.0f} "
                                    f"bit/s; {self.options['baudrate']} baud is too slow")
        self.last_epoch = b""

    async def start(self) -> list[Endpoint]:
        link = await self.open_pty(self._on_data)
        p = self.sim.profile
        self.every("epoch", 1.0 / p.rate, self._epoch, priority=10)
        log.info("%s: NMEA 0183 GNSS on %s (%d baud, %g Hz)", self.name, link.path, link.baudrate, p.rate)
        return [Endpoint(self.name, self.protocol, "pty", link.path,
                         {"connect": f"uart://{link.path}:{link.baudrate}", "baudrate": link.baudrate,
                          "rate_hz": p.rate, "talker": p.talker})]

    def _on_data(self, data: bytes) -> None:
        self.counters["bytes_ignored"] += len(data)

    def epoch_sentences(self, t: float) -> bytes:
        """Sample the receiver at the vehicle's state and encode one epoch's sentences."""
        p = self.sim.profile
        fix = self.sim.sample(self.ctx.vehicle.state)
        wall = dt.datetime.fromtimestamp(self.ctx.wall_time(t), dt.timezone.utc)
        utc = wall.hour * 3600 + wall.minute * 60 + wall.second + wall.microsecond * 1e-6
        date = (wall.day, wall.month, wall.year)
        talker = p.talker
        if fix.fix:
            out = nmea.gga(talker, utc, fix.lat_deg, fix.lon_deg, fix.quality, fix.satellites, fix.hdop, fix.alt_m,
                           p.geoid_separation)
            course = math.degrees(fix.course)
            out += nmea.rmc(talker, utc, date, True, fix.lat_deg, fix.lon_deg, fix.speed, course,
                            "D" if fix.quality == 2 else "A")
            out += nmea.vtg(talker, True, fix.speed, course)
            self.counters["fixes"] += 1
        else:
            out = nmea.gga(talker, utc, None, None, 0, fix.satellites, None, None)
            out += nmea.rmc(talker, utc, date, False, None, None, 0.0, 0.0)
            out += nmea.vtg(talker, False, 0.0, 0.0)
        out += nmea.zda(talker, utc, date)
        if p.dual_antenna:
            out += nmea.hdt(talker, math.degrees(fix.heading) if fix.fix else None)
        if self.observed("reading"):
            self.publish("reading", {"t": float(t), "fix": bool(fix.fix), "quality": int(fix.quality),
                                     "lat_deg": fix.lat_deg, "lon_deg": fix.lon_deg, "alt_m": fix.alt_m,
                                     "satellites": int(fix.satellites), "speed_m_s": fix.speed,
                                     "submerged": bool(fix.submerged)})
        return out

    def _epoch(self, t: float) -> None:
        if "stuck" in self.faults and self.last_epoch:
            out = self.last_epoch
        else:
            out = self.epoch_sentences(t)
            self.last_epoch = out
        self.counters["epochs"] += 1
        if "dropout" not in self.faults and self.link is not None:
            self.link.write(out)

    def inject_fault(self, fault: str, params: Mapping[str, Any]) -> None:
        if fault == "outage":
            self.sim.outage = True
        super().inject_fault(fault, params)

    def clear_fault(self, fault: str) -> None:
        super().clear_fault(fault)
        if fault == "outage":
            self.sim.outage = False
