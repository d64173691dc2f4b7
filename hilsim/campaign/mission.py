"""One mission run: the bridge (``hilsim run``) and the stack under test, each in its own process group.

The run folder holds everything of the run and nothing of another: the
scenario copy (when the case changes it), ``endpoints.json``, the ptys
(``pty/``), ``truth.csv`` and ``bridge_summary.json`` (the bridge's),
``bridge.log``, ``stack.log`` and the stack's own output folder ``stack/``.
Ports are the scenario's (0, or vendor ports with free-port fallback), so
concurrent runs never collide. A stack that outlives ``timeout_s`` is killed
(SIGTERM, then SIGKILL to its whole process group) and the run is recorded as
timed out; the process groups are always cleaned up, whatever happens.
"""

from __future__ import annotations

import atexit
import functools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from hilsim.campaign import criteria
from hilsim.campaign.matrix import Case, expand_command
from hilsim.campaign.metrics import read_truth, truth_metrics
from hilsim.campaign.spec import Campaign

_GROUPS: set[int] = set()
_LOCK = threading.Lock()


def _register(p: subprocess.Popen[bytes]) -> None:
    with _LOCK:
        _GROUPS.add(p.pid)


def _kill_group(pgid: int, sig: int = signal.SIGKILL) -> None:
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def _forget(p: subprocess.Popen[bytes]) -> None:
    """SIGKILL whatever is left of the process group and reap the leader."""
    _kill_group(p.pid)
    try:
        p.wait(timeout=5)
    except subprocess.TimeoutExpired:  # pragma: no cover - SIGKILL does not fail
        pass
    with _LOCK:
        _GROUPS.discard(p.pid)


def cleanup_all() -> None:
    """Kill every process group a run of this process started and has not reaped (Ctrl-C, exit)."""
    with _LOCK:
        groups = list(_GROUPS)
        _GROUPS.clear()
    for g in groups:
        _kill_group(g)


atexit.register(cleanup_all)

_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """Linux: SIGTERM this child when the thread that started it dies (a killed Ray worker, say)."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass


@functools.lru_cache(maxsize=1)
def bridge_options() -> frozenset[str]:
    """The options ``hilsim run`` of this Python understands (the truth and summary files are recent)."""
    try:
        out = subprocess.run([sys.executable, "-m", "hilsim", "run", "--help"], capture_output=True,
                             text=True, timeout=60).stdout
    except (OSError, subprocess.TimeoutExpired):
        return frozenset()
    return frozenset(w.strip(",[]") for w in out.split() if w.startswith("--"))


_LINUX_PREEXEC = _die_with_parent if sys.platform.startswith("linux") else None


def _tail(path: Path, n: int = 8) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        v = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return v if isinstance(v, dict) else None


def bridge_command(c: Campaign, case: Case, scenario: Path, run_dir: Path) -> list[str]:
    cmd = [sys.executable, "-m", "hilsim", "run", str(scenario)]
    cmd += ["--fast"] if c.fast else ["--time-scale", f"{c.time_scale:g}"]
    if c.duration_s is not None:
        cmd += ["--duration", f"{c.duration_s:g}"]
    cmd += ["--endpoints", str(run_dir / "endpoints.json"), "--pty-dir", str(run_dir / "pty")]
    if case.seed is not None:
        cmd += ["--seed", str(case.seed)]
    opts = bridge_options()
    if "--truth" in opts:
        cmd += ["--truth", str(run_dir / "truth.csv")]
    if "--summary" in opts:
        cmd += ["--summary", str(run_dir / "bridge_summary.json")]
    return cmd


def _stop(p: subprocess.Popen[bytes], grace_s: float, group: bool) -> int | None:
    """SIGTERM (the leader, or its whole group), wait ``grace_s``; then SIGKILL the group. None if killed."""
    if p.poll() is None:
        if group:
            _kill_group(p.pid, signal.SIGTERM)
        else:
            p.send_signal(signal.SIGTERM)
    try:
        rc: int | None = p.wait(timeout=grace_s)
    except subprocess.TimeoutExpired:
        rc = None
    _forget(p)
    return rc


def run_mission(c: Campaign, case: Case, run_dir: Path, scenario: Path) -> dict[str, Any]:
    """Run one case in ``run_dir`` (created); returns its result row (see :mod:`results`)."""
    assert c.stack is not None
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "pty").mkdir(exist_ok=True)
    stack_out = run_dir / "stack"
    stack_out.mkdir(exist_ok=True)
    endpoints = run_dir / "endpoints.json"
    endpoints.unlink(missing_ok=True)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    t0 = time.monotonic()
    row: dict[str, Any] = {"case": case.id, "index": case.index, "key": case.key, "seed": case.seed,
                           "params": dict(case.params), "exit_code": None, "timed_out": False,
                           "bridge_exit": None}
    values = {"endpoints": str(endpoints), "out": str(stack_out), "seed": "" if case.seed is None else str(case.seed),
              "run": str(run_dir), "python": sys.executable, "campaign_dir": str(c.folder),
              "scenario": str(scenario), "case": case.id}
    bridge: subprocess.Popen[bytes] | None = None
    stack: subprocess.Popen[bytes] | None = None
    error = None
    try:
        with open(run_dir / "bridge.log", "wb") as blog:
            bridge = subprocess.Popen(bridge_command(c, case, scenario, run_dir), stdout=blog,
                                      stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                      start_new_session=True, preexec_fn=_LINUX_PREEXEC)
        _register(bridge)
        deadline = time.monotonic() + c.stack.startup_timeout_s
        while not endpoints.exists():
            if bridge.poll() is not None:
                error = f"the bridge exited ({bridge.returncode}) before its endpoints: {_tail(run_dir / 'bridge.log', 3)}"
                break
            if time.monotonic() > deadline:
                error = f"no endpoints after {c.stack.startup_timeout_s:g} s"
                break
            time.sleep(0.05)
        if error is None:
            time.sleep(0.05)  # the endpoints file is written whole, but give its writer a moment
            cmd = expand_command(c.stack.command, values)
            with open(run_dir / "stack.log", "wb") as slog:
                stack = subprocess.Popen(cmd, stdout=slog, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                         cwd=c.folder if c.folder.is_dir() else run_dir,
                                         env=dict(env, **c.stack.env), start_new_session=True,
                                         preexec_fn=_LINUX_PREEXEC)
            _register(stack)
            try:
                row["exit_code"] = stack.wait(timeout=c.stack.timeout_s)
            except subprocess.TimeoutExpired:
                row["timed_out"] = True
                _stop(stack, 5.0, group=True)
            _forget(stack)
    except OSError as exc:
        error = f"cannot start: {exc}"
    finally:
        if stack is not None and stack.poll() is None:
            _forget(stack)
        if bridge is not None:
            row["bridge_exit"] = _stop(bridge, 30.0, group=False)
    row["wall_s"] = round(time.monotonic() - t0, 3)
    summary_path = Path(expand_command(c.stack.summary, values)[0])
    row["summary"] = _read_json(summary_path) or {}
    row["bridge"] = _read_json(run_dir / "bridge_summary.json") or {}
    truth_file = run_dir / "truth.csv"
    row["truth"] = truth_metrics(read_truth(truth_file), c.metrics) if truth_file.is_file() else {}
    row["run_dir"] = run_dir.name
    judge_row(c, row, error)
    return row


def judge_row(c: Campaign, row: dict[str, Any], error: str | None = None) -> None:
    """Fill ``status`` (pass | fail | timeout | error), ``failed`` (names) and ``failure`` (detail)."""
    facts = {"exit_code": row.get("exit_code"), "timed_out": row.get("timed_out", False),
             "wall_s": row.get("wall_s"), "summary": row.get("summary", {}), "bridge": row.get("bridge", {}),
             "truth": row.get("truth", {})}
    crit = c.criteria or [criteria.parse("exit_code == 0", "exit_code")]
    verdicts = [criteria.evaluate(k, facts) for k in crit]
    bad = [v for v in verdicts if not v.ok]
    if error is not None:
        row.update(status="error", failed="error", failure=error)
    elif row.get("timed_out"):
        assert c.stack is not None
        row.update(status="timeout", failed="timeout",
                   failure=f"the stack ran past timeout_s = {c.stack.timeout_s:g} s and was killed")
    elif bad:
        row.update(status="fail", failed=",".join(v.criterion.name for v in bad),
                   failure="; ".join(f"{v.criterion.name}: {v.detail}" for v in bad))
    else:
        row.update(status="pass", failed="", failure="")
