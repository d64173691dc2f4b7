"""The 6-DOF model's RK4 step as one compiled kernel (numba), with the same
source run by CPython where numba is missing or switched off.

The equations are :mod:`hilsim.sim.vehicle6dof`'s (its module doc); this module
is only their arithmetic, on floats and flat arrays, so that numba can compile it
to machine code. A step of the BlueROV2 Heavy costs about 10 us as Python floats
(four right-hand sides of some 120 operations and six sines each) and well under
a microsecond compiled, plus numba's call overhead (about 0.8 us): the physics of
issue #19 runs above 1000x real time at 200 Hz with its thrusters.

- :func:`pack` turns the profile's constants into the parameter vector ``par``.
- :func:`rk4` advances the 12 states by one step under a wrench held over it in
  still water; :func:`rk4_current` in a uniform steady current or a current
  tabulated over time and depth (bilinear, clamped at the grids' ends:
  :class:`hilsim.sim.vehicle.Current`'s law), evaluated at each RK4 stage's depth
  and time.
- ``HILSIM_JIT=0`` in the environment, or numba not importable, runs the same
  functions in CPython (about 4x slower; :data:`COMPILED` says which). numba caches
  the machine code beside this file (``__pycache__``), or in the user's cache
  directory (``NUMBA_CACHE_DIR`` names another), so a bridge compiles it once per
  installation (about 2 s), then loads it in about 0.1 s; with no writable cache
  folder each process compiles it.
"""

from __future__ import annotations

import math
import os
from typing import Any, Callable, Union

import numpy as np

# the parameter vector's layout (pack() writes it, _deriv() reads it)
P_MASS = 0      # 6: mu mv mw Ip Iq Ir (rigid + added)
P_INV = 6       # 6: their inverses
P_LIN = 12      # 6: linear damping
P_QUAD = 18     # 6: quadratic damping
P_RIGID = 24    # 1: rigid-body mass m
P_ADDED = 25    # 3: added translational masses a_u a_v a_w
P_WB = 28       # 1: W - B
P_BR = 29       # 3: B * r_b
P_DI = 32       # 3: Ir - Iq, Ip - Ir, Iq - Ip
P_DA = 35       # 3: a_w - a_v, a_u - a_w, a_v - a_u
N_PAR = 38

STILL, UNIFORM, TABLE = 0, 1, 2  # the current's mode

Params = Union[np.ndarray, tuple[float, ...]]  # pack()'s vector; CPython is given it as a tuple


def pack(mass: tuple[float, ...], lin: tuple[float, ...], quad: tuple[float, ...], rigid: float,
         added: tuple[float, float, float], wb: float, b: float,
         rb: tuple[float, float, float]) -> np.ndarray:
    """The parameter vector (N_PAR,) of a profile: DOF masses/inertias (6,), linear and
    quadratic damping (6,) each, rigid mass [kg], added masses (3,), W - B [N],
    buoyancy B [N], centre of buoyancy r_b (3,) [m] from the CG (body frame)."""
    ip, iq, ir = mass[3:]
    au, av, aw = added
    par = np.array([*mass, *(1.0 / x for x in mass), *lin, *quad, rigid, *added, wb,
                    b * rb[0], b * rb[1], b * rb[2], ir - iq, ip - ir, iq - ip,
                    aw - av, au - aw, av - au], dtype=np.float64)
    assert par.shape == (N_PAR,)
    return par


def _bracket(grid: np.ndarray, x: float) -> tuple[int, int, float]:
    """Indices (i, j) and the weight of j for linear interpolation in ``grid``, clamped
    (as hilsim.sim.vehicle._bracket)."""
    n = grid.shape[0]
    if n == 1 or x <= grid[0]:
        return 0, 0, 0.0
    if x >= grid[n - 1]:
        return n - 1, n - 1, 0.0
    j = int(np.searchsorted(grid, x, side="right"))
    return j - 1, j, (x - grid[j - 1]) / (grid[j] - grid[j - 1])


def _current(mode: int, ct: np.ndarray, cdp: np.ndarray, cv: np.ndarray, depth: float,
             time: float) -> tuple[float, float, float]:
    """NED current [m/s] at ``depth`` and ``time``: cv (m, k, 3) over times ct (m,) and
    depths cdp (k,)."""
    if mode == STILL:
        return 0.0, 0.0, 0.0
    if mode == UNIFORM:
        return cv[0, 0, 0], cv[0, 0, 1], cv[0, 0, 2]
    ti, tj, tw = _bracket(ct, time)
    di, dj, dw = _bracket(cdp, depth)
    out0 = out1 = out2 = 0.0
    for c in range(3):
        lo = cv[ti, di, c] * (1.0 - dw) + cv[ti, dj, c] * dw
        hi = cv[tj, di, c] * (1.0 - dw) + cv[tj, dj, c] * dw
        val = lo * (1.0 - tw) + hi * tw
        if c == 0:
            out0 = val
        elif c == 1:
            out1 = val
        else:
            out2 = val
    return out0, out1, out2


def _deriv(par: Params, phi: float, theta: float, psi: float, u: float, v: float, w: float,
           p: float, q: float, r: float, fx: float, fy: float, fz: float, mx: float, my: float,
           mz: float, cn: float, ce: float, cd: float) -> tuple[float, float, float, float, float, float,
                                                              float, float, float, float, float, float]:
    """Time derivatives of (x, y, z, phi, theta, psi, u, v, w, p, q, r) under the wrench
    (fx..mz) in the NED current (cn, ce, cd): the equations of hilsim.sim.vehicle6dof."""
    sf, cf = math.sin(phi), math.cos(phi)
    st, ct = math.sin(theta), math.cos(theta)
    sy, cy = math.sin(psi), math.cos(psi)
    # body -> NED rotation, Z-Y-X; its last row is g_b = R^T e_z
    r00, r10, r20 = cy * ct, sy * ct, -st
    stsf, stcf = st * sf, st * cf
    r01, r11, r21 = cy * stsf - sy * cf, sy * stsf + cy * cf, ct * sf
    r02, r12, r22 = cy * stcf + sy * sf, sy * stcf - cy * sf, ct * cf
    # velocity relative to the water, and the translational momentum m v + A v_r
    ur = u - (r00 * cn + r10 * ce + r20 * cd)
    vr = v - (r01 * cn + r11 * ce + r21 * cd)
    wr = w - (r02 * cn + r12 * ce + r22 * cd)
    m = par[P_RIGID]
    p1x = m * u + par[P_ADDED] * ur
    p1y = m * v + par[P_ADDED + 1] * vr
    p1z = m * w + par[P_ADDED + 2] * wr
    wb = par[P_WB]
    bxb, byb, bzb = par[P_BR], par[P_BR + 1], par[P_BR + 2]
    du = (fx + wb * r20 - (par[P_LIN] + par[P_QUAD] * abs(ur)) * ur - q * p1z + r * p1y) * par[P_INV]
    dv = (fy + wb * r21 - (par[P_LIN + 1] + par[P_QUAD + 1] * abs(vr)) * vr - r * p1x + p * p1z) * par[P_INV + 1]
    dw = (fz + wb * r22 - (par[P_LIN + 2] + par[P_QUAD + 2] * abs(wr)) * wr - p * p1y + q * p1x) * par[P_INV + 2]
    dp = (mx - byb * r22 + bzb * r21 - (par[P_LIN + 3] + par[P_QUAD + 3] * abs(p)) * p
          - par[P_DI] * q * r - par[P_DA] * vr * wr) * par[P_INV + 3]
    dq = (my - bzb * r20 + bxb * r22 - (par[P_LIN + 4] + par[P_QUAD + 4] * abs(q)) * q
          - par[P_DI + 1] * r * p - par[P_DA + 1] * wr * ur) * par[P_INV + 4]
    dr = (mz - bxb * r21 + byb * r20 - (par[P_LIN + 5] + par[P_QUAD + 5] * abs(r)) * r
          - par[P_DI + 2] * p * q - par[P_DA + 2] * ur * vr) * par[P_INV + 5]
    qs_rc = q * sf + r * cf
    if -1e-9 < ct < 1e-9:  # pitch at +-90 deg: the Euler rates are singular there; step past it
        ct = 1e-9
    return (r00 * u + r01 * v + r02 * w, r10 * u + r11 * v + r12 * w, r20 * u + r21 * v + r22 * w,
            p + qs_rc * st / ct, q * cf - r * sf, qs_rc / ct,
            du, dv, dw, dp, dq, dr)


_NO_GRID = np.zeros(1)
_NO_TABLE = np.zeros((1, 1, 3))
_PI = math.pi
_TWO_PI = 2.0 * math.pi
_HALF_PI = 0.5 * math.pi


def rk4(par: Params, s: tuple[float, ...], w: tuple[float, ...], time0: float,
        dt: float) -> tuple[float, ...]:
    """One RK4 step in still water: see :func:`rk4_current`."""
    return rk4_current(par, STILL, _NO_GRID, _NO_GRID, _NO_TABLE, s, w, time0, dt)


def rk4_current(par: Params, mode: int, ct: np.ndarray, cdp: np.ndarray, cv: np.ndarray,
                s: tuple[float, ...], w: tuple[float, ...], time0: float, dt: float) -> tuple[float, ...]:
    """One classical RK4 step of ``dt`` [s] from the state ``s`` (``VehicleState.flat()``:
    its first 12 values are used) at ``time0`` [s], the body wrench ``w`` (6,) held, in the
    current (``mode``; times ``ct``, depths ``cdp``, velocities ``cv``). Returns the 15
    values of ``VehicleState.flat()`` at ``time0 + dt``: the 12 states (angles wrapped to
    (-pi, pi], a pitch past +-90 deg written as the same rotation) and the mean
    (du, dv, dw)/dt over the step."""
    x0, y0, z0, f0, t0, s0 = s[0], s[1], s[2], s[3], s[4], s[5]
    u0, v0, w0, p0, q0, r0 = s[6], s[7], s[8], s[9], s[10], s[11]
    fx, fy, fz, mx, my, mz = w[0], w[1], w[2], w[3], w[4], w[5]
    h = 0.5 * dt
    c0, c1, c2 = _current(mode, ct, cdp, cv, z0, time0)
    a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11 = _deriv(
        par, f0, t0, s0, u0, v0, w0, p0, q0, r0, fx, fy, fz, mx, my, mz, c0, c1, c2)
    c0, c1, c2 = _current(mode, ct, cdp, cv, z0 + h * a2, time0 + h)
    b0, b1, b2, b3, b4, b5, b6, b7, b8, b9, b10, b11 = _deriv(
        par, f0 + h * a3, t0 + h * a4, s0 + h * a5, u0 + h * a6, v0 + h * a7, w0 + h * a8,
        p0 + h * a9, q0 + h * a10, r0 + h * a11, fx, fy, fz, mx, my, mz, c0, c1, c2)
    c0, c1, c2 = _current(mode, ct, cdp, cv, z0 + h * b2, time0 + h)
    e0, e1, e2, e3, e4, e5, e6, e7, e8, e9, e10, e11 = _deriv(
        par, f0 + h * b3, t0 + h * b4, s0 + h * b5, u0 + h * b6, v0 + h * b7, w0 + h * b8,
        p0 + h * b9, q0 + h * b10, r0 + h * b11, fx, fy, fz, mx, my, mz, c0, c1, c2)
    c0, c1, c2 = _current(mode, ct, cdp, cv, z0 + dt * e2, time0 + dt)
    d0, d1, d2, d3, d4, d5, d6, d7, d8, d9, d10, d11 = _deriv(
        par, f0 + dt * e3, t0 + dt * e4, s0 + dt * e5, u0 + dt * e6, v0 + dt * e7, w0 + dt * e8,
        p0 + dt * e9, q0 + dt * e10, r0 + dt * e11, fx, fy, fz, mx, my, mz, c0, c1, c2)
    k6 = dt / 6.0
    u1 = u0 + k6 * (a6 + 2.0 * (b6 + e6) + d6)
    v1 = v0 + k6 * (a7 + 2.0 * (b7 + e7) + d7)
    w1 = w0 + k6 * (a8 + 2.0 * (b8 + e8) + d8)
    roll = f0 + k6 * (a3 + 2.0 * (b3 + e3) + d3)
    pitch = t0 + k6 * (a4 + 2.0 * (b4 + e4) + d4)
    yaw = s0 + k6 * (a5 + 2.0 * (b5 + e5) + d5)
    if pitch > _HALF_PI or pitch < -_HALF_PI:  # over the top: the same rotation with |pitch| <= 90 deg
        pitch = (_PI if pitch > 0 else -_PI) - pitch
        roll += _PI
        yaw += _PI
    inv = 1.0 / dt
    return (x0 + k6 * (a0 + 2.0 * (b0 + e0) + d0), y0 + k6 * (a1 + 2.0 * (b1 + e1) + d1),
            z0 + k6 * (a2 + 2.0 * (b2 + e2) + d2),
            (roll + _PI) % _TWO_PI - _PI, pitch, (yaw + _PI) % _TWO_PI - _PI,
            u1, v1, w1,
            p0 + k6 * (a9 + 2.0 * (b9 + e9) + d9), q0 + k6 * (a10 + 2.0 * (b10 + e10) + d10),
            r0 + k6 * (a11 + 2.0 * (b11 + e11) + d11),
            (u1 - u0) * inv, (v1 - v0) * inv, (w1 - w0) * inv)


def _compile() -> tuple[bool, str]:
    """Replace the module's functions by numba dispatchers (lazy: each compiles, or loads
    its cached machine code, on its first call). (compiled?, why not)."""
    if os.environ.get("HILSIM_JIT", "1").strip().lower() in ("0", "no", "false", "off"):
        return False, "HILSIM_JIT=0"
    try:
        import numba
    except ImportError as exc:  # a platform without numba's wheels: CPython runs the same code
        return False, f"numba not importable ({exc})"
    g = globals()
    names = ("_bracket", "_current", "_deriv", "rk4_current", "rk4")  # callees first: rk4 resolves them as globals
    try:
        jit: Callable[[Any], Any] = numba.njit(cache=True, nogil=True)
        compiled = [jit(g[name]) for name in names]
    except RuntimeError:  # no writable cache folder (numba's "no locator available"): compile in each process
        jit = numba.njit(nogil=True)
        compiled = [jit(g[name]) for name in names]
    for name, fn in zip(names, compiled):
        g[name] = fn
    return True, ""


COMPILED, WHY_NOT_COMPILED = _compile()
