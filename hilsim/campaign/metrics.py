"""Metrics of the bridge's ground truth (``truth.csv`` of ``hilsim run --truth FILE``).

The file has a header row and one row per truth sample (20 Hz by default):
``time_s, north_m, east_m, down_m, roll_deg, pitch_deg, yaw_deg, u_m_s, v_m_s,
w_m_s, p_deg_s, q_deg_s, r_deg_s``, ``thrust_N.<thruster>`` per thruster,
``contact`` (0/1), ``contact_object``, ``contact_force_N``, ``penetration_m``,
``clearance_m``, ``altitude_m``, ``faults``. Missing columns give no metric
(a criterion naming one then fails as "missing").
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np


def read_truth(path: Path) -> dict[str, np.ndarray]:
    """Columns of a truth CSV: numeric columns as float arrays, the others as object arrays."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        return {}
    head = [h.strip() for h in rows[0]]
    body = [r for r in rows[1:] if len(r) == len(head)]
    cols: dict[str, np.ndarray] = {}
    for j, name in enumerate(head):
        raw = [r[j] for r in body]
        try:
            cols[name] = np.array([float(x) if x.strip() != "" else math.nan for x in raw], dtype=float)
        except ValueError:
            cols[name] = np.array(raw, dtype=object)
    return cols


def _f(x: Any) -> float | None:
    v = float(x)
    return round(v, 6) if math.isfinite(v) else None


def _nanmax(a: np.ndarray) -> float | None:
    a = a[np.isfinite(a)]
    return _f(a.max()) if a.size else None


def _nanmin(a: np.ndarray) -> float | None:
    a = a[np.isfinite(a)]
    return _f(a.min()) if a.size else None


def truth_metrics(cols: Mapping[str, np.ndarray], params: Mapping[str, float] | None = None) -> dict[str, Any]:
    """Scalar metrics of a truth table.

    Always (where the columns exist): ``samples``, ``sim_time_s``; ``contacts`` (number of
    contact onsets, a run starting in contact counts one), ``contact_time_s``,
    ``contact_objects`` (names, ";"-joined), ``max_contact_force_N``, ``max_penetration_m``;
    ``min_clearance_m``, ``min_altitude_m``; ``max_depth_m``, ``min_depth_m``, ``final_depth_m``,
    ``final_north_m``, ``final_east_m``, ``final_yaw_deg``; ``distance_m`` (path length);
    ``max_speed_m_s`` (|(u, v, w)|); ``fault_time_s`` (time with any fault active).
    With ``depth_target_m`` in ``params``: ``max_depth_error_m`` and ``rms_depth_error_m`` of
    ``down_m`` against the target from ``depth_from_s`` [s of simulation time] on (default 0), and
    only over the last ``depth_last_s`` [s] of the run when that is given.
    """
    params = params or {}
    m: dict[str, Any] = {}
    t = cols.get("time_s")
    if t is None or t.size == 0:
        return m
    m["samples"] = int(t.size)
    m["sim_time_s"] = _f(t[-1])
    dt = np.diff(t, append=t[-1])
    if "contact" in cols:
        c = np.nan_to_num(cols["contact"].astype(float)) > 0.5
        m["contacts"] = int(np.count_nonzero(c[1:] & ~c[:-1]) + (1 if c.size and c[0] else 0))
        m["contact_time_s"] = _f(float(np.sum(dt[c])))
        if "contact_object" in cols:
            names = sorted({n for x, on in zip(cols["contact_object"], c) if on
                            for n in str(x).split(";") if n not in ("", "nan")})
            m["contact_objects"] = ";".join(names)
    for col, key in (("contact_force_N", "max_contact_force_N"), ("penetration_m", "max_penetration_m")):
        if col in cols and cols[col].dtype == float:
            m[key] = _nanmax(cols[col]) if np.isfinite(cols[col]).any() else 0.0
    for col, key in (("clearance_m", "min_clearance_m"), ("altitude_m", "min_altitude_m")):
        if col in cols and cols[col].dtype == float:
            m[key] = _nanmin(cols[col])
    if "down_m" in cols:
        z = cols["down_m"]
        m["max_depth_m"], m["min_depth_m"], m["final_depth_m"] = _nanmax(z), _nanmin(z), _f(z[-1])
        target = params.get("depth_target_m")
        if target is not None:
            start = params.get("depth_from_s", 0.0)
            if "depth_last_s" in params:
                start = max(start, float(t[-1]) - params["depth_last_s"])
            sel = (t >= start) & np.isfinite(z)
            if sel.any():
                err = z[sel] - target
                m["max_depth_error_m"] = _f(np.max(np.abs(err)))
                m["rms_depth_error_m"] = _f(np.sqrt(np.mean(err * err)))
    if "north_m" in cols and "east_m" in cols:
        m["final_north_m"], m["final_east_m"] = _f(cols["north_m"][-1]), _f(cols["east_m"][-1])
        if "down_m" in cols:
            p = np.stack([cols["north_m"], cols["east_m"], cols["down_m"]], axis=1)
            m["distance_m"] = _f(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
    if "yaw_deg" in cols:
        m["final_yaw_deg"] = _f(cols["yaw_deg"][-1])
    if all(k in cols for k in ("u_m_s", "v_m_s", "w_m_s")):
        m["max_speed_m_s"] = _nanmax(np.sqrt(cols["u_m_s"] ** 2 + cols["v_m_s"] ** 2 + cols["w_m_s"] ** 2))
    if "faults" in cols:
        f = cols["faults"]
        active = np.array([str(x) not in ("", "nan", "0") for x in f]) if f.dtype == object else np.nan_to_num(f) > 0
        m["fault_time_s"] = _f(float(np.sum(dt[active])))
    return m
