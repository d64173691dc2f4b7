"""The render worker: a child process that owns the ray-cast world.

Embree holds the GIL while it traces, so sonar frames are rendered in their
own process and the main process's asyncio loop (links, physics) never waits
on a frame. The parent sends ``(id, profile, pose, settings, time, frame)``
requests over a pipe and awaits replies without blocking (the pipe's file
descriptor is watched by the event loop).

If the worker dies or does not answer within ``timeout`` seconds, it is
killed and started again; the request in flight fails with
:class:`~hilsim.devices.base.RenderFailed`, which the device counts (the
gap shows in its frame numbers) while every other device carries on.

Deadline-aware rendering: a sonar request may carry its budget (the device's
ping period [s]). When a frame takes more than ``ADAPT_HIGH`` of its budget (wall
time from the request to the answer, waiting behind other devices' frames included:
a busy machine shows there), the frames that follow cast fewer elevation rays per
beam (:class:`RayGovernor`: levels ``ADAPT_STEP`` apart, never below the profile's
``min_elevation_rays``; the range spreading keeps the image free of empty bins, its
width cap ``spread_max_bins`` widened by as much as the rays are fewer);
after ``ADAPT_CALM`` frames in a row under ``ADAPT_LOW`` of their budget, one level
more again. A profile with ``adaptive_rays = false`` always gets its ray count.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import multiprocessing as mp
import os
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from hilsim.devices.base import RenderFailed
from hilsim.sim.geometry import Pose

log = logging.getLogger(__name__)


def _tune_allocator() -> None:
    """Keep glibc from returning each frame's large temporaries to the kernel only to
    fault them in again on the next frame (measured: 29 -> 20 ms per tank frame)."""
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 64 << 20)   # M_MMAP_THRESHOLD
        libc.mallopt(-1, 256 << 20)  # M_TRIM_THRESHOLD
    except (OSError, AttributeError):  # not glibc: nothing to tune
        pass


def _worker_main(conn: Connection, scenario_path: str, seed: int) -> None:
    """Child process: build the world once, then answer render requests until told to stop."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and stops us
    _tune_allocator()
    from hilsim.sim.scenario import load_scenario
    from hilsim.sim.sonar import ImagingSonar
    from hilsim.sim.sonar_profile import load_sonar_profile

    scenario = load_scenario(scenario_path)
    world = scenario.build_world()
    sonars: dict[str, ImagingSonar] = {}
    cameras: dict[tuple[str, int], Any] = {}
    conn.send(("ready", os.getpid()))
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        req_id, op, args = msg
        try:
            if op == "sonar":
                profile_path, position, rotation, settings, t, frame_index, body = args
                sonar = sonars.get(profile_path)
                if sonar is None:
                    sonar = sonars[profile_path] = ImagingSonar(load_sonar_profile(profile_path), seed=seed)
                t0 = time.perf_counter()
                frame = sonar.render(world, Pose(position, rotation), settings, time=t, frame_index=frame_index)
                seconds = time.perf_counter() - t0
                # the vehicle's altitude: straight down from the body origin
                down = world.cast(np.asarray([body], dtype=float), np.array([[0.0, 0.0, 1.0]]))
                conn.send((req_id, True, (frame, seconds, float(down.t[0]))))
            elif op == "camera":  # a camera picture (the console/recorder ask only while shown/recorded)
                profile_path, position, rotation, t, max_width = args
                cam = cameras.get((profile_path, max_width))
                if cam is None:
                    from dataclasses import replace

                    from hilsim.sim.camera import Camera, load_camera_profile
                    prof = load_camera_profile(profile_path)
                    if max_width and prof.width > max_width:  # same field of view, fewer pixels
                        prof = replace(prof, width=int(max_width),
                                       height=max(1, round(prof.height * max_width / prof.width)))
                    cam = cameras[(profile_path, max_width)] = Camera(prof)
                conn.send((req_id, True, cam.render(world, Pose(position, rotation), time=t).rgb))
            elif op == "altitude":
                (position,) = args
                hits = world.cast(np.asarray([position], dtype=float), np.array([[0.0, 0.0, 1.0]]))
                conn.send((req_id, True, float(hits.t[0])))
            elif op == "move":  # a scripted object motion (the timeline)
                name, position, rpy = args
                world.place(name, Pose.from_xyz_rpy(position, rpy).matrix(), scenario.object_placement(name).matrix())
                conn.send((req_id, True, None))
            elif op == "crash":  # for tests of the restart path
                os._exit(3)
            elif op == "hang":
                time.sleep(float(args[0]))
                conn.send((req_id, True, None))
            else:
                conn.send((req_id, False, f"unknown op {op!r}"))
        except Exception as exc:  # report, keep serving
            conn.send((req_id, False, f"{type(exc).__name__}: {exc}"))


ADAPT_STEP = 0.7    # each level casts this fraction of the rays of the level above
ADAPT_HIGH = 0.7    # a frame taking over this fraction of its budget lowers the ray count ...
ADAPT_TARGET = 0.5  # ... by the levels that bring it to about this fraction (cost ~ rays)
ADAPT_LOW = 0.35    # frames under this fraction of their budget (one level up stays under HIGH) ...
ADAPT_CALM = 3      # ... this many in a row: one level up


class RayGovernor:
    """Elevation rays per beam for one sonar stream, from how long its frames take.

    full: the requested ray count (the settings'); floor: the fewest (the profile's
    ``min_elevation_rays``). ``rays`` is the count for the next frame; ``update(seconds,
    budget)`` [s] tells how long the last one took against its budget.
    """

    def __init__(self, full: int, floor: int) -> None:
        floor = max(1, min(int(floor), int(full)))
        levels = [int(full)]
        while levels[-1] > floor:
            levels.append(max(floor, min(levels[-1] - 1, round(full * ADAPT_STEP ** len(levels)))))
        self.levels = levels
        self.level = 0
        self.calm = 0

    @property
    def rays(self) -> int:
        return self.levels[self.level]

    def update(self, seconds: float, budget: float) -> None:
        load = seconds / budget if budget > 0 else math.inf
        if load > ADAPT_HIGH:
            steps = max(1, math.ceil(math.log(min(load, 100.0) / ADAPT_TARGET) / math.log(1.0 / ADAPT_STEP)))
            self.level = min(len(self.levels) - 1, self.level + steps)
            self.calm = 0
        elif load < ADAPT_LOW:
            self.calm += 1
            if self.calm >= ADAPT_CALM and self.level > 0:
                self.level -= 1
                self.calm = 0
        else:
            self.calm = 0


class RenderWorker:
    """Parent side of the render worker. One request at a time (frames queue up)."""

    def __init__(self, scenario_path: Path | str, seed: int, timeout: float = 10.0,
                 start_timeout: float = 60.0) -> None:
        self.scenario_path = str(scenario_path)
        self.seed = int(seed)
        self.timeout = float(timeout)
        self.start_timeout = float(start_timeout)
        self.restarts = 0
        self.failures = 0
        self.renders = 0
        self._ctx = mp.get_context("spawn")
        self._proc: Any = None
        self._conn: Connection | None = None
        self._lock = asyncio.Lock()
        self._ids = itertools.count(1)
        self._closed = False
        self.replay: list[tuple[str, tuple[Any, ...]]] = []  # world changes to redo after a restart
        self.governors: dict[tuple[str, int], RayGovernor] = {}  # (profile, requested rays) -> its governor
        self._profiles: dict[str, Any] = {}

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    async def start(self) -> None:
        parent, child = self._ctx.Pipe(duplex=True)
        self._proc = self._ctx.Process(target=_worker_main, args=(child, self.scenario_path, self.seed),
                                       name="hilsim-render", daemon=True)
        self._proc.start()
        child.close()
        self._conn = parent
        try:
            kind, pid = await self._recv(self.start_timeout)
        except RenderFailed:
            raise RenderFailed(f"render worker did not start within {self.start_timeout:.0f} s") from None
        log.info("render worker started (pid %s)", pid)
        for op, args in self.replay:  # a restarted worker gets the world as it was
            self._conn.send((0, op, args))
            await self._recv(self.start_timeout)

    async def _recv(self, timeout: float) -> Any:
        """Wait for one message on the pipe without blocking the loop."""
        conn = self._conn
        if conn is None:
            raise RenderFailed("render worker is not running")
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[None] = loop.create_future()
        fd = conn.fileno()
        loop.add_reader(fd, lambda: fut.done() or fut.set_result(None))
        try:
            await asyncio.wait_for(fut, timeout)
        except asyncio.TimeoutError:
            raise RenderFailed(f"render worker did not answer within {timeout:.1f} s") from None
        finally:
            loop.remove_reader(fd)
        try:
            return conn.recv()
        except (EOFError, OSError) as exc:
            raise RenderFailed(f"render worker died ({exc or 'pipe closed'})") from None

    async def _restart(self, why: str) -> None:
        self.restarts += 1
        code = self._proc.exitcode if self._proc is not None else None
        log.error("render worker %s (exit code %s); restarting it (restart #%d)", why, code, self.restarts)
        self._kill()
        if not self._closed:
            await self.start()

    def _kill(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except OSError:
                pass
            self._conn = None
        if self._proc is not None:
            if self._proc.is_alive():
                self._proc.kill()
            self._proc.join(timeout=5)
            self._proc = None

    async def call(self, op: str, *args: Any, timeout: float | None = None) -> Any:
        """Send one request, await its reply; RenderFailed on crash/hang (worker restarted)."""
        async with self._lock:
            if self._closed:
                raise RenderFailed("render worker is closed")
            if self._conn is None:
                await self.start()
            assert self._conn is not None
            req_id = next(self._ids)
            try:
                self._conn.send((req_id, op, args))
                while True:
                    rid, ok, payload = await self._recv(self.timeout if timeout is None else timeout)
                    if rid == req_id:
                        break
            except (RenderFailed, OSError, EOFError) as exc:
                self.failures += 1
                await self._restart(f"failed: {exc}")
                raise RenderFailed(str(exc)) from None
            if not ok:
                self.failures += 1
                raise RenderFailed(f"render error: {payload}")
            return payload

    async def render_sonar(self, profile_path: str, pose: Pose, settings: Any, t: float, frame_index: int,
                           body_position: Any = (0.0, 0.0, 0.0), budget_s: float | None = None) -> Any:
        """(SonarFrame, render seconds, altitude [m] below ``body_position``) for a sonar
        profile at a sensor pose. With ``budget_s`` [s] (the frame's period) the ray count
        adapts (module docstring); the frame's ``settings.elevation_rays`` says which was used."""
        governor = None
        if budget_s is not None and budget_s > 0:
            profile = self._profiles.get(profile_path)
            if profile is None:
                from hilsim.sim.sonar_profile import load_sonar_profile

                profile = self._profiles[profile_path] = load_sonar_profile(profile_path)
            if profile.adaptive_rays:
                if settings is None:
                    settings = profile.default_settings()
                key = (profile_path, int(settings.elevation_rays))
                governor = self.governors.get(key)
                if governor is None:
                    governor = self.governors[key] = RayGovernor(key[1], profile.min_elevation_rays)
                if governor.rays != settings.elevation_rays:
                    # k times fewer rays cover k times wider footprints: the cap of a footprint's
                    # width [bins] (grazing incidence) scales with them, or bins would stay empty
                    settings = settings.replace(elevation_rays=governor.rays, spread_max_bins=settings.spread_max_bins
                                                * settings.elevation_rays / governor.rays)
        t0 = time.perf_counter()
        try:
            out = await self.call("sonar", profile_path, np.asarray(pose.position), np.asarray(pose.rotation),
                                  settings, t, frame_index, np.asarray(body_position, dtype=float))
        except RenderFailed:
            if governor is not None and budget_s is not None:
                governor.update(2.0 * budget_s, budget_s)
            raise
        if governor is not None and budget_s is not None:
            before, took = governor.rays, time.perf_counter() - t0
            governor.update(took, budget_s)
            if governor.rays != before:
                log.debug("%s: %d elevation rays per beam from the next frame (this one took %.0f ms of %.0f)",
                          Path(profile_path).stem, governor.rays, 1e3 * took, 1e3 * budget_s)
        self.renders += 1
        return out

    async def change_world(self, op: str, *args: Any) -> None:
        """A lasting change of the world (``move``): applied now and after any restart."""
        self.replay.append((op, args))
        if self._conn is not None:
            await self.call(op, *args)

    async def close(self) -> None:
        self._closed = True
        if self._conn is not None:
            try:
                self._conn.send(None)
            except OSError:
                pass
        if self._proc is not None:
            await asyncio.get_running_loop().run_in_executor(None, self._proc.join, 3.0)
        self._kill()
