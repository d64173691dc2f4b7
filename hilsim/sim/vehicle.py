"""Vehicle dynamics: a diagonal low-speed model (the paper's eq. 11, generalised).

For each modelled degree of freedom (surge u, sway v, heave w, yaw r)::

    m_i dnu_i/dt = -k_i nu_r,i - k_i|i| nu_r,i |nu_r,i| + tau_i + c_i

with m_i the mass (or yaw inertia) including added mass, k_i and k_i|i| the
linear and quadratic damping, tau_i the thrusters' force (moment), c_i a
constant force (``W_w`` in eq. 11: negative heave = net buoyancy pushes up),
and ``nu_r = nu - nu_current`` the velocity relative to the water: damping
acts on the relative velocity, inertia on the velocity over ground (the
difference, ``m_A d(nu_c)/dt``, vanishes for a current constant in NED and is
neglected otherwise). Off-diagonal, Coriolis and centripetal terms are
dropped, as the paper does for a slow, symmetric vehicle.

Roll and pitch are held by the vehicle's own attitude control (the paper's
assumption): they are not integrated, the input state's roll/pitch are carried
through unchanged, the kinematics use heading only, and thruster moments
about x and y are ignored. A DOF a profile does not list is held at zero
velocity. Kinematics: ``d(x, y)/dt = Rz(psi) (u, v)``, ``dz/dt = w``,
``dpsi/dt = r`` (NED, body x forward / y starboard / z down).

Integrator: classical RK4 on the whole state (x, y, z, psi, u, v, w, r), with
the wrench held over the step (zero-order hold, as a sampled controller
applies it). Why: the stiffest rate is ``lambda = (k + 2 k_q |nu|) / m``. For
Cyclops at its top speeds (about 0.75 m/s) lambda is below 1/s in u, v, w and
about 3/s in yaw (our estimated yaw terms), so ``lambda dt <= 0.16`` at 50 ms,
far inside RK4's real-axis stability limit (2.79), with a local error of order
``(lambda dt)^5 / 120``. A BlueROV2-size vehicle (lambda up to about 20/s in
yaw) stays stable at 50 ms too (lambda dt about 1). Semi-implicit Euler would
be unconditionally stable but only first order: at 50 ms its error is about
``lambda dt / 2`` of a transient (several percent), which would break the
agreement of 1 ms and 50 ms runs. RK4 is evaluated in plain Python floats
(eight scalars: faster than numpy calls on arrays this small). In still water
the velocity equations do not depend on the pose, so each DOF's RK4 stages
are computed alone and the position and heading are integrated from those
same stages with the RK4 weights: the same scheme as RK4 on the full state.

Profiles (``devices/vehicles/*.toml``) are read by :func:`load_vehicle_profile`;
another vehicle is another file. Water currents are :class:`Current`.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from hilsim.config import Doc, check_keys, load_toml, quantity, require
from hilsim.resources import find_profile
from hilsim.sim.geometry import F64
from hilsim.sim.state import VehicleState
from hilsim.sim.thrusters import Thruster, ThrusterProfile, ThrusterSet, load_thruster_profile

DOF_NAMES = ("surge", "sway", "heave", "roll", "pitch", "yaw")
MODELLED_DOFS = ("surge", "sway", "heave", "yaw")
_ROTATIONAL = ("roll", "pitch", "yaw")
_TWO_PI = 2.0 * math.pi


def _bracket(grid: tuple[float, ...], x: float) -> tuple[int, int, float]:
    """Indices (i, j) and weight of j for linear interpolation in ``grid``, clamped."""
    if len(grid) == 1 or x <= grid[0]:
        return 0, 0, 0.0
    if x >= grid[-1]:
        return len(grid) - 1, len(grid) - 1, 0.0
    j = bisect.bisect_right(grid, x)
    return j - 1, j, (x - grid[j - 1]) / (grid[j] - grid[j - 1])


@dataclass(frozen=True)
class Current:
    """Water velocity over ground, NED (3,) [m/s], constant or tabulated.

    velocities (m, k, 3) [m/s] at times (m,) [s] and depths (k,) [m] (either
    grid may have a single entry for "does not vary"); interpolated bilinearly,
    held constant beyond the grids' ends. Build with :meth:`constant`,
    :meth:`over_depth`, :meth:`over_time` or the full constructor.
    """

    velocities: tuple[tuple[tuple[float, float, float], ...], ...]
    times: tuple[float, ...] = (0.0,)
    depths: tuple[float, ...] = (0.0,)

    def __post_init__(self) -> None:
        arr = np.asarray(self.velocities, dtype=float)
        if arr.shape != (len(self.times), len(self.depths), 3):
            raise ValueError(f"velocities must be (len(times), len(depths), 3), got {arr.shape}")
        for g in (self.times, self.depths):
            if any(b <= a for a, b in zip(g, g[1:])):
                raise ValueError("times and depths must be strictly increasing")

    @staticmethod
    def constant(velocity: Sequence[float]) -> "Current":
        """A uniform, steady current (3,) NED [m/s]."""
        v = tuple(float(c) for c in velocity)
        return Current((((v[0], v[1], v[2]),),))

    @staticmethod
    def over_depth(depths: Sequence[float], velocities: Sequence[Sequence[float]]) -> "Current":
        """A steady profile: depths (k,) [m], velocities (k, 3) NED [m/s]."""
        rows = tuple((float(a), float(b), float(c)) for a, b, c in velocities)
        return Current((rows,), depths=tuple(float(d) for d in depths))

    @staticmethod
    def over_time(times: Sequence[float], velocities: Sequence[Sequence[float]]) -> "Current":
        """A uniform current varying in time: times (m,) [s], velocities (m, 3) NED [m/s]."""
        rows = tuple(((float(a), float(b), float(c)),) for a, b, c in velocities)
        return Current(rows, times=tuple(float(t) for t in times))

    @property
    def is_zero(self) -> bool:
        """True when the water is still everywhere."""
        return not any(c for plane in self.velocities for row in plane for c in row)

    def velocity(self, depth: float, time: float) -> tuple[float, float, float]:
        """NED current (north, east, down) [m/s] at ``depth`` [m] and ``time`` [s]."""
        if len(self.times) == 1 and len(self.depths) == 1:
            return self.velocities[0][0]
        ti, tj, tw = _bracket(self.times, time)
        di, dj, dw = _bracket(self.depths, depth)
        out = []
        for c in range(3):
            lo = self.velocities[ti][di][c] * (1 - dw) + self.velocities[ti][dj][c] * dw
            hi = self.velocities[tj][di][c] * (1 - dw) + self.velocities[tj][dj][c] * dw
            out.append(lo * (1 - tw) + hi * tw)
        return out[0], out[1], out[2]


@dataclass(frozen=True)
class DofParameters:
    """One DOF's coefficients, SI: mass [kg] or inertia [kg m^2] (incl. added);
    linear_damping [N s/m | N m s/rad]; quadratic_damping [N s^2/m^2 | N m s^2/rad^2];
    constant_force [N | N m] added to the right-hand side (W_w in eq. 11)."""

    mass: float
    linear_damping: float
    quadratic_damping: float
    constant_force: float = 0.0


@dataclass(frozen=True)
class VehicleProfile:
    """A vehicle: which DOFs it models, their coefficients, and its thrusters.

    dofs: names from :data:`DOF_NAMES` (the others are held); params: DOF name ->
    :class:`DofParameters`; thrusters: placed thrusters (body frame);
    supply_voltage [V] or None (the thruster profile's nominal); sources:
    dotted key -> where its value comes from.
    """

    name: str
    dofs: tuple[str, ...]
    params: dict[str, DofParameters]
    thrusters: tuple[Thruster, ...] = ()
    supply_voltage: float | None = None
    sources: dict[str, str] = field(default_factory=dict)

    def thruster_set(self, supply_voltage: float | None = None, water_temperature: float = 288.15) -> ThrusterSet:
        """A fresh :class:`ThrusterSet` for this vehicle (voltage [V], temperature [K])."""
        return ThrusterSet(self.thrusters, supply_voltage or self.supply_voltage, water_temperature)


def _dof_units(dof: str) -> tuple[str, str, str, str]:
    if dof in _ROTATIONAL:
        return "kg*m^2", "N*m*s/rad", "N*m*s^2/rad^2", "N*m"
    return "kg", "N*s/m", "N*s^2/m^2", "N"


def load_vehicle_profile(path: Path | str) -> VehicleProfile:
    """Read a vehicle profile TOML; thruster profiles are resolved with
    :func:`hilsim.resources.find_profile` (beside the file first, then ``devices/``)."""
    path = Path(path)
    doc = load_toml(path)
    check_keys(doc, doc.data, ("vehicle", "dynamics", "thrusters"), "")
    veh = require(doc, doc.data, "vehicle", "")
    check_keys(doc, veh, ("name", "description", "dofs", "mass", "layout_note"), "vehicle")
    dofs = veh.get("dofs", list(MODELLED_DOFS))
    if not isinstance(dofs, list) or not dofs or any(d not in DOF_NAMES for d in dofs) or len(set(dofs)) != len(dofs):
        raise doc.error("vehicle.dofs", f"expected a list of distinct names from {DOF_NAMES}, got {dofs!r}")
    dyn = require(doc, doc.data, "dynamics", "")
    check_keys(doc, dyn, DOF_NAMES, "dynamics")
    params: dict[str, DofParameters] = {}
    sources: dict[str, str] = {}
    for dof in dofs:
        where = f"dynamics.{dof}"
        if dof not in dyn:
            raise doc.error("dynamics", f"DOF {dof!r} is listed in vehicle.dofs but has no [{where}] table")
        tab = dyn[dof]
        keys = ("mass", "linear_damping", "quadratic_damping", "constant_force")
        check_keys(doc, tab, keys, where)
        units = _dof_units(dof)
        vals = [float(quantity(doc, tab, k, u, where, default=0.0 if k == "constant_force" else None))
                for k, u in zip(keys, units)]
        if vals[0] <= 0 or vals[1] < 0 or vals[2] < 0:
            raise doc.error(where, "mass must be > 0 and damping >= 0")
        params[dof] = DofParameters(*vals)
        sources.update({f"{where}.{k}": str(tab[k]["source"]) for k in keys if k in tab})
    thrusters, voltage = _load_thrusters(doc, path)
    return VehicleProfile(str(veh.get("name", path.stem)), tuple(dofs), params, thrusters, voltage, sources)


def _load_thrusters(doc: Doc, path: Path) -> tuple[tuple[Thruster, ...], float | None]:
    th = doc.data.get("thrusters")
    if th is None:
        return (), None
    check_keys(doc, th, ("profile", "supply_voltage", "unit"), "thrusters")
    cache: dict[str, ThrusterProfile] = {}

    def profile(name: str, key: str) -> ThrusterProfile:
        if name not in cache:
            try:
                cache[name] = load_thruster_profile(find_profile("thrusters", name, base=path.parent))
            except FileNotFoundError as exc:
                raise doc.error(key, str(exc)) from None
        return cache[name]

    voltage = quantity(doc, th, "supply_voltage", "V", "thrusters", default=0.0) or None
    units = th.get("unit", [])
    if not isinstance(units, list) or not units:
        raise doc.error("thrusters", "expected one or more [[thrusters.unit]] tables")
    out = []
    for i, u in enumerate(units):
        where = f"thrusters.unit.{i}"
        check_keys(doc, u, ("name", "position", "direction", "profile"), where)
        pos = np.array(quantity(doc, u, "position", "m", where, length=3))
        d = np.array(quantity(doc, u, "direction", "1", where, length=3))
        if not np.linalg.norm(d) > 1e-9:
            raise doc.error(f"{where}.direction", "direction must be a non-zero vector")
        name = str(u.get("profile", th.get("profile", "")))
        if not name:
            raise doc.error(where, "no thruster profile: set thrusters.profile or this unit's profile")
        out.append(Thruster(str(u.get("name", f"t{i}")), pos, d / np.linalg.norm(d), profile(name, where)))
    return tuple(out), voltage


def _rk4_dof(x0: float, f: float, k: float, q: float, dt: float) -> tuple[float, float, float, float]:
    """RK4 step of ``dx/dt = f - k x - q x |x|`` (all per unit mass).

    Returns (x(dt), x at stage 2, x at stage 3, x at stage 4): the stage values
    are what the kinematics need to be integrated with the same RK4 weights.
    """
    h = 0.5 * dt
    a = f - (k + q * abs(x0)) * x0
    xb = x0 + h * a
    b = f - (k + q * abs(xb)) * xb
    xc = x0 + h * b
    c = f - (k + q * abs(xc)) * xc
    xd = x0 + dt * c
    d = f - (k + q * abs(xd)) * xd
    return x0 + dt / 6.0 * (a + 2.0 * b + 2.0 * c + d), xb, xc, xd


class Vehicle:
    """The dynamics of one vehicle profile. :meth:`step` is pure."""

    def __init__(self, profile: VehicleProfile):
        unsupported = [d for d in profile.dofs if d not in MODELLED_DOFS]
        if unsupported:
            raise ValueError(f"{profile.name}: DOFs {unsupported} are not modelled (roll and pitch are "
                             f"held by the vehicle's own control); model only {MODELLED_DOFS}")
        self.profile = profile

        def coeffs(dof: str) -> tuple[float, float, float, float]:
            p = profile.params.get(dof)
            if p is None:  # held DOF: no acceleration
                return 0.0, 0.0, 0.0, 0.0
            return 1.0 / p.mass, p.linear_damping, p.quadratic_damping, p.constant_force

        self._c = tuple(coeffs(d) for d in MODELLED_DOFS)
        self._held = any(d not in profile.dofs for d in MODELLED_DOFS)

    @staticmethod
    def from_file(path: Path | str) -> "Vehicle":
        """Vehicle from a profile TOML path."""
        return Vehicle(load_vehicle_profile(path))

    def steady_speed(self, dof: str, force: float) -> float:
        """[m/s | rad/s] still-water speed where damping balances ``force`` + constant force."""
        p = self.profile.params[dof]
        f = force + p.constant_force
        k, kq = p.linear_damping, p.quadratic_damping
        x = abs(f)
        s = x / k if kq == 0 else (-k + math.sqrt(k * k + 4 * kq * x)) / (2 * kq)
        return math.copysign(s, f)

    def step(self, state: VehicleState, dt: float, wrench: Sequence[float] | F64,
             current: Current | None = None) -> VehicleState:
        """Advance ``state`` by ``dt`` [s] under the body ``wrench`` (6,) (Fx, Fy, Fz [N],
        Mx, My, Mz [N m]; Mx, My ignored) held over the step, in ``current``
        (None: still water). Returns the new state; its ``acceleration`` is the
        mean body acceleration (du, dv, dw)/dt [m/s^2] over the step."""
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        wr = wrench.tolist() if isinstance(wrench, np.ndarray) else wrench
        (iu, ku, qu, cu), (iv, kv, qv, cv), (iw, kw, qw, cw), (ir, kr, qr, cr) = self._c
        forces = ((wr[0] + cu) * iu, (wr[1] + cv) * iv, (wr[2] + cw) * iw, (wr[5] + cr) * ir)
        t0 = state.time
        x0, y0, z0 = state.position.tolist()
        roll, pitch, psi0 = state.attitude.tolist()
        u0, v0, w0 = state.velocity.tolist()
        r0 = float(state.angular_velocity[2])
        if self._held:  # a held DOF keeps zero velocity
            u0, v0, w0, r0 = (a if i else 0.0 for a, i in zip((u0, v0, w0, r0), (iu, iv, iw, ir)))
        if current is None or current.is_zero:
            # still water: the four velocity ODEs are independent of the pose
            u = _rk4_dof(u0, forces[0], ku * iu, qu * iu, dt)
            v = _rk4_dof(v0, forces[1], kv * iv, qv * iv, dt)
            w = _rk4_dof(w0, forces[2], kw * iw, qw * iw, dt)
            r = _rk4_dof(r0, forces[3], kr * ir, qr * ir, dt)
        else:
            u, v, w, r = self._rk4_current(t0, z0, psi0, (u0, v0, w0, r0), forces, current, dt)
        # kinematics with the same RK4 weights, at the stages' headings and velocities
        h, k6 = dt * 0.5, dt / 6.0
        psi_b, psi_c, psi_d = psi0 + h * r0, psi0 + h * r[1], psi0 + dt * r[2]
        ca, cb, cc, cd = math.cos(psi0), math.cos(psi_b), math.cos(psi_c), math.cos(psi_d)
        sa, sb, sc, sd = math.sin(psi0), math.sin(psi_b), math.sin(psi_c), math.sin(psi_d)
        x = x0 + k6 * (ca * u0 - sa * v0 + 2.0 * (cb * u[1] - sb * v[1] + cc * u[2] - sc * v[2])
                       + cd * u[3] - sd * v[3])
        y = y0 + k6 * (sa * u0 + ca * v0 + 2.0 * (sb * u[1] + cb * v[1] + sc * u[2] + cc * v[2])
                       + sd * u[3] + cd * v[3])
        z = z0 + k6 * (w0 + 2.0 * (w[1] + w[2]) + w[3])
        psi = psi0 + k6 * (r0 + 2.0 * (r[1] + r[2]) + r[3])
        psi = (psi + math.pi) % _TWO_PI - math.pi
        inv = 1.0 / dt
        buf = np.array((x, y, z, roll, pitch, psi, u[0], v[0], w[0], 0.0, 0.0, r[0],
                        (u[0] - u0) * inv, (v[0] - v0) * inv, (w[0] - w0) * inv))
        return VehicleState(t0 + dt, buf[0:3], buf[3:6], buf[6:9], buf[9:12], buf[12:15])

    def _rk4_current(self, t0: float, z0: float, psi0: float, nu0: tuple[float, float, float, float],
                     forces: tuple[float, float, float, float], current: Current, dt: float
                     ) -> tuple[tuple[float, float, float, float], ...]:
        """RK4 of (z, psi, u, v, w, r) with damping on the velocity relative to ``current``;
        returns per DOF (end value, stage-2, stage-3, stage-4 velocity) like :func:`_rk4_dof`."""
        (iu, ku, qu, _), (iv, kv, qv, _), (iw, kw, qw, _), (ir, kr, qr, _) = self._c
        fu, fv, fw, fr = forces

        def deriv(t: float, z: float, psi: float, nu: tuple[float, ...]) -> tuple[float, ...]:
            u, v, w, r = nu
            c, s = math.cos(psi), math.sin(psi)
            cn, ce, cd = current.velocity(z, t)
            ur, vr, wr = u - (c * cn + s * ce), v - (c * ce - s * cn), w - cd
            return (fu - (ku * ur + qu * ur * abs(ur)) * iu, fv - (kv * vr + qv * vr * abs(vr)) * iv,
                    fw - (kw * wr + qw * wr * abs(wr)) * iw, fr - (kr * r + qr * r * abs(r)) * ir)

        h = dt * 0.5
        k1 = deriv(t0, z0, psi0, nu0)
        nu2 = tuple(a + h * b for a, b in zip(nu0, k1))
        k2 = deriv(t0 + h, z0 + h * nu0[2], psi0 + h * nu0[3], nu2)
        nu3 = tuple(a + h * b for a, b in zip(nu0, k2))
        k3 = deriv(t0 + h, z0 + h * nu2[2], psi0 + h * nu2[3], nu3)
        nu4 = tuple(a + dt * b for a, b in zip(nu0, k3))
        k4 = deriv(t0 + dt, z0 + dt * nu3[2], psi0 + dt * nu3[3], nu4)
        out = [(nu0[i] + dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]), nu2[i], nu3[i], nu4[i])
               for i in range(4)]
        return out[0], out[1], out[2], out[3]

    def step_with_thrusters(self, state: VehicleState, dt: float, thrusters: ThrusterSet,
                            current: Current | None = None) -> VehicleState:
        """One physics tick: the thrusters' wrench at the step's start, held over
        ``dt`` [s]; the rotors are then advanced to the step's end (mutates ``thrusters``)."""
        wrench = thrusters.wrench()
        thrusters.advance(dt, state.time + dt)
        return self.step(state, dt, wrench, current)
