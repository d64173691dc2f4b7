"""ArduPilot JSON backend codec, checked from ArduPilot's documented protocol.

Servo packets are built here with ``struct`` from the readme's layout (not with our
encoder). Replies are read by :func:`ardupilot_parse`, a Python rendering of what
SIM_JSON.cpp does: the buffer's newlines become NULs, the last complete line is
parsed, each key of its key table is found by substring search (the section first,
then the key after it), the value starts right after ``":`` and is read with
``atof`` / ``strtoull`` / ``sscanf("[%f, %f, %f]")``.
"""

from __future__ import annotations

import json
import math
import re
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilsim.protocols.ardupilot_json import (ServoDecoder, ServoPacket, decode_servo, encode_reply,
                                             encode_servo, quaternion_from_euler)
from hilsim.protocols.codec import NEED_DATA, BadFrame
from hilsim.sim.geometry import rpy_to_matrix

# SIM_JSON.h's key table: (section, key, type, required)
KEYTABLE = [
    ("", "timestamp", "double", True),
    ("imu", "gyro", "vec3", True),
    ("imu", "accel_body", "vec3", True),
    ("", "position", "vec3", True),
    ("", "attitude", "vec3", False),
    ("", "quaternion", "quat", False),
    ("", "velocity", "vec3", True),
    ("", "rng_1", "float", False),
    ("", "rng_2", "float", False),
    ("", "no_time_sync", "bool", False),
]
_NUM = r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:inf|nan))"


def _atof(p: str) -> float:
    """atof: leading whitespace, then the longest number prefix; 0 when there is none."""
    m = re.match(r"\s*" + _NUM, p, re.IGNORECASE)
    return float(m.group(1)) if m else 0.0


def _sscanf_vec(p: str, n: int) -> list[float] | None:
    """sscanf(p, "[%f, %f, ...]") == n: '[' must be the first character; each %f skips
    leading whitespace; ', ' in the format is a comma then any whitespace."""
    m = re.match(r"\[" + r"\s*,".join([r"\s*" + _NUM] * n), p, re.IGNORECASE)
    return [float(g) for g in m.groups()] if m else None


def ardupilot_parse(buffer: bytes) -> dict[str, object] | None:
    """What ArduPilot's JSON backend takes from its receive buffer, or None when it takes nothing."""
    text = buffer.replace(b"\n", b"\0")
    p2 = text.rfind(b"\0")
    if p2 <= 0:
        return None
    p1 = text.rfind(b"\0", 0, p2)
    if p1 < 0:
        return None
    line = text[p1 + 1:p2].decode("latin-1")
    out: dict[str, object] = {}
    for section, key, kind, required in KEYTABLE:
        i = line.find(section)
        if i < 0:
            if required:
                return None
            continue
        j = line.find(key, i + len(section) + 1)
        if j < 0:
            if required:
                return None
            continue
        p = line[j + len(key) + 2:]
        if kind in ("double", "float"):
            out[key] = _atof(p)
        elif kind == "bool":
            m = re.match(r"\s*(\d+)", p)
            out[key] = bool(int(m.group(1))) if m else False
        else:
            v = _sscanf_vec(p, 4 if kind == "quat" else 3)
            if v is None:
                return None  # "Failed to parse": the mandatory-field check fails
            out[key] = v
    if "attitude" not in out and "quaternion" not in out:
        return None
    return out


def servo_datagram(magic: int, rate: int, count: int, pwm: list[int]) -> bytes:
    return struct.pack("<HHI", magic, rate, count) + struct.pack(f"<{len(pwm)}H", *pwm)


# -- servo packets ----------------------------------------------------------------

def test_sixteen_channel_packet() -> None:
    pwm = [1100 + 50 * i for i in range(16)]
    pkt = decode_servo(servo_datagram(18458, 1200, 77, pwm))
    assert pkt == ServoPacket(1200, 77, tuple(pwm))
    assert pkt.channels == 16 and pkt.step == pytest.approx(1 / 1200)


def test_thirty_two_channel_packet() -> None:
    pwm = [1500] * 8 + [0] * 24
    pkt = decode_servo(servo_datagram(29569, 400, 2 ** 32 - 1, pwm))
    assert isinstance(pkt, ServoPacket)
    assert pkt.channels == 32 and pkt.frame_count == 2 ** 32 - 1 and pkt.pwm == tuple(pwm)


@pytest.mark.parametrize("data, why", [
    (b"", "short"),
    (b"\x1a\x48\xb0\x04", "short"),
    (servo_datagram(18458, 1200, 1, [1500] * 16)[:39], "bytes for magic"),
    (servo_datagram(18458, 1200, 1, [1500] * 16) + b"\0", "bytes for magic"),
    (servo_datagram(29569, 1200, 1, [1500] * 16), "bytes for magic"),  # 32-channel magic, 16 values
    (servo_datagram(12345, 1200, 1, [1500] * 16), "unknown magic"),
    (servo_datagram(18458, 0, 1, [1500] * 16), "frame_rate 0"),
    (b'{"timestamp":1}', "magic"),
])
def test_bad_packets_are_bad_frames(data: bytes, why: str) -> None:
    ev = decode_servo(data)
    assert isinstance(ev, BadFrame) and why in ev.reason
    assert len(ev.data) <= 64


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=100))
def test_any_datagram_decodes_without_raising(data: bytes) -> None:
    ev = decode_servo(data)
    magic = struct.unpack("<H", data[:2])[0] if len(data) >= 2 else None
    ok = ((len(data) == 40 and magic == 18458) or (len(data) == 72 and magic == 29569)) and data[2:4] != b"\0\0"
    assert isinstance(ev, ServoPacket) == ok


def test_decoder_contract_per_datagram() -> None:
    dec = ServoDecoder(max_pending=3)
    assert dec.next_event() is NEED_DATA
    good = servo_datagram(18458, 1200, 5, [1500] * 16)
    for d in (good, b"junk", b"", good, good):
        dec.receive_data(d)  # b"" is no datagram
    assert dec.dropped == 1 and dec.buffered_bytes == 4 + 40 + 40  # the oldest datagram dropped
    events = []
    while (ev := dec.next_event()) is not NEED_DATA:
        events.append(ev)
    assert [type(e) for e in events] == [BadFrame, ServoPacket, ServoPacket]
    assert dec.buffered_bytes == 0


def test_our_servo_encoder_matches_the_readme_layout() -> None:
    assert encode_servo([1500] * 8, 9, 1200) == servo_datagram(18458, 1200, 9, [1500] * 8 + [0] * 8)
    assert encode_servo([1600] * 20, 3, 400) == servo_datagram(29569, 400, 3, [1600] * 20 + [0] * 12)


# -- replies ----------------------------------------------------------------------

STATE = dict(timestamp=12.3456789, gyro=(0.01, -0.02, 0.5), accel_body=(0.1, -0.2, -9.80665),
             position=(1.5, -2.25, 3.0), velocity=(0.2, 0.0, -0.05),
             quaternion=(0.9238795325112867, 0.0, 0.0, 0.3826834323650898))


def test_reply_reads_back_through_ardupilots_parser() -> None:
    reply = encode_reply(**STATE, rng_1=1.75, no_time_sync=True)  # type: ignore[arg-type]
    assert reply.startswith(b"\n") and reply.endswith(b"}\n") and reply.count(b"\n") == 2
    assert b": " not in reply and b", " not in reply  # compact
    got = ardupilot_parse(reply)
    assert got is not None
    assert got["timestamp"] == STATE["timestamp"]
    for key in ("gyro", "accel_body", "position", "velocity", "quaternion"):
        assert got[key] == pytest.approx(list(STATE[key]), abs=1e-6)  # type: ignore[arg-type]
    assert got["rng_1"] == pytest.approx(1.75) and got["no_time_sync"] is True
    assert "attitude" not in got and "rng_2" not in got
    # and it is JSON to any other reader
    assert json.loads(reply)["imu"]["accel_body"][2] == -9.80665


def test_optional_keys_left_out() -> None:
    reply = encode_reply(**STATE)  # type: ignore[arg-type]
    got = ardupilot_parse(reply)
    assert got is not None and "rng_1" not in got and "no_time_sync" not in got
    assert b"no_time_sync" not in reply


def test_parser_takes_the_last_complete_reply_of_its_buffer() -> None:
    first = encode_reply(**{**STATE, "timestamp": 1.0})  # type: ignore[arg-type]
    second = encode_reply(**{**STATE, "timestamp": 2.0})  # type: ignore[arg-type]
    got = ardupilot_parse(first + second)
    assert got is not None and got["timestamp"] == 2.0


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_never_reach_the_wire(bad: float) -> None:
    for key in ("timestamp", "gyro", "position", "quaternion"):
        value = bad if key == "timestamp" else tuple([bad] + list(STATE[key])[1:])  # type: ignore[arg-type]
        with pytest.raises(ValueError, match=key):
            encode_reply(**{**STATE, key: value})  # type: ignore[arg-type]
    reply = encode_reply(**STATE, rng_1=bad)  # type: ignore[arg-type]
    assert b"rng_1" not in reply and b"nan" not in reply.lower() and b"inf" not in reply.lower()
    assert ardupilot_parse(reply) is not None


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64), min_size=17, max_size=17),
       st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True)))
def test_any_finite_state_gives_valid_json_that_ardupilot_reads(vals: list[float], rng: float | None) -> None:
    reply = encode_reply(vals[0], vals[1:4], vals[4:7], vals[7:10], vals[10:13], vals[13:17], rng_1=rng)
    doc = json.loads(reply)
    assert doc["timestamp"] == vals[0] and doc["quaternion"] == vals[13:17]
    got = ardupilot_parse(reply)
    assert got is not None
    assert got["position"] == pytest.approx(vals[7:10], rel=1e-6)


def test_wrong_vector_length_is_our_bug() -> None:
    with pytest.raises(ValueError, match="gyro"):
        encode_reply(**{**STATE, "gyro": (0.0, 0.0)})  # type: ignore[arg-type]


@pytest.mark.parametrize("rpy", [(0.0, 0.0, 0.0), (0.3, -0.2, 2.5), (-1.0, 0.7, -3.0), (0.0, 0.0, math.pi)])
def test_quaternion_is_the_body_to_ned_rotation(rpy: tuple[float, float, float]) -> None:
    w, x, y, z = quaternion_from_euler(*rpy)
    assert w >= 0 and w * w + x * x + y * y + z * z == pytest.approx(1.0)
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    np.testing.assert_allclose(rot, rpy_to_matrix(*rpy), atol=1e-12)


def test_the_test_parser_is_as_strict_as_ardupilots() -> None:
    """The reference parser refuses what ArduPilot refuses: a space between the colon and a
    vector, a missing required key, no attitude at all; so the tests above can fail."""
    good = b'\n{"timestamp":1,"imu":{"gyro":[0,0,0],"accel_body":[0,0,-9.8]},"position":[0,0,0],' \
           b'"velocity":[0,0,0],"quaternion":[1,0,0,0]}\n'
    assert ardupilot_parse(good) is not None
    assert ardupilot_parse(good.replace(b'"gyro":[', b'"gyro": [')) is None
    assert ardupilot_parse(good.replace(b'"velocity"', b'"speed"')) is None
    assert ardupilot_parse(good.replace(b',"quaternion":[1,0,0,0]', b"")) is None
    assert ardupilot_parse(good.rstrip(b"\n")) is None  # no newline after it: not complete
