"""Navigation devices (DVL, GNSS, Ping1D): reply latency and report-rate accuracy; prints figures, never pass/fail.

Run: ``.venv/bin/python benchmarks/bench_navigation.py [--seconds S]``.

The bridge runs as ``hilsim run`` in its own process on the water-tank scenario
(its DVL, GNSS and Ping1D altimeter, among every other device), with a client
streaming the DIDSON-like sonar (``RATE 15``) throughout, so the render worker
and the frame shipping compete with the navigation devices. The clients speak
the wire protocols from the vendors' documents with raw sockets and pyserial
(no hilsim import on the client side), so their own overhead stays small.

Figures, per device:

* reply latency p50/p99/max: DVL ``get_config`` over TCP (one in flight), DVL
  ``wcv`` on its pty (115200 baud), Ping1D ``general_request`` of ``distance``
  on its pty (115200 baud);
* report rates against the device's nominal ones, measured at the client from
  arrival times and from the devices' own time stamps: DVL velocity reports
  (10 Hz at the tank's 1.15 m altitude), DVL dead reckoning (5 Hz), GNSS epochs
  (the scenario's 1 Hz), Ping1D ``profile`` stream (10 Hz); with the inter-arrival
  jitter (p99 |interval - nominal|).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import struct
import tempfile
import threading
import time
from pathlib import Path

import serial

from _common import ROOT, host_port, pct, report_latency, start_bridge, stream_sonar


def rate(label: str, arrivals: list[float], stamps: list[float], nominal: float) -> None:
    if len(arrivals) < 3:
        print(f"  {label:<44} too few reports ({len(arrivals)})")
        return
    span = arrivals[-1] - arrivals[0]
    r_arr = (len(arrivals) - 1) / span
    r_stamp = (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 2 and stamps[-1] > stamps[0] else float("nan")
    gaps = [b - a for a, b in zip(arrivals, arrivals[1:])]
    jitter = pct([abs(g - 1.0 / nominal) for g in gaps], 0.99)
    print(f"  {label:<44} nominal {nominal:5.2f} Hz  arrivals {r_arr:6.3f} Hz ({100 * (r_arr / nominal - 1):+5.2f} %)"
          f"  stamps {r_stamp:6.3f} Hz  jitter p99 {jitter * 1e3:6.2f} ms")


def dvl_json(addr: tuple[str, int], seconds: float) -> None:
    s = socket.create_connection(addr)
    s.settimeout(2.0)
    buf = b""
    vel_t, vel_s, pos_t, pos_s = [], [], [], []

    def read_line() -> dict:
        nonlocal buf
        while b"\n" not in buf:
            buf += s.recv(65536)
        line, buf = buf.split(b"\n", 1)
        now = time.monotonic()
        m = json.loads(line)
        if m.get("type") == "velocity":
            vel_t.append(now)
            vel_s.append(m["time_of_validity"] / 1e6)
        elif m.get("type") == "position_local":
            pos_t.append(now)
            pos_s.append(m["ts"])
        return m

    end = time.monotonic() + seconds
    while time.monotonic() < end:
        read_line()
    rtts = []
    for _ in range(300):
        t0 = time.perf_counter()
        s.sendall(b'{"command": "get_config"}\n')
        while read_line().get("response_to") != "get_config":
            pass
        rtts.append(time.perf_counter() - t0)
    s.close()
    report_latency("DVL JSON get_config (TCP)", rtts)
    rate("DVL velocity reports (1.15 m: range mode 1)", vel_t, vel_s, 10.0)
    rate("DVL dead-reckoning reports", pos_t, pos_s, 5.0)


def dvl_serial(path: str) -> None:
    rtts = []
    with serial.Serial(path, 115200, timeout=1.0) as port:
        buf = b""
        for _ in range(100):
            port.reset_input_buffer()
            buf = b""
            t0 = time.perf_counter()
            port.write(b"wcv\n")
            while b"wrv," not in buf or not buf.split(b"wrv,", 1)[1].count(b"\n"):
                buf += port.read(port.in_waiting or 1)
            rtts.append(time.perf_counter() - t0)
    report_latency("DVL serial wcv (pty, 115200 baud)", rtts)


def gnss(path: str, baud: int, nominal: float, seconds: float) -> None:
    arrivals, stamps = [], []
    with serial.Serial(path, baud, timeout=0.5) as port:
        port.reset_input_buffer()
        end, buf = time.monotonic() + seconds, b""
        while time.monotonic() < end:
            buf += port.read(port.in_waiting or 1)
            while b"\r\n" in buf:
                line, buf = buf.split(b"\r\n", 1)
                if line[3:6] == b"GGA":
                    arrivals.append(time.monotonic())
                    hms = line.split(b",")[1]
                    if hms:
                        stamps.append(int(hms[:2]) * 3600 + int(hms[2:4]) * 60 + float(hms[4:]))
    rate(f"GNSS epochs (GGA, {baud} baud)", arrivals, stamps, nominal)


def ping_packet(mid: int, payload: bytes = b"") -> bytes:
    head = b"BR" + struct.pack("<HHBB", len(payload), mid, 0, 0) + payload
    return head + struct.pack("<H", sum(head) & 0xFFFF)


def read_packet(port: serial.Serial, buf: bytearray) -> tuple[int, bytes]:
    while True:
        i = buf.find(b"BR")
        if i >= 0 and len(buf) >= i + 8:
            n, mid = struct.unpack_from("<HH", buf, i + 2)
            if len(buf) >= i + 10 + n:
                payload = bytes(buf[i + 8:i + 8 + n])
                del buf[:i + 10 + n]
                return mid, payload
        buf += port.read(port.in_waiting or 1)


def ping1d(path: str, seconds: float) -> None:
    rtts = []
    with serial.Serial(path, 115200, timeout=1.0) as port:
        buf = bytearray()
        for _ in range(200):
            t0 = time.perf_counter()
            port.write(ping_packet(6, struct.pack("<H", 1212)))
            while read_packet(port, buf)[0] != 1212:
                pass
            rtts.append(time.perf_counter() - t0)
        report_latency("Ping1D general_request distance (pty)", rtts)
        port.write(ping_packet(1400, struct.pack("<H", 1300)))
        arrivals, stamps = [], []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            mid, payload = read_packet(port, buf)
            if mid == 1300:
                arrivals.append(time.monotonic())
                stamps.append(struct.unpack_from("<I", payload, 8)[0] * 0.1)   # ping_number x 100 ms
        port.write(ping_packet(1401, struct.pack("<H", 1300)))
    rate("Ping1D profile stream (continuous_start)", arrivals, stamps, 10.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="length of each rate measurement [s] (default 5)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-nav-"))
    bridge = start_bridge(tmp, "water_tank", "--status-interval", "0", "--log-level", "WARNING", "--no-console",
                          "--pty-dir", str(tmp / "run"), cwd=ROOT)
    stop = threading.Event()
    try:
        ep = bridge.endpoint

        def hp(e: dict) -> tuple[str, int]:
            return host_port(e["address"])

        print(f"hilsim navigation benchmark: {platform.python_implementation()} {platform.python_version()}, "
              f"{os.cpu_count()} CPUs; load average {os.getloadavg()[0]:.2f}; bridge pid {bridge.pid}; "
              f"{args.seconds:g} s per rate run")
        got = [0]
        t = threading.Thread(target=stream_sonar, args=(hp(ep("ddf-stream")), 15, stop, got), daemon=True)
        t.start()
        time.sleep(1.5)
        b0, t0 = got[0], time.monotonic()
        print("With the DDF sonar streaming (RATE 15):")
        dvl_json(hp(ep("dvl-json")), args.seconds)
        dvl_serial(ep("dvl-serial")["address"])
        g = ep("nmea-gnss")
        gnss(g["address"], int(g["baudrate"]), float(g["rate_hz"]), max(args.seconds, 4.0))
        ping1d(ep("ping1d")["address"], args.seconds)
        frame = 1024 + 96 * 512
        print(f"  ({(got[0] - b0) / frame / (time.monotonic() - t0):.1f} sonar frames/s received meanwhile; "
              f"load average now {os.getloadavg()[0]:.2f})")
    finally:
        stop.set()
        bridge.stop()


if __name__ == "__main__":
    main()
