"""Six-degree-of-freedom vehicle dynamics (Fossen's model, diagonal coefficients).

For the profiles that give the data (a ``[hydrostatics]`` table and all six
DOFs under ``[dynamics]``)::

    M dnu/dt + C(nu, nu_r) + D(nu_r) nu_r + g(eta) = tau

nu = (u, v, w, p, q, r) body velocities over ground, nu_r = nu minus the
current (an irrotational current: only the linear part changes). The body
origin is the centre of gravity (CG), so the rigid-body inertia is diagonal:

- ``M = diag(m_u, m_v, m_w, I_p, I_q, I_r)``: the ``[dynamics.<dof>].mass``
  of the profile, rigid body plus added mass (``m + X_udot``, ``I_x + K_pdot``);
  the added translational mass ``a_i = m_i - m`` (m = ``[vehicle].mass``).
- Coriolis and centripetal terms in Kirchhoff's form, with the momenta
  ``P1 = m v + A v_r`` (A = diag(a_u, a_v, a_w)) and ``P2 = I omega``::

      C = [omega x P1 ; omega x P2 + v_r x (A v_r)]

  (the rigid body's ``m omega x v`` and ``omega x I omega``, the added mass's
  ``omega x A v_r``, and the Munk moment ``v_r x A v_r``). In still water
  ``nu . C = 0``: the terms move energy between DOFs and create none.
- Damping per DOF on the relative velocity, ``(k_i + k_i|i| |x|) x``.
- Restoring force and moment of the weight W at the CG and the buoyancy B at
  ``r_b`` (body frame, from the CG): with ``g_b = R^T e_z = (-sin theta,
  cos theta sin phi, cos theta cos phi)`` the force is ``(W - B) g_b`` and the
  moment ``-B r_b x g_b`` (a CB above the CG rights the vehicle).
- Kinematics: ``d(x, y, z)/dt = R(phi, theta, psi) (u, v, w)`` and the
  Z-Y-X Euler rates ``dphi/dt = p + (q sin phi + r cos phi) tan theta``,
  ``dtheta/dt = q cos phi - r sin phi``, ``dpsi/dt = (q sin phi + r cos phi) / cos theta``
  (singular at pitch +-90 deg: the rates are bounded there, and a state pitched past
  it is written back as the same rotation with |pitch| <= 90 deg).

Integrator: classical RK4 on the 12 states, the wrench held over the step, the
current evaluated at each stage's depth and time. The step is one call of a
compiled kernel (:mod:`hilsim.sim.vehicle6dof_kernel`, numba; the same source runs
in CPython without numba): the Heavy with 8 thrusters runs above 1000x real time
at 200 Hz. Stiffest rates of a BlueROV2: damping ``(k + 2 k_q |x|) / m`` a few per
second, restoring ``omega_n`` about 2 rad/s: ``lambda dt`` stays far inside RK4's
stability region at 50 ms.

The step returns a :class:`VehicleState` (``from_flat`` layout); its
``acceleration`` is the mean of ``(du, dv, dw)/dt`` over the step, as the
4-DOF model's. The specific force an IMU reads follows from it (see
:func:`specific_force`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Mapping, Protocol, Sequence

import numpy as np

from hilsim.sim.geometry import F64
from hilsim.sim.state import VehicleState

if TYPE_CHECKING:
    from hilsim.sim.thrusters import ThrusterSet


class _Dof(Protocol):
    @property
    def mass(self) -> float: ...

    @property
    def linear_damping(self) -> float: ...

    @property
    def quadratic_damping(self) -> float: ...


class VehicleProfile(Protocol):
    """What the 6-DOF model reads of a :class:`hilsim.sim.vehicle.VehicleProfile`
    (declared here: ``vehicle`` imports this module, not the other way round)."""

    @property
    def name(self) -> str: ...

    @property
    def params(self) -> Mapping[str, _Dof]: ...

    @property
    def rigid_mass(self) -> float | None: ...

    @property
    def hydrostatics(self) -> "Hydrostatics | None": ...


class Current(Protocol):
    """What the model reads of a :class:`hilsim.sim.vehicle.Current`."""

    @property
    def is_zero(self) -> bool: ...

    def velocity(self, depth: float, time: float) -> tuple[float, float, float]: ...

    @property
    def velocities(self) -> tuple[tuple[tuple[float, float, float], ...], ...]:
        """(m, k, 3) NED [m/s] over ``times`` (m,) [s] and ``depths`` (k,) [m]."""
        ...

    @property
    def times(self) -> tuple[float, ...]: ...

    @property
    def depths(self) -> tuple[float, ...]: ...


GRAVITY = 9.80665  # [m/s^2] standard gravity (what ArduPilot and the IMU models use)
_sin, _cos = math.sin, math.cos
_new = object.__new__


@dataclass(frozen=True)
class Hydrostatics:
    """Weight and buoyancy: weight [N] (m g) acting at the CG (the body origin),
    buoyancy [N] (rho g V) acting at centre_of_buoyancy (3,) [m] in the body
    frame (x forward, y starboard, z down; negative z = CB above the CG)."""

    weight: float
    buoyancy: float
    centre_of_buoyancy: tuple[float, float, float]

    @property
    def net_down(self) -> float:
        """[N] W - B: positive sinks."""
        return self.weight - self.buoyancy

    def righting_stiffness(self) -> tuple[float, float]:
        """(roll, pitch) [N m/rad] restoring stiffness about level, ``-B z_b``."""
        zb = self.centre_of_buoyancy[2]
        return -self.buoyancy * zb, -self.buoyancy * zb


def specific_force(state: VehicleState, gravity: float = GRAVITY) -> tuple[float, float, float]:
    """Specific force (3,) [m/s^2] in the body frame, what an accelerometer at the CG
    reads: the true acceleration in the body frame ``dv/dt + omega x v`` minus gravity
    in the body frame ``R^T (0, 0, g)``. Level at rest: (0, 0, -g)."""
    x, y, z, roll, pitch, yaw, u, v, w, p, q, r, du, dv, dw = state.flat()
    sr, cr, sp, cp = _sin(roll), _cos(roll), _sin(pitch), _cos(pitch)
    return (du + q * w - r * v + gravity * sp,
            dv + r * u - p * w - gravity * cp * sr,
            dw + p * v - q * u - gravity * cp * cr)


class Vehicle6DOF:
    """6-DOF dynamics of one profile (built by ``Vehicle(profile)`` when the profile has
    hydrostatics). :meth:`step` is pure; the interface is :class:`hilsim.sim.vehicle.Vehicle`'s."""

    profile: VehicleProfile

    def __init__(self, profile: VehicleProfile):
        hs = profile.hydrostatics
        if hs is None or profile.rigid_mass is None:
            raise ValueError(f"{profile.name}: a 6-DOF model needs [hydrostatics] and [vehicle].mass")
        missing = [d for d in ("surge", "sway", "heave", "roll", "pitch", "yaw") if d not in profile.params]
        if missing:
            raise ValueError(f"{profile.name}: a 6-DOF model needs every DOF; missing {missing}")
        self.profile = profile
        par = profile.params
        m = profile.rigid_mass
        self._mass = tuple(par[d].mass for d in ("surge", "sway", "heave", "roll", "pitch", "yaw"))
        self._inv = tuple(1.0 / x for x in self._mass)
        self._lin = tuple(par[d].linear_damping for d in ("surge", "sway", "heave", "roll", "pitch", "yaw"))
        self._quad = tuple(par[d].quadratic_damping for d in ("surge", "sway", "heave", "roll", "pitch", "yaw"))
        self._rigid = m
        self._added = (self._mass[0] - m, self._mass[1] - m, self._mass[2] - m)
        if min(self._added) < 0:
            raise ValueError(f"{profile.name}: a translational [dynamics] mass is below [vehicle].mass")
        self._wb = hs.net_down
        self._b = hs.buoyancy
        self._rb = hs.centre_of_buoyancy
        from hilsim.sim import vehicle6dof_kernel as kernel  # numba loads with the first 6-DOF vehicle only

        self._rk4, self._rk4_current = kernel.rk4, kernel.rk4_current
        packed = kernel.pack(self._mass, self._lin, self._quad, m, self._added, self._wb, self._b, self._rb)
        # CPython indexes a tuple of floats faster than an array
        self._par: kernel.Params = packed if kernel.COMPILED else tuple(packed.tolist())
        self._tables: tuple[object, tuple[int, F64, F64, F64]] | None = None  # the last current's

    def steady_speed(self, dof: str, force: float) -> float:
        """[m/s | rad/s] still-water speed of a translational DOF where damping balances
        ``force`` [N] (plus W - B in heave), level attitude."""
        p = self.profile.params[dof]
        f = force + (self._wb if dof == "heave" else 0.0)
        k, kq = p.linear_damping, p.quadratic_damping
        x = abs(f)
        s = x / k if kq == 0 else (-k + math.sqrt(k * k + 4 * kq * x)) / (2 * kq)
        return math.copysign(s, f)

    def step(self, state: VehicleState, dt: float, wrench: Sequence[float] | F64,
             current: Current | None = None) -> VehicleState:
        """Advance ``state`` by ``dt`` [s] under the body ``wrench`` (6,) (Fx, Fy, Fz [N],
        Mx, My, Mz [N m]) held over the step, in ``current`` (None: still water)."""
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        wr = tuple(wrench.tolist() if isinstance(wrench, np.ndarray) else (float(x) for x in wrench))
        if len(wr) != 6:
            raise ValueError(f"a 6-DOF wrench has 6 components, got {len(wr)}")
        return self._step(state, dt, wr, current)

    def step_with_thrusters(self, state: VehicleState, dt: float, thrusters: "ThrusterSet",
                            current: Current | None = None) -> VehicleState:
        """One physics tick: the thrusters' full wrench (forces and all three moments: an
        off-centre thruster rolls and pitches the vehicle) at the step's start, held over
        ``dt`` [s]; the rotors are then advanced to the step's end (mutates ``thrusters``)."""
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        return self._step(state, dt, thrusters.tick6(dt, state.time + dt), current)

    def _step(self, state: VehicleState, dt: float, wr: tuple[float, ...],
              current: Current | None) -> VehicleState:
        """RK4 of the 12 states (see the module doc) with the wrench ``wr`` (6,) held:
        one call of the compiled kernel (:mod:`hilsim.sim.vehicle6dof_kernel`)."""
        d = state.__dict__
        flat = d.get("_flat")
        if flat is None or "position" in d:
            flat = state.flat()
        out = _new(VehicleState)
        od = out.__dict__
        time0 = state.time
        od["time"] = time0 + dt
        if current is None or current.is_zero:
            od["_flat"] = self._rk4(self._par, flat, wr, time0, dt)
        else:
            od["_flat"] = self._rk4_current(self._par, *self._current_tables(current), flat, wr, time0, dt)
        return out

    def _current_tables(self, current: Current) -> tuple[int, F64, F64, F64]:
        """The kernel's view of ``current`` (mode, times, depths, velocities), built once per
        current object."""
        cached = self._tables
        if cached is not None and cached[0] is current:
            return cached[1]
        from hilsim.sim import vehicle6dof_kernel as kernel

        vel = np.ascontiguousarray(current.velocities, dtype=np.float64)
        times = np.ascontiguousarray(current.times, dtype=np.float64)
        depths = np.ascontiguousarray(current.depths, dtype=np.float64)
        mode = kernel.UNIFORM if vel.shape[:2] == (1, 1) else kernel.TABLE
        tables = (mode, times, depths, vel)
        self._tables = (current, tables)
        return tables
