"""ARIS acoustic settings: ping modes, the SDK's ranges, and the checks the sonar makes (sans-I/O).

Times in [us], frame rates in [frames/s], gains in [dB] (the protocol's units).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Final

from hilsim.protocols.aris.constants import FREQ_HIGH, SYSTEM_1200, SYSTEM_1800, SYSTEM_3000

# Acoustic-settings limits (ARIS SDK's "Engineering Test Command List" ranges).
SAMPLES_PER_BEAM_RANGE: Final = (200, 4000)
SAMPLE_PERIOD_RANGE: Final = (4, 100)  # [us]
SAMPLE_START_DELAY_RANGE: Final = (930, 60000)  # [us]
CYCLE_PERIOD_RANGE: Final = (1802, 150000)  # [us]
PULSE_WIDTH_RANGE: Final = (4, 80)  # [us]
FRAME_RATE_RANGE: Final = (1.0, 15.0)  # [frames/s]
RECEIVER_GAIN_RANGE: Final = (0.0, 24.0)  # [dB]
CYCLE_PERIOD_MARGIN: Final = 360  # [us] after the last sample


def beams_for_ping_mode(ping_mode: int) -> int:
    """Beams by pingMode: 1-2 -> 48, 3-5 -> 96, 6-8 -> 64, 9-12 -> 128; 0 if unknown."""
    for lo, hi, n in ((1, 2, 48), (3, 5, 96), (6, 8, 64), (9, 12, 128)):
        if lo <= ping_mode <= hi:
            return n
    return 0


# Pings per frame by pingMode (estimate from the SDK's ping-mode table: the
# receive channels fire in groups; ARIS 1800 mode 1 = 3, mode 3 = 6).
PINGS_PER_FRAME: Final = {1: 3, 2: 3, 3: 6, 4: 6, 5: 6, 6: 4, 7: 4, 8: 4, 9: 8, 10: 8, 11: 8, 12: 8}
VALID_PING_MODES: Final = {SYSTEM_1800: (1, 3), SYSTEM_3000: (6, 9), SYSTEM_1200: (1,)}

# ------------------------------------------------------- acoustic settings


@dataclass(frozen=True)
class AcousticSettings:
    """``SetAcousticSettings``. Times in [us], frame_rate [frames/s], receiver_gain [dB]."""

    cookie: int = 0
    frame_rate: float = 10.0
    samples_per_beam: int = 512
    sample_start_delay: int = 930
    cycle_period: int = 10000
    sample_period: int = 10
    pulse_width: int = 10
    ping_mode: int = 3
    enable_transmit: bool = True
    frequency: int = FREQ_HIGH
    enable_150_volts: bool = True
    receiver_gain: float = 12.0

    def window(self, sound_speed: float) -> tuple[float, float]:
        """(start [m], end [m]) of the sampled range window at ``sound_speed`` [m/s]."""
        start = self.sample_start_delay * 1e-6 * sound_speed / 2.0
        length = self.samples_per_beam * self.sample_period * 1e-6 * sound_speed / 2.0
        return start, start + length

    @staticmethod
    def for_window(start: float, end: float, samples: int, sound_speed: float, *, frame_rate: float = 10.0,
                   ping_mode: int = 3, frequency: int = FREQ_HIGH, cookie: int = 1,
                   receiver_gain: float = 12.0) -> "AcousticSettings":
        """Settings whose window is as close as the integer microseconds allow to [start, end] [m]."""
        delay = max(SAMPLE_START_DELAY_RANGE[0], round(2.0 * start / sound_speed * 1e6))
        period = max(SAMPLE_PERIOD_RANGE[0], round(2.0 * (end - start) / sound_speed * 1e6 / samples))
        pings = PINGS_PER_FRAME.get(ping_mode, 1)
        cycle = max(CYCLE_PERIOD_RANGE[0], delay + samples * period + CYCLE_PERIOD_MARGIN)
        frame_rate = min(frame_rate, 1e6 / (cycle * pings))
        return AcousticSettings(cookie=cookie, frame_rate=frame_rate, samples_per_beam=samples,
                                sample_start_delay=delay, cycle_period=cycle, sample_period=period,
                                pulse_width=min(max(period, PULSE_WIDTH_RANGE[0]), PULSE_WIDTH_RANGE[1]),
                                ping_mode=ping_mode, frequency=frequency, receiver_gain=receiver_gain)


@dataclass(frozen=True)
class SettingsCheck:
    """Outcome of :func:`check_settings`: ``applied`` (possibly constrained) settings or
    ``invalid``, with the reasons."""

    outcome: str  # "applied" | "constrained" | "invalid"
    settings: AcousticSettings
    reasons: tuple[str, ...] = ()


def check_settings(s: AcousticSettings, system_type: int = SYSTEM_1800) -> SettingsCheck:
    """Validate settings as the sonar would (see protocols/aris.md, "Invalid settings").

    Invalid (nothing applied; cookie goes to InvalidSettings): a ping mode the
    system lacks, a frequency that disagrees with the ping mode's beams on an
    ARIS 1800 (48 beams = LF, 96 = HF), samplesPerBeam, samplePeriod,
    sampleStartDelay, pulseWidth or cyclePeriod outside their ranges, a
    non-finite frame rate or gain, a window longer than the longest cycle. Constrained (applied with changes; cookie
    goes to AppliedSettings and ConstrainedSettings): a cycle period too short
    for the window (raised), a frame rate above what the cycle period allows
    or outside 1..15 (clamped), a gain outside 0..24 dB (clamped).
    """
    why: list[str] = []
    if s.ping_mode not in VALID_PING_MODES.get(system_type, ()):
        why.append(f"pingMode {s.ping_mode} not available on this system")
    elif system_type == SYSTEM_1800 and (beams_for_ping_mode(s.ping_mode) == 96) != (s.frequency == FREQ_HIGH):
        why.append(f"pingMode {s.ping_mode} does not agree with frequency {s.frequency}")
    for name, (lo, hi) in (("samples_per_beam", SAMPLES_PER_BEAM_RANGE), ("sample_period", SAMPLE_PERIOD_RANGE),
                           ("sample_start_delay", SAMPLE_START_DELAY_RANGE), ("pulse_width", PULSE_WIDTH_RANGE),
                           ("cycle_period", CYCLE_PERIOD_RANGE)):
        v = getattr(s, name)
        if not lo <= v <= hi:
            why.append(f"{name} {v} outside {lo}..{hi}")
    if not (math.isfinite(s.frame_rate) and math.isfinite(s.receiver_gain)):
        why.append("frame rate or gain is not a finite number")
    need = s.sample_start_delay + s.samples_per_beam * s.sample_period + CYCLE_PERIOD_MARGIN
    if need > CYCLE_PERIOD_RANGE[1]:
        why.append(f"the window needs a {need} us cycle, more than {CYCLE_PERIOD_RANGE[1]} us")
    if why:
        return SettingsCheck("invalid", s, tuple(why))
    changes: dict[str, object] = {}
    notes: list[str] = []
    cycle = s.cycle_period
    if cycle < need:
        cycle = need
        changes["cycle_period"] = cycle
        notes.append(f"cyclePeriod raised to {cycle} us")
    max_rate = min(FRAME_RATE_RANGE[1], 1e6 / (cycle * PINGS_PER_FRAME.get(s.ping_mode, 1)))
    rate = min(max(s.frame_rate, FRAME_RATE_RANGE[0]), max_rate)
    if rate != s.frame_rate:
        changes["frame_rate"] = rate
        notes.append(f"frameRate constrained to {rate:.3g}")
    gain = min(max(s.receiver_gain, RECEIVER_GAIN_RANGE[0]), RECEIVER_GAIN_RANGE[1])
    if gain != s.receiver_gain:
        changes["receiver_gain"] = gain
        notes.append(f"receiverGain constrained to {gain:g} dB")
    if changes:
        return SettingsCheck("constrained", replace(s, **changes), tuple(notes))  # type: ignore[arg-type]
    return SettingsCheck("applied", s)
