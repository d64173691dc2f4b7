"""Start ``hilsim run`` as a real subprocess for tests and read DDF with struct (not our decoder)."""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FILE_HDR = 1024
FRAME_HDR = 1024


@dataclass
class BridgeProc:
    proc: subprocess.Popen
    endpoints: list[dict]
    log_path: Path

    def endpoint(self, protocol: str) -> dict:
        return next(e for e in self.endpoints if e["protocol"] == protocol)

    def tcp(self, protocol: str) -> tuple[str, int]:
        host, port = self.endpoint(protocol)["address"].rsplit(":", 1)
        return host, int(port)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self, timeout: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        return self.proc.returncode


def start_bridge(tmp: Path, *args: str, env: dict | None = None, timeout: float = 60.0) -> BridgeProc:
    """``hilsim run --endpoints FILE ARGS`` in a subprocess; waits for the endpoints file."""
    ep = tmp / "endpoints.json"
    log_path = tmp / "bridge.log"
    e = dict(os.environ)
    e.update(env or {})
    proc = subprocess.Popen([sys.executable, "-m", "hilsim", "run", "--endpoints", str(ep), *args],
                            stdout=open(log_path, "wb"), stderr=subprocess.STDOUT, env=e, cwd=tmp)
    deadline = time.monotonic() + timeout
    while not ep.exists():
        if proc.poll() is not None:
            raise RuntimeError(f"bridge exited with {proc.returncode}:\n{log_path.read_text()}")
        if time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError(f"bridge did not come up:\n{log_path.read_text()}")
        time.sleep(0.05)
    return BridgeProc(proc, json.loads(ep.read_text()), log_path)


def recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise EOFError(f"connection closed after {len(buf)} of {n} bytes")
        buf += chunk
    return bytes(buf)


@dataclass
class Frame:
    number: int
    time_us: int
    depth: float
    altitude: float
    heading: float
    window_start: int
    window_length: int
    samples: bytes      # numbeams x samples, beam fastest, beam 0 starboard
    raw: bytes          # the whole frame as received


def read_file_header(sock: socket.socket) -> dict:
    h = recv_exact(sock, FILE_HDR)
    return {"raw": h, "signature": h[:4], "numframes": struct.unpack_from("<i", h, 4)[0],
            "numbeams": struct.unpack_from("<i", h, 16)[0], "samples": struct.unpack_from("<i", h, 24)[0],
            "windowstart": struct.unpack_from("<i", h, 32)[0], "windowlength": struct.unpack_from("<i", h, 36)[0]}


def read_frame(sock: socket.socket, numbeams: int, samples: int) -> Frame:
    hdr = recv_exact(sock, FRAME_HDR)
    data = recv_exact(sock, numbeams * samples)
    return parse_frame(hdr + data, numbeams)


def parse_frame(raw: bytes, numbeams: int) -> Frame:
    return Frame(number=struct.unpack_from("<i", raw, 0)[0], time_us=struct.unpack_from("<Q", raw, 4)[0],
                 depth=struct.unpack_from("<f", raw, 128)[0], altitude=struct.unpack_from("<f", raw, 132)[0],
                 heading=struct.unpack_from("<f", raw, 152)[0],
                 window_start=struct.unpack_from("<i", raw, 52)[0], window_length=struct.unpack_from("<i", raw, 56)[0],
                 samples=raw[FRAME_HDR:], raw=raw)
