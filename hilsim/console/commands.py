"""What a page may ask of the bridge: a small command set, validated before anything is done.

A page sends JSON text messages of at most :data:`MAX_COMMAND_BYTES`::

    {"op": "fault", "target": "depth", "fault": "dropout"}   # one of the menu's faults
    {"op": "clear", "target": "depth", "fault": "dropout"}
    {"op": "camera", "show": true}                           # the page shows the camera (or not)

Faults come only from the menu the bridge offers (:func:`fault_menu`: the scenario's
devices' own fault kinds, ``silent`` for CAN devices, ``fail`` for each thruster) with
the menu's parameters; a page names no parameters, paths or other devices. Anything
else (binary, not JSON, unknown op or key, wrong type, a fault not on the menu) is
refused with :class:`Refused`, whose message goes back to the page as an error.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Mapping

MAX_COMMAND_BYTES = 1024
#: fault -> the parameters a page's injection uses (the timeline's keys)
FAULT_PARAMS: dict[str, dict[str, float]] = {"noise": {"factor": 10.0}, "saturate": {"fraction": 0.5}}
#: the fault kinds the console offers (the issue's list; bit errors and saturation stay the timeline's)
OFFERED = ("dropout", "stuck", "noise", "silent", "fail")
_KEYS = {"fault": {"op", "target", "fault"}, "clear": {"op", "target", "fault"}, "camera": {"op", "show"}}


class Refused(ValueError):
    """A page's message the console does not accept (the message says why)."""


@dataclass(frozen=True)
class Command:
    op: str
    target: str = ""
    fault: str = ""
    show: bool = False
    params: Mapping[str, float] = field(default_factory=dict)


def fault_menu(bridge: Any) -> list[dict[str, Any]]:
    """``[{"target", "fault", "label"}]``: the faults a page may inject on this bridge (those of
    ``bridge.faults.targets()`` the console offers)."""
    labels = {"silent": "CAN bus silent"}
    menu: list[dict[str, Any]] = []
    for target, kinds in bridge.faults.targets().items():
        who = target.replace("thruster:", "thruster ")
        for f in kinds:
            if f in OFFERED:
                menu.append({"target": target, "fault": f, "label": f"{who}: {labels.get(f, f)}"})
    return menu


def parse_command(data: Any, menu: list[dict[str, Any]]) -> Command:
    """A page's text message as a :class:`Command`; :class:`Refused` for anything else."""
    if not isinstance(data, str):
        raise Refused("only JSON text messages are accepted")
    if len(data.encode("utf-8", "replace")) > MAX_COMMAND_BYTES:
        raise Refused(f"message longer than {MAX_COMMAND_BYTES} bytes")
    try:
        msg = json.loads(data)
    except (ValueError, RecursionError):
        raise Refused("not JSON") from None
    if not isinstance(msg, dict):
        raise Refused("expected a JSON object")
    op = msg.get("op")
    if not isinstance(op, str) or op not in _KEYS:
        raise Refused(f"unknown op {str(op)[:40]!r}; ops: {', '.join(_KEYS)}")
    extra = set(msg) - _KEYS[op]
    if extra:
        raise Refused(f"op {op!r} takes no {', '.join(sorted(str(k)[:40] for k in extra))}")
    if op == "camera":
        show = msg.get("show")
        if not isinstance(show, bool):
            raise Refused("'camera' needs show: true or false")
        return Command("camera", show=show)
    target, fault = msg.get("target"), msg.get("fault")
    if not isinstance(target, str) or not isinstance(fault, str):
        raise Refused(f"{op!r} needs a target and a fault (strings)")
    if not any(m["target"] == target and m["fault"] == fault for m in menu):
        raise Refused(f"no fault {fault[:40]!r} on {target[:60]!r} in this bridge's menu")
    return Command(op, target=target, fault=fault, params=dict(FAULT_PARAMS.get(fault, {})))


def active_faults(bridge: Any) -> list[dict[str, Any]]:
    """The faults active now, from ``bridge.faults.active()``, as ``[{"target", "fault"}]``."""
    faults = getattr(bridge, "faults", None)
    if faults is None:
        return []
    out = []
    for item in faults.active():
        if isinstance(item, Mapping):
            target, fault = item.get("target"), item.get("fault")
        else:
            target, fault = item[0], item[1]
        out.append({"target": str(target), "fault": str(fault)})
    return out
