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
agreement of 1 ms and 50 ms runs. RK4 is written out in plain Python floats
(eight scalars: numpy calls on arrays this small cost more than the
arithmetic). In still water the velocity equations do not depend on the
pose, so each DOF's RK4 stages are computed alone and the position and
heading are integrated from those same stages with the RK4 weights: the same
scheme as RK4 on the full state. A DOF at rest under no force stays at rest
(RK4 gives exactly that; its stages are not computed), and with no turn the
four stages share one heading. With a current, yaw (which does not feel it)
is integrated first and fixes the stages' headings. The step returns a
:class:`VehicleState` built from its 15 numbers (:meth:`VehicleState.from_flat`):
the arrays are made only if read, and the next step reads the numbers.

A profile with a ``[hydrostatics]`` table (the BlueROV2s) lists all six DOFs and
is integrated by the 6-DOF model of :mod:`hilsim.sim.vehicle6dof` instead
(``Vehicle(profile)`` builds it): roll and pitch, Coriolis terms and the
restoring moments of the centres of gravity and buoyancy. Everything above
describes the diagonal model that Cyclops keeps.

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
from hilsim.sim.ardupilot_frames import ArdupilotTable, check_layout, parse_ardupilot
from hilsim.sim.contact import Hull, load_hull
from hilsim.sim.geometry import F64
from hilsim.sim.state import VehicleState
from hilsim.sim.thrusters import Thruster, ThrusterProfile, ThrusterSet, load_thruster_profile
from hilsim.sim.vehicle6dof import Hydrostatics, Vehicle6DOF

DOF_NAMES = ("surge", "sway", "heave", "roll", "pitch", "yaw")
MODELLED_DOFS = ("surge", "sway", "heave", "yaw")
_ROTATIONAL = ("roll", "pitch", "yaw")
_TWO_PI = 2.0 * math.pi
_PI = math.pi
_cos, _sin = math.cos, math.sin
_new = object.__new__
_Stages = tuple[float, float, float, float]  # a velocity at the step's end, then at RK4 stages 2, 3, 4


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
    _zero: bool = field(init=False, repr=False, compare=False)  # still water everywhere
    _const: tuple[float, float, float] | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        arr = np.asarray(self.velocities, dtype=float)
        if arr.shape != (len(self.times), len(self.depths), 3):
            raise ValueError(f"velocities must be (len(times), len(depths), 3), got {arr.shape}")
        for g in (self.times, self.depths):
            if any(b <= a for a, b in zip(g, g[1:])):
                raise ValueError("times and depths must be strictly increasing")
        # cached for the physics step: still water, and the velocity of a uniform steady current
        zero = not any(c for plane in self.velocities for row in plane for c in row)
        const = self.velocities[0][0] if len(self.times) == 1 and len(self.depths) == 1 else None
        object.__setattr__(self, "_zero", zero)
        object.__setattr__(self, "_const", None if const is None else tuple(float(c) for c in const))

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
        return self._zero

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
    dotted key -> where its value comes from; rigid_mass [kg] the mass in air
    (``[vehicle].mass``) or None; hydrostatics: weight and buoyancy (a 6-DOF
    profile, :mod:`hilsim.sim.vehicle6dof`) or None; ardupilot: the
    ``[ardupilot]`` table (ArduSub frame and servo map) or None.
    """

    name: str
    dofs: tuple[str, ...]
    params: dict[str, DofParameters]
    thrusters: tuple[Thruster, ...] = ()
    supply_voltage: float | None = None
    sources: dict[str, str] = field(default_factory=dict)
    rigid_mass: float | None = None
    hydrostatics: Hydrostatics | None = None
    ardupilot: ArdupilotTable | None = None
    hull: Hull | None = None  # collision hull ([hull], hilsim.sim.contact); None: a point

    @property
    def six_dof(self) -> bool:
        """True when the profile is integrated by the 6-DOF model (it has hydrostatics)."""
        return self.hydrostatics is not None

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
    check_keys(doc, doc.data, ("vehicle", "dynamics", "thrusters", "hydrostatics", "ardupilot", "hull"), "")
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
    rigid = float(quantity(doc, veh, "mass", "kg", "vehicle")) if "mass" in veh else None
    hydro = None
    if "hydrostatics" in doc.data:
        hydro = _load_hydrostatics(doc, doc.data["hydrostatics"], dofs, params, rigid, sources)
    ardupilot = None
    if "ardupilot" in doc.data:
        ardupilot = parse_ardupilot(doc, doc.data["ardupilot"], [t.name for t in thrusters])
        bad = check_layout(ardupilot, thrusters)
        if bad:
            raise doc.error("ardupilot", "the thrusters do not match ArduSub's " + ardupilot.frame
                            + " layout: " + "; ".join(bad))
    return VehicleProfile(str(veh.get("name", path.stem)), tuple(dofs), params, thrusters, voltage, sources,
                          rigid, hydro, ardupilot, load_hull(doc))


def _load_hydrostatics(doc: Doc, tab: dict, dofs: list[str], params: dict[str, DofParameters],
                       rigid: float | None, sources: dict[str, str]) -> Hydrostatics:
    """``[hydrostatics]``: weight [N], buoyancy [N], centre_of_buoyancy (3,) [m] from the CG.
    Makes the profile 6-DOF: every DOF listed, [vehicle].mass given, no heave constant_force."""
    check_keys(doc, tab, ("weight", "buoyancy", "centre_of_buoyancy", "note"), "hydrostatics")
    if sorted(dofs) != sorted(DOF_NAMES):
        raise doc.error("vehicle.dofs", f"a profile with [hydrostatics] is 6-DOF: list all of {DOF_NAMES}")
    if rigid is None or rigid <= 0:
        raise doc.error("vehicle", "a 6-DOF profile needs vehicle.mass (in air, without added mass) > 0")
    if any(params[d].constant_force for d in dofs):
        raise doc.error("dynamics", "a 6-DOF profile takes weight and buoyancy from [hydrostatics]; "
                                    "remove constant_force")
    for d in ("surge", "sway", "heave"):
        if params[d].mass < rigid:
            raise doc.error(f"dynamics.{d}.mass", f"below vehicle.mass ({rigid} kg): it includes added mass")
    weight = float(quantity(doc, tab, "weight", "N", "hydrostatics"))
    buoyancy = float(quantity(doc, tab, "buoyancy", "N", "hydrostatics"))
    cb = quantity(doc, tab, "centre_of_buoyancy", "m", "hydrostatics", length=3)
    if weight <= 0 or buoyancy <= 0:
        raise doc.error("hydrostatics", "weight and buoyancy must be > 0")
    sources.update({f"hydrostatics.{k}": str(tab[k]["source"])
                    for k in ("weight", "buoyancy", "centre_of_buoyancy")})
    return Hydrostatics(weight, buoyancy, (float(cb[0]), float(cb[1]), float(cb[2])))


def _load_thrusters(doc: Doc, path: Path) -> tuple[tuple[Thruster, ...], float | None]:
    th = doc.data.get("thrusters")
    if th is None:
        return (), None
    check_keys(doc, th, ("profile", "supply_voltage", "unit"), "thrusters")
    cache: dict[str, ThrusterProfile] = {}

    def profile(name: str, key: str) -> ThrusterProfile:
        if name not in cache:
            try:
                cache[name] = load_thruster_profile(find_profile("thrusters", name, base=path.parent,
                                                                 doc=doc, key=key))
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
        key = f"{where}.profile" if "profile" in u else "thrusters.profile"
        out.append(Thruster(str(u.get("name", f"t{i}")), pos, d / np.linalg.norm(d), profile(name, key)))
    return tuple(out), voltage


def _kinematics(x0: float, y0: float, k6: float, cos: _Stages, sin: _Stages, u: _Stages, v: _Stages
                ) -> tuple[float, float]:
    """North, east [m] after a step: ``d(x, y)/dt = Rz(psi) (u, v)`` with the RK4 weights
    (``k6 = dt / 6``), given cos, sin of the heading and u, v [m/s] at the four stages."""
    ca, cb, cc, cd = cos
    sa, sb, sc, sd = sin
    u0, ub, uc, ud = u
    v0, vb, vc, vd = v
    return (x0 + k6 * (ca * u0 - sa * v0 + 2.0 * (cb * ub - sb * vb + cc * uc - sc * vc) + cd * ud - sd * vd),
            y0 + k6 * (sa * u0 + ca * v0 + 2.0 * (sb * ub + cb * vb + sc * uc + cc * vc) + sd * ud + cd * vd))


class Vehicle:
    """The dynamics of one vehicle profile. :meth:`step` is pure.

    ``Vehicle(profile)`` of a 6-DOF profile (one with ``[hydrostatics]``) builds a
    :class:`hilsim.sim.vehicle6dof.Vehicle6DOF`, which has the same interface."""

    def __new__(cls, profile: VehicleProfile) -> "Vehicle":
        if cls is Vehicle and profile.hydrostatics is not None:
            return Vehicle6DOF(profile)  # type: ignore[return-value]
        return super().__new__(cls)

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

        # per DOF (surge, sway, heave, yaw): 1 / mass, damping, quadratic damping, constant force
        self._c = tuple(coeffs(d) for d in MODELLED_DOFS)
        # the same with the damping per unit mass (still water)
        self._cm = tuple((i, k * i, q * i, c) for i, k, q, c in self._c)
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
        return self._step(state, dt, wr[0], wr[1], wr[2], wr[5], current)

    def step_with_thrusters(self, state: VehicleState, dt: float, thrusters: ThrusterSet,
                            current: Current | None = None) -> VehicleState:
        """One physics tick: the thrusters' wrench at the step's start, held over
        ``dt`` [s]; the rotors are then advanced to the step's end (mutates ``thrusters``)."""
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        fx, fy, fz, _mx, _my, mz = thrusters.tick6(dt, state.time + dt)  # a 4-DOF body: roll and pitch held
        return self._step(state, dt, fx, fy, fz, mz, current)

    def _step(self, state: VehicleState, dt: float, fx: float, fy: float, fz: float, mz: float,
              current: Current | None) -> VehicleState:
        """:meth:`step` with the wrench's Fx, Fy, Fz [N] and Mz [N m]; RK4 written out
        per DOF in Python floats (the stage values feed the kinematics)."""
        t0 = state.time
        sd = state.__dict__
        flat = sd.get("_flat")
        if flat is None or "position" in sd:  # arrays (given, or built and maybe read)
            x0, y0, z0 = state.position.tolist()
            roll, pitch, psi0 = state.attitude.tolist()
            u0, v0, w0 = state.velocity.tolist()
            r0 = float(state.angular_velocity[2])
        else:
            x0, y0, z0, roll, pitch, psi0, u0, v0, w0, _, _, r0, _, _, _ = flat
        (iu, ku, qu, cu), (iv, kv, qv, cv), (iw, kw, qw, cw), (ir, kr, qr, cr) = self._cm
        if self._held:  # a held DOF keeps zero velocity
            u0, v0, w0, r0 = (a if i else 0.0 for a, i in zip((u0, v0, w0, r0), (iu, iv, iw, ir)))
        h = 0.5 * dt
        k6 = dt / 6.0
        if current is None or current._zero:
            # still water: each velocity ODE is on its own, dx/dt = f - (k + q |x|) x per unit
            # mass. A DOF at rest under no force stays at rest (what RK4 gives, skipped).
            f = (fx + cu) * iu
            if f == 0.0 and u0 == 0.0:
                u1 = ub = uc = ud = u0
            else:
                a = f - (ku + qu * abs(u0)) * u0
                ub = u0 + h * a
                b = f - (ku + qu * abs(ub)) * ub
                uc = u0 + h * b
                c = f - (ku + qu * abs(uc)) * uc
                ud = u0 + dt * c
                u1 = u0 + k6 * (a + 2.0 * b + 2.0 * c + (f - (ku + qu * abs(ud)) * ud))
            f = (fy + cv) * iv
            if f == 0.0 and v0 == 0.0:
                v1 = vb = vc = vd = v0
            else:
                a = f - (kv + qv * abs(v0)) * v0
                vb = v0 + h * a
                b = f - (kv + qv * abs(vb)) * vb
                vc = v0 + h * b
                c = f - (kv + qv * abs(vc)) * vc
                vd = v0 + dt * c
                v1 = v0 + k6 * (a + 2.0 * b + 2.0 * c + (f - (kv + qv * abs(vd)) * vd))
            f = (fz + cw) * iw
            if f == 0.0 and w0 == 0.0:
                w1 = wb = wc = wd = w0
            else:
                a = f - (kw + qw * abs(w0)) * w0
                wb = w0 + h * a
                b = f - (kw + qw * abs(wb)) * wb
                wc = w0 + h * b
                c = f - (kw + qw * abs(wc)) * wc
                wd = w0 + dt * c
                w1 = w0 + k6 * (a + 2.0 * b + 2.0 * c + (f - (kw + qw * abs(wd)) * wd))
            f = (mz + cr) * ir
            if f == 0.0 and r0 == 0.0:  # no turn: one heading for all the stages
                r1 = rb = rc = rd = r0
                ca, sa = _cos(psi0), _sin(psi0)
                su = u0 + 2.0 * (ub + uc) + ud  # the RK4 sums of the body velocities
                sv = v0 + 2.0 * (vb + vc) + vd
                x = x0 + k6 * (ca * su - sa * sv)
                y = y0 + k6 * (sa * su + ca * sv)
            else:
                a = f - (kr + qr * abs(r0)) * r0
                rb = r0 + h * a
                b = f - (kr + qr * abs(rb)) * rb
                rc = r0 + h * b
                c = f - (kr + qr * abs(rc)) * rc
                rd = r0 + dt * c
                r1 = r0 + k6 * (a + 2.0 * b + 2.0 * c + (f - (kr + qr * abs(rd)) * rd))
                # the kinematics at the stages' headings (as _kinematics, written out)
                psi_b, psi_c, psi_d = psi0 + h * r0, psi0 + h * rb, psi0 + dt * rc
                ca, cb, cc, cd = _cos(psi0), _cos(psi_b), _cos(psi_c), _cos(psi_d)
                sa, sb, sc, sd_ = _sin(psi0), _sin(psi_b), _sin(psi_c), _sin(psi_d)
                x = x0 + k6 * (ca * u0 - sa * v0 + 2.0 * (cb * ub - sb * vb + cc * uc - sc * vc)
                               + cd * ud - sd_ * vd)
                y = y0 + k6 * (sa * u0 + ca * v0 + 2.0 * (sb * ub + cb * vb + sc * uc + cc * vc)
                               + sd_ * ud + cd * vd)
        else:
            (u1, ub, uc, ud), (v1, vb, vc, vd), (w1, wb, wc, wd), (r1, rb, rc, rd), cos, sin = \
                self._rk4_current(t0, z0, psi0, u0, v0, w0, r0, fx, fy, fz, mz, current, dt)
            x, y = _kinematics(x0, y0, k6, cos, sin, (u0, ub, uc, ud), (v0, vb, vc, vd))
        z = z0 + k6 * (w0 + 2.0 * (wb + wc) + wd)
        psi = psi0 + k6 * (r0 + 2.0 * (rb + rc) + rd)
        psi = (psi + _PI) % _TWO_PI - _PI
        inv = 1.0 / dt
        # VehicleState.from_flat without its checks: the arrays are built when first read
        out = _new(VehicleState)
        od = out.__dict__
        od["time"] = t0 + dt
        od["_flat"] = (x, y, z, roll, pitch, psi, u1, v1, w1, 0.0, 0.0, r1,
                       (u1 - u0) * inv, (v1 - v0) * inv, (w1 - w0) * inv)
        return out

    def _rk4_current(self, t0: float, z0: float, psi0: float, u0: float, v0: float, w0: float, r0: float,
                     fx: float, fy: float, fz: float, mz: float, current: Current, dt: float
                     ) -> tuple[_Stages, _Stages, _Stages, _Stages, _Stages, _Stages]:
        """RK4 of (z, psi, u, v, w, r) with damping on the velocity relative to ``current``.

        Returns per DOF (end value, stage-2, stage-3, stage-4 velocity), then the
        cosines and the sines of the four stages' headings. Yaw does not feel the
        current, so its stages come first and fix the headings at which the
        current is rotated into the body frame."""
        (iu, ku, qu, cu), (iv, kv, qv, cv), (iw, kw, qw, cw), (ir, kr, qr, cr) = self._c
        fu, fv, fw, fr = (fx + cu) * iu, (fy + cv) * iv, (fz + cw) * iw, (mz + cr) * ir
        h = dt * 0.5
        k6 = dt / 6.0
        ka = fr - (kr * r0 + qr * r0 * abs(r0)) * ir
        rb = r0 + h * ka
        kb = fr - (kr * rb + qr * rb * abs(rb)) * ir
        rc = r0 + h * kb
        kc = fr - (kr * rc + qr * rc * abs(rc)) * ir
        rd = r0 + dt * kc
        r1 = r0 + k6 * (ka + 2.0 * kb + 2.0 * kc + (fr - (kr * rd + qr * rd * abs(rd)) * ir))
        psi_b, psi_c, psi_d = psi0 + h * r0, psi0 + h * rb, psi0 + dt * rc
        cos = (_cos(psi0), _cos(psi_b), _cos(psi_c), _cos(psi_d))
        sin = (_sin(psi0), _sin(psi_b), _sin(psi_c), _sin(psi_d))
        ca, cb, cc, cd = cos
        sa, sb, sc, sd = sin
        const = current._const
        vel = current.velocity
        # stage 1 (t0, z0, psi0); a stage's heave gives the next stage's depth
        cn, ce, cz = const if const is not None else vel(z0, t0)
        ur, vr, wr = u0 - (ca * cn + sa * ce), v0 - (ca * ce - sa * cn), w0 - cz
        au = fu - (ku * ur + qu * ur * abs(ur)) * iu
        av = fv - (kv * vr + qv * vr * abs(vr)) * iv
        aw = fw - (kw * wr + qw * wr * abs(wr)) * iw
        ub, vb, wb = u0 + h * au, v0 + h * av, w0 + h * aw
        # stage 2 (t0 + h, z0 + h w0, psi_b)
        if const is None:
            cn, ce, cz = vel(z0 + h * w0, t0 + h)
        ur, vr, wr = ub - (cb * cn + sb * ce), vb - (cb * ce - sb * cn), wb - cz
        bu = fu - (ku * ur + qu * ur * abs(ur)) * iu
        bv = fv - (kv * vr + qv * vr * abs(vr)) * iv
        bw = fw - (kw * wr + qw * wr * abs(wr)) * iw
        uc, vc, wc = u0 + h * bu, v0 + h * bv, w0 + h * bw
        # stage 3 (t0 + h, z0 + h wb, psi_c)
        if const is None:
            cn, ce, cz = vel(z0 + h * wb, t0 + h)
        ur, vr, wr = uc - (cc * cn + sc * ce), vc - (cc * ce - sc * cn), wc - cz
        cu_ = fu - (ku * ur + qu * ur * abs(ur)) * iu
        cv_ = fv - (kv * vr + qv * vr * abs(vr)) * iv
        cw_ = fw - (kw * wr + qw * wr * abs(wr)) * iw
        ud, vd, wd = u0 + dt * cu_, v0 + dt * cv_, w0 + dt * cw_
        # stage 4 (t0 + dt, z0 + dt wc, psi_d)
        if const is None:
            cn, ce, cz = vel(z0 + dt * wc, t0 + dt)
        ur, vr, wr = ud - (cd * cn + sd * ce), vd - (cd * ce - sd * cn), wd - cz
        du = fu - (ku * ur + qu * ur * abs(ur)) * iu
        dv = fv - (kv * vr + qv * vr * abs(vr)) * iv
        dw = fw - (kw * wr + qw * wr * abs(wr)) * iw
        return ((u0 + k6 * (au + 2.0 * bu + 2.0 * cu_ + du), ub, uc, ud),
                (v0 + k6 * (av + 2.0 * bv + 2.0 * cv_ + dv), vb, vc, vd),
                (w0 + k6 * (aw + 2.0 * bw + 2.0 * cw_ + dw), wb, wc, wd),
                (r1, rb, rc, rd), cos, sin)
