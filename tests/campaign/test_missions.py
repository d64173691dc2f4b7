"""Mission campaigns end to end: the real bridge (``hilsim run``) and the reference stack (examples/mission.py)
in their own processes, on the local pool and on Ray's local mode.

The missions are short (a 2 s hold, time scale 4: about 12 s of wall time each).
"""

from __future__ import annotations

import io
import json
import os
import time
from pathlib import Path

import pytest

from hilsim.campaign.mission import bridge_options
from hilsim.campaign.results import read_table
from hilsim.campaign.runner import Outcome, run_campaign

pytestmark = pytest.mark.alone  # missions load both cores: make test runs these after the others, one at a time

ROOT = Path(__file__).resolve().parents[2]
MISSION = ROOT / "examples" / "mission.py"
FAULTS = ROOT / "scenarios" / "water_tank" / "campaigns" / "faults" / "vertical_thrusters_fail.toml"
HAS_TRUTH = "--truth" in bridge_options()

# the turns (20 deg and back) stay: without them the approach of the DVL-aided stack fails now and then
STACK = "{python} " + str(MISSION) + " {endpoints} --out {out} --quiet --no-plots --hold-time 2 --timeout 90"
TRUTH_PASS = ('no_contact = "truth.contacts == 0"\nabove_floor = "truth.min_altitude_m > 0.8"\n'
              'depth = "truth.max_depth_error_m < 0.05"\n' if HAS_TRUTH else "")
CAMPAIGN = f"""name = "four"
scenario = "water_tank"
time_scale = 4.0
duration_s = 130.0

[stack]
command = "{STACK}"
timeout_s = 90.0
cpus = 1.0             # two runs at once on a 2-core machine (each about 1 core at time scale 4)

[matrix]
seed = [1, 2]
current_m_s = [[0.0, 0.0, 0.0], [0.02, 0.0, 0.0]]

[metrics]
depth_target_m = 1.8
depth_last_s = 5.0     # the end of the approach and the hold, whatever the dive took

[pass]
exit = "exit_code == 0"
completed = "summary.success == true"
{TRUTH_PASS}"""


def table(o: Outcome) -> dict[str, tuple[str, str]]:
    return {r["key"]: (r["status"], r["failed"]) for r in o.rows}


@pytest.fixture(scope="module")
def four(tmp_path_factory: pytest.TempPathFactory) -> Outcome:
    tmp = tmp_path_factory.mktemp("four")
    (tmp / "four.toml").write_text(CAMPAIGN)
    return run_campaign(tmp / "four.toml", out=tmp / "out")


def test_four_reference_missions_pass_locally(four: Outcome) -> None:
    assert len(four.rows) == 4
    assert all(r["status"] == "pass" for r in four.rows), [(r["case"], r["failure"]) for r in four.rows]
    rows = read_table(four.out / "results.parquet")
    assert [(r["param.seed"], json.loads(r["param.current_m_s"])[0]) for r in rows] == [
        (1, 0.0), (1, 0.02), (2, 0.0), (2, 0.02)]
    assert all(r["exit_code"] == 0 and r["summary.success"] is True for r in rows)
    report = (four.out / "report.html").read_text()
    # self-contained: no script, style or link fetched from anywhere
    assert "<script src" not in report and "http://" not in report and "https://" not in report
    assert 'id="q"' in report and 'id="st"' in report and report.count('class="col"') >= 4   # the filters
    for r in rows:
        run = four.out / "runs" / r["run_dir"]
        assert (run / "stack" / "summary.json").is_file() and (run / "bridge.log").is_file()
        assert f'href="runs/{r["run_dir"]}/bridge.log"' in report
        # each run had its own ptys, and the bridge removed them when it stopped
        assert (run / "pty").is_dir() and not any((run / "pty").iterdir())
        # the current of the case reached the bridge (its timeline logs it)
        log = (run / "bridge.log").read_text()
        cur = json.loads(r["param.current_m_s"])[0]
        if cur:
            assert "current velocity=(0.02, 0.0, 0.0)" in log
            assert (run / "scenario" / "scenario.toml").is_file()
        else:
            assert "velocity=(0.02" not in log
    if HAS_TRUTH:
        assert all(r["truth.contacts"] == 0 for r in rows)


def test_resume_runs_only_what_is_missing_or_errored(four: Outcome) -> None:
    """--resume after a crash: a run missing from the journal and a run recorded as an error
    (its bridge or stack could not run) are run again; a failed run is a result and is kept."""
    journal = four.out / "results.jsonl"
    rows = [json.loads(ln) for ln in journal.read_text().splitlines()]
    keep = [r for r in rows if r["index"] != 2]
    for r in keep:
        if r["index"] == 1:
            r.update(status="error", failed="error", failure="RuntimeError: the bridge did not come up")
        elif r["index"] == 3:
            r.update(status="fail", failed="depth")
    journal.write_text("".join(json.dumps(r) + "\n" for r in keep))
    before = {r["key"]: r["wall_s"] for r in keep if r["index"] != 1}
    untouched = four.out / "runs" / next(r for r in keep if r["index"] == 0)["run_dir"] / "bridge.log"
    mtime = untouched.stat().st_mtime_ns
    again = run_campaign(four.campaign.path, out=four.out, resume=True)
    assert again.ran == 2
    assert len(again.rows) == 4 and sorted(r["index"] for r in again.rows) == [0, 1, 2, 3]  # one row a run
    expected = table(four)
    key3 = next(r["key"] for r in again.rows if r["index"] == 3)
    expected[key3] = ("fail", "depth")
    assert table(again) == expected
    redone = [r for r in again.rows if r["index"] in (1, 2)]
    assert [r["status"] for r in redone] == ["pass", "pass"]
    assert {r["key"]: r["wall_s"] for r in again.rows if r["index"] not in (1, 2)} == before
    assert untouched.stat().st_mtime_ns == mtime
    assert len(read_table(four.out / "results.parquet")) == 4


def _listening(pids: set[int]) -> list[str]:
    """Local addresses (hex, as /proc/net shows them) of the TCP sockets ``pids`` listen on."""
    inodes = set()
    for pid in pids:
        try:
            for fd in Path(f"/proc/{pid}/fd").iterdir():
                link = os.readlink(fd)
                if link.startswith("socket:["):
                    inodes.add(link[8:-1])
        except OSError:
            continue
    out = []
    for table_ in ("/proc/net/tcp", "/proc/net/tcp6"):
        for ln in Path(table_).read_text().splitlines()[1:]:
            f = ln.split()
            if f[3] == "0A" and f[9] in inodes:   # LISTEN
                out.append(f[1])
    return out


def _descendants(pid: int) -> set[int]:
    kids: dict[int, list[int]] = {}
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                ppid = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            kids.setdefault(ppid, []).append(int(proc.name))
    out, todo = set(), [pid]
    while todo:
        for k in kids.get(todo.pop(), []):
            if k not in out:
                out.add(k)
                todo.append(k)
    return out


def test_the_same_campaign_on_ray_local_gives_the_same_table(four: Outcome, tmp_path: Path) -> None:
    from hilsim.campaign.executors import ray_available

    why = ray_available()
    if why:
        pytest.skip(why)
    class Watch(io.StringIO):
        """The progress stream: as each run ends (Ray up), the addresses Ray's processes listen on."""
        seen: list[str] = []

        def write(self, text: str) -> int:
            self.seen += _listening(_descendants(os.getpid()) | {os.getpid()})
            return super().write(text)

    watch = Watch()
    # the seed-1 half of the campaign (the same cases, keys and seeds: a case's key is its parameters')
    half = tmp_path / "half.toml"
    half.write_text(four.campaign.path.read_text().replace("seed = [1, 2]", "seed = [1]"))
    o = run_campaign(half, out=tmp_path / "ray", ray="local", ray_cpus=2, stream=watch)
    assert len(o.rows) == 2 and all(r["params"]["seed"] == 1 for r in o.rows)
    same_cases = {k: v for k, v in table(four).items() if k in table(o)}
    assert len(same_cases) == 2 and table(o) == same_cases
    for r in o.rows:   # the run folders came back from the Ray workers
        run = o.out / "runs" / r["run_dir"]
        assert (run / "stack" / "summary.json").is_file() and (run / "bridge.log").is_file()
    # the local Ray listened on loopback only, and stopped with the campaign
    assert watch.seen, "no listening socket found for Ray's processes"
    assert all(_loopback(a) for a in watch.seen), watch.seen
    assert not any(b"raylet" in (Path(f"/proc/{p}/cmdline").read_bytes() if Path(f"/proc/{p}/cmdline").exists()
                                 else b"") for p in _descendants(os.getpid()))


def _loopback(hex_addr: str) -> bool:
    """/proc/net/tcp{,6} local address: 127.0.0.0/8 (little-endian hex, first octet last), ::1, ::ffff:127.x."""
    ip = hex_addr.split(":")[0]
    if len(ip) == 8:
        return ip.endswith("7F")
    return ip == "00000000000000000000000001000000" or (ip.startswith("0000000000000000FFFF0000") and ip.endswith("7F"))


def test_a_failed_thruster_fails_the_criterion_it_cannot_meet(tmp_path: Path) -> None:
    criterion = "truth.max_depth_m > 1.7" if HAS_TRUTH else "summary.depth.final_m > 1.7"
    (tmp_path / "f.toml").write_text(f"""name = "failed_thrusters"
scenario = "water_tank"
time_scale = 4.0
duration_s = 40.0
[stack]
command = "{STACK.replace('--timeout 90', '--timeout 12')}"
timeout_s = 60.0
[matrix]
timeline = ["{FAULTS}"]
[pass]
dived = "{criterion}"
""")
    o = run_campaign(tmp_path / "f.toml", out=tmp_path / "out")
    (r,) = o.rows
    assert r["status"] == "fail" and r["failed"] == "dived", r["failure"]
    assert r["failure"].startswith("dived: ") and "missing" not in r["failure"]
    assert r["exit_code"] == 1 and r["summary"]["success"] is False
    log = (o.out / "runs" / r["run_dir"] / "bridge.log").read_text()
    assert "vertical_front_left" in log


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is dead
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


def test_a_hung_stack_is_timed_out_recorded_and_cleaned_up(tmp_path: Path) -> None:
    (tmp_path / "h.toml").write_text("""name = "hang"
scenario = "water_tank"
time_scale = 1.0
[stack]  # seed 1 hangs (with a child of its own); seed 2 exits at once
command = "sh -c 'if [ {seed} = 1 ]; then sleep 600 & echo $! > {run}/child.pid; echo $$ > {run}/stack.pid; wait; fi'"
timeout_s = 3.0
[matrix]
seed = [1, 2]
[pass]
exit = "exit_code == 0"
""")
    t0 = time.monotonic()
    progress = io.StringIO()
    o = run_campaign(tmp_path / "h.toml", out=tmp_path / "out", workers=1, stream=progress)
    took = time.monotonic() - t0
    lines = progress.getvalue().splitlines()
    assert lines[0].startswith("campaign hang: 1/2 (timeout 1) elapsed 0:00:") and "ETA 0:00:" in lines[0]
    assert lines[1].startswith("campaign hang: 2/2 (pass 1, timeout 1)") and lines[1].endswith("ETA 0:00:00")
    r, ok = o.rows
    assert ok["status"] == "pass" and ok["exit_code"] == 0   # the campaign went on after the hung run
    assert r["status"] == "timeout" and r["timed_out"] is True and r["exit_code"] is None
    assert "timeout_s = 3 s" in r["failure"]
    assert 3.0 <= r["wall_s"] < 40.0 and took < 90.0
    run = o.out / "runs" / r["run_dir"]
    for name in ("stack.pid", "child.pid"):
        assert not _alive(int((run / name).read_text())), name
    assert r["bridge_exit"] == 0   # the bridge was stopped cleanly by SIGTERM
    # nothing of the run is left: no process names the run folder
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                cmd = (proc / "cmdline").read_bytes().decode(errors="replace")
            except OSError:
                continue
            assert str(run) not in cmd or not _alive(int(proc.name)), cmd


def test_ctrl_c_stops_the_campaign_and_its_runs(tmp_path: Path) -> None:
    import signal
    import subprocess
    import sys

    (tmp_path / "h.toml").write_text("""name = "interrupted"
scenario = "water_tank"
time_scale = 1.0
[stack]
command = "sh -c 'sleep 600 & echo $! > {run}/child.pid; echo $$ > {run}/stack.pid; wait'"
timeout_s = 600.0
""")
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "hilsim", "campaign", str(tmp_path / "h.toml"), "--out", str(out)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not list(out.glob("runs/*/child.pid")) and time.monotonic() < deadline:
            time.sleep(0.1)
        (run,) = [f.parent for f in out.glob("runs/*/child.pid")]
        time.sleep(0.2)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130 and "interrupted" in err and "Traceback" not in err, err
    for name in ("stack.pid", "child.pid"):
        assert not _alive(int((run / name).read_text())), name
    for proc in Path("/proc").iterdir():   # no bridge (nor anything else) of the run is left
        if proc.name.isdigit():
            try:
                cmd = (proc / "cmdline").read_bytes().decode(errors="replace")
            except OSError:
                continue
            assert str(run) not in cmd or not _alive(int(proc.name)), cmd
