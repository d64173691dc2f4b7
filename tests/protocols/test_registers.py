"""The register-map engine: map files, encodings against physics and the reference
check value, reads/writes and their exception codes, map errors."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilsim.config import ConfigError
from hilsim.protocols.registers import (
    ILLEGAL_ADDRESS,
    ILLEGAL_VALUE,
    TYPES,
    ModbusError,
    Register,
    RegisterImage,
    load_map,
)
from hilsim.resources import data_path
from hilsim.sim.navigation import ATMOSPHERE, GRAVITY

KELLER = data_path("protocols", "keller_serie30.toml")
WIT = data_path("protocols", "witmotion_hwt905.toml")


def f32(words: list[int]) -> float:
    return float(struct.unpack(">f", struct.pack(">HH", *words))[0])


@pytest.fixture()
def keller() -> RegisterImage:
    return RegisterImage(load_map(KELLER))


@pytest.fixture()
def wit() -> RegisterImage:
    return RegisterImage(load_map(WIT))


def test_keller_check_value() -> None:
    """The reference: bytes 3F 6D BA AC are 0.92863 bar, and 0.92863 bar encodes to them."""
    p1 = load_map(KELLER)["P1"]
    assert p1.decode([0x3F6D, 0xBAAC]) == pytest.approx(0.92863, abs=5e-6)
    assert p1.encode(p1.decode([0x3F6D, 0xBAAC])) == (0x3F6D, 0xBAAC)
    hi, lo = p1.encode_si(0.92863e5)  # the 5-digit value is a few float32 steps away
    assert hi == 0x3F6D and p1.decode([hi, lo]) == pytest.approx(0.92863, abs=1e-7)


@pytest.mark.parametrize("depth", [0.0, 0.5, 1.5, 10.0, 250.0])
@pytest.mark.parametrize("rho", [998.0, 1025.0])
def test_keller_pressure_is_rho_g_depth(keller: RegisterImage, depth: float, rho: float) -> None:
    """Every P1 representation decodes to P_atm + rho g depth; TOB1 to the temperature in deg C."""
    p = ATMOSPHERE + rho * GRAVITY * depth
    keller.update({"pressure": p, "temperature": 293.15})
    for addr in (0x0002, 0x0100):
        bar = f32(keller.read(addr, 2))
        assert (bar * 1e5 - ATMOSPHERE) / (rho * GRAVITY) == pytest.approx(depth, abs=2e-7 * p / (rho * GRAVITY) + 1e-9)
    hi, lo = keller.read(0x0012, 2)
    pa = struct.unpack(">i", struct.pack(">HH", hi, lo))[0]  # 1/100 mbar = 1 Pa per count
    assert abs(pa - p) <= 0.5
    assert f32(keller.read(0x0008, 2)) == pytest.approx(20.0, abs=1e-5)
    block = keller.read(0x0100, 4)  # one read of P1 and TOB1 together
    assert block[:2] == keller.read(0x0002, 2) and block[2:] == keller.read(0x0008, 2)


def test_keller_channel_error_and_overflow(keller: RegisterImage) -> None:
    """NaN = channel error; +-inf = over/underflow (float), saturation (int32)."""
    keller.update({"pressure": math.nan, "temperature": 290.0})
    assert keller.read(0x0002, 2) == [0x7FC0, 0x0000]
    assert math.isnan(f32(keller.read(0x0002, 2)))
    keller.update({"pressure": math.inf})
    assert keller.read(0x0002, 2) == [0x7F80, 0x0000]
    assert keller.read(0x0012, 2) == [0x7FFF, 0xFFFF]
    keller.update({"pressure": -math.inf})
    assert keller.read(0x0002, 2) == [0xFF80, 0x0000]
    assert keller.read(0x0012, 2) == [0x8000, 0x0000]
    # absent channels read NaN; constants are there from the start
    assert math.isnan(f32(keller.read(0x0004, 2))) and math.isnan(f32(keller.read(0x000A, 2)))
    assert keller.read(0x0202, 2) == [1234567 >> 16, 1234567 & 0xFFFF]
    assert keller.read(0x020D, 1) == [1]


def test_keller_addresses(keller: RegisterImage) -> None:
    keller.update({"pressure": 1.2e5, "temperature": 290.0})
    assert len(keller.read(0x0000, 12)) == 12   # CH0 .. TOB2 in one read
    assert keller.read(0x0003, 1) == keller.read(0x0002, 2)[1:]  # half a float is a register too
    for addr, count in [(0x000C, 1), (0x000B, 2), (0x0010, 4), (0x0300, 2), (0xFFFF, 1), (0x0000, 20)]:
        with pytest.raises(ModbusError) as e:
            keller.read(addr, count)
        assert e.value.code == ILLEGAL_ADDRESS
    with pytest.raises(ModbusError) as e:
        keller.read(0xFF00, 1)  # write-only
    assert e.value.code == ILLEGAL_ADDRESS
    for count in (0, 126, 1000):
        with pytest.raises(ModbusError) as e:
            keller.read(0x0002, count)
        assert e.value.code == ILLEGAL_VALUE


def test_keller_writes(keller: RegisterImage) -> None:
    assert [(r.name, v) for r, v in keller.check_write(0x020D, [7])] == [("device_address", 7.0)]
    assert [r.name for r, _ in keller.check_write(0xFF00, [0])] == ["set_zero_P1"]
    cases = [(0x0002, [0, 0], ILLEGAL_ADDRESS),   # read-only: the map's code (02)
             (0x0012, [0, 1], ILLEGAL_ADDRESS),
             (0x0C00, [1], ILLEGAL_ADDRESS),      # outside the map
             (0x020D, [0], ILLEGAL_VALUE),        # address 0 is not an address
             (0x020D, [248], ILLEGAL_VALUE),
             (0x020C, [1, 1], ILLEGAL_ADDRESS)]   # half outside
    for addr, words, code in cases:
        with pytest.raises(ModbusError) as e:
            keller.check_write(addr, words)
        assert e.value.code == code, (hex(addr), words)


def test_witmotion_scalings_at_rest(wit: RegisterImage) -> None:
    """Level and at rest: AZ = +1 g = 2048 counts in the sensor's Z-up axes; angles 0; unit quaternion."""
    wit.update({"specific_force.x": 0.0, "specific_force.y": 0.0, "specific_force.z": -GRAVITY,
                "angular_velocity.x": 0.0, "angular_velocity.y": 0.0, "angular_velocity.z": 0.0,
                "attitude.roll": 0.0, "attitude.pitch": 0.0, "attitude.yaw": 0.0,
                "magnetic_field.x": 2e-5, "magnetic_field.y": 0.0, "magnetic_field.z": 4.5e-5,
                "quaternion.w": 1.0, "quaternion.x": 0.0, "quaternion.y": 0.0, "quaternion.z": 0.0,
                "temperature": 298.15})
    regs = wit.read(0x34, 13)
    assert regs[0:3] == [0, 0, 2048]
    assert regs[6:9] == [200, 0, (-450) & 0xFFFF]   # 100 nT per count, z up
    assert regs[9:12] == [0, 0, 0]
    assert regs[12] == 2500                          # 25.00 deg C
    assert wit.read(0x51, 4) == [32767, 0, 0, 0]     # 1.0 saturates at 32767/32768


@pytest.mark.parametrize("deg,counts", [(90.0, 16384), (-90.0, -16384), (179.995, 32767), (180.0, -32768),
                                        (-180.0, -32768), (45.0, 8192)])
def test_witmotion_angles_wrap(wit: RegisterImage, deg: float, counts: int) -> None:
    """Angles are /32768 x 180 deg and wrap (180 deg is -180 deg); yaw is counter-clockwise positive."""
    wit.update({"attitude.roll": math.radians(deg), "attitude.yaw": math.radians(-deg)})
    roll, _, yaw = wit.read(0x3D, 3)
    assert roll == counts & 0xFFFF
    assert yaw == counts & 0xFFFF or (abs(deg) == 180.0 and yaw == 0x8000)


def test_witmotion_rates_and_saturation(wit: RegisterImage) -> None:
    wit.update({"angular_velocity.z": math.radians(-1000.0), "angular_velocity.x": math.radians(3000.0),
                "specific_force.x": 20 * GRAVITY})
    assert wit.read(0x39, 1) == [16384]     # -1000 deg/s in z-down is +1000 deg/s in z-up: 16384 counts
    assert wit.read(0x37, 1) == [32767]     # beyond 2000 deg/s: saturates
    assert wit.read(0x34, 1) == [32767]


@settings(max_examples=200, deadline=None)
@given(rtype=st.sampled_from(sorted(TYPES)), order=st.sampled_from(["big", "little"]),
       words=st.lists(st.integers(0, 0xFFFF), min_size=2, max_size=2))
def test_decode_encode_round_trip(rtype: str, order: str, words: list[int]) -> None:
    """Any words decode to a value that encodes back to the same words (floats: unless NaN)."""
    r = Register("x", 0, type=rtype, word_order=order)
    w = words[:r.words]
    value = r.decode(w)
    if math.isnan(value):
        assert math.isnan(r.decode(list(r.encode(value))))
    else:
        assert list(r.encode(value)) == w


@settings(max_examples=200, deadline=None)
@given(x=st.floats(-1e6, 1e6, allow_nan=False), scale=st.sampled_from([1.0, 0.01, 0.5, 100.0]))
def test_int_encoding_rounds_to_the_nearest_count(x: float, scale: float) -> None:
    r = Register("x", 0, type="int32", scale=scale)
    assert abs(r.decode(list(r.encode(x))) - x) <= scale / 2 + 1e-9 * abs(x)


def test_word_order_little() -> None:
    r = Register("x", 0, type="float32", word_order="little")
    assert r.encode(0.92863) == (r.encode(0.92863)[0], 0x3F6D)
    assert r.decode([0xBAAC, 0x3F6D]) == pytest.approx(0.92863, abs=5e-6)


def test_bundled_maps_load_and_sources() -> None:
    k, w = load_map(KELLER), load_map(WIT)
    assert k.device_id == 1 and k.transparent_id == 250 and k.read_functions == (3, 4)
    assert k.sources == {"pressure", "temperature"} and k.actions == {"device_id", "set_zero"}
    assert w.device_id == 0x50 and w.transparent_id is None
    addrs = {r.name: r.address for r in w.registers}
    assert [addrs[n] for n in ("AX", "GX", "HX", "Roll", "TEMP", "Q0", "Q3")] == [0x34, 0x37, 0x3A, 0x3D, 0x40, 0x51, 0x54]


def _map_file(tmp_path: Path, body: str) -> Path:
    p = tmp_path / "m.toml"
    p.write_text('[map]\nname = "t"\n\n' + body)
    return p


@pytest.mark.parametrize("body,match", [
    ('[[registers]]\nname = "a"\naddress = 1\nsourc = "pressure"\n', "did you mean 'source'"),
    ('[[registers]]\nname = "a"\naddress = 1\ntype = "float64"\nsource = "p"\n', "expected one of"),
    ('[[registers]]\nname = "a"\naddress = 1\nunit = "furlong"\nsource = "p"\n', "unknown unit"),
    ('[[registers]]\nname = "a"\naddress = 1\n', "needs a source signal or a constant"),
    ('[[registers]]\nname = "a"\naddress = 0x10000\nsource = "p"\n', "integer in"),
    ('[[registers]]\nname = "a"\naddress = 0xFFFF\ntype = "int32"\nsource = "p"\n', "runs past"),
    ('[[registers]]\nname = "a"\naddress = 2\ntype = "float32"\nsource = "p"\n'
     '[[registers]]\nname = "b"\naddress = 3\nsource = "p"\n', "overlaps"),
    ('[[registers]]\nname = "a"\naddress = 2\nsource = "p"\nscale = 0\n', "positive"),
])
def test_map_errors_name_file_and_key(tmp_path: Path, body: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match) as e:
        load_map(_map_file(tmp_path, body))
    assert "m.toml" in str(e.value)


def test_map_error_has_line(tmp_path: Path) -> None:
    p = _map_file(tmp_path, '[[registers]]\nname = "a"\naddress = 1\nsource = "p"\nnegate = "yes"\n')
    with pytest.raises(ConfigError) as e:
        load_map(p)
    assert e.value.line == 8 and "negate" in str(e.value)
