"""Build a scenario's sensors from their profiles (shared by ``render`` and the bridge)."""

from __future__ import annotations

from pathlib import Path

from hilsim.resources import find_profile
from hilsim.sim.camera import Camera, load_camera_profile
from hilsim.sim.scenario import Scenario, SensorMount
from hilsim.sim.sonar import ImagingSonar
from hilsim.sim.sonar_profile import load_sonar_profile

PROFILE_FOLDER = {"sonar": "sonars", "camera": "cameras", "depth": "sensors", "imu": "sensors", "dvl": "sensors",
                  "gnss": "sensors", "echosounder": "sensors"}


def profile_path(scenario: Scenario, mount: SensorMount) -> Path:
    """The profile file of a mounted sensor (the scenario's folder first, then devices/)."""
    return find_profile(PROFILE_FOLDER[mount.kind], mount.profile, base=scenario.folder)


def build_sonar(scenario: Scenario, mount: SensorMount, seed: int | None = None) -> ImagingSonar:
    if mount.kind != "sonar":
        raise ValueError(f"sensor {mount.name!r} is a {mount.kind}, not a sonar")
    return ImagingSonar(load_sonar_profile(profile_path(scenario, mount)),
                        seed=scenario.seed if seed is None else seed)


def build_camera(scenario: Scenario, mount: SensorMount) -> Camera:
    if mount.kind != "camera":
        raise ValueError(f"sensor {mount.name!r} is a {mount.kind}, not a camera")
    return Camera(load_camera_profile(profile_path(scenario, mount)))
