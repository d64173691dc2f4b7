"""ArduPilot SITL's "JSON" physics backend (sans-I/O): servo packets in, state replies out.

Facts (``shared/reference/ardupilot-json.md``; ArduPilot ``libraries/SITL/SIM_JSON.{h,cpp}``
and ``libraries/SITL/examples/JSON/readme.md``):

- Over UDP, ArduPilot sends one servo packet per physics step, little-endian,
  packed: u16 magic (18458 = 16 channels, 29569 = 32 channels), u16 frame_rate
  [Hz], u32 frame_count, then u16 PWM [us] per servo output, output 1 first
  (40 or 72 bytes in all). The physics answers each packet to its source.
- The reply is one JSON object between newlines. ArduPilot's parser finds each
  key by substring search (a section such as ``imu`` first, then the key after
  it), skips the key and the ``":`` after it and reads the value there: a number
  with ``atof``/``strtoull``, a vector with ``sscanf("[%f, %f, %f]")`` (the
  bracket must follow the colon at once). So the reply is compact JSON, no key
  contains another key's name, every number is finite, and ``no_time_sync`` is
  the integer 1 (``strtoull`` reads ``true`` as 0).
- A reply that does not parse stays in ArduPilot's 65 kB buffer for good: the
  encoder never produces one (non-finite required values raise ``ValueError``,
  our bug, never a malformed datagram; a non-finite range is left out).

Datagrams keep their boundaries, so decoding is per datagram:
:func:`decode_servo` returns a :class:`ServoPacket` or a :class:`BadFrame`;
:class:`ServoDecoder` offers the same through the codec contract
(``receive_data`` takes one whole datagram). :func:`encode_reply` builds the
reply bytes.
"""

from __future__ import annotations

import math
import struct
from collections import deque
from dataclasses import dataclass
from typing import Deque, Sequence, Union

from hilsim.protocols.codec import NEED_DATA, BadFrame, NeedData

MAGIC_16 = 18458
MAGIC_32 = 29569
CHANNELS = {MAGIC_16: 16, MAGIC_32: 32}
HEADER = struct.Struct("<HHI")
SIZE = {MAGIC_16: HEADER.size + 2 * 16, MAGIC_32: HEADER.size + 2 * 32}  # 40, 72 bytes
_PWM = {MAGIC_16: struct.Struct("<16H"), MAGIC_32: struct.Struct("<32H")}
_BAD_PREFIX = 64  # bytes of a bad datagram kept in its BadFrame


@dataclass(frozen=True)
class ServoPacket:
    """One servo packet: frame_rate [Hz] (the step ArduPilot asks for is 1 / frame_rate),
    frame_count [1], pwm (16,) or (32,) [us] per servo output (index 0 = output 1;
    0 = output off)."""

    frame_rate: int
    frame_count: int
    pwm: tuple[int, ...]

    @property
    def channels(self) -> int:
        """16 or 32."""
        return len(self.pwm)

    @property
    def step(self) -> float:
        """[s] the physics step ArduPilot asks for."""
        return 1.0 / self.frame_rate


def decode_servo(datagram: bytes) -> Union[ServoPacket, BadFrame]:
    """One datagram -> :class:`ServoPacket`, or :class:`BadFrame` (too short, unknown
    magic, wrong length for its magic, frame_rate 0). Never raises on peer input."""
    n = len(datagram)
    if n < HEADER.size:
        return BadFrame(f"short datagram ({n} bytes)", bytes(datagram[:_BAD_PREFIX]))
    magic, rate, count = HEADER.unpack_from(datagram, 0)
    size = SIZE.get(magic)
    if size is None:
        return BadFrame(f"unknown magic {magic}", bytes(datagram[:_BAD_PREFIX]))
    if n != size:
        return BadFrame(f"{n} bytes for magic {magic} ({size} expected)", bytes(datagram[:_BAD_PREFIX]))
    if rate == 0:
        return BadFrame("frame_rate 0", bytes(datagram[:_BAD_PREFIX]))
    return ServoPacket(rate, count, _PWM[magic].unpack_from(datagram, HEADER.size))


def encode_servo(pwm: Sequence[int], frame_count: int, frame_rate: int = 1200) -> bytes:
    """A servo packet as ArduPilot sends it (16 channels if ``len(pwm) <= 16``, else 32;
    missing outputs are 0). For tests and benchmarks."""
    channels = 16 if len(pwm) <= 16 else 32
    if len(pwm) > 32:
        raise ValueError("at most 32 servo outputs")
    magic = MAGIC_16 if channels == 16 else MAGIC_32
    values = list(pwm) + [0] * (channels - len(pwm))
    return HEADER.pack(magic, frame_rate, frame_count & 0xFFFFFFFF) + _PWM[magic].pack(*values)


class ServoDecoder:
    """The codec contract over datagrams: each ``receive_data`` call is one whole datagram;
    ``next_event`` gives :class:`ServoPacket` or :class:`BadFrame` per datagram, in order,
    then :data:`NEED_DATA`. At most ``max_pending`` undrained datagrams are kept (the
    oldest are dropped and counted in ``dropped``)."""

    def __init__(self, max_pending: int = 64):
        self._pending: Deque[bytes] = deque()
        self.max_pending = max_pending
        self.dropped = 0

    @property
    def buffered_bytes(self) -> int:
        return sum(len(d) for d in self._pending)

    def receive_data(self, data: bytes) -> None:
        if not data:
            return
        if len(self._pending) >= self.max_pending:
            self._pending.popleft()
            self.dropped += 1
        self._pending.append(bytes(data[:SIZE[MAGIC_32] + 1]))  # longer ones are bad anyway

    def next_event(self) -> Union[ServoPacket, BadFrame, NeedData]:
        if not self._pending:
            return NEED_DATA
        return decode_servo(self._pending.popleft())


def _num(x: float, key: str) -> str:
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"{key}: non-finite value {x!r} (a reply must never carry NaN or inf)")
    if x == 0.0:
        return "0"
    return repr(x)


def _vec(values: Sequence[float], n: int, key: str) -> str:
    if len(values) != n:
        raise ValueError(f"{key}: expected {n} values, got {len(values)}")
    return "[" + ",".join([_num(v, key) for v in values]) + "]"


def encode_reply(timestamp: float, gyro: Sequence[float], accel_body: Sequence[float],
                 position: Sequence[float], velocity: Sequence[float], quaternion: Sequence[float],
                 rng_1: float | None = None, no_time_sync: bool = False) -> bytes:
    """The JSON state reply, newline before and after, compact.

    timestamp [s] simulation time; gyro (3,) [rad/s] body rates (p, q, r);
    accel_body (3,) [m/s^2] specific force in the body frame (level at rest:
    (0, 0, -g)); position (3,) [m] NED from home; velocity (3,) [m/s] NED;
    quaternion (4,) [1] (w, x, y, z) body -> NED; rng_1 [m] the first rangefinder
    (left out when None or not finite: no reading); no_time_sync: ask ArduPilot to
    run as fast as the physics answers. Raises ``ValueError`` for a non-finite or
    missing required value (our bug, never sent)."""
    parts = [
        '{"timestamp":', _num(timestamp, "timestamp"),
        ',"imu":{"gyro":', _vec(gyro, 3, "gyro"), ',"accel_body":', _vec(accel_body, 3, "accel_body"),
        '},"position":', _vec(position, 3, "position"),
        ',"velocity":', _vec(velocity, 3, "velocity"),
        ',"quaternion":', _vec(quaternion, 4, "quaternion"),
    ]
    if rng_1 is not None and math.isfinite(rng_1):
        parts += [',"rng_1":', _num(rng_1, "rng_1")]
    if no_time_sync:
        parts.append(',"no_time_sync":1')
    parts.append("}\n")
    return ("\n" + "".join(parts)).encode("ascii")


def quaternion_from_euler(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) [1] of the Z-Y-X rotation body -> NED from roll, pitch, yaw [rad]
    (ArduPilot's ``Quaternion::from_euler``), w >= 0."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    w = cr * cp * cy + sr * sp * sy
    x = sr * cp * cy - cr * sp * sy
    y = cr * sp * cy + sr * cp * sy
    z = cr * cp * sy - sr * sp * cy
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    return w, x, y, z
