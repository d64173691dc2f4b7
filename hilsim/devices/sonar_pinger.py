"""Per-client sonar pinging shared by the Oculus and ARIS devices.

Each client of a vendor sonar sets its own ping configuration (range, rate,
beams ...). :class:`ClientPinger` holds one entry per pinging client and one
scheduler event, present only while some entry pings (a protocol nobody uses
costs nothing). At each tick the due entries are grouped by their render
key (profile + settings): one render per group serves every client in it,
and a client with the same settings whose ping falls due within half its
period comes along (its frame is a little early; its rate is kept), so any
number of identical clients cost one render per period, whatever their phase.

One batch renders at a time. Pings that fall due meanwhile wait, one per
client (no queue): when the batch ends the pinger takes every entry due by
then, so each waiting client is served next, in turn, and a client busy
with costly settings cannot starve another. A slow renderer thus lowers
every client's rate alike and never builds a backlog; whole periods a client
lost that way are counted in ``busy_skips``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Awaitable, Callable, Hashable

from hilsim.devices.base import DeviceContext, Periodic, RenderedFrame, RenderFailed
from hilsim.sim.sonar_profile import SonarSettings

log = logging.getLogger(__name__)


@dataclass
class PingEntry:
    """One client's ping configuration. period [s]; next_due [s] simulation time."""

    owner: Any
    profile: str
    settings: SonarSettings
    period: float
    next_due: float = 0.0
    cid: int = -1  # the key it is registered under
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def key(self) -> Hashable:
        return (self.profile, self.settings)


OnFrame = Callable[[list[PingEntry], RenderedFrame, int], None]


class ClientPinger:
    """Schedules renders for per-client configurations (see module docstring).

    on_frame(entries, rendered, frame_index) is called for each rendered group.
    tick_hz: the scheduler event's rate [Hz] (the finest ping period served).
    """

    def __init__(self, ctx: DeviceContext, name: str, mount: str, on_frame: OnFrame,
                 tick_hz: float = 40.0) -> None:
        self.ctx = ctx
        self.name = name
        self.mount = mount
        self.on_frame = on_frame
        self.tick = 1.0 / tick_hz
        self.entries: dict[int, PingEntry] = {}
        self._event: Periodic | None = None
        self._busy = False
        self.frame_index = 0
        self.renders = 0
        self.busy_skips = 0
        self.failures = 0
        self.rays = 0

    def set(self, key: int, entry: PingEntry | None) -> None:
        """Set (or with None remove) the entry of client ``key``; a new entry pings at once."""
        if entry is None or entry.period <= 0.0:
            self.entries.pop(key, None)
        else:
            old = self.entries.get(key)
            entry.next_due = old.next_due if old is not None else self.ctx.now()
            entry.cid = key
            self.entries[key] = entry
        self._update_event()

    def _update_event(self) -> None:
        if self.entries and self._event is None:
            self._event = self.ctx.every(f"{self.name}.ping", self.tick, self._on_tick, priority=20,
                                         tolerance=self.tick)
        elif not self.entries and self._event is not None:
            self._event.cancel()
            self._event = None

    async def close(self) -> None:
        """Stop pinging (a render in flight finds its entries gone and sends nothing)."""
        self.entries.clear()
        self._update_event()

    def _on_tick(self, t: float) -> Awaitable[Any] | None:
        if self._busy:
            return None   # due pings wait for the batch in flight, which takes them when it ends
        batch = self._take_due(t)
        if not batch:
            return None
        self._busy = True
        return self.ctx.defer(self._render_batches(batch))

    def _take_due(self, t: float) -> list[list[PingEntry]]:
        """The entries due at ``t`` [s], grouped by render key, with the entries of the same key due within
        half their period; each one's next ping scheduled (whole periods already missed are skipped and
        counted, never caught up in a burst)."""
        due = [e for e in self.entries.values() if e.next_due <= t + 1e-9]
        if not due:
            return []
        groups: dict[Hashable, list[PingEntry]] = {}
        for e in due:
            nxt = e.next_due + e.period
            if nxt <= t:
                self.busy_skips += int((t - e.next_due) / e.period)
                nxt = t + e.period
            e.next_due = nxt
            groups.setdefault(e.key, []).append(e)
        # same settings, due soon: served now and put on the group's schedule, so identical clients
        # converge on one render per period (the early frame is at most half a period early; the
        # interval to the next one is a whole period, so the rate holds)
        taken = {id(e) for e in due}
        for e in self.entries.values():
            g = groups.get(e.key)
            if g is not None and id(e) not in taken and e.next_due - t <= 0.5 * e.period:
                same = [x.next_due for x in g if x.period == e.period]
                e.next_due = min(same) if same else t + e.period
                g.append(e)
        return list(groups.values())

    async def _render_batches(self, batch: list[list[PingEntry]]) -> None:
        try:
            while batch:
                for group in batch:
                    await self._render_group(group)
                batch = self._take_due(self.ctx.now())   # whatever fell due meanwhile, every client once
        finally:
            self._busy = False

    async def _render_group(self, group: list[PingEntry]) -> None:
        head = group[0]
        index = self.frame_index
        self.frame_index += 1
        try:
            r = await self.ctx.render(self.mount, head.profile, head.settings, frame_index=index,
                                      budget_s=min(e.period for e in group))
        except RenderFailed as exc:
            self.failures += 1
            log.warning("%s: ping %d lost: %s", self.name, index, exc)
            return
        self.renders += 1
        self.rays = r.rays  # elevation rays per beam of the last frame (status line)
        live = [e for e in group if self.entries.get(e.cid) is e]
        if live:
            self.on_frame(live, r, index)


def publish_frame(device: Any, r: RenderedFrame, index: int) -> None:
    """Publish a frame a sonar device served on its ``sonar`` topic (once per render, whatever the
    number of clients it went to), for the console and recorders."""
    if not device.observed("sonar"):
        return
    f = r.frame
    device.publish("sonar", {"t": float(r.state.time), "image": f.image, "range_min": float(f.range_min),
                             "range_max": float(f.range_max), "azimuths": f.azimuths,
                             "gain_db": float(f.settings.gain_db), "frame_index": int(index),
                             "rays": int(r.rays)})
