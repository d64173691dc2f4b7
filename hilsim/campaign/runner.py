"""Running a campaign: cases to tasks, an executor, the journal, the progress line, the results.

Layout of ``--out``::

    results.jsonl            one line per finished run (or frame), written as they finish
    results.parquet          missions: one row per run   (results.csv without pyarrow)
    index.parquet            renders: one row per frame  (index.csv without pyarrow)
    report.html              the table, filters, links to each run's plots and logs
    runs/<case>/             a mission run's folder (bridge.log, stack.log, stack/, truth.csv, ...)
    frames/<case>/NNNNN.npz  a render campaign's frames (+ .png, _labels.png)
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from hilsim.campaign import executors
from hilsim.campaign.executors import Task
from hilsim.campaign.matrix import Case, expand, write_scenario
from hilsim.campaign.results import Journal, write_table
from hilsim.campaign.spec import Campaign, load_campaign


# ---- tasks (module level: pickled to processes and Ray workers) ------------------------------

def mission_task(c: Campaign, case: Case, out: Path) -> list[dict[str, Any]]:
    from hilsim.campaign.mission import run_mission

    run_dir = out / "runs" / case.id
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    return [run_mission(c, case, run_dir, write_scenario(c, case, run_dir))]


def ray_mission_task(c: Campaign, case: Case, payload: bytes) -> tuple[list[dict[str, Any]], bytes]:
    """On a Ray worker without the driver's folders: unpack the case's scenario, run, pack the run folder."""
    from hilsim.campaign.mission import run_mission

    tmp = Path(tempfile.mkdtemp(prefix="hilsim-campaign-"))
    try:
        run_dir = tmp / case.id
        executors.unpack(payload, run_dir)
        row = run_mission(c, case, run_dir, run_dir / "scenario" / c.scenario.name)
        return [row], executors.pack(run_dir, exclude=("scenario", "pty"))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def render_task(c: Campaign, case: Case, scenario: Path, poses: list[Any], out: Path) -> list[dict[str, Any]]:
    from hilsim.campaign.render import render_chunk

    return render_chunk(c, case, scenario, poses, out)


def ray_render_task(c: Campaign, case: Case, payload: bytes, poses: list[Any]) -> tuple[list[dict[str, Any]], bytes]:
    from hilsim.campaign.render import render_chunk

    tmp = Path(tempfile.mkdtemp(prefix="hilsim-render-"))
    try:
        executors.unpack(payload, tmp / "scenario")
        rows = render_chunk(c, case, tmp / "scenario" / c.scenario.name, poses, tmp / "out")
        return rows, executors.pack(tmp / "out")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# ---- progress ---------------------------------------------------------------------------------

@dataclass
class Progress:
    """A progress line with counts and an ETA on stderr (one line per update when not a terminal)."""

    total: int
    name: str
    stream: TextIO = field(default_factory=lambda: sys.stderr)
    done: int = 0
    counts: dict[str, int] = field(default_factory=dict)
    t0: float = field(default_factory=time.monotonic)

    def update(self, rows: list[dict[str, Any]]) -> None:
        for r in rows:
            self.done += 1
            st = str(r.get("status", "done"))
            self.counts[st] = self.counts.get(st, 0) + 1
        el = time.monotonic() - self.t0
        eta = el / self.done * (self.total - self.done) if self.done else float("nan")
        counts = ", ".join(f"{k} {v}" for k, v in sorted(self.counts.items()))
        line = (f"campaign {self.name}: {self.done}/{self.total} ({counts}) elapsed {_hms(el)}, "
                f"ETA {_hms(eta) if eta == eta else '?'}")
        tty = getattr(self.stream, "isatty", lambda: False)()
        self.stream.write(("\r" + line + "\x1b[K") if tty else line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if getattr(self.stream, "isatty", lambda: False)():
            self.stream.write("\n")


def _hms(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


# ---- the campaign -------------------------------------------------------------------------------

@dataclass
class Outcome:
    campaign: Campaign
    out: Path
    rows: list[dict[str, Any]]
    ran: int
    table: Path | None
    report: Path | None

    @property
    def ok(self) -> bool:
        good = ("pass",) if self.campaign.kind == "mission" else ("done",)
        return all(r.get("status") in good for r in self.rows)


def run_campaign(path: Path | str, out: Path | None = None, workers: int | None = None,
                 ray: str | None = None, resume: bool = False, ray_cpus: int | None = None,
                 shared: bool = False, stream: TextIO | None = None) -> Outcome:
    """Run a campaign file. ``ray``: None (local pool), ``"local"`` (a local Ray) or a Ray address.
    ``shared``: with Ray, ``out`` is a folder every worker sees (runs write there, nothing is sent back)."""
    c = load_campaign(path)
    out = (out or Path("out") / "campaigns" / c.name).resolve()
    out.mkdir(parents=True, exist_ok=True)
    journal = Journal(out / "results.jsonl")
    if not resume:
        journal.path.unlink(missing_ok=True)
    # done: what --resume keeps. A mission run that errored (its bridge or stack could not run,
    # a worker died) produced no result and is run again; pass, fail and timeout are results.
    done = {r["key"] for r in _latest(journal.load(), c.kind)
            if not (c.kind == "mission" and r.get("status") == "error")}
    cases = expand(c)
    tasks = _tasks(c, cases, out, done, ray is not None and not shared)
    total = len(tasks) if c.kind == "mission" else sum(len(t.args[3]) for t in tasks)
    progress = Progress(total, c.name, stream or sys.stderr)

    def on_done(t: Task, result: Any) -> None:
        rows, data = result if isinstance(result, tuple) else (result, None)
        if data is not None:
            dest = out / "runs" / t.args[1].id if c.kind == "mission" else out
            if c.kind == "mission" and dest.exists():
                shutil.rmtree(dest)
            executors.unpack(data, dest)
        for r in rows:
            journal.append(r)
        progress.update(rows)

    def on_error(t: Task, exc: BaseException) -> None:
        case: Case = t.args[1]
        if c.kind == "mission":
            row = {"case": case.id, "index": case.index, "key": case.key, "seed": case.seed,
                   "params": dict(case.params), "status": "error", "failed": "error",
                   "failure": f"{type(exc).__name__}: {exc}", "run_dir": case.id}
            journal.append(row)
            progress.update([row])
        else:
            progress.stream.write(f"campaign {c.name}: a render task of case {case.id} failed: "
                                  f"{type(exc).__name__}: {exc}\n")

    started_ray = False
    try:
        if ray is None:
            cpus = c.stack.cpus if c.stack else 1.0
            n = executors.local_workers(cpus, workers)
            from hilsim.campaign.mission import cleanup_all as abort

            executors.run_local(tasks, n, processes=c.kind == "render", on_done=on_done, on_error=on_error,
                                on_abort=abort)
        else:
            started_ray = executors.ray_init(None if ray == "local" else ray, ray_cpus)
            executors.run_ray(tasks, on_done, on_error)
    finally:
        if started_ray:   # a Ray this campaign started (or joined) is left: its processes stop
            executors.ray_shutdown()
        from hilsim.campaign.mission import cleanup_all

        cleanup_all()
        progress.close()
        rows = _latest(journal.load(), c.kind)
        table = report = None
        if rows:
            table = write_table(rows, out) if c.kind == "mission" else _index(rows, out)
            from hilsim.campaign.report import write_report

            report = write_report(c, rows, out)
    wanted = {k.key for k in cases} if c.kind == "mission" else None
    rows = [r for r in rows if wanted is None or r["key"] in wanted]
    return Outcome(c, out, rows, len(tasks), table, report)


def _index(rows: list[dict[str, Any]], out: Path) -> Path:
    path = write_table(rows, out)
    final = path.with_name("index" + path.suffix)
    path.replace(final)
    return final


def _latest(rows: list[dict[str, Any]], kind: str) -> list[dict[str, Any]]:
    """A mission journal's rows, the last one of each run (a run redone by ``--resume`` after an
    error appends its new row), in the order the runs first appeared. Render rows are per frame."""
    if kind != "mission":
        return rows
    latest: dict[str, dict[str, Any]] = {}
    for r in rows:
        latest[r["key"]] = r
    return list(latest.values())


def _tasks(c: Campaign, cases: list[Case], out: Path, done: set[str], send_back: bool) -> list[Task]:
    tasks: list[Task] = []
    if c.kind == "mission":
        assert c.stack is not None
        for case in cases:
            if case.key in done:
                continue
            if send_back:
                stage = out / "runs" / case.id
                if stage.exists():
                    shutil.rmtree(stage)
                stage.mkdir(parents=True)
                write_scenario(c, case, stage, force=True)
                payload = executors.pack(stage)
                tasks.append(Task(case.id, ray_mission_task, (c, case, payload), c.stack.cpus))
            else:
                tasks.append(Task(case.id, mission_task, (c, case, out), c.stack.cpus))
        return tasks
    from hilsim.campaign.render import chunks

    for case in cases:
        stage = out / "runs" / case.id
        stage.mkdir(parents=True, exist_ok=True)
        scenario = write_scenario(c, case, stage, force=send_back)
        payload = executors.pack(stage / "scenario") if send_back else b""
        for part in chunks(c, case, done):
            if send_back:
                tasks.append(Task(f"{case.id}:{part[0][0]}", ray_render_task, (c, case, payload, part), 1.0))
            else:
                tasks.append(Task(f"{case.id}:{part[0][0]}", render_task, (c, case, scenario, part, out), 1.0))
    return tasks
