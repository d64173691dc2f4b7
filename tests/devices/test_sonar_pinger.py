"""The pinging policy shared by the Oculus and ARIS devices (hilsim/devices/sonar_pinger.py), on a
stepped clock with a renderer of known speed: every client gets its share of a slow renderer, and
identical settings share one render per period whatever the clients' phases.

The end-to-end versions (real bridge, real clients) are in tests/runtime/test_abuse.py; this one
pins the policy down deterministically.
"""

from __future__ import annotations

import asyncio
from types import SimpleNamespace
from collections import Counter

from hilsim.devices.sonar_pinger import ClientPinger, PingEntry

TICK = 0.025


class SteppedContext:
    """The slice of DeviceContext the pinger uses: a clock the test steps, a scheduler that only
    records the event, and a renderer that takes ``render_s`` of that clock."""

    def __init__(self, render_s: float) -> None:
        self.t = 0.0
        self.render_s = render_s
        self.renders: list[tuple[float, object]] = []
        self.tasks: set[asyncio.Task] = set()

    def now(self) -> float:
        return self.t

    def every(self, name, period, callback, *, offset=0.0, priority=0, tolerance=None):
        return self  # the test calls the pinger's tick itself; the handle only needs cancel()

    def cancel(self) -> None:
        pass

    def defer(self, coro):
        """As the bridge in real time: the render runs as a task, the tick returns at once."""
        task = asyncio.ensure_future(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return None

    async def render(self, mount, profile, settings, frame_index=0, budget_s=None):
        start = self.t
        while self.t < start + self.render_s - 1e-9:
            await asyncio.sleep(0)
        self.renders.append((start, settings))
        return SimpleNamespace(index=frame_index, rays=1000)


def run(render_s: float, clients: list[tuple[str, float, float]], duration: float) -> tuple[Counter, list]:
    """clients: (settings, period [s], start [s]); returns frames per client and the renders."""
    ctx = SteppedContext(render_s)
    got: Counter = Counter()

    def on_frame(entries, rendered, index):
        for e in entries:
            got[e.owner] += 1

    async def main():
        p = ClientPinger(ctx, "sonar", "mount", on_frame, tick_hz=1 / TICK)
        pending = sorted(enumerate(clients), key=lambda c: c[1][2])
        while ctx.t < duration:
            while pending and pending[0][1][2] <= ctx.t + 1e-9:
                i, (settings, period, _) = pending.pop(0)
                p.set(i, PingEntry(owner=i, profile="prof", settings=settings, period=period))
            p._on_tick(ctx.t)
            for _ in range(5):
                await asyncio.sleep(0)
            ctx.t = round(ctx.t + TICK, 9)
        await p.close()
        for t in list(ctx.tasks):
            t.cancel()
        await asyncio.gather(*ctx.tasks, return_exceptions=True)
        return p

    asyncio.run(main())
    return got, ctx.renders


def test_clients_at_other_phases_share_a_slow_renderer_fairly():
    # two clients, different settings, 2 Hz each, a quarter period apart; a render takes 0.3 s, so the
    # renderer can give 1/0.6 = 1.67 frames/s to each, and neither may be starved by the other's render
    got, renders = run(0.3, [("wide", 0.5, 0.0), ("narrow", 0.5, 0.125)], 20.0)
    rates = [got[i] / 20.0 for i in range(2)]
    assert all(r >= 1.4 for r in rates), rates
    assert abs(rates[0] - rates[1]) <= 0.1, rates


def test_a_fast_renderer_gives_every_client_its_own_rate():
    got, renders = run(0.02, [("a", 0.5, 0.0), ("b", 0.25, 0.1), ("c", 1.0, 0.3)], 20.0)
    for i, period in enumerate((0.5, 0.25, 1.0)):
        assert abs(got[i] - 20.0 / period) <= 2, (i, got[i])


def test_identical_settings_cost_one_render_per_period_whatever_the_phase():
    starts = (0.0, 0.13, 0.23, 0.46)
    got, renders = run(0.05, [("same", 0.5, s) for s in starts], 20.0)
    for i, s in enumerate(starts):
        assert abs(got[i] - (20.0 - s) / 0.5) <= 2, (i, got[i])
    # once all have joined, one render per period serves them all (not one per client)
    late = [r for r in renders if r[0] >= 1.0]
    assert len(late) <= 19.0 / 0.5 + 2, len(late)


def test_a_renderer_slower_than_the_period_skips_whole_periods_without_a_backlog():
    got, renders = run(0.7, [("x", 0.25, 0.0)], 14.0)
    # back to back renders, one frame each, never a burst of stale ones
    assert abs(got[0] - 14.0 / 0.7) <= 2, got[0]
    starts = [r[0] for r in renders]
    assert all(b - a >= 0.7 - 1e-6 for a, b in zip(starts, starts[1:]))


def test_a_taken_vendor_port_falls_back_to_a_free_one(caplog):
    """Oculus and ARIS listen on their vendor's fixed port; if something holds it, the device serves
    on a free port with a warning (the endpoints show where) instead of not starting."""
    import socket

    from hilsim.links.tcp import TcpServer
    from hilsim.links.tcp import serve_with_fallback as serve_vendor_port

    async def main():
        holder = socket.socket()
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        taken = holder.getsockname()[1]
        try:
            server, host, port = await serve_vendor_port("sonar", lambda p: TcpServer("sonar", port=p), taken)
            assert host == "127.0.0.1" and port not in (0, taken)
            r, w = await asyncio.open_connection(host, port)      # it serves there
            w.close()
            await server.close()
        finally:
            holder.close()

    with caplog.at_level("WARNING"):
        asyncio.run(main())
    assert "is taken; serving on a free port instead" in caplog.text
