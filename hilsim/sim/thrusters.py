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

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from hilsim.config import Doc, check_keys, load_toml, quantity, require
from hilsim.sim.geometry import F64

COMMAND_KINDS = ("normalized", "duty", "rpm", "erpm", "current")
_RPM = 2.0 * math.pi / 60.0  # [rad/s] per [rev/min]
_THERMAL_STEP = 0.05  # [s] the winding temperature is advanced at most this often


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
    """Target speed fraction ``s*`` [1] for a command ``value`` of ``kind`` (see module doc)."""
    vmax = min(1.0, supply_voltage / profile.nominal_voltage)
    if kind in ("normalized", "duty"):
        frac = max(-1.0, min(1.0, value))
        s = frac * supply_voltage / profile.nominal_voltage
    elif kind in ("rpm", "erpm"):
        rpm = value / profile.pole_pairs if kind == "erpm" else value
        s = frac = rpm / profile.max_rpm
    elif kind == "current":
        frac = value / profile.max_current
        s = math.copysign(math.sqrt(min(abs(frac), 1.0)), frac)
    else:
        raise ValueError(f"unknown command kind {kind!r}; expected one of {COMMAND_KINDS}")
    if not math.isfinite(frac) or abs(frac) < profile.dead_band:
        return 0.0
    return max(-vmax, min(vmax, s))


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
    """The thrusters of one vehicle and their ESC state (mutable; arrays of n).

    Device code calls :meth:`command` and :meth:`telemetry`; the physics tick
    calls :meth:`wrench` then :meth:`advance`. Times ``now`` [s] are the
    simulation clock's. ``matrix`` (6, n) maps thrusts [N] to the body wrench;
    ``max_thrust`` / ``min_thrust`` (n,) [N] are the reachable thrusts at the
    supply voltage (the allocation's limits).
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
        self._tau = [p.time_constant for p in profiles]
        self._timeout = [p.watchdog_timeout for p in profiles]
        self._dead = [p.dead_band for p in profiles]
        self._speed = [0.0] * n
        self._target = [0.0] * n     # target speed fraction (0 once the watchdog has tripped)
        self._cmd_time = [-math.inf] * n
        self._timed_out = [True] * n
        self._expiry = math.inf      # [s] earliest time a live command goes stale
        self._temp = [self.water_temperature] * n
        self._thermal_dt = 0.0
        self._alpha: tuple[float, list[float]] = (-1.0, [])
        self._now = 0.0
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
        p = self.thrusters[index].profile
        self._target[index] = target_speed(p, kind, float(value), self.supply_voltage)
        self._cmd_time[index] = now
        self._timed_out[index] = False
        self._expiry = min(self._expiry, now + self._timeout[index])

    def command_all(self, kind: str, values: Iterable[float], now: float) -> None:
        """Command every thruster at once (e.g. a DroneCAN RawCommand array); (n,) values."""
        vals = list(values)
        if len(vals) != len(self):
            raise ValueError(f"expected {len(self)} commands, got {len(vals)}")
        for i, v in enumerate(vals):
            self.command(i, kind, v, now)

    def telemetry(self, index: int) -> ThrusterTelemetry:
        """ESC telemetry of thruster ``index`` from its current rotor state."""
        p = self.thrusters[index].profile
        s = float(self._speed[index])
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
    @property
    def speeds(self) -> F64:
        """(n,) [1] rotor speed fractions (a copy)."""
        return np.array(self._speed)

    def thrusts(self) -> F64:
        """(n,) [N] thrust of each thruster at the current rotor speeds."""
        if self._shared is not None:
            return self._shared.thrust(self._speed)
        return np.array([float(p.thrust(s)) for p, s in zip(self._profiles, self._speed)])

    def wrench(self) -> F64:
        """(6,) body wrench (Fx, Fy, Fz [N], Mx, My, Mz [N m]) at the current speeds."""
        if self._shared is not None:  # the common case, without the wrappers
            p = self._shared
            return self.matrix @ np.interp(self._speed, p.curve_speed, p.curve_thrust)
        return self.matrix @ self.thrusts()

    def advance(self, dt: float, now: float) -> None:
        """Advance the rotor speeds by ``dt`` [s] to time ``now`` [s] (watchdog checked at ``now``)."""
        self._now = now
        if now > self._expiry:
            self._watchdog(now)
        if self._alpha[0] != dt:
            self._alpha = (dt, [-math.expm1(-dt / tau) for tau in self._tau])
        # exact first-order lag; a zero target below the dead band stops the rotor
        speeds = []
        for s0, t0, a, d0 in zip(self._speed, self._target, self._alpha[1], self._dead):
            s1 = s0 + (t0 - s0) * a
            speeds.append(0.0 if t0 == 0.0 and -d0 < s1 < d0 else s1)
        self._speed = speeds
        self._thermal_dt += dt
        if self._thermal_dt >= _THERMAL_STEP:
            self._advance_thermal(self._thermal_dt)
            self._thermal_dt = 0.0

    def _watchdog(self, now: float) -> None:
        """Zero the target of every thruster whose command is older than its timeout."""
        expiry = math.inf
        for i, (tc, to) in enumerate(zip(self._cmd_time, self._timeout)):
            if now - tc > to:
                self._timed_out[i] = True
                self._target[i] = 0.0
            else:
                expiry = min(expiry, tc + to)
        self._expiry = expiry

    def _advance_thermal(self, dt: float) -> None:
        for k, (p, s) in enumerate(zip(self._profiles, self._speed)):
            loss = (p.max_current * s * s) ** 2 * p.winding_resistance  # [W] copper loss
            steady = self.water_temperature + p.thermal_resistance * loss
            self._temp[k] += (steady - self._temp[k]) * -math.expm1(-dt / p.thermal_time_constant)

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
