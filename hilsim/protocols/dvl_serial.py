"""Water Linked DVL A50/A125 serial protocol, sans-I/O (the device's side).

Spec: ``protocols/dvl-serial.md``, from Water Linked's "DVL A50/A125 serial
protocol" (waterlinked/docs ``docs/dvl/dvl-serial-protocol.md``, protocol 2.8.0).
115200 8N1. A packet is ``w`` + direction (``c`` to the DVL, ``r`` from it) +
a command letter + ``,option`` ... + ``*xx`` + a line end (``\\n``, ``\\r\\n`` or
``\\r``). ``xx`` is the CRC-8 (polynomial 0x07, init 0, no reflection, no final
xor; check value 0xf4) of every byte before the ``*``, two lower-case hex
digits. The DVL always sends it; it is optional in commands.

Reports: :func:`wrz` (velocity), :func:`wru` (one transducer), :func:`wrp`
(dead reckoning). Answers: ``wra`` (ack), ``wrn`` (nack), ``wr?`` (malformed),
``wr!`` (checksum mismatch), ``wrv`` (version), ``wrw`` (product), ``wrc``
(configuration).

:class:`SerialCommandDecoder` gives :class:`SerialCommand` (the letter after
``wc`` and its options) or :class:`BadSerial` (a
:class:`~hilsim.protocols.codec.BadFrame` with the answer the DVL gives:
``wr?`` or ``wr!``). Which letters exist is the device's business
(:data:`COMMANDS`); :func:`parse_wcs` reads ``wcs`` options into the
parameters :class:`~hilsim.protocols.dvl_json.DvlConfig` applies.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Sequence, Union

from hilsim.protocols.codec import BadFrame, LineDecoder, Oversize
from hilsim.protocols.dvl_json import DvlConfig

VERSION: Final = "2.8.0"
COMMANDS: Final = {"v": "protocol version", "w": "product detail", "s": "set configuration",
                   "c": "get configuration", "r": "reset dead reckoning", "x": "trigger ping",
                   "g": "calibrate gyro", "p": "serial output protocol"}
MAX_LINE: Final = 256


def _crc8_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = ((c << 1) ^ 0x07) & 0xFF if c & 0x80 else (c << 1) & 0xFF
        table.append(c)
    return tuple(table)


_CRC8 = _crc8_table()


def crc8(data: bytes) -> int:
    """CRC-8 (poly 0x07, init 0x00, not reflected, xorout 0x00) of ``data``."""
    c = 0
    for b in data:
        c = _CRC8[c ^ b]
    return c


def packet(body: str) -> bytes:
    """``body*xx\\r\\n`` (the DVL's line end is CR LF)."""
    raw = body.encode("ascii")
    return raw + b"*%02x\r\n" % crc8(raw)


def _yn(flag: bool) -> str:
    return "y" if flag else "n"


def wrz(v: Sequence[float], valid: bool, altitude: float, fom: float, covariance: Sequence[Sequence[float]],
        time_of_validity_us: int, time_of_transmission_us: int, time_ms: float, status: int) -> bytes:
    """Velocity report: v (3,) [m/s]; altitude [m] (-1 without lock); fom [m/s]; covariance (3, 3)
    [(m/s)^2] (9 entries separated by ``;``); Unix times [us]; time_ms since the last report [ms]."""
    cov = ";".join(f"{float(c):.6g}" for row in covariance for c in row)
    return packet(f"wrz,{v[0]:.3f},{v[1]:.3f},{v[2]:.3f},{_yn(valid)},{altitude:.2f},{fom:.3f},{cov},"
                  f"{int(time_of_validity_us)},{int(time_of_transmission_us)},{time_ms:.2f},{int(status)}")


def wru(ident: int, velocity: float, distance: float, rssi: float, nsd: float) -> bytes:
    """Transducer report: id 0-3, velocity along the beam [m/s] (0 when invalid), distance along the
    beam [m] (-1 when invalid), rssi and nsd [dBm]."""
    return packet(f"wru,{int(ident)},{velocity:.3f},{distance:.2f},{round(rssi)},{round(nsd)}")


def wrp(ts_s: float, x: float, y: float, z: float, pos_std: float, roll_deg: float, pitch_deg: float,
        yaw_deg: float, status: int) -> bytes:
    """Dead-reckoning report: Unix time [s], x, y, z [m], position std [m], roll, pitch, yaw [deg]."""
    return packet(f"wrp,{ts_s:.3f},{x:.2f},{y:.2f},{z:.2f},{pos_std:.2f},{roll_deg:.1f},{pitch_deg:.1f},"
                  f"{yaw_deg:.1f},{int(status)}")


def wrc(cfg: DvlConfig) -> bytes:
    """Configuration: speed of sound, mounting rotation offset, acoustic, dark mode, range mode,
    periodic cycling."""
    return packet(f"wrc,{cfg.speed_of_sound:.2f},{cfg.mounting_rotation_offset:.2f},{_yn(cfg.acoustic_enabled)},"
                  f"{_yn(cfg.dark_mode_enabled)},{cfg.range_mode},{_yn(cfg.periodic_cycling_enabled)}")


def wrv(version: str = VERSION) -> bytes:
    return packet(f"wrv,{version}")


def wrw(name: str, version: str, chip_id: str) -> bytes:
    return packet(f"wrw,{name},{version},{chip_id}")


ACK: Final = packet("wra")
NACK: Final = packet("wrn")
MALFORMED: Final = packet("wr?")
BAD_CHECKSUM: Final = packet("wr!")


@dataclass(frozen=True)
class SerialCommand:
    """``wc<letter>[,options]``: the letter (``"s"``) and the options as written."""

    letter: str
    options: tuple[str, ...]


@dataclass(frozen=True)
class BadSerial(BadFrame):
    """A line the DVL does not accept; ``answer`` is its reply (``wr?`` or ``wr!``)."""

    answer: bytes = MALFORMED


Event = Union[SerialCommand, BadSerial, Oversize]


def parse_line(line: bytes) -> SerialCommand | BadSerial:
    """One command line (no line end) -> :class:`SerialCommand` or :class:`BadSerial`."""
    data = line[:64]
    star = line.rfind(b"*")
    body = line
    if star >= 0:
        body = line[:star]
        try:
            want = int(line[star + 1:].decode("ascii"), 16)
        except (UnicodeDecodeError, ValueError):
            return BadSerial("checksum is not hex", data, MALFORMED)
        if len(line) - star != 3:
            return BadSerial("checksum is not 2 hex digits", data, MALFORMED)
        if crc8(body) != want:
            return BadSerial(f"checksum {crc8(body):02x} != {want:02x}", data, BAD_CHECKSUM)
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        return BadSerial("not ASCII", data, MALFORMED)
    if len(text) < 3 or not text.startswith("wc"):
        return BadSerial("a command starts with 'wc'", data, MALFORMED)
    parts = text.split(",")
    if len(parts[0]) != 3:
        return BadSerial(f"unknown command {parts[0]!r}", data, MALFORMED)
    return SerialCommand(parts[0][2], tuple(parts[1:]))


def parse_wcs(options: Sequence[str]) -> dict[str, object] | str:
    """``wcs`` options (speed of sound, mounting rotation offset, acoustic, dark mode[, range mode,
    periodic cycling]; blank = unchanged) -> parameters for :meth:`DvlConfig.apply`, or why malformed."""
    if len(options) not in (4, 5, 6):
        return f"wcs takes 4 to 6 options, got {len(options)}"
    out: dict[str, object] = {}
    names = ("speed_of_sound", "mounting_rotation_offset", "acoustic_enabled", "dark_mode_enabled", "range_mode",
             "periodic_cycling_enabled")
    for name, opt in zip(names, options):
        if opt == "":
            continue
        if name in ("speed_of_sound", "mounting_rotation_offset"):
            try:
                out[name] = float(opt)
            except ValueError:
                return f"{name} must be a number"
        elif name == "range_mode":
            out[name] = opt
        else:
            if opt not in ("y", "n"):
                return f"{name} must be y or n"
            out[name] = opt == "y"
    return out


class SerialCommandDecoder(LineDecoder[Event]):
    """DVL serial command lines -> events (sans-I/O); any of LF, CR LF, CR ends a line."""

    MAX_LINE = MAX_LINE
    CR_ENDS_LINE = True
    SKIP_BLANK = False

    @property
    def commands(self) -> int:
        return self.good

    def parse_line(self, line: bytes) -> Event:
        return parse_line(line)


__all__ = ["ACK", "BAD_CHECKSUM", "BadSerial", "COMMANDS", "MALFORMED", "NACK", "SerialCommand",
           "SerialCommandDecoder", "VERSION", "crc8", "packet", "parse_line", "parse_wcs", "wrc", "wrp", "wru",
           "wrv", "wrw", "wrz"]
