"""The ARIS 1024-byte frame header (also the .aris file's) and file header, and the sample order (sans-I/O).

Sample order: with ``ReorderedSamples = 1`` the samples are ``sample * numBeams +
beam`` with beam 0 the rightmost (starboard) beam; the simulator's frames have
beam 0 at port, so :func:`samples_to_wire` / :func:`samples_from_wire` reverse
the beams (nothing else needs to know).
"""

from __future__ import annotations

import struct
from typing import Final, Mapping, Union

import numpy as np
import numpy.typing as npt

from hilsim.protocols.aris.constants import FILE_VERSION, HEADER_SIZE


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
