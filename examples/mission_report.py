"""The mission's summary (statistics, JSON, CSV) and plots (PNG). Used by examples/mission.py.

Times are seconds of simulation time from the mission's start (the first
control tick); ``t0_unix`` in the summary is that instant as frame time.
"""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np


def _stats(err: np.ndarray) -> dict[str, float | int | None]:
    err = err[np.isfinite(err)]
    if len(err) == 0:
        return {"n": 0, "mean": None, "rms": None, "max_abs": None}
    return {"n": int(len(err)), "mean": round(float(err.mean()), 4), "rms": round(float(np.sqrt((err ** 2).mean())), 4),
            "max_abs": round(float(np.abs(err).max()), 4)}


def _r(x: float | None, nd: int = 3) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), nd)


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def summarize(p: Any, mission: Any, cols: dict[str, list[float]], frames: dict[str, list[float]],
              info: dict[str, Any]) -> dict[str, Any]:
    t = np.asarray(cols.get("t", []), float)
    phases = [{"name": ph.name, "start_s": _r(ph.start, 2), "end_s": _r(ph.end, 2),
               "duration_s": _r(ph.end - ph.start, 2), "outcome": ph.outcome} for ph in mission.phases]
    by_name = {ph.name: ph for ph in mission.phases}

    def window(start: float, end: float) -> np.ndarray:
        """Ticks in [start, end): the tick that ends a phase already belongs to the next one."""
        return (t >= start) & (t < end) if len(t) else np.zeros(0, bool)

    end_all = float(t[-1]) if len(t) else 0.0
    out: dict[str, Any] = {"success": mission.failure is None, "failure": mission.failure,
                           "parameters": {"depth_m": p.depth, "headings_deg": list(p.headings),
                                          "hold_range_m": p.hold_range, "hold_time_s": p.hold_time,
                                          "approach_speed_m_s": p.approach_speed,
                                          "control_rate_hz": p.control_rate},
                           "phases": phases, "duration_s": _r(end_all, 2)}

    # depth: from the end of the dive (settled) to the surfacing (or the end of the mission)
    depth = np.asarray(cols.get("depth", []), float)
    dive = by_name.get("dive")
    d: dict[str, Any] = {"target_m": p.depth, "dive_time_s": _r(dive.end - dive.start, 2) if dive else None}
    surface = by_name.get("surface")
    end_depth = surface.start if surface is not None else end_all
    if dive is not None and math.isfinite(dive.end):
        d["after_dive"] = _stats(depth[window(dive.end, end_depth)] - p.depth)
    if surface is not None:
        sel = window(surface.start, surface.end if math.isfinite(surface.end) else end_all + 1.0)
        d["surface"] = {"target_m": p.surface_depth,
                        "final_m": _r(float(depth[sel][-1])) if sel.any() else None}
    if "hold" in by_name:
        h = by_name["hold"]
        d["hold"] = _stats(depth[window(h.start, h.end if math.isfinite(h.end) else end_all)] - p.depth)
    d["final_m"] = _r(float(depth[-1])) if len(depth) else None
    out["depth"] = d

    # heading: each turn (settling time, overshoot), then the approach and the hold
    heading = np.asarray(cols.get("heading", []), float)
    href = np.asarray(cols.get("heading_ref", []), float)
    herr = _wrap(heading - href) if len(heading) else heading
    hd: dict[str, Any] = {"turns": []}
    for ph in mission.phases:
        if not ph.name.startswith("turn_"):
            continue
        sel = window(ph.start, ph.end if math.isfinite(ph.end) else end_all)
        e = herr[sel]
        start_err = float(e[0]) if len(e) else math.nan
        over = float(np.max(-e * math.copysign(1.0, start_err))) if len(e) and start_err != 0 else 0.0
        hd["turns"].append({"to_deg": float(ph.name[5:]), "settle_s": _r(ph.end - ph.start, 2),
                            "overshoot_deg": _r(max(over, 0.0), 2),
                            "final_error_deg": _r(float(e[-1]) if len(e) else None, 2)})
    for name in ("approach", "hold"):
        if name in by_name:
            ph = by_name[name]
            hd[name] = _stats(herr[window(ph.start, ph.end if math.isfinite(ph.end) else end_all)])
    out["heading"] = hd

    # sonar
    ft = np.asarray(frames.get("t", []), float)
    found = np.asarray(frames.get("found", []), float) > 0.5
    edge = np.asarray(frames.get("shadow_edge", []), float)
    near = np.asarray(frames.get("near_edge", []), float)
    s: dict[str, Any] = {"frames": int(len(ft)), "detections": int(found.sum()),
                         "frames_lost": info.get("frames_lost"), "hold_range_m": p.hold_range}
    ap = by_name.get("approach")
    if mission.first_detection is not None:
        s["first_detection_s"] = _r(mission.first_detection, 2)
        if ap is not None:
            s["detection_after_approach_start_s"] = _r(mission.first_detection - ap.start, 2)
    if "hold" in by_name:
        h = by_name["hold"]
        sel = (ft >= h.start) & (ft < (h.end if math.isfinite(h.end) else end_all + 1.0))
        hs = sel & found
        s["hold"] = {"frames": int(sel.sum()), "detections": int(hs.sum()),
                     "range_m": _stats(edge[hs]) | {"std": _r(float(np.std(edge[hs])), 4) if hs.any() else None},
                     "range_error_m": _stats(edge[hs] - p.hold_range),
                     "near_edge_m": _r(float(np.median(near[hs])) if hs.any() else None),
                     "final_range_m": _r(float(edge[hs][-1]) if hs.any() else None)}
    out["sonar"] = s

    # thrusters
    cmds = np.array([cols.get(f"cmd{i}", []) for i in range(8)], float)
    thrusts = np.array([cols.get(f"thrust{i}", []) for i in range(8)], float)
    out["thrusters"] = {"command": info.get("esc_command"),
                        "max_abs_command": [_r(float(np.max(np.abs(c))) if c.size else None, 4) for c in cmds],
                        "max_abs_thrust_n": [_r(float(np.max(np.abs(c))) if c.size else None, 2) for c in thrusts]}
    out["thrusters"]["faults"] = info.get("thruster_faults", [])
    ok = np.asarray(cols.get("depth_ok", []), float)
    out["depth"]["invalid_readings"] = int(np.sum(ok < 0.5)) if ok.size else 0
    # DVL: the reports the approach and the hold flew on; the altitude and surge velocity in the hold
    dvl_alt = np.asarray(cols.get("dvl_altitude", []), float)
    dvl_vx = np.asarray(cols.get("dvl_vx", []), float)
    dv: dict[str, Any] = {"reports": info.get("dvl_reports", 0), "valid": info.get("dvl_valid", 0)}
    if "hold" in by_name and dvl_alt.size:
        h = by_name["hold"]
        sel = window(h.start, h.end if math.isfinite(h.end) else end_all)
        dv["hold_altitude_m"] = _stats(dvl_alt[sel])
        dv["hold_vx_m_s"] = _stats(dvl_vx[sel])
    out["dvl"] = dv

    # GNSS: the fixes logged at the surface
    g = info.get("gnss_log") or {}
    gq = np.asarray(g.get("quality", []), float)
    gs: dict[str, Any] = {"fixes": int(len(gq)), "sentences": info.get("gnss_sentences", 0)}
    if len(gq):
        gt = np.asarray(g["t"], float)
        gs.update({"first_fix_s": _r(float(gt[0]), 2), "quality": int(gq[-1]),
                   "lat_deg": _r(float(np.mean(g["lat_deg"])), 7), "lon_deg": _r(float(np.mean(g["lon_deg"])), 7),
                   "alt_m": _r(float(np.mean(g["alt_m"])), 2), "satellites": int(g["satellites"][-1]),
                   "hdop": _r(float(g["hdop"][-1]), 2)})
        if surface is not None:
            gs["after_surfacing_start_s"] = _r(float(gt[0]) - surface.start, 2)
    out["gnss"] = gs
    out["timing"] = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in info.items()
                     if k not in ("thruster_faults", "gnss_log")}
    out["control_ticks"] = int(len(t))
    return out


def text(summary: dict[str, Any]) -> str:
    s = summary
    lines = [f"mission {'COMPLETED' if s['success'] else 'FAILED: ' + str(s['failure'])} "
             f"in {s['duration_s']} s of simulation time ({s['timing'].get('wall_s', 0):.1f} s wall, "
             f"clock x{s['timing'].get('time_scale_estimate', 1):.2f})"]
    lines.append("phases: " + ", ".join(f"{ph['name']} {ph['duration_s']} s ({ph['outcome']})" for ph in s["phases"]))
    d = s["depth"]
    if "after_dive" in d:
        a = d["after_dive"]
        lines.append(f"depth {d['target_m']} m: dive {d['dive_time_s']} s; after the dive error mean {a['mean']} m, "
                     f"rms {a['rms']} m, max {a['max_abs']} m")
    for tr in s["heading"]["turns"]:
        lines.append(f"turn to {tr['to_deg']:g} deg: {tr['settle_s']} s, overshoot {tr['overshoot_deg']} deg, "
                     f"final error {tr['final_error_deg']} deg")
    if "hold" in s["heading"]:
        h = s["heading"]["hold"]
        lines.append(f"heading in the hold: error mean {h['mean']} deg, rms {h['rms']} deg, max {h['max_abs']} deg")
    so = s["sonar"]
    det = (f"first at {so['first_detection_s']} s ({so.get('detection_after_approach_start_s')} s into the approach)"
           if "first_detection_s" in so else "none")
    lines.append(f"sonar: {so['frames']} frames ({so['frames_lost']} lost), {so['detections']} detections, {det}")
    if "hold" in so:
        h = so["hold"]
        lines.append(f"target range in the hold: {h['range_m']['mean']} m (std {h['range_m']['std']}, requested "
                     f"{so['hold_range_m']} m), final {h['final_range_m']} m, nearest return {h['near_edge_m']} m, "
                     f"{h['detections']}/{h['frames']} frames with the target")
    for f in s["thrusters"].get("faults", []):
        lines.append(f"thruster {f['thruster']} (VESC {f['controller']}) reported stopped while commanded "
                     f"from t = {f['t_s']} s")
    dv = s.get("dvl", {})
    if dv.get("reports"):
        alt = dv.get("hold_altitude_m", {})
        lines.append(f"DVL: {dv['valid']}/{dv['reports']} reports with bottom lock; altitude in the hold "
                     f"{alt.get('mean')} m")
    g = s.get("gnss", {})
    if g.get("fixes"):
        lines.append(f"GNSS at the surface: {g['fixes']} fixes from {g.get('after_surfacing_start_s')} s after the "
                     f"surfacing began: {g['lat_deg']}, {g['lon_deg']} (quality {g['quality']}, "
                     f"{g['satellites']} satellites)")
    if s["depth"].get("invalid_readings"):
        lines.append(f"depth sensor: {s['depth']['invalid_readings']} control ticks without a valid reading "
                     "(flown on the last good one)")
    return "\n".join(lines)


def _shade(ax: Any, phases: Sequence[dict[str, Any]]) -> None:
    colours = ["#f2f2f2", "#e3ecf7"]
    for i, ph in enumerate(phases):
        if ph["start_s"] is None or ph["end_s"] is None:
            continue
        ax.axvspan(ph["start_s"], ph["end_s"], color=colours[i % 2], zorder=0)
        ax.text(ph["start_s"], 1.0, " " + ph["name"], transform=ax.get_xaxis_transform(), va="top", fontsize=7,
                color="0.35")


def draw_plots(out: Path, summary: dict[str, Any], cols: dict[str, list[float]], frames: dict[str, list[float]],
          names: Sequence[str]) -> list[str]:
    try:
        import matplotlib
    except ImportError:
        print("mission: plots skipped: matplotlib is not installed (pip install matplotlib, "
              "or `pip install -e '.[examples]'` in a hilsim checkout)", file=sys.stderr)
        return []
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(cols.get("t", []), float)
    phases = summary["phases"]
    p = summary["parameters"]
    written = []

    def save(fig: Any, name: str) -> None:
        fig.tight_layout()
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        written.append(name)

    def depth_ax(ax: Any) -> None:
        _shade(ax, phases)
        ax.plot(t, cols["depth"], lw=1.2, label="depth (Keller)")
        ax.plot(t, cols["depth_ref"], "k--", lw=1, label="target")
        ax.invert_yaxis()
        ax.set_ylabel("depth [m]")
        ax.legend(loc="lower right", fontsize=8)

    def heading_ax(ax: Any) -> None:
        _shade(ax, phases)
        ax.plot(t, _wrap(np.asarray(cols["heading"])), lw=1.2, label="heading (WitMotion)")
        ax.plot(t, _wrap(np.asarray(cols["heading_ref"])), "k--", lw=1, label="target")
        ax.set_ylabel("heading [deg]")
        ax.legend(loc="upper right", fontsize=8)

    def range_ax(ax: Any) -> None:
        _shade(ax, phases)
        ft = np.asarray(frames.get("t", []), float)
        found = np.asarray(frames.get("found", []), float) > 0.5
        if len(ft):
            ax.plot(ft, frames["floor_far"], color="0.6", lw=0.8, label="floor far edge (outer beams)")
            ax.plot(ft[found], np.asarray(frames["shadow_edge"])[found], ".", ms=3, label="target shadow edge")
            ax.plot(ft[found], np.asarray(frames["near_edge"])[found], ".", ms=2, color="tab:green",
                    label="nearest return")
        ax.plot(t, cols["range"], color="tab:red", lw=1.2, label="filtered target range")
        ax.axhline(p["hold_range_m"], color="k", ls="--", lw=1, label="requested")
        ax.set_ylabel("range [m]")
        ax.legend(loc="upper right", fontsize=7)

    def thruster_ax(ax: Any, idx: Sequence[int], title: str) -> None:
        _shade(ax, phases)
        for i in idx:
            ax.plot(t, cols[f"cmd{i}"], lw=1, label=names[i])
        ax.set_ylabel(f"{summary['thrusters']['command']} ({title})")
        ax.legend(loc="upper right", fontsize=7, ncol=2)

    for name, draw in (("depth.png", depth_ax), ("heading.png", heading_ax), ("range.png", range_ax)):
        fig, ax = plt.subplots(figsize=(9, 3.4))
        draw(ax)
        ax.set_xlabel("simulation time [s]")
        save(fig, name)
    fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    thruster_ax(axes[0], range(0, 4), "horizontal")
    thruster_ax(axes[1], range(4, 8), "vertical")
    axes[1].set_xlabel("simulation time [s]")
    save(fig, "thrusters.png")
    fig, axes = plt.subplots(4, 1, figsize=(9, 11), sharex=True)
    depth_ax(axes[0])
    heading_ax(axes[1])
    range_ax(axes[2])
    thruster_ax(axes[3], range(8), "all")
    axes[3].set_xlabel("simulation time [s]")
    axes[0].set_title("reference mission: " + ("completed" if summary["success"] else f"FAILED ({summary['failure']})"))
    save(fig, "overview.png")
    return written


def _csv(path: Path, cols: dict[str, list[float]]) -> None:
    keys = list(cols)
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(keys)
        for row in zip(*(cols[k] for k in keys)):
            w.writerow([f"{v:.6g}" if isinstance(v, float) else v for v in row])


def write_outputs(out: Path, p: Any, mission: Any, cols: dict[str, list[float]], frames: dict[str, list[float]],
                  info: dict[str, Any], plots: bool = True, thruster_names: Sequence[str] = ()) -> dict[str, Any]:
    """summary.json, mission_log.csv (control ticks), sonar_log.csv (frames) and the PNGs into ``out``.
    Returns the summary with its printable form under "text" (not in the JSON)."""
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(p, mission, cols, frames, info)
    files = ["summary.json", "mission_log.csv", "sonar_log.csv"]
    _csv(out / "mission_log.csv", cols)
    _csv(out / "sonar_log.csv", frames)
    if plots and cols.get("t"):
        files += draw_plots(out, summary, cols, frames, thruster_names)
    summary["files"] = files
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    summary["text"] = text(summary) + f"\nwritten to {out}/: " + ", ".join(files)
    return summary
