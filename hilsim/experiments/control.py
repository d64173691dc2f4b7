"""A simple track-following controller for the experiments (ours; the paper gives none).

The paper's water-tank run has Cyclops move "forward 1.5 m above bottom" at a
steady speed. :class:`TrackController` reproduces that with four independent
loops on the diagonal model of :mod:`hilsim.sim.vehicle` (each DOF is a mass
``m`` with linear damping ``k`` and quadratic damping ``k_q``):

- surge, PI on the body speed ``u`` toward ``speed`` [m/s], plus the model's
  steady-state force ``k u* + k_q u*|u*|`` as feed-forward;
- heave, PID on the depth ``z`` toward ``depth`` [m] (PD does the work; the
  slow integral removes the offset the net buoyancy ``W_w`` would leave);
- yaw, PD on the heading error toward ``heading`` [rad];
- sway, PD on the cross-track offset from the line through ``origin`` along
  ``heading`` (starboard positive).

Gains are placed from the vehicle profile, not tuned by hand: a loop of
bandwidth ``omega`` [rad/s] and damping ratio ``zeta`` gets
``Kp = m omega^2`` and ``Kd = 2 zeta m omega - k`` (never below 0); the surge
PI gets ``Kp = m omega`` and ``Ki = Kp omega / 4``. Forces are clamped to
80 % of what the thrusters can give along each axis, and an integral is frozen
while its axis is clamped (anti-windup).

:meth:`TrackController.apply` turns the body wrench (Fx, Fy, Fz [N], Mx, My,
Mz [N m]) into thruster commands exactly as an autopilot talking to real ESCs
would: :meth:`ThrusterSet.allocate` gives the thrusts, and
:meth:`ThrusterSet.command_for_thrust` the normalised command of each thruster.
The thruster model (first-order lag, dead band, saturation) then decides what
thrust the vehicle really gets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hilsim.sim.geometry import F64, wrap_angle
from hilsim.sim.state import VehicleState
from hilsim.sim.thrusters import ThrusterSet
from hilsim.sim.vehicle import VehicleProfile

AXIS_MARGIN = 0.8  # fraction of each axis' reachable force the controller may ask for


@dataclass(frozen=True)
class LoopTuning:
    """Closed-loop bandwidths [rad/s] and damping ratio [1] of the four loops."""

    surge_bandwidth: float = 2.0
    heave_bandwidth: float = 1.0
    yaw_bandwidth: float = 1.5
    sway_bandwidth: float = 0.8
    damping_ratio: float = 0.9


def axis_limits(thrusters: ThrusterSet) -> F64:
    """(6,) largest |wrench| [N, N m] the thrusters can produce along each single axis."""
    out = np.zeros(6)
    for i in range(6):
        w = np.zeros(6)
        w[i] = 1e6
        out[i] = abs(float(thrusters.allocate(w).wrench[i]))
    return out


class TrackController:
    """Holds ``speed`` [m/s] along the line through ``origin`` (3,) NED [m] with
    heading ``heading`` [rad], at depth ``depth`` [m]; see the module doc."""

    def __init__(self, profile: VehicleProfile, thrusters: ThrusterSet, *, speed: float, depth: float,
                 heading: float, origin: F64, tuning: LoopTuning = LoopTuning()) -> None:
        for dof in ("surge", "sway", "heave", "yaw"):
            if dof not in profile.params:
                raise ValueError(f"vehicle {profile.name!r} does not model {dof}; the track controller needs it")
        self.thrusters = thrusters
        self.speed, self.depth, self.heading = float(speed), float(depth), float(heading)
        self.origin = np.asarray(origin, dtype=float)
        self.limits = axis_limits(thrusters) * AXIS_MARGIN
        p, z = profile.params, tuning.damping_ratio
        su, hv, yw, sw = p["surge"], p["heave"], p["yaw"], p["sway"]
        self.feed_forward = su.linear_damping * speed + su.quadratic_damping * speed * abs(speed)
        self.kp_u = su.mass * tuning.surge_bandwidth
        self.ki_u = self.kp_u * tuning.surge_bandwidth / 4.0

        def pd(mass: float, damping: float, omega: float) -> tuple[float, float]:
            return mass * omega * omega, max(0.0, 2.0 * z * mass * omega - damping)

        self.kp_z, self.kd_z = pd(hv.mass, hv.linear_damping, tuning.heave_bandwidth)
        self.ki_z = self.kp_z * tuning.heave_bandwidth / 10.0
        self.kp_psi, self.kd_psi = pd(yw.mass, yw.linear_damping, tuning.yaw_bandwidth)
        self.kp_y, self.kd_y = pd(sw.mass, sw.linear_damping, tuning.sway_bandwidth)
        self._int_u = 0.0   # [m/s * s] integral of the speed error
        self._int_z = 0.0   # [m * s] integral of the depth error
        self._last_t: float | None = None
        need = abs(self.feed_forward)
        if need > self.limits[0]:
            raise ValueError(f"speed {speed:g} m/s needs {need:.0f} N of surge thrust; the thrusters of "
                             f"{profile.name!r} can hold about {self.limits[0]:.0f} N")

    def cross_track(self, state: VehicleState) -> float:
        """[m] offset of the body origin from the track line, positive to starboard of it."""
        dx = float(state.position[0]) - float(self.origin[0])
        dy = float(state.position[1]) - float(self.origin[1])
        return -math.sin(self.heading) * dx + math.cos(self.heading) * dy

    def wrench(self, state: VehicleState) -> F64:
        """(6,) body wrench [N, N m] for ``state``; advances the integrals by the
        time since the previous call."""
        t = state.time
        dt = 0.0 if self._last_t is None else max(0.0, t - self._last_t)
        self._last_t = t
        u, v, w = state.velocity.tolist()
        r = float(state.angular_velocity[2])
        e_u = self.speed - u
        e_z = self.depth - state.depth
        fx = self.feed_forward + self.kp_u * e_u + self.ki_u * self._int_u
        fz = self.kp_z * e_z - self.kd_z * w + self.ki_z * self._int_z
        lx, lz = self.limits[0], self.limits[2]
        if abs(fx) < lx:  # anti-windup: integrate only while the axis is not clamped
            self._int_u += e_u * dt
        if abs(fz) < lz:
            self._int_z += e_z * dt
        e_psi = wrap_angle(self.heading - state.heading)
        mz = self.kp_psi * e_psi - self.kd_psi * r
        fy = -self.kp_y * self.cross_track(state) - self.kd_y * v
        raw = np.array([fx, fy, fz, 0.0, 0.0, mz])
        out: F64 = np.clip(raw, -self.limits, self.limits)
        return out

    def apply(self, state: VehicleState, now: float) -> F64:
        """Compute the wrench for ``state``, allocate it and command every thruster
        at time ``now`` [s]; returns the thrusts (n,) [N] asked for."""
        alloc = self.thrusters.allocate(self.wrench(state))
        for i, thrust in enumerate(alloc.thrusts.tolist()):
            cmd = self.thrusters.command_for_thrust(i, thrust, "normalized")
            self.thrusters.command(i, "normalized", cmd, now)
        return alloc.thrusts
