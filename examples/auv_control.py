"""Estimation and control: observers, the target track, the mission's phases and its controllers."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from auv_sonar import Detection
from auv_vehicle import (
    DVL_DOWN,
    HEAVE,
    SONAR_DOWN,
    SONAR_HALF_ELEVATION_DEG,
    SONAR_TILT_DEG,
    SURGE,
    YAW,
    Axis,
    DeadBandDither,
    ThrusterModel,
    allocate,
    layout_matrix,
)


def wrap180(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


def clamp(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


class AxisObserver:
    """Position/velocity of one axis: the model predicts with the commanded force, a measurement
    corrects it like an alpha-beta filter."""

    def __init__(self, axis: Axis, alpha: float, beta: float) -> None:
        self.axis, self.alpha, self.beta = axis, alpha, beta
        self.x = math.nan
        self.v = 0.0

    def predict(self, force: float, dt: float) -> None:
        a = (force + self.axis.bias - self.axis.drag(self.v)) / self.axis.mass
        if math.isfinite(self.x):
            self.x += self.v * dt + 0.5 * a * dt * dt
        self.v += a * dt

    def correct(self, measured: float, dt: float) -> None:
        if not math.isfinite(measured):
            return
        if not math.isfinite(self.x):
            self.x = measured
            return
        r = measured - self.x
        self.x += self.alpha * r
        self.v += self.beta * r / dt

    def correct_rate(self, measured: float, gain: float) -> None:
        """A measured rate (a DVL's velocity) pulls the estimate by ``gain`` of the difference."""
        if math.isfinite(measured):
            self.v += gain * (measured - self.v)


class TargetTrack:
    """Horizontal distance ``d`` [m] from the sonar to the target's foot, from the detections;
    predicted between frames with the surge speed.

    The sonar, ``SONAR_DOWN`` below the body origin and tilted ``SONAR_TILT_DEG`` down with a
    +-``SONAR_HALF_ELEVATION_DEG`` aperture, sees a flat floor from ``h / sin(tilt + half)`` to
    ``h / sin(tilt - half)``: every frame's floor band (outer beams) measures the sonar's height ``h``
    above the floor, hence the floor's depth (vehicle depth + ``SONAR_DOWN`` + h, median of 15), and
    ``h`` at any later depth. The shadow edge R is the slant range to the target's foot, so
    ``d = sqrt(R^2 - h^2)``. A frame measures its own (ping) time: the innovation is taken against
    the estimate of that time (kept a few seconds), so a late frame corrects without lag. ``alpha``
    corrects d, ``beta`` a surge speed bias (a current, a wrong model)."""

    def __init__(self, alpha: float = 0.5, beta: float = 0.1) -> None:
        self.alpha, self.beta = alpha, beta
        self.d = math.nan
        self.floor_depth = math.nan
        self.floors: deque[float] = deque(maxlen=15)  # floor depth [m] from the last frames
        self.h = math.nan
        self.speed_bias = 0.0   # [m/s] added to the model's surge speed
        self.last = -math.inf   # sim time of the last detection used
        self.history: deque[tuple[float, float]] = deque(maxlen=100)  # (t, d) estimates
        self.floor_source = "sonar"   # "dvl" once the DVL measures the floor: the sonar's band is not used

    def dvl_floor(self, floor_depth: float) -> None:
        """[m] the floor's depth from a DVL (vehicle depth + DVL_DOWN + its altitude)."""
        if math.isfinite(floor_depth):
            self.floor_source = "dvl"
            self.floors.append(floor_depth)
            self.floor_depth = float(np.median(self.floors))

    @staticmethod
    def height(det: Detection) -> float:
        """[m] the sonar's height above a flat floor, from the floor band of the outer beams."""
        lo = math.radians(SONAR_TILT_DEG - SONAR_HALF_ELEVATION_DEG)
        hi = math.radians(SONAR_TILT_DEG + SONAR_HALF_ELEVATION_DEG)
        return 0.5 * (det.floor_far * math.sin(lo) + det.floor_near * math.sin(hi))

    def predict(self, t: float, u: float, dt: float, depth: float) -> None:
        if math.isfinite(self.floor_depth):
            self.h = self.floor_depth - depth - SONAR_DOWN
        if math.isfinite(self.d):
            self.d -= (u + self.speed_bias) * dt
            self.history.append((t, self.d))

    def _at(self, t: float) -> float:
        for ti, di in reversed(self.history):
            if ti <= t:
                return di
        return self.d

    def measure(self, t: float, det: Detection, depth_then: float) -> None:
        """A frame pinged at t [s], when the vehicle was at ``depth_then`` [m]."""
        if (self.floor_source == "sonar" and math.isfinite(det.floor_far) and math.isfinite(det.floor_near)
                and math.isfinite(depth_then)):
            self.floors.append(depth_then + SONAR_DOWN + self.height(det))
            self.floor_depth = float(np.median(self.floors))  # robust to a frame where the target hides the floor
            if not math.isfinite(self.h):
                self.h = self.floor_depth - depth_then - SONAR_DOWN
        if not det.found or not math.isfinite(self.h) or det.shadow_edge <= self.h:
            return
        d = math.sqrt(det.shadow_edge ** 2 - self.h ** 2)
        if not math.isfinite(self.d) or t - self.last > 5.0:
            self.d, self.speed_bias = d, 0.0
            self.history.clear()
        else:
            r = d - self._at(t)
            self.d += self.alpha * r
            gap = clamp(t - self.last, 0.1, 2.0)
            self.speed_bias = clamp(self.speed_bias - self.beta * r / gap, -0.05, 0.05)
        self.last = t

    def valid(self, t: float) -> bool:
        return math.isfinite(self.d) and t - self.last < 5.0

    def range(self) -> float:
        """[m] the shadow edge range the estimate predicts."""
        return math.hypot(self.d, self.h)


@dataclass
class Params:
    depth: float = 1.8            # [m] to dive to and hold
    headings: tuple[float, ...] = (20.0, 0.0)   # [deg] visited in turn before the approach
    hold_range: float = 1.25      # [m] target shadow edge range to hold
    hold_time: float = 20.0       # [s] of station keeping
    approach_speed: float = 0.05  # [m/s] while searching / the most while approaching
    max_search: float = 3.0       # [m] dead-reckoned travel without a detection -> abort
    control_rate: float = 10.0    # [Hz] of simulation time
    timeout: float = 240.0        # [s] of simulation time for the whole mission
    surface: bool = False         # end with a surfacing phase that waits for GNSS fixes (needs a GNSS)
    surface_depth: float = 0.2    # [m] body depth at the surface: the GNSS mast 0.4 m out of the water
    gnss_fixes: int = 3           # fixes to log at the surface before the mission completes
    surface_timeout: float = 60.0  # [s] in the surfacing phase without those fixes -> fail
    depth_tol: float = 0.05       # [m] settled: |error| below this ...
    heading_tol: float = 2.0      # [deg]
    range_tol: float = 0.03       # [m]
    settle_time: float = 3.0      # [s] ... for this long


@dataclass
class Phase:
    name: str
    start: float
    end: float = math.nan
    outcome: str = ""


class Mission:
    """The phases and the controllers; step() runs one control tick.

    Each axis is a cascade: position error -> rate reference (clamped) -> force
    = model drag at the reference rate + mass x gain x rate error (+ a slow
    integral on depth). Depth: Keller depth through a model-driven observer.
    Heading: WitMotion heading and gyro rate. Surge (approach and hold): the
    target track's distance and the surge speed, the model's corrected by the
    DVL's measured velocity (:meth:`dvl`), whose altitude also gives the floor's
    depth (the track's sonar height); without a DVL, the model alone and the
    sonar's floor band. Sway is left alone. At the end (``surface``) it rises to
    ``surface_depth``, holds position on the DVL, and completes once the GNSS
    has given ``gnss_fixes`` fixes (:meth:`gnss`)."""

    def __init__(self, p: Params, esc: str = "duty") -> None:
        self.p = p
        self.layout = layout_matrix()
        self.alloc = np.linalg.pinv(self.layout)
        self.thr = ThrusterModel()
        self.dither = DeadBandDither(self.layout.shape[1], self.thr.dead_band_thrust(esc))
        self.depth_obs = AxisObserver(HEAVE, alpha=0.15, beta=0.02)   # Keller: 0.6 mbar (6 mm) steps
        self.surge_obs = AxisObserver(SURGE, alpha=0.0, beta=0.0)     # no speed sensor: the model only
        self.track = TargetTrack()
        self.depth_history: deque[tuple[float, float]] = deque(maxlen=100)
        self.plan = ["dive"] + [f"turn_{h:g}" for h in p.headings] + ["approach", "hold"] \
            + (["surface"] if p.surface else [])
        self.depth_ref = p.depth
        self.dvl_u = math.nan          # [m/s] the DVL's last valid surge velocity
        self.dvl_altitude = math.nan   # [m] and altitude
        self.gnss_fixes: list[dict[str, float]] = []   # fixes logged in the surfacing phase
        self.phases: list[Phase] = []
        self.settled_since: float | None = None
        self.heading_ref = math.nan
        self.depth_int = 0.0
        self.travel = 0.0             # [m] dead-reckoned forward travel in the approach
        self.first_detection: float | None = None
        self.force = (0.0, 0.0, 0.0, 0.0)
        self.done = False
        self.failure: str | None = None

    @property
    def phase(self) -> str:
        return self.phases[-1].name if self.phases else "wait"

    def dvl(self, report: dict | None, depth: float) -> None:
        """The DVL's latest velocity report (None: none fresh) at vehicle ``depth`` [m]: its vx (the DVL
        is mounted straight, so vx is surge) corrects the surge speed; its altitude, the floor's depth."""
        if report is None or not report.get("velocity_valid"):
            self.dvl_u = self.dvl_altitude = math.nan
            return
        self.dvl_u, self.dvl_altitude = float(report["vx"]), float(report["altitude"])
        self.surge_obs.correct_rate(self.dvl_u, 0.5)
        if self.phase not in ("surface",) and math.isfinite(depth):
            self.track.dvl_floor(depth + DVL_DOWN + self.dvl_altitude)

    def gnss(self, t: float, fix: dict[str, float]) -> None:
        """A GGA epoch; fixes (quality > 0) count in the surfacing phase."""
        if self.phase == "surface" and fix.get("quality", 0) > 0 and math.isfinite(fix.get("lat_deg", math.nan)):
            self.gnss_fixes.append({**fix, "t": t})

    def start(self, t: float, heading: float) -> None:
        self.heading_ref = heading
        self._enter(self.plan[0], t)

    def _enter(self, name: str, t: float) -> None:
        self.phases.append(Phase(name, t))
        self.settled_since = None
        if name.startswith("turn_"):
            self.heading_ref = float(name[5:]) % 360.0
        if name == "surface":
            self.depth_ref = self.p.surface_depth
            self.depth_int = 0.0

    def _next(self, t: float, outcome: str) -> None:
        cur = self.phases[-1]
        cur.end, cur.outcome = t, outcome
        i = self.plan.index(cur.name) + 1
        if i >= len(self.plan):
            self.done = True
        else:
            self._enter(self.plan[i], t)

    def fail(self, t: float, why: str) -> None:
        if self.phases and not math.isfinite(self.phases[-1].end):
            self.phases[-1].end, self.phases[-1].outcome = t, "failed: " + why
        self.failure = why
        self.done = True

    def _settled(self, t: float, ok: bool) -> bool:
        if not ok:
            self.settled_since = None
            return False
        if self.settled_since is None:
            self.settled_since = t
        return t - self.settled_since >= self.p.settle_time

    def sonar(self, t: float, det: Detection) -> None:
        """A sonar frame pinged at sim time t [s]."""
        if det.found and self.first_detection is None and self.phase in ("approach", "hold"):
            self.first_detection = t
        depth_then = next((z for ti, z in reversed(self.depth_history) if ti <= t),
                          self.depth_history[0][1] if self.depth_history else math.nan)
        self.track.measure(t, det, depth_then)

    def target_range(self, t: float) -> float:
        return self.track.range() if self.track.valid(t) else math.nan

    def step(self, t: float, dt: float, depth: float, heading: float, yaw_rate: float) -> np.ndarray:
        """One control tick at sim time t [s]: depth [m], heading [deg], yaw rate [deg/s] -> thrusts (8,) [N]."""
        p = self.p
        fx_prev, _, fz_prev, _ = self.force
        self.depth_obs.predict(fz_prev, dt)
        self.depth_obs.correct(depth, dt)
        self.surge_obs.predict(fx_prev, dt)
        u = self.surge_obs.v
        z, w = self.depth_obs.x, self.depth_obs.v
        self.track.predict(t, u, dt, z)
        self.depth_history.append((t, z))
        phase = self.phase

        # heave: depth -> heave rate reference -> force (model feed-forward + integral)
        ez = self.depth_ref - z
        w_ref = clamp(0.5 * ez, -0.2, 0.2)
        if abs(ez) < 0.3:
            self.depth_int = clamp(self.depth_int + ez * dt, -20.0, 20.0)
        fz = HEAVE.drag(w_ref) - HEAVE.bias + HEAVE.mass * 2.0 * (w_ref - w) + 1.0 * self.depth_int

        # yaw: heading -> yaw rate reference -> moment
        eh = wrap180(self.heading_ref - heading)
        r_ref = math.radians(clamp(0.6 * eh, -15.0, 15.0))
        mz = YAW.drag(r_ref) + YAW.mass * 2.4 * (r_ref - math.radians(yaw_rate))

        # surge, in the approach and the hold: the target's distance -> surge speed reference -> force
        fx = 0.0
        tracked = self.track.valid(t)
        if phase == "surface":      # hold position over ground on the DVL while rising
            fx = SURGE.drag(0.0) + SURGE.mass * 1.0 * (0.0 - u)
        if phase in ("approach", "hold"):
            self.travel += u * dt
            if tracked:
                d_hold = math.sqrt(max(p.hold_range ** 2 - self.track.h ** 2, 0.0))
                u_ref = clamp(0.3 * (self.track.d - d_hold), -p.approach_speed, p.approach_speed)
            elif self.first_detection is None:
                u_ref = p.approach_speed   # searching: creep ahead until the target shows
            else:
                u_ref = 0.0                # target lost: stop and wait for it
            u_ref -= self.track.speed_bias
            fx = SURGE.drag(u_ref) + SURGE.mass * 1.0 * (u_ref - u)

        # phase logic
        settled_depth = abs(ez) < p.depth_tol
        if phase == "dive":
            if self._settled(t, settled_depth and abs(w) < 0.02):
                self._next(t, "settled")
        elif phase.startswith("turn_"):
            if self._settled(t, settled_depth and abs(eh) < p.heading_tol and abs(yaw_rate) < 1.0):
                self._next(t, "settled")
        elif phase == "approach":
            rng = self.target_range(t)
            if self.first_detection is None and self.travel > p.max_search:
                self.fail(t, f"no target within {p.max_search:g} m")
            elif self._settled(t, tracked and abs(rng - p.hold_range) < p.range_tol and abs(u) < 0.02
                               and settled_depth):
                self._next(t, "settled")
        elif phase == "hold":
            if t - self.phases[-1].start >= p.hold_time:
                self._next(t, "completed")
        elif phase == "surface":
            if len(self.gnss_fixes) >= p.gnss_fixes:
                self._next(t, "gnss fix")
            elif t - self.phases[-1].start > p.surface_timeout:
                self.fail(t, f"no GNSS fix within {p.surface_timeout:g} s of surfacing")

        thrusts = self.dither(allocate(self.alloc, fx, 0.0, fz, mz, self.thr.limit))
        w = self.layout @ thrusts     # what the thrusters give (limits, dead band): the observers' input
        self.force = (float(w[0]), float(w[1]), float(w[2]), float(w[5]))
        return thrusts
