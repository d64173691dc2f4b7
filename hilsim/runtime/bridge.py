"""The live bridge: a scenario's world, vehicle, sensors and devices, run together.

``Bridge`` builds everything a scenario wires up and is the
:class:`~hilsim.devices.base.DeviceContext` its devices see. One asyncio
loop runs every link and the scheduler (physics at ``physics_rate``, each
device's periodic events); sonar frames are rendered in a worker process.

Lifecycle: ``await bridge.start()`` (returns the endpoints once everything
listens) -> ``await bridge.run(duration)`` -> ``await bridge.close()``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any, Awaitable, Callable, Mapping, TypeVar

import numpy as np

from hilsim.config import ConfigError, Doc, load_toml
from hilsim.devices import device_class
from hilsim.devices.base import Device, Endpoint, OptionError, Periodic, RenderedFrame, RenderFailed
from hilsim.runtime.observe import Observers
from hilsim.resources import find_profile
from hilsim.runtime.clock import LockstepClock, RealTimeClock, ScaledClock, VirtualClock
from hilsim.runtime.faults import Faults
from hilsim.runtime.scheduler import DEFAULT_PHYSICS_RATE, ONE_SHOT, Scheduler, VehicleLoop
from hilsim.runtime.worker import RenderWorker
from hilsim.sim.scenario import Scenario, load_scenario
from hilsim.sim.sonar_profile import SonarProfile, SonarSettings, load_sonar_profile
from hilsim.sim.state import VehicleState
from hilsim.sim.vehicle import Current, Vehicle, load_vehicle_profile
from hilsim.sim.geometry import Pose
from hilsim.sim.world import World
from hilsim.runtime.timeline import Timeline
from hilsim.runtime.truth import DEFAULT_TRUTH_RATE, RunTruth

log = logging.getLogger("hilsim.bridge")
T = TypeVar("T")

LOOPBACK = "127.0.0.1"


class Bridge:
    """Everything a scenario wires up, run in one asyncio loop (+ the render worker).

    fast: virtual clock, as fast as possible; bind: host servers listen on;
    broadcast: destination of UDP status/beacons; record: optional ``.ddf``
    recording of the first DIDSON-like stream; epoch: UNIX time [s] stamped
    for simulation time 0 (default: the wall clock at start).
    """

    def __init__(self, scenario: Scenario | Path | str, *, fast: bool = False, bind: str = LOOPBACK,
                 broadcast: str = LOOPBACK, seed: int | None = None, record: Path | str | None = None,
                 physics_rate: float = DEFAULT_PHYSICS_RATE, run_dir: Path | str | None = None,
                 epoch: float | None = None, status_interval: float = 5.0,
                 worker_timeout: float = 10.0, time_scale: float = 1.0, console: int | None = None,
                 record_mcap: Path | str | None = None, foxglove: int | None = None) -> None:
        self.scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
        self.fast = fast
        self.bind = bind
        self.broadcast = broadcast
        self.seed = self.scenario.seed if seed is None else int(seed)
        self.record = Path(record) if record is not None else None
        self.epoch = epoch
        self.status_interval = status_interval
        self._own_run_dir = run_dir is None
        self.run_dir = Path(run_dir) if run_dir is not None else Path(tempfile.mkdtemp(prefix="hilsim-"))
        # async_margin=0: never block the loop to sharpen a tick; every link shares this loop,
        # and a tick a millisecond late costs nothing (the physics integrates to the tick's time)
        if fast:
            clock: VirtualClock | RealTimeClock = VirtualClock()
        elif time_scale != 1.0:
            clock = ScaledClock(time_scale)
        else:
            clock = RealTimeClock(async_margin=0.0)
        self.time_scale = 1.0 if fast else float(time_scale)
        # late = more than half a period behind (asyncio's timer jitter of about a millisecond is not)
        self.scheduler = Scheduler(clock, late_fraction=0.5)
        self.vehicle = self._build_vehicle(physics_rate)
        self.worker = RenderWorker(self.scenario.path, self.seed, timeout=worker_timeout)
        self.devices: list[Device] = []
        self.endpoints: list[Endpoint] = []
        self._shared: dict[tuple[Any, ...], Any] = {}
        self._profiles: dict[str, SonarProfile] = {}
        self._tasks: set[asyncio.Task[Any]] = set()
        self._started = False
        self._closed = False
        self._wall0 = 0.0
        self._world: World | None = None
        # the ground truth (hilsim.runtime.truth): files (None: truth.csv, summary.json in the run folder)
        self.truth_path: Path | None = None
        self.summary_path: Path | None = None
        self.truth_rate = DEFAULT_TRUTH_RATE
        self.truth: RunTruth | None = None
        self.observers = Observers()
        # the console (port, 0: free), an MCAP recording, the Foxglove server (hilsim.console.prepare)
        self.console_port, self.record_mcap, self.foxglove_port = console, record_mcap, foxglove
        self.attached: Any = None

    # -- building --------------------------------------------------------------

    def _build_vehicle(self, physics_rate: float) -> VehicleLoop:
        spec = self.scenario.vehicle
        if spec is None:
            raise ConfigError(self.scenario.path, "vehicle", "the bridge needs a [vehicle] table")
        profile = load_vehicle_profile(find_profile("vehicles", spec.profile, base=self.scenario.folder))
        thrusters = profile.thruster_set() if profile.thrusters else None
        state = VehicleState(time=0.0, position=np.array(spec.position, dtype=float),
                             attitude=np.array([0.0, 0.0, spec.attitude[2]]))
        return VehicleLoop(Vehicle(profile), thrusters, state, physics_rate=physics_rate)

    def _device_specs(self) -> list[tuple[str, str, dict[str, Any]]]:
        doc = Doc(self.scenario.path, self.scenario.path.read_text(), self.scenario.raw)
        raw = self.scenario.raw.get("devices", [])
        if not isinstance(raw, list):
            raise doc.error("devices", "expected an array of tables: [[devices]]")
        out, names = [], set()
        for i, t in enumerate(raw):
            if not isinstance(t, Mapping):
                raise doc.error(f"devices.{i}", "expected a table")
            name, proto = t.get("name"), t.get("protocol")
            if not isinstance(name, str) or not name:
                raise doc.error(f"devices.{i}", "a device needs a 'name'")
            if not isinstance(proto, str):
                raise doc.error(f"devices.{name}", "a device needs a 'protocol'")
            if name in names:
                raise doc.error(f"devices.{name}", f"duplicate device name {name!r}")
            names.add(name)
            out.append((name, proto, {k: v for k, v in t.items() if k not in ("name", "protocol", "description")}))
        return out

    def _device_error(self, doc: Doc, name: str, exc: Exception, prefix: str = "") -> ConfigError:
        """A device's error as the scenario's: file, line and ``[devices.<name>(.<option>)]``."""
        if isinstance(exc, ConfigError) and exc.path is not None and exc.path.resolve() == self.scenario.path:
            return exc  # already names the scenario's line and key
        if isinstance(exc, OptionError):
            return doc.error(f"devices.{name}.{exc.option}", prefix + exc.message)
        message = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        return doc.error(f"devices.{name}", f"{prefix}{message}")

    async def start(self) -> list[Endpoint]:
        """Start the worker, every device and the physics; returns the endpoints.

        A device refusing its options (when built or started), or failing to open its link,
        raises :class:`ConfigError` naming the scenario's file, the line and the device's key."""
        if self._started:
            return self.endpoints
        self._started = True
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._wall0 = time.time() if self.epoch is None else float(self.epoch)
        specs = self._device_specs()
        doc = Doc(self.scenario.path, self.scenario.path.read_text(), self.scenario.raw)
        classes = []
        for name, proto, options in specs:
            try:
                classes.append(device_class(proto))
            except KeyError as exc:
                raise doc.error(f"devices.{name}.protocol", str(exc.args[0])) from None
        masters = [name for (name, _, _), cls in zip(specs, classes) if cls.clock_master]
        if len(masters) > 1:
            raise doc.error(f"devices.{masters[1]}", f"two devices drive the clock ({', '.join(masters)}); "
                            "a run has one clock master")
        if masters:  # a peer drives the simulation clock (lockstep): the scheduler waits for its steps
            self.scheduler.clock = LockstepClock()
            log.info("lockstep: device %s drives the simulation clock", masters[0])
        for (name, proto, options), cls in zip(specs, classes):
            try:
                self.devices.append(cls(name, options, self))
            except (ValueError, KeyError) as exc:
                raise self._device_error(doc, name, exc) from None
        if self.record is not None:
            suffix = self.record.suffix.lower()
            takers = [d for d in self.devices if suffix in d.records]
            if not takers:
                kinds = sorted({x for d in self.devices for x in d.records})
                raise ValueError(f"--record {self.record}: no device of this scenario records {suffix or 'that'} "
                                 f"files (it can record: {', '.join(kinds) or 'nothing'})")
            takers[0].record_to(self.record)
        if any(d.needs_renderer for d in self.devices):
            await self.worker.start()
        if (self.console_port, self.record_mcap, self.foxglove_port) != (None, None, None):
            from hilsim.console import prepare  # listening before the devices start: their first readings count
            self.attached = prepare(self, console_port=self.console_port, record_mcap=self.record_mcap,
                                    foxglove_port=self.foxglove_port)
        self.vehicle.attach(self.scheduler)
        try:
            for d in self.devices:
                try:
                    self.endpoints.extend(await d.start())
                except (ValueError, KeyError, OSError) as exc:  # a bad option, a port in use...
                    raise self._device_error(doc, d.name, exc, "cannot start: ") from None
        except BaseException:
            await self.close()
            raise
        if isinstance(self.scheduler.clock, RealTimeClock):
            self.scheduler.clock.reset()
        if self.epoch is None:  # simulation time 0 is now, on the wall clock
            self._wall0 = time.time() - self.scheduler.clock.now()
        self.faults = Faults(self.devices, self.vehicle.thrusters, self.now, self.publish)
        self.timeline = Timeline(self, doc)
        self.timeline.schedule()
        self.truth = RunTruth(self, self.truth_path or self.run_dir / "truth.csv",
                              self.summary_path or self.run_dir / "summary.json", self.truth_rate)
        if self.attached is not None:
            try:
                self.endpoints.extend(await self.attached.start())
            except (OSError, RuntimeError) as exc:  # a port in use, an unwritable file
                await self.close()
                raise ValueError(f"cannot start the console/recorder: {exc}") from None
        if self.status_interval > 0:
            self.scheduler.add("status", self.status_interval, self._log_status, priority=100,
                               tolerance=self.status_interval)
        return self.endpoints

    # -- running ---------------------------------------------------------------

    async def run(self, duration: float | None = None) -> None:
        """Run until ``duration`` [s] of simulation time (None: until :meth:`stop`)."""
        if not self._started:
            await self.start()
        await self.scheduler.run_async(until=duration)

    def stop(self) -> None:
        self.scheduler.stop()

    # -- scripted changes (the timeline) ----------------------------------------

    def at(self, t: float, callback: Callable[[float], Any], name: str = "at") -> None:
        """Run ``callback(t)`` once at simulation time ``t`` [s] (now, if already past)."""
        holder: list[Any] = []

        def once(tt: float) -> Any:
            self.scheduler.remove(holder[0])
            return callback(tt)

        holder.append(self.scheduler.add(name, ONE_SHOT, once, offset=max(t, 0.0), priority=5, tolerance=ONE_SHOT))

    def object_names(self) -> list[str]:
        """The scenario's object names as written in its file."""
        return self.scenario.raw_object_names()

    def set_current(self, velocity: tuple[float, float, float]) -> None:
        """The water current from now on: NED [m/s]."""
        self.vehicle.current = None if not any(velocity) else Current.constant(velocity)

    def teleport(self, position: tuple[float, float, float], rpy: tuple[float, float, float]) -> None:
        """Put the vehicle at ``position`` (NED [m]) heading ``rpy[2]`` [rad], at rest."""
        s = self.vehicle.state
        self.vehicle.state = VehicleState(time=s.time, position=np.array(position, dtype=float),
                                          attitude=np.array([0.0, 0.0, rpy[2]]))

    def reset_vehicle(self) -> None:
        """Put the vehicle back at the scenario's start, at rest (a clock master that restarted)."""
        spec = self.scenario.vehicle
        assert spec is not None
        self.teleport(tuple(spec.position), (0.0, 0.0, spec.attitude[2]))  # type: ignore[arg-type]

    async def move_object(self, name: str, position: tuple[float, float, float],
                          rpy: tuple[float, float, float], t: float | None = None) -> None:
        """Place object ``name`` at a new pose: the worker's scene (every sonar sees it from the next
        frame) and the main process's (contacts, DVL and altimeter beams). Observers hear it on
        topic ``world`` (``{"t", "action": "move", "object", "position_m", "rpy_rad"}``; t [s] the
        move's simulation time, as the timeline scheduled it, default :meth:`now`): the console and
        the recorder then show the main process's scene (:attr:`world`) again."""
        self.world.place(name, Pose.from_xyz_rpy(position, rpy).matrix(),
                         self.scenario.object_placement(name).matrix())
        self.publish("world", {"t": float(self.now() if t is None else t), "action": "move", "object": name,
                               "position_m": [float(v) for v in position], "rpy_rad": [float(v) for v in rpy]})
        if self.worker.pid is not None:
            await self.worker.change_world("move", name, tuple(position), tuple(rpy))

    async def close(self) -> None:
        """Close every device and link, stop the worker, remove the run folder."""
        if self._closed:
            return
        self._closed = True
        if self.truth is not None:
            self.truth.finish()
        if self.attached is not None:
            await self.attached.close()
        for d in reversed(self.devices):
            try:
                await d.close()
            except Exception:  # noqa: BLE001 - close the rest regardless
                log.exception("closing device %s", d.name)
        for key, link in reversed(list(self._shared.items())):
            try:
                await link.close()
            except Exception:  # noqa: BLE001
                log.exception("closing shared link %s", key)
        for t in list(self._tasks):
            t.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        await self.worker.close()
        if self._own_run_dir:
            shutil.rmtree(self.run_dir, ignore_errors=True)

    # -- DeviceContext ---------------------------------------------------------

    @property
    def world(self) -> World:
        """The main process's ray-cast scene (short queries: DVL beams, altimeters, contacts);
        built on first use, kept in step with the timeline's object moves."""
        if self._world is None:
            self._world = self.scenario.build_world()
        return self._world

    def every(self, name: str, period: float, callback: Callable[[float], Any], *, offset: float = 0.0,
              priority: int = 20, tolerance: float | None = None) -> Periodic:
        return _Handle(self.scheduler, self.scheduler.add(name, period, callback, offset=offset,
                                                          priority=priority, tolerance=tolerance))

    def observed(self, topic: str) -> bool:
        return self.observers.observed(topic)

    def publish(self, topic: str, message: Mapping[str, Any]) -> None:
        self.observers.publish(topic, message)

    def now(self) -> float:
        if self.fast and not self.lockstep:
            return self.vehicle.state.time
        return max(self.vehicle.state.time, self.scheduler.clock.now())

    def wall_time(self, sim_time: float) -> float:
        return self._wall0 + sim_time

    def sonar_profile(self, name: str) -> SonarProfile:
        path = str(find_profile("sonars", name, base=self.scenario.folder))
        if path not in self._profiles:
            self._profiles[path] = load_sonar_profile(path)
        return self._profiles[path]

    async def render(self, mount: str, profile: str, settings: SonarSettings | None = None, *,
                     frame_index: int = 0, budget_s: float | None = None) -> RenderedFrame:
        state = self.vehicle.state
        m = self.scenario.sensor(mount)
        pose = state.pose @ m.mount
        path = str(find_profile("sonars", profile, base=self.scenario.folder))
        # the ray count adapts to the wall clock only in real time (scaled: the period is shorter on
        # it); a virtual or lockstep clock keeps it fixed, so a seed gives the same bytes
        wall_budget = None if budget_s is None or self.fast or self.lockstep else budget_s / self.time_scale
        frame, seconds, altitude = await self.worker.render_sonar(path, pose, settings, state.time, frame_index,
                                                                  state.position, budget_s=wall_budget)
        return RenderedFrame(frame, state, seconds, altitude, rays=frame.settings.elevation_rays)

    async def render_camera(self, mount: str, *, max_width: int = 0) -> tuple[Any, VehicleState]:
        """((h, w, 3) uint8 picture, state) of camera ``mount`` now, rendered in the worker at most
        ``max_width`` px wide (0: the profile's size); raises RenderFailed."""
        state, m = self.vehicle.state, self.scenario.sensor(mount)
        pose = state.pose @ m.mount
        path = str(find_profile("cameras", m.profile, base=self.scenario.folder))
        rgb = await self.worker.call("camera", path, np.asarray(pose.position), np.asarray(pose.rotation),
                                     state.time, int(max_width))
        return rgb, state

    async def altitude(self) -> float:
        """[m] distance from the vehicle straight down to the first surface (inf if none)."""
        return float(await self.worker.call("altitude", np.asarray(self.vehicle.state.position)))

    def pty_path(self, option: str | os.PathLike[str] | None, default: str) -> Path:
        """Where a device's pty symlink goes: ``option`` (a name or relative path) or ``default``,
        inside the run folder (``hilsim run --pty-dir``; a fresh temporary folder by default).
        A scenario is data and may not place files elsewhere: absolute paths and ``..`` are refused."""
        return path_inside(self.run_dir, option or default, "pty path", "choose the folder with --pty-dir")

    def output_path(self, option: str | os.PathLike[str]) -> Path:
        """A file a scenario asks a device to write (a recording): relative to the scenario's
        folder and inside it. Recordings anywhere else are asked for on the command line."""
        return path_inside(self.scenario.folder, option, "output path", "record elsewhere with hilsim run --record")

    async def shared(self, key: tuple[Any, ...], factory: Callable[[], Awaitable[T]]) -> T:
        if key not in self._shared:
            self._shared[key] = await factory()
        return self._shared[key]  # type: ignore[no-any-return]

    async def advance(self, dt: float) -> None:
        """Lockstep: grant ``dt`` [s] of simulation time (only with a ``clock_master`` device); returns
        when physics, thrusters and every device's schedule have run to the new time."""
        clock = self.scheduler.clock
        if not isinstance(clock, LockstepClock):
            raise RuntimeError("advance() is for a clock_master device's lockstep; this bridge runs its own clock")
        await clock.advance(dt)
        self.vehicle.physics_tick(clock.now())  # the state exactly at the granted time

    @property
    def lockstep(self) -> bool:
        return isinstance(self.scheduler.clock, LockstepClock)

    def defer(self, coro: Awaitable[Any]) -> Awaitable[Any] | None:
        """For scheduler callbacks: in fast mode and in lockstep return ``coro`` (simulated time
        waits for it: a sonar frame is rendered at its simulated time, however fast the peer
        steps); in real time run it as a task so the tick returns at once."""
        if self.fast or self.lockstep:
            return coro
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return None

    # -- status ----------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        s = self.vehicle.state
        late = sum(ev.stats.late for ev in self.scheduler.events)
        skipped = sum(ev.stats.skipped for ev in self.scheduler.events)
        return {"time_s": round(s.time, 3), "depth_m": round(s.depth, 3),
                "heading_deg": round(math.degrees(s.heading) % 360.0, 1), "late_ticks": late,
                "skipped_ticks": skipped, "render_restarts": self.worker.restarts,
                "devices": {d.name: d.status() for d in self.devices},
                "contacts": self.truth.contacts if self.truth is not None else 0}

    def _log_status(self, t: float) -> None:
        st = self.status()
        parts = []
        for name, ds in st["devices"].items():
            shown = [f"{k} {v:g}" if isinstance(v, (int, float)) else f"{k} {v}"
                     for k, v in ds.items() if v and k not in ("device_id",)]
            parts.append(f"{name}({', '.join(shown)})" if shown else name)
        log.info("t=%.1fs depth %.2f m heading %.1f deg | contacts %d | late ticks %d, skipped %d | %s",
                 st["time_s"], st["depth_m"], st["heading_deg"], st["contacts"], st["late_ticks"], st["skipped_ticks"],
                 " ".join(parts) or "no devices")


class _Handle:
    """A :class:`~hilsim.devices.context.Periodic` over a scheduler event."""

    __slots__ = ("_scheduler", "event")

    def __init__(self, scheduler: Scheduler, event: Any) -> None:
        self._scheduler, self.event = scheduler, event

    def cancel(self) -> None:
        self._scheduler.remove(self.event)


def path_inside(base: Path, rel: str | os.PathLike[str], what: str = "path", hint: str = "") -> Path:
    """``base / rel``, refusing absolute paths and anything that leaves ``base`` (``..``, symlinked
    folders). The last component is not resolved: it may be a symlink we own (a pty)."""
    p = Path(rel)
    hint = f" ({hint})" if hint else ""
    if p.is_absolute():
        raise ValueError(f"{what} {str(rel)!r} is absolute; scenario paths must stay inside {base}{hint}")
    if p.name in ("", ".", ".."):
        raise ValueError(f"{what} {str(rel)!r} does not name a file{hint}")
    full = (base / p).parent.resolve() / p.name
    if base.resolve() not in full.parents:
        raise ValueError(f"{what} {str(rel)!r} leaves {base}{hint}")
    full.parent.mkdir(parents=True, exist_ok=True)
    return full


def endpoints_table(endpoints: list[Endpoint]) -> str:
    """A fixed-width text table of the endpoints."""
    rows = [("DEVICE", "PROTOCOL", "TRANSPORT", "ADDRESS", "EXTRA")]
    for e in endpoints:
        rows.append((e.device, e.protocol, e.transport, e.address,
                     " ".join(f"{k}={v}" for k, v in e.extra.items())))
    widths = [max(len(r[i]) for r in rows) for i in range(5)]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows)


def write_endpoints(path: Path | str, endpoints: list[Endpoint]) -> None:
    """Write the endpoints JSON atomically (readers never see a half-written file)."""
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(json.dumps([e.to_json() for e in endpoints], indent=2) + "\n")
    os.replace(tmp, p)
