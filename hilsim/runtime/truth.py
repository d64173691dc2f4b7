"""The ground truth of a run: ``truth.csv``, contact events, and the run's summary JSON.

:class:`TruthRecorder` listens to a :class:`~hilsim.runtime.scheduler.VehicleLoop`
(``tick_listeners``): every physics tick feeds the contact events, and one row
per physics tick, decimated to ``rate_hz`` (20 Hz by default; 0 or None: every
tick), goes to the CSV file::

    time_s, north_m, east_m, down_m, roll_deg, pitch_deg, yaw_deg, u_m_s, v_m_s, w_m_s,
    p_deg_s, q_deg_s, r_deg_s, thrust_N.<thruster>..., contact, contact_object,
    contact_force_N, penetration_m, clearance_m, altitude_m, faults, surfaced,
    <columns added with add_columns>...

``contact`` is 1 while the hull overlaps a solid object (``contact_object``: their
names joined by ``;``), ``contact_force_N`` the normal force on the hull,
``penetration_m`` the overlap the sensors see (at most the contact's 1 mm resting
overlap), ``clearance_m`` the hull's distance to the nearest object (0 in contact),
``altitude_m`` the distance from the body origin straight down to the first surface
(``inf``: none), ``faults`` the active faults as ``target:fault`` joined by ``;``,
``surfaced`` 1 while the hull's top is at the water surface.

:class:`ContactEvents` turns the per-tick contacts into events, one per object
touched (a contact that lifts off for less than ``hold_s`` continues the same
event): start, end, peak force, normal speed at impact, largest overlap. Each
start and end is logged as one line (logger ``hilsim.contact``).

:func:`run_summary` and :func:`write_summary` make the summary JSON written at
shutdown. Plumbing only: every number comes from the simulator.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
from pathlib import Path
from typing import IO, Any, Callable, Iterable, Mapping, Sequence

log = logging.getLogger("hilsim.contact")
_tlog = logging.getLogger("hilsim.truth")

DEFAULT_TRUTH_RATE = 20.0  # [Hz]
BASE_COLUMNS = ("time_s", "north_m", "east_m", "down_m", "roll_deg", "pitch_deg", "yaw_deg",
                "u_m_s", "v_m_s", "w_m_s", "p_deg_s", "q_deg_s", "r_deg_s")
CONTACT_COLUMNS = ("contact", "contact_object", "contact_force_N", "penetration_m", "clearance_m",
                   "altitude_m", "faults", "surfaced")
_DEG = 180.0 / math.pi


def _num(v: float) -> str:
    return "inf" if v == math.inf else f"{v:.9g}"


class ContactEvents:
    """Contact events from the contact step's reports.

    hold_s [s]: a contact that lifts off for less than this continues the same event.
    on_event(kind, event): called with ``"start"`` or ``"end"`` and the event dict
    (``start_s, end_s, object, peak_force_N, impact_speed_m_s, max_penetration_m``)."""

    def __init__(self, hold_s: float = 0.2,
                 on_event: Callable[[str, Mapping[str, Any]], None] | None = None) -> None:
        self.hold_s = float(hold_s)
        self.on_event = on_event
        self.events: list[dict[str, Any]] = []
        self._open: dict[str, dict[str, Any]] = {}

    @property
    def count(self) -> int:
        """Contacts so far (open ones included)."""
        return len(self.events)

    def update(self, t: float, info: Any) -> None:
        """One physics tick at time ``t`` [s]; ``info`` a :class:`hilsim.sim.contact.ContactInfo`."""
        objects = info.objects
        if not objects and not self._open:
            return
        for k, name in enumerate(objects):
            ev = self._open.get(name)
            if ev is None:
                ev = {"start_s": t, "end_s": t, "object": name, "peak_force_N": 0.0,
                      "impact_speed_m_s": float(info.speeds[k]), "max_penetration_m": 0.0}
                self._open[name] = ev
                self.events.append(ev)
                log.info("contact start t=%.3f s object %s impact speed %.3f m/s", t, name, ev["impact_speed_m_s"])
                self._emit("start", ev, float(info.forces[k]))
            ev["end_s"] = t
            ev["peak_force_N"] = max(ev["peak_force_N"], float(info.forces[k]))
            ev["max_penetration_m"] = max(ev["max_penetration_m"], min(float(info.depths[k]), info.penetration))
        for name in [n for n, ev in self._open.items() if n not in objects and t - ev["end_s"] >= self.hold_s]:
            self._end(name)

    def _end(self, name: str) -> None:
        ev = self._open.pop(name)
        log.info("contact end t=%.3f s object %s after %.3f s, peak force %.1f N, max penetration %.4f m",
                 ev["end_s"], name, ev["end_s"] - ev["start_s"], ev["peak_force_N"], ev["max_penetration_m"])
        self._emit("end", ev, 0.0)

    def _emit(self, kind: str, ev: Mapping[str, Any], force: float) -> None:
        if self.on_event is not None:
            self.on_event(kind, {**ev, "force_N": force if kind == "start" else ev["peak_force_N"]})

    def close(self) -> None:
        """End every open contact (at its last touching tick)."""
        for name in list(self._open):
            self._end(name)

    def summary(self) -> dict[str, Any]:
        """``{"count": N, "events": [...]}`` for the summary JSON (numbers rounded)."""
        keys = ("start_s", "end_s", "object", "peak_force_N", "impact_speed_m_s", "max_penetration_m")
        evs = [{k: (round(e[k], 6) if isinstance(e[k], float) else e[k]) for k in keys} for e in self.events]
        return {"count": len(evs), "events": evs}


class TruthRecorder:
    """Writes ``truth.csv`` from a vehicle loop's physics ticks.

    path: the CSV file; loop: a :class:`~hilsim.runtime.scheduler.VehicleLoop` (its
    thrusters name the thrust columns; its contact model answers clearance and
    altitude); rate_hz [Hz]: rows per simulated second (0 or None: every tick);
    faults: an object with ``active()`` -> ``[{"target", "fault", ...}]`` and a
    ``history`` of records with ``t, target, fault, on`` (hilsim.runtime.faults.Faults), or None;
    events: the :class:`ContactEvents` to feed (a new one by default).
    """

    def __init__(self, path: Path | str, loop: Any, rate_hz: float | None = DEFAULT_TRUTH_RATE,
                 faults: Any = None, events: ContactEvents | None = None) -> None:
        self.path = Path(path)
        self.loop = loop
        self.period = 1.0 / rate_hz if rate_hz else 0.0
        self.faults = faults
        self.events = events if events is not None else ContactEvents()
        self.thruster_names: tuple[str, ...] = tuple(loop.thrusters.names) if loop.thrusters is not None else ()
        self._extra: list[tuple[tuple[str, ...], Callable[[Any], Sequence[Any]]]] = []
        self._file: IO[str] | None = None
        self._writer: Any = None
        self._next = -math.inf
        self._failed = self._closed = False
        self.rows = 0
        self.last_time = 0.0

    @property
    def columns(self) -> tuple[str, ...]:
        """The CSV header."""
        cols = BASE_COLUMNS + tuple(f"thrust_N.{n}" for n in self.thruster_names) + CONTACT_COLUMNS
        for names, _ in self._extra:
            cols += names
        return cols

    def add_columns(self, names: Iterable[str], fn: Callable[[Any], Sequence[Any]]) -> None:
        """More columns: ``fn(state)`` returns one value per name at each row. Before the first row."""
        if self._file is not None:
            raise RuntimeError("add_columns after the truth file was started")
        names = tuple(names)
        clash = set(names) & set(self.columns)
        if clash:
            raise ValueError(f"truth columns already exist: {sorted(clash)}")
        self._extra.append((names, fn))

    def attach(self) -> "TruthRecorder":
        """Start listening to the loop's physics ticks (the file is opened at the first row)."""
        self.loop.tick_listeners.append(self.on_tick)
        return self

    def on_tick(self, state: Any, info: Any) -> None:
        """A physics tick: feed the events; write a row when one is due."""
        t = state.time
        self.last_time = t
        self.events.update(t, info)
        if t + 1e-9 < self._next:
            return
        self._next = t + self.period if self._next == -math.inf else max(self._next + self.period, t)
        self._write(state, info)

    def open(self) -> None:
        """Create the file and write the header (at the first row if not called; OSError if the
        file cannot be written: call it at start to find out then)."""
        if self._file is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "w", newline="", encoding="utf-8")
            self._writer = csv.writer(self._file)
            self._writer.writerow(self.columns)

    def _write(self, state: Any, info: Any) -> None:
        if self._failed or self._closed:
            return
        try:
            self._row(state, info)
        except OSError as exc:  # a full disk: the run goes on without its truth file
            self._failed = True
            _tlog.error("ground truth: cannot write %s (%s); no more rows are recorded", self.path, exc)

    def _row(self, state: Any, info: Any) -> None:
        self.open()
        f = state.flat()
        row = [f"{state.time:.6f}"] + [_num(v) for v in f[0:3]] + [_num(v * _DEG) for v in f[3:6]]
        row += [_num(v) for v in f[6:9]] + [_num(v * _DEG) for v in f[9:12]]
        if self.thruster_names:
            row += [_num(float(x)) for x in self.loop.thrusters.thrusts()]
        contacts = self.loop.contacts
        clearance = 0.0 if info.objects else contacts.clearance(state)[0]
        row += ["1" if info.objects else "0", ";".join(info.objects), _num(info.force),
                _num(info.penetration if info.objects else 0.0), _num(clearance), _num(contacts.altitude(state)),
                ";".join(self.active_faults()), "1" if info.surfaced else "0"]
        for names, fn in self._extra:
            vals = list(fn(state))
            if len(vals) != len(names):
                raise ValueError(f"truth columns {names}: got {len(vals)} values")
            row += [_num(v) if isinstance(v, float) else str(v) for v in vals]
        self._writer.writerow(row)
        self.rows += 1

    def active_faults(self) -> list[str]:
        """The active faults as ``target:fault``."""
        if self.faults is None:
            return []
        return [f"{a['target']}:{a['fault']}" for a in self.faults.active()]

    def fault_history(self) -> list[dict[str, Any]]:
        """``[{"t_s", "target", "fault", "on"}]`` from the faults' history."""
        if self.faults is None:
            return []
        return [{"t_s": round(float(r.t), 6), "target": r.target, "fault": r.fault, "on": bool(r.on)}
                for r in self.faults.history]

    def close(self) -> None:
        """End the open contact events and close the file (a file with its header even if no tick ran)."""
        self.events.close()
        if self._closed:
            return
        self._closed = True
        try:
            self.open()  # a file with its header even if no tick ran
            assert self._file is not None
            self._file.close()
        except OSError as exc:
            _tlog.error("ground truth: cannot write %s (%s)", self.path, exc)
        self._file = None


class RunTruth:
    """The ground truth of a bridge's run: the bridge's world under the vehicle's contacts, a
    :class:`TruthRecorder` on its vehicle loop, contact events published on the observers'
    ``contact`` topic (``{"t", "event": "start"/"end", "object", "force_N", "speed_m_s"}``), and
    the summary JSON at :meth:`finish`.

    bridge: a :class:`hilsim.runtime.bridge.Bridge` (uses ``vehicle``, ``world``, ``faults``,
    ``publish``, ``status()``, ``scenario.name``, ``seed``); truth_path, summary_path: files;
    rate_hz [Hz]: truth rows per simulated second (0 or None: every physics tick)."""

    def __init__(self, bridge: Any, truth_path: Path | str, summary_path: Path | str | None,
                 rate_hz: float | None = DEFAULT_TRUTH_RATE) -> None:
        import time

        self.bridge = bridge
        self.summary_path = Path(summary_path) if summary_path is not None else None
        self._wall0 = time.monotonic()
        bridge.vehicle.world = bridge.world
        self.events = ContactEvents(on_event=self._publish)
        self.recorder = TruthRecorder(truth_path, bridge.vehicle, rate_hz, faults=getattr(bridge, "faults", None),
                                      events=self.events).attach()
        for device in getattr(bridge, "devices", ()):  # columns a device offers (a PWM per servo output)
            columns = getattr(device, "truth_columns", None)
            if columns is not None:
                self.recorder.add_columns(*columns())
        self.recorder.open()  # a file that cannot be written is an error at start, not mid-run
        self.summary: dict[str, Any] | None = None

    @property
    def contacts(self) -> int:
        """Contacts so far."""
        return self.events.count

    def _publish(self, kind: str, ev: Mapping[str, Any]) -> None:
        self.bridge.publish("contact", {"t": ev["start_s"] if kind == "start" else ev["end_s"], "event": kind,
                                        "object": ev["object"], "force_N": ev["force_N"],
                                        "speed_m_s": ev["impact_speed_m_s"]})

    def finish(self) -> dict[str, Any]:
        """Close the truth file and write the summary JSON (once); returns the summary."""
        import time

        if self.summary is not None:
            return self.summary
        self.recorder.close()
        st = self.bridge.status()
        self.summary = run_summary(scenario=self.bridge.scenario.name, seed=self.bridge.seed,
                                   sim_time_s=self.bridge.vehicle.state.time, wall_s=time.monotonic() - self._wall0,
                                   late_ticks=st.get("late_ticks", 0), skipped_ticks=st.get("skipped_ticks", 0),
                                   devices=st.get("devices", {}), recorder=self.recorder)
        if self.summary_path is not None:
            write_summary(self.summary_path, self.summary)
        run_dir = getattr(self.bridge, "run_dir", None)
        gone = bool(getattr(self.bridge, "_own_run_dir", False)) and run_dir is not None and \
            Path(run_dir) in self.recorder.path.parents
        _tlog.info(
            "ground truth: %s (%d rows), %d contact%s; summary: %s%s", self.recorder.path, self.recorder.rows,
            self.events.count, "" if self.events.count == 1 else "s", self.summary_path,
            " (in the temporary run folder, removed at exit: keep them with --endpoints, --pty-dir, --truth "
            "and --summary)" if gone else "")
        return self.summary


def run_summary(*, scenario: str, seed: int, sim_time_s: float, wall_s: float, late_ticks: int,
                skipped_ticks: int, devices: Mapping[str, Any], recorder: TruthRecorder | None,
                faults: Sequence[Mapping[str, Any]] | None = None) -> dict[str, Any]:
    """The run's summary: ``{"scenario", "seed", "sim_time_s", "wall_s", "late_ticks",
    "skipped_ticks", "devices": {name: status}, "contacts": {"count", "events"},
    "faults": [{"t_s", "target", "fault", "on"}], "truth": path}``."""
    return {
        "scenario": scenario, "seed": int(seed), "sim_time_s": round(float(sim_time_s), 6),
        "wall_s": round(float(wall_s), 3), "late_ticks": int(late_ticks), "skipped_ticks": int(skipped_ticks),
        "devices": {k: dict(v) for k, v in devices.items()},
        "contacts": recorder.events.summary() if recorder is not None else {"count": 0, "events": []},
        "faults": list(faults) if faults is not None else (recorder.fault_history() if recorder else []),
        "truth": str(recorder.path) if recorder is not None else None,
    }


def write_summary(path: Path | str, summary: Mapping[str, Any]) -> None:
    """Write the summary JSON atomically (a reader never sees half a file)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(json.dumps(summary, indent=2, default=_jsonable) + "\n")
    os.replace(tmp, p)


def _jsonable(v: Any) -> Any:
    """Numbers and sequences numpy or a device status may hold."""
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, (set, frozenset, tuple)):
        return list(v)
    return str(v)
