"""Water Linked DVL JSON and serial codecs, checked against the vendor's documents.

The field lists below are written from waterlinked/docs (dvl-json-protocol.md,
dvl-serial-protocol.md), not from our encoder; the serial checksum is checked with
crcmod's predefined "crc-8", the implementation the vendor's document names.
"""

from __future__ import annotations

import json

import pytest

from hilsim.protocols import dvl_json as dj
from hilsim.protocols import dvl_serial as ds
from hilsim.protocols.codec import Oversize, drain

VELOCITY_KEYS = {"time", "vx", "vy", "vz", "fom", "covariance", "altitude", "transducers", "velocity_valid",
                 "status", "format", "type", "time_of_validity", "time_of_transmission"}
TRANSDUCER_KEYS = {"id", "velocity", "distance", "rssi", "nsd", "beam_valid"}
POSITION_KEYS = {"ts", "x", "y", "z", "std", "roll", "pitch", "yaw", "type", "status", "format"}
RESPONSE_KEYS = {"response_to", "success", "error_message", "result", "format", "type"}


def _beams(valid: bool = True) -> list[dj.Transducer]:
    return [dj.Transducer(i, 0.01 * i, 1.5 + 0.1 * i if valid else -1.0, -40.0, -95.0, valid) for i in range(4)]


def test_velocity_report_has_the_documented_fields() -> None:
    line = dj.velocity_report(106.4, (0.3, -0.1, 0.02), 0.0016, [[1e-6, 0, 0], [0, 1e-6, 0], [0, 0, 2e-7]], 1.25,
                              _beams(), True, 0, 1_638_191_471_563_017, 1_638_191_471_752_336)
    assert line.endswith(b"\n") and line.count(b"\n") == 1
    obj = json.loads(line)
    assert set(obj) == VELOCITY_KEYS
    assert obj["type"] == "velocity" and obj["format"] == "json_v3.3"
    assert (obj["vx"], obj["vy"], obj["vz"], obj["altitude"]) == (0.3, -0.1, 0.02, 1.25)
    assert len(obj["covariance"]) == 3 and all(len(r) == 3 for r in obj["covariance"])
    assert [t["id"] for t in obj["transducers"]] == [0, 1, 2, 3]
    assert all(set(t) == TRANSDUCER_KEYS for t in obj["transducers"])
    assert obj["velocity_valid"] is True and isinstance(obj["time_of_validity"], int)


def test_position_and_response_fields() -> None:
    obj = json.loads(dj.position_report(49056.809, 1.0, 2.0, 0.5, 0.01, 0.5, -0.5, 90.0, 0))
    assert set(obj) == POSITION_KEYS and obj["type"] == "position_local" and obj["yaw"] == 90.0
    obj = json.loads(dj.response("get_config", True, "", dj.DvlConfig().as_result()))
    assert set(obj) == RESPONSE_KEYS and obj["type"] == "response" and obj["success"] is True
    assert set(obj["result"]) == {"speed_of_sound", "acoustic_enabled", "dark_mode_enabled",
                                  "mounting_rotation_offset", "range_mode", "periodic_cycling_enabled"}


def test_nan_never_reaches_the_wire() -> None:
    obj = json.loads(dj.velocity_report(float("nan"), (float("inf"), 0, 0), 0, [[0] * 3] * 3, float("nan"),
                                        _beams(False), False, 0, 0, 0))
    assert obj["vx"] == -1.0 and obj["altitude"] == -1.0


def test_command_decoder() -> None:
    stream = (b'{"command": "get_config"}\n{"command":"set_config","parameters":{"speed_of_sound":1480}}\r\n'
              b'{"command": "bogus"}\n{not json\n[1, 2]\n{"parameters": {}}\n\n' + b"{" * 5000 + b"\n"
              + b'{"command":"trigger_ping"}\n')
    whole = list(drain(dj.CommandDecoder(), stream))
    dec = dj.CommandDecoder()
    assert whole == [e for i in range(len(stream)) for e in drain(dec, stream[i:i + 1])]
    kinds = [type(e).__name__ for e in whole]
    assert kinds == ["Command", "Command", "Command", "BadCommand", "BadCommand", "BadCommand", "Oversize",
                     "Command"]
    assert whole[1].parameters == {"speed_of_sound": 1480}
    assert whole[2].command == "bogus" and whole[7].command == "trigger_ping"
    assert isinstance(whole[6], Oversize)


def test_config_validation_is_all_or_nothing() -> None:
    cfg = dj.DvlConfig()
    assert cfg.apply({"speed_of_sound": 1480, "range_mode": "1<=3"}) == ""
    assert (cfg.speed_of_sound, cfg.range_mode) == (1480.0, "1<=3")
    for bad in ({"speed_of_sound": 999}, {"speed_of_sound": True}, {"mounting_rotation_offset": 400},
                {"acoustic_enabled": "no"}, {"range_mode": "=7"}, {"nonsense": 1}, {}, [1],
                {"dark_mode_enabled": True, "speed_of_sound": "x"}):
        assert cfg.apply(bad) != ""
    assert (cfg.speed_of_sound, cfg.range_mode, cfg.dark_mode_enabled) == (1480.0, "1<=3", False)
    for mode in ("auto", "wt", "=0", "=4", "0<=4"):
        assert cfg.apply({"range_mode": mode}) == ""


# ---- serial -----------------------------------------------------------------------------------

crcmod = pytest.importorskip("crcmod.predefined", reason="crcmod (test extra) is the vendor's named CRC-8")


def _check_crc(line: bytes) -> str:
    assert line.endswith(b"\r\n")
    body, crc = line[:-2].rsplit(b"*", 1)
    assert len(crc) == 2 and crc == crc.lower()
    assert crcmod.mkPredefinedCrcFun("crc-8")(body) == int(crc, 16)
    return body.decode("ascii")


def test_vendor_examples_checksums() -> None:
    """The CRC of the examples printed in the vendor's document."""
    for text, crc in (("wru,0,0.070,1.10,-40,-95", 0x9C), ("wrp,49056.809,0.41,0.15,1.23,0.4,53.9,13.0,19.3,0", 0xDE),
                      ("wrx,1164.94,0.000,0.000,0.000,2.707,-1.00,n,1", 0x39)):
        assert ds.crc8(text.encode()) == crc
    assert ds.packet("wru,0,0.070,1.10,-40,-95") == b"wru,0,0.070,1.10,-40,-95*9c\r\n"


def test_reports_follow_the_documented_layout() -> None:
    body = _check_crc(ds.wrz((0.12, -0.4, 2.0), True, 1.3, 1.855, [[1e-7, 0, 1.4], [0, 1.2, 0], [0.2, 0, 1e9]],
                             7, 14, 123.0, 1))
    f = body.split(",")
    assert f[0] == "wrz" and len(f) == 12
    assert (float(f[1]), float(f[2]), float(f[3]), f[4], float(f[5]), float(f[6])) == (0.12, -0.4, 2.0, "y", 1.3, 1.855)
    assert [float(c) for c in f[7].split(";")] == [1e-7, 0, 1.4, 0, 1.2, 0, 0.2, 0, 1e9]
    assert (int(f[8]), int(f[9]), float(f[10]), int(f[11])) == (7, 14, 123.0, 1)
    f = _check_crc(ds.wru(2, 2.2, 1.4, -56.2, -98.0)).split(",")
    assert f == ["wru", "2", "2.200", "1.40", "-56", "-98"]
    f = _check_crc(ds.wrp(49056.809, 0.41, 0.15, 1.23, 0.4, 53.9, 13.0, 19.3, 0)).split(",")
    assert f[0] == "wrp" and len(f) == 10 and float(f[1]) == 49056.809 and float(f[8]) == 19.3
    f = _check_crc(ds.wrc(dj.DvlConfig())).split(",")
    assert f[0] == "wrc" and len(f) == 7 and f[3:] == ["y", "n", "auto", "y"]
    for fixed in (ds.ACK, ds.NACK, ds.MALFORMED, ds.BAD_CHECKSUM, ds.wrv()):
        _check_crc(fixed)


def test_serial_command_decoder() -> None:
    good_crc = ds.packet("wcv")[:-2]
    stream = (b"wcv\n" + good_crc + b"\r" + b"wcs,1450,,n,,,\r\n" + b"wcv*00\n" + b"hello\n" + b"wcs*zz\n"
              + b"wcq,1\r\n" + b"x" * 300 + b"\n" + b"wcr\n")
    whole = list(drain(ds.SerialCommandDecoder(), stream))
    dec = ds.SerialCommandDecoder()
    assert whole == [e for i in range(len(stream)) for e in drain(dec, stream[i:i + 1])]
    kinds = [type(e).__name__ for e in whole]
    assert kinds == ["SerialCommand", "SerialCommand", "SerialCommand", "BadSerial", "BadSerial", "BadSerial",
                     "SerialCommand", "Oversize", "SerialCommand"]
    assert whole[2] == ds.SerialCommand("s", ("1450", "", "n", "", "", ""))
    assert whole[3].answer == ds.BAD_CHECKSUM and whole[4].answer == ds.MALFORMED
    assert whole[6].letter == "q"
    params = ds.parse_wcs(whole[2].options)
    assert params == {"speed_of_sound": 1450.0, "acoustic_enabled": False}
    assert isinstance(ds.parse_wcs(("1", "2")), str) and isinstance(ds.parse_wcs(("x", "", "", "")), str)
    assert ds.parse_wcs(("", "", "", "y")) == {"dark_mode_enabled": True}
