"""Soak: the default scenario with every device, well-behaved clients on each and abusive ones
cycling, for a given time. Prints figures and a verdict line; never passes or fails (the
short version runs as tests/runtime/test_soak.py, which asserts on what ``main`` returns).

Run: ``python benchmarks/soak.py [--minutes 10] [--cycle S] [--json FILE]``.

The bridge is ``hilsim run`` on scenarios/water_tank (its own process, real time). Clients
(tests/runtime/abuse_clients.py, threads in this process):

* well-behaved, all the time: a DDF reader (RATE 5), an Oculus client firing at 2 Hz, an
  ARIS client (3 frames/s, PING every 0.5 s), Modbus pollers over TCP (Keller P1 and the
  WitMotion block, 100 Hz each) and over RTU on the ptys (10 Hz each), a VESC CAN commander
  on the socketcand server (SET_RPM to controller 2 at 20 Hz, reading STATUS_1), a DroneCAN
  commander on the slcan pty (RawCommand to ESC 0 at 20 Hz, reading esc.Status), a VESC UART
  GET_VALUES poller and a VRCSR poller (20 Hz each);
* abusive, one kind per cycle, in turn, in a child process (so they do not share the
  well-behaved clients' interpreter): ``flood`` (connects reset at once and half messages on
  every TCP server), ``hold`` (idle, half-closed, never-reading and stalled-huge-header
  clients on every TCP server, then reset), ``blast`` (one server's decoder fed costly
  bytes as fast as loopback carries them, a different server each time), ``modbus-flood``
  (8 clients pipelining requests to each Modbus server) and ``can-flood`` (a socketcand
  client sending frames far beyond the bus's capacity).

Each cycle: the abuse for 60 % of it, then quiet; at the end of the quiet part one row is
sampled: the bridge's RSS and open file descriptors (so rows compare like with like),
the CPU the bridge's main process used (its event loop and the physics; the render
worker is a child process), what every client got, lost replies, the bridge's drop
counters, late ticks and skipped ticks (from its status line). Warm-up is the first full
turn of abuse kinds (or 20 % of the cycles, if more); after it the verdict fits RSS
[MB/min] and descriptors over the rows and counts lost replies. Goal: flat memory and descriptors after warm-up, zero lost replies to
well-behaved clients.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import queue
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from tests.runtime import abuse_clients as ac  # noqa: E402
from tests.runtime.bridge_helpers import start_bridge  # noqa: E402

KINDS = ac.ABUSE_KINDS
DROP_COUNTERS = ("dropped", "dropped_in", "dropped_out", "busy_skips", "late_skips", "render_failures",
                 "throttled", "refused", "replies_dropped")
REQUEST_CLIENTS = ("modbus-tcp", "modbus-rtu", "vesc-uart", "vrcsr")


# ------------------------------------------------------------------ well-behaved clients


def well_behaved(endpoints: list[dict]) -> list[ac.Client]:
    def ep(device: str, transports: tuple[str, ...]) -> dict:
        return next(e for e in endpoints if e["device"] == device and e["transport"] in transports)

    tcp = ("tcp",)
    clients: list[ac.Client] = [
        ac.DdfReader(ep("sonar_ddf", tcp)["address"], rate_hz=5),
        ac.OculusFirer(ep("sonar_oculus", tcp)["address"], rate=4),
        ac.ArisClient(ep("sonar_aris", tcp)["address"], frame_rate=3.0),
        ac.ModbusTcpPoller(ep("depth", tcp)["address"], 1, 0x0002, 2, timeout=5.0, name="depth-tcp"),
        ac.ModbusTcpPoller(ep("imu", tcp)["address"], 0x50, 0x34, 13, timeout=5.0, name="imu-tcp"),
        ac.ModbusRtuPoller(ep("depth", ("pty",))["address"], 1, 0x0002, 2, timeout=5.0, name="depth-rtu"),
        ac.ModbusRtuPoller(ep("imu", ("pty",))["address"], 0x50, 0x34, 13, timeout=5.0, name="imu-rtu"),
        ac.SocketcandCommander(ep("vesc_can", ("socketcand",))["address"], controller=2, erpm=3000),
        ac.SlcanCommander(ep("dronecan_esc", ("slcan",))["address"], value=2000),
        ac.VescUartPoller(ep("vesc_uart", ("pty",))["address"], timeout=5.0),
        ac.VrcsrPoller(ep("vrcsr", ("pty",))["address"], timeout=5.0),
    ]
    for c in clients:
        c.restart = True
    return clients


SHORT = {"ddf-reader": "ddf", "oculus-firer": "oculus", "aris-client": "aris", "depth-tcp": "kel.tcp",
         "imu-tcp": "imu.tcp", "depth-rtu": "kel.rtu", "imu-rtu": "imu.rtu", "socketcand-commander": "vesc.can",
         "slcan-commander": "dronecan", "vesc-uart-poller": "vesc.uart", "vrcsr-poller": "vrcsr"}


def slope(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of ys over xs (0 for fewer than 2 points)."""
    n = len(xs)
    if n < 2:
        return 0.0
    mx, my = sum(xs) / n, sum(ys) / n
    den = sum((x - mx) ** 2 for x in xs)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / den if den else 0.0


# ------------------------------------------------------------------ the soak


def main(minutes: float = 10.0, cycle: float | None = None, out: Callable[[str], None] = print,
         workdir: Path | None = None, json_path: Path | None = None) -> dict[str, Any]:
    """Run the soak for ``minutes``; prints the table and the verdict via ``out``; returns the figures."""
    total = minutes * 60.0
    cycle = cycle or min(10.0, max(3.0, total / 10.0))
    n_cycles = max(2, round(total / cycle))
    warmup = min(n_cycles - 2, max(len(KINDS), round(0.2 * n_cycles)))
    tmp = Path(workdir) if workdir is not None else Path(tempfile.mkdtemp(prefix="hilsim-soak-"))
    tmp.mkdir(parents=True, exist_ok=True)
    status_s = max(1.0, min(5.0, cycle / 2))
    bridge = start_bridge(tmp, "--status-interval", f"{status_s:g}")
    ctx = mp.get_context("forkserver")  # abusers in a clean child, not forked from this threaded process
    ctx.set_forkserver_preload(["tests.runtime.abuse_clients"])
    clients = well_behaved(bridge.endpoints)
    rows: list[dict[str, Any]] = []
    try:
        for c in clients:
            c.start()
        ac.wait_until(lambda: all(c.stats.received > 0 for c in clients), 30)
        out(f"soak: {minutes:g} min, {n_cycles} cycles of {cycle:g} s (abuse {0.6 * cycle:.1f} s, then quiet), "
            f"warm-up {warmup} cycles; bridge pid {bridge.proc.pid}, log {bridge.log_path}")
        header = (f"{'t[s]':>6} {'RSS[MB]':>7} {'fds':>4} {'cpu%':>4} " + " ".join(f"{SHORT[c.name]:>8}" for c in clients)
                  + f" {'lost':>4} {'drops':>7} {'late':>7} {'skipped':>7}  abuse")
        out(header)
        t_start = time.monotonic()
        prev = {c.name: 0 for c in clients}
        prev_drops = prev_late = prev_skip = 0.0
        prev_cpu, prev_t = ac.cpu_seconds(bridge.proc.pid), time.monotonic()
        t_cycle = t_start
        for i in range(n_cycles):
            t_cycle = max(t_cycle + cycle, time.monotonic()) if i else t_start
            kind = KINDS[i % len(KINDS)]
            q = ctx.Queue()
            child = ctx.Process(target=ac.abuse_child, args=(kind, bridge.endpoints, 0.6 * cycle, i // len(KINDS), q),
                                daemon=True)
            child.start()
            child.join(0.6 * cycle + 30)
            if child.is_alive():
                child.kill()
            try:
                what = q.get(timeout=2)
            except queue.Empty:
                what = {"kind": kind, "error": "no report"}
            # quiet until the cycle ends, but long enough for the bridge to let go of the abusers
            time.sleep(max(0.4 * cycle, t_cycle + cycle - time.monotonic()))
            if bridge.proc.poll() is not None:
                raise RuntimeError(f"the bridge exited with {bridge.proc.returncode}:\n{bridge.log()[-3000:]}")
            rss, fds = ac.proc_stats(bridge.proc.pid)
            cpu, now = ac.cpu_seconds(bridge.proc.pid), time.monotonic()
            cpu_pct, prev_cpu, prev_t = 100.0 * (cpu - prev_cpu) / (now - prev_t), cpu, now
            st = ac.last_status(bridge.log()) or {"devices": {}, "late_ticks": 0, "skipped_ticks": 0}
            drops = sum(v for d in st["devices"].values() for k, v in d.items() if k in DROP_COUNTERS)
            got = {c.name: c.stats.received for c in clients}
            lost = sum(c.stats.lost for c in clients) + clients[0].stats.gaps
            row = {"t": round(time.monotonic() - t_start, 1), "rss_mb": round(rss, 1), "fds": fds,
                   "bridge_cpu_pct": round(cpu_pct),
                   "served": {k: got[k] - prev[k] for k in got}, "lost": lost, "drops": drops - prev_drops,
                   "late_ticks": st["late_ticks"] - prev_late, "skipped_ticks": st["skipped_ticks"] - prev_skip,
                   "abuse": what, "warmup": i < warmup}
            rows.append(row)
            prev, prev_drops, prev_late, prev_skip = got, drops, st["late_ticks"], st["skipped_ticks"]
            detail = ", ".join(f"{k} {v}" for k, v in what.items() if k != "kind")
            out(f"{row['t']:>6.0f} {rss:>7.1f} {fds:>4} {cpu_pct:>4.0f} " + " ".join(f"{row['served'][c.name]:>8}" for c in clients)
                + f" {lost:>4} {row['drops']:>7.0f} {row['late_ticks']:>7.0f} {row['skipped_ticks']:>7.0f}  {kind}{' (' + detail + ')' if detail else ''}"
                + ("  [warm-up]" if row["warmup"] else ""))
    finally:
        for c in clients:
            c.stopping.set()
        for c in clients:
            c.join(5)
        code = bridge.stop()
    measured = [r for r in rows if not r["warmup"]]
    minutes_axis = [r["t"] / 60.0 for r in measured]
    rss_slope = slope(minutes_axis, [r["rss_mb"] for r in measured])
    fds_after = [r["fds"] for r in measured]
    rss_after = [r["rss_mb"] for r in measured]
    lost = sum(c.stats.lost for c in clients)
    gaps = clients[0].stats.gaps
    errors = {c.name: c.errors for c in clients if c.errors}
    served = {c.name: c.stats.received for c in clients}
    rtts = {c.name: (ac.percentile(c.stats.rtts, 50), ac.percentile(c.stats.rtts, 99))
            for c in clients if c.stats.rtts}
    result = {
        "minutes": minutes, "cycle_s": cycle, "rows": rows, "rss_slope_mb_per_min": rss_slope,
        "rss_after_warmup": rss_after, "fds_after_warmup": fds_after,
        "fds_spread": (max(fds_after) - min(fds_after)) if fds_after else 0,
        "lost_replies": lost, "ddf_gaps": gaps, "served": served, "errors": errors,
        "rtt_ms": {k: (round(a * 1e3, 2), round(b * 1e3, 2)) for k, (a, b) in rtts.items()},
        "bridge_exit": code, "log": str(bridge.log_path),
    }
    out("round trips p50/p99 [ms]: " + ", ".join(f"{SHORT[k]} {a}/{b}" for k, (a, b) in result["rtt_ms"].items()))
    out("served in all: " + ", ".join(f"{SHORT[k]} {v}" for k, v in served.items()))
    if errors:
        out(f"client errors (reconnected): {json.dumps(errors)}")
    flat_fds = result["fds_spread"] <= 3
    flat_rss = abs(rss_slope) * max(1.0, minutes) < 20.0  # less than 20 MB over the run's length
    out(f"VERDICT: memory {'flat' if flat_rss else 'GROWING'} after warm-up ({rss_slope:+.2f} MB/min, "
        f"{min(rss_after, default=0):.0f}-{max(rss_after, default=0):.0f} MB); fds "
        f"{'flat' if flat_fds else 'GROWING'} ({min(fds_after, default=0)}-{max(fds_after, default=0)}); "
        f"lost replies {lost}, DDF frame gaps {gaps}; bridge exit {code} -> "
        f"{'OK' if flat_rss and flat_fds and lost == 0 and gaps == 0 and code == 0 else 'NOT OK'}")
    if json_path is not None:
        Path(json_path).write_text(json.dumps(result, indent=1, default=str))
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="how long (default 10)")
    ap.add_argument("--cycle", type=float, default=None, help="seconds per abuse cycle (default: 10, fewer for short runs)")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures as JSON")
    a = ap.parse_args()
    main(a.minutes, a.cycle, json_path=a.json)
