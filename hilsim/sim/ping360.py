"""A mechanical scanning sonar (Blue Robotics Ping360): one beam, turned by a stepper motor.

The beam is a one-beam :class:`~hilsim.sim.sonar.ImagingSonar` (the same intensity law, echo
spreading, gain, TVG, absorption and seeded speckle as the other sonars), cast with Embree
against the world from the transducer's pose at the head angle: the head turns about the
sensor mount's z axis (down in the mount frame), angle 0 along the mount's x axis, growing
towards its y axis (clockwise seen from above for a mount level and upright). 400 gradians
per turn.

Timing, as the device takes it (:func:`ping_duration`): the head steps to the new angle,
transmits, and listens for ``number_of_samples x sample_period x 25 ns``; measured sweep
times of a real Ping360 over Ethernet (Blue Robotics forum, "Ping 360 time info/split
image": 400 pings at 1-gradian steps took 10.7 s at 2 m, 20.6 s at 20 m, 37.6 s at 50 m;
40 pings at 10-gradian steps 3.3 s, 4.2 s, 5.9 s) are met by a fixed 18.2 ms per ping plus
6.13 ms per gradian the head turns, on top of the listening time (within 4 % on all six).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hilsim.sim.geometry import Pose, rpy_to_matrix
from hilsim.sim.sonar import ImagingSonar
from hilsim.sim.sonar_profile import SonarProfile, SonarSettings
from hilsim.sim.world import World

GRADIANS = 400
TICK_S = 25e-9                # [s] per sample_period unit
PING_OVERHEAD_S = 0.0182      # [s] per ping besides listening and turning (fit to the forum's sweep times)
STEP_S_PER_GRADIAN = 0.00613  # [s] per gradian the head turns (same fit)
GAIN_DB = {0: -6.0, 1: 0.0, 2: 6.0}  # gain_setting low / normal / high [dB] around the profile's (estimate)


def turn_gradians(a: int, b: int) -> int:
    """Gradians the head turns from angle ``a`` to ``b`` (the shorter way round)."""
    d = abs(int(b) - int(a)) % GRADIANS
    return min(d, GRADIANS - d)


def listen_s(samples: int, sample_period: int) -> float:
    """[s] the receiver listens: ``samples x sample_period x 25 ns``."""
    return samples * sample_period * TICK_S


def ping_duration(from_angle: int, to_angle: int, samples: int, sample_period: int,
                  transmit_duration_us: int = 0) -> float:
    """[s] from a transducer command to its data: turn, transmit, listen (see the module docstring)."""
    return (PING_OVERHEAD_S + STEP_S_PER_GRADIAN * turn_gradians(from_angle, to_angle)
            + transmit_duration_us * 1e-6 + listen_s(samples, sample_period))


@dataclass(frozen=True)
class PingSettings:
    """What a client commands: samples (200..1200), sample_period [25 ns ticks], gain_setting 0/1/2,
    transmit_duration [us], transmit_frequency [kHz]."""

    samples: int = 1200
    sample_period: int = 88
    gain_setting: int = 1
    transmit_duration: int = 11
    transmit_frequency: int = 750

    def range_m(self, sound_speed: float) -> float:
        """[m] the far edge of the last sample."""
        return self.samples * self.sample_period * TICK_S * sound_speed / 2.0


class ScanningSonar:
    """A Ping360-like head: ``ping(world, mount_pose, angle, settings)`` -> (samples,) uint8.

    profile: a one-beam sonar profile (``devices/sonars/ping360.toml``); seed: realism seed."""

    def __init__(self, profile: SonarProfile, seed: int = 0) -> None:
        if profile.n_beams != 1:
            raise ValueError(f"a scanning sonar has one beam; profile {profile.name!r} has {profile.n_beams}")
        self.profile = profile
        self.sonar = ImagingSonar(profile, seed=seed)

    def head_pose(self, mount_pose: Pose, angle: int) -> Pose:
        """The transducer's world pose at head angle ``angle`` [grad] for a mount at ``mount_pose``."""
        yaw = 2.0 * math.pi * (int(angle) % GRADIANS) / GRADIANS
        return mount_pose @ Pose(np.zeros(3), rpy_to_matrix(0.0, 0.0, yaw))

    def settings(self, s: PingSettings, sound_speed: float) -> SonarSettings:
        """Render settings for the commanded ones: window 0..range, samples, gain."""
        return self.profile.default_settings().replace(
            range_min=0.0, range_max=s.range_m(sound_speed), n_samples=int(s.samples),
            gain_db=self.profile.defaults.gain_db + GAIN_DB.get(int(s.gain_setting), 0.0))

    def ping(self, world: World, mount_pose: Pose, angle: int, s: PingSettings, *, sound_speed: float,
             time: float = 0.0, index: int = 0) -> np.ndarray:
        """(samples,) uint8 echo intensities at head angle ``angle``, nearest first."""
        frame = self.sonar.render(world, self.head_pose(mount_pose, angle), self.settings(s, sound_speed),
                                  time=time, frame_index=index)
        return np.ascontiguousarray(frame.image[:, 0])
