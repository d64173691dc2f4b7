"""NMEA 0183 encoder checked by pynmea2 (an independent parser: checksums, fields), decoder by cuts."""

from __future__ import annotations

import datetime as dt
import functools
import operator

import pytest

from hilsim.protocols import nmea
from hilsim.protocols.codec import NEED_DATA, Oversize, drain

pynmea2 = pytest.importorskip("pynmea2", reason="pynmea2 (test extra) is the independent NMEA parser")

UTC = 12 * 3600 + 34 * 60 + 56.78        # 12:34:56.78
DATE = (24, 11, 2026)


def _xor_checksum(line: bytes) -> int:
    """Checksum written from the NMEA rule: XOR of the bytes between '$' and '*'."""
    return functools.reduce(operator.xor, line[1:line.index(b"*")], 0)


def _check(line: bytes) -> "pynmea2.NMEASentence":
    assert line.endswith(b"\r\n") and line.startswith(b"$")
    assert len(line) <= nmea.MAX_SENTENCE
    assert int(line[line.index(b"*") + 1:-2], 16) == _xor_checksum(line)
    assert line[line.index(b"*") + 1:-2].isupper() or line[line.index(b"*") + 1:-2].isdigit()
    return pynmea2.parse(line.decode("ascii").strip(), check=True)


@pytest.mark.parametrize("lat,lon", [(59.9133, 10.7389), (-33.8568, 151.2153), (0.0001, -0.0001),
                                     (47.28523, -122.99999999)])
def test_gga_fix_parsed_by_pynmea2(lat: float, lon: float) -> None:
    msg = _check(nmea.gga("GP", UTC, lat, lon, 1, 9, 0.87, 12.34, 18.5))
    assert msg.sentence_type == "GGA"
    assert msg.latitude == pytest.approx(lat, abs=1e-6)   # 1e-5 min = 2e-7 deg
    assert msg.longitude == pytest.approx(lon, abs=1e-6)
    assert msg.gps_qual == 1 and int(msg.num_sats) == 9
    assert float(msg.horizontal_dil) == pytest.approx(0.87)
    assert msg.altitude == pytest.approx(12.34) and msg.altitude_units == "M"
    assert float(msg.geo_sep) == pytest.approx(18.5)
    assert msg.timestamp == dt.time(12, 34, 56, 780000, tzinfo=msg.timestamp.tzinfo)


def test_gga_no_fix_is_empty_with_quality_0() -> None:
    line = nmea.gga("GP", UTC, None, None, 0, 0, None, None)
    msg = _check(line)
    assert msg.gps_qual == 0
    assert msg.lat == "" and msg.lon == "" and msg.altitude is None


def test_rmc_valid_and_void() -> None:
    msg = _check(nmea.rmc("GP", UTC, DATE, True, 10.5, -20.25, 2.0 * nmea.KNOT, 271.5))
    assert msg.status == "A"
    assert msg.latitude == pytest.approx(10.5) and msg.longitude == pytest.approx(-20.25)
    assert msg.spd_over_grnd == pytest.approx(2.0) and msg.true_course == pytest.approx(271.5)
    assert msg.datestamp == dt.date(2026, 11, 24)
    void = _check(nmea.rmc("GP", UTC, DATE, False, None, None, 0.0, 0.0))
    assert void.status == "V" and void.lat == ""


def test_vtg_zda_hdt() -> None:
    v = _check(nmea.vtg("GP", True, 1.0, 45.0))
    assert float(v.true_track) == pytest.approx(45.0)
    assert float(v.spd_over_grnd_kts) == pytest.approx(1.0 / nmea.KNOT, abs=1e-3)
    assert float(v.spd_over_grnd_kmph) == pytest.approx(3.6, abs=1e-3)
    z = _check(nmea.zda("GP", UTC, DATE))
    assert (int(z.day), int(z.month), int(z.year)) == (24, 11, 2026)
    h = _check(nmea.hdt("GN", 359.99))
    assert float(h.heading) == pytest.approx(359.99)
    assert float(_check(nmea.hdt("GN", -90.0)).heading) == 270.0


def test_decoder_whole_and_byte_by_byte() -> None:
    stream = (nmea.gga("GP", UTC, 1.0, 2.0, 1, 8, 1.0, 3.0) + b"garbage\r\n"
              + nmea.rmc("GP", UTC, DATE, True, 1.0, 2.0, 0.0, 0.0)
              + b"$GPHDT,12.0,T*00\r\n" + b"$" + b"x" * 300 + b"\r\n" + nmea.zda("GP", UTC, DATE))
    whole = list(drain(nmea.NmeaDecoder(), stream))
    dec = nmea.NmeaDecoder()
    cut = [ev for i in range(len(stream)) for ev in drain(dec, stream[i:i + 1])]
    assert whole == cut
    kinds = [type(e).__name__ for e in whole]
    assert kinds == ["Sentence", "BadSentence", "Sentence", "BadSentence", "Oversize", "Sentence"]
    assert isinstance(whole[4], Oversize)
    assert whole[0].kind == "GGA" and whole[2].kind == "RMC" and whole[5].fields[1:4] == ("24", "11", "2026")
    assert dec.next_event() is NEED_DATA and dec.buffered_bytes == 0


def test_lat_lon_round_trip() -> None:
    for deg in (0.0, 12.999999, 89.5, 45.000001):
        s, h = nmea.format_lat(deg)
        assert nmea.parse_lat(s, h) == pytest.approx(deg, abs=2e-7)
        s, h = nmea.format_lon(-deg * 2)
        assert nmea.parse_lon(s, h) == pytest.approx(-deg * 2, abs=2e-7)
