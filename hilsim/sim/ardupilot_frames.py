"""ArduSub's motor layouts and a vehicle profile's ``[ardupilot]`` table.

ArduSub mixes its six axes into motor outputs with one factor per motor and axis
(``AP_Motors6DOF::setup_motors``). For the two BlueROV2 frames the factors are
(roll, pitch, yaw, throttle, forward, lateral), motor n on servo output n:

- ``vectored`` (``FRAME_CONFIG`` 1, BlueROV2, 6 thrusters): motors 1-4 horizontal
  (yaw +1/-1/-1/+1, forward -1/-1/+1/+1, lateral +1/-1/+1/-1), motors 5 and 6
  vertical (roll +1 / -1, throttle -1).
- ``vectored_6dof`` (``FRAME_CONFIG`` 2, BlueROV2 Heavy, 8 thrusters): motors 1-4
  as above, 5-8 vertical with roll +1/-1/+1/-1, pitch -1/-1/+1/+1, throttle -1.

A motor whose PWM rises above 1500 us pushes the vehicle so as to produce its
factors' signs: forward = +x, lateral = +y (starboard), throttle = up (-z),
roll = starboard down (+Mx), pitch = nose up (+My), yaw = clockwise seen from
above (+Mz). The profile maps servo output n to one of its thrusters with a
direction of +1 or -1 (-1: the thruster's positive thrust is the motor's
negative, as ``MOT_n_DIRECTION`` would reverse it on the vehicle).
:func:`check_layout` holds the thrusters' geometry to those signs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from hilsim.config import Doc, check_keys

if TYPE_CHECKING:
    from hilsim.sim.thrusters import Thruster

# factors per motor: (roll, pitch, yaw, throttle, forward, lateral), from AP_Motors6DOF.cpp
FRAMES: dict[str, tuple[tuple[float, float, float, float, float, float], ...]] = {
    "vectored": (
        (0, 0, 1, 0, -1, 1),
        (0, 0, -1, 0, -1, -1),
        (0, 0, -1, 0, 1, 1),
        (0, 0, 1, 0, 1, -1),
        (1, 0, 0, -1, 0, 0),
        (-1, 0, 0, -1, 0, 0),
    ),
    "vectored_6dof": (
        (0, 0, 1, 0, -1, 1),
        (0, 0, -1, 0, -1, -1),
        (0, 0, -1, 0, 1, 1),
        (0, 0, 1, 0, 1, -1),
        (1, -1, 0, -1, 0, 0),
        (-1, -1, 0, -1, 0, 0),
        (1, 1, 0, -1, 0, 0),
        (-1, 1, 0, -1, 0, 0),
    ),
}
FRAME_CONFIG = {"vectored": 1, "vectored_6dof": 2}  # ArduSub's FRAME_CONFIG parameter values


@dataclass(frozen=True)
class ServoMap:
    """One servo output driving one thruster: servo [1-based output number],
    thruster [index into the profile's thrusters], direction [+1 | -1]."""

    servo: int
    thruster: int
    direction: int


@dataclass(frozen=True)
class ArdupilotTable:
    """A profile's ``[ardupilot]`` table: frame (a key of :data:`FRAMES`) and the servo map."""

    frame: str
    motors: tuple[ServoMap, ...]

    @property
    def frame_config(self) -> int:
        """ArduSub's ``FRAME_CONFIG`` value for this frame."""
        return FRAME_CONFIG[self.frame]


def parse_ardupilot(doc: Doc, table: Any, names: Sequence[str]) -> ArdupilotTable:
    """Read ``[ardupilot]`` (frame, ``[[ardupilot.motor]]`` with servo, thruster, direction)
    against the thruster ``names`` (n,) of the profile; errors name the key."""
    check_keys(doc, table, ("frame", "motor", "note"), "ardupilot")
    frame = table.get("frame")
    if frame not in FRAMES:
        raise doc.error("ardupilot.frame", f"expected one of {sorted(FRAMES)}, got {frame!r}")
    motors = table.get("motor", [])
    if not isinstance(motors, list) or not motors:
        raise doc.error("ardupilot", "expected [[ardupilot.motor]] tables")
    out: list[ServoMap] = []
    for i, m in enumerate(motors):
        where = f"ardupilot.motor.{i}"
        check_keys(doc, m, ("servo", "thruster", "direction", "note"), where)
        servo, name, direction = m.get("servo"), m.get("thruster"), m.get("direction", 1)
        if not isinstance(servo, int) or not 1 <= servo <= 32:
            raise doc.error(f"{where}.servo", f"expected a servo output number 1..32, got {servo!r}")
        if name not in names:
            raise doc.error(f"{where}.thruster", f"no thruster {name!r}; thrusters: {', '.join(names)}")
        if direction not in (1, -1):
            raise doc.error(f"{where}.direction", f"expected 1 or -1, got {direction!r}")
        out.append(ServoMap(servo, list(names).index(name), int(direction)))
    servos = [m.servo for m in out]
    if len(set(servos)) != len(servos) or len({m.thruster for m in out}) != len(out):
        raise doc.error("ardupilot", "each servo output and each thruster may appear only once")
    if sorted(servos) != list(range(1, len(FRAMES[frame]) + 1)):
        raise doc.error("ardupilot", f"frame {frame!r} drives servo outputs 1..{len(FRAMES[frame])}, "
                                     f"got {sorted(servos)}")
    return ArdupilotTable(str(frame), tuple(sorted(out, key=lambda m: m.servo)))


def motor_wrench(thruster: "Thruster", direction: int) -> np.ndarray:
    """(6,) body wrench per newton of the motor's positive command (Fx, Fy, Fz, Mx, My, Mz)."""
    d = np.asarray(thruster.direction, dtype=float) * direction
    return np.concatenate([d, np.cross(np.asarray(thruster.position, dtype=float), d)])


def check_layout(table: ArdupilotTable, thrusters: Sequence["Thruster"], tol: float = 1e-9) -> list[str]:
    """Where the geometry disagrees with ArduSub's factors: for every motor and every axis
    with a non-zero factor the motor's wrench must have that sign (throttle = -Fz), and an
    axis with a zero factor may not be driven along a force axis. Empty when they agree."""
    problems = []
    for m in table.motors:
        roll, pitch, yaw, throttle, forward, lateral = FRAMES[table.frame][m.servo - 1]
        w = motor_wrench(thrusters[m.thruster], m.direction)
        got = {"forward": w[0], "lateral": w[1], "throttle": -w[2], "roll": w[3], "pitch": w[4], "yaw": w[5]}
        want = {"forward": forward, "lateral": lateral, "throttle": throttle, "roll": roll, "pitch": pitch,
                "yaw": yaw}
        for axis, f in want.items():
            if f and not np.sign(got[axis]) == np.sign(f):
                problems.append(f"servo {m.servo} ({thrusters[m.thruster].name}): {axis} {got[axis]:+.3f}, "
                                f"ArduSub's factor {f:+g}")
            if not f and axis in ("forward", "lateral", "throttle") and abs(got[axis]) > tol:
                problems.append(f"servo {m.servo} ({thrusters[m.thruster].name}): pushes {axis} "
                                f"({got[axis]:+.3f}) where ArduSub's factor is 0")
    return problems
