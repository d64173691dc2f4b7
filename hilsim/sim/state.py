"""The vehicle's state: a frozen value that goes into and comes out of a step."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hilsim.sim.geometry import F64, Pose, rpy_to_matrix


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
    """

    time: float = 0.0
    position: F64 = field(default_factory=_zeros3)
    attitude: F64 = field(default_factory=_zeros3)
    velocity: F64 = field(default_factory=_zeros3)
    angular_velocity: F64 = field(default_factory=_zeros3)
    acceleration: F64 = field(default_factory=_zeros3)

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
