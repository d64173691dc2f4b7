"""The vehicle's state: a frozen value that goes into and comes out of a step."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from hilsim.sim.geometry import F64, Pose, rpy_to_matrix

_ARRAYS = ("position", "attitude", "velocity", "angular_velocity", "acceleration")
_new = object.__new__


def _zeros3() -> F64:
    return np.zeros(3)


@dataclass(frozen=True)
class VehicleState:
    """Everything the sensors sample.

    time: [s] simulation time.
    position: (3,) [m] NED position of the body origin (centre of gravity).
    attitude: (3,) [rad] roll, pitch, yaw (yaw = heading, 0 north, pi/2 east).
    velocity: (3,) [m/s] body-frame linear velocity (u, v, w) over ground.
    angular_velocity: (3,) [rad/s] body rates (p, q, r).
    acceleration: (3,) [m/s^2] body-frame linear acceleration (du/dt, dv/dt, dw/dt).

    A state made by :meth:`from_flat` (as the physics step makes them, 200 per
    simulated second) holds its 15 numbers and builds the arrays on first use.
    """

    time: float = 0.0
    position: F64 = field(default_factory=_zeros3)
    attitude: F64 = field(default_factory=_zeros3)
    velocity: F64 = field(default_factory=_zeros3)
    angular_velocity: F64 = field(default_factory=_zeros3)
    acceleration: F64 = field(default_factory=_zeros3)

    @staticmethod
    def from_flat(time: float, values: Sequence[float]) -> "VehicleState":
        """A state at ``time`` [s] from 15 floats: position, attitude, velocity,
        angular_velocity, acceleration (3 each, in that order, units as the fields)."""
        values = tuple(float(v) for v in values)
        if len(values) != 15:
            raise ValueError(f"expected 15 values, got {len(values)}")
        state = _new(VehicleState)
        d = state.__dict__
        d["time"] = float(time)
        d["_flat"] = values
        return state

    def flat(self) -> tuple[float, ...]:
        """The 15 floats of :meth:`from_flat` (position, attitude, velocity,
        angular_velocity, acceleration)."""
        d = self.__dict__
        flat: tuple[float, ...] | None = d.get("_flat")
        if flat is not None and "position" not in d:
            return flat
        return tuple(np.concatenate([np.asarray(getattr(self, k), dtype=float).reshape(3)
                                     for k in _ARRAYS]).tolist())

    if not TYPE_CHECKING:  # mypy keeps checking attribute names
        def __getattr__(self, name: str) -> Any:
            """Build the arrays of a :meth:`from_flat` state on first access."""
            d = self.__dict__
            flat = d.get("_flat")
            if flat is None or name not in _ARRAYS:
                raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
            buf = np.array(flat)
            d["position"], d["attitude"], d["velocity"] = buf[0:3], buf[3:6], buf[6:9]
            d["angular_velocity"], d["acceleration"] = buf[9:12], buf[12:15]
            return d[name]

    @property
    def pose(self) -> Pose:
        """Body -> world (NED) transform."""
        return Pose(np.asarray(self.position, dtype=float), rpy_to_matrix(*self.attitude))

    @property
    def depth(self) -> float:
        """[m] depth of the body origin (NED z)."""
        return float(self.position[2])

    @property
    def heading(self) -> float:
        """[rad] yaw."""
        return float(self.attitude[2])
