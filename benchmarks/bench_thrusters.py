"""Thruster CAN benchmark: command-to-telemetry latency and sustained frame rate, per transport.

Starts ``hilsim run`` (real-time clock) on the water tank with one VESC CAN device
(8 ESCs, controller ids 1..8, STATUS_1/4/5 at ``--status-hz``) on the socketcand
server, then on the slcan pty, and drives it with unmodified python-can clients
in this process (the bridge runs in its own process, as in use):

* latency: SET_RPM to controller 1 alternating between two set-points; the time
  from sending the command to receiving the first STATUS_1 of that ESC whose
  ERPM has moved towards the new set-point (>= 2 % of the step). It includes
  the wait for the next status tick (uniform over the status period), the
  physics tick (5 ms at 200 Hz) and the transport. p50 / p99 / max [ms].
* rate: commands for 8 thrusters at 100 Hz each (800 frames/s) plus the
  telemetry (8 x 3 x status-hz frames/s) for ``--seconds``, then 2x, 4x, 8x and
  16x the command rate; for each: frames sent / applied by the device, dropped
  (the bus's per-client budget at 1 Mbit/s, and full queues), and the
  telemetry received. Counters come from the bridge's status lines.

Prints figures; never passes or fails.
Usage: python benchmarks/bench_thrusters.py [--seconds 10] [--trials 100] [--status-hz 50]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import logging

import can
import cantools
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hilsim.protocols.vesc_can import dbc_path  # noqa: E402


def scenario(tmp: Path, transport: str, status_hz: float) -> Path:
    text = (ROOT / "scenarios" / "water_tank" / "scenario.toml").read_text()
    cut = text.find("[[devices]]")
    text = text[:cut] if cut >= 0 else text
    text += f"""
[[devices]]
name = "vesc_can"
protocol = "vesc-can"
transport = "{transport}"
channel = "can0"
status_rate_hz = {status_hz}
"""
    p = tmp / f"scenario_{transport}.toml"
    p.write_text(text)
    return p


class BridgeProc:
    def __init__(self, tmp: Path, scen: Path) -> None:
        self.ep = tmp / f"{scen.stem}.endpoints.json"
        self.log_path = tmp / f"{scen.stem}.log"
        self.proc = subprocess.Popen([sys.executable, "-m", "hilsim", "run", "--endpoints", str(self.ep),
                                      "--status-interval", "0.5", str(scen)],
                                     stdout=open(self.log_path, "wb"), stderr=subprocess.STDOUT, cwd=tmp)
        deadline = time.monotonic() + 60
        while not self.ep.exists():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(self.log_path.read_text())
            time.sleep(0.05)
        self.endpoint = json.loads(self.ep.read_text())[0]

    def counters(self) -> dict[str, float]:
        """The last status line's counters of the vesc_can device."""
        lines = [ln for ln in self.log_path.read_text(errors="replace").splitlines() if "vesc_can(" in ln]
        if not lines:
            return {}
        body = re.search(r"vesc_can\(([^)]*)\)", lines[-1])
        out = {}
        for part in (body.group(1).split(", ") if body else []):
            k, _, v = part.rpartition(" ")
            out[k] = float(v)
        return out

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def open_client(endpoint: dict) -> can.BusABC:
    if endpoint["transport"] == "socketcand":
        return can.Bus(interface="socketcand", channel=endpoint["channel"], host=endpoint["host"],
                       port=endpoint["port"], tcp_tune=True)
    return can.Bus(interface="slcan", channel=endpoint["channel"], bitrate=endpoint["bitrate"], sleep_after_open=0)


def latency(client: can.BusABC, db, trials: int) -> np.ndarray:
    cmd = db.get_message_by_name("VESC1_SET_RPM")
    st = db.get_message_by_name("VESC1_STATUS_1")
    points = (8000, 16000)  # ERPM
    out = []
    last = 0.0
    for k in range(trials + 2):
        target = points[k % 2]
        step = target - last
        # refresh the previous set-point until the rotor has settled, reading the status
        settle = time.monotonic() + 0.25
        while time.monotonic() < settle:
            msg = client.recv(0.02)
            if msg is not None and msg.arbitration_id == st.frame_id:
                last = st.decode(msg.data)["erpm"]
        step = target - last
        time.sleep(random.uniform(0.0, 0.02))  # a command at any phase of the status period
        t0 = time.perf_counter()
        client.send(can.Message(arbitration_id=cmd.frame_id, data=cmd.encode({"erpm": target}), is_extended_id=True))
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            msg = client.recv(0.05)
            if msg is not None and msg.arbitration_id == st.frame_id:
                erpm = st.decode(msg.data)["erpm"]
                if (erpm - last) * np.sign(step) >= 0.02 * abs(step):
                    if k >= 2:  # the first two only bring the rotor to the set-points
                        out.append(time.perf_counter() - t0)
                    last = erpm
                    break
        # keep commanding at 20 Hz meanwhile, so the watchdog never trips
        client.send(can.Message(arbitration_id=cmd.frame_id, data=cmd.encode({"erpm": target}), is_extended_id=True))
    return np.array(out) * 1e3


class RawSlcanClient:
    """A lean slcan host for the rate test: bulk pty reads and writes (python-can's slcan reader
    takes one byte per call, which tops out below the telemetry rate on a 2-core machine)."""

    def __init__(self, path: str) -> None:
        import serial

        self.port = serial.Serial(path, 115200, timeout=0.05)
        self.port.write(b"C\rS8\rO\r")
        self._buf = b""

    def send(self, msg: can.Message) -> None:
        self.port.write(b"T%08X%d%s\r" % (msg.arbitration_id, len(msg.data), msg.data.hex().upper().encode()))

    def recv(self, timeout: float) -> can.Message | None:
        while b"\r" not in self._buf:
            chunk = self.port.read(max(1, self.port.in_waiting))
            if not chunk:
                return None
            self._buf += chunk
        line, _, self._buf = self._buf.partition(b"\r")
        if line[:1] == b"T" and len(line) >= 10:
            return can.Message(arbitration_id=int(line[1:9], 16), data=bytes.fromhex(line[10:].decode()),
                               is_extended_id=True)
        return can.Message(arbitration_id=0x7FF, is_extended_id=False)  # an ack or another reply

    def shutdown(self) -> None:
        self.port.write(b"C\r")
        self.port.close()


class StatusCounter:
    """Reads a client continuously (a real program would) and counts the VESC status frames."""

    def __init__(self, client: can.BusABC, db) -> None:
        self.ids = {db.get_message_by_name(f"VESC{c}_{s}").frame_id for c in range(1, 9)
                    for s in ("STATUS_1", "STATUS_4", "STATUS_5")}
        self.client = client
        self.count = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.client.recv(0.05)
            if msg is not None and msg.arbitration_id in self.ids:
                self.count += 1

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2)


def rate(sender: can.BusABC, counter: StatusCounter, db, cmd_hz: float, seconds: float) -> tuple[int, int, float]:
    """Send SET_DUTY to ids 1..8 at cmd_hz each for ``seconds``. Returns (sent, status frames received, s)."""
    msgs = []
    for cid in range(1, 9):
        m = db.get_message_by_name(f"VESC{cid}_SET_DUTY")
        msgs.append(can.Message(arbitration_id=m.frame_id, data=m.encode({"duty": 0.3}), is_extended_id=True))
    got0 = counter.count
    sent = 0
    period = 1.0 / cmd_hz
    t0 = time.monotonic()
    next_t = t0
    while time.monotonic() - t0 < seconds:
        for m in msgs:
            sender.send(m)
            sent += 1
        next_t += period
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    elapsed = time.monotonic() - t0
    return sent, counter.count - got0, elapsed


def run_transport(tmp: Path, transport: str, args: argparse.Namespace, db) -> None:
    b = BridgeProc(tmp, scenario(tmp, transport, args.status_hz))
    try:
        ep = dict(b.endpoint)
        print(f"\n== {transport}: {b.endpoint['address']} (status {args.status_hz:g} Hz, 8 ESCs)")
        client = open_client(ep)
        time.sleep(0.5)
        lat = latency(client, db, args.trials)
        if lat.size:
            print(f"command -> STATUS_1 latency over {lat.size} steps: p50 {np.percentile(lat, 50):.1f} ms, "
                  f"p99 {np.percentile(lat, 99):.1f} ms, max {lat.max():.1f} ms "
                  f"(status period {1e3 / args.status_hz:.1f} ms)")
        if transport == "socketcand":
            sender, receiver = client, open_client(ep)
        else:  # one pty: one host both sends and receives
            client.shutdown()
            client = sender = receiver = RawSlcanClient(ep["channel"])  # type: ignore[assignment]
            print("(rate test over slcan with a lean bulk-reading host; python-can's slcan reader is the "
                  "bottleneck at these rates)")
        counter = StatusCounter(receiver, db)
        # the sender reads too (a program that does not read its socket loses frames, counted)
        drain = StatusCounter(sender, db) if sender is not receiver else None
        time.sleep(0.5)
        tele_hz = 8 * 3 * args.status_hz
        print(f"{'commands/s':>10} {'sent':>8} {'applied':>8} {'dropped_in':>10} {'dropped_out':>11} "
              f"{'telemetry/s':>11} (expected {tele_hz:g})")
        for mult in (1, 2, 4, 8, 10, 16):
            seconds = args.seconds if mult == 1 else max(2.0, args.seconds / 3)
            time.sleep(1.2)  # a fresh status line
            before = b.counters()
            sent, got, elapsed = rate(sender, counter, db, 100.0 * mult, seconds)
            time.sleep(1.2)  # the next status line
            after = b.counters()
            d = {k: after.get(k, 0.0) - before.get(k, 0.0) for k in ("commands", "dropped_in", "dropped_out")}
            print(f"{sent / elapsed:10.0f} {sent:8d} {d['commands']:8.0f} {d['dropped_in']:10.0f} "
                  f"{d['dropped_out']:11.0f} {got / elapsed:11.0f}")
        counter.stop()
        if drain is not None:
            drain.stop()
        if receiver is not sender:
            receiver.shutdown()
        client.shutdown()
    finally:
        b.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="duration of the 800 frames/s run [s]")
    ap.add_argument("--trials", type=int, default=100, help="latency samples")
    ap.add_argument("--status-hz", type=float, default=50.0, help="VESC status rate [Hz]")
    ap.add_argument("--transports", default="socketcand,slcan")
    args = ap.parse_args()
    logging.getLogger("can").setLevel(logging.ERROR)  # python-can warns on every split TCP read
    db = cantools.database.load_file(str(dbc_path()))
    print(f"bench_thrusters: {os.cpu_count()} cores, python-can {can.__version__}")
    with tempfile.TemporaryDirectory(prefix="bench-thrusters-") as tmp:
        for transport in args.transports.split(","):
            run_transport(Path(tmp), transport.strip(), args, db)


if __name__ == "__main__":
    main()
