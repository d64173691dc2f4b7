"""Thrusters: ESC + motor + propeller models, a placed set, its wrench and the allocation.

A thruster's state is its rotor speed as a fraction ``s = omega / max_speed``
of full speed at the profile's nominal voltage. A command sets a target
``s*``; the speed follows with a first-order lag advanced exactly
(``1 - exp(-dt / time_constant)``, stable at any step). Thrust is the
profile's tabulated, asymmetric curve at ``s``; saturation is the table's end
(``|s| <= 1``) and, for open-loop kinds, the supply voltage.

Command kinds, as the protocols deliver them (``V`` supply, ``Vn`` nominal):

- ``"normalized"`` [1] in [-1, 1]: PWM (1100..1900 us -> -1..1), DroneCAN
  esc.RawCommand (int14 / 8191), VRCSR float power. Open loop like a duty:
  ``s* = value * V / Vn``.
- ``"duty"`` [1] in [-1, 1]: VESC SET_DUTY (int32 / 1e5); same mapping.
- ``"rpm"`` [rev/min] mechanical, closed loop: ``s* = rpm / max_rpm``.
- ``"erpm"`` [rev/min] electrical (VESC SET_RPM): ``rpm = erpm / pole_pairs``.
- ``"current"`` [A] motor current (VESC SET_CURRENT / 1e3), closed-loop
  torque; the propeller's load torque grows as ``omega^2``, so at steady
  state ``s* = sign(I) sqrt(|I| / max_current)`` (thrust ~ current).

Dead band: a command below ``dead_band`` of full scale (value, rpm / max_rpm
or I / max_current) holds the motor stopped; with a zero target the rotor is
taken as stopped once ``|s|`` falls below the dead band. Watchdog: a command
older than ``watchdog_timeout`` [s] is replaced by a zero target
(``timed_out``) until the next command, as real ESCs do.

Telemetry is derived from the rotor state, never echoed from the command:
rpm, motor current ``max_current * s|s|`` (the steady propeller load), the
duty that holds ``s``, input current ``|I_motor * duty|``, the sagging bus
voltage and a first-order winding temperature.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from hilsim.config import Doc, check_keys, load_toml, quantity, require
from hilsim.sim.geometry import F64

COMMAND_KINDS = ("normalized", "duty", "rpm", "erpm", "current")
_RPM = 2.0 * math.pi / 60.0  # [rad/s] per [rev/min]
_ZERO6 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
_THERMAL_STEP = 0.05  # [s] the winding temperature is advanced at most this often
_EVENT_MARGIN = 1.0 + 1e-12  # re-anchor a hair early rather than a tick late
_F_FLOOR = 1e-30  # re-anchor a group before its decay factor underflows
_exp = math.exp
_RENORMALISE = 4096  # re-anchorings between two fresh sums of W0 and W1


@dataclass(frozen=True, eq=False)
class ThrusterProfile:
    """A thruster type (motor + propeller + ESC). SI units.

    max_speed [rad/s] full rotor speed at nominal_voltage [V]; curve_speed (k,)
    [1] speed fractions, strictly increasing from -1 to 1; curve_thrust (k,) [N]
    strictly increasing, 0 at s = 0; dead_band [1]; time_constant [s];
    watchdog_timeout [s]; max_current [A] motor current at full speed;
    pole_pairs [1]; winding_resistance and source_resistance [ohm];
    thermal_resistance [K/W]; thermal_time_constant [s]; sources: key -> source.
    """

    name: str
    max_speed: float
    nominal_voltage: float
    curve_speed: F64
    curve_thrust: F64
    dead_band: float
    time_constant: float
    watchdog_timeout: float
    max_current: float
    pole_pairs: int = 7
    winding_resistance: float = 0.1
    thermal_resistance: float = 1.5
    thermal_time_constant: float = 60.0
    source_resistance: float = 0.0
    sources: dict[str, str] = field(default_factory=dict)

    @property
    def max_rpm(self) -> float:
        """[rev/min] full mechanical speed at the nominal voltage."""
        return self.max_speed / _RPM

    def thrust(self, s: float | Sequence[float] | F64) -> F64:
        """Thrust [N] at speed fraction(s) ``s`` [1] (any shape; clamped to the table)."""
        return np.asarray(np.interp(s, self.curve_speed, self.curve_thrust), dtype=np.float64)

    def speed_for_thrust(self, thrust: float | Sequence[float] | F64) -> F64:
        """Inverse of :meth:`thrust`: speed fraction [1] giving ``thrust`` [N] (clamped)."""
        return np.asarray(np.interp(thrust, self.curve_thrust, self.curve_speed), dtype=np.float64)


def load_thruster_profile(path: Path | str) -> ThrusterProfile:
    """Read a thruster profile TOML (``devices/thrusters/*.toml``) into SI units."""
    doc = load_toml(path)
    check_keys(doc, doc.data, ("thruster", "curve"), "")
    t = require(doc, doc.data, "thruster", "")
    c = require(doc, doc.data, "curve", "")
    keys = ("name", "description", "max_speed", "nominal_voltage", "dead_band", "time_constant",
            "watchdog_timeout", "max_current", "pole_pairs", "winding_resistance",
            "thermal_resistance", "thermal_time_constant", "source_resistance")
    check_keys(doc, t, keys, "thruster")
    check_keys(doc, c, ("speed", "thrust"), "curve")
    sources = {k: str(t[k]["source"]) for k in keys[2:] if isinstance(t.get(k), dict) and "source" in t[k]}

    def q(key: str, unit: str, default: float | None = None, zero_ok: bool = False) -> float:
        v = float(quantity(doc, t, key, unit, "thruster", default=default))
        if v < 0 or (v == 0 and not zero_ok):
            raise doc.error(f"thruster.{key}", f"must be {'>=' if zero_ok else '>'} 0, got {v}")
        return v

    speed = np.asarray(quantity(doc, c, "speed", "1", "curve"), dtype=float)
    thrust = np.asarray(quantity(doc, c, "thrust", "N", "curve"), dtype=float)
    if speed.size < 3 or speed.shape != thrust.shape:
        raise doc.error("curve.thrust", "speed and thrust need the same number (>= 3) of values")
    if not (np.all(np.diff(speed) > 0) and np.all(np.diff(thrust) > 0)):
        raise doc.error("curve.thrust", "speed and thrust must both be strictly increasing")
    if speed[0] != -1.0 or speed[-1] != 1.0 or abs(float(np.interp(0.0, speed, thrust))) > 1e-9:
        raise doc.error("curve.speed", "the curve must span s = -1..1 and give zero thrust at s = 0")
    dead_band = float(quantity(doc, t, "dead_band", "1", "thruster"))
    if not 0.0 <= dead_band < 0.5:
        raise doc.error("thruster.dead_band", f"must be in [0, 0.5), got {dead_band}")
    return ThrusterProfile(
        name=str(t.get("name", Path(path).stem)), max_speed=q("max_speed", "rad/s"),
        nominal_voltage=q("nominal_voltage", "V"), curve_speed=speed, curve_thrust=thrust,
        dead_band=dead_band, time_constant=q("time_constant", "s"),
        watchdog_timeout=q("watchdog_timeout", "s"), max_current=q("max_current", "A"),
        pole_pairs=int(q("pole_pairs", "1", 7.0)), winding_resistance=q("winding_resistance", "ohm", 0.1),
        thermal_resistance=q("thermal_resistance", "K/W", 1.5),
        thermal_time_constant=q("thermal_time_constant", "s", 60.0),
        source_resistance=q("source_resistance", "ohm", 0.0, zero_ok=True), sources=sources)


@dataclass(frozen=True)
class Thruster:
    """A thruster placed on a vehicle: body-frame position (3,) [m] and unit
    direction (3,) in which positive thrust pushes the vehicle."""

    name: str
    position: F64
    direction: F64
    profile: ThrusterProfile


@dataclass(frozen=True)
class ThrusterTelemetry:
    """What an ESC reports, derived from the rotor state.

    rpm, erpm [rev/min] signed; thrust [N]; motor_current [A] signed;
    input_current [A] >= 0; duty [1] in [-1, 1]; voltage [V]; temperature [K];
    command_age [s] since the last command (inf if none); timed_out: the
    watchdog has zeroed the target.
    """

    rpm: float
    erpm: float
    thrust: float
    motor_current: float
    input_current: float
    duty: float
    voltage: float
    temperature: float
    command_age: float
    timed_out: bool


def target_speed(profile: ThrusterProfile, kind: str, value: float, supply_voltage: float) -> float:
    """Target speed fraction ``s*`` [1] for a command ``value`` of ``kind`` (see module doc).
    A NaN command is a zero target."""
    if kind == "normalized" or kind == "duty":
        frac = -1.0 if value < -1.0 else 1.0 if value > 1.0 else value  # NaN stays NaN
        s = frac * supply_voltage / profile.nominal_voltage
    elif kind == "rpm" or kind == "erpm":
        rpm = value / profile.pole_pairs if kind == "erpm" else value
        s = frac = rpm / profile.max_rpm
    elif kind == "current":
        frac = value / profile.max_current
        s = math.copysign(math.sqrt(min(abs(frac), 1.0)), frac)
    else:
        raise ValueError(f"unknown command kind {kind!r}; expected one of {COMMAND_KINDS}")
    if not math.isfinite(frac) or -profile.dead_band < frac < profile.dead_band:
        return 0.0
    vmax = supply_voltage / profile.nominal_voltage
    if vmax > 1.0:
        vmax = 1.0
    return -vmax if s < -vmax else vmax if s > vmax else s


@dataclass(frozen=True)
class Allocation:
    """Result of an allocation: thrusts (n,) [N]; wrench (6,) achieved [N, N m];
    scale [1] the fraction of the requested wrench achieved along its direction
    (1 when feasible); saturated: the request was out of reach."""

    thrusts: F64
    wrench: F64
    scale: float
    saturated: bool


def allocate_wrench(matrix: F64, wrench: F64, lower: F64, upper: F64,
                    dofs: Sequence[int] = (0, 1, 2, 3, 4, 5)) -> Allocation:
    """Thrusts f (n,) [N] with ``matrix @ f`` equal to ``wrench`` on the rows ``dofs``.

    matrix (6, n) thrust -> wrench; wrench (6,) [N, N m]; lower, upper (n,) [N]
    thrust limits (lower <= 0 <= upper). A part of the wrench that no thrust
    combination can produce is dropped first (least-squares projection). If
    the minimum-norm solution ``pinv(B) w`` is within the limits it is
    returned (the wrench is reproduced exactly). Otherwise the direction of the wrench is kept and its size is
    the largest reachable: a linear programme maximises ``a`` in [0, 1]
    subject to ``B f = a w`` and the limits, then a second one finds, at that
    ``a``, the thrusts of least total magnitude (no thrusters fighting). The
    zero wrench is always reachable, so no change of direction is ever needed.
    """
    from scipy.optimize import linprog

    rows = list(dofs)
    b = matrix[rows]
    n = b.shape[1]
    f = np.linalg.pinv(b) @ np.asarray(wrench, dtype=float)[rows]
    w = b @ f  # the reachable part of the request
    tol = 1e-9 * max(1.0, float(np.max(upper)))
    if np.all(f <= upper + tol) and np.all(f >= lower - tol):
        f = np.clip(f, lower, upper)
        return Allocation(f, matrix @ f, 1.0, False)
    # stage 1: variables (f, a); maximise a subject to b f - a w = 0
    limits = list(zip(lower.tolist(), upper.tolist()))
    res = linprog(np.r_[np.zeros(n), -1.0], A_eq=np.hstack([b, -w[:, None]]), b_eq=np.zeros(len(rows)),
                  bounds=limits + [(0.0, 1.0)], method="highs")
    if res.status != 0:
        raise RuntimeError(f"allocation LP failed: {res.message}")
    scale = float(res.x[-1]) * (1.0 - 1e-9)
    # stage 2: variables (f, t) with t >= |f|; minimise sum t subject to b f = scale w
    eye = np.eye(n)
    a_ub = np.block([[eye, -eye], [-eye, -eye]])
    res2 = linprog(np.concatenate([np.zeros(n), np.ones(n)]), A_ub=a_ub, b_ub=np.zeros(2 * n),
                   A_eq=np.hstack([b, np.zeros_like(b)]), b_eq=scale * w,
                   bounds=limits + [(0.0, None)] * n,
                   method="highs")
    f = np.clip(res2.x[:n] if res2.status == 0 else res.x[:n], lower, upper)
    return Allocation(f, matrix @ f, scale, True)


class ThrusterSet:
    """The thrusters of one vehicle and their ESC state (mutable; n thrusters).

    Device code calls :meth:`command` and :meth:`telemetry`; the physics tick
    calls :meth:`wrench` then :meth:`advance` (or both at once through
    ``Vehicle.step_with_thrusters``). Times ``now`` [s] are the simulation
    clock's. ``matrix`` (6, n) maps thrusts [N] to the body wrench;
    ``max_thrust`` / ``min_thrust`` (n,) [N] are the reachable thrusts at the
    supply voltage (the allocation's limits).

    Rotor state in closed form, so that a physics tick costs O(1) rather than
    O(n): thrusters sharing a time constant form a group with one decay factor
    ``F = exp(-(t - t_anchor) / tau)``, and each speed is ``s_i = target_i +
    dev_i F``, the exact first-order lag. Between events every thrust lies on
    one straight piece of its (piecewise-linear) curve, ``a_j + b_j s``, so the
    wrench is ``W0 + W1 F``. An event is a speed reaching a knot of its curve,
    a zero target's speed entering the dead band (each foreseen as the F at
    which it happens), a command or the watchdog changing a target; at an
    event only the thrusters concerned are re-anchored and W0, W1 change by
    their terms' change (:meth:`_rebuild`). The decay factors are reset to 1
    and the sums taken afresh before F could underflow and every
    ``_RENORMALISE`` re-anchorings. The result equals stepping every rotor and
    interpolating its thrust each tick, to rounding (tests hold the two equal).
    """

    def __init__(self, thrusters: Sequence[Thruster], supply_voltage: float | None = None,
                 water_temperature: float = 288.15):
        """``supply_voltage`` [V] (default: the first profile's nominal);
        ``water_temperature`` [K] the windings cool towards."""
        if not thrusters:
            raise ValueError("a ThrusterSet needs at least one thruster")
        self.thrusters = tuple(thrusters)
        n = len(self.thrusters)
        self.supply_voltage = float(supply_voltage or self.thrusters[0].profile.nominal_voltage)
        self.water_temperature = float(water_temperature)
        self.names = tuple(t.name for t in self.thrusters)
        pos = np.array([t.position for t in self.thrusters], dtype=float).reshape(n, 3)
        dirs = np.array([t.direction for t in self.thrusters], dtype=float).reshape(n, 3)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        # (6, n) map from thrusts [N] to the body wrench (Fx, Fy, Fz, Mx, My, Mz)
        self.matrix: F64 = np.vstack([dirs.T, np.cross(pos, dirs).T])
        profiles = [t.profile for t in self.thrusters]
        self._profiles = profiles
        self._shared = profiles[0] if all(p is profiles[0] for p in profiles) else None
        # per-thruster state as Python lists: cheaper than numpy for n ~ 8
        self._timeout = [p.watchdog_timeout for p in profiles]
        self._dead = [p.dead_band for p in profiles]
        self._target = [0.0] * n    # target speed fraction (0 once the watchdog has tripped)
        self._limit = [math.inf] * n      # fault injection: |target speed| <= limit [1]
        self._dev = [0.0] * n       # speed = target + dev * F of the thruster's group
        self._cmd_time = [-math.inf] * n
        self._timed_out = [True] * n
        self._expiry = math.inf     # [s] earliest time a live command goes stale
        self._temp = [self.water_temperature] * n
        self._thermal_dt = 0.0
        # steady winding temperature rise [K] per s^4: max_current^2 winding_resistance thermal_resistance
        self._heat = [p.max_current ** 2 * p.winding_resistance * p.thermal_resistance for p in profiles]
        self._thermal_tau = [p.thermal_time_constant for p in profiles]
        self._thermal_taus = sorted(set(self._thermal_tau))
        self._now = 0.0
        # the curves as straight pieces: thrust = a[j] + b[j] s on knots[j] <= s <= knots[j + 1]
        pieces: dict[int, tuple[list[float], list[float], list[float]]] = {}
        for p in profiles:
            if id(p) not in pieces:
                xp, fp = p.curve_speed.tolist(), p.curve_thrust.tolist()
                b = [(fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j]) for j in range(len(xp) - 1)]
                pieces[id(p)] = (xp, [fp[j] - b[j] * xp[j] for j in range(len(b))], b)
        self._pieces = [pieces[id(p)] for p in profiles]
        # (Fx, Fy, Fz, Mx, My, Mz) per unit thrust: the allocation matrix's columns
        self._cols = [tuple(float(self.matrix[r, i]) for r in range(6)) for i in range(n)]
        taus = sorted({p.time_constant for p in profiles})
        self._group = [taus.index(p.time_constant) for p in profiles]
        self._members = [[i for i in range(n) if self._group[i] == g] for g in range(len(taus))]
        self._hint = [0] * n                 # index of the straight piece each speed was on
        self._on = [0.0] * n                 # thrust = on + slope * F while on that piece
        self._slope = [0.0] * n
        self._fe = [0.0] * n                 # re-anchor the thruster once its group's F <= this
        self._stale = [True] * n             # retargeted since its last re-anchoring
        self._updates = 0                    # re-anchorings since the sums were last taken afresh
        self._taus = taus
        self._single = len(taus) == 1
        self._f = [1.0] * len(taus)          # decay factor F of each group
        self._fevent = [0.0] * len(taus)     # re-anchor the group once F <= this
        self._w0 = _ZERO6                    # wrench (Fx, Fy, Fz, Mx, My, Mz) = w0 + sum_g w1[g] F[g]
        self._w1 = [_ZERO6] * len(taus)
        self._dirty = True
        self._rebuild()
        self.max_thrust = np.array([float(p.thrust(min(1.0, self.supply_voltage / p.nominal_voltage)))
                                    for p in profiles])
        self.min_thrust = np.array([float(p.thrust(-min(1.0, self.supply_voltage / p.nominal_voltage)))
                                    for p in profiles])

    def __len__(self) -> int:
        return len(self.thrusters)

    def index(self, name: str) -> int:
        """Index of the thruster called ``name``."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no thruster {name!r}; thrusters: {', '.join(self.names)}") from None

    # -- commands and telemetry (device side) ---------------------------------
    def command(self, index: int, kind: str, value: float, now: float) -> None:
        """Command thruster ``index`` with ``value`` of ``kind`` at time ``now`` [s]."""
        target = target_speed(self._profiles[index], kind, float(value), self.supply_voltage)
        limit = self._limit[index]
        if target > limit:
            target = limit
        elif target < -limit:
            target = -limit
        if target != self._target[index]:
            self._retarget(index, target)
        self._cmd_time[index] = now
        self._timed_out[index] = False
        expiry = now + self._timeout[index]
        if expiry < self._expiry:
            self._expiry = expiry

    def set_limit(self, index: int, fraction: float | None) -> None:
        """Fault injection: cap thruster ``index``'s speed at ``fraction`` [0, 1] of full
        speed (0: a failed thruster, its rotor spins down and stays stopped; 0 < f < 1: it
        saturates early); ``None`` clears the fault. Commands keep arriving and counting
        for the watchdog; only the speed they can reach changes."""
        limit = math.inf if fraction is None else max(0.0, float(fraction))
        self._limit[index] = limit
        t = self._target[index]
        if abs(t) > limit:
            self._retarget(index, math.copysign(limit, t))

    def command_all(self, kind: str, values: Iterable[float], now: float) -> None:
        """Command every thruster at once (e.g. a DroneCAN RawCommand array); (n,) values."""
        vals = list(values)
        if len(vals) != len(self):
            raise ValueError(f"expected {len(self)} commands, got {len(vals)}")
        command = self.command
        for i, v in enumerate(vals):
            command(i, kind, v, now)

    def telemetry(self, index: int) -> ThrusterTelemetry:
        """ESC telemetry of thruster ``index`` from its current rotor state."""
        p = self.thrusters[index].profile
        s = self._target[index] + self._dev[index] * self._f[self._group[index]]
        rpm = s * p.max_rpm
        i_motor = p.max_current * s * abs(s)
        duty = max(-1.0, min(1.0, s * p.nominal_voltage / self.supply_voltage))
        i_in = abs(i_motor * duty)
        return ThrusterTelemetry(
            rpm=rpm, erpm=rpm * p.pole_pairs, thrust=float(p.thrust(s)), motor_current=i_motor,
            input_current=i_in, duty=duty, voltage=self.supply_voltage - p.source_resistance * i_in,
            temperature=float(self._temp[index]), command_age=self._now - float(self._cmd_time[index]),
            timed_out=bool(self._timed_out[index]))

    # -- physics side ----------------------------------------------------------
    def _speeds(self) -> list[float]:
        """(n,) [1] the rotor speed fractions now."""
        if self._single:
            f = self._f[0]
            return [t + d * f for t, d in zip(self._target, self._dev)]
        fs = self._f
        return [t + d * fs[g] for t, d, g in zip(self._target, self._dev, self._group)]

    @property
    def speeds(self) -> F64:
        """(n,) [1] rotor speed fractions (a copy)."""
        return np.array(self._speeds())

    def thrusts(self) -> F64:
        """(n,) [N] thrust of each thruster at the current rotor speeds."""
        if self._shared is not None:
            return self._shared.thrust(self._speeds())
        return np.array([float(p.thrust(s)) for p, s in zip(self._profiles, self._speeds())])

    def wrench(self) -> F64:
        """(6,) body wrench (Fx, Fy, Fz [N], Mx, My, Mz [N m]) at the current speeds."""
        if self._shared is not None:  # the common case, without the wrappers
            p = self._shared
            return self.matrix @ np.interp(self._speeds(), p.curve_speed, p.curve_thrust)
        return self.matrix @ self.thrusts()

    def roll_pitch_moments(self) -> tuple[float, float]:
        """(Mx, My) [N m] of the thrusts at the current speeds: the two rows of the wrench
        that :meth:`tick` leaves out (:meth:`tick6` gives all six)."""
        mx, my = self._w0[3], self._w0[4]
        for w1, f in zip(self._w1, self._f):
            mx += w1[3] * f
            my += w1[4] * f
        return mx, my

    def tick(self, dt: float, now: float) -> tuple[float, float, float, float]:
        """One physics tick of a 4-DOF vehicle: the wrench's (Fx, Fy, Fz [N], Mz [N m])
        at the current speeds (what :meth:`wrench` gives, to rounding), then :meth:`advance`."""
        fx, fy, fz, _mx, _my, mz = self.tick6(dt, now)
        return fx, fy, fz, mz

    def tick6(self, dt: float, now: float) -> tuple[float, float, float, float, float, float]:
        """One physics tick: the whole wrench (Fx, Fy, Fz [N], Mx, My, Mz [N m]) at the
        current speeds (what :meth:`wrench` gives, to rounding), then :meth:`advance`."""
        w0 = self._w0
        if not self._single:
            fx, fy, fz, mx, my, mz = w0
            for w1, f in zip(self._w1, self._f):
                fx += w1[0] * f
                fy += w1[1] * f
                fz += w1[2] * f
                mx += w1[3] * f
                my += w1[4] * f
                mz += w1[5] * f
            self.advance(dt, now)
            return fx, fy, fz, mx, my, mz
        # one group: advance() written out
        fs = self._f
        f = fs[0]
        w1 = self._w1[0]
        out = (w0[0] + w1[0] * f, w0[1] + w1[1] * f, w0[2] + w1[2] * f,
               w0[3] + w1[3] * f, w0[4] + w1[4] * f, w0[5] + w1[5] * f)
        self._now = now
        if now > self._expiry:
            self._watchdog(now)
        f = fs[0] = fs[0] * _exp(-dt / self._taus[0])  # dt varies by rounding on a clock grid
        if f <= self._fevent[0] or self._dirty:
            self._rebuild()
        td = self._thermal_dt + dt
        if td >= _THERMAL_STEP:
            self._advance_thermal(td)
            td = 0.0
        self._thermal_dt = td
        return out

    def advance(self, dt: float, now: float) -> None:
        """Advance the rotor speeds by ``dt`` [s] to time ``now`` [s] (watchdog checked at ``now``)."""
        self._now = now
        if now > self._expiry:
            self._watchdog(now)
        fs, fe = self._f, self._fevent
        event = False
        for g, tau in enumerate(self._taus):
            f = fs[g] = fs[g] * _exp(-dt / tau)
            event = event or f <= fe[g]
        if event or self._dirty:
            self._rebuild()
        td = self._thermal_dt + dt
        if td >= _THERMAL_STEP:
            self._advance_thermal(td)
            td = 0.0
        self._thermal_dt = td

    def _retarget(self, index: int, target: float) -> None:
        """Set a new target speed, keeping the rotor's present speed."""
        f = self._f[self._group[index]]
        s = self._target[index] + self._dev[index] * f
        self._target[index] = target
        self._dev[index] = (s - target) / f
        self._stale[index] = True
        self._dirty = True

    def _rebuild(self) -> None:
        """Re-anchor the thrusters that are due: those retargeted since the last call
        and those whose F reached their event threshold. For each: stop a zero-target
        rotor inside the dead band, find its thrust's straight piece, update W0 and W1
        by the change of its terms, and find the F of its next event. Every
        ``_RENORMALISE`` updates, or when an F nears underflow, every group is
        re-anchored at F = 1 and the sums are taken afresh (no rounding drift)."""
        target, dev, dead, hint, stale = self._target, self._dev, self._dead, self._hint, self._stale
        on, slope, fe = self._on, self._slope, self._fe
        pieces, cols = self._pieces, self._cols
        fs, fevent = self._f, self._fevent
        if self._updates >= _RENORMALISE or min(fs) <= _F_FLOOR * _EVENT_MARGIN:
            for members, f in zip(self._members, fs):
                for i in members:
                    dev[i] *= f
                    stale[i] = True
                    on[i] = slope[i] = 0.0
            fs[:] = [1.0] * len(fs)
            self._w0 = _ZERO6
            self._w1 = [_ZERO6] * len(fs)
            self._updates = 0
            self._dirty = True
        w0x, w0y, w0z, w0k, w0m, w0n = self._w0
        for g, members in enumerate(self._members):
            f = fs[g]
            if f > fevent[g] and not self._dirty:
                continue
            w1x, w1y, w1z, w1k, w1m, w1n = self._w1[g]
            due = _F_FLOOR
            for i in members:
                if not stale[i] and fe[i] < f:
                    if fe[i] > due:
                        due = fe[i]
                    continue
                stale[i] = False
                self._updates += 1
                t = target[i]
                s = t + dev[i] * f
                if t == 0.0 and -dead[i] < s < dead[i]:
                    s = 0.0  # a zero target below the dead band stops the rotor
                    dev[i] = 0.0
                d = dev[i]
                xp, a, b = pieces[i]
                j = hint[i]
                if not xp[j] <= s <= xp[j + 1]:
                    j = hint[i] = min(max(bisect.bisect_right(xp, s) - 1, 0), len(b) - 1)
                # thrust = on + slope * F on this piece; W0, W1 change by the terms' change
                o, sl = a[j] + b[j] * t, b[j] * d
                do, dsl = o - on[i], sl - slope[i]
                on[i], slope[i] = o, sl
                cx, cy, cz, ck, cm, cn = cols[i]
                w0x += cx * do
                w0y += cy * do
                w0z += cz * do
                w0k += ck * do
                w0m += cm * do
                w0n += cn * do
                w1x += cx * dsl
                w1y += cy * dsl
                w1z += cz * dsl
                w1k += ck * dsl
                w1m += cm * dsl
                w1n += cn * dsl
                # the F at which the speed leaves its piece (or stops in the dead band)
                e = 0.0
                if d > 0.0:
                    if t < xp[j]:
                        e = (xp[j] - t) / d * _EVENT_MARGIN
                    if t == 0.0:
                        e = max(e, dead[i] / d * _EVENT_MARGIN)
                elif d < 0.0:
                    if t > xp[j + 1]:
                        e = (xp[j + 1] - t) / d * _EVENT_MARGIN
                    if t == 0.0:
                        e = max(e, -dead[i] / d * _EVENT_MARGIN)
                fe[i] = e
                if e > due:
                    due = e
            self._w1[g] = (w1x, w1y, w1z, w1k, w1m, w1n)
            fevent[g] = due
        self._w0 = (w0x, w0y, w0z, w0k, w0m, w0n)
        if not any(slope):  # every rotor at its target: W1 is exactly zero, not a residue
            self._w1 = [_ZERO6] * len(fs)
            if not any(on):  # and every thrust zero (all stopped): so is W0
                self._w0 = _ZERO6
        self._dirty = False

    def _watchdog(self, now: float) -> None:
        """Zero the target of every thruster whose command is older than its timeout."""
        expiry = math.inf
        for i, (tc, to) in enumerate(zip(self._cmd_time, self._timeout)):
            if now - tc > to:
                self._timed_out[i] = True
                if self._target[i] != 0.0:
                    self._retarget(i, 0.0)
            else:
                expiry = min(expiry, tc + to)
        self._expiry = expiry

    def _advance_thermal(self, dt: float) -> None:
        """Winding temperatures over ``dt`` [s] towards the steady temperature of the
        present copper loss ``(max_current s^2)^2 winding_resistance``, exactly (first order)."""
        water = self.water_temperature
        if self._single and len(self._thermal_taus) == 1:  # the common case, in one pass
            a, f = -math.expm1(-dt / self._thermal_taus[0]), self._f[0]
            self._temp = [tk + (water + c * (t + d * f) ** 4 - tk) * a
                          for tk, c, t, d in zip(self._temp, self._heat, self._target, self._dev)]
            return
        for k, (s, c, tau) in enumerate(zip(self._speeds(), self._heat, self._thermal_tau)):
            self._temp[k] += (water + c * s ** 4 - self._temp[k]) * -math.expm1(-dt / tau)

    # -- allocation (controller side) ------------------------------------------
    def allocate(self, wrench: Sequence[float] | F64, dofs: Sequence[int] = (0, 1, 2, 3, 4, 5)) -> Allocation:
        """Thrusts [N] for a desired body wrench (6,) over the DOF indices ``dofs``.

        See :func:`allocate_wrench`: exact minimum-norm when
        feasible, otherwise the largest wrench along the requested direction.
        """
        return allocate_wrench(self.matrix, np.asarray(wrench, dtype=float), self.min_thrust,
                               self.max_thrust, dofs)

    def command_for_thrust(self, index: int, thrust: float, kind: str = "normalized") -> float:
        """The steady-state command of ``kind`` giving ``thrust`` [N] on thruster ``index``.

        Units as the command kinds (module doc). Thrusts inside the dead band give 0.
        """
        p = self.thrusters[index].profile
        s = float(p.speed_for_thrust(thrust))
        if kind in ("normalized", "duty"):
            c = s * p.nominal_voltage / self.supply_voltage
            frac = c
        elif kind in ("rpm", "erpm"):
            c = s * p.max_rpm * (p.pole_pairs if kind == "erpm" else 1)
            frac = s
        elif kind == "current":
            c = p.max_current * s * abs(s)
            frac = c / p.max_current
        else:
            raise ValueError(f"unknown command kind {kind!r}; expected one of {COMMAND_KINDS}")
        return 0.0 if abs(frac) < p.dead_band else c
