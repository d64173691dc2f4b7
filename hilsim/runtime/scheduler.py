"""One scheduler of periodic events against a swappable clock.

An event has a period [s], an offset [s] and a callback taking the tick's
*scheduled* time [s] (not the wall time: the same events give the same
results in real time and in virtual time). Deadlines are the absolute grid
``offset + k * period`` with integer ``k``, so nothing drifts. Events due at
the same time run by ``priority`` (lower first), then in the order added.

Late ticks are counted, never bunched: a tick runs once, however late, and
the next one is the latest grid point already due (run at once, late) or the
next one ahead; grid points passed over are counted as skipped. Lateness is
``clock.now() - deadline`` just before the callback; a tick is *late* when
that exceeds the event's tolerance.

:meth:`Scheduler.run` runs synchronously (fast mode, tests); the live bridge
awaits :meth:`Scheduler.run_async` in the asyncio loop that also serves its
links. :class:`VehicleLoop` binds the physics and the navigation sensors.
"""

from __future__ import annotations

import heapq
import inspect
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Sequence

from hilsim.runtime.clock import Clock, VirtualClock

if TYPE_CHECKING:
    from hilsim.sim.contact import ContactInfo, ContactModel
    from hilsim.sim.state import VehicleState
    from hilsim.sim.thrusters import ThrusterSet
    from hilsim.sim.vehicle import Current, Vehicle

DEFAULT_PHYSICS_RATE = 200.0  # [Hz]
MAX_STEP = 0.02               # [s] the longest physics step (late ticks are split into steps this long)
ONE_SHOT = 1e12               # [s] the period of an event that runs once (it is removed when it fires)


@dataclass
class EventStats:
    """Timing of one event: ticks run, late ticks, skipped grid points, and
    lateness [s] (max and sum; every value in ``lateness`` when recorded)."""

    ticks: int = 0
    late: int = 0
    skipped: int = 0
    max_lateness: float = 0.0
    total_lateness: float = 0.0
    lateness: list[float] | None = None

    @property
    def mean_lateness(self) -> float:
        """[s] mean lateness over the ticks run."""
        return self.total_lateness / self.ticks if self.ticks else 0.0


@dataclass(eq=False)
class PeriodicEvent:
    """A periodic event: ``callback(t)`` at ``t = offset + k * period`` [s].

    tolerance [s]: lateness above it counts as late (default min(1 ms, period / 4)).
    A callback may return an awaitable; :meth:`Scheduler.run_async` awaits it.
    """

    name: str
    period: float
    callback: Callable[[float], Any]
    offset: float = 0.0
    priority: int = 0
    tolerance: float = -1.0
    stats: EventStats = field(default_factory=EventStats)
    index: int = 0
    active: bool = True

    def deadline(self, k: int) -> float:
        """[s] the k-th grid time."""
        return self.offset + k * self.period


class Scheduler:
    """Runs periodic events against ``clock`` (default a :class:`VirtualClock`).

    record_lateness: keep every tick's lateness in ``EventStats.lateness``.
    late_fraction: if set, an event added without a tolerance counts a tick as late when it
    runs more than this fraction of its period after its deadline (the bridge uses 0.5: on
    an asyncio loop a millisecond of timer jitter is normal and harmless; half a period is
    not); if None, the tolerance is min(1 ms, period / 4).
    """

    def __init__(self, clock: Clock | None = None, record_lateness: bool = False,
                 late_fraction: float | None = None):
        self.clock = clock if clock is not None else VirtualClock()
        self.record_lateness = record_lateness
        self.late_fraction = late_fraction
        self.events: list[PeriodicEvent] = []
        self._heap: list[tuple[float, int, int, PeriodicEvent]] = []
        self._seq = 0
        self._stopping = False
        self._started = False

    def add(self, name: str, period: float, callback: Callable[[float], Any], offset: float = 0.0,
            priority: int = 0, tolerance: float | None = None) -> PeriodicEvent:
        """Add an event; period, offset and tolerance in [s]. Added before the
        first run, its first tick is at ``offset`` (reset a real clock right
        before running); added later, at the first grid point not yet past."""
        if not (period > 0 and math.isfinite(period)):
            raise ValueError(f"event {name!r}: period must be a positive number of seconds, got {period}")
        # the default 1 ms is wall time: on a clock running k times faster it is k ms of sim time
        scale = float(getattr(self.clock, "scale", 1.0))
        if tolerance is not None:
            tol = float(tolerance)
        elif self.late_fraction is not None:
            tol = self.late_fraction * period
        else:
            tol = min(1e-3 * scale, period / 4)
        ev = PeriodicEvent(name, float(period), callback, float(offset), int(priority), tol)
        if self.record_lateness:
            ev.stats.lateness = []
        if self._started:
            ev.index = max(0, math.ceil((self.clock.now() - ev.offset) / ev.period - 1e-9))
        self.events.append(ev)
        self._push(ev)
        return ev

    def remove(self, event: PeriodicEvent) -> None:
        """Stop an event; its pending tick is dropped."""
        event.active = False
        if event in self.events:
            self.events.remove(event)

    def stop(self) -> None:
        """Make a running :meth:`run` / :meth:`run_async` return after the current tick (a clock
        that waits for someone else's time, :class:`~hilsim.runtime.clock.LockstepClock`, is woken)."""
        self._stopping = True
        wake = getattr(self.clock, "wake", None)
        if wake is not None:
            wake()

    def _push(self, ev: PeriodicEvent) -> None:
        self._seq += 1
        heapq.heappush(self._heap, (ev.deadline(ev.index), ev.priority, self._seq, ev))

    def _next(self, until: float | None) -> tuple[float, PeriodicEvent] | None:
        while self._heap:
            t, _, _, ev = self._heap[0]
            if not ev.active:
                heapq.heappop(self._heap)
                continue
            if until is not None and t > until + 1e-12:
                return None
            heapq.heappop(self._heap)
            return t, ev
        return None

    def _begin(self, t: float, ev: PeriodicEvent) -> None:
        lateness = max(0.0, self.clock.now() - t)
        s = ev.stats
        s.ticks += 1
        s.total_lateness += lateness
        s.max_lateness = max(s.max_lateness, lateness)
        if lateness > ev.tolerance:
            s.late += 1
        if s.lateness is not None:
            s.lateness.append(lateness)

    def _reschedule(self, ev: PeriodicEvent) -> None:
        if not ev.active:
            return
        due = math.floor((self.clock.now() - ev.offset) / ev.period + 1e-9)
        nxt = max(ev.index + 1, due)
        ev.stats.skipped += nxt - ev.index - 1
        ev.index = nxt
        self._push(ev)

    def run(self, until: float) -> None:
        """Run every tick with deadline <= ``until`` [s], waiting on the clock
        (instantly for a virtual one), then wait until ``until`` itself.

        The hot loop of fast mode: :meth:`_next`, :meth:`_begin` and
        :meth:`_reschedule` are written out here (same semantics) to save
        about a microsecond per tick."""
        self._stopping = False
        self._started = True
        heap, clock = self._heap, self.clock
        now, sleep_until = clock.now, clock.sleep_until
        pop, push, floor = heapq.heappop, heapq.heappush, math.floor
        limit = until + 1e-12
        while not self._stopping:
            while heap and not heap[0][3].active:
                pop(heap)
            if not heap or heap[0][0] > limit:
                break
            t, _, _, ev = pop(heap)
            sleep_until(t)
            lateness = now() - t
            if lateness < 0.0:
                lateness = 0.0
            st = ev.stats
            st.ticks += 1
            st.total_lateness += lateness
            if lateness > st.max_lateness:
                st.max_lateness = lateness
            if lateness > ev.tolerance:
                st.late += 1
            if st.lateness is not None:
                st.lateness.append(lateness)
            result = ev.callback(t)
            if result is not None and inspect.isawaitable(result):
                if inspect.iscoroutine(result):
                    result.close()
                raise TypeError(f"event {ev.name!r} returned an awaitable; use run_async")
            if ev.active:
                due = floor((now() - ev.offset) / ev.period + 1e-9)
                nxt = ev.index + 1
                if due > nxt:
                    st.skipped += due - nxt
                    nxt = due
                ev.index = nxt
                self._seq += 1
                push(heap, (ev.offset + nxt * ev.period, ev.priority, self._seq, ev))
        if not self._stopping:
            sleep_until(until)

    async def run_async(self, until: float | None = None) -> None:
        """As :meth:`run`, in asyncio: other tasks run while waiting for a deadline.
        ``until`` None runs until :meth:`stop` (or cancellation)."""
        self._stopping = False
        self._started = True
        while not self._stopping:
            nxt = self._next(until)
            if nxt is None:
                if until is None:  # no events yet: wait for some to be added
                    await self.clock.sleep_until_async(self.clock.now() + 0.01)
                    continue
                break
            t, ev = nxt
            await self.clock.sleep_until_async(t)
            if self._stopping and self.clock.now() < t:  # woken to stop before its time: not run
                self._push(ev)
                break
            self._begin(t, ev)
            result = ev.callback(t)
            if inspect.isawaitable(result):
                await result
            self._reschedule(ev)
        if until is not None and not self._stopping:
            await self.clock.sleep_until_async(until)

    def report(self) -> str:
        """One line per event: ticks, late, skipped, max and mean lateness [ms]."""
        lines = []
        for ev in self.events:
            if ev.period >= ONE_SHOT:  # a pending one-shot (Bridge.at), not a periodic event
                continue
            s = ev.stats
            lines.append(f"{ev.name}: {s.ticks} ticks at {1 / ev.period:g} Hz, {s.late} late, "
                         f"{s.skipped} skipped, lateness max {s.max_lateness * 1e3:.3f} ms "
                         f"mean {s.mean_lateness * 1e3:.3f} ms")
        return "\n".join(lines)


class VehicleLoop:
    """The physics and the navigation sensors, as events of a scheduler.

    Physics runs every ``1 / physics_rate`` [s] (priority 0): it integrates
    from the state's time to the tick's time, so a skipped tick lengthens the
    step instead of losing time, then the contact step
    (:class:`hilsim.sim.contact.ContactModel`: the hull against ``world`` and the
    water surface) corrects the state. Each sensor runs at its own rate and offset
    (priority 10, after the physics of the same instant) and passes its
    reading to ``on_reading(sensor, reading)``. ``tick_listeners`` are called
    after every physics tick as ``listener(state, contact_info)`` (the ground truth).
    """

    def __init__(self, vehicle: "Vehicle", thrusters: "ThrusterSet | None", state: "VehicleState",
                 current: "Current | None" = None, physics_rate: float = DEFAULT_PHYSICS_RATE,
                 world: Any = None, contacts: "ContactModel | None" = None):
        from hilsim.sim.contact import ContactModel

        self.vehicle = vehicle
        self.thrusters = thrusters
        self.state = state
        self.current = current
        self.physics_rate = float(physics_rate)
        self.readings: dict[str, Any] = {}
        self.wrench: Sequence[float] = (0.0,) * 6  # used when there are no thrusters
        self.contacts = contacts if contacts is not None else ContactModel.for_profile(vehicle.profile, world)
        self.tick_listeners: list[Callable[["VehicleState", "ContactInfo"], None]] = []

    @property
    def world(self) -> Any:
        """The scene the hull collides with (a :class:`hilsim.sim.world.World`, or None:
        only the water surface). The bridge sets its own."""
        return self.contacts.world

    @world.setter
    def world(self, world: Any) -> None:
        self.contacts.world = world

    @property
    def surface(self) -> bool:
        """Whether the water surface (z = 0) keeps the hull under it."""
        return self.contacts.surface

    @surface.setter
    def surface(self, on: bool) -> None:
        self.contacts.surface = bool(on)

    def physics_tick(self, t: float) -> None:
        """Advance the state to time ``t`` [s], in steps of at most :data:`MAX_STEP` (a tick that
        comes late on a loaded machine is integrated in several steps, never one long one that
        the integrator or the contacts could not take)."""
        dt_all = t - self.state.time
        if dt_all <= 1e-12:
            return
        n = max(1, math.ceil(dt_all / MAX_STEP - 1e-9))
        thrusters = self.thrusters
        for i in range(n):
            state = self.state
            dt = (t - state.time) / (n - i)
            if thrusters is not None:
                new = self.vehicle.step_with_thrusters(state, dt, thrusters, self.current)
            else:
                new = self.vehicle.step(state, dt, self.wrench, self.current)
            self.state = self.contacts.step(state, new, dt)
        new = self.state
        if self.tick_listeners:
            info = self.contacts.last
            for listener in self.tick_listeners:
                listener(new, info)

    def attach(self, scheduler: Scheduler, sensors: Sequence[Any] = (),
               on_reading: Callable[[Any, Any], None] | None = None) -> list[PeriodicEvent]:
        """Register the physics and ``sensors`` (hilsim.sim.navigation sensors) on ``scheduler``."""
        events = [scheduler.add("physics", 1.0 / self.physics_rate, self.physics_tick, priority=0)]
        for sensor in sensors:
            def tick(t: float, sensor: Any = sensor) -> None:
                reading = sensor.sample(self.state)
                self.readings[sensor.name] = reading
                if on_reading is not None:
                    on_reading(sensor, reading)
            events.append(scheduler.add(sensor.name, sensor.period, tick, offset=sensor.offset, priority=10))
        return events
