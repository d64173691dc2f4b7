"""Scripted scenarios: timed events and injected faults (the scenario's ``[[timeline]]``).

Each entry happens once, at ``at_s`` seconds of simulation time::

    [[timeline]]
    at_s = 20.0
    action = "current"            # the water current changes (NED [m/s])
    velocity_m_s = [0.2, 0.0, 0.0]

    [[timeline]]
    at_s = 30.0
    action = "move"               # an object moves (a target that moves)
    object = "cuboid"
    position_m = [1.0, 0.5, 2.85]
    orientation_deg = [0.0, 0.0, 30.0]

    [[timeline]]
    at_s = 40.0
    action = "teleport"           # the vehicle is put somewhere else, at rest
    position_m = [-3.0, 0.0, 1.5]
    orientation_deg = [0.0, 0.0, 0.0]

    [[timeline]]
    at_s = 50.0
    action = "fault"              # a fault a HIL test needs
    target = "depth"              # a device name, or "thruster:<name or index>"
    fault = "dropout"
    duration_s = 10.0             # optional: cleared after it; else until an action = "clear"

Faults, and how they show on the wire:

=============  ===========================  =============================================
target         fault                        on the wire
=============  ===========================  =============================================
Modbus sensor  ``dropout``                  Keller: P1 reads NaN (its channel error);
                                            others: no reply (TCP: gateway exception 0B)
Modbus sensor  ``stuck``                    registers keep their last values
Modbus sensor  ``noise`` (``factor``)       the profile's noise figures x factor
DDF sonar      ``dropout``                  no frames (the head stops pinging)
DVL, GNSS,     ``dropout`` / ``stuck`` /    silent / the last report repeated / the
Ping1D         ``noise`` (``factor``)       profile's noise figures x factor
DVL            ``lock_loss``                velocity_valid false, beams invalid, altitude -1
GNSS           ``outage``                   no fix (GGA quality 0, RMC V); the fix returns
                                            the profile's time to fix after it ends
CAN device     ``silent``                   its bus carries nothing, either way
serial device  ``bit_errors`` (``rate``)    bits flip on its line both ways (CRC errors)
thruster:X     ``fail``                     rotor spins down and stays stopped: thrust 0,
                                            telemetry RPM 0 while commands keep coming
thruster:X     ``saturate`` (``fraction``)  speed capped at that fraction of full speed
=============  ===========================  =============================================
"""

from __future__ import annotations

import difflib
import logging
import math
from dataclasses import dataclass, field
from typing import Any, Awaitable, Callable, Mapping, Protocol

from hilsim.config import Doc, check_keys, number, vector
from hilsim.runtime.faults import Faults

log = logging.getLogger("hilsim.timeline")

ACTIONS = {
    "current": ("velocity_m_s",),
    "move": ("object", "position_m", "orientation_deg"),
    "teleport": ("position_m", "orientation_deg"),
    "fault": ("target", "fault", "duration_s", "factor", "rate", "fraction"),
    "clear": ("target", "fault"),
}


class TimelineHost(Protocol):
    """What the timeline acts on (the bridge)."""

    faults: Faults

    def object_names(self) -> list[str]: ...
    def at(self, t: float, callback: Callable[[float], Any], name: str = "at") -> None: ...
    def set_current(self, velocity: tuple[float, float, float]) -> None: ...
    def teleport(self, position: tuple[float, float, float], rpy: tuple[float, float, float]) -> None: ...
    def move_object(self, name: str, position: tuple[float, float, float],
                    rpy: tuple[float, float, float], t: float | None = None) -> Awaitable[None]: ...


@dataclass(frozen=True)
class TimelineEvent:
    at: float                      # [s] simulation time
    action: str
    where: str                     # "timeline.N" for error messages
    params: Mapping[str, Any] = field(default_factory=dict)


def parse_timeline(doc: Doc) -> list[TimelineEvent]:
    """Validate ``[[timeline]]`` (file, line and key named on errors); events sorted by time."""
    raw = doc.data.get("timeline", [])
    if not isinstance(raw, list):
        raise doc.error("timeline", "expected an array of tables: [[timeline]]")
    out = []
    for i, t in enumerate(raw):
        where = f"timeline.{i}"
        if not isinstance(t, Mapping):
            raise doc.error(where, "expected a table")
        action = t.get("action")
        if action not in ACTIONS:
            close = difflib.get_close_matches(str(action), list(ACTIONS), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else f"; one of {', '.join(ACTIONS)}"
            raise doc.error(f"{where}.action", f"unknown action {action!r}{hint}")
        check_keys(doc, t, ("at_s", "action", "description") + ACTIONS[action], where)
        at = number(doc, t, "at_s", where, lo=0.0)
        p: dict[str, Any] = {}
        if action == "current":
            p["velocity"] = vector(doc, t, "velocity_m_s", 3, where)
        elif action in ("move", "teleport"):
            if action == "move":
                if not isinstance(t.get("object"), str):
                    raise doc.error(f"{where}.object", "'move' needs the name of an object")
                p["object"] = t["object"]
            p["position"] = vector(doc, t, "position_m", 3, where)
            p["rpy"] = tuple(math.radians(a) for a in vector(doc, t, "orientation_deg", 3, where, (0.0, 0.0, 0.0)))
        else:
            for k in ("target", "fault"):
                if not isinstance(t.get(k), str):
                    raise doc.error(f"{where}.{k}", f"'{action}' needs '{k}' (a name)")
                p[k] = t[k]
            if action == "fault":
                if "duration_s" in t:
                    p["duration"] = number(doc, t, "duration_s", where, lo=0.0)
                for k, lo, hi in (("factor", 0.0, 1e6), ("rate", 0.0, 0.5), ("fraction", 0.0, 1.0)):
                    if k in t:
                        p[k] = number(doc, t, k, where, lo=lo, hi=hi)
        out.append(TimelineEvent(at, str(action), where, p))
    return sorted(out, key=lambda e: e.at)


class Timeline:
    """Checks a scenario's timeline against the built bridge and schedules it."""

    def __init__(self, host: TimelineHost, doc: Doc) -> None:
        self.host = host
        self.doc = doc
        self.events = parse_timeline(doc)
        self.fired: list[tuple[float, str]] = []
        for ev in self.events:
            self._check(ev)

    def _check(self, ev: TimelineEvent) -> None:
        p = ev.params
        if ev.action == "move":
            names = self.host.object_names()
            if p["object"] not in names:
                raise self.doc.error(f"{ev.where}.object", f"no object {p['object']!r}; objects: {', '.join(names)}")
        if ev.action in ("fault", "clear"):
            try:
                kinds = self.host.faults.kinds(p["target"])
            except KeyError as exc:
                raise self.doc.error(f"{ev.where}.target", str(exc.args[0])) from None
            if p["fault"] not in kinds:
                raise self.doc.error(f"{ev.where}.fault", f"{p['target']!r} has no fault {p['fault']!r}; "
                                     f"try one of {', '.join(kinds) or 'none'}")

    def schedule(self) -> None:
        for ev in self.events:
            self.host.at(ev.at, lambda t, ev=ev: self.fire(ev, t), f"timeline@{ev.at:g}s:{ev.action}")

    async def fire(self, ev: TimelineEvent, t: float) -> None:
        h, p = self.host, ev.params
        self.fired.append((t, ev.action))
        log.warning("t=%.2fs timeline: %s %s", t, ev.action,
                    ", ".join(f"{k}={v}" for k, v in p.items()) or "")
        if ev.action == "current":
            h.set_current(p["velocity"])
        elif ev.action == "teleport":
            h.teleport(p["position"], p["rpy"])
        elif ev.action == "move":
            await h.move_object(p["object"], p["position"], p["rpy"], t=t)
        elif ev.action == "fault":
            h.faults.inject(p["target"], p["fault"], {k: v for k, v in p.items() if k not in ("target", "fault")})
            if "duration" in p:
                h.at(t + p["duration"], lambda t2: h.faults.clear(p["target"], p["fault"]),
                     f"timeline:clear {p['fault']}")
        elif ev.action == "clear":
            h.faults.clear(p["target"], p["fault"])
