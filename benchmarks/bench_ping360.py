"""Ping360 through the live bridge, with Blue Robotics' client (brping) over UDP and the pty, while a
DDF client takes the DIDSON-like stream: device_data latency p50/p99 (transducer command -> answer,
wall time at time scale 1) against the device's own timing, and a full sweep's time against the
sweep times measured on a real Ping360 (Blue Robotics forum: 400 pings at 1-gradian steps took
10.74 s at 2 m, 20.57 s at 20 m over Ethernet)."""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hilsim.sim.ping360 import ping_duration  # noqa: E402
from tests.runtime.bridge_helpers import FILE_HDR, FRAME_HDR, recv_exact, start_bridge  # noqa: E402

MEASURED = {88: 10.74, 888: 20.57}  # [s] per 400-ping sweep at 1 gradian, by sample period (2 m, 20 m)


def ddf_reader(address: str, stop: threading.Event, counter: list[int]) -> None:
    host, port = address.rsplit(":", 1)
    s = socket.create_connection((host, int(port)), timeout=5)
    recv_exact(s, FILE_HDR)
    while not stop.is_set():
        try:
            recv_exact(s, FRAME_HDR + 96 * 512)
            counter[0] += 1
        except (OSError, EOFError):  # the bridge stopped
            break
    s.close()


def percentile(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q / 100 * (len(xs) - 1))))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--pings", type=int, default=100, help="transducer commands per latency run")
    ap.add_argument("--sweeps", action="store_true", help="also time full 400-ping sweeps (about 30 s)")
    args = ap.parse_args()
    import brping

    with tempfile.TemporaryDirectory() as tmp:
        bridge = start_bridge(Path(tmp), "--status-interval", "0")
        try:
            ddf = next(e for e in bridge.endpoints if e["protocol"] == "ddf-stream")
            stop, frames = threading.Event(), [0]
            t = threading.Thread(target=ddf_reader, args=(ddf["address"], stop, frames), daemon=True)
            t.start()
            for transport in ("udp", "pty"):
                e = next(x for x in bridge.endpoints if x["protocol"] == "ping360" and x["transport"] == transport)
                p = brping.Ping360()
                if transport == "udp":
                    host, port = e["address"].rsplit(":", 1)
                    p.connect_udp(host, int(port))
                else:
                    p.connect_serial(e["address"], 115200)
                assert p.initialize(), "no answer from the Ping360"
                p.set_number_of_samples(1200)
                p.set_gain_setting(0)
                for period in (88, 888):
                    p.set_sample_period(period)
                    p.transmitAngle(0)
                    lat = []
                    for i in range(1, args.pings + 1):
                        t0 = time.perf_counter()
                        assert p.transmitAngle(i % 400) is not None
                        lat.append(time.perf_counter() - t0)
                    model = ping_duration(0, 1, 1200, period, 11)
                    print(f"{transport} sample_period {period} ({1200 * period * 25e-9 * 1482 / 2:.1f} m): "
                          f"device_data latency p50 {statistics.median(lat) * 1e3:.1f} ms, "
                          f"p99 {percentile(lat, 99) * 1e3:.1f} ms (the device's own time {model * 1e3:.1f} ms)")
                    if args.sweeps and transport == "udp":
                        t0 = time.perf_counter()
                        for a in range(400):
                            p.transmitAngle(a)
                        sweep = time.perf_counter() - t0
                        print(f"  sweep of 400 pings at 1 gradian: {sweep:.2f} s (real Ping360: "
                              f"{MEASURED[period]:.2f} s; {sweep / MEASURED[period]:.2f}x)")
                p.iodev.close()
            stop.set()
            print(f"DDF frames received meanwhile: {frames[0]}; load average {os.getloadavg()[0]:.1f}")
        finally:
            bridge.stop()


if __name__ == "__main__":
    main()
