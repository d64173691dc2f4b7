"""Frames and rotations. Pure numpy.

Conventions (everywhere inside hilsim): the world frame is NED (x north,
y east, z down) [m]; a body frame is x forward, y starboard, z down. Attitude
is roll, pitch, yaw [rad], applied Z-Y-X: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``
maps body vectors to world vectors. Positive pitch raises the nose, so a sensor
tilted 45 deg *down* has pitch = -45 deg.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


def rot_x(a: float) -> F64:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> F64:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> F64:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rpy_to_matrix(roll: float, pitch: float, yaw: float) -> F64:
    """(3, 3) rotation body->world from roll, pitch, yaw [rad] (Z-Y-X order)."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def matrix_to_rpy(r: F64) -> tuple[float, float, float]:
    """Inverse of :func:`rpy_to_matrix`: (roll, pitch, yaw) [rad]."""
    pitch = float(np.arcsin(np.clip(-r[2, 0], -1.0, 1.0)))
    roll = float(np.arctan2(r[2, 1], r[2, 2]))
    yaw = float(np.arctan2(r[1, 0], r[0, 0]))
    return roll, pitch, yaw


def wrap_angle(a: float) -> float:
    """Wrap an angle [rad] to [-pi, pi)."""
    return float((a + np.pi) % (2.0 * np.pi) - np.pi)


@dataclass(frozen=True)
class Pose:
    """A rigid transform: ``world = rotation @ local + position``.

    position: (3,) float [m]; rotation: (3, 3) float, local->parent.
    """

    position: F64 = field(default_factory=lambda: np.zeros(3))
    rotation: F64 = field(default_factory=lambda: np.eye(3))

    @staticmethod
    def from_xyz_rpy(xyz: Sequence[float] | F64, rpy: Sequence[float] | F64) -> "Pose":
        """Pose from a position [m] and roll, pitch, yaw [rad]."""
        return Pose(np.asarray(xyz, dtype=float).reshape(3), rpy_to_matrix(*(float(a) for a in rpy)))

    def __matmul__(self, other: "Pose") -> "Pose":
        """Compose: ``(self @ other)`` maps other's local frame into self's parent."""
        return Pose(self.rotation @ other.position + self.position, self.rotation @ other.rotation)

    def inverse(self) -> "Pose":
        rt = self.rotation.T
        return Pose(-rt @ self.position, rt)

    def apply(self, points: F64) -> F64:
        """Transform (n, 3) points from local to parent."""
        return np.asarray(points, dtype=float) @ self.rotation.T + self.position

    def apply_dirs(self, dirs: F64) -> F64:
        """Rotate (n, 3) directions from local to parent."""
        return np.asarray(dirs, dtype=float) @ self.rotation.T

    def rpy(self) -> tuple[float, float, float]:
        return matrix_to_rpy(self.rotation)

    def matrix(self) -> F64:
        """(4, 4) homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.position
        return m
