"""VESC CAN codec: the DBC against the reference layouts, known vectors, round trips, bad frames."""

from __future__ import annotations

import struct

import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilsim.protocols import vesc_can as vc
from hilsim.protocols.can import CanFrame

# (packet number, [(signal, first byte, bits, scale)]) from the reference notes (bldc comm_can)
REFERENCE = {
    "SET_DUTY": (0, [("duty", 0, 32, 1e5)]),
    "SET_CURRENT": (1, [("current", 0, 32, 1e3)]),
    "SET_CURRENT_BRAKE": (2, [("current_brake", 0, 32, 1e3)]),
    "SET_RPM": (3, [("erpm", 0, 32, 1)]),
    "SET_CURRENT_REL": (10, [("current_rel", 0, 32, 1e5)]),
    "STATUS_1": (9, [("erpm", 0, 32, 1), ("current", 4, 16, 10), ("duty", 6, 16, 1000)]),
    "STATUS_4": (16, [("temp_fet", 0, 16, 10), ("temp_motor", 2, 16, 10), ("current_in", 4, 16, 10),
                      ("pid_pos", 6, 16, 50)]),
    "STATUS_5": (27, [("tachometer", 0, 32, 1), ("v_in", 4, 16, 10), ("reserved", 6, 16, 1)]),
}


def test_dbc_layouts_match_the_reference_for_every_controller():
    db = cantools.database.load_file(str(vc.dbc_path()))
    for cid in range(1, 9):
        for name, (number, signals) in REFERENCE.items():
            msg = db.get_message_by_name(f"VESC{cid}_{name}")
            assert msg.is_extended_frame
            assert msg.frame_id == (number << 8) | cid
            assert msg.length == (4 if name.startswith("SET") else 8)
            assert [s.name for s in msg.signals] == [s[0] for s in signals]
            for sig, (_, byte, bits, scale) in zip(msg.signals, signals):
                assert sig.byte_order == "big_endian" and sig.is_signed
                assert sig.start == byte * 8 + 7 and sig.length == bits
                assert sig.scale == pytest.approx(1 / scale) and sig.offset == 0
    assert len(db.messages) == 8 * len(REFERENCE)


def test_known_vector_51_amps_to_controller_23():
    frame = vc.encode(vc.VescCommand(23, "SET_CURRENT", 51.0))
    assert frame.arbitration_id == 0x0117 and frame.is_extended
    assert frame.data == bytes.fromhex("0000C738")
    assert vc.decode(CanFrame(0x0117, bytes.fromhex("0000C738"))) == vc.VescCommand(23, "SET_CURRENT", 51.0)


def test_status_bytes_are_big_endian_scaled_integers():
    f1 = vc.encode(vc.Status1(7, erpm=-25200, current=12.3, duty=-0.5))
    assert f1.arbitration_id == (9 << 8) | 7
    assert f1.data == struct.pack(">ihh", -25200, 123, -500)
    f4 = vc.encode(vc.Status4(7, temp_fet=21.5, temp_motor=40.2, current_in=3.3, pid_pos=10.0))
    assert f4.data == struct.pack(">hhhh", 215, 402, 33, 500)
    f5 = vc.encode(vc.Status5(7, tachometer=-123456, v_in=15.9))
    assert f5.arbitration_id == (27 << 8) | 7 and f5.data == struct.pack(">ihh", -123456, 159, 0)


def test_status_values_beyond_a_field_saturate():
    f = vc.encode(vc.Status1(1, erpm=1e12, current=-1e6, duty=float("nan")))
    assert struct.unpack(">ihh", f.data) == (2 ** 31 - 1, -32768, 0)


def test_six_byte_command_with_off_delay_is_accepted():
    data = struct.pack(">ih", 5000, 250)
    assert vc.decode(CanFrame((3 << 8) | 2, data)) == vc.VescCommand(2, "SET_RPM", 5000.0)


@pytest.mark.parametrize("frame", [
    CanFrame(0x117, bytes(4), is_extended=False),       # standard id
    CanFrame(0x1404060A, bytes(8)),                     # a DroneCAN id (bits above 15)
    CanFrame((5 << 8) | 1, bytes(8)),                   # FILL_RX_BUFFER: not handled here
])
def test_frames_that_are_not_ours_give_none(frame):
    assert vc.decode(frame) is None


def test_short_and_remote_frames_are_bad():
    assert isinstance(vc.decode(CanFrame((3 << 8) | 1, b"\x00\x01")), vc.BadFrame)
    assert isinstance(vc.decode(CanFrame((9 << 8) | 1, bytes(7))), vc.BadFrame)
    assert isinstance(vc.decode(CanFrame((3 << 8) | 1, b"", is_remote=True, dlc=4)), vc.BadFrame)


def test_our_misuse_raises():
    with pytest.raises(ValueError):
        vc.encode(vc.VescCommand(1, "SET_POS", 1.0))
    with pytest.raises(ValueError):
        vc.encode(vc.VescCommand(256, "SET_RPM", 1.0))
    with pytest.raises(ValueError):
        vc.encode(vc.VescCommand(1, "SET_RPM", 3e9))


_SCALES = {"SET_DUTY": 1e5, "SET_CURRENT": 1e3, "SET_CURRENT_BRAKE": 1e3, "SET_RPM": 1.0, "SET_CURRENT_REL": 1e5}


@given(cid=st.integers(0, 255), name=st.sampled_from(sorted(_SCALES)), raw=st.integers(-(2 ** 31), 2 ** 31 - 1))
def test_command_round_trip(cid, name, raw):
    value = raw / _SCALES[name]
    frame = vc.encode(vc.VescCommand(cid, name, value))
    assert frame.data == struct.pack(">i", raw)  # independent packing
    back = vc.decode(frame)
    assert isinstance(back, vc.VescCommand) and back.controller_id == cid and back.command == name
    assert back.value == pytest.approx(value, abs=0.5 / _SCALES[name])


@given(cid=st.integers(0, 255), erpm=st.integers(-(2 ** 31), 2 ** 31 - 1),
       current=st.floats(-3276.8, 3276.7), duty=st.floats(-32.768, 32.767),
       t=st.floats(-3000, 3000), tach=st.integers(-(2 ** 31), 2 ** 31 - 1), v=st.floats(0, 3000))
def test_status_round_trip(cid, erpm, current, duty, t, tach, v):
    s1 = vc.decode(vc.encode(vc.Status1(cid, erpm, current, duty)))
    assert isinstance(s1, vc.Status1) and s1.erpm == erpm
    assert s1.current == pytest.approx(current, abs=0.051) and s1.duty == pytest.approx(duty, abs=0.00051)
    s4 = vc.decode(vc.encode(vc.Status4(cid, t, t / 2, current / 4, 0.0)))
    assert isinstance(s4, vc.Status4) and s4.temp_fet == pytest.approx(t, abs=0.051)
    s5 = vc.decode(vc.encode(vc.Status5(cid, tach, v)))
    assert s5 == vc.Status5(cid, tach, pytest.approx(v, abs=0.051))


@settings(max_examples=300)
@given(ident=st.integers(0, 0x1FFFFFFF), data=st.binary(max_size=8), ext=st.booleans())
def test_any_frame_decodes_without_raising(ident, data, ext):
    if not ext:
        ident &= 0x7FF
    out = vc.decode(CanFrame(ident, data, ext))
    assert out is None or isinstance(out, (vc.BadFrame, vc.VescCommand, vc.Status1, vc.Status4, vc.Status5))
