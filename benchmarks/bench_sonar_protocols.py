"""Sonar protocols through a running bridge: frames/s and ping-to-client latency, 1 and 4 clients.

Starts the water tank with a DIDSON-like stream (if present), an Oculus and an ARIS device,
all on 127.0.0.1 with free ports, then for each protocol connects N clients (plain
sockets in threads), lets them receive for ``--seconds`` and prints per protocol and N:
frames/s per client (mean), renders/s of the device, and the latency from the ping's
simulation time (mapped to wall time as the device stamps it) to the moment a client
holds the whole frame (median, p95). Prints figures, never passes or fails.

    python benchmarks/bench_sonar_protocols.py [--seconds 5] [--clients 1,4]
"""

from __future__ import annotations

import argparse
import asyncio
import importlib.util
import socket
import statistics
import struct
import sys
import tempfile
import threading
import time
from pathlib import Path

from _common import DDF_HEADER, ROOT, host_port, recv_exact

sys.path.insert(0, str(ROOT))

from hilsim.protocols import aris as ar  # noqa: E402
from hilsim.protocols import oculus as oc  # noqa: E402

HAVE_DDF = importlib.util.find_spec("hilsim.devices.ddf_stream") is not None


def start_bridge(tmp: Path) -> tuple[object, asyncio.AbstractEventLoop, dict, threading.Thread, float]:
    from hilsim.runtime.bridge import Bridge

    text = (ROOT / "scenarios" / "water_tank" / "scenario.toml").read_text().split("\n[[devices]]")[0]
    text += ('\n[[devices]]\nname = "oculus"\nprotocol = "oculus"\nport = 0\nstatus_port = 9\n'
             '\n[[devices]]\nname = "aris"\nprotocol = "aris"\nport = 0\nbeacon_port = 9\nmax_clients = 8\n')
    if HAVE_DDF:
        text += '\n[[devices]]\nname = "ddf"\nprotocol = "ddf-stream"\nport = 0\n'
    (tmp / "scenario.toml").write_text(text)
    box: dict = {}
    ready = threading.Event()

    def serve() -> None:
        async def main() -> None:
            b = Bridge(tmp / "scenario.toml", status_interval=0)
            eps = await b.start()
            box.update(bridge=b, loop=asyncio.get_running_loop(), eps={e.protocol: e for e in eps})
            ready.set()
            try:
                await b.run()
            finally:
                await b.close()

        asyncio.run(main())

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    ready.wait(120)
    b, loop = box["bridge"], box["loop"]

    async def offset() -> float:  # wall clock minus the wall time the devices stamp for "now"
        return time.time() - b.wall_time(b.now())

    off = asyncio.run_coroutine_threadsafe(offset(), loop).result(10)
    return b, loop, box["eps"], th, off


def addr(ep) -> tuple[str, int]:
    return host_port(ep.address)


def oculus_client(ep, seconds: float, out: list, b, off: float) -> None:
    s = socket.create_connection(addr(ep), timeout=10)
    s.sendall(oc.encode_fire(oc.Fire(master_mode=2, ping_rate=oc.PING_RATE_HIGH, flags=0x09, range=4.0, version=2)))
    buf = bytearray()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        buf += s.recv(1 << 20)
        while len(buf) >= 16:
            size = 16 + struct.unpack_from("<I", buf, 10)[0]
            if len(buf) < size:
                break
            if struct.unpack_from("<H", buf, 6)[0] == 0x23:
                t = struct.unpack_from("<d", buf, 153)[0]  # pingStartTime [s sim]
                out.append(time.time() - (b.wall_time(t) + off))
            del buf[:size]
    s.close()


def aris_client(ep, seconds: float, out: list, b, off: float) -> None:
    s = socket.create_connection(addr(ep), timeout=10)
    u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    u.bind(("127.0.0.1", 0))
    u.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    u.settimeout(0.2)
    st = ar.AcousticSettings.for_window(0.83, 5.83, 512, 1482.0, frame_rate=15.0)
    for c in (ar.SetFrameStreamReceiver(u.getsockname()[1]), ar.SetAcoustics(st), ar.Ping()):
        s.sendall(ar.encode_command(c))
    asm = ar.FrameAssembler()
    end = time.monotonic() + seconds
    last = time.monotonic()
    while time.monotonic() < end:
        if time.monotonic() - last > 0.5:
            s.sendall(ar.encode_command(ar.Ping()))
            last = time.monotonic()
        try:
            d = u.recv(65536)
        except socket.timeout:
            continue
        for e in asm.receive_datagram(d):
            if isinstance(e, ar.AssembledFrame):
                out.append(time.time() - struct.unpack_from("<Q", e.header, 4)[0] / 1e6 - off)
    s.close()
    u.close()


def ddf_client(ep, seconds: float, out: list, b, off: float) -> None:
    s = socket.create_connection(addr(ep), timeout=10)
    s.sendall(b"RATE 15\n")
    h = recv_exact(s, DDF_HEADER)
    size = DDF_HEADER + struct.unpack_from("<i", h, 16)[0] * struct.unpack_from("<i", h, 24)[0]
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        f = recv_exact(s, size)
        out.append(time.time() - struct.unpack_from("<Q", f, 4)[0] / 1e6 - off)
    s.close()


CLIENT = {"oculus": oculus_client, "aris": aris_client, "ddf-stream": ddf_client}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--clients", default="1,4")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        b, loop, eps, th, off = start_bridge(Path(tmp))
        print(f"sonar protocols, water tank, {a.seconds:g} s per run (latency: ping's sim time -> whole frame at client)")
        print(f"{'protocol':<11} {'clients':>7} {'frames/s/client':>16} {'renders/s':>10} {'lat med ms':>11} {'lat p95 ms':>11}")
        for proto in (["ddf-stream"] if HAVE_DDF else []) + ["oculus", "aris"]:
            dev = next(d for d in b.devices if d.protocol == proto)
            for n in (int(x) for x in a.clients.split(",")):
                outs: list[list[float]] = [[] for _ in range(n)]
                r0 = getattr(getattr(dev, "pinger", None), "renders", getattr(dev, "frames_rendered", 0))
                ths = [threading.Thread(target=CLIENT[proto], args=(eps[proto], a.seconds, outs[i], b, off))
                       for i in range(n)]
                for t in ths:
                    t.start()
                for t in ths:
                    t.join()
                r1 = getattr(getattr(dev, "pinger", None), "renders", getattr(dev, "frames_rendered", 0))
                lat = sorted(x for o in outs for x in o[1:])  # the first frame may predate the config
                fps = statistics.mean(len(o) for o in outs) / a.seconds
                med = statistics.median(lat) * 1e3 if lat else float("nan")
                p95 = lat[int(0.95 * (len(lat) - 1))] * 1e3 if lat else float("nan")
                print(f"{proto:<11} {n:>7} {fps:>16.1f} {(r1 - r0) / a.seconds:>10.1f} {med:>11.1f} {p95:>11.1f}")
                time.sleep(0.5)
        loop.call_soon_threadsafe(b.stop)
        th.join(30)


if __name__ == "__main__":
    main()
