"""Faults on a running bridge: one path for the timeline, the console and tests.

A target is a device name (its own faults and its links' faults, as the device
declares them: :meth:`hilsim.devices.base.Device.fault_kinds`) or
``thruster:<name or index>`` (``fail``, ``saturate``). The runtime names no
protocol: what a fault does on the wire is the device's (or the link's) business.
Every change is logged, kept in :meth:`Faults.active` and the history, and
published on the ``fault`` topic.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

log = logging.getLogger("hilsim.faults")

THRUSTER_FAULTS = ("fail", "saturate")


@dataclass(frozen=True)
class FaultRecord:
    t: float              # [s] simulation time
    target: str
    fault: str
    on: bool


class Faults:
    """Inject and clear faults on ``devices`` and the vehicle's ``thrusters`` (a ThrusterSet or None).

    now(): [s] simulation time; publish(topic, message): the observers' publish."""

    def __init__(self, devices: Sequence[Any], thrusters: Any, now: Callable[[], float],
                 publish: Callable[[str, Mapping[str, Any]], None]) -> None:
        self.devices = devices
        self.thrusters = thrusters
        self.now = now
        self.publish = publish
        self._active: dict[tuple[str, str], Mapping[str, Any]] = {}
        self.history: list[FaultRecord] = []

    # -- what can be injected --------------------------------------------------------

    def kinds(self, target: str) -> tuple[str, ...]:
        """The faults ``target`` can show; KeyError (with what exists) for an unknown target."""
        if target.startswith("thruster:"):
            self.thruster_index(target)
            return THRUSTER_FAULTS
        return self._device(target).fault_kinds()

    def targets(self) -> dict[str, tuple[str, ...]]:
        """Every target and its faults (devices first, then each thruster)."""
        out = {d.name: d.fault_kinds() for d in self.devices if d.fault_kinds()}
        if self.thrusters is not None:
            out.update({f"thruster:{n}": THRUSTER_FAULTS for n in self.thrusters.names})
        return out

    def thruster_index(self, target: str) -> int:
        if self.thrusters is None:
            raise KeyError("the vehicle has no thrusters")
        name = target.split(":", 1)[1]
        if name.isdigit() and int(name) < len(self.thrusters):
            return int(name)
        return int(self.thrusters.index(name))

    def _device(self, name: str) -> Any:
        for d in self.devices:
            if d.name == name:
                return d
        names = ", ".join(d.name for d in self.devices)
        raise KeyError(f"no device {name!r}; devices: {names}, or thruster:<name>")

    def check(self, target: str, fault: str) -> None:
        """ValueError/KeyError when ``target`` cannot show ``fault`` (the message says what can)."""
        kinds = self.kinds(target)
        if fault not in kinds:
            raise ValueError(f"{target!r} has no fault {fault!r}; try one of {', '.join(kinds) or 'none'}")

    # -- changing them ----------------------------------------------------------------

    def inject(self, target: str, fault: str, params: Mapping[str, Any] | None = None) -> None:
        """Start ``fault`` on ``target`` (params: ``factor``, ``rate``, ``fraction`` ... as the fault takes)."""
        self._set(target, fault, True, dict(params or {}))

    def clear(self, target: str, fault: str) -> None:
        """End ``fault`` on ``target`` (nothing happens if it is not active)."""
        self._set(target, fault, False, {})

    def active(self) -> list[dict[str, Any]]:
        """The active faults: ``[{"target", "fault", "params"}]``."""
        return [{"target": t, "fault": f, "params": dict(p)} for (t, f), p in self._active.items()]

    def _set(self, target: str, fault: str, on: bool, params: Mapping[str, Any]) -> None:
        self.check(target, fault)
        if target.startswith("thruster:"):
            frac = (0.0 if fault == "fail" else float(params.get("fraction", 0.5))) if on else None
            self.thrusters.set_limit(self.thruster_index(target), frac)
        else:
            self._device(target).set_fault(fault, on, params)
        key = (target, fault)
        if on:
            self._active[key] = params
        else:
            self._active.pop(key, None)
        t = self.now()
        self.history.append(FaultRecord(t, target, fault, on))
        log.warning("t=%.2fs fault %s on %s %s", t, fault, target, "injected" if on else "cleared")
        self.publish("fault", {"t": t, "target": target, "fault": fault, "on": on})
