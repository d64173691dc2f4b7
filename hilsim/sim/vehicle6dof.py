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

Integrator: classical RK4 on the 12 states in Python floats (as the 4-DOF
model: numpy on vectors this small costs more than the arithmetic), the wrench
held over the step. Stiffest rates of a BlueROV2: damping ``(k + 2 k_q |x|) / m``
a few per second, restoring ``omega_n`` about 2 rad/s: ``lambda dt`` stays far
inside RK4's stability region at 50 ms.

The step returns a :class:`VehicleState` (``from_flat`` layout); its
``acceleration`` is the mean of ``(du, dv, dw)/dt`` over the step, as the
4-DOF model's. The specific force an IMU reads follows from it (see
:func:`specific_force`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Mapping, Protocol, Sequence

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

GRAVITY = 9.80665  # [m/s^2] standard gravity (what ArduPilot and the IMU models use)
_TWO_PI = 2.0 * math.pi
_PI = math.pi
_HALF_PI = 0.5 * math.pi
_sin, _cos, _tan = math.sin, math.cos, math.tan
_new = object.__new__
_STILL = (0.0, 0.0, 0.0)  # still water (compared by identity)


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


def _body_current(cn: float, ce: float, cd: float, sf: float, cf: float, st: float, ct: float,
                  sy: float, cy: float) -> tuple[float, float, float]:
    """A NED vector (cn, ce, cd) in the body frame, ``R^T c``, from the sines and cosines
    of roll, pitch, yaw."""
    r00, r10, r20 = cy * ct, sy * ct, -st
    r01, r11, r21 = cy * st * sf - sy * cf, sy * st * sf + cy * cf, ct * sf
    r02, r12, r22 = cy * st * cf + sy * sf, sy * st * cf - cy * sf, ct * cf
    return (r00 * cn + r10 * ce + r20 * cd, r01 * cn + r11 * ce + r21 * cd, r02 * cn + r12 * ce + r22 * cd)


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
        self._deriv = _make_deriv(self._mass, self._lin, self._quad, m, self._added, self._wb, self._b, self._rb)

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
        wr = wrench.tolist() if isinstance(wrench, np.ndarray) else [float(x) for x in wrench]
        return self._step(state, dt, wr, current)

    def step_with_thrusters(self, state: VehicleState, dt: float, thrusters: "ThrusterSet",
                            current: Current | None = None) -> VehicleState:
        """One physics tick: the thrusters' full wrench (forces and all three moments: an
        off-centre thruster rolls and pitches the vehicle) at the step's start, held over
        ``dt`` [s]; the rotors are then advanced to the step's end (mutates ``thrusters``)."""
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        mx, my = thrusters.roll_pitch_moments()
        fx, fy, fz, mz = thrusters.tick(dt, state.time + dt)
        return self._step(state, dt, [fx, fy, fz, mx, my, mz], current)

    def _step(self, state: VehicleState, dt: float, wr: list[float],
              current: Current | None) -> VehicleState:
        """RK4 of the 12 states (see the module doc) with the wrench ``wr`` (6,) held."""
        d = state.__dict__
        flat = d.get("_flat")
        if flat is None or "position" in d:
            flat = state.flat()
        x0, y0, z0, f0, t0, s0, u0, v0, w0, p0, q0, r0 = flat[:12]
        time0 = state.time
        fx, fy, fz, mx, my, mz = wr
        deriv = self._deriv
        h = 0.5 * dt
        if current is None or current.is_zero:
            c1 = c2 = c3 = c4 = _STILL
        else:
            vel = current.velocity
            c1 = vel(z0, time0)
        a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11 = deriv(
            f0, t0, s0, u0, v0, w0, p0, q0, r0, fx, fy, fz, mx, my, mz, c1)
        if c1 is not _STILL:
            c2 = vel(z0 + h * a2, time0 + h)
        b0, b1, b2, b3, b4, b5, b6, b7, b8, b9, b10, b11 = deriv(
            f0 + h * a3, t0 + h * a4, s0 + h * a5, u0 + h * a6, v0 + h * a7, w0 + h * a8,
            p0 + h * a9, q0 + h * a10, r0 + h * a11, fx, fy, fz, mx, my, mz, c2)
        if c1 is not _STILL:
            c3 = vel(z0 + h * b2, time0 + h)
        c0_, c1_, c2_, c3_, c4_, c5_, c6_, c7_, c8_, c9_, c10_, c11_ = deriv(
            f0 + h * b3, t0 + h * b4, s0 + h * b5, u0 + h * b6, v0 + h * b7, w0 + h * b8,
            p0 + h * b9, q0 + h * b10, r0 + h * b11, fx, fy, fz, mx, my, mz, c3)
        if c1 is not _STILL:
            c4 = vel(z0 + dt * c2_, time0 + dt)
        d0, d1, d2, d3, d4, d5, d6, d7, d8, d9, d10, d11 = deriv(
            f0 + dt * c3_, t0 + dt * c4_, s0 + dt * c5_, u0 + dt * c6_, v0 + dt * c7_, w0 + dt * c8_,
            p0 + dt * c9_, q0 + dt * c10_, r0 + dt * c11_, fx, fy, fz, mx, my, mz, c4)
        k6 = dt / 6.0
        u1 = u0 + k6 * (a6 + 2.0 * (b6 + c6_) + d6)
        v1 = v0 + k6 * (a7 + 2.0 * (b7 + c7_) + d7)
        w1 = w0 + k6 * (a8 + 2.0 * (b8 + c8_) + d8)
        roll = f0 + k6 * (a3 + 2.0 * (b3 + c3_) + d3)
        pitch = t0 + k6 * (a4 + 2.0 * (b4 + c4_) + d4)
        yaw = s0 + k6 * (a5 + 2.0 * (b5 + c5_) + d5)
        if pitch > _HALF_PI or pitch < -_HALF_PI:  # over the top: the same rotation with |pitch| <= 90 deg
            pitch = (_PI if pitch > 0 else -_PI) - pitch
            roll += _PI
            yaw += _PI
        inv = 1.0 / dt
        out = _new(VehicleState)
        od = out.__dict__
        od["time"] = time0 + dt
        od["_flat"] = (x0 + k6 * (a0 + 2.0 * (b0 + c0_) + d0), y0 + k6 * (a1 + 2.0 * (b1 + c1_) + d1),
                       z0 + k6 * (a2 + 2.0 * (b2 + c2_) + d2),
                       (roll + _PI) % _TWO_PI - _PI, pitch, (yaw + _PI) % _TWO_PI - _PI,
                       u1, v1, w1,
                       p0 + k6 * (a9 + 2.0 * (b9 + c9_) + d9), q0 + k6 * (a10 + 2.0 * (b10 + c10_) + d10),
                       r0 + k6 * (a11 + 2.0 * (b11 + c11_) + d11),
                       (u1 - u0) * inv, (v1 - v0) * inv, (w1 - w0) * inv)
        return out


def _make_deriv(mass: tuple[float, ...], lin: tuple[float, ...], quad: tuple[float, ...], rigid: float,
                added: tuple[float, float, float], wb: float, b: float,
                rb: tuple[float, float, float]) -> Callable[..., tuple[float, ...]]:
    """The right-hand side with the profile's constants bound as locals (fast in CPython).

    The returned function takes (phi, theta, psi [rad], u, v, w [m/s], p, q, r [rad/s],
    Fx, Fy, Fz [N], Mx, My, Mz [N m], current (3,) NED [m/s]) and gives the time
    derivatives of (x, y, z, phi, theta, psi, u, v, w, p, q, r) (12,) in SI."""
    mu, mv, mw, ip, iq, ir = mass
    ju, jv, jw, jp, jq, jr = (1.0 / x for x in mass)
    ku, kv, kw, kp, kq, kr = lin
    qu, qv, qw, qp, qq, qr = quad
    au, av, aw = added
    m = rigid
    xb, yb, zb = rb
    bxb, byb, bzb = b * xb, b * yb, b * zb
    irq, ipr, iqp = ir - iq, ip - ir, iq - ip
    awv, auw, avu = aw - av, au - aw, av - au
    sin, cos = _sin, _cos

    def deriv(phi: float, theta: float, psi: float, u: float, v: float, w: float, p: float, q: float,
              r: float, fx: float, fy: float, fz: float, mx: float, my: float, mz: float,
              cur: tuple[float, float, float]) -> tuple[float, ...]:
        sf, cf = sin(phi), cos(phi)
        st, ct = sin(theta), cos(theta)
        sy, cy = sin(psi), cos(psi)
        # body -> NED rotation, Z-Y-X; its last row is g_b = R^T e_z
        r00, r10, r20 = cy * ct, sy * ct, -st
        stsf, stcf = st * sf, st * cf
        r01, r11, r21 = cy * stsf - sy * cf, sy * stsf + cy * cf, ct * sf
        r02, r12, r22 = cy * stcf + sy * sf, sy * stcf - cy * sf, ct * cf
        if cur is _STILL:
            ur, vr, wr = u, v, w
            p1x, p1y, p1z = mu * u, mv * v, mw * w
        else:
            cn, ce, cd = cur
            ur = u - (r00 * cn + r10 * ce + r20 * cd)
            vr = v - (r01 * cn + r11 * ce + r21 * cd)
            wr = w - (r02 * cn + r12 * ce + r22 * cd)
            p1x, p1y, p1z = m * u + au * ur, m * v + av * vr, m * w + aw * wr
        du = (fx + wb * r20 - (ku + qu * abs(ur)) * ur - q * p1z + r * p1y) * ju
        dv = (fy + wb * r21 - (kv + qv * abs(vr)) * vr - r * p1x + p * p1z) * jv
        dw = (fz + wb * r22 - (kw + qw * abs(wr)) * wr - p * p1y + q * p1x) * jw
        dp = (mx - byb * r22 + bzb * r21 - (kp + qp * abs(p)) * p - irq * q * r - awv * vr * wr) * jp
        dq = (my - bzb * r20 + bxb * r22 - (kq + qq * abs(q)) * q - ipr * r * p - auw * wr * ur) * jq
        dr = (mz - bxb * r21 + byb * r20 - (kr + qr * abs(r)) * r - iqp * p * q - avu * ur * vr) * jr
        qs_rc = q * sf + r * cf
        if -1e-9 < ct < 1e-9:  # pitch at +-90 deg: the Euler rates are singular there; step past it
            ct = 1e-9
        return (r00 * u + r01 * v + r02 * w, r10 * u + r11 * v + r12 * w, r20 * u + r21 * v + r22 * w,
                p + qs_rc * st / ct, q * cf - r * sf, qs_rc / ct,
                du, dv, dw, dp, dq, dr)

    return deriv
