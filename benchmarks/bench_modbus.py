"""Modbus request round trips and throughput: prints figures, never pass/fail.

Run: ``.venv/bin/python benchmarks/bench_modbus.py [--seconds S]``.

The bridge runs as ``hilsim run`` in its own process on the water-tank scenario
(with its DIDSON-like sonar ``sonar_ddf``) plus a Keller depth sensor on Modbus
TCP and RTU. Clients are separate processes, as real ones would be; the
round-trip time is measured by a raw-socket poller (send a 12-byte read of P1,
wait for the 13-byte answer) so the client's own overhead stays small.

Figures:

1. p50/p99/max round trip at 100 Hz polling, sonar idle (nobody connected);
2. the same with a client streaming the sonar at 30 frames/s (``RATE 30``; the
   render worker renders every frame, the bridge ships 50 kB frames);
3. the same plus 15 other clients polling at 100 Hz (16 in all; the 15 share
   one process, asyncio);
4. the same with 4 clients flooding (pipelining 32 requests, as fast as they
   can; each throttled to its 1000 requests/s budget) and 2 sending random
   bytes, reconnecting when dropped (one process);
5. requests/s one server sustains, sonar streaming: 8 closed-loop clients (one
   request in flight each) on the default device (each client's budget is 1000
   requests/s) and on a second Keller with ``max_client_rate = 0``, and 8
   pipelining clients (32 in flight each) on the latter;
6. RTU round trip on the pty at 115200 baud (paced replies).

Goal (issue 6): p99 under 5 ms at 100 Hz polling with the sonar streaming.
``--clock-margin-ms 0`` reruns everything with the scheduler's clock never
sleeping synchronously inside the event loop (an experiment knob: the bridge
is otherwise unchanged).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import socket
import struct
import sys
import tempfile
import threading
import time
from pathlib import Path

from _common import ROOT, host_port, recv_exact, report_latency, start_bridge, stream_sonar

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DEVICES = """
[[devices]]
name = "bench_depth"
protocol = "modbus-keller"
transport = ["tcp", "rtu"]
baudrate = 115200
max_clients = 64

[[devices]]
name = "bench_depth_unlimited"
protocol = "modbus-keller"
transport = ["tcp"]
max_clients = 64
max_client_rate = 0
"""
READ_P1 = struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, 0x0002, 2)   # tid 1, unit 1, fc 3, P1
REPLY = 6 + 1 + 1 + 1 + 4
CLOCK_PATCH = """
import functools, sys
import hilsim.runtime.clock as clock
clock.RealTimeClock.__init__ = functools.partialmethod(clock.RealTimeClock.__init__, async_margin={margin!r})
from hilsim.cli import main
sys.exit(main({argv!r}))
"""


def poller(addr: tuple[str, int], rate: float, count: int, out: "mp.Queue[list[float]] | None") -> None:
    """Poll P1 at ``rate`` Hz; put the round trips [s] on ``out``."""
    s = socket.create_connection(addr)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    rtts = []
    t_next = time.perf_counter()
    for _ in range(count):
        t0 = time.perf_counter()
        s.sendall(READ_P1)
        recv_exact(s, REPLY)
        rtts.append(time.perf_counter() - t0)
        t_next += 1.0 / rate
        time.sleep(max(0.0, t_next - time.perf_counter()))
    s.close()
    if out is not None:
        out.put(rtts)


def flooder(addr: tuple[str, int], seconds: float, depth: int, garbage: bool, out: "mp.Queue[int] | None") -> None:
    """Pipeline ``depth`` requests per write as fast as possible (or random bytes); count replies."""
    end = time.monotonic() + seconds
    burst = READ_P1 * depth
    n = 0
    while time.monotonic() < end:
        try:
            s = socket.create_connection(addr)
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            while time.monotonic() < end:
                if garbage:
                    s.sendall(os.urandom(256))
                    if not s.recv(4096):
                        break
                else:
                    s.sendall(burst)
                    recv_exact(s, REPLY * depth)
                    n += depth
            s.close()
        except (OSError, EOFError):
            time.sleep(0.001)
    if out is not None:
        out.put(n)


def many_pollers(addr: tuple[str, int], n: int, rate: float, count: int) -> None:
    """``n`` pollers at ``rate`` Hz in one process (asyncio), as background load."""
    import asyncio

    async def one() -> None:
        r, w = await asyncio.open_connection(*addr)
        t_next = time.perf_counter()
        for _ in range(count):
            w.write(READ_P1)
            await r.readexactly(REPLY)
            t_next += 1.0 / rate
            await asyncio.sleep(max(0.0, t_next - time.perf_counter()))
        w.close()

    async def run() -> None:
        await asyncio.gather(*(one() for _ in range(n)))

    asyncio.run(run())


def many_flooders(addr: tuple[str, int], seconds: float, depth: int, n_flood: int, n_garbage: int,
                  out: "mp.Queue[int]") -> None:
    """``n_flood`` clients pipelining ``depth`` requests as fast as they can and ``n_garbage``
    clients sending random bytes (reconnecting when dropped), in one process (asyncio)."""
    import asyncio

    replies = [0]

    async def one(garbage: bool) -> None:
        end = time.monotonic() + seconds
        burst = READ_P1 * depth
        while time.monotonic() < end:
            try:
                r, w = await asyncio.open_connection(*addr)
                while time.monotonic() < end:
                    if garbage:
                        w.write(os.urandom(256))
                        if not await r.read(4096):
                            break
                    else:
                        w.write(burst)
                        await r.readexactly(REPLY * depth)
                        replies[0] += depth
                w.close()
            except (OSError, asyncio.IncompleteReadError):
                await asyncio.sleep(0.001)

    async def run() -> None:
        await asyncio.gather(*(one(i >= n_flood) for i in range(n_flood + n_garbage)))

    asyncio.run(run())
    out.put(replies[0])


def report(label: str, rtts: list[float]) -> None:
    report_latency(label, rtts, width=46)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="length of each latency run [s] (default 10)")
    ap.add_argument("--clock-margin-ms", type=float, default=None,
                    help="experiment: run the bridge with RealTimeClock(async_margin=this) instead of its "
                         "default (the synchronous sleep the scheduler ends each wait with, inside the loop)")
    args = ap.parse_args()
    n_polls = int(args.seconds * 100)
    tmp = Path(tempfile.mkdtemp(prefix="bench-modbus-"))
    scenario = tmp / "scenario.toml"
    scenario.write_text((ROOT / "scenarios/water_tank/scenario.toml").read_text() + DEVICES)

    def patched(argv: list[str]) -> list[str]:
        """The same command with the clock's default margin changed before the bridge builds it."""
        return [sys.executable, "-c", CLOCK_PATCH.format(margin=args.clock_margin_ms / 1e3, argv=argv)]

    bridge = start_bridge(tmp, str(scenario), "--status-interval", "0", "--log-level", "WARNING", cwd=tmp,
                          command=None if args.clock_margin_ms is None else patched)
    try:
        eps = bridge.endpoints

        def addr(proto: str, transport: str = "tcp", device: str | None = None) -> tuple[str, int]:
            e = next(e for e in eps if e["protocol"] == proto and e["transport"] == transport
                     and (device is None or e["device"] == device))
            return host_port(e["address"])

        modbus = addr("modbus-keller", device="bench_depth")
        unlimited = addr("modbus-keller", device="bench_depth_unlimited")
        rtu_path = next(e["address"] for e in eps if e["device"] == "bench_depth" and e["transport"] == "pty")
        print(f"hilsim Modbus benchmark: {platform.python_implementation()} {platform.python_version()}, "
              f"{os.cpu_count()} CPUs, {platform.machine()}; bridge pid {bridge.pid}; {args.seconds:g} s per run"
              + ("" if args.clock_margin_ms is None else f"; clock async_margin {args.clock_margin_ms:g} ms"))
        ctx = mp.get_context("spawn")

        def measured(rate: float = 100.0) -> list[float]:
            q: mp.Queue[list[float]] = ctx.Queue()
            p = ctx.Process(target=poller, args=(modbus, rate, n_polls, q))
            p.start()
            rtts = q.get(timeout=args.seconds * 3 + 30)
            p.join()
            return rtts

        poller(modbus, 100.0, 50, None)  # warm up
        print("TCP round trip, one poller at 100 Hz (reading P1):")
        report("sonar idle", measured())

        stop = threading.Event()
        ddf_bytes = [0]
        t = threading.Thread(target=stream_sonar, args=(addr("ddf-stream"), 30, stop, ddf_bytes), daemon=True)
        t.start()
        time.sleep(1.0)
        b0, t0 = ddf_bytes[0], time.monotonic()
        report("sonar streaming (RATE 30)", measured())
        frame_size = 1024 + 96 * 512
        print(f"  ({(ddf_bytes[0] - b0) / frame_size / (time.monotonic() - t0):.1f} sonar frames/s received meanwhile)")

        others = ctx.Process(target=many_pollers, args=(modbus, 15, 100.0, n_polls + 100))
        others.start()
        time.sleep(0.5)
        report("sonar streaming + 15 other pollers at 100 Hz", measured())
        others.join()

        fq: mp.Queue[int] = ctx.Queue()
        floods = ctx.Process(target=many_flooders, args=(modbus, args.seconds + 2, 32, 4, 2, fq))
        floods.start()
        time.sleep(0.5)
        report("sonar + 4 flooding + 2 garbage clients", measured())
        flood_n = fq.get(timeout=60)
        floods.join()
        print(f"  (the flooders got {flood_n / (args.seconds + 2):.0f} replies/s meanwhile)")

        print("Throughput of one Modbus TCP server (sonar streaming; max_client_rate 1000/s vs no limit):")
        for label, target, depth in (("8 clients, 1 in flight each, limited", modbus, 1),
                                     ("8 clients, 1 in flight each, no limit", unlimited, 1),
                                     ("8 clients, 32 in flight each, no limit", unlimited, 32)):
            tq: mp.Queue[int] = ctx.Queue()
            secs = min(args.seconds, 5.0)
            ps = [ctx.Process(target=flooder, args=(target, secs, depth, False, tq)) for _ in range(8)]
            for p in ps:
                p.start()
            total = sum(tq.get(timeout=60) for _ in ps)
            for p in ps:
                p.join()
            print(f"  {label:<46} {total / secs:8.0f} requests/s")
        stop.set()
        t.join(5)

        print("RTU round trip on the pty at 115200 baud (8-byte request, 9-byte reply):")
        rtts = rtu_rtt(rtu_path, 200)
        report("one master polling at 50 Hz", rtts)
        print(f"  (the 9-byte reply alone takes {9 * 10 / 115200 * 1e3:.2f} ms on the wire)")
    finally:
        bridge.stop()


def rtu_rtt(path: str, count: int) -> list[float]:
    import termios
    import tty

    from pymodbus.framer import FramerRTU

    frame = bytes([1, 3, 0, 2, 0, 2])
    frame += FramerRTU.compute_CRC(frame).to_bytes(2, "big")
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd, termios.TCSANOW)
    rtts = []
    try:
        for _ in range(count):
            t0 = time.perf_counter()
            os.write(fd, frame)
            got = b""
            while len(got) < 9:
                got += os.read(fd, 64)
            rtts.append(time.perf_counter() - t0)
            time.sleep(0.02)
    finally:
        os.close(fd)
    return rtts


if __name__ == "__main__":
    main()
