"""NMEA 0183 sentences a GNSS receiver sends (GGA, RMC, VTG, ZDA, HDT), sans-I/O.

Spec: ``protocols/nmea0183.md`` (from NMEA 0183 v2.3/4.x as receivers print it;
shared/reference/navigation-sensors.md). A sentence is
``$<talker><type>,<field>,...*<checksum>\\r\\n``: the checksum is the XOR of the
bytes between ``$`` and ``*``, written as two upper-case hex digits. The whole
sentence is at most 82 characters with the line end.

Encoders take SI values and degrees at the edge: latitude/longitude [deg]
(written ``ddmm.mmmmm`` / ``dddmm.mmmmm`` with N/S, E/W), speed [m/s]
(written in knots and km/h), course and heading [deg true], altitude and
geoid separation [m], time as seconds of the UTC day [s] plus a calendar date.
A receiver without a fix writes the empty fields a real one writes (GGA
quality 0, RMC status ``V``, mode ``N``).

:class:`NmeaDecoder` (for the peers in the tests and the fuzz table) frames
lines with :class:`~hilsim.protocols.codec.LineFramer` and gives
:class:`Sentence` events, or :class:`BadSentence` (a :class:`BadFrame`) for a
line that is not a sentence or whose checksum is wrong, or ``Oversize``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence, Union

from hilsim.protocols.codec import BadFrame, LineDecoder, Oversize

MAX_SENTENCE = 82          # characters, '$' to the line end included (NMEA 0183)
KNOT = 1852.0 / 3600.0     # [m/s] one knot


def checksum(body: bytes) -> int:
    """XOR of ``body`` (the bytes between ``$`` and ``*``)."""
    c = 0
    for b in body:
        c ^= b
    return c


def sentence(address: str, fields: Sequence[str]) -> bytes:
    """``$<address>,<fields...>*HH\\r\\n`` for ``address`` = talker + type (``"GPGGA"``)."""
    body = ",".join([address, *fields]).encode("ascii")
    return b"$" + body + b"*%02X\r\n" % checksum(body)


def _hms(seconds_of_day: float | None) -> str:
    """``hhmmss.ss`` of seconds since UTC midnight [s]; empty when unknown."""
    if seconds_of_day is None:
        return ""
    cs = int(round(seconds_of_day * 100.0)) % (86400 * 100)
    h, rem = divmod(cs, 360000)
    m, rem = divmod(rem, 6000)
    return f"{h:02d}{m:02d}{rem // 100:02d}.{rem % 100:02d}"


def _format_angle(deg: float, digits: int, hemispheres: tuple[str, str]) -> tuple[str, str]:
    """(degrees in ``digits`` digits then ``mm.mmmmm``, the hemisphere letter: ``hemispheres[0]``
    for ``deg`` >= 0, else ``hemispheres[1]``) of an angle [deg]."""
    a = abs(deg)
    d = int(a)
    minutes = round((a - d) * 60.0, 5)
    if minutes >= 60.0:
        d, minutes = d + 1, 0.0
    return f"{d:0{digits}d}{minutes:08.5f}", hemispheres[0] if deg >= 0 else hemispheres[1]


def format_lat(lat_deg: float) -> tuple[str, str]:
    """(``ddmm.mmmmm``, ``N``/``S``) of a latitude [deg]."""
    return _format_angle(lat_deg, 2, ("N", "S"))


def format_lon(lon_deg: float) -> tuple[str, str]:
    """(``dddmm.mmmmm``, ``E``/``W``) of a longitude [deg]."""
    return _format_angle(lon_deg, 3, ("E", "W"))


def _parse_angle(value: str, hemi: str, digits: int, hemispheres: tuple[str, str], what: str) -> float:
    """[deg] of ``value`` (degrees in ``digits`` digits, then minutes) and its hemisphere letter
    ``hemi`` (``hemispheres[1]`` negative); ValueError naming ``what`` if malformed."""
    if len(value) < digits + 2 or hemi not in hemispheres:
        raise ValueError(f"bad {what} {value!r},{hemi!r}")
    deg = int(value[:digits]) + float(value[digits:]) / 60.0
    return -deg if hemi == hemispheres[1] else deg


def parse_lat(value: str, hemi: str) -> float:
    """Latitude [deg] of ``ddmm.mmmm`` and N/S (ValueError if malformed)."""
    return _parse_angle(value, hemi, 2, ("N", "S"), "latitude")


def parse_lon(value: str, hemi: str) -> float:
    """Longitude [deg] of ``dddmm.mmmm`` and E/W (ValueError if malformed)."""
    return _parse_angle(value, hemi, 3, ("E", "W"), "longitude")


def gga(talker: str, utc_s: float | None, lat_deg: float | None, lon_deg: float | None, quality: int,
        satellites: int, hdop: float | None, alt_m: float | None, geoid_sep_m: float = 0.0,
        dgps_age_s: float | None = None, dgps_station: int | None = None) -> bytes:
    """GGA, fix data. ``quality`` 0 (no fix: position, altitude and separation empty, HDOP 99.99
    as receivers print it), 1 GPS, 2 DGPS, 4 RTK fixed, 5 RTK float. utc_s: seconds of the UTC
    day [s] (None: empty); alt_m: altitude above mean sea level [m]; geoid_sep_m [m]."""
    if quality == 0 or lat_deg is None or lon_deg is None:
        return sentence(f"{talker}GGA", [_hms(utc_s), "", "", "", "", "0", f"{satellites:02d}", "99.99",
                                         "", "", "", "", "", ""])
    la, ns = format_lat(lat_deg)
    lo, ew = format_lon(lon_deg)
    return sentence(f"{talker}GGA", [
        _hms(utc_s), la, ns, lo, ew, str(int(quality)), f"{satellites:02d}",
        "" if hdop is None else f"{hdop:.2f}", "" if alt_m is None else f"{alt_m:.2f}", "M",
        f"{geoid_sep_m:.2f}", "M", "" if dgps_age_s is None else f"{dgps_age_s:.1f}",
        "" if dgps_station is None else f"{dgps_station:04d}"])


def _date(day: int, month: int, year: int) -> str:
    return f"{day:02d}{month:02d}{year % 100:02d}"


def rmc(talker: str, utc_s: float | None, date: tuple[int, int, int] | None, valid: bool,
        lat_deg: float | None, lon_deg: float | None, speed_m_s: float, course_deg: float,
        mode: str = "A") -> bytes:
    """RMC, recommended minimum data (NMEA 2.3, with the mode indicator). ``valid`` False: status
    ``V``, position/speed/course empty, mode ``N``. date: (day, month, year); speed [m/s]
    (written in knots); course over ground [deg true]."""
    d = "" if date is None else _date(*date)
    if not valid or lat_deg is None or lon_deg is None:
        return sentence(f"{talker}RMC", [_hms(utc_s), "V", "", "", "", "", "", "", d, "", "", "N"])
    la, ns = format_lat(lat_deg)
    lo, ew = format_lon(lon_deg)
    return sentence(f"{talker}RMC", [_hms(utc_s), "A", la, ns, lo, ew, f"{speed_m_s / KNOT:.3f}",
                                     f"{course_deg % 360.0:.2f}", d, "", "", mode])


def vtg(talker: str, valid: bool, speed_m_s: float, course_deg: float, mode: str = "A") -> bytes:
    """VTG, course [deg true] and speed over ground [m/s] (written in knots and km/h); empty
    when ``valid`` is False (mode ``N``)."""
    if not valid:
        return sentence(f"{talker}VTG", ["", "T", "", "M", "", "N", "", "K", "N"])
    return sentence(f"{talker}VTG", [f"{course_deg % 360.0:.2f}", "T", "", "M", f"{speed_m_s / KNOT:.3f}", "N",
                                     f"{speed_m_s * 3.6:.3f}", "K", mode])


def zda(talker: str, utc_s: float | None, date: tuple[int, int, int] | None) -> bytes:
    """ZDA, UTC time and date (local zone 00:00); empty fields when unknown."""
    if utc_s is None or date is None:
        return sentence(f"{talker}ZDA", ["", "", "", "", "", ""])
    day, month, year = date
    return sentence(f"{talker}ZDA", [_hms(utc_s), f"{day:02d}", f"{month:02d}", f"{year:04d}", "00", "00"])


def hdt(talker: str, heading_deg: float | None) -> bytes:
    """HDT, true heading [deg] (a dual-antenna receiver); empty without a heading solution."""
    return sentence(f"{talker}HDT", ["" if heading_deg is None or not math.isfinite(heading_deg)
                                     else f"{heading_deg % 360.0:.2f}", "T"])


# ---- decoding ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class Sentence:
    """A sentence with a good checksum: talker (``"GP"``), kind (``"GGA"``), its fields."""

    talker: str
    kind: str
    fields: tuple[str, ...]


@dataclass(frozen=True)
class BadSentence(BadFrame):
    """A line that is not an NMEA sentence (no ``$``, no ``*HH``, not ASCII) or whose checksum is wrong."""


Event = Union[Sentence, BadSentence, Oversize]


def parse_sentence(line: bytes) -> Sentence | BadSentence:
    """One line (without its line end) -> :class:`Sentence` or :class:`BadSentence`."""
    data = line[:64]
    if not line.startswith((b"$", b"!")):
        return BadSentence("no '$' at the start", data)
    star = line.rfind(b"*")
    if star < 0 or len(line) - star != 3:
        return BadSentence("no '*HH' checksum", data)
    body = line[1:star]
    try:
        want = int(line[star + 1:], 16)
        text = body.decode("ascii")
    except (ValueError, UnicodeDecodeError):
        return BadSentence("checksum not hex or sentence not ASCII", data)
    if checksum(body) != want:
        return BadSentence(f"checksum {checksum(body):02X} != {want:02X}", data)
    parts = text.split(",")
    address = parts[0]
    if len(address) < 3 or not address.isalnum():
        return BadSentence(f"bad address {address!r}", data)
    if address.startswith("P"):       # proprietary: P + maker
        return Sentence("P", address[1:], tuple(parts[1:]))
    return Sentence(address[:2], address[2:], tuple(parts[1:]))


class NmeaDecoder(LineDecoder[Event]):
    """NMEA 0183 lines -> :class:`Sentence` / :class:`BadSentence` / ``Oversize`` (sans-I/O).

    Lines longer than ``max_line`` bytes (default: a generous 2 x the 82-character limit) are
    ``Oversize``; memory is bounded by that plus the last chunk."""

    MAX_LINE = 2 * MAX_SENTENCE
    CR_ENDS_LINE = False
    SKIP_BLANK = False

    @property
    def sentences(self) -> int:
        return self.good

    def parse_line(self, line: bytes) -> Event:
        return parse_sentence(line)


__all__ = ["BadSentence", "KNOT", "MAX_SENTENCE", "NmeaDecoder", "Sentence", "checksum", "format_lat",
           "format_lon", "gga", "hdt", "parse_lat", "parse_lon", "parse_sentence", "rmc", "sentence", "vtg",
           "zda"]
