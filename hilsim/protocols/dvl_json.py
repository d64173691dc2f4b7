"""Water Linked DVL A50/A125 TCP JSON API, sans-I/O (the device's side).

Spec: ``protocols/dvl-json.md``, from Water Linked's "DVL A50/A125 TCP JSON API"
(waterlinked/docs ``docs/dvl/dvl-json-protocol.md``, protocol ``json_v3.3``).
One JSON object per line (``\\n``), both ways.

Reports (device -> client): :func:`velocity_report` (``"type": "velocity"``,
one per velocity computation), :func:`position_report` (``"type":
"position_local"``, dead reckoning, about 5 Hz), :func:`response` (``"type":
"response"``: ``response_to``, ``success``, ``error_message``, ``result``).
Every message carries ``"format"`` (:data:`FORMAT`).

Commands (client -> device): :class:`CommandDecoder` frames lines and gives
:class:`Command` events (``command`` and ``parameters``), or
:class:`BadCommand` (a :class:`~hilsim.protocols.codec.BadFrame` with the
``response_to`` to answer) for a line that is not a JSON object or has no
string ``command``, or ``Oversize`` for a line beyond ``max_line``. Which
commands exist and what their parameters mean is :class:`DvlConfig`'s and the
device's business; :data:`COMMANDS` lists the documented ones.

The vendor's document shows no reply to malformed JSON or an unknown command;
we answer both with a ``response`` whose ``success`` is false and whose
``error_message`` says why (``response_to`` is the command's name, or ``""``
when no name could be read), which is what a client written from the docs
checks (``success``) and logs (``error_message``).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from typing import Any, Final, Mapping, Sequence, Union

from hilsim.protocols.codec import BadFrame, LineDecoder, Oversize

FORMAT: Final = "json_v3.3"
PORT: Final = 16171
COMMANDS: Final = ("get_config", "set_config", "calibrate_gyro", "reset_dead_reckoning", "trigger_ping",
                   "get_version_info")
MAX_LINE: Final = 4096
_RANGE_MODE = re.compile(r"^(auto|wt|=[0-4]|[0-4]<=[0-4])$")


def _num(x: float) -> float:
    """A finite float for JSON (NaN/inf are not JSON)."""
    x = float(x)
    return x if math.isfinite(x) else -1.0


def _line(obj: Mapping[str, Any]) -> bytes:
    return json.dumps(obj, separators=(", ", ": "), allow_nan=False).encode("utf-8") + b"\n"


@dataclass(frozen=True)
class Transducer:
    """One beam of a velocity report: id 0-3, velocity along the beam [m/s], distance along the
    beam [m] (-1 when invalid), rssi and nsd [dBm], beam_valid."""

    id: int
    velocity: float
    distance: float
    rssi: float
    nsd: float
    beam_valid: bool


def velocity_report(time_ms: float, v: Sequence[float], fom: float, covariance: Sequence[Sequence[float]],
                    altitude: float, transducers: Sequence[Transducer], velocity_valid: bool, status: int,
                    time_of_validity_us: int, time_of_transmission_us: int, water_tracking: bool = False,
                    fmt: str = FORMAT) -> bytes:
    """One velocity-and-transducer report line. time_ms [ms] since the last report; v (3,) [m/s]
    vx, vy, vz in the vehicle frame; fom [m/s]; covariance (3, 3) [(m/s)^2]; altitude [m] along Z
    (-1 without lock); time_* Unix [us]. ``water_tracking``: type ``velocity_water``."""
    return _line({
        "time": _num(time_ms), "vx": _num(v[0]), "vy": _num(v[1]), "vz": _num(v[2]), "fom": _num(fom),
        "covariance": [[_num(c) for c in row] for row in covariance],
        "altitude": _num(altitude),
        "transducers": [{"id": int(t.id), "velocity": _num(t.velocity), "distance": _num(t.distance),
                         "rssi": _num(t.rssi), "nsd": _num(t.nsd), "beam_valid": bool(t.beam_valid)}
                        for t in transducers],
        "velocity_valid": bool(velocity_valid), "status": int(status), "format": fmt,
        "type": "velocity_water" if water_tracking else "velocity",
        "time_of_validity": int(time_of_validity_us), "time_of_transmission": int(time_of_transmission_us),
    })


def position_report(ts_s: float, x: float, y: float, z: float, std: float, roll_deg: float, pitch_deg: float,
                    yaw_deg: float, status: int, fmt: str = FORMAT) -> bytes:
    """One dead-reckoning report line: ts Unix [s]; x, y, z [m] (z down) in the frame of the last
    reset; std [m]; roll, pitch, yaw [deg]; status 0 (ok) or 1."""
    return _line({"ts": _num(ts_s), "x": _num(x), "y": _num(y), "z": _num(z), "std": _num(std),
                  "roll": _num(roll_deg), "pitch": _num(pitch_deg), "yaw": _num(yaw_deg),
                  "type": "position_local", "status": int(status), "format": fmt})


def response(response_to: str, success: bool, error_message: str = "", result: Any = None,
             fmt: str = FORMAT) -> bytes:
    """A command's response line."""
    return _line({"response_to": response_to, "success": bool(success), "error_message": error_message,
                  "result": result, "format": fmt, "type": "response"})


@dataclass
class DvlConfig:
    """The DVL's configuration as ``get_config`` reports it. speed_of_sound [m/s] (1000-2000);
    mounting_rotation_offset [deg] (0-360); range_mode ``auto``, ``=a``, ``a<=b`` (a, b in 0-4) or
    ``wt`` (water tracking)."""

    speed_of_sound: float = 1475.0
    acoustic_enabled: bool = True
    dark_mode_enabled: bool = False
    mounting_rotation_offset: float = 0.0
    range_mode: str = "auto"
    periodic_cycling_enabled: bool = True

    def as_result(self) -> dict[str, Any]:
        return {"speed_of_sound": float(self.speed_of_sound), "acoustic_enabled": self.acoustic_enabled,
                "dark_mode_enabled": self.dark_mode_enabled,
                "mounting_rotation_offset": float(self.mounting_rotation_offset), "range_mode": self.range_mode,
                "periodic_cycling_enabled": self.periodic_cycling_enabled}

    def apply(self, parameters: Any) -> str:
        """Set the given parameters (all or none); returns "" or the error message."""
        if not isinstance(parameters, Mapping) or not parameters:
            return "parameters must be a non-empty object"
        new = dict(self.as_result())
        for key, value in parameters.items():
            if key not in new:
                return f"unknown parameter {key!r}"
            if key in ("speed_of_sound", "mounting_rotation_offset"):
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                    return f"{key} must be a number"
                lo, hi = (1000.0, 2000.0) if key == "speed_of_sound" else (0.0, 360.0)
                if not lo <= value <= hi:
                    return f"{key} must be in [{lo:g}, {hi:g}]"
                new[key] = float(value)
            elif key == "range_mode":
                if not isinstance(value, str) or not _RANGE_MODE.match(value):
                    return "range_mode must be 'auto', 'wt', '=a' or 'a<=b' with a, b in 0-4"
                new[key] = value
            else:
                if not isinstance(value, bool):
                    return f"{key} must be true or false"
                new[key] = value
        for key, value in new.items():
            setattr(self, key, value)
        return ""


@dataclass(frozen=True)
class Command:
    """A command line: ``command`` and its ``parameters`` (``{}`` when absent); ``raw``: the object."""

    command: str
    parameters: Any = None
    raw: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class BadCommand(BadFrame):
    """A line that is not a command: malformed JSON, not an object, no string ``command``.
    ``response_to``: the command name if one could be read, else ``""``."""

    response_to: str = ""


Event = Union[Command, BadCommand, Oversize]


def parse_command(line: bytes) -> Command | BadCommand:
    """One line -> :class:`Command` or :class:`BadCommand`."""
    data = line[:64]
    try:
        obj = json.loads(line.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        return BadCommand(f"malformed JSON: {str(exc)[:80]}", data)
    if not isinstance(obj, dict):
        return BadCommand("a command must be a JSON object", data)
    name = obj.get("command")
    if not isinstance(name, str):
        return BadCommand("missing string field 'command'", data)
    return Command(name, obj.get("parameters"), obj)


class CommandDecoder(LineDecoder[Event]):
    """JSON command lines -> :class:`Command` / :class:`BadCommand` / ``Oversize`` (sans-I/O)."""

    MAX_LINE = MAX_LINE
    CR_ENDS_LINE = False
    SKIP_BLANK = True

    @property
    def commands(self) -> int:
        return self.good

    def parse_line(self, line: bytes) -> Event:
        return parse_command(line)


__all__ = ["BadCommand", "COMMANDS", "Command", "CommandDecoder", "DvlConfig", "FORMAT", "PORT", "Transducer",
           "parse_command", "position_report", "response", "velocity_report"]
