"""Water Linked DVL A50: the TCP JSON API (port 16171) and the serial protocol on a pty.

The DVL pings on its own schedule: each ping casts the four beams
(:class:`hilsim.sim.dvl.Dvl`) at the vehicle's current state and the next one
follows after the interval the altitude gives (2-15 Hz: faster close to the
bottom). Each ping sends a velocity report (JSON ``"type": "velocity"`` to every
TCP client; ``wrz`` + four ``wru`` on the serial line) and advances dead
reckoning; dead-reckoning reports (``position_local`` / ``wrp``) go out at 5 Hz.
``acoustic_enabled = false`` stops the pings (and so the velocity reports)
except those queued by ``trigger_ping`` / ``wcx`` (at most 15), run in quick
succession. Commands: protocols/dvl-json.md and protocols/dvl-serial.md; bad
input is answered as documented there and counted, never raised.

Options: port (16171, a free port when taken), max_clients, idle_timeout_s,
sensor (the scenario's DVL mount, default ``dvl``), serial (also serve the
serial protocol on a pty), path (its symlink in the run folder), baudrate
(115200). Faults: dropout (silent), stuck (the last ping repeated), noise
(``factor`` x the profile's noise), lock_loss (no bottom lock).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any, Mapping

import numpy as np

from hilsim.devices.base import DeviceContext, Endpoint, SensorFaults, TcpServerDevice
from hilsim.protocols import dvl_json as dj
from hilsim.protocols import dvl_serial as ds
from hilsim.protocols.codec import Oversize, drain

log = logging.getLogger(__name__)

MAX_TRIGGERS = 15          # queued trigger_ping commands (dvl-json-protocol.md)
TRIGGER_GAP = 1.0 / 15.0   # [s] between queued pings ("quick succession": the fastest ping rate)
IDLE_POLL = 0.1            # [s] how often a DVL with acoustics off looks at its trigger queue


class DvlDevice(SensorFaults, TcpServerDevice):
    protocol = "dvl-a50"
    OPTIONS = {**TcpServerDevice.OPTIONS, "port": dj.PORT, "sensor": "dvl", "serial": True, "path": None,
               "baudrate": 115200}
    FAULTS = ("dropout", "stuck", "noise", "lock_loss")
    NOISE_FIELDS = ("velocity_noise", "velocity_noise_fraction", "distance_noise")
    COMMAND_CHANNEL = False  # its clients mostly listen to the reports: a quiet one is not idle
    COUNTERS = ("pings", "velocity_reports", "position_reports", "commands", "bad_commands")

    def __init__(self, name: str, options: Mapping[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.mount = self.sensor_mount("dvl")
        if not isinstance(self.options["serial"], bool):
            raise self.option_error("serial", "serial must be true or false")
        self.path = self.option_pty_path("path", name) if self.options["serial"] else None
        baud = self.option_int("baudrate", 1)
        if baud not in (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600):
            raise self.option_error("baudrate", f"baudrate {baud} is not one the DVL offers")
        self.config = dj.DvlConfig(speed_of_sound=float(ctx.scenario.water.sound_speed))
        self.sim: Any = None
        self.serial_link: Any = None
        self.serial_output = 3            # wcp protocol number: 3 = WL serial V2, 0 = off
        self.decoders: dict[int, dj.CommandDecoder] = {}
        self.serial_decoder = ds.SerialCommandDecoder()
        self.triggers = 0
        self.last_ping: Any = None
        self.last_report_t: float | None = None

    # -- lifecycle -----------------------------------------------------------------
    async def start(self) -> list[Endpoint]:
        from hilsim.sim.dvl import Dvl, load_dvl_profile
        from hilsim.sim.rig import profile_path

        profile = load_dvl_profile(profile_path(self.ctx.scenario, self.mount))
        self.sim = Dvl(profile, self.ctx.world, self.mount.mount, seed=self.ctx.seed, name=self.name,
                       sound_speed_true=float(self.ctx.scenario.water.sound_speed))
        self._apply_config()
        host, port = await self.serve(vendor_port=True, command_channel=True, queue_len=64)
        eps = [Endpoint(self.name, "dvl-json", "tcp", f"{host}:{port}",
                        {"connect": f"tcp://{host}:{port}", "format": dj.FORMAT})]
        if self.path is not None:
            from hilsim.links.pty import PtyLink

            link = PtyLink(self.name, self.path, baudrate=int(self.options["baudrate"]), on_data=self._on_serial)
            await link.start()
            self.serial_link = self.own(link)
            eps.append(Endpoint(self.name, "dvl-serial", "pty", link.path,
                                {"connect": f"uart://{link.path}:{link.baudrate}", "baudrate": link.baudrate}))
        self.ctx.at(self.ctx.now(), self._ping, name=f"{self.name}.ping")
        self.every("dead_reckoning", 1.0 / profile.dead_reckoning_rate, self._dead_reckoning)
        log.info("%s: DVL JSON on %s:%d%s", self.name, host, port,
                 f", serial on {self.serial_link.path}" if self.serial_link else "")
        return eps

    def status(self) -> dict[str, float]:
        out = super().status()
        if self.serial_link is not None:
            out["serial_bytes_in"] = float(self.serial_link.bytes_in)
            out["serial_bytes_out"] = float(self.serial_link.bytes_out)
        return out

    # -- pings ---------------------------------------------------------------------
    def _apply_config(self) -> None:
        c = self.config
        self.sim.speed_of_sound = c.speed_of_sound
        self.sim.mounting_rotation_offset = math.radians(c.mounting_rotation_offset)
        self.sim.range_mode = c.range_mode

    def _ping(self, t: float) -> None:
        if self._closed:
            return
        triggered = False
        if not self.config.acoustic_enabled:
            if self.triggers <= 0:
                self.ctx.at(t + IDLE_POLL, self._ping, name=f"{self.name}.ping")
                return
            self.triggers -= 1
            triggered = True
        state = self.ctx.vehicle.state
        if "stuck" in self.faults and self.last_ping is not None:
            ping = dataclasses.replace(self.last_ping, time=state.time)
        else:
            ping = self.sim.ping(state)
            if "lock_loss" in self.faults:
                ping = dataclasses.replace(ping, valid=False, beam_valid=np.zeros(4, dtype=bool),
                                           distance=np.full(4, -1.0), beam_velocity=np.zeros(4),
                                           velocity=np.zeros(3), altitude=-1.0, fom=10.0)
            self.sim.integrate(ping, state)
        self.last_ping = ping
        self.counters["pings"] += 1
        if "dropout" not in self.faults:
            self._report(ping, t)
        interval = min(ping.interval, TRIGGER_GAP) if triggered else ping.interval
        self.ctx.at(t + interval, self._ping, name=f"{self.name}.ping")

    def _report(self, ping: Any, t: float) -> None:
        dt_ms = 0.0 if self.last_report_t is None else 1000.0 * (t - self.last_report_t)
        self.last_report_t = t
        tov = int(round(self.ctx.wall_time(ping.time) * 1e6))
        tot = int(round(self.ctx.wall_time(self.ctx.now()) * 1e6))
        beams = [dj.Transducer(i, float(ping.beam_velocity[i]), float(ping.distance[i]), float(ping.rssi[i]),
                               float(ping.nsd[i]), bool(ping.beam_valid[i])) for i in range(4)]
        cov = ping.covariance.tolist()
        self.server.broadcast(dj.velocity_report(dt_ms, ping.velocity, ping.fom, cov, ping.altitude, beams,
                                                 ping.valid, 0, tov, tot, water_tracking=ping.water_tracking))
        if self._serial_on():
            out = ds.wrz(ping.velocity, ping.valid, ping.altitude, ping.fom, cov, tov, tot, dt_ms, 0)
            out += b"".join(ds.wru(b.id, b.velocity if b.beam_valid else 0.0, b.distance, b.rssi, b.nsd)
                            for b in beams)
            self.serial_link.write(out)
        self.counters["velocity_reports"] += 1
        if self.observed("reading"):
            self.publish("reading", {"t": float(ping.time), "vx_m_s": float(ping.velocity[0]),
                                     "vy_m_s": float(ping.velocity[1]), "vz_m_s": float(ping.velocity[2]),
                                     "altitude_m": float(ping.altitude), "fom_m_s": float(ping.fom),
                                     "velocity_valid": bool(ping.valid)})

    def _dead_reckoning(self, t: float) -> None:
        if self.sim is None or "dropout" in self.faults:
            return
        dr = self.sim.dead_reckoning(self.ctx.vehicle.state)
        ts = self.ctx.wall_time(t)
        roll, pitch, yaw = (math.degrees(a) for a in dr.attitude)
        x, y, z = (float(v) for v in dr.position)
        self.server.broadcast(dj.position_report(ts, x, y, z, dr.std, roll, pitch, yaw, dr.status))
        if self._serial_on():
            self.serial_link.write(ds.wrp(ts, x, y, z, dr.std, roll, pitch, yaw, dr.status))
        self.counters["position_reports"] += 1

    def _serial_on(self) -> bool:
        return self.serial_link is not None and self.serial_output != 0

    # -- JSON commands -------------------------------------------------------------
    def on_disconnect(self, client: Any) -> None:
        self.decoders.pop(client.id, None)

    def on_data(self, client: Any, data: bytes) -> None:
        dec = self.decoders.setdefault(client.id, dj.CommandDecoder())
        for ev in drain(dec, data, limit=10_000):
            if isinstance(ev, dj.Command):
                self.counters["commands"] += 1
                reply = self._command(ev.command, ev.parameters)
            elif isinstance(ev, dj.BadCommand):
                self.counters["bad_commands"] += 1
                reply = dj.response(ev.response_to, False, ev.reason)
            else:   # Oversize: the line is skipped to its end
                self.counters["bad_commands"] += 1
                reply = dj.response("", False, f"line longer than {dj.MAX_LINE} bytes")
            if "dropout" not in self.faults:
                self.server.send(client, reply)

    def _command(self, name: str, params: Any) -> bytes:
        if self.observed("command"):
            self.publish("command", {"t": self.ctx.now(), "command": name})
        if name == "get_config":
            return dj.response(name, True, "", self.config.as_result())
        if name == "set_config":
            err = self.config.apply(params)
            if not err:
                self._apply_config()
            return dj.response(name, not err, err)
        if name == "reset_dead_reckoning":
            self.sim.reset_dead_reckoning(self.ctx.vehicle.state)
            return dj.response(name, True)
        if name == "calibrate_gyro":
            self.sim.calibrate_gyro()
            return dj.response(name, True)
        if name == "trigger_ping":
            if self.triggers >= MAX_TRIGGERS:
                return dj.response(name, False, "trigger queue is full")
            if not self.config.acoustic_enabled:   # with acoustics on the DVL pings anyway: nothing to queue
                self.triggers += 1
            return dj.response(name, True)
        if name == "get_version_info":
            return dj.response(name, True, "", {"chipid": "0x0000000000000000", "hardware_revision": 4,
                                                "product_id": 21035, "product_name": "DVL A50",
                                                "variant": "standard", "version_short": "2.7.2",
                                                "version": "2.7.2 (hilsim)", "is_ready": True})
        return dj.response(name, False, f"unknown command {name!r}")

    # -- serial commands -----------------------------------------------------------
    def _on_serial(self, data: bytes) -> None:
        if data.endswith(b"\r"):
            # a lone CR ends a command (the DVL acts after its ~10 ms inter-character timeout); an LF that
            # follows in the next read only makes a blank line, which is ignored
            data += b"\n"
        for ev in drain(self.serial_decoder, data, limit=10_000):
            if isinstance(ev, ds.SerialCommand):
                self.counters["commands"] += 1
                reply = self._serial_command(ev)
            else:
                self.counters["bad_commands"] += 1
                reply = ev.answer if isinstance(ev, ds.BadSerial) else ds.MALFORMED
            if "dropout" not in self.faults and self.serial_link is not None:
                self.serial_link.write(reply)

    def _serial_command(self, cmd: ds.SerialCommand) -> bytes:
        letter, opts = cmd.letter, cmd.options
        if letter == "v":
            return ds.wrv()
        if letter == "w":
            return ds.wrw("dvl-a50", "2.7.2", "0x0000000000000000")
        if letter == "c":
            return ds.wrc(self.config)
        if letter == "s":
            params = ds.parse_wcs(opts)
            if isinstance(params, str):
                return ds.MALFORMED
            if not params:
                return ds.ACK
            if self.config.apply(params):
                return ds.NACK
            self._apply_config()
            return ds.ACK
        if letter == "r":
            self.sim.reset_dead_reckoning(self.ctx.vehicle.state)
            return ds.ACK
        if letter == "g":
            self.sim.calibrate_gyro()
            return ds.ACK
        if letter == "x":
            if self.triggers >= MAX_TRIGGERS:
                return ds.NACK
            if not self.config.acoustic_enabled:
                self.triggers += 1
            return ds.ACK
        if letter == "p":
            if len(opts) != 1 or opts[0] not in ("0", "1", "2", "3", "6"):
                return ds.MALFORMED
            if opts[0] in ("2", "6"):     # PD6 / PD4 are not emulated
                return ds.NACK
            self.serial_output = int(opts[0])
            return ds.ACK
        return ds.MALFORMED
