#!/usr/bin/env python3
"""Run the reference mission against a live hilsim bridge, start to finish.

1. starts ``hilsim run --endpoints <run dir>/endpoints.json [--time-scale K]`` (the
   hilsim of this Python: ``sys.executable -m hilsim``), its log in ``<out>/bridge.log``;
2. waits for the endpoints file;
3. runs ``examples/mission.py`` on it (its live status lines on this terminal; its
   summary, CSV logs and PNG plots into ``<out>``);
4. stops the bridge with SIGTERM and checks that it shut down cleanly.

    python examples/demo.py [--time-scale 4] [--out out/mission] [-- MISSION OPTIONS]

Exit status: 0 when the mission completed and the bridge stopped cleanly, else 1. Ctrl-C or SIGTERM
stops the mission cleanly (thrusters to zero, summary written), then the bridge.
No hilsim import: the bridge is another process, reached only through its endpoints.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def parse_args(argv: list[str] | None) -> tuple[argparse.Namespace, list[str]]:
    argv = list(sys.argv[1:] if argv is None else argv)
    mission_args: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, mission_args = argv[:i], argv[i + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 epilog="Options after -- go to examples/mission.py (see its --help).")
    ap.add_argument("--time-scale", type=float, default=1.0,
                    help="run the bridge this many times faster than real time (default 1)")
    ap.add_argument("--out", type=Path, default=Path("out/mission"), help="output folder (default out/mission)")
    ap.add_argument("--scenario", default=None, help="scenario for hilsim run (default: its own, water_tank)")
    ap.add_argument("--run-dir", type=Path, default=None,
                    help="folder for endpoints.json (default: a temporary one, removed at the end)")
    ap.add_argument("--startup-timeout", type=float, default=60.0, help="[s] to wait for the endpoints file")
    return ap.parse_args(argv), mission_args


def stop_bridge(bridge: subprocess.Popen, timeout: float = 30.0) -> int | None:
    """SIGTERM, wait; SIGKILL after ``timeout`` [s] (then None: not a clean shutdown)."""
    if bridge.poll() is None:
        bridge.send_signal(signal.SIGTERM)
    try:
        return bridge.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        bridge.kill()
        bridge.wait()
        return None


def tail(path: Path, n: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


def main(argv: list[str] | None = None) -> int:
    a, mission_args = parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    own_run_dir = a.run_dir is None
    run_dir = Path(tempfile.mkdtemp(prefix="hilsim-demo-")) if own_run_dir else a.run_dir
    run_dir.mkdir(parents=True, exist_ok=True)
    endpoints = run_dir / "endpoints.json"
    endpoints.unlink(missing_ok=True)
    log_path = a.out / "bridge.log"
    cmd = [sys.executable, "-m", "hilsim", "run", "--endpoints", str(endpoints), "--time-scale", f"{a.time_scale:g}"]
    if a.scenario:
        cmd.insert(4, a.scenario)
    print("demo: starting the bridge:", " ".join(cmd[1:]), flush=True)
    with open(log_path, "w") as log:
        bridge = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                  start_new_session=True)  # Ctrl-C reaches the mission; we stop the bridge
    mission_rc: int | None = None
    bridge_rc: int | None = None
    mission: subprocess.Popen | None = None

    def on_sigterm(signum: int, frame: object) -> None:  # stop as Ctrl-C would: the mission first
        if mission is not None and mission.poll() is None:
            mission.send_signal(signal.SIGTERM)
        else:
            raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_sigterm)
    try:
        deadline = time.monotonic() + a.startup_timeout
        while not endpoints.exists():
            if bridge.poll() is not None:
                print(f"demo: the bridge exited ({bridge.returncode}) before writing its endpoints:\n"
                      f"{tail(log_path)}", file=sys.stderr)
                return 1
            if time.monotonic() > deadline:
                print(f"demo: no endpoints file after {a.startup_timeout:g} s:\n{tail(log_path)}", file=sys.stderr)
                return 1
            time.sleep(0.1)
        print(f"demo: bridge up (pid {bridge.pid}, log {log_path}); running the mission", flush=True)
        console = [e["url"] for e in json.loads(endpoints.read_text()) if e.get("device") == "console"]
        if console:
            print(f"demo: watch it live in a browser: {console[0]}", flush=True)
        mcmd = [sys.executable, str(HERE / "mission.py"), str(endpoints), "--out", str(a.out), *mission_args]
        mission = subprocess.Popen(mcmd)
        while mission_rc is None:
            try:
                mission_rc = mission.wait()
            except KeyboardInterrupt:  # the mission got the Ctrl-C too: it stops its thrusters, writes its summary
                print("demo: interrupted; waiting for the mission to wrap up", file=sys.stderr, flush=True)
    except KeyboardInterrupt:
        print("demo: interrupted before the mission started", file=sys.stderr)
        mission_rc = 130
    finally:
        bridge_rc = stop_bridge(bridge)
        if own_run_dir:
            shutil.rmtree(run_dir, ignore_errors=True)
    clean = bridge_rc == 0
    print(f"demo: mission exit {mission_rc}; bridge "
          + ("stopped cleanly (exit 0)" if clean else f"did not stop cleanly (exit {bridge_rc})")
          + f"; outputs in {a.out}{os.sep}", flush=True)
    if not clean:
        print(tail(log_path), file=sys.stderr)
    return 0 if mission_rc == 0 and clean else 1


if __name__ == "__main__":
    sys.exit(main())
