"""What open console pages cost the bridge: DDF stream and Modbus latency without and with pages.

Starts ``hilsim run`` on the water tank (real-time clock, console on a free port) and measures
over ``--seconds``, first with no page open, then with ``--pages`` pages open (WebSocket clients in
another process that behave like the page: they show the camera and read everything):
  * 8 DDF clients: frames/s per client, ping-to-client latency p50 / p99 [ms] (as bench_bridge);
  * a Modbus TCP poller reading the Keller's P1 at 100 Hz: round trip p50 / p99 [ms];
  * with pages: what each page received (states/s, sonar frames/s, camera pictures/s, drops).
Prints figures; never passes or fails.
Usage: python benchmarks/bench_console.py [--seconds 10] [--pages 3]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from _common import ROOT, ddf_clients, host_port, recv_exact, start_bridge

READ_P1 = struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, 0x0002, 2)   # tid 1, unit 1, fc 3, P1
REPLY = 6 + 1 + 1 + 1 + 4


def modbus_poller(addr: tuple[str, int], seconds: float, out: list[float]) -> None:
    s = socket.create_connection(addr)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    end = time.monotonic() + seconds
    t_next = time.perf_counter()
    while time.monotonic() < end:
        t0 = time.perf_counter()
        s.sendall(READ_P1)
        recv_exact(s, REPLY)
        out.append(time.perf_counter() - t0)
        t_next += 0.01
        time.sleep(max(0.0, t_next - time.perf_counter()))
    s.close()


def measure(ddf: tuple[str, int], modbus: tuple[str, int], seconds: float) -> dict:
    rtts: list[float] = []
    th = threading.Thread(target=modbus_poller, args=(modbus, seconds, rtts))
    th.start()
    r = ddf_clients(ddf, 8, seconds)
    th.join()
    ms = np.array(rtts) * 1e3
    r.update(modbus_p50=float(np.percentile(ms, 50)), modbus_p99=float(np.percentile(ms, 99)))
    return r


async def _pages(url: str, n: int, seconds: float, camera: bool = True) -> list[dict]:
    import aiohttp

    async def one() -> dict:
        got = {"state": 0, "sonar": 0, "camera": 0, "bytes": 0}
        async with aiohttp.ClientSession() as s, s.ws_connect(url + "ws", max_msg_size=0) as ws:
            await ws.send_str(json.dumps({"op": "camera", "show": camera}))
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                try:
                    msg = await asyncio.wait_for(ws.receive(), max(0.01, end - time.monotonic()))
                except asyncio.TimeoutError:
                    break
                if msg.type == aiohttp.WSMsgType.TEXT:
                    got["bytes"] += len(msg.data)
                    if '"type":"state"' in msg.data[:20]:
                        got["state"] += 1
                        got["console"] = json.loads(msg.data)["devices"].get("console", {})
                elif msg.type == aiohttp.WSMsgType.BINARY:
                    got["bytes"] += len(msg.data)
                    (k,) = struct.unpack(">I", msg.data[:4])
                    got[json.loads(msg.data[4:4 + k])["type"]] += 1
                else:
                    break
        return got

    return list(await asyncio.gather(*(one() for _ in range(n))))


def page_main(url: str, n: int, seconds: float, camera: bool) -> None:
    """Child process: ``n`` page-like WebSocket clients for ``seconds``; prints what they got as JSON."""
    print(json.dumps(asyncio.run(_pages(url, n, seconds, camera))), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--pages", type=int, default=3)
    ap.add_argument("--no-camera", action="store_true", help="the pages hide the camera (default: they show it)")
    ap.add_argument("--page-client", nargs=3, metavar=("URL", "N", "SECONDS"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.page_client:
        page_main(args.page_client[0], int(args.page_client[1]), float(args.page_client[2]), not args.no_camera)
        return
    tmp = Path(tempfile.mkdtemp())
    bridge = start_bridge(tmp, "--log-level", "WARNING", "--status-interval", "0", "--console", "0", cwd=ROOT)
    try:
        eps = bridge.endpoints
        ddf = bridge.endpoint("ddf-stream")
        mb = next(x for x in eps if x["device"] == "depth" and x["transport"] == "tcp")
        ddf_addr, modbus = host_port(ddf["address"]), host_port(mb["address"])
        url = next(x for x in eps if x["device"] == "console")["url"]
        time.sleep(2.0)
        print(f"water tank, DDF at {ddf['frame_rate_hz']} Hz to 8 clients, Modbus P1 at 100 Hz; "
              f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}")
        base = measure(ddf_addr, modbus, args.seconds)
        pages = subprocess.Popen([sys.executable, __file__, "--page-client", url, str(args.pages),
                                  str(args.seconds + 3.0)] + (["--no-camera"] if args.no_camera else []),
                                 stdout=subprocess.PIPE, text=True)
        time.sleep(1.5)
        with_pages = measure(ddf_addr, modbus, args.seconds)
        got = json.loads(pages.communicate(timeout=60)[0] or "[]")
        shown = "hidden" if args.no_camera else "shown"
        for label, r in (("no page", base), (f"{args.pages} pages (camera {shown})", with_pages)):
            print(f"  {label}: {r['rate_mean']:.1f} frames/s per DDF client (slowest {r['rate_min']:.1f}); "
                  f"ping-to-client p50 {r['p50']:.1f} ms, p99 {r['p99']:.1f} ms; Modbus p50 {r['modbus_p50']:.2f} ms, "
                  f"p99 {r['modbus_p99']:.2f} ms")
        print(f"  pages vs none: DDF p99 {100 * (with_pages['p99'] / base['p99'] - 1):+.1f} %, "
              f"Modbus p99 {with_pages['modbus_p99'] - base['modbus_p99']:+.2f} ms; "
              f"load {os.getloadavg()[0]:.2f}")
        span = args.seconds + 3.0
        c = got[0].get("console", {}) if got else {}
        if c.get("ticks"):
            print(f"  the console's own time on the bridge's loop: {c['tick_ms'] / c['ticks']:.2f} ms per update "
                  f"(10 a second for all pages: {c['tick_ms'] / c['ticks']:.1f} % of a core)")
        for i, g in enumerate(got):
            print(f"  page {i + 1}: {g['state'] / span:.1f} states/s, {g['sonar'] / span:.1f} sonar frames/s, "
                  f"{g['camera'] / span:.1f} camera pictures/s, {g['bytes'] / span / 1e6:.2f} MB/s")
    finally:
        bridge.stop()


if __name__ == "__main__":
    main()
