"""The serial dialects of the depth and IMU sensors: prints figures, never pass/fail.

Run: ``.venv/bin/python benchmarks/bench_serial_sensors.py [--seconds S]``.

The bridge runs as ``hilsim run`` in its own process on the water-tank scenario (with
its DIDSON-like sonar ``sonar_ddf``) plus a Keller depth sensor on an RTU pty at 9600
baud (KELLER bus beside Modbus) and a WitMotion IMU with its UART stream on a pty at
115200 baud. The clients here are written from the vendors' documents (raw fds, struct):

1. KELLER bus F73 (read P1) round trip at 9600 baud, p50/p99/max, one master polling at
   20 Hz, sonar idle then streaming (RATE 30);
2. the WitMotion stream's rate accuracy: after ``unlock; RRATE`` (and RSW = angles +
   quaternion), packets counted for S seconds at 10, 100 and 200 Hz, sonar streaming:
   cycles/s against the asked rate, and the p50/p99 spacing of the angle packets.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import select
import struct
import tempfile
import termios
import time
import tty
from pathlib import Path

from _common import ROOT, host_port, pct, report_latency, start_bridge, stream_sonar

DEVICES = """
[[devices]]
name = "bench_depth"
protocol = "modbus-keller"
transport = ["rtu"]
baudrate = 9600

[[devices]]
name = "bench_imu"
protocol = "modbus-witmotion"
transport = ["uart"]
uart_baudrate = 115200
"""


def keller_crc(body: bytes) -> bytes:
    crc = 0xFFFF
    for b in body:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return bytes([crc >> 8, crc & 0xFF])  # KELLER: high byte first


def open_raw(path: str) -> int:
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd, termios.TCSANOW)
    return fd


def read_exact(fd: int, n: int, timeout: float = 1.0) -> bytes:
    buf = b""
    end = time.monotonic() + timeout
    while len(buf) < n and time.monotonic() < end:
        r, _, _ = select.select([fd], [], [], max(0.0, end - time.monotonic()))
        if r:
            buf += os.read(fd, n - len(buf))
    return buf


def keller_rtts(path: str, count: int, rate: float) -> list[float]:
    fd = open_raw(path)
    try:
        init = bytes([250, 48])
        os.write(fd, init + keller_crc(init))
        read_exact(fd, 10)
        req = bytes([250, 73, 1])
        req += keller_crc(req)
        out = []
        t_next = time.perf_counter()
        for _ in range(count):
            t0 = time.perf_counter()
            os.write(fd, req)
            reply = read_exact(fd, 9)
            if len(reply) == 9 and keller_crc(reply[:7]) == reply[7:]:
                out.append(time.perf_counter() - t0)
            t_next += 1.0 / rate
            time.sleep(max(0.0, t_next - time.perf_counter()))
        return out
    finally:
        os.close(fd)


def wit_rate(path: str, code: int, seconds: float) -> tuple[float, list[float]]:
    """Set RSW = angles + quaternion and RRATE = ``code``; count the cycles for ``seconds``."""
    fd = open_raw(path)
    try:
        for reg, value in ((0x69, 0xB588), (0x02, 1 << 3 | 1 << 9), (0x69, 0xB588), (0x03, code)):
            os.write(fd, bytes([0xFF, 0xAA, reg]) + struct.pack("<H", value))
            time.sleep(0.02)
        time.sleep(0.3)
        termios.tcflush(fd, termios.TCIFLUSH)
        stamps: list[float] = []
        buf = b""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            r, _, _ = select.select([fd], [], [], 0.05)
            if not r:
                continue
            now = time.perf_counter()
            buf += os.read(fd, 4096)
            i = 0
            while i + 11 <= len(buf):
                if buf[i] == 0x55 and sum(buf[i:i + 10]) & 0xFF == buf[i + 10]:
                    if buf[i + 1] == 0x53:
                        stamps.append(now)
                    i += 11
                else:
                    i += 1
            buf = buf[i:]
        gaps = [b - a for a, b in zip(stamps, stamps[1:])]
        return len(stamps) / seconds, gaps
    finally:
        os.close(fd)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="length of each run [s] (default 5)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-serial-"))
    scenario = tmp / "scenario.toml"
    scenario.write_text((ROOT / "scenarios/water_tank/scenario.toml").read_text() + DEVICES)
    bridge = start_bridge(tmp, str(scenario), "--status-interval", "0", "--log-level", "WARNING", cwd=tmp)
    try:
        eps = bridge.endpoints
        keller = next(e["address"] for e in eps if e["device"] == "bench_depth" and e["protocol"] == "keller-bus"
                      and e["transport"] == "pty")
        uart = next(e["address"] for e in eps if e["device"] == "bench_imu" and e["protocol"] == "witmotion-uart")
        ddf = host_port(bridge.endpoint("ddf-stream", transport="tcp")["address"])
        load = os.getloadavg()
        print(f"hilsim serial sensors benchmark: {platform.python_implementation()} {platform.python_version()}, "
              f"{os.cpu_count()} CPUs; load average {load[0]:.2f} {load[1]:.2f}; {args.seconds:g} s per run")
        n = int(args.seconds * 20)
        print("KELLER bus F73 (P1) round trip at 9600 baud (5-byte request, 9-byte reply):")
        report_latency("sonar idle, 20 Hz polling", keller_rtts(keller, n, 20.0))
        ctx = mp.get_context("spawn")
        stop = ctx.Event()
        # the sonar at 30 frames/s from a process of its own: its 1.5 MB/s must not starve the
        # serial readers of the interpreter
        t = ctx.Process(target=stream_sonar, args=(ddf, 30, stop), daemon=True)
        t.start()
        time.sleep(1.0)
        report_latency("sonar streaming (RATE 30), 20 Hz polling", keller_rtts(keller, n, 20.0))
        print(f"  (the 9-byte reply takes {9 * 10 / 9600 * 1e3:.2f} ms on the wire at 9600 baud; the pty does "
              f"not pace the master's request)")
        print("WitMotion UART stream at 115200 baud, angles + quaternion, sonar streaming:")
        for code, hz in ((0x06, 10.0), (0x09, 100.0), (0x0B, 200.0)):
            rate, gaps = wit_rate(uart, code, args.seconds)
            spacing = (f"spacing p50 {pct(gaps, .5) * 1e3:6.2f} ms  p99 {pct(gaps, .99) * 1e3:6.2f} ms"
                       if gaps else "")
            print(f"  RRATE {code:#04x} ({hz:5.0f} Hz): {rate:7.2f} cycles/s ({(rate / hz - 1) * 100:+5.1f} %)  "
                  f"{spacing}")
        stop.set()
        t.join(3)
    finally:
        bridge.stop()


if __name__ == "__main__":
    main()
