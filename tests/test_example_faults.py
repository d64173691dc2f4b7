"""The reference control stack (examples/) under injected faults, end to end on a real bridge.

The scenario is the default water tank with a ``[[timeline]]`` that, mid-mission,
(1) drops the Keller depth sensor out for 1.5 s (simulation time 20 s): P1 reads
NaN, its documented channel error, and (2) fails the thruster
``vertical_front_left`` for good (simulation time 30 s): its rotor stops and its
VESC (controller id 5) reports 0 ERPM in STATUS_1 while commands keep coming.

What the stack is expected to do, from its own documentation (examples/README.md)
and the physics: it rides out a depth gap shorter than 2 s on the last good
reading; it notices the stopped rotor from the ESC telemetry (a warning and the
summary name the thruster and its controller id); its depth integrator absorbs
the lost thrust, so the three healthy vertical thrusters carry what four did,
and the vertical demand settles where the vehicle's net buoyancy (Table 1's
W_w = -2.5 N, from devices/vehicles/cyclops.toml) puts it: 4 x demand before,
3 x demand after. The mission completes; depth and the sonar range hold. No
hilsim import: the stack and this test see the bridge through the wire only.
"""

from __future__ import annotations

import csv
import json
import math
import signal
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.alone  # missions load both cores: make test runs these after the others, one at a time

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
SCENARIO = ROOT / "scenarios" / "water_tank" / "scenario.toml"
VEHICLE = ROOT / "devices" / "vehicles" / "cyclops.toml"

DEPTH, HOLD_RANGE, HOLD_TIME = 1.8, 1.25, 10.0
DROPOUT_AT, DROPOUT_S = 20.0, 1.5     # [s] simulation time of the bridge
FAIL_AT = 30.0
FAILED, PEER = 4, 5                    # thruster indices (vertical_front_left, vertical_front_right)

TIMELINE = f'''
[[timeline]]
at_s = {DROPOUT_AT}
action = "fault"
target = "depth"
fault = "dropout"
duration_s = {DROPOUT_S}

[[timeline]]
at_s = {FAIL_AT}
action = "fault"
target = "thruster:vertical_front_left"
fault = "fail"
'''


def _net_buoyancy() -> float:
    """[N] the force the vertical thrusters must push down with to hold depth (-W_w, Table 1)."""
    prof = tomllib.loads(VEHICLE.read_text())
    return -float(prof["dynamics"]["heave"]["constant_force"]["value"])


@pytest.fixture(scope="module")
def faulted(tmp_path_factory: pytest.TempPathFactory) -> dict:
    tmp = tmp_path_factory.mktemp("faults")
    scenario = tmp / "scenario.toml"
    scenario.write_text(SCENARIO.read_text() + TIMELINE)
    out = tmp / "out"
    with open(tmp / "demo.log", "w") as log:
        proc = subprocess.Popen(
            [sys.executable, str(EXAMPLES / "demo.py"), "--time-scale", "4", "--out", str(out),
             "--scenario", str(scenario), "--", "--depth", str(DEPTH), "--hold-range", str(HOLD_RANGE),
             "--hold-time", str(HOLD_TIME), "--no-plots"],
            stdout=log, stderr=subprocess.STDOUT, cwd=tmp)
        try:
            proc.wait(timeout=180)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else {}
    rows = list(csv.DictReader(open(out / "mission_log.csv"))) if (out / "mission_log.csv").exists() else []
    cols = {k: np.array([float(r[k]) for r in rows]) for k in (rows[0] if rows else {})}
    return {"rc": proc.returncode, "log": (tmp / "demo.log").read_text(errors="replace"), "summary": summary,
            "cols": cols}


def _offset(cols: dict) -> float:
    """[s] bridge simulation time minus mission time, from the dropout's first NaN reading."""
    bad = cols["t"][cols["depth_ok"] < 0.5]
    assert len(bad), "the depth dropout never showed on the wire"
    return DROPOUT_AT - float(bad[0])


def test_the_mission_completes_through_both_faults(faulted):
    assert faulted["rc"] == 0, faulted["log"][-3000:]
    s = faulted["summary"]
    assert s["success"], s.get("failure")
    assert [p["outcome"] for p in s["phases"]] == ["settled"] * 4 + ["completed"]
    assert "Traceback" not in faulted["log"]


def test_the_depth_dropout_reads_nan_for_its_duration_and_is_ridden_out(faulted):
    c = faulted["cols"]
    bad = c["t"][c["depth_ok"] < 0.5]
    # one contiguous gap as long as the fault (the control rate is 10 Hz; the poll may straddle the ends)
    assert len(bad) == faulted["summary"]["depth"]["invalid_readings"] >= 5
    # one gap no longer than the fault (a starved machine may skip control ticks inside it)
    assert bad[-1] - bad[0] <= DROPOUT_S + 0.2, bad
    ok_inside = (c["t"] > bad[0]) & (c["t"] < bad[-1]) & (c["depth_ok"] > 0.5)
    assert not ok_inside.any(), "the dropout should be one gap"
    # the stack flew on the last good reading: the depth stayed put through the gap and after it
    gap = (c["t"] >= bad[0] - 1.0) & (c["t"] <= bad[-1] + 3.0)
    assert np.all(np.abs(c["depth"][gap] - DEPTH) < 0.05)


def test_the_failed_thruster_shows_zero_erpm_and_the_stack_flags_it(faulted):
    c, s = faulted["cols"], faulted["summary"]
    fail_t = FAIL_AT - _offset(c)                        # mission time of the failure
    before = (c["t"] > fail_t - 12.0) & (c["t"] < fail_t - 0.2)
    after = c["t"] > fail_t + 1.5                        # the rotor has spun down
    f, peer = c[f"erpm{FAILED}"], c[f"erpm{PEER}"]
    # before: the two front vertical ESCs, given the same demand, report the same speed, and spin
    spun = before & (np.abs(peer) > 500)
    assert spun.sum() >= 5
    # (the stack reads each ESC's latest STATUS_1: while the demand swings, one of the two may be a
    # status period behind the other, so a few ticks differ by more)
    close = np.abs(f[spun] - peer[spun]) <= 0.1 * np.abs(peer[spun]) + 200
    assert close.mean() >= 0.9, (f[spun][~close], peer[spun][~close])
    # after: controller 5 reads 0 ERPM on every tick while its peer spins on
    assert np.all(f[after] == 0), f[after][f[after] != 0][:5]
    assert (np.abs(peer[after]) > 500).sum() >= 10
    assert np.all(c[f"thrust{FAILED}"][after] == c[f"thrust{PEER}"][after])   # still commanded like its peer
    # the stack noticed: exactly this thruster, after the failure, within its documented evidence time
    assert [(x["thruster"], x["controller"]) for x in s["thrusters"]["faults"]] == [("vertical_front_left", 5)]
    t_flag = s["thrusters"]["faults"][0]["t_s"]
    assert fail_t < t_flag < fail_t + 8.0
    assert "WARNING thruster vertical_front_left" in faulted["log"]


def test_the_depth_loop_absorbs_the_lost_thruster_as_the_buoyancy_requires(faulted):
    c = faulted["cols"]
    fail_t = FAIL_AT - _offset(c)
    w = _net_buoyancy()                                  # 2.5 N for Cyclops
    dive_end = next(p for p in faulted["summary"]["phases"] if p["name"] == "dive")["end_s"]
    before = (c["t"] > dive_end + 4.0) & (c["t"] < fail_t - 0.2)
    after = c["t"] > fail_t + 8.0                        # the integrator has caught up
    assert before.sum() >= 50 and after.sum() >= 50, (dive_end, fail_t, c["t"][-1])
    vertical = c[f"thrust{FAILED}"]                      # the stack demands the same of all four
    # 4 thrusters hold the buoyancy before, 3 after: the demand per thruster rises by 4/3
    # (had the lost thrust not been made up, 3 x the old demand would fall 25 % short)
    n_before, n_after = 4 * vertical[before].mean(), 3 * vertical[after].mean()
    print(f"\nnet vertical thrust demanded: {n_before:.2f} N on 4 thrusters before, {n_after:.2f} N on 3 after "
          f"(-W_w = {w:.2f} N)")
    assert n_before == pytest.approx(w, rel=0.2), n_before
    assert n_after == pytest.approx(w, rel=0.2), n_after
    assert np.all(np.abs(c["depth"][c["t"] > fail_t] - DEPTH) < 0.05)
    hold = faulted["summary"]["sonar"]["hold"]
    assert abs(hold["range_m"]["mean"] - HOLD_RANGE) < 0.05
