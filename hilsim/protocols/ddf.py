"""DIDSON-like frame stream: a DDF version 4 file sent over TCP (sans-I/O).

The spec is ``protocols/ddf-stream.md``. The server's bytes form a valid
DDF_04 file: a 1024-byte file header, then per frame a 1024-byte frame
header and ``numbeams x samplesperchannel`` uint8 samples. All integers are
little-endian int32 unless noted; the layouts below are the DDF_04 tables.

Sample order. The simulator hands over a frame as a ``(n_samples, n_beams)``
uint8 array with beams in ascending azimuth: sim beam 0 is the most negative
azimuth (port). On the wire beam 0 is the rightmost (starboard) beam and the
beam index runs fastest: byte ``sample * numbeams + wire_beam`` of the sample
block, ``wire_beam = numbeams - 1 - sim_beam``. :func:`encode_frame` and
:func:`decode_frame` do the reversal; nothing else needs to know.

Frame time. The 8-byte ``frametime`` field holds uint64 microseconds since
1970-01-01T00:00:00Z (what the same bytes mean in DDF_05/ARIS files; DDF_04
readers that read it as two int32 see its low and high words). The calendar
fields year..hsecond (hsecond = hundredths) hold the same instant in UTC.
Both are filled from one value, :attr:`FrameHeader.time` [s since epoch].

Platform fields (float32): velocity [m/s], depth [m], altitude [m], pitch,
roll, heading [deg], pitchrate, rollrate, headingrate [deg/s]; sonar
pan/tilt/roll [deg]; latitude/longitude float64 [deg].

The command channel (client -> server ASCII lines) is
:mod:`hilsim.protocols.ddf_commands`; its replies travel in the reply area of
the next frame header (bytes 768..1023), so the stream stays a valid DDF
file. Peer errors raise :class:`ProtocolError`; misuse by our own code
raises ValueError.
"""

from __future__ import annotations

import calendar
import math
import numbers
import struct
from dataclasses import dataclass, fields
from datetime import datetime, timedelta, timezone
from typing import Final, Sequence, Union

import numpy as np
import numpy.typing as npt

from hilsim.protocols.codec import NEED_DATA, NeedData

# --------------------------------------------------------------- constants

SIGNATURE: Final = b"DDF\x04"  # file header bytes 0..3, uint32 0x04464444
FILE_HEADER_SIZE: Final = 1024  # [bytes]
FRAME_HEADER_SIZE: Final = 1024  # [bytes]
NUMFRAMES_OFFSET: Final = 4  # file header int32 a seeking recorder may patch
NUMBEAMS_HF: Final = 96
NUMBEAMS_LF: Final = 48
SAMPLES_PER_CHANNEL: Final = 512
MAX_NUMBEAMS: Final = 512  # plausibility bounds: a frame stays <= 2 MiB
MAX_SAMPLES_PER_CHANNEL: Final = 4096

TRANSMIT_HF: Final = 0x1  # frame header `transmit` bits
TRANSMIT_ENABLE: Final = 0x2
TRANSMIT_2MHZ: Final = 0x4
CONFIG_CLASSIC: Final = 0x1  # frame header `configflags`: 1 classic, 0 extended windows
CONFIG_LONG_RANGE: Final = 0x2  # DIDSON-LR

# Window codes. start [m] = code x step, step doubled at LF (1..31).
# length [m] = table[code + (0 at HF, 2 at LF)] for code 0..3.
START_CODE_MIN: Final = 1
START_CODE_MAX: Final = 31
LENGTH_CODE_MIN: Final = 0
LENGTH_CODE_MAX: Final = 3
EXTENDED_START_STEP_M: Final = 0.419
CLASSIC_START_STEP_M: Final = 0.375
EXTENDED_LENGTHS_M: Final = (1.25, 2.5, 5.0, 10.0, 20.0, 40.0)
CLASSIC_LENGTHS_M: Final = (1.125, 2.25, 4.5, 9.0, 18.0, 36.0)
LR_EXTENDED_LENGTHS_M: Final = (2.5, 5.0, 10.0, 20.0, 40.0, 70.0)
LR_CLASSIC_LENGTHS_M: Final = (2.25, 4.5, 9.0, 18.0, 36.0, 72.0)

REPLY_AREA_OFFSET: Final = 768  # in the frame header; free in DDF_04 and DDF_05
RAYS_OFFSET: Final = 732  # int32 in the frame header (zero padding in DDF_04, past DDF_05's fields): rays used
REPLY_AREA_SIZE: Final = 256  # [bytes]; holds at most 255 bytes of reply lines

_I32_MIN, _I32_MAX = -(2**31), 2**31 - 1
_F32_MAX = 3.4028234663852886e38


class ProtocolError(ValueError):
    """The peer sent bytes that break the DDF stream or the command syntax."""


# ------------------------------------------------------------ window codes


def _window_tables(
    high_freq: bool, extended: bool, long_range: bool
) -> tuple[float, tuple[float, ...], int]:
    step = EXTENDED_START_STEP_M if extended else CLASSIC_START_STEP_M
    if long_range:
        lengths = LR_EXTENDED_LENGTHS_M if extended else LR_CLASSIC_LENGTHS_M
    else:
        lengths = EXTENDED_LENGTHS_M if extended else CLASSIC_LENGTHS_M
    return (step if high_freq else 2.0 * step), lengths, (0 if high_freq else 2)


def window_from_codes(
    start_code: int,
    length_code: int,
    high_freq: bool,
    extended: bool = True,
    long_range: bool = False,
) -> tuple[float, float]:
    """Window codes -> (start [m], length [m]).

    start_code 1..31, length_code 0..3 (ValueError otherwise). HF extended:
    start = code x 0.419 m, lengths 1.25/2.5/5/10 m; LF doubles the start
    step and shifts the length table by two (5/10/20/40 m).
    """
    if not START_CODE_MIN <= start_code <= START_CODE_MAX:
        raise ValueError(f"window start code {start_code} out of range 1..31")
    if not LENGTH_CODE_MIN <= length_code <= LENGTH_CODE_MAX:
        raise ValueError(f"window length code {length_code} out of range 0..3")
    step, lengths, shift = _window_tables(high_freq, extended, long_range)
    return start_code * step, lengths[length_code + shift]


def codes_for_window(
    start_m: float,
    length_m: float,
    high_freq: bool,
    extended: bool = True,
    long_range: bool = False,
) -> tuple[int, int]:
    """(start [m], length [m]) -> the nearest (start_code, length_code).

    Out-of-range requests clamp to the nearest valid code; a length exactly
    between two table entries takes the shorter one.
    """
    if not (math.isfinite(start_m) and math.isfinite(length_m)):
        raise ValueError(f"window must be finite, got {start_m!r}, {length_m!r}")
    step, lengths, shift = _window_tables(high_freq, extended, long_range)
    start_code = min(max(round(start_m / step), START_CODE_MIN), START_CODE_MAX)
    candidates = range(LENGTH_CODE_MIN, LENGTH_CODE_MAX + 1)
    length_code = min(candidates, key=lambda c: (abs(lengths[c + shift] - length_m), c))
    return start_code, length_code


def transmit_flags(high_freq: bool, enabled: bool = True, two_mhz: bool = False) -> int:
    """The frame header `transmit` field: bit0 HF, bit1 enable, bit2 2 MHz."""
    return (
        (TRANSMIT_HF if high_freq else 0)
        | (TRANSMIT_ENABLE if enabled else 0)
        | (TRANSMIT_2MHZ if two_mhz else 0)
    )


# ----------------------------------------------------------------- headers


@dataclass(frozen=True)
class FileHeader:
    """DDF_04 file header. Window fields are codes; see :meth:`window_m`.

    framerate [frames/s] (int32), resolution 1 = HF / 0 = LF, samplerate
    [Hz] float32 (informative), receivergain [dB], sspd sound speed [m/s].
    Text fields are ASCII, at most 31 (date) / 255 (idstring) characters.
    """

    numframes: int = 0  # 0 = live stream / unknown
    framerate: int = 10
    resolution: int = 1
    numbeams: int = NUMBEAMS_HF
    samplerate: float = 0.0
    samplesperchannel: int = SAMPLES_PER_CHANNEL
    receivergain: int = 20
    windowstart: int = 2
    windowlength: int = 2
    reverse: int = 0
    serialnumber: int = 0
    date: str = ""
    idstring: str = ""
    id1: int = 0
    id2: int = 0
    id3: int = 0
    id4: int = 0
    startframe: int = 0
    endframe: int = 0
    timelapse: int = 0
    recordinterval: int = 0
    radioseconds: int = 0
    frameinterval: int = 0
    flags: int = 0
    auxflags: int = 0
    sspd: int = 0
    flags3d: int = 0

    def window_m(self, extended: bool = True, long_range: bool = False) -> tuple[float, float]:
        """(start [m], length [m]) of the window codes at connect time."""
        return window_from_codes(
            self.windowstart, self.windowlength, self.resolution == 1, extended, long_range
        )


@dataclass(frozen=True)
class FrameHeader:
    """DDF_04 frame header; units in the module docstring.

    time: [s] since 1970-01-01 UTC, microsecond resolution on the wire.
    transmit: bit flags (:func:`transmit_flags`); configflags: bit0 classic
    windows, bit1 long-range model. receivergain [dB]; degc1/degc2 [degC].
    replies: command reply lines (:func:`pack_replies`), at most 255 bytes.
    rays: hilsim's elevation rays per beam this frame was rendered with (0: not stated),
        at ``RAYS_OFFSET`` (protocols/ddf-stream.md).
    """

    framenumber: int = 0
    time: float = 0.0
    version: bytes = SIGNATURE
    status: int = 0
    transmit: int = TRANSMIT_HF | TRANSMIT_ENABLE
    windowstart: int = 2
    windowlength: int = 2
    threshold: int = 0
    intensity: int = 0
    receivergain: int = 20
    degc1: int = 0
    degc2: int = 0
    humidity: int = 0
    focus: int = 0
    battery: int = 0
    status1: str = ""
    status2: str = ""
    panwcom: float = 0.0
    tiltwcom: float = 0.0
    velocity: float = 0.0
    depth: float = 0.0
    altitude: float = 0.0
    pitch: float = 0.0
    pitchrate: float = 0.0
    roll: float = 0.0
    rollrate: float = 0.0
    heading: float = 0.0
    headingrate: float = 0.0
    sonarpan: float = 0.0
    sonartilt: float = 0.0
    sonarroll: float = 0.0
    latitude: float = 0.0
    longitude: float = 0.0
    sonarposition: float = 0.0
    configflags: int = 0
    replies: bytes = b""
    rays: int = 0

    @property
    def high_freq(self) -> bool:
        return bool(self.transmit & TRANSMIT_HF)

    @property
    def window_m(self) -> tuple[float, float]:
        """(start [m], length [m]) from the codes, transmit and configflags."""
        return window_from_codes(
            self.windowstart,
            self.windowlength,
            self.high_freq,
            extended=not self.configflags & CONFIG_CLASSIC,
            long_range=bool(self.configflags & CONFIG_LONG_RANGE),
        )


# Layouts: (field, struct code) in wire order, packed little-endian.
_FILE_LAYOUT: Final = (
    ("version", "4s"), ("numframes", "i"), ("framerate", "i"), ("resolution", "i"),
    ("numbeams", "i"), ("samplerate", "f"), ("samplesperchannel", "i"),
    ("receivergain", "i"), ("windowstart", "i"), ("windowlength", "i"),
    ("reverse", "i"), ("serialnumber", "i"), ("date", "32s"), ("idstring", "256s"),
    ("id1", "i"), ("id2", "i"), ("id3", "i"), ("id4", "i"), ("startframe", "i"),
    ("endframe", "i"), ("timelapse", "i"), ("recordinterval", "i"),
    ("radioseconds", "i"), ("frameinterval", "i"), ("flags", "i"), ("auxflags", "i"),
    ("sspd", "i"), ("flags3d", "i"),
)  # fmt: skip
_CALENDAR = ("year", "month", "day", "hour", "minute", "second", "hsecond")
_FRAME_LAYOUT: Final = (
    ("framenumber", "i"), ("frametime", "Q"), ("version", "4s"), ("status", "i"),
    *((name, "i") for name in _CALENDAR),
    ("transmit", "i"), ("windowstart", "i"), ("windowlength", "i"), ("threshold", "i"),
    ("intensity", "i"), ("receivergain", "i"), ("degc1", "i"), ("degc2", "i"),
    ("humidity", "i"), ("focus", "i"), ("battery", "i"), ("status1", "16s"),
    ("status2", "8s"), ("panwcom", "f"), ("tiltwcom", "f"), ("velocity", "f"),
    ("depth", "f"), ("altitude", "f"), ("pitch", "f"), ("pitchrate", "f"), ("roll", "f"),
    ("rollrate", "f"), ("heading", "f"), ("headingrate", "f"), ("sonarpan", "f"),
    ("sonartilt", "f"), ("sonarroll", "f"), ("latitude", "d"), ("longitude", "d"),
    ("sonarposition", "f"), ("configflags", "i"),
)  # fmt: skip
_FILE_STRUCT: Final = struct.Struct("<" + "".join(code for _, code in _FILE_LAYOUT))
_FRAME_STRUCT: Final = struct.Struct("<" + "".join(code for _, code in _FRAME_LAYOUT))
assert _FILE_STRUCT.size == 392 and _FRAME_STRUCT.size == 196
_EPOCH: Final = datetime(1970, 1, 1, tzinfo=timezone.utc)


def _check(kind: str, name: str, code: str, value: object) -> object:
    """Validate one value for its struct code; returns the value to pack."""
    where = f"{kind}.{name}"
    if code in ("i", "Q"):  # numpy integers welcome
        low, high = (_I32_MIN, _I32_MAX) if code == "i" else (0, 2**64 - 1)
        if not isinstance(value, numbers.Integral) or not low <= int(value) <= high:
            raise ValueError(f"{where}={value!r} is not an {'int32' if code == 'i' else 'uint64'}")
        return int(value)
    if code in ("f", "d"):  # numpy floats welcome
        if not isinstance(value, numbers.Real):
            raise ValueError(f"{where}={value!r} is not a number")
        number = float(value)
        if code == "f" and math.isfinite(number) and abs(number) > _F32_MAX:
            raise ValueError(f"{where}={value!r} does not fit a float32")
        return number
    if name == "version":
        if not isinstance(value, bytes):
            raise ValueError(f"{where} must be bytes")
        return value
    size = int(code[:-1])  # an "Ns" text field
    if not isinstance(value, str):
        raise ValueError(f"{where} must be str")
    try:
        raw = value.encode("ascii")
    except UnicodeEncodeError:
        raise ValueError(f"{where}={value!r} is not ASCII") from None
    if b"\0" in raw or len(raw) >= size:
        raise ValueError(f"{where} holds at most {size - 1} ASCII characters, no NUL")
    return raw


def _text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("ascii", errors="replace")


def encode_file_header(h: FileHeader) -> bytes:
    """FileHeader -> exactly 1024 bytes, starting with ``DDF\\x04``."""
    values = [
        SIGNATURE if name == "version" else _check("FileHeader", name, code, getattr(h, name))
        for name, code in _FILE_LAYOUT
    ]
    return _FILE_STRUCT.pack(*values).ljust(FILE_HEADER_SIZE, b"\0")


def _signature_problem(prefix: bytes) -> str | None:
    """Why ``prefix`` (up to 4 bytes) cannot start a DDF_04 stream, or None."""
    n = min(len(prefix), 4)
    if prefix[:n] == SIGNATURE[:n]:
        return None
    if n == 4 and prefix[:3] == b"DDF":
        extra = " (DDF version 5 is ARIS)" if prefix[3] == 5 else ""
        return f"DDF version {prefix[3]} is not supported, only version 4{extra}"
    return f"not a DDF version 4 stream: starts {prefix[:n].hex(' ')}, expected 44 44 46 04 ('DDF\\x04')"


def decode_file_header(data: bytes) -> FileHeader:
    """The first 1024 bytes of ``data`` -> FileHeader; ProtocolError if bad."""
    problem = _signature_problem(bytes(data[:4]))
    if problem:
        raise ProtocolError(problem)
    if len(data) < FILE_HEADER_SIZE:
        raise ProtocolError(f"file header needs {FILE_HEADER_SIZE} bytes, got {len(data)}")
    values = dict(zip((n for n, _ in _FILE_LAYOUT), _FILE_STRUCT.unpack_from(data)))
    del values["version"]
    for name in ("date", "idstring"):
        values[name] = _text(values[name])
    return FileHeader(**values)


def _split_time(t: float) -> tuple[int, tuple[int, ...]]:
    """[s] since epoch -> (microseconds, UTC calendar fields)."""
    if not (math.isfinite(t) and t >= 0.0):
        raise ValueError(f"FrameHeader.time={t!r} must be finite and >= 0 (s since 1970 UTC)")
    us = round(t * 1_000_000)
    try:
        d = _EPOCH + timedelta(microseconds=us)
    except OverflowError:
        raise ValueError(f"FrameHeader.time={t!r} is beyond year 9999") from None
    return us, (d.year, d.month, d.day, d.hour, d.minute, d.second, d.microsecond // 10_000)


def _join_time(us: int, cal: Sequence[int]) -> float:
    """frametime [us] and calendar fields -> [s]; frametime wins if they agree."""
    year, month, day, hour, minute, second, hsecond = cal
    try:
        datetime(year, month, day, hour, minute, second)
        if not 0 <= hsecond <= 99:
            raise ValueError
    except ValueError:
        return us / 1_000_000
    centis = calendar.timegm((year, month, day, hour, minute, second)) * 100 + hsecond
    if us // 10_000 == centis:
        return us / 1_000_000
    return centis / 100  # a foreign file whose frametime means something else


def encode_frame_header(h: FrameHeader) -> bytes:
    """FrameHeader -> exactly 1024 bytes (replies at bytes 768..1023)."""
    if len(h.version) != 4:
        raise ValueError("FrameHeader.version must be 4 bytes")
    if len(h.replies) >= REPLY_AREA_SIZE or b"\0" in h.replies:
        raise ValueError(f"FrameHeader.replies holds at most {REPLY_AREA_SIZE - 1} bytes, no NUL")
    us, cal = _split_time(h.time)
    wire = {f.name: getattr(h, f.name) for f in fields(h)}
    wire.update(zip(_CALENDAR, cal), frametime=us)
    values = [_check("FrameHeader", n, c, wire[n]) for n, c in _FRAME_LAYOUT]
    out = bytearray(FRAME_HEADER_SIZE)
    _FRAME_STRUCT.pack_into(out, 0, *values)
    struct.pack_into("<i", out, RAYS_OFFSET, _check("FrameHeader", "rays", "i", h.rays))
    out[REPLY_AREA_OFFSET : REPLY_AREA_OFFSET + len(h.replies)] = h.replies
    return bytes(out)


def decode_frame_header(data: bytes) -> FrameHeader:
    """The first 1024 bytes of ``data`` -> FrameHeader (any field values)."""
    if len(data) < FRAME_HEADER_SIZE:
        raise ProtocolError(f"frame header needs {FRAME_HEADER_SIZE} bytes, got {len(data)}")
    values = dict(zip((n for n, _ in _FRAME_LAYOUT), _FRAME_STRUCT.unpack_from(data)))
    cal = [values.pop(name) for name in _CALENDAR]
    values["time"] = _join_time(values.pop("frametime"), cal)
    for name in ("status1", "status2"):
        values[name] = _text(values[name])
    area = bytes(data[REPLY_AREA_OFFSET : REPLY_AREA_OFFSET + REPLY_AREA_SIZE])
    values["replies"] = area.split(b"\0", 1)[0]
    values["rays"] = struct.unpack_from("<i", data, RAYS_OFFSET)[0]
    return FrameHeader(**values)


# ------------------------------------------------------------------ frames

Samples = npt.NDArray[np.uint8]  # (n_samples, n_beams), sim order: beam 0 = port


def frame_bytes(header: FileHeader) -> int:
    """Bytes per frame (header + samples) for a stream; ProtocolError if absurd."""
    if not 1 <= header.numbeams <= MAX_NUMBEAMS:
        raise ProtocolError(f"numbeams {header.numbeams} out of range 1..{MAX_NUMBEAMS}")
    if not 1 <= header.samplesperchannel <= MAX_SAMPLES_PER_CHANNEL:
        raise ProtocolError(
            f"samplesperchannel {header.samplesperchannel} out of range"
            f" 1..{MAX_SAMPLES_PER_CHANNEL}"
        )
    return FRAME_HEADER_SIZE + header.numbeams * header.samplesperchannel


def encode_frame(header: FrameHeader, samples: Samples) -> bytes:
    """Frame header + samples on the wire; ``samples`` (n_samples, n_beams) uint8.

    Sim beam b goes to wire beam n_beams-1-b; byte index = sample*n_beams + beam.
    """
    if not isinstance(samples, np.ndarray) or samples.dtype != np.uint8 or samples.ndim != 2:
        raise ValueError("samples must be a 2-D uint8 array (n_samples, n_beams)")
    wire = np.ascontiguousarray(samples[:, ::-1])
    return encode_frame_header(header) + wire.tobytes()


def decode_frame(data: bytes, numbeams: int, samplesperchannel: int) -> tuple[FrameHeader, Samples]:
    """One wire frame -> (header, samples (samplesperchannel, numbeams) in sim order)."""
    expected = FRAME_HEADER_SIZE + numbeams * samplesperchannel
    if len(data) != expected:
        raise ProtocolError(f"frame needs {expected} bytes, got {len(data)}")
    wire = np.frombuffer(data, np.uint8, numbeams * samplesperchannel, FRAME_HEADER_SIZE)
    samples = wire.reshape(samplesperchannel, numbeams)[:, ::-1].copy()
    return decode_frame_header(data), samples


# ------------------------------------------------------- stream reader/writer




@dataclass(frozen=True)
class FileHeaderEvent:
    header: FileHeader


@dataclass(frozen=True, eq=False)
class FrameEvent:
    """One frame; samples (samplesperchannel, numbeams) uint8 in sim order."""

    header: FrameHeader
    samples: Samples

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, FrameEvent):
            return NotImplemented
        return self.header == other.header and np.array_equal(self.samples, other.samples)


@dataclass(frozen=True)
class EndOfStream:
    """The peer closed; trailing_bytes of an incomplete last frame were dropped."""

    trailing_bytes: int = 0


DdfEvent = Union[FileHeaderEvent, FrameEvent, EndOfStream]


class DdfReader:
    """Incremental DDF_04 stream decoder (client side, recordings).

    ``receive_data(bytes)`` then ``next_event()`` until NEED_DATA;
    ``receive_data(b"")`` marks the end of the stream. Events: one
    FileHeaderEvent, a FrameEvent per frame, then EndOfStream after the end.
    A bad signature, an absurd frame size or an end inside the file header
    raises ProtocolError, now and on every later call (no resync: DDF frames
    carry no marker). The bytes held between events never exceed one frame
    (<= 1024 + MAX_NUMBEAMS x MAX_SAMPLES_PER_CHANNEL) beyond what the caller
    fed since its last drain.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._pos = 0
        self._eof = False
        self._end: EndOfStream | None = None
        self._error: ProtocolError | None = None
        self.file_header: FileHeader | None = None
        self._frame_size = 0

    @property
    def buffered_bytes(self) -> int:
        return len(self._buf) - self._pos

    def receive_data(self, data: bytes) -> None:
        if self._eof:
            if data:
                raise ValueError("receive_data after the end of the stream")
            return
        if not data:
            self._eof = True
            return
        if self._pos and 2 * self._pos >= len(self._buf):
            del self._buf[: self._pos]
            self._pos = 0
        self._buf += data

    def next_event(self) -> DdfEvent | NeedData:
        if self._error is not None:
            raise self._error
        try:
            return self._next()
        except ProtocolError as exc:
            self._error = exc
            raise

    def _take(self, n: int) -> bytes:
        chunk = bytes(self._buf[self._pos : self._pos + n])
        self._pos += n
        return chunk

    def _next(self) -> DdfEvent | NeedData:
        avail = self.buffered_bytes
        if self._end is not None:
            return self._end
        if self.file_header is None:
            problem = _signature_problem(bytes(self._buf[self._pos : self._pos + 4]))
            if problem:
                raise ProtocolError(problem)
            if avail < FILE_HEADER_SIZE:
                if self._eof:
                    raise ProtocolError(
                        f"stream ended after {avail} bytes, inside the 1024-byte file header"
                    )
                return NEED_DATA
            header = decode_file_header(self._take(FILE_HEADER_SIZE))
            self._frame_size = frame_bytes(header)
            self.file_header = header
            return FileHeaderEvent(header)
        if avail < self._frame_size:
            if self._eof:
                self._end = EndOfStream(avail)
                self._buf.clear()
                self._pos = 0
                return self._end
            return NEED_DATA
        frame_header, samples = decode_frame(
            self._take(self._frame_size), self.file_header.numbeams,
            self.file_header.samplesperchannel,
        )  # fmt: skip
        return FrameEvent(frame_header, samples)


class DdfWriter:
    """Encoder for the server and recorders: ``send(event) -> bytes``.

    The first event must be a FileHeaderEvent; every FrameEvent's samples
    must then have the shape (samplesperchannel, numbeams). Misuse raises
    ValueError.
    """

    def __init__(self) -> None:
        self.file_header: FileHeader | None = None

    def send(self, event: FileHeaderEvent | FrameEvent) -> bytes:
        if isinstance(event, FileHeaderEvent):
            if self.file_header is not None:
                raise ValueError("the file header was already sent")
            frame_bytes(event.header)
            data = encode_file_header(event.header)
            self.file_header = event.header
            return data
        if self.file_header is None:
            raise ValueError("send a FileHeaderEvent before the first frame")
        shape = (self.file_header.samplesperchannel, self.file_header.numbeams)
        if event.samples.shape != shape:
            raise ValueError(f"frame samples shape {event.samples.shape} != {shape}")
        return encode_frame(event.header, event.samples)
