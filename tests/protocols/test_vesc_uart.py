"""VESC UART codec: the pyvesc vector, framing round trips, byte-at-a-time, garbage, bounds."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilsim.protocols import vesc_uart as vu

SET_RPM_5000 = bytes.fromhex("02 05 08 00001388 448d 03")  # pyvesc SetRPM(5000), reference notes


def drain(dec: vu.PacketDecoder) -> list[bytes]:
    out = []
    for _ in range(100000):
        ev = dec.next_event()
        if ev is vu.NEED_DATA:
            return out
        out.append(ev)
    raise AssertionError("decoder did not settle")


def feed(data: bytes, one_at_a_time: bool = False) -> tuple[list[bytes], vu.PacketDecoder]:
    dec = vu.PacketDecoder()
    out: list[bytes] = []
    if one_at_a_time:
        for b in data:
            dec.receive_data(bytes([b]))
            out += drain(dec)
    else:
        dec.receive_data(data)
        out += drain(dec)
    return out, dec


def test_crc_check_value():
    assert vu.crc16(b"123456789") == 0x31C3  # CRC-16/XMODEM check value


def test_known_vector_pyvesc_set_rpm():
    assert vu.frame(vu.encode_command(vu.SetRpm(5000))) == SET_RPM_5000
    payloads, _ = feed(SET_RPM_5000)
    assert payloads == [bytes.fromhex("0800001388")]
    assert vu.decode_command(payloads[0]) == vu.SetRpm(5000.0)


def test_against_pyvesc_encoder():
    pyvesc = pytest.importorskip("pyvesc", reason="pyvesc (optional independent encoder) not installed")
    # pyvesc takes the raw integers: duty x 1e5, milliamps, ERPM
    for msg, expect in [(pyvesc.SetRPM(-12000), vu.SetRpm(-12000.0)), (pyvesc.SetDutyCycle(25000), vu.SetDuty(0.25)),
                        (pyvesc.SetCurrent(12500), vu.SetCurrent(12.5)),
                        (pyvesc.SetCurrentBrake(3000), vu.SetCurrentBrake(3.0))]:
        payloads, _ = feed(pyvesc.encode(msg))
        assert [vu.decode_command(p) for p in payloads] == [expect]


@given(st.binary(min_size=1, max_size=vu.MAX_PAYLOAD))
def test_framing_round_trip_short_and_long(payload):
    wire = vu.frame(payload)
    assert wire[0] == (0x02 if len(payload) <= 255 else 0x03) and wire[-1] == 0x03
    assert feed(wire)[0] == [payload]
    assert feed(wire, one_at_a_time=True)[0] == [payload]


@settings(max_examples=150)
@given(st.lists(st.tuples(st.binary(max_size=40), st.binary(min_size=1, max_size=300)), min_size=1, max_size=5),
       st.binary(max_size=40))
def test_garbage_between_packets_is_skipped(chunks, tail):
    wire = b"".join(g + vu.frame(p) for g, p in chunks) + tail
    want = [p for _, p in chunks]
    for one in (False, True):
        got, dec = feed(wire, one)
        assert got[:len(want)] == want
        assert dec.buffered_bytes <= vu.MAX_PAYLOAD + 6 + 1


def test_truncated_packet_then_valid_one():
    good = vu.frame(vu.encode_command(vu.SetDuty(0.5)))
    truncated = vu.frame(b"\x04" + bytes(60))[:-5]
    got, dec = feed(truncated + good)
    assert got == [vu.encode_command(vu.SetDuty(0.5))]
    assert dec.stats.framing_errors + dec.stats.crc_errors >= 1 and dec.stats.bytes_skipped > 0


def test_bad_crc_is_counted_and_skipped():
    bad = bytearray(SET_RPM_5000)
    bad[-2] ^= 0xFF
    got, dec = feed(bytes(bad) + SET_RPM_5000)
    assert got == [bytes.fromhex("0800001388")] and dec.stats.crc_errors == 1


def test_huge_length_allocates_nothing_and_resyncs():
    dec = vu.PacketDecoder()
    dec.receive_data(b"\x03\xff\xff")  # claims 65535 bytes
    assert drain(dec) == [] and dec.buffered_bytes == 0 and dec.stats.framing_errors == 1
    dec.receive_data(b"\x02\xff")  # claims 255: waits, but holds only what was fed
    assert drain(dec) == [] and dec.buffered_bytes == 2
    dec.receive_data(SET_RPM_5000)
    assert drain(dec) == [bytes.fromhex("0800001388")]


@settings(max_examples=200)
@given(st.binary(max_size=2000))
def test_random_bytes_never_raise_and_stay_bounded(data):
    got, dec = feed(data)
    assert dec.buffered_bytes <= vu.MAX_PAYLOAD + 6
    got2, _ = feed(data + SET_RPM_5000)
    assert got2[-1:] == [bytes.fromhex("0800001388")]  # a valid packet after garbage is decoded


@given(st.binary(min_size=1, max_size=20), st.integers(0, 19), st.binary(max_size=3))
def test_mutated_packets_never_raise(payload, index, mutation):
    wire = bytearray(vu.frame(payload))
    wire[index % len(wire): index % len(wire) + len(mutation)] = mutation
    got, _ = feed(bytes(wire) + SET_RPM_5000)
    assert got[-1] == bytes.fromhex("0800001388")
    for p in got:
        vu.decode_command(p)


@pytest.mark.parametrize("cmd", [vu.SetDuty(-0.95), vu.SetCurrent(51.0), vu.SetCurrentBrake(3.0), vu.SetRpm(-7000),
                                 vu.GetValues(), vu.GetValues(0x81), vu.GetFwVersion(), vu.Alive(),
                                 vu.ForwardCan(3, vu.SetRpm(1000)), vu.ForwardCan(9, vu.GetValues())])
def test_command_round_trip(cmd):
    assert vu.decode_command(vu.encode_command(cmd)) == cmd


def test_bad_command_payloads_are_unsupported_not_errors():
    for payload in (b"", b"\x05\x00", b"\x22", b"\x22\x01\x22\x02\x04", b"\x32\x00", b"\x63"):
        assert isinstance(vu.decode_command(payload), vu.Unsupported)


def test_values_reply_layout_matches_the_firmware_order():
    v = vu.Values(temp_fet=25.5, temp_motor=41.0, avg_motor_current=-12.34, avg_input_current=3.21, duty_now=-0.5,
                  rpm=-21000, v_in=15.8, tachometer=-600, tachometer_abs=600, fault_code=0, controller_id=3)
    p = vu.encode_values(v)
    assert len(p) == 74 and p[0] == vu.COMM_GET_VALUES
    # independent unpacking of the first fields: int16 x10, int16 x10, int32 x100, int32 x100, id, iq, int16 x1000
    t_fet, t_mot, i_mot, i_in, _, _, duty, rpm, vin = struct.unpack_from(">hhiiiihih", p, 1)
    assert (t_fet, t_mot, i_mot, i_in, duty, rpm, vin) == (255, 410, -1234, 321, -500, -21000, 158)
    assert p[1 + 57] == 3  # controller id after fault (1 byte) and pid_pos (4 bytes)
    assert vu.decode_values(p) == v


@given(st.integers(0, (1 << 22) - 1), st.floats(-3000, 3000), st.integers(-(2 ** 31), 2 ** 31 - 1))
def test_selective_values_round_trip(mask, temp, tach):
    v = vu.Values(temp_fet=temp, temp_motor=temp, tachometer=tach, rpm=float(tach), controller_id=7)
    back = vu.decode_values(vu.encode_values(v, mask))
    assert back is not None
    assert back.temp_fet == (pytest.approx(temp, abs=0.051) if mask & 1 else 0.0)
    assert back.tachometer == (tach if mask & (1 << 13) else 0)
    assert back.controller_id == (7 if mask & (1 << 17) else 0)


def test_fw_version_reply():
    p = vu.encode_fw_version(vu.FwVersion(6, 2, "hilsim"))
    assert p[:3] == bytes([0, 6, 2]) and p[3:10] == b"hilsim\0" and len(p) == 10 + 12 + 4
