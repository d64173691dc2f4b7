"""Sound Metrics ARIS: command channel, availability beacon, frame stream, frame header (sans-I/O).

The spec is ``protocols/aris.md``; the messages are ``protocols/aris/*.proto``
(generated modules in :mod:`hilsim.protocols.aris_pb`).

* UDP beacon (sonar -> anyone, 1 Hz): protobuf ``Availability``
  (:func:`encode_availability`, every field written even when zero).
* TCP command channel (client -> sonar): each command is a 4-byte
  big-endian length then a serialized ``Command``; :class:`CommandReader`
  turns the byte stream into events and never raises or allocates more than
  ``max_length + 4`` bytes plus what was fed.
* UDP frame stream (sonar -> receiver): each frame as ``FramePart`` datagrams
  of at most 1500 bytes (:func:`split_frame`); :class:`FrameAssembler` puts
  them back together on the client side.
* The 1024-byte frame header (also the .aris file's): :data:`FRAME_HEADER_LAYOUT`,
  :func:`encode_frame_header`, :func:`decode_frame_header`.

Sample order: with ``ReorderedSamples = 1`` the samples are ``sample * numBeams +
beam`` with beam 0 the rightmost (starboard) beam; the simulator's frames have
beam 0 at port, so :func:`samples_to_wire` / :func:`samples_from_wire` reverse
the beams (nothing else needs to know).
"""

from __future__ import annotations

import heapq
import math
import struct
from collections import deque
from dataclasses import dataclass
from typing import Final, Mapping, Union

import numpy as np
import numpy.typing as npt
from google.protobuf.message import DecodeError, Message

from hilsim.protocols.aris_pb import aris_availability_pb2 as pb_avail
from hilsim.protocols.aris_pb import aris_commands_pb2 as pb_cmd
from hilsim.protocols.aris_pb import aris_frame_stream_pb2 as pb_frame

# --------------------------------------------------------------- constants

BEACON_PORT: Final = 56124
COMMAND_PORT: Final = 56888
MAX_DATAGRAM: Final = 1500
MAX_COMMAND_LENGTH: Final = 1024  # real commands are < 100 bytes
MAX_FRAME_DATA: Final = 128 * 4096  # beams x samples [bytes]
HEADER_SIZE: Final = 1024
FILE_VERSION: Final = 0x05464444  # "DDF\x05"

SYSTEM_1800: Final = 0
SYSTEM_3000: Final = 1
SYSTEM_1200: Final = 2

(SET_DATETIME, SET_FRAMESTREAM_RECEIVER, SET_FRAMESTREAM_SETTINGS, SET_ACOUSTICS, SET_SALINITY,
 SET_TELEPHOTO, SET_FOCUS) = range(7)
PING: Final = 14
FREQ_LOW: Final = 0
FREQ_HIGH: Final = 1
SALINITIES: Final = (0, 15, 35)

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

# ------------------------------------------------------------ frame header

# (struct code, name) in wire order: aris-file-sdk FrameHeader.h field list.
FRAME_HEADER_LAYOUT: Final[tuple[tuple[str, str], ...]] = tuple(
    (c, n) for c, n in (x.split() for x in (
        "I FrameIndex;Q FrameTime;I Version;I Status;Q sonarTimeStamp;I TS_Day;I TS_Hour;"
        "I TS_Minute;I TS_Second;I TS_Hsecond;I TransmitMode;f WindowStart;f WindowLength;"
        "I Threshold;i Intensity;I ReceiverGain;I DegC1;I DegC2;I Humidity;I Focus;I Battery;"
        "f UserValue1;f UserValue2;f UserValue3;f UserValue4;f UserValue5;f UserValue6;"
        "f UserValue7;f UserValue8;f Velocity;f Depth;f Altitude;f Pitch;f PitchRate;f Roll;"
        "f RollRate;f Heading;f HeadingRate;f CompassHeading;f CompassPitch;f CompassRoll;"
        "d Latitude;d Longitude;f SonarPosition;I ConfigFlags;f BeamTilt;f TargetRange;"
        "f TargetBearing;I TargetPresent;I FirmwareRevision;I Flags;I SourceFrame;f WaterTemp;"
        "I TimerPeriod;f SonarX;f SonarY;f SonarZ;f SonarPan;f SonarTilt;f SonarRoll;f PanPNNL;"
        "f TiltPNNL;f RollPNNL;d VehicleTime;f TimeGGK;I DateGGK;I QualityGGK;I NumSatsGGK;"
        "f DOPGGK;f EHTGGK;f HeaveTSS;I YearGPS;I MonthGPS;I DayGPS;I HourGPS;I MinuteGPS;"
        "I SecondGPS;I HSecondGPS;f SonarPanOffset;f SonarTiltOffset;f SonarRollOffset;"
        "f SonarXOffset;f SonarYOffset;f SonarZOffset;16f Tmatrix;f SampleRate;f AccellX;"
        "f AccellY;f AccellZ;I PingMode;I FrequencyHiLow;I PulseWidth;I CyclePeriod;"
        "I SamplePeriod;I TransmitEnable;f FrameRate;f SoundSpeed;I SamplesPerBeam;I Enable150V;"
        "I SampleStartDelay;I LargeLens;I TheSystemType;I SonarSerialNumber;Q ReservedEK;"
        "I ArisErrorFlagsUint;I MissedPackets;I ArisAppVersion;I Available2;I ReorderedSamples;"
        "I Salinity;f Pressure;f BatteryVoltage;f MainVoltage;f SwitchVoltage;I FocusMotorMoving;"
        "I VoltageChanging;I FocusTimeoutFault;I FocusOverCurrentFault;I FocusNotFoundFault;"
        "I FocusStalledFault;I FPGATimeoutFault;I FPGABusyFault;I FPGAStuckFault;I CPUTempFault;"
        "I PSUTempFault;I WaterTempFault;I HumidityFault;I PressureFault;I VoltageReadFault;"
        "I VoltageWriteFault;I FocusCurrentPosition;f TargetPan;f TargetTilt;f TargetRoll;"
        "I PanMotorErrorCode;I TiltMotorErrorCode;I RollMotorErrorCode;f PanAbsPosition;"
        "f TiltAbsPosition;f RollAbsPosition;f PanAccelX;f PanAccelY;f PanAccelZ;f TiltAccelX;"
        "f TiltAccelY;f TiltAccelZ;f RollAccelX;f RollAccelY;f RollAccelZ;I AppliedSettings;"
        "I ConstrainedSettings;I InvalidSettings;I EnableInterpacketDelay;"
        "I InterpacketDelayPeriod;I Uptime;H ArisAppVersionMajor;H ArisAppVersionMinor;"
        "Q GoTime;f PanVelocity;f TiltVelocity;f RollVelocity;I GpsTimeAge"
    ).split(";"))
)

# .aris file header (aris-file-sdk FileHeader.h), 1024 bytes.
FILE_HEADER_LAYOUT: Final[tuple[tuple[str, str], ...]] = tuple(
    (c, n) for c, n in (x.split() for x in (
        "I Version;I FrameCount;I FrameRate;I HighResolution;I NumRawBeams;f SampleRate;"
        "I SamplesPerChannel;I ReceiverGain;f WindowStart;f WindowLength;I Reverse;I SN;"
        "32s strDate;256s strHeaderID;i UserID1;i UserID2;i UserID3;i UserID4;I StartFrame;"
        "I EndFrame;I TimeLapse;I RecordInterval;I RadioSeconds;I FrameInterval;I Flags;"
        "I AuxFlags;I Sspd;I Flags3D;I SoftwareVersion;I WaterTemp;I Salinity;I PulseLength;"
        "I TxMode;I VersionFGPA;I VersionPSuC;I ThumbnailFI;Q FileSize;Q OptionalHeaderSize;"
        "Q OptionalTailSize;I VersionMinor;I LargeLens"
    ).split(";"))
)

HeaderValue = Union[int, float, bytes, tuple[float, ...]]


def _offsets(layout: tuple[tuple[str, str], ...]) -> tuple[struct.Struct, dict[str, int]]:
    fmt, offs, off = "<", {}, 0
    for code, name in layout:
        offs[name] = off
        fmt += code
        off += struct.calcsize("<" + code)
    return struct.Struct(fmt), offs


_FRAME_STRUCT, FRAME_OFFSETS = _offsets(FRAME_HEADER_LAYOUT)
_FILE_STRUCT, FILE_OFFSETS = _offsets(FILE_HEADER_LAYOUT)
assert _FRAME_STRUCT.size == 732 and _FILE_STRUCT.size == 456
assert FRAME_OFFSETS["PingMode"] == 436 and FRAME_OFFSETS["ReorderedSamples"] == 516
assert FRAME_OFFSETS["AppliedSettings"] == 680 and FRAME_OFFSETS["InvalidSettings"] == 688
assert FILE_OFFSETS["NumRawBeams"] == 16 and FILE_OFFSETS["SN"] == 44


def _pack(st: struct.Struct, layout: tuple[tuple[str, str], ...], values: Mapping[str, HeaderValue],
          what: str) -> bytes:
    names = {n for _, n in layout}
    unknown = set(values) - names
    if unknown:
        raise ValueError(f"unknown {what} field(s): {', '.join(sorted(unknown))}")
    flat: list[object] = []
    for code, name in layout:
        v = values.get(name)
        if code == "16f":
            t = tuple(v) if isinstance(v, tuple) else (0.0,) * 16
            if len(t) != 16:
                raise ValueError(f"{what}.{name} needs 16 values")
            flat.extend(float(x) for x in t)
        elif code.endswith("s"):
            flat.append(v if isinstance(v, bytes) else b"")
        elif code in "fd":
            flat.append(float(v) if isinstance(v, (int, float)) else 0.0)
        else:
            flat.append(int(v) if isinstance(v, (int, float)) else 0)
    try:
        return st.pack(*flat).ljust(HEADER_SIZE, b"\0")
    except struct.error as exc:
        raise ValueError(f"{what}: {exc}") from None


def _unpack(st: struct.Struct, layout: tuple[tuple[str, str], ...], data: bytes) -> dict[str, HeaderValue]:
    raw = bytes(data[:HEADER_SIZE]).ljust(HEADER_SIZE, b"\0")
    flat = list(st.unpack_from(raw))
    out: dict[str, HeaderValue] = {}
    i = 0
    for code, name in layout:
        if code == "16f":
            out[name] = tuple(flat[i : i + 16])
            i += 16
        else:
            out[name] = flat[i]
            i += 1
    return out


def encode_frame_header(values: Mapping[str, HeaderValue]) -> bytes:
    """Field name -> value (FrameHeader.h names) -> 1024 bytes; missing fields are 0.

    ValueError for an unknown name or a value that does not fit its field.
    """
    return _pack(_FRAME_STRUCT, FRAME_HEADER_LAYOUT, values, "FrameHeader")


def decode_frame_header(data: bytes) -> dict[str, HeaderValue]:
    """The first 1024 bytes (shorter input is zero-padded, as receivers do) -> field dict."""
    return _unpack(_FRAME_STRUCT, FRAME_HEADER_LAYOUT, data)


def encode_file_header(values: Mapping[str, HeaderValue]) -> bytes:
    """.aris file header fields -> 1024 bytes (Version defaults to DDF_05)."""
    return _pack(_FILE_STRUCT, FILE_HEADER_LAYOUT, {"Version": FILE_VERSION, **values}, "FileHeader")


def decode_file_header(data: bytes) -> dict[str, HeaderValue]:
    return _unpack(_FILE_STRUCT, FILE_HEADER_LAYOUT, data)


def samples_to_wire(samples: npt.NDArray[np.uint8]) -> bytes:
    """(n_samples, n_beams) uint8, beam 0 = port -> wire bytes (beam 0 = starboard)."""
    if samples.dtype != np.uint8 or samples.ndim != 2:
        raise ValueError("samples must be a 2-D uint8 array (n_samples, n_beams)")
    return np.ascontiguousarray(samples[:, ::-1]).tobytes()


def samples_from_wire(data: bytes, n_beams: int, n_samples: int) -> npt.NDArray[np.uint8]:
    """Wire bytes -> (n_samples, n_beams) uint8 with beam 0 = port (a copy)."""
    arr = np.frombuffer(data, np.uint8, n_beams * n_samples)
    return arr.reshape(n_samples, n_beams)[:, ::-1].copy()


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
        from dataclasses import replace

        return SettingsCheck("constrained", replace(s, **changes), tuple(notes))  # type: ignore[arg-type]
    return SettingsCheck("applied", s)


# ------------------------------------------------------------------ commands


@dataclass(frozen=True)
class SetDateTime:
    text: str  # "2014-Jan-31 23:58:15"


@dataclass(frozen=True)
class SetFrameStreamReceiver:
    port: int
    ip: str | None = None  # None: the TCP peer's address


@dataclass(frozen=True)
class SetAcoustics:
    settings: AcousticSettings


@dataclass(frozen=True)
class SetSalinity:
    salinity: int  # [ppt] 0, 15 or 35


@dataclass(frozen=True)
class SetFocus:
    focus_range: float | None = None  # [m]
    position: int | None = None  # motor units


@dataclass(frozen=True)
class Ping:
    pass


@dataclass(frozen=True)
class Unsupported:
    """A well-formed command of a type we accept but do not act on."""

    command_type: int


@dataclass(frozen=True)
class BadCommand:
    """A length-prefixed frame whose payload is not a valid Command."""

    reason: str
    length: int = 0


@dataclass(frozen=True)
class Oversize:
    """A length prefix above the bound; the reader resynchronises."""

    length: int


@dataclass(frozen=True)
class Junk:
    """Bytes skipped while resynchronising."""

    n_bytes: int


Command = Union[SetDateTime, SetFrameStreamReceiver, SetAcoustics, SetSalinity, SetFocus, Ping]
CommandEvent = Union[SetDateTime, SetFrameStreamReceiver, SetAcoustics, SetSalinity, SetFocus, Ping,
                     Unsupported, BadCommand, Oversize, Junk]


def _settings_pb(s: AcousticSettings, m: pb_cmd.Command.SetAcousticSettings) -> None:
    m.cookie = s.cookie
    m.frameRate = s.frame_rate
    m.samplesPerBeam = s.samples_per_beam
    m.sampleStartDelay = s.sample_start_delay
    m.cyclePeriod = s.cycle_period
    m.samplePeriod = s.sample_period
    m.pulseWidth = s.pulse_width
    m.pingMode = s.ping_mode
    m.enableTransmit = s.enable_transmit
    m.frequency = s.frequency  # type: ignore[assignment]
    m.enable150Volts = s.enable_150_volts
    m.receiverGain = s.receiver_gain


def command_message(cmd: Command) -> pb_cmd.Command:
    """A command event -> the protobuf Command (every field set explicitly)."""
    m = pb_cmd.Command()
    if isinstance(cmd, SetDateTime):
        m.type = SET_DATETIME  # type: ignore[assignment]
        m.dateTime.dateTime = cmd.text
    elif isinstance(cmd, SetFrameStreamReceiver):
        m.type = SET_FRAMESTREAM_RECEIVER  # type: ignore[assignment]
        m.frameStreamReceiver.port = cmd.port
        if cmd.ip is not None:
            m.frameStreamReceiver.ip = cmd.ip
    elif isinstance(cmd, SetAcoustics):
        m.type = SET_ACOUSTICS  # type: ignore[assignment]
        _settings_pb(cmd.settings, m.settings)
    elif isinstance(cmd, SetSalinity):
        m.type = SET_SALINITY  # type: ignore[assignment]
        m.salinity.salinity = cmd.salinity  # type: ignore[assignment]
    elif isinstance(cmd, SetFocus):
        m.type = SET_FOCUS  # type: ignore[assignment]
        m.focusPosition.SetInParent()
        if cmd.focus_range is not None:
            m.focusPosition.focusRange = cmd.focus_range
        if cmd.position is not None:
            m.focusPosition.position = cmd.position
    elif isinstance(cmd, Ping):
        m.type = PING  # type: ignore[assignment]
        m.ping.SetInParent()
    else:
        raise ValueError(f"not a command: {cmd!r}")
    return m


def frame_command(payload: bytes) -> bytes:
    """Prefix ``payload`` with its 4-byte big-endian length."""
    return struct.pack(">I", len(payload)) + payload


def encode_command(cmd: Command) -> bytes:
    """A command event -> length prefix + serialized Command."""
    return frame_command(command_message(cmd).SerializeToString())


def _has_unknown(m: Message) -> bool:
    from google.protobuf import unknown_fields

    if len(unknown_fields.UnknownFieldSet(m)):
        return True
    for fd, v in m.ListFields():
        if fd.message_type is not None and _has_unknown(v):
            return True
    return False


def parse_command(payload: bytes, strict: bool = False) -> CommandEvent:
    """One serialized Command -> a command event, Unsupported or BadCommand (never raises).

    strict: also reject unknown fields and unknown types (used while resynchronising).
    """
    m = pb_cmd.Command()
    try:
        m.ParseFromString(payload)
    except (DecodeError, RuntimeWarning, ValueError) as exc:
        return BadCommand(f"not a Command: {exc}", len(payload))
    if not m.HasField("type"):
        return BadCommand("Command without a (known) type", len(payload))
    if strict and _has_unknown(m):
        return BadCommand("unknown fields", len(payload))
    t = int(m.type)
    if t == SET_DATETIME and m.HasField("dateTime"):
        text: object = m.dateTime.dateTime
        if not isinstance(text, str):  # proto2 strings are not checked: invalid UTF-8 comes back as bytes
            return BadCommand("dateTime is not UTF-8 text", len(payload))
        return SetDateTime(text)
    if t == SET_FRAMESTREAM_RECEIVER and m.HasField("frameStreamReceiver"):
        r = m.frameStreamReceiver
        ip: object = r.ip if r.HasField("ip") else None
        if ip is not None and not isinstance(ip, str):
            return BadCommand("frameStreamReceiver ip is not UTF-8 text", len(payload))
        return SetFrameStreamReceiver(int(r.port), ip)
    if t == SET_ACOUSTICS and m.HasField("settings"):
        s = m.settings
        return SetAcoustics(AcousticSettings(
            cookie=s.cookie, frame_rate=float(s.frameRate), samples_per_beam=s.samplesPerBeam,
            sample_start_delay=s.sampleStartDelay, cycle_period=s.cyclePeriod, sample_period=s.samplePeriod,
            pulse_width=s.pulseWidth, ping_mode=s.pingMode, enable_transmit=s.enableTransmit,
            frequency=int(s.frequency), enable_150_volts=s.enable150Volts, receiver_gain=float(s.receiverGain)))
    if t == SET_SALINITY and m.HasField("salinity"):
        return SetSalinity(int(m.salinity.salinity))
    if t == SET_FOCUS and m.HasField("focusPosition"):
        f = m.focusPosition
        return SetFocus(float(f.focusRange) if f.HasField("focusRange") else None,
                        int(f.position) if f.HasField("position") else None)
    if t == PING:
        return Ping()
    if t in (SET_DATETIME, SET_FRAMESTREAM_RECEIVER, SET_ACOUSTICS, SET_SALINITY, SET_FOCUS):
        return BadCommand(f"command type {t} without its message", len(payload))
    if strict:
        return BadCommand(f"command type {t} not handled", len(payload))
    return Unsupported(t)


class CommandReader:
    """Incremental decoder of the ARIS command channel (sonar side).

    ``receive_data(bytes)`` then ``next_event()`` until None. In sync, each
    frame is a 4-byte big-endian length and that many payload bytes. A length
    above ``max_length`` gives :class:`Oversize`, a payload that is not a valid
    Command gives :class:`BadCommand`; either drops the reader out of sync. Out
    of sync it looks, byte by byte, for the first offset holding a complete
    frame whose payload parses strictly (known type, its message, no unknown
    fields), reports the bytes before it as :class:`Junk` and goes on in sync.
    Memory: the buffer holds at most ``max_length + 4`` bytes beyond what was
    fed since the last drain; a 4 GB length prefix allocates nothing. Out of
    sync, the offsets still waiting for bytes are remembered (at most
    ``max_length + 4`` of them, about 150 bytes of bookkeeping each).

    Cost: amortized linear in the bytes received, however they are cut. In
    sync, a frame still arriving is not looked at again until the stream
    reaches its end (``_wait_end``). Out of sync, every offset is judged once
    when its length prefix is whole: a length above the bound or a complete
    frame that does not parse is forgotten (more bytes cannot change it), a
    frame still incomplete is remembered with the stream offset it needs
    (``_waiting``, a heap) and parsed once when that offset arrives;
    ``_scan`` is how far offsets were judged. Offsets are stream offsets
    (``_base`` is the offset of ``_buf[0]``), untouched when consumed bytes
    are dropped.
    """

    def __init__(self, max_length: int = MAX_COMMAND_LENGTH) -> None:
        self.max_length = int(max_length)
        self._buf = bytearray()
        self._pos = 0
        self._base = 0  # stream offset of _buf[0]
        self._synced = True
        self._pending: list[CommandEvent] = []
        self._wait_end = 0  # in sync: the frame at _pos is incomplete until the stream reaches this offset
        # out of sync: offsets below _scan are judged; the incomplete ones as (offset needed, offset) in
        # _waiting, and in ascending order in _waiting_order (those still in _waiting_set are incomplete)
        self._scan = 0
        self._waiting: list[tuple[int, int]] = []
        self._waiting_order: deque[int] = deque()
        self._waiting_set: set[int] = set()
        self.errors = 0
        self.commands = 0

    @property
    def buffered_bytes(self) -> int:
        return len(self._buf) - self._pos

    def receive_data(self, data: bytes) -> None:
        if self._pos and 2 * self._pos >= len(self._buf):
            del self._buf[: self._pos]
            self._base += self._pos
            self._pos = 0
        self._buf += data

    def events(self) -> list[CommandEvent]:
        out: list[CommandEvent] = []
        while (ev := self.next_event()) is not None:
            out.append(ev)
        return out

    def next_event(self) -> CommandEvent | None:
        if self._pending:
            return self._pending.pop(0)
        ev = self._next_synced() if self._synced else self._resync()
        if isinstance(ev, (BadCommand, Oversize)):
            self.errors += 1
        elif ev is not None and not isinstance(ev, Junk):
            self.commands += 1
        return ev

    def _next_synced(self) -> CommandEvent | None:
        buf, pos = self._buf, self._pos
        if len(buf) - pos < 4 or self._base + len(buf) < self._wait_end:
            return None
        (length,) = struct.unpack_from(">I", buf, pos)
        if length > self.max_length:
            self._synced = False
            self._pos = pos + 1
            return Oversize(length)
        end = pos + 4 + length
        if len(buf) < end:
            self._wait_end = self._base + end
            return None
        ev = parse_command(bytes(buf[pos + 4 : end]))
        if isinstance(ev, BadCommand):
            self._synced = False
            self._pos = pos + 1
        else:
            self._pos = end
        return ev

    def _resync(self) -> CommandEvent | None:
        """The first offset (from _pos) holding a complete frame that parses strictly.

        Same outcome as trying every offset from _pos on every call; only
        offsets whose frame became complete and offsets not judged before are
        looked at (see the class docstring).
        """
        buf, base, start = self._buf, self._base, self._base + self._pos
        stream_end = base + len(buf)
        waiting, waiting_set = self._waiting, self._waiting_set
        best, best_end = -1, 0
        best_ev: CommandEvent | None = None
        while waiting and waiting[0][0] <= stream_end:
            end, j = heapq.heappop(waiting)
            waiting_set.discard(j)
            if j < start:
                continue
            ev = parse_command(bytes(buf[j + 4 - base : end - base]), strict=True)
            if not isinstance(ev, BadCommand) and (best < 0 or j < best):
                best, best_end, best_ev = j, end, ev
        if best < 0:
            # offsets below _scan are not commands or still incomplete: judge the new ones in order
            j = max(self._scan, start)
            while j <= stream_end - 4:
                (length,) = struct.unpack_from(">I", buf, j - base)
                if length <= self.max_length:
                    end = j + 4 + length
                    if end > stream_end:
                        heapq.heappush(waiting, (end, j))
                        self._waiting_order.append(j)
                        waiting_set.add(j)
                    else:
                        ev = parse_command(bytes(buf[j + 4 - base : end - base]), strict=True)
                        if not isinstance(ev, BadCommand):
                            best, best_end, best_ev = j, end, ev
                            break
                j += 1
            self._scan = j
        if best_ev is not None:
            # every offset remembered lies before best_end (it was judged when the stream ended
            # before best_end), where the reader goes on in sync: forget them
            waiting.clear()
            self._waiting_order.clear()
            waiting_set.clear()
            self._synced = True
            self._pos = best_end - base
            if best > start:
                self._pending.append(best_ev)
                self.commands += 1
                return Junk(best - start)
            return best_ev
        order = self._waiting_order
        while order and (order[0] < start or order[0] not in waiting_set):
            order.popleft()
        keep_from = order[0] if order else max(start, stream_end - 3)
        if keep_from > start:
            self._pos = keep_from - base
            return Junk(keep_from - start)
        return None


# ----------------------------------------------------------- availability


@dataclass(frozen=True)
class Availability:
    serial_number: int
    system_type: int = SYSTEM_1800
    software_version: tuple[int, int, int] = (2, 8, 0)
    connection_state: int = 0  # 0 AVAILABLE, 1 BUSY
    system_variants: int = 0


def encode_availability(a: Availability) -> bytes:
    """The beacon datagram; every field is set, so zeros are written too."""
    m = pb_avail.Availability()
    m.serialNumber = a.serial_number
    m.systemType = a.system_type  # type: ignore[assignment]
    m.softwareVersion.major, m.softwareVersion.minor, m.softwareVersion.buildnumber = a.software_version
    m.connectionState = a.connection_state  # type: ignore[assignment]
    m.systemVariants = a.system_variants
    return m.SerializeToString()


def decode_availability(data: bytes) -> Availability | BadCommand:
    m = pb_avail.Availability()
    try:
        m.ParseFromString(bytes(data))
    except (DecodeError, RuntimeWarning, ValueError) as exc:
        return BadCommand(f"not an Availability message: {exc}", len(data))
    if not m.HasField("serialNumber"):
        return BadCommand("Availability without serialNumber", len(data))
    v = m.softwareVersion
    return Availability(m.serialNumber, int(m.systemType), (v.major, v.minor, v.buildnumber),
                        int(m.connectionState), m.systemVariants)


# ------------------------------------------------------------- frame stream


def _frame_part(frame_index: int, total: int, offset: int, data: bytes, header: bytes | None) -> pb_frame.FramePart:
    m = pb_frame.FramePart()
    m.frame_index = frame_index
    m.total_data_size = total
    if header is not None:
        m.header = header
    m.data = data
    m.data_offset = offset
    m.ack_port = 0
    return m


def split_frame(frame_index: int, header: bytes, samples: bytes, max_datagram: int = MAX_DATAGRAM) -> list[bytes]:
    """One frame -> FramePart datagrams of at most ``max_datagram`` bytes.

    header: the 1024-byte frame header; its trailing zero bytes are not sent
    ("the bytes in use"; receivers pad to 1024). The first part carries it.
    Every part writes frame_index, total_data_size, data, data_offset and
    ack_port, even when zero.
    """
    if len(header) > HEADER_SIZE:
        raise ValueError("frame header is longer than 1024 bytes")
    used = bytes(header).rstrip(b"\0") or b"\0"
    total = len(samples)
    parts: list[bytes] = []
    offset = 0
    first = True
    while first or offset < total:
        head = used if first else None
        overhead = _frame_part(frame_index, total, offset, b"", head).ByteSize()
        room = max_datagram - overhead - 3  # data: tag + 2-byte length
        if room <= 0:
            raise ValueError("max_datagram too small for a frame part")
        chunk = samples[offset : offset + room]
        msg = _frame_part(frame_index, total, offset, bytes(chunk), head).SerializeToString()
        assert len(msg) <= max_datagram
        parts.append(msg)
        offset += len(chunk)
        first = False
    return parts


@dataclass(frozen=True)
class AssembledFrame:
    frame_index: int
    header: bytes  # 1024 bytes, zero-padded
    data: bytes  # total_data_size bytes, wire order


@dataclass(frozen=True)
class DroppedFrame:
    frame_index: int
    received: int
    total: int


@dataclass(frozen=True)
class BadDatagram:
    reason: str


AssemblerEvent = Union[AssembledFrame, DroppedFrame, BadDatagram]


class FrameAssembler:
    """Client side: FramePart datagrams -> whole frames (sans-I/O).

    Keeps one frame in progress; a part of a newer frame drops an incomplete
    older one (:class:`DroppedFrame`); parts of older frames are ignored.
    Memory is bounded by ``2 x max_data`` bytes: the frame and a map of the
    bytes received (a larger total_data_size is a :class:`BadDatagram`). A
    frame is complete when every byte was received, however the parts overlap.
    """

    def __init__(self, max_data: int = MAX_FRAME_DATA * 2) -> None:
        self.max_data = max_data
        self._index = -1
        self._total = 0
        self._data = bytearray()
        self._header: bytes | None = None
        self._got = bytearray()  # 1 per byte of the frame received
        self._received = 0
        self._done = -1

    def receive_datagram(self, datagram: bytes) -> list[AssemblerEvent]:
        m = pb_frame.FramePart()
        try:
            m.ParseFromString(bytes(datagram))
        except (DecodeError, RuntimeWarning, ValueError) as exc:
            return [BadDatagram(f"not a FramePart: {exc}")]
        for f in ("frame_index", "total_data_size", "data", "data_offset"):
            if not m.HasField(f):
                return [BadDatagram(f"FramePart without {f}")]
        idx, total, off = m.frame_index, m.total_data_size, m.data_offset
        if not 0 <= total <= self.max_data or off < 0 or off + len(m.data) > total:
            return [BadDatagram(f"FramePart out of bounds: total {total}, offset {off}, {len(m.data)} bytes")]
        out: list[AssemblerEvent] = []
        if idx <= self._done or (idx < self._index):
            return out
        if idx != self._index:
            if self._index >= 0 and self._index > self._done:
                out.append(DroppedFrame(self._index, self._received, self._total))
            self._index, self._total = idx, total
            self._data = bytearray(total)
            self._header, self._got, self._received = None, bytearray(total), 0
        if total != self._total:
            return out + [BadDatagram("total_data_size changed within a frame")]
        if m.HasField("header"):
            self._header = bytes(m.header[:HEADER_SIZE]).ljust(HEADER_SIZE, b"\0")
        n = len(m.data)
        self._received += n - self._got.count(1, off, off + n)
        self._got[off : off + n] = b"\x01" * n
        self._data[off : off + n] = m.data
        if self._received >= total and self._header is not None:
            out.append(AssembledFrame(idx, self._header, bytes(self._data)))
            self._done = idx
            self._data, self._got = bytearray(), bytearray()
        return out
