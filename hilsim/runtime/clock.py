"""Clocks the scheduler runs against: real time, or virtual time (as fast as possible).

A clock's time is seconds [s] since its epoch (for :class:`RealTimeClock`,
its creation or :meth:`RealTimeClock.reset`). The scheduler asks a clock to
wait until an *absolute* deadline, never for a duration, so waiting errors do
not accumulate: over an hour the ticks stay on the grid.
"""

from __future__ import annotations

import asyncio
import math
import time
from abc import ABC, abstractmethod
from typing import Callable


class Clock(ABC):
    """A time source the scheduler can wait on. ``realtime`` tells which kind."""

    realtime: bool = False

    @abstractmethod
    def now(self) -> float:
        """[s] current time since the clock's epoch."""

    @abstractmethod
    def sleep_until(self, deadline: float) -> None:
        """Block until ``now() >= deadline`` [s] (returns at once if already past)."""

    @abstractmethod
    async def sleep_until_async(self, deadline: float) -> None:
        """Wait in asyncio until ``now() >= deadline`` [s]; other tasks run meanwhile."""


class VirtualClock(Clock):
    """Virtual time: waiting jumps the time to the deadline at once (never backwards).

    For tests and batch runs: a 60 s scenario takes as long as its callbacks.
    """

    realtime = False

    def __init__(self, start: float = 0.0):
        self._t = float(start)

    def now(self) -> float:
        return self._t

    def sleep_until(self, deadline: float) -> None:
        if deadline > self._t:
            self._t = float(deadline)

    async def sleep_until_async(self, deadline: float) -> None:
        self.sleep_until(deadline)
        await asyncio.sleep(0)  # let the loop's other tasks run between ticks


class RealTimeClock(Clock):
    """Wall-clock time from ``time.monotonic`` (or ``source``) since the epoch.

    ``sleep_until`` sleeps to the absolute deadline with ``time.sleep`` (on
    Linux its overshoot is a fraction of a millisecond) and re-checks, so it
    never returns early. ``sleep_until_async`` awaits ``asyncio.sleep`` until
    ``async_margin`` [s] before the deadline (asyncio's timers round up to
    whole milliseconds) and then sleeps the remainder synchronously, blocking
    the loop at most ``async_margin``; 0 leaves the timing to asyncio alone.
    """

    realtime = True

    def __init__(self, source: Callable[[], float] = time.monotonic, async_margin: float = 0.0015):
        self._source = source
        self.async_margin = float(async_margin)
        self._epoch = source()

    def reset(self) -> None:
        """Make ``now()`` zero again (call right before a run starts)."""
        self._epoch = self._source()

    def now(self) -> float:
        return self._source() - self._epoch

    def sleep_until(self, deadline: float) -> None:
        while True:
            remaining = deadline - self.now()
            if remaining <= 0:
                return
            time.sleep(remaining)

    async def sleep_until_async(self, deadline: float) -> None:
        remaining = deadline - self.now()
        if remaining > self.async_margin:
            await asyncio.sleep(remaining - self.async_margin)
        else:
            await asyncio.sleep(0)
        self.sleep_until(deadline)


class ScaledClock(RealTimeClock):
    """Real time running ``scale`` times faster than the wall clock [sim s per wall s].

    For clients outside the process that pace themselves by the simulation's
    timestamps (a control stack under test in CI): deadlines stay absolute,
    so nothing drifts, and every wait sleeps ``1 / scale`` as long.
    """

    def __init__(self, scale: float, async_margin: float = 0.0):
        if not (scale > 0 and math.isfinite(scale)):
            raise ValueError(f"time scale must be a positive number, got {scale}")
        self.scale = float(scale)
        super().__init__(source=lambda: time.monotonic() * self.scale, async_margin=async_margin)

    def sleep_until(self, deadline: float) -> None:
        while True:
            remaining = deadline - self.now()
            if remaining <= 0:
                return
            time.sleep(remaining / self.scale)

    async def sleep_until_async(self, deadline: float) -> None:
        remaining = deadline - self.now()
        if remaining > 0:
            await asyncio.sleep(remaining / self.scale)
        else:
            await asyncio.sleep(0)
        self.sleep_until(deadline)


class LockstepClock(Clock):
    """Virtual time that a peer hands out step by step (ArduPilot's JSON backend in lockstep).

    The scheduler's waits end only once the peer has granted the time (:meth:`advance`);
    :meth:`advance` returns when everything due up to the new time has run (the scheduler
    waits for a deadline past it). While the peer is silent, simulated time stands still and
    the event loop keeps serving every other link.
    """

    realtime = False

    def __init__(self) -> None:
        self._t = 0.0
        self._granted = 0.0
        self._wake: asyncio.Future[None] | None = None
        self._idle: asyncio.Future[None] | None = None
        self._woken = False

    @property
    def granted(self) -> float:
        """[s] the time the peer has allowed so far."""
        return self._granted

    def now(self) -> float:
        return self._t

    def sleep_until(self, deadline: float) -> None:
        if deadline > self._granted + 1e-12:
            raise RuntimeError("a lockstep clock cannot wait synchronously past the time it was granted")
        self._t = max(self._t, deadline)

    async def sleep_until_async(self, deadline: float) -> None:
        """Wait until the peer has granted ``deadline``; returns early (time unchanged) when
        :meth:`wake` is called to stop the scheduler."""
        loop = asyncio.get_running_loop()
        self._woken = False
        while deadline > self._granted + 1e-12:
            if self._idle is not None and not self._idle.done():
                self._idle.set_result(None)  # all that was due by the granted time has run
            self._wake = loop.create_future()
            await self._wake
            if self._woken:
                return
        if deadline > self._t:
            self._t = float(deadline)
        await asyncio.sleep(0)

    def wake(self) -> None:
        """End a wait without granting time (the scheduler is stopping)."""
        self._woken = True
        if self._wake is not None and not self._wake.done():
            self._wake.set_result(None)
        if self._idle is not None and not self._idle.done():
            self._idle.set_result(None)

    async def advance(self, dt: float) -> None:
        """Grant ``dt`` [s] more; returns once the scheduler has run everything due by then."""
        if not (dt >= 0 and math.isfinite(dt)):
            raise ValueError(f"a lockstep step must be a finite non-negative time, got {dt}")
        self._granted += dt
        self._idle = asyncio.get_running_loop().create_future()
        if self._wake is not None and not self._wake.done():
            self._wake.set_result(None)
        await self._idle
        self._t = max(self._t, self._granted)

    def reset(self) -> None:
        """Nothing to do: the peer's grants are the only source of time."""
