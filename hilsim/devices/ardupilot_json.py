"""ArduPilot SITL's JSON physics backend as a device: ArduSub flies the simulated vehicle in lockstep.

ArduPilot (``--model JSON:127.0.0.1``) sends one servo packet per physics step
to UDP 9002 and waits for the state (:mod:`hilsim.protocols.ardupilot_json`).
This device binds that port (another one, with a warning, when it is taken; the
endpoints table says which), and for each packet:

- a new ``frame_count``: the servo outputs command the thrusters through the
  vehicle profile's ``[ardupilot]`` table (PWM 1100-1900 us -> -1..1 normalised,
  times the motor's direction; the thruster profile applies its dead band and
  lag; PWM 0 = off), then the simulation advances by the step ArduPilot asks for
  (``1 / frame_rate``) through ``ctx.advance`` (physics, thrusters, every other
  device's schedule), and the state at the new time is sent to the packet's source;
- the same ``frame_count`` again: the same reply again, no step;
- a smaller ``frame_count`` (ArduPilot restarted): the vehicle is put back at the
  scenario's start, at rest, the reply timestamps start again at 0, and it is logged;
- a malformed datagram: counted (``malformed``) and ignored, never answered.

While ArduPilot is silent the simulation stands still (the device is the clock
master, ``clock_master = True``) and every other device keeps serving its clients.

The state sent: ``timestamp`` [s] since ArduPilot's session began; ``gyro`` the body
rates; ``accel_body`` the specific force at the CG in the body frame
(:func:`hilsim.sim.vehicle6dof.specific_force`; level at rest (0, 0, -9.80665));
``position`` NED [m] from the scenario's origin (home at the surface: D = depth);
``velocity`` NED [m/s]; ``quaternion`` body -> NED; ``rng_1`` [m] along the beam
axis (sensor +z) of the vehicle's echosounder (option ``rangefinder``: a sensor
name, default the scenario's first ``echosounder``; ``"none"``: no rangefinder),
cast with Embree in ``ctx.world``, ``rangefinder_max_m`` when nothing is in range;
``no_time_sync`` when the bridge runs ``--fast``.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import math
import time
from collections import deque
from typing import Any, Callable, ClassVar, Mapping, Sequence

import numpy as np

from hilsim.devices.base import Device, DeviceContext, Endpoint
from hilsim.protocols.ardupilot_json import ServoPacket, decode_servo, encode_reply, quaternion_from_euler
from hilsim.sim.geometry import rpy_to_matrix
from hilsim.sim.vehicle import load_vehicle_profile
from hilsim.sim.vehicle6dof import specific_force

log = logging.getLogger(__name__)

ARDUPILOT_PORT = 9002
PWM_NEUTRAL = 1500.0  # [us]
PWM_SPAN = 400.0      # [us] 1100..1900 -> -1..1
_QUEUE = 64           # datagrams waiting at most (ArduPilot has one in flight; more is a flood)


class _Protocol(asyncio.DatagramProtocol):
    def __init__(self, device: "ArdupilotJsonDevice") -> None:
        self.device = device

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.device._received(data, addr)

    def error_received(self, exc: Exception) -> None:
        self.device.counters["socket_errors"] += 1


class ArdupilotJsonDevice(Device):
    """The ``ardupilot-json`` device (see the module doc). Options: ``port`` (9002, ArduPilot's;
    0 picks a free one), ``rangefinder`` (sensor name | ``"none"`` | unset: the first echosounder),
    ``rangefinder_max_m`` [m]."""

    protocol = "ardupilot-json"
    clock_master = True
    OPTIONS: ClassVar[Mapping[str, Any]] = {"port": ARDUPILOT_PORT, "rangefinder": None, "rangefinder_max_m": 50.0}
    COUNTERS = ("frames", "repeats", "restarts", "malformed", "dropped")

    def __init__(self, name: str, options: Mapping[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.option_int("port", 0, 65535)
        self.max_range = self.option_number("rangefinder_max_m", 0.0, lo_open=True)
        spec = ctx.scenario.vehicle
        if spec is None:
            raise self.option_error("port", "the ardupilot-json device needs the scenario's [vehicle]")
        from hilsim.resources import find_profile

        profile = load_vehicle_profile(find_profile("vehicles", spec.profile, base=ctx.scenario.folder))
        if profile.ardupilot is None:
            raise self.option_error("port", f"vehicle profile {profile.name!r} has no [ardupilot] table "
                                    "(frame and servo outputs)")
        self.table = profile.ardupilot
        self._servo = [(m.servo - 1, m.thruster, float(m.direction)) for m in self.table.motors]
        self._rng_mount = self._rangefinder_mount()
        self.transport: asyncio.DatagramTransport | None = None
        self.host, self.port = ctx.bind, 0
        self._queue: deque[tuple[bytes, Any]] = deque()
        self._wake: asyncio.Event | None = None
        self._task: asyncio.Task[None] | None = None
        self._last_count: int | None = None
        self._last_reply = b""
        self._epoch = 0.0
        self._rate_window: deque[float] = deque(maxlen=240)  # wall times of the last frames
        self.last_pwm: tuple[int, ...] = ()

    def _rangefinder_mount(self) -> Any:
        choice = self.options["rangefinder"]
        sensors = self.ctx.scenario.sensors
        if choice in ("none", False):
            return None
        if choice is None:
            return next((s.mount for s in sensors if s.kind == "echosounder"), None)
        try:
            return self.ctx.scenario.sensor(str(choice)).mount
        except KeyError as exc:
            raise self.option_error("rangefinder", str(exc.args[0])) from None

    # -- lifecycle -----------------------------------------------------------------

    async def start(self) -> list[Endpoint]:
        loop = asyncio.get_running_loop()
        port = int(self.options["port"])
        try:
            transport, _ = await loop.create_datagram_endpoint(lambda: _Protocol(self),
                                                               local_addr=(self.ctx.bind, port))
        except OSError as exc:
            if exc.errno != errno.EADDRINUSE or port == 0:
                raise
            log.warning("%s: UDP port %d is taken; serving on a free port instead (start ArduPilot with "
                        "--sim-port-out <port> to reach it)", self.name, port)
            transport, _ = await loop.create_datagram_endpoint(lambda: _Protocol(self),
                                                               local_addr=(self.ctx.bind, 0))
        self.transport = transport
        self.host, self.port = transport.get_extra_info("sockname")[:2]
        self.own(transport)
        self._wake = asyncio.Event()
        self._task = asyncio.ensure_future(self._serve())
        log.info("%s: the simulation waits for ArduPilot's servo packets on udp %s:%d (ArduSub SITL: "
                 "--model JSON:%s%s, FRAME_CONFIG %d)", self.name, self.host, self.port, self.host,
                 "" if self.port == ARDUPILOT_PORT else f" --sim-port-out {self.port}", self.table.frame_config)
        extra = {"frame": self.table.frame, "FRAME_CONFIG": self.table.frame_config,
                 "servos": len(self.table.motors), "rangefinder": "rng_1" if self._rng_mount is not None else "none",
                 "lockstep": True}
        return [Endpoint(self.name, self.protocol, "udp", f"{self.host}:{self.port}", extra)]

    async def on_close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except (asyncio.CancelledError, Exception):  # noqa: BLE001 - shutting down
                pass
            self._task = None

    # -- datagrams -----------------------------------------------------------------

    def _received(self, data: bytes, addr: Any) -> None:
        if len(self._queue) >= _QUEUE:
            self.counters["dropped"] += 1
            return
        self._queue.append((data, addr))
        if self._wake is not None:
            self._wake.set()

    async def _serve(self) -> None:
        assert self._wake is not None
        while True:
            while not self._queue:
                self._wake.clear()
                await self._wake.wait()
            data, addr = self._queue.popleft()
            try:
                await self.handle(data, addr)
            except asyncio.CancelledError:
                raise
            except Exception:  # noqa: BLE001 - a bug of ours must not stop the lockstep
                self.counters["errors"] += 1
                log.exception("%s: handling a servo packet", self.name)

    async def handle(self, data: bytes, addr: Any) -> None:
        """One datagram from ArduPilot (``addr``: its source, where the reply goes)."""
        pkt = decode_servo(data)
        if not isinstance(pkt, ServoPacket):
            self.counters["malformed"] += 1
            if self.counters["malformed"] in (1, 10, 100) or self.counters["malformed"] % 1000 == 0:
                log.warning("%s: malformed datagram from %s ignored (%s; %d so far)", self.name, addr,
                            pkt.reason, self.counters["malformed"])
            return
        count = pkt.frame_count
        last = self._last_count
        if last is not None and count == last:
            self.counters["repeats"] += 1
            self._send(self._last_reply, addr)
            return
        if last is not None and count < last:
            self.counters["restarts"] += 1
            log.info("%s: ArduPilot restarted (frame_count %d after %d): the vehicle is back at the "
                     "scenario's start", self.name, count, last)
            self._reset_vehicle()
            last = None
        if last is None:
            self._epoch = self.ctx.vehicle.state.time
        self._last_count = count
        self._command(pkt)
        await self.ctx.advance(pkt.step)
        self.counters["frames"] += 1
        self._rate_window.append(time.monotonic())
        try:
            reply = self.reply()
        except ValueError:  # a non-finite state: our bug; never send it, keep the last good reply
            self.counters["errors"] += 1
            log.exception("%s: state not sendable", self.name)
            reply = self._last_reply
        self._last_reply = reply
        self._send(reply, addr)

    def _send(self, reply: bytes, addr: Any) -> None:
        if reply and self.transport is not None:
            self.transport.sendto(reply, addr)

    def _command(self, pkt: ServoPacket) -> None:
        """Servo outputs -> thruster commands (normalised, through the thruster profile)."""
        thrusters = self.ctx.vehicle.thrusters
        pwm = pkt.pwm
        self.last_pwm = pwm
        if thrusters is None:
            return
        now = self.ctx.now()
        n = len(pwm)
        for out, index, direction in self._servo:
            us = pwm[out] if out < n else 0
            if us == 0:
                value = 0.0  # output off
            else:
                value = (us - PWM_NEUTRAL) / PWM_SPAN
                value = -1.0 if value < -1.0 else 1.0 if value > 1.0 else value
            thrusters.command(index, "normalized", direction * value, now)
        if self.observed("command"):
            self.publish("command", {"t": now, "frame_count": pkt.frame_count, "frame_rate": pkt.frame_rate,
                                     "pwm": list(pwm)})

    def _reset_vehicle(self) -> None:
        self.ctx.reset_vehicle()
        thrusters = self.ctx.vehicle.thrusters
        if thrusters is not None:
            now = self.ctx.now()
            for _, index, _ in self._servo:
                thrusters.command(index, "normalized", 0.0, now)

    # -- the state -----------------------------------------------------------------

    def reply(self) -> bytes:
        """The JSON state of the vehicle now (see the module doc)."""
        state = self.ctx.vehicle.state
        x, y, z, roll, pitch, yaw, u, v, w, p, q, r, _, _, _ = state.flat()
        rot = rpy_to_matrix(roll, pitch, yaw)
        vel = (rot @ np.array([u, v, w])).tolist()
        return encode_reply(state.time - self._epoch, (p, q, r), specific_force(state), (x, y, z), vel,
                            quaternion_from_euler(roll, pitch, yaw), self.range(state, rot),
                            no_time_sync=bool(self.ctx.fast))

    def range(self, state: Any, rot: np.ndarray | None = None) -> float | None:
        """[m] along the rangefinder's beam to the first surface (``rangefinder_max_m`` if none
        within it), None without a rangefinder."""
        mount = self._rng_mount
        if mount is None:
            return None
        if rot is None:
            rot = rpy_to_matrix(*state.attitude)
        origin = np.asarray(state.position, dtype=float) + rot @ mount.position
        direction = rot @ (mount.rotation @ np.array([0.0, 0.0, 1.0]))
        hits = self.ctx.world.cast(origin[None, :], direction[None, :], 0.0, self.max_range)
        t = float(hits.t[0])
        return t if math.isfinite(t) else self.max_range

    def truth_columns(self) -> tuple[tuple[str, ...], Callable[[Any], Sequence[Any]]]:
        """Columns for the run's truth record: the PWM [us] of each servo output the vehicle's
        ``[ardupilot]`` table uses (``pwm_1`` ...), as last received (0 before the first packet)."""
        outs = sorted(m.servo for m in self.table.motors)

        def values(state: Any) -> list[int]:
            pwm = self.last_pwm
            return [pwm[o - 1] if o - 1 < len(pwm) else 0 for o in outs]

        return tuple(f"pwm_{o}" for o in outs), values

    # -- status --------------------------------------------------------------------

    def lockstep_rate(self) -> float:
        """[frames/s] answered over the last few seconds of wall time (0 when idle)."""
        win = self._rate_window
        if len(win) < 2 or time.monotonic() - win[-1] > 1.0:
            return 0.0
        return (len(win) - 1) / max(win[-1] - win[0], 1e-9)

    def status(self) -> dict[str, float]:
        return {**super().status(), "rate_hz": round(self.lockstep_rate(), 1)}
