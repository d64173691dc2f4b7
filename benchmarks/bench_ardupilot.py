"""ArduPilot JSON backend in lockstep: servo packets answered per second, alone and with a sonar streaming.

Starts ``hilsim run`` on the ArduSub pool (a temporary copy: the ardupilot device on a
free port and, for the second run, a DIDSON-like stream of the pool's sonar at 15 Hz
of simulated time with a client reading it), then plays ArduPilot: one servo packet,
wait for the reply, next frame_count (frame_rate 1200 Hz, ArduPilot's default physics
rate), for ``--seconds`` of wall time. Prints frames answered per second (goal >= 1200:
ArduSub then runs at real time or faster), the reply latency p50/p99, and the sonar
frames the client received. Never passes or fails.

Usage: ``.venv/bin/python benchmarks/bench_ardupilot.py [--seconds 10]``
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
POOL = ROOT / "scenarios" / "ardusub_pool" / "scenario.toml"
DDF_HEADER, DDF_FRAME = 1024, 1024 + 96 * 512


def scenario(folder: Path, sonar: bool) -> Path:
    text = POOL.read_text().split("# ---- devices")[0].replace('profile = "oculus_m750d"', 'profile = "didson_hf"')
    text += '\n[[devices]]\nname = "ardupilot"\nprotocol = "ardupilot-json"\nport = 0\n'
    if sonar:
        text += '\n[[devices]]\nname = "sonar_ddf"\nprotocol = "ddf-stream"\nsensor = "sonar"\nport = 0\n'
    path = folder / ("pool_sonar" if sonar else "pool") / "scenario.toml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def start(path: Path, tmp: Path) -> tuple[subprocess.Popen[bytes], list[dict]]:
    endpoints = tmp / f"{path.parent.name}.json"
    proc = subprocess.Popen([sys.executable, "-m", "hilsim", "run", str(path), "--endpoints", str(endpoints),
                             "--log-level", "WARNING"], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while not endpoints.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"hilsim run did not start: {proc.stderr.read().decode() if proc.stderr else ''}")
        time.sleep(0.1)
    time.sleep(0.2)
    eps = json.loads(endpoints.read_text())
    return proc, eps if isinstance(eps, list) else eps.get("endpoints", [])


def port_of(eps: list[dict], protocol: str) -> int:
    return int(next(e for e in eps if e["protocol"] == protocol)["address"].rsplit(":", 1)[1])


def sonar_reader(port: int, stop: threading.Event, got: list[float]) -> None:
    s = socket.create_connection(("127.0.0.1", port), timeout=30)
    buf = bytearray()
    need = DDF_HEADER
    while not stop.is_set():
        try:
            chunk = s.recv(1 << 20)
        except socket.timeout:
            continue
        if not chunk:
            break
        buf += chunk
        while len(buf) >= need:
            del buf[:need]
            if need == DDF_FRAME:
                got.append(time.monotonic())
            need = DDF_FRAME
    s.close()


def play(port: int, seconds: float) -> tuple[int, np.ndarray]:
    """ArduPilot's side: packet, wait for the reply, next frame. Frames answered, latencies [s]."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(5.0)
    addr = ("127.0.0.1", port)
    pwm = [1500, 1500, 1500, 1500, 1600, 1600] + [0] * 10
    lat = []
    count = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        count += 1
        t0 = time.perf_counter()
        sock.sendto(struct.pack("<HHI16H", 18458, 1200, count, *pwm), addr)
        reply = sock.recv(65536)
        lat.append(time.perf_counter() - t0)
        assert reply.startswith(b"\n{") and reply.endswith(b"}\n")
    sock.close()
    return count, np.array(lat)


def measure(tmp: Path, sonar: bool, seconds: float) -> None:
    proc, eps = start(scenario(tmp, sonar), tmp)
    stop, frames = threading.Event(), []
    reader = None
    try:
        if sonar:
            reader = threading.Thread(target=sonar_reader, args=(port_of(eps, "ddf-stream"), stop, frames))
            reader.start()
        play(port_of(eps, "ardupilot-json"), 1.0)  # warm up
        t0 = time.monotonic()
        n, lat = play(port_of(eps, "ardupilot-json"), seconds)
        wall = time.monotonic() - t0
        stop.set()
        p50, p99 = np.percentile(lat, [50, 99]) * 1e3
        sim = n / 1200.0
        line = (f"  {'with sonar' if sonar else 'alone':10s} {n / wall:7.0f} frames/s answered "
                f"({n / wall / 1200:4.2f}x ArduSub's real time at 1200 Hz)  reply p50 {p50:.2f} ms  p99 {p99:.2f} ms")
        if sonar:
            inside = [t for t in frames if t >= t0]
            line += f"  sonar {len(inside) / wall:.1f} frames/s received ({len(inside) / sim:.1f} per simulated s)"
        print(line, flush=True)
    finally:
        stop.set()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
        if reader is not None:
            reader.join(5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    args = ap.parse_args()
    print(f"ArduPilot JSON lockstep benchmark (python {sys.version.split()[0]}, {os.cpu_count()} cpus, "
          f"load {os.getloadavg()[0]:.2f})")
    with tempfile.TemporaryDirectory(prefix="hilsim-bench-ap-") as tmp:
        measure(Path(tmp), False, args.seconds)
        measure(Path(tmp), True, args.seconds)
    print(f"  load average {os.getloadavg()[0]:.2f} (other processes share these cores)")


if __name__ == "__main__":
    main()
