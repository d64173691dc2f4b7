"""The seed paper's water-tank run (sections 3-4, Fig. 4), simulated on the virtual clock.

Cyclops starts ``run_up`` metres south of position A (at least 1 m, and at
least 5 s of travel at the set speed so the speed loop has settled), at the
scenario's vehicle depth (1.5 m above the floor) and the positions' heading.
Each physics tick (200 Hz) the Cyclops dynamics (:mod:`hilsim.sim.vehicle`,
net buoyancy ``W_w`` included) integrate the wrench of the thrusters
(:mod:`hilsim.sim.thrusters`: lag, dead band, saturation); every 20 ms the
:class:`~hilsim.experiments.control.TrackController` reads the state and
commands the thrusters. When the vehicle's along-track coordinate passes that
of A, B and C, the sonar (its profile's default settings: the artifact-free
sampling, with the profile's realism) and the camera are rendered from the
*actual* state at that tick, not from the nominal position.

Everything is deterministic: virtual time, fixed rates, seeded sonar noise
keyed by the capture index.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TextIO

import numpy as np

from hilsim.experiments.control import TrackController
from hilsim.experiments.tank_geometry import TankGeometry
from hilsim.resources import find_profile, find_scenario
from hilsim.runtime.clock import VirtualClock
from hilsim.runtime.scheduler import Scheduler, VehicleLoop
from hilsim.sim.camera import Camera, CameraFrame
from hilsim.sim.geometry import F64, wrap_angle
from hilsim.sim.rig import build_camera, build_sonar
from hilsim.sim.scenario import Scenario, SensorMount, load_scenario
from hilsim.sim.sonar import ImagingSonar, SonarFrame
from hilsim.sim.state import VehicleState
from hilsim.sim.thrusters import ThrusterSet
from hilsim.sim.vehicle import Vehicle, VehicleProfile, load_vehicle_profile
from hilsim.sim.world import World

POSITIONS = ("A", "B", "C")
PHYSICS_RATE = 200.0     # [Hz]
CONTROL_RATE = 50.0      # [Hz]
TRAJECTORY_RATE = 10.0   # [Hz] rows of trajectory.csv
LOG_INTERVAL = 1.0       # [s] of simulated time between progress lines
MIN_RUN_UP = 1.0         # [m] start at least this far before A
RUN_UP_TIME = 5.0        # [s] and at least this long before A at the set speed
TRAJECTORY_FIELDS = ("t_s", "x_m", "y_m", "z_m", "altitude_m", "heading_deg", "u_m_s", "v_m_s", "w_m_s",
                     "cross_track_m")


@dataclass
class Rig:
    """What the run needs, built from a scenario."""

    scenario: Scenario
    world: World
    geometry: TankGeometry
    sonar: ImagingSonar
    sonar_mount: SensorMount
    camera: Camera
    camera_mount: SensorMount
    profile: VehicleProfile
    thrusters: ThrusterSet

    @staticmethod
    def load(scenario_arg: str | None, seed: int | None) -> Rig:
        """Load and check the scenario (ValueError/KeyError/ConfigError with a clear message)."""
        scenario = load_scenario(find_scenario(scenario_arg))
        missing = [p for p in POSITIONS if p not in scenario.positions]
        if missing:
            raise ValueError(f"scenario {scenario.name!r} has no named positions {', '.join(missing)} "
                             f"(named: {', '.join(scenario.positions) or 'none'}); the water-tank "
                             "experiment needs [positions.A], [positions.B] and [positions.C]")
        if scenario.vehicle is None:
            raise ValueError(f"scenario {scenario.name!r} has no [vehicle]; the experiment drives one")
        world = scenario.build_world()
        sonar_mount, camera_mount = scenario.sensor("sonar"), scenario.sensor("camera")
        profile = load_vehicle_profile(find_profile("vehicles", scenario.vehicle.profile, base=scenario.folder))
        if not profile.thrusters:
            raise ValueError(f"vehicle {profile.name!r} has no thrusters to drive it with")
        return Rig(scenario, world, TankGeometry.from_world(world), build_sonar(scenario, sonar_mount, seed=seed),
                   sonar_mount, build_camera(scenario, camera_mount), camera_mount, profile,
                   profile.thruster_set())

    def altitude(self, position: F64) -> float:
        """[m] distance straight down from ``position`` (NED) to the first surface (inf if none)."""
        hits = self.world.cast(np.asarray(position, dtype=float).reshape(1, 3), np.array([[0.0, 0.0, 1.0]]))
        return float(hits.t[0])


@dataclass
class Capture:
    """The sensors at one position: the actual state, the altitude [m] and the frames."""

    label: str
    state: VehicleState
    altitude: float
    sonar: SonarFrame
    camera: CameraFrame


@dataclass
class RunResult:
    """The run: captures by label, trajectory rows (see TRAJECTORY_FIELDS), the set-up."""

    captures: dict[str, Capture]
    trajectory: list[tuple[float, ...]]
    start: F64
    heading: float           # [rad]
    target_depth: float      # [m]
    speed: float             # [m/s]
    duration: float          # [s] simulated
    controller: TrackController
    extra: dict[str, Any] = field(default_factory=dict)


def run(rig: Rig, speed: float, stream: TextIO | None = None) -> RunResult:
    """Drive the vehicle through A, B and C at ``speed`` [m/s]; render at each."""
    out = stream if stream is not None else sys.stderr
    say: Callable[[str], None] = lambda msg: print(msg, file=out, flush=True)
    if not (math.isfinite(speed) and speed > 0.0):
        raise ValueError(f"--speed must be a positive number of m/s, got {speed}")
    sc = rig.scenario
    assert sc.vehicle is not None
    pos = {k: np.asarray(sc.positions[k].position, dtype=float) for k in POSITIONS}
    heading = sc.positions["A"].yaw
    if abs(wrap_angle(heading)) > math.radians(1.0):
        raise ValueError("the water-tank experiment runs north (positions' yaw_deg = 0), toward the cuboid's "
                         f"south face; position A has yaw {math.degrees(heading):.1f} deg")
    along = np.array([math.cos(heading), math.sin(heading), 0.0])
    target_depth = float(sc.vehicle.position[2])
    run_up = max(MIN_RUN_UP, RUN_UP_TIME * speed)
    start = pos["A"] - run_up * along
    start[2] = target_depth
    marks = sorted((float((pos[k] - start) @ along), k) for k in POSITIONS)
    if marks[0][0] <= 0.0 or [k for _, k in marks] != list(POSITIONS):
        raise ValueError(f"positions A, B, C must lie in that order along the heading; got {marks}")

    ctrl = TrackController(rig.profile, rig.thrusters, speed=speed, depth=target_depth, heading=heading,
                           origin=start)
    loop = VehicleLoop(Vehicle(rig.profile), rig.thrusters,
                       VehicleState(time=0.0, position=start.copy(), attitude=np.array([0.0, 0.0, heading])),
                       physics_rate=PHYSICS_RATE)
    sched = Scheduler(VirtualClock())
    loop.attach(sched)
    captures: dict[str, Capture] = {}
    traj: list[tuple[float, ...]] = []
    pending = list(marks)
    say(f"water-tank: {sc.name}, vehicle {rig.profile.name} from x = {start[0]:.3f} m at depth "
        f"{target_depth:.3f} m ({rig.geometry.floor_z - target_depth:.3f} m above the floor), "
        f"heading {math.degrees(heading):.1f} deg, {speed:g} m/s; captures at "
        + ", ".join(f"{k} (x = {pos[k][0]:.3f} m)" for k in POSITIONS))

    def status(s: VehicleState) -> str:
        return (f"t = {s.time:6.2f} s  x = {s.position[0]:+.3f} m  depth = {s.depth:.3f} m  "
                f"u = {s.velocity[0]:.3f} m/s")

    def control_tick(t: float) -> None:
        ctrl.apply(loop.state, t)

    def capture_tick(t: float) -> None:
        s = loop.state
        travelled = float((s.position - start) @ along)
        while pending and travelled >= pending[0][0]:
            _, label = pending.pop(0)
            index = POSITIONS.index(label)
            sonar_pose = s.pose @ rig.sonar_mount.mount
            frame = rig.sonar.render(rig.world, sonar_pose, time=s.time, frame_index=index)
            cam = rig.camera.sample(rig.world, s, rig.camera_mount.mount)
            captures[label] = Capture(label, s, rig.altitude(s.position), frame, cam)
            faces = sorted(k for k, v in frame.hit_counts.get("cuboid", {}).items() if k != "total" and v)
            say(f"{status(s)}  -> captured {label}: sonar {frame.n_hits:,} hits, cuboid faces "
                f"{', '.join(faces) or 'none'}")
        if not pending:
            sched.stop()

    def trajectory_tick(t: float) -> None:
        s = loop.state
        traj.append((s.time, *s.position.tolist(), rig.altitude(s.position), math.degrees(s.heading),
                     *s.velocity.tolist(), ctrl.cross_track(s)))
        if abs(t / LOG_INTERVAL - round(t / LOG_INTERVAL)) < 1e-9:
            say(status(s))

    sched.add("control", 1.0 / CONTROL_RATE, control_tick, priority=5)
    sched.add("capture", 1.0 / PHYSICS_RATE, capture_tick, priority=10)
    sched.add("trajectory", 1.0 / TRAJECTORY_RATE, trajectory_tick, priority=11)
    limit = 3.0 * marks[-1][0] / speed + 30.0
    sched.run(until=limit)
    if pending:
        raise ValueError(f"the vehicle did not reach {', '.join(k for _, k in pending)} within {limit:.0f} s "
                         f"of simulated time ({status(loop.state)})")
    say(f"run done: {loop.state.time:.2f} s simulated")
    return RunResult(captures, traj, start, heading, target_depth, speed, loop.state.time, ctrl)
