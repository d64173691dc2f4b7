"""VESC CAN (vedderb/bldc ``comm_can``): commands in, status out, through the DBC.

The layouts live in ``protocols/vesc_can.dbc`` and are encoded and decoded by
cantools (compiled once, on first use), so the same file works in a user's
own CAN tools. Identifier: extended 29 bits, ``(command << 8) | controller_id``;
data big-endian. The DBC lists controller ids 1..8; every other id 0..255
uses the same layouts (the messages of controller 1 serve as templates).

    command            no.  data                          value here
    SET_DUTY            0   int32 duty x 1e5              duty [1] in [-1, 1]
    SET_CURRENT         1   int32 current x 1e3           motor current [A]
    SET_CURRENT_BRAKE   2   int32 current x 1e3           brake current [A]
    SET_RPM             3   int32 ERPM                    electrical [rev/min]
    SET_CURRENT_REL    10   int32 fraction x 1e5          [1] of the max current
    STATUS_1            9   int32 ERPM, int16 current x 10, int16 duty x 1000
    STATUS_4           16   int16 T_fet x 10, T_motor x 10, I_in x 10, PID pos x 50
    STATUS_5           27   int32 tachometer, int16 V_in x 10, int16 reserved

Commands may carry the optional 6-byte form (an int16 off-delay appended);
the off-delay is read and ignored. :func:`decode` never raises on a frame
from the bus: a frame that is not VESC traffic gives ``None``, a VESC frame
that is malformed gives :class:`BadFrame`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, Final, Union

from hilsim.protocols import codec
from hilsim.protocols.can import CanFrame

COMMANDS: Final[dict[str, int]] = {
    "SET_DUTY": 0, "SET_CURRENT": 1, "SET_CURRENT_BRAKE": 2, "SET_RPM": 3, "SET_CURRENT_REL": 10,
}
STATUS: Final[dict[str, int]] = {"STATUS_1": 9, "STATUS_4": 16, "STATUS_5": 27}
_SIGNAL: Final[dict[str, str]] = {  # the value signal of each command message
    "SET_DUTY": "duty", "SET_CURRENT": "current", "SET_CURRENT_BRAKE": "current_brake",
    "SET_RPM": "erpm", "SET_CURRENT_REL": "current_rel",
}
_BY_NUMBER: Final[dict[int, str]] = {v: k for k, v in {**COMMANDS, **STATUS}.items()}
DBC_NAME: Final = "vesc_can.dbc"


@dataclass(frozen=True)
class VescCommand:
    """A command to one ESC. ``value`` in the command's unit (module table)."""

    controller_id: int
    command: str
    value: float


@dataclass(frozen=True)
class Status1:
    controller_id: int
    erpm: float           # [rev/min] electrical
    current: float        # [A] motor current
    duty: float           # [1]


@dataclass(frozen=True)
class Status4:
    controller_id: int
    temp_fet: float       # [degC]
    temp_motor: float     # [degC]
    current_in: float     # [A] input current
    pid_pos: float        # [deg]


@dataclass(frozen=True)
class Status5:
    controller_id: int
    tachometer: int       # commutation steps (6 per electrical revolution)
    v_in: float           # [V]


@dataclass(frozen=True)
class BadFrame(codec.BadInput):
    """A frame with a VESC identifier whose contents cannot be a VESC packet."""

    frame: CanFrame = CanFrame(0, b"")


VescMessage = Union[VescCommand, Status1, Status4, Status5]


def dbc_path() -> Path:
    """Where the DBC file is (the checkout's or the installed package's ``protocols/``)."""
    from hilsim.resources import data_path

    return data_path("protocols", DBC_NAME)


@cache
def database() -> Any:
    """The cantools database of the DBC, loaded once."""
    import cantools

    return cantools.database.load_file(str(dbc_path()), strict=True)


@cache
def _template(name: str) -> Any:
    return database().get_message_by_name(f"VESC1_{name}")


def arbitration_id(command: str, controller_id: int) -> int:
    """29-bit identifier of ``command`` (a COMMANDS or STATUS name) for ``controller_id`` 0..255."""
    number = COMMANDS.get(command, STATUS.get(command))
    if number is None:
        raise ValueError(f"unknown VESC packet {command!r}; known: {', '.join([*COMMANDS, *STATUS])}")
    if not 0 <= controller_id <= 255:
        raise ValueError(f"VESC controller id {controller_id} out of range 0..255")
    return (number << 8) | controller_id


def _clamped(msg: Any, values: dict[str, float]) -> dict[str, float]:
    """Saturate each value at its signal's range (as the firmware's integer casts would clip)."""
    out = {}
    for sig in msg.signals:
        v = float(values.get(sig.name, 0.0))
        if not math.isfinite(v):
            v = 0.0
        lo, hi = sig.minimum, sig.maximum
        out[sig.name] = min(max(v, lo), hi)
    return out


def encode(message: VescMessage) -> CanFrame:
    """A command or status -> its CAN frame (ValueError for an unknown command or id).

    Status values outside a field's range are saturated at the range; a command
    value outside its int32 range raises (the caller's bug)."""
    if isinstance(message, VescCommand):
        name = message.command
        if name not in COMMANDS:
            raise ValueError(f"unknown VESC command {name!r}; known: {', '.join(COMMANDS)}")
        msg = _template(name)
        sig = msg.get_signal_by_name(_SIGNAL[name])
        if not (sig.minimum <= message.value <= sig.maximum):
            raise ValueError(f"{name} value {message.value} outside {sig.minimum}..{sig.maximum}")
        data = msg.encode({_SIGNAL[name]: message.value}, strict=True)
        cid = message.controller_id
    else:
        if isinstance(message, Status1):
            name, values = "STATUS_1", {"erpm": message.erpm, "current": message.current, "duty": message.duty}
        elif isinstance(message, Status4):
            name, values = "STATUS_4", {"temp_fet": message.temp_fet, "temp_motor": message.temp_motor,
                                        "current_in": message.current_in, "pid_pos": message.pid_pos}
        elif isinstance(message, Status5):
            name, values = "STATUS_5", {"tachometer": message.tachometer, "v_in": message.v_in, "reserved": 0}
        else:
            raise TypeError(f"not a VESC message: {message!r}")
        msg = _template(name)
        data = msg.encode(_clamped(msg, values), strict=True)
        cid = message.controller_id
    return CanFrame(arbitration_id(name, cid), bytes(data), is_extended=True)


def decode(frame: CanFrame) -> VescMessage | BadFrame | None:
    """A frame from the bus -> a command or status; None if it is not one of ours.

    Not ours: a standard-id frame, an id with bits above 15 set, or a packet
    number this module does not handle (e.g. the firmware's buffer transfer
    packets). Never raises.
    """
    if not frame.is_extended or frame.arbitration_id >> 16:
        return None
    name = _BY_NUMBER.get((frame.arbitration_id >> 8) & 0xFF)
    if name is None:
        return None
    cid = frame.arbitration_id & 0xFF
    if frame.is_remote:
        return BadFrame(f"{name}: remote frame", frame)
    msg = _template(name)
    if len(frame.data) < msg.length:
        return BadFrame(f"{name}: {len(frame.data)} data bytes, expected {msg.length}", frame)
    try:
        v = msg.decode(frame.data[:msg.length], decode_choices=False, scaling=True)
    except Exception as exc:  # noqa: BLE001 - cantools' own errors; the frame is bad, not us
        return BadFrame(f"{name}: {exc}", frame)
    if name in COMMANDS:
        return VescCommand(cid, name, float(v[_SIGNAL[name]]))
    if name == "STATUS_1":
        return Status1(cid, float(v["erpm"]), float(v["current"]), float(v["duty"]))
    if name == "STATUS_4":
        return Status4(cid, float(v["temp_fet"]), float(v["temp_motor"]), float(v["current_in"]),
                       float(v["pid_pos"]))
    return Status5(cid, int(v["tachometer"]), float(v["v_in"]))
