"""Truth metrics from a truth.csv written here by hand (values checked against arithmetic, not our output)."""

from __future__ import annotations

import math
from pathlib import Path

from hilsim.campaign.metrics import read_truth, truth_metrics

HEAD = ("time_s,north_m,east_m,down_m,roll_deg,pitch_deg,yaw_deg,u_m_s,v_m_s,w_m_s,p_deg_s,q_deg_s,r_deg_s,"
        "thrust_N.a,contact,contact_object,contact_force_N,penetration_m,clearance_m,altitude_m,faults,surfaced")


def test_truth_metrics_of_a_small_table(tmp_path: Path) -> None:
    rows = [  # t, n, e, d, yaw, u, v, w, contact, object, force, pen, clearance, altitude, faults
        (0.0, 0.0, 0.0, 1.5, 0.0, 0.0, 0.0, 0.0, 0, "", 0.0, 0.0, 0.8, 1.5, ""),
        (0.5, 3.0, 4.0, 1.5, 10.0, 3.0, 4.0, 0.0, 1, "cuboid", 12.5, 0.001, 0.0, 0.2, ""),
        (1.0, 3.0, 4.0, 1.8, 20.0, 0.0, 0.0, 0.6, 1, "cuboid;floor", 20.0, 0.0008, 0.0, "inf", "thruster:0:fail"),
        (1.5, 3.0, 4.0, 1.9, 30.0, 0.0, 0.0, 0.0, 0, "", 0.0, 0.0, 0.3, 1.1, "thruster:0:fail"),
        (2.0, 3.0, 4.0, 1.7, 40.0, 0.0, 0.0, 0.0, 1, "floor", 5.0, 0.0002, 0.0, 1.0, ""),
    ]
    lines = [HEAD]
    for t, n, e, d, yaw, u, v, w, c, obj, f, pen, cl, alt, fl in rows:
        lines.append(f"{t},{n},{e},{d},0,0,{yaw},{u},{v},{w},0,0,0,1.0,{c},{obj},{f},{pen},{cl},{alt},{fl},0")
    p = tmp_path / "truth.csv"
    p.write_text("\n".join(lines) + "\n")
    m = truth_metrics(read_truth(p), {"depth_target_m": 1.8, "depth_from_s": 1.0})
    assert m["samples"] == 5 and m["sim_time_s"] == 2.0
    assert m["contacts"] == 2                              # onsets at 0.5 s and 2.0 s
    assert m["contact_time_s"] == 1.0                      # rows at 0.5, 1.0 (0.5 s each), 2.0 (last: 0)
    assert m["contact_objects"] == "cuboid;floor"
    assert m["max_contact_force_N"] == 20.0 and m["max_penetration_m"] == 0.001
    assert m["min_clearance_m"] == 0.0 and m["min_altitude_m"] == 0.2   # inf is no surface below
    assert m["max_depth_m"] == 1.9 and m["min_depth_m"] == 1.5 and m["final_depth_m"] == 1.7
    assert math.isclose(m["distance_m"], 5.0 + 0.3 + 0.1 + 0.2)
    assert math.isclose(m["max_speed_m_s"], 5.0)
    assert m["final_north_m"] == 3.0 and m["final_east_m"] == 4.0 and m["final_yaw_deg"] == 40.0
    assert m["fault_time_s"] == 1.0                        # rows at 1.0 and 1.5
    # from 1.0 s on: errors 0.0, 0.1, -0.1
    assert math.isclose(m["max_depth_error_m"], 0.1) and math.isclose(m["rms_depth_error_m"], math.sqrt(0.02 / 3), abs_tol=1e-6)  # rounded to 1 um
    last = truth_metrics(read_truth(p), {"depth_target_m": 1.8, "depth_last_s": 0.6})   # rows at 1.5 and 2.0 s
    assert math.isclose(last["max_depth_error_m"], 0.1) and math.isclose(last["rms_depth_error_m"], 0.1)


def test_a_run_without_contact_counts_none(tmp_path: Path) -> None:
    p = tmp_path / "truth.csv"
    p.write_text(HEAD + "\n" + "\n".join(f"{t},0,0,1.5,0,0,0,0,0,0,0,0,0,0,0,,0,0,0.5,1.5,,0" for t in (0.0, 0.05)) + "\n")
    m = truth_metrics(read_truth(p))
    assert m["contacts"] == 0 and m["contact_time_s"] == 0.0 and m["contact_objects"] == ""
    assert m["fault_time_s"] == 0.0 and "max_depth_error_m" not in m
