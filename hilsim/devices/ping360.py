"""Blue Robotics Ping360 scanning sonar: ping-protocol on a pty (115200 8N1) and on UDP (12345).

The head (:class:`hilsim.sim.ping360.ScanningSonar`: one beam cast with Embree from the mount
at the head angle) works in simulated time as the device does (protocols/ping360.md):

* ``transducer`` (2601): the head turns to ``angle``, transmits when ``transmit`` is 1 and
  listens ``number_of_samples x sample_period x 25 ns``; then ``device_data`` (2300) with the
  echo (empty data when ``transmit`` is 0), rendered from the vehicle's state at that time (the
  vehicle moves during a sweep). A new command while one is under way replaces it.
* ``auto_transmit`` (2602): the head sweeps from ``start_angle`` to ``stop_angle`` in steps of
  ``num_steps`` gradians (back and forth for a sector, round and round for a full turn), one
  ``auto_device_data`` (2301) per step with ``delay`` ms between pings, until ``motor_off``
  (2903, answered with ``ack``), ``reset`` or a ``transducer`` command.
* requests (``general_request``, or an empty packet of a get id): ``device_information``
  (device_type 2), ``protocol_version``, ``device_data`` (the current state, no data);
  ``ping360_set_device_id`` -> ack (the new id is used from then on).
* an unknown id, a payload that does not fit, a value out of the protocol's range -> ``nack``
  with the id and the reason; a bad checksum -> ``nack``; bytes outside packets are skipped.

Replies go back on the link the request came from: the pty, or the UDP address that sent it.
Options: path, baudrate, sensor (a scenario sonar mount with a one-beam profile, default
``ping360``), profile (default the mount's), device_id, udp_port (12345; 0 a free one; -1
none; a taken port falls back to a free one), transport ``["pty", "udp"]``.
Fault: dropout (the head answers nothing).
"""

from __future__ import annotations

import asyncio
import errno
import logging
from dataclasses import dataclass, replace
from typing import Any, Callable, Mapping

from hilsim.devices.base import DeviceContext, Endpoint, PtyDevice
from hilsim.protocols import ping360 as p360
from hilsim.protocols import ping_protocol as pp
from hilsim.protocols.codec import drain
from hilsim.sim.ping360 import GRADIANS, PingSettings, ScanningSonar, ping_duration

log = logging.getLogger(__name__)

FIRMWARE = (3, 3, 0)        # reported in device_information
PROTOCOL = (1, 0, 0)        # protocol_version
TRANSPORTS = ("pty", "udp")
Reply = Callable[[bytes], None]


@dataclass
class AutoScan:
    start: int
    stop: int
    step: int
    delay_s: float
    direction: int = 1


class _Udp(asyncio.DatagramProtocol):
    def __init__(self, on_datagram: Callable[[bytes, Any], None]) -> None:
        self.on_datagram = on_datagram

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.on_datagram(data, addr)


class Ping360Device(PtyDevice):
    protocol = "ping360"
    OPTIONS = {**PtyDevice.OPTIONS, "sensor": "ping360", "profile": None, "device_id": 1, "udp_port": 12345,
               "transport": ["pty", "udp"]}
    FAULTS = ("dropout",)
    COUNTERS = ("pings", "requests", "nacks", "bad_input")

    def __init__(self, name: str, options: Mapping[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.mount = self.sonar_mount()
        ref = str(self.options["profile"] or ctx.scenario.sensor(self.mount).profile)
        try:
            self.sim = ScanningSonar(ctx.sonar_profile(ref), seed=ctx.seed)
        except (KeyError, ValueError, OSError) as exc:
            raise self.option_error("profile" if self.options["profile"] else "sensor",
                                    str(exc.args[0] if exc.args else exc)) from None
        self.device_id = self.option_int("device_id", 1, 254)
        self.option_int("udp_port", -1, 65535)
        transport = self.options["transport"]
        self.transports = (transport,) if isinstance(transport, str) else tuple(transport)
        if not self.transports or any(t not in TRANSPORTS for t in self.transports):
            raise self.option_error("transport", f"transport must be a list of {TRANSPORTS}, got {transport!r}")
        self.settings = PingSettings()
        self.angle = 0
        self.busy_until = 0.0        # [s] sim time the head finishes what it is doing
        self.generation = 0          # a new command cancels the one under way
        self.auto: AutoScan | None = None
        self.auto_reply: Reply | None = None
        self.dropout = False
        self._decoders: dict[Any, pp.PingDecoder] = {}
        self._udp: asyncio.DatagramTransport | None = None
        self.udp_address = ""

    # -- lifecycle -------------------------------------------------------------------

    async def start(self) -> list[Endpoint]:
        endpoints = []
        if "pty" in self.transports:
            link = await self.open_pty(lambda data: self._receive("pty", data, self._pty_write))
            endpoints.append(Endpoint(self.name, self.protocol, "pty", link.path,
                                      {"connect": f"uart://{link.path}:{link.baudrate}", "baudrate": link.baudrate,
                                       "device_id": self.device_id}))
        port = int(self.options["udp_port"])
        if "udp" in self.transports and port >= 0:
            host, bound = await self._open_udp(port)
            self.udp_address = f"{host}:{bound}"
            endpoints.append(Endpoint(self.name, self.protocol, "udp", self.udp_address,
                                      {"connect": f"udp://{self.udp_address}", "device_id": self.device_id}))
        return endpoints

    async def _open_udp(self, port: int) -> tuple[str, int]:
        loop = asyncio.get_running_loop()
        proto = _Udp(self._on_datagram)
        try:
            transport, _ = await loop.create_datagram_endpoint(lambda: proto, local_addr=(self.ctx.bind, port))
        except OSError as exc:
            if exc.errno != errno.EADDRINUSE or port == 0:
                raise
            log.warning("%s: UDP port %d is taken; serving on a free port instead", self.name, port)
            transport, _ = await loop.create_datagram_endpoint(lambda: proto, local_addr=(self.ctx.bind, 0))
        self._udp = self.own(transport)
        host, bound = transport.get_extra_info("sockname")[:2]
        return host, bound

    def status(self) -> dict[str, float]:
        return {**super().status(), "angle": float(self.angle), "auto": float(self.auto is not None)}

    def inject_fault(self, fault: str, params: Mapping[str, Any]) -> None:
        self.dropout = True

    def clear_fault(self, fault: str) -> None:
        self.dropout = False

    # -- input -----------------------------------------------------------------------

    def _pty_write(self, data: bytes) -> None:
        if self.link is not None:
            self.link.write(data)

    def _on_datagram(self, data: bytes, addr: Any) -> None:
        if len(self._decoders) > 64 and addr not in self._decoders:  # bounded: forget the oldest peer
            self._decoders.pop(next(iter(self._decoders)))
        transport = self._udp

        def reply(out: bytes, addr: Any = addr) -> None:
            if transport is not None:
                try:
                    transport.sendto(out, addr)
                except OSError as exc:
                    log.debug("%s: reply to %s not sent: %s", self.name, addr, exc)
        self._receive(addr, data, reply)

    def _receive(self, key: Any, data: bytes, reply: Reply) -> None:
        dec = self._decoders.setdefault(key, pp.PingDecoder())
        for ev in drain(dec, data, limit=1000):
            if self.dropout:
                continue
            if isinstance(ev, pp.Message):
                self._handle(ev, reply)
            elif isinstance(ev, (pp.BadChecksum, pp.UnknownMessage, pp.BadPayload)):
                self.counters["bad_input"] += 1
                self._nack(reply, ev.message_id, ev.reason)
            else:  # junk between packets (the auto-baud 'U' of a serial client), oversize lengths
                self.counters["bad_input"] += 1

    def _send(self, reply: Reply, message: str | int, fields: Mapping[str, Any] | None = None) -> None:
        reply(pp.encode(message, fields or {}, src=self.device_id, dst=0))

    def _nack(self, reply: Reply, mid: int, why: str) -> None:
        self.counters["nacks"] += 1
        self._send(reply, "nack", {"nacked_id": mid & 0xFFFF, "nack_message": why[:60]})

    def _handle(self, m: pp.Message, reply: Reply) -> None:
        if m.is_request:
            self.counters["requests"] += 1
            wanted = m.fields.get("requested_id", 0) if m.message_id == 6 else m.message_id
            self._answer_request(int(wanted), reply)
        elif m.message_id == p360.TRANSDUCER:
            self._transducer(m.fields, reply)
        elif m.message_id == p360.AUTO_TRANSMIT:
            self._auto_transmit(m.fields, reply)
        elif m.message_id == p360.MOTOR_OFF:
            self._stop()
            self._send(reply, "ack", {"acked_id": p360.MOTOR_OFF})
        elif m.message_id == p360.RESET:
            self._stop()
            self._send(reply, "ack", {"acked_id": p360.RESET})
        elif m.message_id == p360.SET_DEVICE_ID:
            new = int(m.fields["id"])
            if not 1 <= new <= 254:
                self._nack(reply, m.message_id, "device id must be 1-254")
                return
            self.device_id = new
            self._send(reply, "ack", {"acked_id": p360.SET_DEVICE_ID})
        else:  # a message of another device (a Ping1D's): not ours
            self._nack(reply, m.message_id, f"{m.name} is not a Ping360 message")

    def _answer_request(self, wanted: int, reply: Reply) -> None:
        if wanted == 4:
            self._send(reply, "device_information", {
                "device_type": p360.DEVICE_TYPE, "device_revision": 1, "firmware_version_major": FIRMWARE[0],
                "firmware_version_minor": FIRMWARE[1], "firmware_version_patch": FIRMWARE[2], "reserved": 0})
        elif wanted == 5:
            self._send(reply, "protocol_version", {"version_major": PROTOCOL[0], "version_minor": PROTOCOL[1],
                                                   "version_patch": PROTOCOL[2], "reserved": 0})
        elif wanted == p360.DEVICE_DATA:
            self._send(reply, "device_data", self._data_fields(b""))
        else:
            self._nack(reply, wanted, "not a Ping360 get message")

    def _data_fields(self, data: bytes, angle: int | None = None) -> dict[str, Any]:
        s = self.settings
        return {"mode": 1, "gain_setting": s.gain_setting, "angle": self.angle if angle is None else angle,
                "transmit_duration": s.transmit_duration, "sample_period": s.sample_period,
                "transmit_frequency": s.transmit_frequency, "number_of_samples": s.samples, "data": data}

    def _checked(self, f: Mapping[str, Any], reply: Reply, mid: int) -> PingSettings | None:
        """The commanded settings, or None (and a nack) for a value out of the protocol's range."""
        problems = []
        if not p360.SAMPLES_MIN <= f["number_of_samples"] <= p360.SAMPLES_MAX:
            problems.append(f"number_of_samples {f['number_of_samples']} not in 200-1200")
        if not p360.SAMPLE_PERIOD_MIN <= f["sample_period"] <= p360.SAMPLE_PERIOD_MAX:
            problems.append(f"sample_period {f['sample_period']} not in 80-40000")
        if f["gain_setting"] > 2:
            problems.append(f"gain_setting {f['gain_setting']} not 0-2")
        if problems:
            self._nack(reply, mid, "; ".join(problems))
            return None
        return replace(self.settings, samples=int(f["number_of_samples"]), sample_period=int(f["sample_period"]),
                       gain_setting=int(f["gain_setting"]), transmit_duration=int(f["transmit_duration"]),
                       transmit_frequency=int(f["transmit_frequency"]))

    # -- the head ----------------------------------------------------------------------

    def _stop(self) -> None:
        self.auto = None
        self.generation += 1

    def _transducer(self, f: Mapping[str, Any], reply: Reply) -> None:
        s = self._checked(f, reply, p360.TRANSDUCER)
        if s is None:
            return
        angle = int(f["angle"])
        if angle >= GRADIANS:
            self._nack(reply, p360.TRANSDUCER, f"angle {angle} not in 0-399")
            return
        self._stop()
        self.settings = s
        self._schedule_ping(angle, bool(f["transmit"]), reply, "device_data", self.generation)

    def _auto_transmit(self, f: Mapping[str, Any], reply: Reply) -> None:
        s = self._checked(f, reply, p360.AUTO_TRANSMIT)
        if s is None:
            return
        start, stop, step = int(f["start_angle"]), int(f["stop_angle"]), int(f["num_steps"])
        if start >= GRADIANS or stop >= GRADIANS or not 1 <= step <= 10 or f["delay"] > 100:
            self._nack(reply, p360.AUTO_TRANSMIT, "angles 0-399, num_steps 1-10, delay 0-100 ms")
            return
        self._stop()
        self.settings = s
        self.auto = AutoScan(start, stop, step, int(f["delay"]) / 1000.0)
        self.auto_reply = reply
        self._schedule_ping(start, True, reply, "auto_device_data", self.generation)

    def _schedule_ping(self, angle: int, transmit: bool, reply: Reply, kind: str, gen: int, delay: float = 0.0) -> None:
        s = self.settings
        start = max(self.ctx.now(), self.busy_until) + delay
        done = start + ping_duration(self.angle, angle, s.samples if transmit else 0, s.sample_period,
                                     s.transmit_duration if transmit else 0)
        self.busy_until = done
        self.ctx.at(done, lambda t: self._ping_done(t, angle, transmit, reply, kind, gen), f"{self.name}.ping")

    def _ping_done(self, t: float, angle: int, transmit: bool, reply: Reply, kind: str, gen: int) -> None:
        if gen != self.generation:
            return  # replaced by a newer command
        self.angle = angle
        data = b""
        if transmit:
            state = self.ctx.vehicle.state
            pose = state.pose @ self.ctx.scenario.sensor(self.mount).mount
            data = self.sim.ping(self.ctx.world, pose, angle, self.settings,
                                 sound_speed=float(self.ctx.scenario.water.sound_speed), time=t,
                                 index=self.counters["pings"]).tobytes()
            self.counters["pings"] += 1
        if not self.dropout:
            fields = self._data_fields(data, angle)
            if kind == "auto_device_data" and self.auto is not None:
                a = self.auto
                fields.update(start_angle=a.start, stop_angle=a.stop, num_steps=a.step,
                              delay=int(round(a.delay_s * 1000)))
            self._send(reply, kind, fields)
        if kind == "auto_device_data" and self.auto is not None:
            self._schedule_ping(self._next_angle(angle), True, reply, kind, gen, self.auto.delay_s)

    def _next_angle(self, angle: int) -> int:
        """The auto scan's next head angle: round and round for a full turn, back and forth in a sector."""
        a = self.auto
        assert a is not None
        span = (a.stop - a.start) % GRADIANS
        if span == 0 or span >= GRADIANS - a.step:  # a full turn
            return (angle + a.step) % GRADIANS
        here = (angle - a.start) % GRADIANS
        nxt = here + a.direction * a.step
        if nxt > span or nxt < 0:  # the sector's edge: turn round
            a.direction = -a.direction
            nxt = min(max(here + a.direction * a.step, 0), span)
        return (a.start + nxt) % GRADIANS
