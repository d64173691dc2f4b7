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
CAN device     ``silent``                   its bus carries nothing, either way
serial device  ``bit_errors`` (``rate``)    bits flip on its line both ways (CRC errors)
thruster:X     ``fail``                     rotor spins down and stays stopped: thrust 0,
                                            telemetry RPM 0 while commands keep coming
thruster:X     ``saturate`` (``fraction``)  speed capped at that fraction of full speed
=============  ===========================  =============================================
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Mapping

from hilsim.config import Doc, check_keys, number, vector

if TYPE_CHECKING:
    from hilsim.runtime.bridge import Bridge

log = logging.getLogger("hilsim.timeline")

ACTIONS = {
    "current": ("velocity_m_s",),
    "move": ("object", "position_m", "orientation_deg"),
    "teleport": ("position_m", "orientation_deg"),
    "fault": ("target", "fault", "duration_s", "factor", "rate", "fraction"),
    "clear": ("target", "fault"),
}
LINK_FAULTS = ("bit_errors", "silent")
THRUSTER_FAULTS = ("fail", "saturate")


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
            import difflib

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


def device_links(device: Any) -> list[Any]:
    """The serial lines (PtyLink) and CAN buses a device holds, also inside its servers."""
    from hilsim.links.can.bus import CanBus
    from hilsim.links.pty import PtyLink

    found: list[Any] = []
    seen: set[int] = set()

    def visit(obj: Any, depth: int) -> None:
        if id(obj) in seen or depth > 2:
            return
        seen.add(id(obj))
        if isinstance(obj, (PtyLink, CanBus)):
            found.append(obj)
        if depth == 2 or not hasattr(obj, "__dict__"):
            return
        for v in vars(obj).values():
            if isinstance(v, (PtyLink, CanBus)) or type(v).__module__.startswith("hilsim.links"):
                visit(v, depth + 1)

    visit(device, 0)
    return found


class Timeline:
    """Checks a scenario's timeline against the built bridge and schedules it."""

    def __init__(self, bridge: "Bridge", doc: Doc) -> None:
        self.bridge = bridge
        self.doc = doc
        self.events = parse_timeline(doc)
        self.fired: list[tuple[float, str]] = []
        for ev in self.events:
            self._check(ev)

    def _check(self, ev: TimelineEvent) -> None:
        b, p = self.bridge, ev.params
        if ev.action == "move":
            names = b.scenario.raw_object_names()
            if p["object"] not in names:
                raise self.doc.error(f"{ev.where}.object", f"no object {p['object']!r}; objects: {', '.join(names)}")
        if ev.action in ("fault", "clear"):
            target, fault = p["target"], p["fault"]
            if target.startswith("thruster:"):
                self._thruster(ev)
                if fault not in THRUSTER_FAULTS:
                    raise self.doc.error(f"{ev.where}.fault", f"a thruster fault is one of {', '.join(THRUSTER_FAULTS)}")
                return
            dev = next((d for d in b.devices if d.name == target), None)
            if dev is None:
                raise self.doc.error(f"{ev.where}.target", f"no device {target!r}; devices: "
                                     f"{', '.join(d.name for d in b.devices)}, or thruster:<name>")
            if fault in LINK_FAULTS:
                return  # the device's links are checked when they exist (after start)
            if fault not in dev.FAULTS:
                can = tuple(dev.FAULTS) + LINK_FAULTS
                raise self.doc.error(f"{ev.where}.fault", f"device {target!r} has no fault {fault!r}; "
                                     f"try one of {', '.join(can)}")

    def _thruster(self, ev: TimelineEvent) -> int:
        ts = self.bridge.vehicle.thrusters
        name = ev.params["target"].split(":", 1)[1]
        if ts is None:
            raise self.doc.error(f"{ev.where}.target", "the vehicle has no thrusters")
        try:
            return int(name) if name.isdigit() and int(name) < len(ts) else ts.index(name)
        except KeyError as exc:
            raise self.doc.error(f"{ev.where}.target", str(exc.args[0])) from None

    def schedule(self) -> None:
        for ev in self.events:
            self.bridge.at(ev.at, lambda t, ev=ev: self.fire(ev, t), f"timeline@{ev.at:g}s:{ev.action}")

    async def fire(self, ev: TimelineEvent, t: float) -> None:
        b, p = self.bridge, ev.params
        self.fired.append((t, ev.action))
        log.warning("t=%.2fs timeline: %s %s", t, ev.action,
                    ", ".join(f"{k}={v}" for k, v in p.items()) or "")
        if ev.action == "current":
            b.set_current(p["velocity"])
        elif ev.action == "teleport":
            b.teleport(p["position"], p["rpy"])
        elif ev.action == "move":
            await b.move_object(p["object"], p["position"], p["rpy"])
        elif ev.action == "fault":
            self._set(ev, on=True)
            if "duration" in p:
                b.at(t + p["duration"], lambda t2: self._clear_after(ev, t2), f"timeline:clear {p['fault']}")
        elif ev.action == "clear":
            self._set(ev, on=False)

    def _clear_after(self, ev: TimelineEvent, t: float) -> None:
        log.warning("t=%.2fs timeline: fault %s on %s cleared", t, ev.params["fault"], ev.params["target"])
        self._set(ev, on=False)

    def _set(self, ev: TimelineEvent, on: bool) -> None:
        b, p = self.bridge, ev.params
        target, fault = p["target"], p["fault"]
        if target.startswith("thruster:"):
            assert b.vehicle.thrusters is not None
            frac = (0.0 if fault == "fail" else float(p.get("fraction", 0.5))) if on else None
            b.vehicle.thrusters.set_limit(self._thruster(ev), frac)
            return
        dev = next(d for d in b.devices if d.name == target)
        if fault in LINK_FAULTS:
            from hilsim.links.can.bus import CanBus
            from hilsim.links.pty import PtyLink

            kind = PtyLink if fault == "bit_errors" else CanBus
            links = [x for x in device_links(dev) if isinstance(x, kind)]
            if not links:
                log.error("timeline: device %s has no %s to apply %s to; ignored", target,
                          "serial line" if fault == "bit_errors" else "CAN bus", fault)
                return
            for link in links:
                if fault == "bit_errors":
                    link.bit_error_rate = float(p.get("rate", 1e-3)) if on else 0.0
                else:
                    link.silent = on
            return
        if on:
            dev.inject_fault(fault, p)
        else:
            dev.clear_fault(fault)
