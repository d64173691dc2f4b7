"""What the benchmarks share: the bridge as a subprocess, plain socket clients, latency figures.

The scripts import it as ``_common`` (``python benchmarks/bench_x.py`` puts this folder first
on ``sys.path``, and processes they spawn inherit it). It prints nothing by itself except
:func:`report_latency`.
"""

from __future__ import annotations

import json
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Callable, Protocol, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DDF_HEADER = 1024                 # [bytes] the DDF stream's file header, and each frame's header
DDF_FRAME = DDF_HEADER + 96 * 512  # [bytes] a frame of the water tank's DIDSON-like sonar (96 beams x 512 samples)
DDF_RAYS_OFFSET = 732             # int32 in a DDF frame header: elevation rays per beam of the frame (0: not stated)


class Flag(Protocol):
    """A ``threading.Event`` or a ``multiprocessing`` one."""

    def is_set(self) -> bool: ...


def host_port(address: str) -> tuple[str, int]:
    """``"host:port"`` (an endpoint's address) -> (host, port)."""
    host, port = address.rsplit(":", 1)
    return host, int(port)


def recv_exact(s: socket.socket, n: int) -> bytes:
    """Exactly ``n`` bytes from ``s``; EOFError if the peer closes first."""
    buf = bytearray()
    while len(buf) < n:
        chunk = s.recv(n - len(buf))
        if not chunk:
            raise EOFError
        buf += chunk
    return bytes(buf)


def pct(xs: Sequence[float], q: float) -> float:
    """The ``q`` quantile (0..1) of ``xs``, nearest rank from below; NaN when ``xs`` is empty."""
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))] if s else float("nan")


def report_latency(label: str, rtts: Sequence[float], width: int = 44) -> None:
    """One line: ``label``, the count and p50 / p99 / max of ``rtts`` [s] in ms."""
    if not rtts:
        print(f"  {label:<{width}} no replies")
        return
    print(f"  {label:<{width}} n={len(rtts):5d}  p50 {pct(rtts, 0.5) * 1e3:6.2f} ms  p99 {pct(rtts, 0.99) * 1e3:6.2f} ms"
          f"  max {max(rtts) * 1e3:6.2f} ms")


@dataclass
class BridgeProcess:
    """A ``hilsim run`` subprocess: ``endpoints`` is its endpoints table, its output is in ``log_path``."""

    proc: subprocess.Popen[bytes]
    endpoints: list[dict[str, Any]]
    log_path: Path
    _log: IO[bytes]

    @property
    def pid(self) -> int:
        return self.proc.pid

    def endpoint(self, protocol: str, **match: Any) -> dict[str, Any]:
        """The first endpoint of ``protocol`` whose other keys equal ``match`` (``transport="tcp"`` ...)."""
        return next(e for e in self.endpoints if e["protocol"] == protocol
                    and all(e.get(k) == v for k, v in match.items()))

    def stop(self, timeout: float = 15.0) -> None:
        """SIGTERM, then SIGKILL if it has not ended within ``timeout`` [s]."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._log.close()


def start_bridge(tmp: Path, *run_args: str, cwd: Path | None = None,
                 command: Callable[[list[str]], list[str]] | None = None, timeout: float = 60.0) -> BridgeProcess:
    """``python -m hilsim run RUN_ARGS --endpoints TMP/endpoints.json`` in a subprocess, its output in
    ``TMP/bridge.log``; returns once the endpoints file is written. ``command``: the command line to
    run instead, given the CLI's arguments (``["run", ...]``). SystemExit with the log if the bridge
    ends or ``timeout`` [s] passes first."""
    ep_file = tmp / "endpoints.json"
    log_path = tmp / "bridge.log"
    argv = ["run", *run_args, "--endpoints", str(ep_file)]
    cmd = [sys.executable, "-m", "hilsim", *argv] if command is None else command(argv)
    log = open(log_path, "wb")
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=cwd)
    bridge = BridgeProcess(proc, [], log_path, log)
    deadline = time.monotonic() + timeout
    while not ep_file.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            bridge.stop()
            raise SystemExit(f"bridge did not start:\n{log_path.read_text(errors='replace')}")
        time.sleep(0.05)
    bridge.endpoints = json.loads(ep_file.read_text())
    return bridge


def stream_sonar(addr: tuple[str, int], rate: int, stop: Flag, counter: list[int] | None = None,
                 timeout: float = 0.5) -> None:
    """A DDF client asking for ``RATE rate`` frames/s and reading until ``stop`` is set or the bridge
    closes (load beside what a benchmark measures); adds the bytes it got to ``counter[0]``."""
    s = socket.create_connection(addr)
    s.sendall(f"RATE {rate}\n".encode())
    s.settimeout(timeout)
    while not stop.is_set():
        try:
            data = s.recv(1 << 20)
        except socket.timeout:
            continue
        if not data:
            break
        if counter is not None:
            counter[0] += len(data)
    s.close()


def ddf_clients(addr: tuple[str, int], n: int, seconds: float) -> dict[str, Any]:
    """``n`` plain socket clients (threads) read the DDF stream for ``seconds`` [s].

    Returns ``rates`` (frames/s each client received; clients with fewer than 3 frames left out),
    ``rate_min``, ``rate_mean``; the ping-to-client latency [ms], the arrival (wall clock) of a
    frame's last byte minus the ping time in its header, over those clients' frames but their first:
    ``p50``, ``p99``, ``max``; ``frames`` received in all; ``rays``: (min, median, max) of the
    elevation rays per beam the frames state ((0, 0.0, 0) when none)."""
    results: list[list[tuple[float, float, int]]] = [[] for _ in range(n)]
    stop = time.monotonic() + seconds

    def client(k: int) -> None:
        s = socket.create_connection(addr, timeout=10)
        recv_exact(s, DDF_HEADER)
        while time.monotonic() < stop:
            raw = recv_exact(s, DDF_FRAME)
            arrived = time.time()
            us = struct.unpack_from("<Q", raw, 4)[0]
            rays = struct.unpack_from("<i", raw, DDF_RAYS_OFFSET)[0]
            results[k].append((arrived, arrived - us / 1e6, rays))
        s.close()

    ts = [threading.Thread(target=client, args=(k,)) for k in range(n)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    rates: list[float] = []
    lat: list[float] = []
    rays: list[int] = []
    for r in results:
        if len(r) > 2:
            rates.append((len(r) - 1) / (r[-1][0] - r[0][0]))
            lat += [x[1] for x in r[1:]]
            rays += [x[2] for x in r]
    lat_ms = np.array(lat) * 1e3
    return {"clients": n, "rate_min": min(rates), "rate_mean": float(np.mean(rates)), "rates": rates,
            "p50": float(np.percentile(lat_ms, 50)), "p99": float(np.percentile(lat_ms, 99)),
            "max": float(lat_ms.max()), "frames": sum(len(r) for r in results),
            "rays": (min(rays), float(np.median(rays)), max(rays)) if rays else (0, 0.0, 0)}
