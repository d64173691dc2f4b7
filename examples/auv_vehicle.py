"""The vehicle as the reference stack sees it: thruster layout and ESC ids, thrust curve, a diagonal
model per degree of freedom, the sonar mount, and the thrust allocation. Replace these for your vehicle.

Numbers for Cyclops (devices/vehicles/cyclops.toml, the seed paper's Table 1) with T200-like
thrusters (devices/thrusters/t200.toml), copied here as the vehicle's configuration: the stack reads
no hilsim file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

G = 9.80665                # [m/s^2]
C45 = math.sqrt(0.5)

#: (name, VESC controller id, position [m] body x fwd / y stbd / z down, unit thrust direction)
#: Cyclops layout (devices/vehicles/cyclops.toml): 0-3 horizontal vectored at +-45 deg, 4-7 vertical
#: (positive thrust pushes down).
THRUSTERS: list[tuple[str, int, tuple[float, float, float], tuple[float, float, float]]] = [
    ("front_left", 1, (0.35, -0.25, 0.0), (C45, C45, 0.0)),
    ("front_right", 2, (0.35, 0.25, 0.0), (C45, -C45, 0.0)),
    ("rear_left", 3, (-0.35, -0.25, 0.0), (C45, -C45, 0.0)),
    ("rear_right", 4, (-0.35, 0.25, 0.0), (C45, C45, 0.0)),
    ("vertical_front_left", 5, (0.2, -0.35, -0.1), (0.0, 0.0, 1.0)),
    ("vertical_front_right", 6, (0.2, 0.35, -0.1), (0.0, 0.0, 1.0)),
    ("vertical_rear_left", 7, (-0.2, -0.35, -0.1), (0.0, 0.0, 1.0)),
    ("vertical_rear_right", 8, (-0.2, 0.35, -0.1), (0.0, 0.0, 1.0)),
]
HORIZONTAL = [0, 1, 2, 3]
VERTICAL = [4, 5, 6, 7]


@dataclass(frozen=True)
class ThrusterModel:
    """T200-like: thrust = T_max s|s| with s the speed fraction; open-loop duty s = duty at 16 V."""
    forward_max: float = 5.1 * G    # [N] at full speed forward
    reverse_max: float = 4.1 * G    # [N] at full speed reverse
    max_rpm: float = 3600.0         # [rev/min] full speed
    pole_pairs: int = 7             # ERPM = RPM x pole pairs
    max_current: float = 24.0       # [A] motor current at full speed (thrust ~ current)
    limit: float = 25.0             # [N] the stack never asks one thruster for more
    dead_band: float = 0.0625       # ESC dead band, fraction of full scale (duty, rpm or current)

    def speed_for(self, thrust: float) -> float:
        """Speed fraction s [-1, 1] giving ``thrust`` [N]."""
        if thrust >= 0:
            return math.sqrt(min(thrust / self.forward_max, 1.0))
        return -math.sqrt(min(-thrust / self.reverse_max, 1.0))

    def command(self, kind: str, thrust: float) -> float:
        """The VESC command value (duty [1], erpm [rev/min] or current [A]) for ``thrust`` [N]."""
        s = self.speed_for(thrust)
        if kind == "duty":
            return s
        if kind == "rpm":
            return s * self.max_rpm * self.pole_pairs
        return math.copysign(s * s * self.max_current, s)

    def dead_band_thrust(self, kind: str) -> tuple[float, float]:
        """(forward, reverse) thrust magnitudes [N] at the edge of the ESC's dead band for ``kind``: the
        least thrust a command of that kind can give (duty and rpm scale the speed, current its square)."""
        f = self.dead_band if kind == "current" else self.dead_band ** 2
        return self.forward_max * f, self.reverse_max * f


class DeadBandDither:
    """Delivers thrusts smaller than the ESC's dead band on average (sigma-delta): a thruster asked for less
    than the dead band accumulates the demand and gets a pulse just past the band when the sum reaches it.
    A slow heavy vehicle feels the mean. Matters for SET_CURRENT (a T200's dead band is about 3 N there,
    more than the whole hover trim); duty and rpm lose only 0.2 N."""

    def __init__(self, n: int, band: tuple[float, float]) -> None:
        self.acc = np.zeros(n)
        self.forward, self.reverse = band

    def __call__(self, thrusts: np.ndarray) -> np.ndarray:
        out = np.array(thrusts, dtype=float)
        for i, t in enumerate(out):
            band = self.forward if t >= 0 else self.reverse
            if abs(t) >= band:
                self.acc[i] = 0.0
                continue
            self.acc[i] += t
            band = self.forward if self.acc[i] >= 0 else self.reverse
            if abs(self.acc[i]) >= band:
                out[i] = math.copysign(1.05 * band, self.acc[i])
                self.acc[i] -= out[i]
            else:
                out[i] = 0.0
        return out


@dataclass(frozen=True)
class Axis:
    """One degree of freedom, diagonal model: m a = F - k v - kq v|v| + bias (SI units)."""
    mass: float
    damping: float
    quadratic: float
    bias: float = 0.0

    def drag(self, v: float) -> float:
        return self.damping * v + self.quadratic * v * abs(v)


# Cyclops (seed paper Table 1; yaw estimated in devices/vehicles/cyclops.toml). heave bias: -2.5 N,
# the vehicle is slightly buoyant (z down).
SURGE = Axis(391.5, 16.0, 229.4)
HEAVE = Axis(639.6, 65.6, 296.8, bias=-2.5)
YAW = Axis(45.0, 20.0, 60.0)

# The sonar mount: 0.4 m ahead, 0.3 m below the body origin, tilted 45 deg down, +-7 deg elevation.
SONAR_DOWN = 0.3           # [m] below the body origin
SONAR_TILT_DEG = 45.0
SONAR_HALF_ELEVATION_DEG = 7.0
# The DVL (Water Linked A50) 0.35 m below the body origin, looking down, its x forward; the GNSS antenna on
# a 0.6 m mast: out of the water once the body origin is less than 0.6 m deep.
DVL_DOWN = 0.35            # [m] below the body origin
GNSS_MAST = 0.6            # [m] above the body origin


def layout_matrix() -> np.ndarray:
    """(6, 8) body wrench (X, Y, Z [N], K, M, N [N m]) per newton of each thruster's thrust:
    force = direction, moment = position x direction."""
    b = np.zeros((6, len(THRUSTERS)))
    for i, (_, _, pos, d) in enumerate(THRUSTERS):
        b[:3, i] = d
        b[3:, i] = np.cross(pos, d)
    return b


def allocation_matrix() -> np.ndarray:
    """(8, 6) map from a body wrench (X, Y, Z [N], K, M, N [N m]) to thruster thrusts [N]: the
    pseudo-inverse of the layout matrix (the least total squared thrust; roll and pitch asked zero)."""
    return np.linalg.pinv(layout_matrix())


def allocate(alloc: np.ndarray, fx: float, fy: float, fz: float, mz: float, limit: float) -> np.ndarray:
    """Thrusts (8,) [N] for surge/sway/heave force [N] and yaw moment [N m]; each group (horizontal,
    vertical) is scaled down as a whole when one of its thrusters would exceed ``limit``."""
    t = alloc @ np.array([fx, fy, fz, 0.0, 0.0, mz])
    for group in (HORIZONTAL, VERTICAL):
        peak = float(np.max(np.abs(t[group])))
        if peak > limit:
            t[group] *= limit / peak
    return t
