"""Blueprint Subsea Oculus M-series: status datagram, SimpleFire, SimplePingResult (sans-I/O).

The spec is ``protocols/oculus.md`` (layouts from ``reference/sonar-protocols.md``
section 3). All integers little-endian, structures packed.

* UDP status (sonar -> anyone, about 1 Hz): a 142-byte :class:`Status`.
* TCP 52100, client -> sonar: :class:`Fire` (SimpleFire v1 = 53 bytes, v2 = 89 bytes).
* TCP, sonar -> client: :class:`PingResult` (SimplePingResult v1 = 122-byte
  struct, v2 = 202-byte struct, then the int16 bearings table [0.01 deg], then
  the image at ``image_offset``: ``n_ranges`` rows of ``n_beams`` samples, each
  row led by a float32 gain when the fire flags ask for gains).
  Invariant: ``16 + payload_size == image_offset + image_size == message_size``.

Beam order. Beam 0 of the image is the most negative bearing (port), as in the
simulator's frames, so no reversal is needed. Ranges start at 0: row ``i``
covers ``[i dr, (i + 1) dr)`` with ``dr = range_resolution``.

Peer input never raises here: :func:`decode_message` and :func:`decode_status`
return a :class:`BadMessage` for bytes that are not a valid message, and
:class:`OculusReader` turns a byte stream into events, skipping junk
(:class:`Junk`) and resynchronising on the ``53 4F`` id. Our own misuse
(encoding out-of-range values) raises ValueError.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Final, Union

import numpy as np
import numpy.typing as npt

from hilsim.protocols import codec
from hilsim.protocols.codec import NEED_DATA, NeedData

# --------------------------------------------------------------- constants

OCULUS_ID: Final = 0x4F53  # bytes 53 4F on the wire
ID_BYTES: Final = b"\x53\x4f"
HEADER_SIZE: Final = 16
STATUS_SIZE: Final = 142
STATUS_PORT: Final = 52102  # UDP, fixed on real devices
DATA_PORT: Final = 52100  # TCP, fixed on real devices

MSG_STATUS: Final = 0x00  # not given by our sources; clients tell the status by port and size
MSG_FIRE: Final = 0x15
MSG_PING_RESULT: Final = 0x22
MSG_SIMPLE_PING_RESULT: Final = 0x23
MSG_USER_CONFIG: Final = 0x55
MSG_LOGS: Final = 0x80
MSG_DUMMY: Final = 0xFF

FIRE_V1_SIZE: Final = 53
FIRE_V2_SIZE: Final = 89
PING_V1_SIZE: Final = 122
PING_V2_SIZE: Final = 202

MODE_LF: Final = 1  # masterMode: low frequency, wide
MODE_HF: Final = 2  # high frequency, narrow

PING_RATE_NORMAL: Final = 0
PING_RATE_HIGH: Final = 1
PING_RATE_HIGHEST: Final = 2
PING_RATE_LOW: Final = 3
PING_RATE_LOWEST: Final = 4
PING_RATE_STANDBY: Final = 5
PING_RATE_HZ: Final = {0: 10.0, 1: 15.0, 2: 40.0, 3: 5.0, 4: 2.0, 5: 0.0}

FLAG_RANGE_METRES: Final = 0x01
FLAG_16BIT: Final = 0x02
FLAG_SEND_GAIN: Final = 0x04
FLAG_SIMPLE: Final = 0x08
FLAG_GAIN_ASSIST: Final = 0x10
FLAG_512_BEAMS: Final = 0x40
EXT_FLAG_32BIT: Final = 0x200

DATA_8BIT: Final = 0  # dataSize codes
DATA_16BIT: Final = 1
DATA_24BIT: Final = 2
DATA_32BIT: Final = 3
_DTYPES: Final[dict[int, np.dtype[np.unsignedinteger]]] = {0: np.dtype("<u1"), 1: np.dtype("<u2"), 3: np.dtype("<u4")}
_SAMPLE_BYTES: Final = {0: 1, 1: 2, 2: 3, 3: 4}

STATUS_MAIN_RUN: Final = 3  # status bits 0-2
STATUS_HIGH_TEMP: Final = 1 << 14
STATUS_OVER_TEMP: Final = 1 << 15
STATUS_TX_FAULT: Final = 1 << 16

PART_M750D: Final = 1032
PART_M1200D: Final = 1042

KNOWN_IDS: Final = frozenset({MSG_FIRE, MSG_PING_RESULT, MSG_SIMPLE_PING_RESULT, MSG_USER_CONFIG, MSG_LOGS,
                               MSG_DUMMY})
MAX_SERVER_PAYLOAD: Final = 4096  # client -> sonar messages are small
MAX_CLIENT_PAYLOAD: Final = 64 * 1024 * 1024  # a ping: <= 1024 beams x 65535 rows x 4 B ...

_HEADER = struct.Struct("<HHHHHIH")
_FIRE_BODY = struct.Struct("<BBBBBdddd")  # @16, 37 bytes
_FIRE_EXT = struct.Struct("<I8I")  # @53, v2 only, 36 bytes
_PING_V1 = struct.Struct("<IIddddIBdHHIII")  # @53
_PING_V2 = struct.Struct("<IIddddddddBdHH4IIII")  # @89
_STATUS = struct.Struct("<IHHI6I4s4s4s6s8dd")  # @16
assert _HEADER.size == HEADER_SIZE and _FIRE_BODY.size == 37 and _FIRE_EXT.size == 36
assert 53 + _PING_V1.size == PING_V1_SIZE and 89 + _PING_V2.size == PING_V2_SIZE
assert HEADER_SIZE + _STATUS.size == STATUS_SIZE

ImageArray = npt.NDArray[np.uint8] | npt.NDArray[np.uint16] | npt.NDArray[np.uint32]


# ------------------------------------------------------------------ values


@dataclass(frozen=True)
class Header:
    """The 16-byte message header (oculus id implied)."""

    msg_id: int
    payload_size: int
    src_device_id: int = 0
    dst_device_id: int = 0
    msg_version: int = 0
    spare: int = 0


@dataclass(frozen=True)
class Fire:
    """SimpleFire v1 (``version`` 0 or 1) or v2 (``version`` 2).

    master_mode: 1 LF wide / 2 HF narrow; ping_rate: 0..5 (:data:`PING_RATE_HZ`,
    5 = standby); flags: FLAG_* bits. range: [m] with FLAG_RANGE_METRES, else
    percent of the maximum range; gain: percent [0, 100]; speed_of_sound [m/s]
    (0 = let the sonar compute it); salinity [ppt]. ext_flags: v2 only.
    """

    master_mode: int = MODE_HF
    ping_rate: int = PING_RATE_NORMAL
    network_speed: int = 0xFF
    gamma: int = 127
    flags: int = FLAG_RANGE_METRES | FLAG_SIMPLE
    range: float = 10.0
    gain: float = 50.0
    speed_of_sound: float = 0.0
    salinity: float = 0.0
    version: int = 2
    ext_flags: int = 0
    reserved: tuple[int, ...] = (0,) * 8
    src_device_id: int = 0
    dst_device_id: int = 0

    @property
    def data_size(self) -> int:
        """The dataSize code a ping answering this fire carries."""
        if self.version == 2 and self.ext_flags & EXT_FLAG_32BIT:
            return DATA_32BIT
        return DATA_16BIT if self.flags & FLAG_16BIT else DATA_8BIT

    @property
    def send_gain(self) -> bool:
        return bool(self.flags & FLAG_SEND_GAIN)

    @property
    def range_in_metres(self) -> bool:
        return bool(self.flags & FLAG_RANGE_METRES)

    @property
    def n_beams_requested(self) -> int:
        return 512 if self.flags & FLAG_512_BEAMS else 256

    @property
    def ping_rate_hz(self) -> float:
        """[Hz]; an unknown code counts as normal (10 Hz), standby as 0."""
        return PING_RATE_HZ.get(self.ping_rate, PING_RATE_HZ[PING_RATE_NORMAL])


@dataclass(frozen=True, eq=False)
class PingResult:
    """A SimplePingResult (``fire.version`` 2 -> v2 layout, else v1).

    image: (n_ranges, n_beams) uint8/uint16/uint32 by ``data_size``; beam 0 = port.
    bearings: (n_beams,) int16 [0.01 deg], ascending. gains: (n_ranges,) float32
    per-row gains when ``fire.send_gain``, else None. Times: ping_start_time [s]
    (v1 carries a uint32 count, v2 a float64). range_resolution [m], frequency [Hz],
    temperature [degC], pressure [bar], heading/pitch/roll [deg] (v2 only).
    rays: hilsim's elevation rays per beam of the ping (v2 only, the first spare u32 @174;
    0: not stated). The size fields are recomputed by :func:`encode_ping_result`; decoded
    values keep what the peer sent.
    """

    fire: Fire
    image: ImageArray
    bearings: npt.NDArray[np.int16]
    range_resolution: float
    gains: npt.NDArray[np.float32] | None = None
    ping_id: int = 0
    status: int = 0
    frequency: float = 0.0
    temperature: float = 0.0
    pressure: float = 0.0
    heading: float = 0.0
    pitch: float = 0.0
    roll: float = 0.0
    speed_of_sound_used: float = 1500.0
    ping_start_time: float = 0.0
    src_device_id: int = 0
    dst_device_id: int = 0
    image_offset: int = 0
    image_size: int = 0
    message_size: int = 0
    rays: int = 0

    @property
    def n_ranges(self) -> int:
        return int(self.image.shape[0])

    @property
    def n_beams(self) -> int:
        return int(self.image.shape[1])

    @property
    def data_size(self) -> int:
        return {1: DATA_8BIT, 2: DATA_16BIT, 4: DATA_32BIT}[self.image.dtype.itemsize]

    @property
    def bearings_deg(self) -> npt.NDArray[np.float64]:
        return np.asarray(self.bearings, dtype=np.float64) * 0.01

    @property
    def ranges(self) -> npt.NDArray[np.float64]:
        """(n_ranges,) [m] row centres; ranges start at 0."""
        return np.asarray((np.arange(self.n_ranges) + 0.5) * self.range_resolution, dtype=np.float64)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PingResult):
            return NotImplemented
        a, b = self.__dict__, other.__dict__
        for k in a:
            x, y = a[k], b[k]
            if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
                if x is None or y is None or not np.array_equal(x, y) or x.dtype != y.dtype:
                    return False
            elif x != y:
                return False
        return True


@dataclass(frozen=True)
class Status:
    """The 142-byte status datagram. ip, ip_mask, connected_ip: dotted quads."""

    device_id: int = 0
    device_type: int = 1
    part_number: int = PART_M750D
    status: int = STATUS_MAIN_RUN
    version_info: tuple[int, ...] = (0,) * 6
    ip: str = "127.0.0.1"
    ip_mask: str = "255.0.0.0"
    connected_ip: str = "0.0.0.0"
    mac: bytes = b"\x00" * 6
    temperatures: tuple[float, ...] = (0.0,) * 8  # [degC]
    pressure: float = 0.0  # [bar]
    src_device_id: int = 0
    msg_id: int = MSG_STATUS

    @property
    def main_run(self) -> bool:
        return self.status & 0x7 == STATUS_MAIN_RUN


@dataclass(frozen=True)
class OtherMessage:
    """A well-framed message we do not interpret (dummy 0xFF, logs, user config ...)."""

    header: Header
    payload: bytes


@dataclass(frozen=True)
class BadMessage(codec.BadInput):
    """A message with a valid frame whose contents are not valid; counted, then ignored."""

    msg_id: int = -1


class Junk(codec.CountedJunk):
    """``n_bytes`` skipped while looking for the next ``53 4F`` id."""

    DEFAULT_REASON = "bytes before the next 53 4F id"


@dataclass(frozen=True, init=False)
class Oversize(codec.Oversize):
    """A header announcing ``payload_size`` (``length``) beyond the reader's bound; only its id was dropped."""

    header: Header = Header(0, 0)

    def __init__(self, header: Header, reason: str = "payload size beyond the reader's bound") -> None:
        object.__setattr__(self, "reason", reason)
        object.__setattr__(self, "length", header.payload_size)
        object.__setattr__(self, "header", header)


Message = Union[Fire, PingResult, OtherMessage, BadMessage]
Event = Union[Fire, PingResult, OtherMessage, BadMessage, Junk, Oversize]


# ------------------------------------------------------------------ helpers


def _ip_bytes(ip: str) -> bytes:
    parts = ip.split(".")
    if len(parts) != 4 or not all(p.isdigit() and 0 <= int(p) <= 255 for p in parts):
        raise ValueError(f"not a dotted-quad IPv4 address: {ip!r}")
    return bytes(int(p) for p in parts)


def _ip_str(raw: bytes) -> str:
    return ".".join(str(b) for b in raw)


def encode_header(h: Header) -> bytes:
    return _HEADER.pack(OCULUS_ID, h.src_device_id, h.dst_device_id, h.msg_id, h.msg_version,
                        h.payload_size, h.spare)


def decode_header(data: bytes) -> Header | None:
    """The first 16 bytes -> Header, or None if too short or the id is wrong."""
    if len(data) < HEADER_SIZE:
        return None
    oid, src, dst, mid, ver, size, spare = _HEADER.unpack_from(data)
    if oid != OCULUS_ID:
        return None
    return Header(mid, size, src, dst, ver, spare)


# -------------------------------------------------------------------- status


def encode_status(s: Status) -> bytes:
    """Status -> exactly 142 bytes."""
    if len(s.version_info) != 6 or len(s.temperatures) != 8 or len(s.mac) != 6:
        raise ValueError("version_info needs 6 values, temperatures 8, mac 6 bytes")
    head = encode_header(Header(s.msg_id, STATUS_SIZE - HEADER_SIZE, s.src_device_id))
    body = _STATUS.pack(s.device_id, s.device_type, s.part_number, s.status, *s.version_info,
                        _ip_bytes(s.ip), _ip_bytes(s.ip_mask), _ip_bytes(s.connected_ip), bytes(s.mac),
                        *s.temperatures, s.pressure)
    return head + body


def decode_status(data: bytes) -> Status | BadMessage:
    """A status datagram -> Status, or BadMessage (wrong size or id)."""
    if len(data) != STATUS_SIZE:
        return BadMessage(f"status datagram has {len(data)} bytes, expected {STATUS_SIZE}")
    h = decode_header(data)
    if h is None:
        return BadMessage("status datagram does not start with the Oculus id 53 4F")
    v = _STATUS.unpack_from(data, HEADER_SIZE)
    return Status(device_id=v[0], device_type=v[1], part_number=v[2], status=v[3],
                  version_info=tuple(v[4:10]), ip=_ip_str(v[10]), ip_mask=_ip_str(v[11]),
                  connected_ip=_ip_str(v[12]), mac=v[13], temperatures=tuple(v[14:22]),
                  pressure=v[22], src_device_id=h.src_device_id, msg_id=h.msg_id)


# ---------------------------------------------------------------------- fire


def _fire_body(f: Fire) -> bytes:
    body = _FIRE_BODY.pack(f.master_mode, f.ping_rate, f.network_speed, f.gamma, f.flags,
                           f.range, f.gain, f.speed_of_sound, f.salinity)
    if f.version == 2:
        if len(f.reserved) != 8:
            raise ValueError("Fire.reserved needs 8 values")
        body += _FIRE_EXT.pack(f.ext_flags, *f.reserved)
    return body


def encode_fire(f: Fire) -> bytes:
    """Fire -> 53 bytes (version 0/1) or 89 bytes (version 2)."""
    if f.version not in (0, 1, 2):
        raise ValueError(f"fire version must be 0, 1 or 2, got {f.version}")
    body = _fire_body(f)
    return encode_header(Header(MSG_FIRE, len(body), f.src_device_id, f.dst_device_id, f.version)) + body


def _decode_fire_body(h: Header, data: bytes) -> Fire:
    mm, rate, speed, gamma, flags, rng, gain, sos, sal = _FIRE_BODY.unpack_from(data, HEADER_SIZE)
    ext, reserved = 0, (0,) * 8
    if h.msg_version == 2:
        ext, *res = _FIRE_EXT.unpack_from(data, FIRE_V1_SIZE)
        reserved = tuple(res)
    return Fire(mm, rate, speed, gamma, flags, rng, gain, sos, sal, h.msg_version, ext, reserved,
                h.src_device_id, h.dst_device_id)


def _decode_fire(h: Header, data: bytes) -> Fire | BadMessage:
    want = FIRE_V2_SIZE if h.msg_version == 2 else FIRE_V1_SIZE
    if len(data) != want:
        return BadMessage(f"fire v{h.msg_version} has {len(data)} bytes, expected {want}", MSG_FIRE)
    f = _decode_fire_body(h, data)
    for name in ("range", "gain", "speed_of_sound", "salinity"):
        if not math.isfinite(getattr(f, name)):
            return BadMessage(f"fire {name} is not a finite number", MSG_FIRE)
    return f


# ---------------------------------------------------------------- ping result


def _row_bytes(n_beams: int, data_size: int, send_gain: bool) -> int:
    return n_beams * _SAMPLE_BYTES[data_size] + (4 if send_gain else 0)


def encode_ping_result(p: PingResult) -> bytes:
    """PingResult -> one SimplePingResult message (v2 layout if ``p.fire.version == 2``).

    The fire echo's flags decide the gain rows; the image dtype decides dataSize
    (it must agree with the fire: 16-bit flag <-> uint16, v2 32-bit flag <-> uint32).
    The image follows the bearings table directly.
    """
    f = p.fire
    img = p.image
    if img.ndim != 2 or img.dtype.itemsize not in (1, 2, 4) or img.dtype.kind != "u":
        raise ValueError("image must be a 2-D uint8/uint16/uint32 array (n_ranges, n_beams)")
    if p.data_size != f.data_size:
        raise ValueError(f"image dtype {img.dtype} does not match the fire flags (dataSize {f.data_size})")
    nr, nb = img.shape
    if not (1 <= nb <= 0xFFFF and 0 <= nr <= 0xFFFF):
        raise ValueError(f"image shape {img.shape} does not fit the uint16 counts")
    if p.bearings.shape != (nb,):
        raise ValueError(f"bearings must have shape ({nb},), got {p.bearings.shape}")
    v2 = f.version == 2
    struct_size = PING_V2_SIZE if v2 else PING_V1_SIZE
    image_offset = struct_size + 2 * nb
    rows = np.ascontiguousarray(img, dtype=img.dtype.newbyteorder("<"))
    if f.send_gain:
        gains = p.gains if p.gains is not None else np.ones(nr, np.float32)
        if gains.shape != (nr,):
            raise ValueError(f"gains must have shape ({nr},)")
        g = np.ascontiguousarray(gains, dtype="<f4").view(np.uint8).reshape(nr, 4)
        image = np.concatenate([g, rows.view(np.uint8).reshape(nr, -1)], axis=1).tobytes()
    else:
        image = rows.tobytes()
    image_size = len(image)
    message_size = image_offset + image_size
    head = encode_header(Header(MSG_SIMPLE_PING_RESULT, message_size - HEADER_SIZE, p.src_device_id,
                                p.dst_device_id, f.version))
    if v2:
        tail = _PING_V2.pack(p.ping_id, p.status, p.frequency, p.temperature, p.pressure, p.heading,
                             p.pitch, p.roll, p.speed_of_sound_used, p.ping_start_time, p.data_size,
                             p.range_resolution, nr, nb, p.rays, 0, 0, 0, image_offset, image_size,
                             message_size)
    else:
        start = int(p.ping_start_time) & 0xFFFFFFFF
        tail = _PING_V1.pack(p.ping_id, p.status, p.frequency, p.temperature, p.pressure,
                             p.speed_of_sound_used, start, p.data_size, p.range_resolution, nr, nb,
                             image_offset, image_size, message_size)
    bearings = np.ascontiguousarray(p.bearings, dtype="<i2").tobytes()
    return head + _fire_body(f) + tail + bearings + image


def _decode_ping(h: Header, data: bytes) -> PingResult | BadMessage:
    bad = lambda why: BadMessage(f"simple ping result: {why}", MSG_SIMPLE_PING_RESULT)  # noqa: E731
    v2 = h.msg_version == 2
    struct_size = PING_V2_SIZE if v2 else PING_V1_SIZE
    if len(data) < struct_size:
        return bad(f"{len(data)} bytes, shorter than the {struct_size}-byte v{2 if v2 else 1} struct")
    fire = _decode_fire_body(h, data)
    if v2:
        (ping_id, status, freq, temp, press, heading, pitch, roll, sos, start, ds, rres, nr, nb,
         _s0, _s1, _s2, _s3, ioff, isize, msize) = _PING_V2.unpack_from(data, FIRE_V2_SIZE)
    else:
        (ping_id, status, freq, temp, press, sos, start, ds, rres, nr, nb, ioff, isize,
         msize) = _PING_V1.unpack_from(data, FIRE_V1_SIZE)
        heading = pitch = roll = 0.0
        _s0 = 0
    if ds not in _DTYPES:
        return bad(f"dataSize {ds} not supported")
    if not HEADER_SIZE + h.payload_size == ioff + isize == msize == len(data):
        return bad(f"size invariant broken: 16 + payloadSize {h.payload_size}, imageOffset {ioff} +"
                   f" imageSize {isize}, messageSize {msize}, received {len(data)}")
    if ioff < struct_size + 2 * nb:
        return bad(f"imageOffset {ioff} overlaps the bearings table")
    send_gain = bool(fire.flags & FLAG_SEND_GAIN)
    row = _row_bytes(nb, ds, send_gain)
    if isize != nr * row:
        return bad(f"imageSize {isize} != nRanges {nr} x {row} bytes per row")
    bearings = np.frombuffer(data, "<i2", nb, struct_size).astype(np.int16)
    raw = np.frombuffer(data, np.uint8, isize, ioff).reshape(nr, row)
    gains = None
    if send_gain:
        gains = raw[:, :4].copy().view("<f4").reshape(nr).astype(np.float32)
        raw = raw[:, 4:]
    dtype = _DTYPES[ds]
    image = np.ascontiguousarray(raw).view(dtype).reshape(nr, nb).astype(dtype.newbyteorder("="))
    return PingResult(fire=fire, image=image, bearings=bearings, range_resolution=rres, gains=gains,
                      ping_id=ping_id, status=status, frequency=freq, temperature=temp, pressure=press,
                      heading=heading, pitch=pitch, roll=roll, speed_of_sound_used=sos,
                      ping_start_time=float(start), src_device_id=h.src_device_id,
                      dst_device_id=h.dst_device_id, image_offset=ioff, image_size=isize, rays=_s0,
                      message_size=msize)


def decode_message(data: bytes) -> Message:
    """One whole message (header + payload) -> Fire, PingResult, OtherMessage or BadMessage."""
    data = bytes(data)
    h = decode_header(data)
    if h is None:
        return BadMessage("not an Oculus message (too short or no 53 4F id)")
    if len(data) != HEADER_SIZE + h.payload_size:
        return BadMessage(f"message has {len(data)} bytes, header says {HEADER_SIZE + h.payload_size}", h.msg_id)
    if h.msg_id == MSG_FIRE:
        return _decode_fire(h, data)
    if h.msg_id == MSG_SIMPLE_PING_RESULT:
        return _decode_ping(h, data)
    if h.msg_id not in KNOWN_IDS:
        return BadMessage(f"unknown message id 0x{h.msg_id:02x}", h.msg_id)
    return OtherMessage(h, data[HEADER_SIZE:])


def encode_message(msg_id: int, payload: bytes = b"", version: int = 0, src_device_id: int = 0,
                   dst_device_id: int = 0) -> bytes:
    """Any message: header + ``payload`` (a dummy keep-alive is ``encode_message(MSG_DUMMY)``)."""
    return encode_header(Header(msg_id, len(payload), src_device_id, dst_device_id, version)) + payload


# -------------------------------------------------------------------- stream




@dataclass
class ReaderStats:
    messages: int = 0
    junk_bytes: int = 0
    bad: int = 0
    oversize: int = 0


class OculusReader(codec.ByteBuffer):
    """Incremental decoder of an Oculus TCP byte stream (either direction).

    ``receive_data(bytes)`` then ``next_event()`` until NEED_DATA. Bytes before
    the next ``53 4F`` id come out as one :class:`Junk` event; a header whose
    payload exceeds ``max_payload`` gives :class:`Oversize` and the reader
    resumes scanning right after its id (so a stalled huge "message" holds
    nothing); a framed message that is not valid (wrong size, broken
    invariant, unknown id) gives :class:`BadMessage` and the reader also
    resumes right after its id. So after any garbage, at most ``16 +
    max_payload`` bytes of valid messages are lost before the reader is in
    step again. Nothing raises on peer input. The buffer never holds more than
    ``16 + max_payload`` bytes plus what the caller fed since its last drain.
    """

    def __init__(self, max_payload: int = MAX_SERVER_PAYLOAD) -> None:
        super().__init__()
        self.max_payload = int(max_payload)
        self.stats = ReaderStats()

    def events(self) -> list[Event]:
        """Every event available now (drains the reader)."""
        out: list[Event] = []
        while True:
            ev = self.next_event()
            if ev is NEED_DATA:
                return out
            out.append(ev)

    def next_event(self) -> Event | NeedData:
        buf, pos = self._buf, self._pos
        idx = buf.find(ID_BYTES, pos)
        if idx < 0:
            # keep a trailing 0x53 that may start an id split across reads
            keep = 1 if len(buf) > pos and buf[-1] == ID_BYTES[0] else 0
            n = len(buf) - pos - keep
            if n > 0:
                self._pos = len(buf) - keep
                self.stats.junk_bytes += n
                return Junk(n)
            return NEED_DATA
        if idx > pos:
            self._pos = idx
            self.stats.junk_bytes += idx - pos
            return Junk(idx - pos)
        if len(buf) - pos < HEADER_SIZE:
            return NEED_DATA
        h = decode_header(bytes(buf[pos : pos + HEADER_SIZE]))
        assert h is not None  # the id matched
        if h.payload_size > self.max_payload:
            self._pos = pos + 2
            self.stats.oversize += 1
            return Oversize(h)
        end = pos + HEADER_SIZE + h.payload_size
        if len(buf) < end:
            return NEED_DATA
        msg = decode_message(bytes(buf[pos:end]))
        if isinstance(msg, BadMessage):
            # the frame may be a false start (a truncated message's header running into the
            # next one): drop only its id and look for the next one inside it
            self._pos = pos + 2
            self.stats.bad += 1
        else:
            self._pos = end
            self.stats.messages += 1
        return msg


# ------------------------------------------------------ helpers for devices


def bearings_from_azimuths(azimuths: npt.ArrayLike) -> npt.NDArray[np.int16]:
    """(n,) [rad] ascending -> int16 [0.01 deg] bearings table."""
    deg = np.degrees(np.asarray(azimuths, dtype=np.float64))
    return np.round(deg * 100.0).astype(np.int16)


def halve_beams(image: npt.NDArray[np.uint8], azimuths: npt.ArrayLike) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.float64]]:
    """Merge adjacent beam pairs: (n, 2m) image and (2m,) azimuths -> (n, m), (m,) (means)."""
    az = np.asarray(azimuths, dtype=np.float64)
    m = image.shape[1] // 2
    pairs = image[:, : 2 * m].reshape(image.shape[0], m, 2).astype(np.uint16)
    merged = ((pairs[:, :, 0] + pairs[:, :, 1] + 1) // 2).astype(np.uint8)
    return merged, az[: 2 * m].reshape(m, 2).mean(axis=1)


def widen_samples(image: npt.NDArray[np.uint8], data_size: int) -> ImageArray:
    """uint8 image -> the dtype of ``data_size``, full scale kept (x257 for 16 bit)."""
    if data_size == DATA_8BIT:
        return image
    if data_size == DATA_16BIT:
        return image.astype(np.uint16) * np.uint16(257)
    if data_size == DATA_32BIT:
        return image.astype(np.uint32) * np.uint32(16843009)
    raise ValueError(f"dataSize {data_size} not supported")


__all__ = [
    "BadMessage", "DATA_16BIT", "DATA_32BIT", "DATA_8BIT", "DATA_PORT", "Event", "Fire", "Header",
    "Junk", "MSG_DUMMY", "MSG_FIRE", "MSG_SIMPLE_PING_RESULT", "Message", "NEED_DATA", "OculusReader",
    "OtherMessage", "Oversize", "PingResult", "STATUS_PORT", "STATUS_SIZE", "Status",
    "bearings_from_azimuths", "decode_header", "decode_message", "decode_status", "encode_fire",
    "encode_header", "encode_message", "encode_ping_result", "encode_status", "halve_beams",
    "widen_samples",
]
