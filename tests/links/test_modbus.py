"""Modbus servers: request handling and exception codes, TCP and RTU framing fed
whole, byte at a time and back to back (several RTU frames in one read, checked
against this file's own CRC), random/mutated/truncated input (hypothesis), and the
real servers on loopback TCP and a pty (client limit, bad CRC, floods, idle drop)."""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import struct
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymodbus.framer import FramerRTU

from hilsim.links.modbus import (
    MAX_RTU_ADU,
    RTU_NEED_MORE,
    RTU_UNDELIMITED,
    ModbusRtuServer,
    ModbusTarget,
    ModbusTcpServer,
    RtuSession,
    TcpSession,
    rtu_request_length,
)
from hilsim.protocols.registers import RegisterImage, load_map
from hilsim.resources import data_path

KELLER = data_path("protocols", "keller_serie30.toml")
WIT = data_path("protocols", "witmotion_hwt905.toml")
P = 1.2e5  # [Pa] the pressure the tests' Keller shows


def keller_target(**kw: object) -> ModbusTarget:
    image = RegisterImage(load_map(KELLER))
    image.update({"pressure": P, "temperature": 290.0})
    zeros: list[float] = []
    t = ModbusTarget(image, actions={"set_zero": lambda r, v: zeros.append(v)}, **kw)  # type: ignore[arg-type]
    t.zeros = zeros  # type: ignore[attr-defined]
    return t


def pdu_read(addr: int, count: int, fc: int = 3) -> bytes:
    return struct.pack(">BHH", fc, addr, count)


def pdu_write1(addr: int, value: int) -> bytes:
    return struct.pack(">BHH", 6, addr, value)


def pdu_write(addr: int, values: list[int]) -> bytes:
    return struct.pack(f">BHHB{len(values)}H", 16, addr, len(values), 2 * len(values), *values)


def tcp(pdu: bytes, unit: int = 1, tid: int = 7) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def rtu(pdu: bytes, unit: int = 1) -> bytes:
    f = bytes([unit]) + pdu
    return f + FramerRTU.compute_CRC(f).to_bytes(2, "big")


def parse_tcp(frame: bytes) -> tuple[int, int, bytes]:
    tid, pid, length, unit = struct.unpack(">HHHB", frame[:7])
    assert pid == 0 and length == len(frame) - 6
    return tid, unit, frame[7:]


def parse_rtu(frame: bytes) -> tuple[int, bytes]:
    assert FramerRTU.check_CRC(frame[:-2], int.from_bytes(frame[-2:], "big")), frame.hex()
    return frame[0], frame[1:-2]


def regs(pdu: bytes) -> list[int]:
    assert pdu[0] in (3, 4) and pdu[1] == len(pdu) - 2, pdu.hex()
    return list(struct.unpack(f">{pdu[1] // 2}H", pdu[2:]))


def p1_words() -> list[int]:
    return list(struct.unpack(">HH", struct.pack(">f", P / 1e5)))


# -- request handling (sans-I/O) ---------------------------------------------

@pytest.mark.parametrize("pdu,expect", [
    (pdu_read(0x0002, 2), "P1"),
    (pdu_read(0x0002, 2, fc=4), "P1"),                 # input registers: the same registers
    (pdu_read(0x0000, 1, fc=1), 0x01),                 # read coils: not a function of the device
    (bytes([0x2B, 0x0E, 0x01, 0x00]), 0x01),           # device identification: not supported
    (bytes([0x41, 1, 2, 3]), 0x01),                    # a user function code
    (pdu_read(0x0C00, 2), 0x02),                       # outside the map
    (pdu_read(0x000A, 4), 0x02),                       # runs into a gap
    (pdu_read(0xFF00, 1), 0x02),                       # write-only register
    (pdu_read(0x0002, 0), 0x03),                       # count 0
    (pdu_read(0x0002, 126), 0x03),                     # count > 125
    (pdu_read(0x0002, 2)[:3], 0x03),                   # truncated PDU
    (pdu_read(0x0002, 2) + b"\0", 0x03),               # trailing byte
    (pdu_write1(0x0002, 5), 0x02),                     # read-only register
    (pdu_write(0x0002, [1, 2]), 0x02),
    (pdu_write(0x0012, [1]), 0x02),                    # half an int32, and read-only
    (pdu_write1(0x020D, 0), 0x03),                     # address out of range
    (pdu_write(0x020D, [5])[:-1], 0x03),               # byte count says 2, one byte sent
    (struct.pack(">BHHB", 16, 0x020D, 1, 4) + b"\0\5\0\0", 0x03),  # byte count != 2 * count
    (pdu_write1(0xFF00, 0), "echo"),                   # set zero
])
def test_tcp_requests_answer_as_the_device(pdu: bytes, expect: object) -> None:
    target = keller_target()
    s = TcpSession(target)
    s.receive_data(tcp(pdu, tid=0x1234))
    [reply] = s.process()
    tid, unit, resp = parse_tcp(reply)
    assert tid == 0x1234 and unit == 1
    if expect == "P1":
        assert regs(resp) == p1_words()
    elif expect == "echo":
        assert resp == pdu and target.zeros == [0.0]  # type: ignore[attr-defined]
    else:
        assert resp == bytes([(pdu[0] & 0x7F) | 0x80, expect]), resp.hex()
    assert target.stats.internal_errors == 0 and s.stats.internal_errors == 0


def test_tcp_units_and_address_write() -> None:
    """TCP reaches the device at its address, 250 (transparent), 0 and 255; other units get 0B.
    A write of the device address moves the device (the reply still carries the old unit)."""
    target = keller_target()
    s = TcpSession(target)
    for unit in (1, 250, 0, 255):
        s.receive_data(tcp(pdu_read(0x0002, 2), unit=unit))
        [(tid, u, resp)] = [parse_tcp(f) for f in s.process()]
        assert u == unit and regs(resp) == p1_words()
    s.receive_data(tcp(pdu_read(0x0002, 2), unit=9))
    assert parse_tcp(s.process()[0])[2] == bytes([0x83, 0x0B])
    s.receive_data(tcp(pdu_write1(0x020D, 9), unit=1))
    assert parse_tcp(s.process()[0])[1:] == (1, pdu_write1(0x020D, 9))
    assert target.device_id == 9
    s.receive_data(tcp(pdu_read(0x020D, 1), unit=9) + tcp(pdu_read(0x020D, 1), unit=1))
    a, b = (parse_tcp(f)[2] for f in s.process())
    assert regs(a) == [9] and b == bytes([0x83, 0x0B])


def _requests() -> list[bytes]:
    return [pdu_read(0x0002, 2), pdu_read(0x0100, 4, fc=4), pdu_read(0x0C00, 2), bytes([0x41, 0, 0]),
            pdu_write1(0x020D, 1), pdu_write(0x020D, [1]), pdu_read(0x0002, 0), pdu_read(0x0202, 2)]


def test_tcp_pipelined_whole_and_byte_at_a_time() -> None:
    stream = b"".join(tcp(p, tid=i) for i, p in enumerate(_requests()))
    whole = TcpSession(keller_target())
    whole.receive_data(stream)
    expected = whole.process()
    assert [parse_tcp(f)[0] for f in expected] == list(range(len(_requests())))
    bytewise = TcpSession(keller_target())
    got: list[bytes] = []
    for b in stream:
        bytewise.receive_data(bytes([b]))
        got += bytewise.process()
    assert got == expected and not bytewise.buffer


@pytest.mark.parametrize("header", [struct.pack(">HHHB", 1, 1, 6, 1),    # protocol id 1
                                    struct.pack(">HHHB", 1, 0, 0, 1),    # length 0
                                    struct.pack(">HHHB", 1, 0, 1, 1),    # no function code
                                    struct.pack(">HHHB", 1, 0, 300, 1)])  # longer than any ADU
def test_tcp_not_modbus_closes_the_connection(header: bytes) -> None:
    s = TcpSession(keller_target())
    s.receive_data(header + pdu_read(2, 2))
    assert s.process() == [] and s.closed and s.stats.malformed == 1


# -- RTU framing -----------------------------------------------------------------

def rtu_session(*targets: ModbusTarget) -> RtuSession:
    return RtuSession(targets or (keller_target(),))


def test_rtu_read_bad_crc_other_ids_transparent_broadcast() -> None:
    target = keller_target()
    s = rtu_session(target)
    [reply] = s.receive_data(rtu(pdu_read(0x0002, 2)))
    assert parse_rtu(reply)[0] == 1 and regs(parse_rtu(reply)[1]) == p1_words()
    bad = bytearray(rtu(pdu_read(0x0002, 2)))
    bad[-1] ^= 0x55
    assert s.receive_data(bytes(bad)) == [] and s.stats.crc_errors == 1
    assert s.resyncing  # the garbled frame's tail is searched for a frame start until the line idles
    assert s.silence() == [] and not s.pending and not s.resyncing and s.stats.crc_errors == 1
    assert s.receive_data(rtu(pdu_read(0x0002, 2), unit=2)) == [] and s.stats.ignored == 1
    [reply] = s.receive_data(rtu(pdu_read(0x0002, 2), unit=250))
    assert parse_rtu(reply)[0] == 250                       # the transparent address answers as asked
    assert s.receive_data(rtu(pdu_write1(0xFF00, 0), unit=0)) == []  # broadcast: done, no reply
    assert target.zeros == [0.0] and s.stats.broadcasts == 1  # type: ignore[attr-defined]
    assert s.receive_data(rtu(pdu_read(0x0002, 2), unit=0)) == []
    [reply] = s.receive_data(rtu(pdu_read(0x0C00, 2)))
    assert parse_rtu(reply)[1] == bytes([0x83, 0x02])


def test_rtu_unknown_function_answered_after_silence() -> None:
    """A frame the length rules cannot delimit is taken whole when the line goes idle:
    a good CRC and an unknown function gets 01; a bad CRC gets nothing."""
    s = rtu_session()
    assert s.receive_data(rtu(bytes([0x41, 1, 2, 3]))) == [] and s.pending
    [reply] = s.silence()
    assert parse_rtu(reply) == (1, bytes([0xC1, 0x01]))
    s.receive_data(rtu(bytes([0x41, 1, 2, 3]))[:-1] + b"\0")
    assert s.silence() == [] and s.stats.crc_errors == 1
    [reply] = s.receive_data(rtu(bytes([0x01, 0, 0, 0, 1])))   # read coils: delimited, 01
    assert parse_rtu(reply) == (1, bytes([0x81, 0x01]))


def test_rtu_two_devices_on_one_line() -> None:
    keller = keller_target()
    wit_image = RegisterImage(load_map(WIT))
    wit = ModbusTarget(wit_image)
    s = RtuSession([keller, wit])
    [a] = s.receive_data(rtu(pdu_read(0x0002, 2), unit=1))
    [b] = s.receive_data(rtu(pdu_read(0x1A, 1), unit=0x50))
    assert regs(parse_rtu(a)[1]) == p1_words() and regs(parse_rtu(b)[1]) == [0x50]
    assert s.receive_data(rtu(pdu_read(0x0002, 2), unit=0x51)) == []


def test_rtu_byte_at_a_time_matches_whole_frames() -> None:
    frames = [rtu(p) for p in _requests() if p[0] in (3, 4, 6, 16)]
    whole = rtu_session()
    expected = [r for f in frames for r in whole.receive_data(f) + whole.silence()]
    bytewise = rtu_session()
    got: list[bytes] = []
    for f in frames:
        for b in f:
            got += bytewise.receive_data(bytes([b]))
        got += bytewise.silence()
    assert got == expected and len(expected) == len(frames)


# -- RTU: frames back to back (several in one read) ------------------------------
# Expected bytes are built here with struct and this file's own CRC-16/MODBUS,
# independently of the project's and pymodbus's framing.

def crc16_modbus(data: bytes) -> int:
    """CRC-16/MODBUS (poly 0xA001 reflected, init 0xFFFF), bit by bit."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def adu(unit: int, pdu: bytes) -> bytes:
    """An RTU frame: address, PDU, CRC low byte first."""
    body = bytes([unit]) + pdu
    return body + struct.pack("<H", crc16_modbus(body))


def regs_reply(unit: int, words: list[int], fc: int = 3) -> bytes:
    return adu(unit, struct.pack(f">BB{len(words)}H", fc, 2 * len(words), *words))


def exc_reply(unit: int, fc: int, code: int) -> bytes:
    return adu(unit, struct.pack(">BB", fc | 0x80, code))


P1_WORDS = list(struct.unpack(">HH", struct.pack(">f", 1.2)))  # Keller P1 [bar] for P = 1.2e5 Pa


def test_crc16_modbus_reference_vectors() -> None:
    assert crc16_modbus(b"123456789") == 0x4B37                  # the CRC catalogue's check value
    assert crc16_modbus(bytes([0x02, 0x07])) == 0x1241           # Modbus serial line spec, appendix B
    assert adu(1, bytes.fromhex("030000000a"))[-2:] == bytes([0xC5, 0xCD])  # sent low byte first
    assert adu(1, pdu_read(0x0002, 2)) == rtu(pdu_read(0x0002, 2))  # the helpers above agree


def wit_target() -> ModbusTarget:
    return ModbusTarget(RegisterImage(load_map(WIT)))


ONE_DEVICE = [  # (request, expected reply), all to the Keller at address 1
    (adu(1, pdu_read(0x0002, 2)), regs_reply(1, P1_WORDS)),
    (adu(1, pdu_read(0x020D, 1)), regs_reply(1, [1])),              # its address register
    (adu(1, pdu_read(0x0C00, 2)), exc_reply(1, 3, 2)),              # outside the map: 02
]
TWO_DEVICES = [  # the Keller at 1 and a WitMotion IMU at 0x50 on one line
    (adu(1, pdu_read(0x0002, 2, fc=4)), regs_reply(1, P1_WORDS, fc=4)),
    (adu(0x50, pdu_read(0x1A, 1)), regs_reply(0x50, [0x50])),       # IICADDR: its address
    (adu(1, pdu_write1(0xFF00, 0)), adu(1, pdu_write1(0xFF00, 0))),  # set zero: echoed
]


@pytest.mark.parametrize("n", [2, 3])
@pytest.mark.parametrize("devices", ["one", "two"])
def test_rtu_back_to_back_requests_each_answered_in_order(devices: str, n: int) -> None:
    """Two or three requests in one read: one reply each, in order, at once (no silence needed),
    byte for byte as computed here. (pymodbus's FramerRTU.decode reports the whole buffer as
    used, so only the first was answered.)"""
    keller = keller_target()
    s = RtuSession([keller] if devices == "one" else [keller, wit_target()])
    pairs = (ONE_DEVICE if devices == "one" else TWO_DEVICES)[:n]
    assert s.receive_data(b"".join(req for req, _ in pairs)) == [rep for _, rep in pairs]
    assert not s.pending and not s.resyncing
    assert s.silence() == []
    assert s.stats.replies == n and s.stats.crc_errors == 0 and s.stats.internal_errors == 0


def test_rtu_back_to_back_with_broadcast_and_other_address() -> None:
    """A broadcast write and a frame for another device between two requests: no reply for
    those two, the requests around them answered in order."""
    keller = keller_target()
    s = RtuSession([keller])
    stream = (adu(1, pdu_read(0x0002, 2)) + adu(0, pdu_write1(0xFF00, 0)) + adu(7, pdu_read(0x0002, 2))
              + adu(1, pdu_read(0x020D, 1)))
    assert s.receive_data(stream) == [regs_reply(1, P1_WORDS), regs_reply(1, [1])]
    assert keller.zeros == [0.0] and s.stats.broadcasts == 1 and s.stats.ignored == 1  # type: ignore[attr-defined]


BAD_MIDDLE = adu(1, pdu_write(0xFF00, [0]))  # 01 10 FF00 0001 02 0000 CRC: would set zero


@pytest.mark.parametrize("pos", range(len(BAD_MIDDLE)))
@pytest.mark.parametrize("flip", [0x01, 0x80, 0xFF])
def test_rtu_bad_crc_between_good_frames(pos: int, flip: int) -> None:
    """Whichever byte of the middle frame is garbled (address, function code, byte count, data,
    CRC): it is dropped and counted, its write is not done, and the frames before and after
    it are answered, in order (by the time the line goes idle at the latest)."""
    keller = keller_target()
    s = RtuSession([keller])
    bad = bytearray(BAD_MIDDLE)
    bad[pos] ^= flip
    first, last = adu(1, pdu_read(0x0002, 2)), adu(1, pdu_read(0x020D, 1))
    replies = s.receive_data(first + bytes(bad) + last) + s.silence()
    assert replies == [regs_reply(1, P1_WORDS), regs_reply(1, [1])]
    assert s.stats.crc_errors == 1 and keller.zeros == []  # type: ignore[attr-defined]
    assert s.stats.internal_errors == 0 and not s.pending and not s.resyncing


def test_rtu_bad_crc_between_good_frames_answered_at_once() -> None:
    """A garbled CRC (the length rules still hold): the frame behind it is answered in the same
    read, and the next read starts clean."""
    s = rtu_session()
    bad = bytearray(adu(1, pdu_read(0x0002, 2)))
    bad[-2] ^= 0x40
    assert s.receive_data(adu(1, pdu_read(0x0002, 2)) + bytes(bad) + adu(1, pdu_read(0x020D, 1))) == [
        regs_reply(1, P1_WORDS), regs_reply(1, [1])]
    assert s.stats.crc_errors == 1 and not s.pending and not s.resyncing
    assert s.receive_data(adu(1, pdu_read(0x0C00, 2))) == [exc_reply(1, 3, 2)]


def test_rtu_undelimitable_frame_still_ends_at_silence() -> None:
    """A user function (no length rule) behind a good frame: the good one is answered at once,
    the other when the line goes idle; two of them run together fail their CRC."""
    s = rtu_session()
    user = adu(1, bytes([0x41, 1, 2, 3]))
    assert s.receive_data(adu(1, pdu_read(0x0002, 2)) + user) == [regs_reply(1, P1_WORDS)]
    assert s.pending and s.silence() == [exc_reply(1, 0x41, 1)]
    assert s.receive_data(user + user) == [] and s.silence() == [] and s.stats.crc_errors == 1


@pytest.mark.parametrize("frame,length", [
    (adu(1, pdu_read(0, 1, fc=1)), 8), (adu(1, pdu_read(0, 1, fc=2)), 8), (adu(1, pdu_read(0, 1)), 8),
    (adu(1, pdu_read(0, 1, fc=4)), 8), (adu(1, struct.pack(">BHH", 5, 0, 0xFF00)), 8),
    (adu(1, pdu_write1(0, 1)), 8),
    (adu(1, bytes([0x07])), 4), (adu(1, bytes([0x0B])), 4), (adu(1, bytes([0x0C])), 4), (adu(1, bytes([0x11])), 4),
    (adu(1, struct.pack(">BHHB", 0x0F, 0, 10, 2) + b"\xff\x03"), 11),
    (adu(1, pdu_write(0, [1, 2, 3])), 15),
    (adu(1, struct.pack(">BHHHHB3H", 0x17, 0, 2, 8, 3, 6, 1, 2, 3)), 19),
    (adu(1, struct.pack(">BB7B", 0x14, 7, 6, 0, 4, 0, 1, 0, 2)), 12),
    (adu(1, struct.pack(">BB9B", 0x15, 9, 6, 0, 4, 0, 7, 0, 1, 0xAB, 0xCD)), 14),
    (adu(1, struct.pack(">BHHH", 0x16, 4, 0xF2, 0x25)), 10),
    (adu(1, struct.pack(">BH", 0x18, 0x04DE)), 6),
    (adu(1, struct.pack(">BHH", 0x08, 0x0000, 0xA537)), 8),  # diagnostics, return query data, 2 bytes
    (adu(1, struct.pack(">BHH", 0x08, 0x000A, 0)), 8),       # clear counters
    (adu(1, bytes([0x2B, 0x0E, 0x01, 0x00])), 7),            # read device identification
])
def test_rtu_request_lengths_by_function(frame: bytes, length: int) -> None:
    """The request lengths of the Modbus spec (examples from its section 6), and that a device
    answers each of them once at once when it is sent twice back to back."""
    assert rtu_request_length(frame) == length == len(frame)
    for cut in range(len(frame)):  # no decision before the bytes that carry the length arrived
        assert rtu_request_length(frame[:cut]) in (RTU_NEED_MORE, length)
    s = rtu_session()
    replies = s.receive_data(frame + frame)
    assert len(replies) == 2 and replies[0] == replies[1] and not s.pending


@pytest.mark.parametrize("frame", [
    adu(1, bytes([0x41, 1, 2, 3])),                                  # a user function
    adu(1, struct.pack(">BHHH", 0x08, 0x0000, 0xA537, 0x1234)),      # return query data, 4 bytes
    adu(1, struct.pack(">BHH", 0x08, 0x0005, 0)),                     # a reserved sub-function
    adu(1, bytes([0x2B, 0x0D, 0, 0])),                               # MEI 0D (CANopen)
    adu(1, bytes([0x83, 0x02])),                                     # an exception response
    adu(1, struct.pack(">BHHB", 0x10, 0, 127, 254) + bytes(6)),      # byte count past 256 bytes
])
def test_rtu_undelimitable_requests_wait_for_silence(frame: bytes) -> None:
    assert rtu_request_length(frame) == RTU_UNDELIMITED
    s = rtu_session()
    assert s.receive_data(frame) == [] and s.pending
    [reply] = s.silence()
    assert reply[0] == 1 and reply[1] == frame[1] | 0x80


# a strategy of valid requests the length rules delimit, to the devices on the line and others
_UNITS = st.sampled_from([0, 1, 2, 250, 0x50])


@st.composite
def delimited_requests(draw: st.DrawFn) -> bytes:
    unit = draw(_UNITS)
    kind = draw(st.sampled_from(["read", "write1", "write", "fixed", "counted", "diag", "mei"]))
    word = st.integers(0, 0xFFFF)
    if kind == "read":  # mostly the devices' own registers, so that most replies carry data
        addr = draw(st.sampled_from([0x0002, 0x0100, 0x020D, 0x0C00, 0x1A, 0x34, 0x3D]) | word)
        pdu = pdu_read(addr, draw(st.integers(0, 130)), fc=draw(st.sampled_from([3, 4])))
    elif kind == "write1":
        pdu = pdu_write1(draw(st.sampled_from([0xFF00, 0x020D, 0x0002, 0x00]) | word),
                         draw(st.sampled_from([0, 1, 9]) | word))
    elif kind == "write":
        pdu = pdu_write(draw(st.sampled_from([0xFF00, 0x0002]) | word), draw(st.lists(word, min_size=1, max_size=10)))
    elif kind == "fixed":
        fc = draw(st.sampled_from([1, 2, 5, 7, 0x0B, 0x0C, 0x11, 0x16, 0x18]))
        size = {7: 0, 0x0B: 0, 0x0C: 0, 0x11: 0, 0x16: 6, 0x18: 2}.get(fc, 4)
        pdu = bytes([fc]) + draw(st.binary(min_size=size, max_size=size))
    elif kind == "counted":
        fc = draw(st.sampled_from([0x0F, 0x14, 0x15, 0x17]))
        head = draw(st.binary(min_size={0x0F: 4, 0x17: 8}.get(fc, 0), max_size={0x0F: 4, 0x17: 8}.get(fc, 0)))
        data = draw(st.binary(max_size=40))
        pdu = bytes([fc]) + head + bytes([len(data)]) + data
    elif kind == "diag":
        pdu = struct.pack(">BHH", 8, draw(st.sampled_from([0, 1, 2, 4, 0x0A, 0x0B, 0x12, 0x14])), draw(word))
    else:
        pdu = bytes([0x2B, 0x0E]) + draw(st.binary(min_size=2, max_size=2))
    return adu(unit, pdu)


def _line() -> RtuSession:
    return RtuSession([keller_target(), wit_target()])


@settings(max_examples=300, deadline=None)
@given(requests=st.lists(delimited_requests(), min_size=1, max_size=8), data=st.data())
def test_rtu_any_split_of_back_to_back_requests_answers_as_one_by_one(requests: list[bytes],
                                                                      data: st.DataObject) -> None:
    """Valid requests sent back to back, the stream cut anywhere: the same replies, in the same
    order, as when each request is sent on its own; all of them before the line goes idle."""
    one_by_one = _line()
    expected = [r for req in requests for r in one_by_one.receive_data(req) + one_by_one.silence()]
    stream = b"".join(requests)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=12), label="cuts"))
    split = _line()
    got: list[bytes] = []
    for a, b in zip([0, *cuts], [*cuts, len(stream)]):
        got += split.receive_data(stream[a:b])
        assert len(split.buffer) <= MAX_RTU_ADU
    assert not split.pending and not split.resyncing
    assert got == expected and split.silence() == []
    answering = sum(1 for req in requests if req[0] in (1, 250, 0x50))
    assert len(expected) <= answering  # at most one reply a request (an address write may move a device)
    assert split.stats.crc_errors == 0 and split.stats.internal_errors == 0
    assert all(t.stats.internal_errors == 0 for t in split.targets)
    for reply in got:
        assert crc16_modbus(reply[:-2]) == struct.unpack("<H", reply[-2:])[0]


@settings(max_examples=300, deadline=None)
@given(requests=st.lists(delimited_requests(), max_size=4), garbage=st.binary(max_size=80),
       at=st.integers(0, 1 << 16), chunk=st.integers(1, 40))
def test_rtu_any_bytes_give_the_same_replies_however_cut(requests: list[bytes], garbage: bytes, at: int,
                                                         chunk: int) -> None:
    """Garbage among valid requests: the replies and counters depend on the bytes, not on how
    the reads cut them (whole, byte at a time, in chunks); the buffer stays bounded."""
    stream = b"".join(requests)
    at %= len(stream) + 1
    stream = stream[:at] + garbage + stream[at:]
    results = []
    for size in (len(stream) or 1, 1, chunk):
        s = _line()
        out: list[bytes] = []
        for i in range(0, len(stream), size):
            out += s.receive_data(stream[i:i + size])
            assert len(s.buffer) <= MAX_RTU_ADU
        out += s.silence()
        assert s.stats.internal_errors == 0
        results.append((out, s.stats.crc_errors, s.stats.malformed, s.stats.requests))
    assert results[1] == results[0] and results[2] == results[0]


# -- robustness: random bytes, mutations, truncations ------------------------

GOOD = [rtu(p) for p in (pdu_read(0x0002, 2), pdu_write1(0x020D, 1), pdu_write(0x020D, [1]))]


def _check_rtu_still_serves(s: RtuSession) -> None:
    s.silence()
    [reply] = s.receive_data(rtu(pdu_read(0x0002, 2)))
    assert regs(parse_rtu(reply)[1]) == p1_words()


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=600), chunk=st.integers(1, 64))
def test_rtu_random_bytes(data: bytes, chunk: int) -> None:
    s = rtu_session()
    for i in range(0, len(data), chunk):
        for reply in s.receive_data(data[i:i + chunk]):
            parse_rtu(reply)  # anything sent is a well-formed frame
    for reply in s.silence():
        parse_rtu(reply)
    assert s.stats.internal_errors == 0 and s.targets[0].stats.internal_errors == 0
    _check_rtu_still_serves(s)


@settings(max_examples=300, deadline=None)
@given(frame=st.sampled_from(GOOD), pos=st.integers(0, 20), byte=st.integers(0, 255),
       cut=st.integers(0, 20), split=st.integers(1, 12))
def test_rtu_mutated_and_truncated_frames(frame: bytes, pos: int, byte: int, cut: int, split: int) -> None:
    mutated = bytearray(frame)
    mutated[pos % len(mutated)] = byte
    for variant in (bytes(mutated), frame[:cut % len(frame)]):
        s = rtu_session()
        replies = s.receive_data(variant[:split]) + s.receive_data(variant[split:]) + s.silence()
        for reply in replies:
            unit, pdu = parse_rtu(reply)
            assert unit in (1, 250) and pdu[0] & 0x7F == variant[1] & 0x7F
        if variant != frame and variant[:len(frame)] != frame:  # changed frames with a bad CRC: silence
            if not FramerRTU.check_CRC(variant[:-2], int.from_bytes(variant[-2:], "big")):
                assert replies == []
        assert s.stats.internal_errors == 0
        _check_rtu_still_serves(s)


@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=600), chunk=st.integers(1, 64))
def test_tcp_random_bytes(data: bytes, chunk: int) -> None:
    """Random bytes: replies are well-formed MBAP frames or the connection is closed;
    the target serves a fresh connection either way."""
    target = keller_target()
    s = TcpSession(target)
    for i in range(0, len(data), chunk):
        s.receive_data(data[i:i + chunk])
        for reply in s.process():
            tid, unit, pdu = parse_tcp(reply)
            assert pdu and (pdu[0] in (3, 4, 6, 16) or pdu[0] & 0x80)
    assert s.stats.internal_errors == 0 and target.stats.internal_errors == 0
    fresh = TcpSession(target)
    fresh.receive_data(tcp(pdu_read(0x0002, 2)))
    assert regs(parse_tcp(fresh.process()[0])[2]) == p1_words()


@settings(max_examples=300, deadline=None)
@given(pdu=st.binary(min_size=1, max_size=260), unit=st.integers(0, 255))
def test_tcp_any_pdu_gets_one_reply(pdu: bytes, unit: int) -> None:
    """Inside a valid MBAP header any PDU gets exactly one reply with the same tid."""
    s = TcpSession(keller_target())
    s.receive_data(tcp(pdu[:253], unit=unit, tid=99))
    replies = s.process()
    if len(pdu[:253]) + 1 > 254:
        assert s.closed
        return
    [reply] = replies
    tid, u, resp = parse_tcp(reply)
    assert tid == 99 and u == unit and resp[0] & 0x7F == pdu[0] & 0x7F
    assert s.stats.internal_errors == 0


# -- real servers ------------------------------------------------------------------

async def _tcp_roundtrip(port: int, frame: bytes, timeout: float = 2.0) -> bytes:
    r, w = await asyncio.open_connection("127.0.0.1", port)
    try:
        w.write(frame)
        await w.drain()
        head = await asyncio.wait_for(r.readexactly(6), timeout)
        return head + await asyncio.wait_for(r.readexactly(struct.unpack(">H", head[4:6])[0]), timeout)
    finally:
        w.close()


def test_tcp_server_survives_abuse_and_limits_clients(caplog: pytest.LogCaptureFixture) -> None:
    async def main() -> None:
        from pymodbus.client import AsyncModbusTcpClient

        srv = ModbusTcpServer("keller-test", keller_target(), port=0, max_clients=4)
        _, port = await srv.start()
        try:
            client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=2, retries=0)
            await client.connect()
            rr = await client.read_holding_registers(0x0002, count=2, device_id=1)
            assert client.convert_from_registers(rr.registers, client.DATATYPE.FLOAT32) == pytest.approx(P / 1e5)
            # not Modbus: the server closes that connection
            r, w = await asyncio.open_connection("127.0.0.1", port)
            w.write(b"GET / HTTP/1.0\r\n\r\n")
            assert await asyncio.wait_for(r.read(), 2.0) == b""
            w.close()
            # truncated frame, then hang up; reset mid-frame
            r, w = await asyncio.open_connection("127.0.0.1", port)
            w.write(tcp(pdu_read(2, 2))[:9])
            await w.drain()
            w.close()
            sock = socket.create_connection(("127.0.0.1", port))
            sock.sendall(tcp(pdu_read(2, 2))[:5])
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            sock.close()
            reply = await _tcp_roundtrip(port, tcp(bytes([0x41]), tid=3))
            assert parse_tcp(reply) == (3, 1, bytes([0xC1, 0x01]))
            # the client limit: 4 connections, the 5th refused with a log line
            await asyncio.sleep(0.05)
            extra = [await asyncio.open_connection("127.0.0.1", port) for _ in range(3)]
            caplog.clear()
            with caplog.at_level(logging.WARNING, logger="hilsim.links.tcp"):
                r5, w5 = await asyncio.open_connection("127.0.0.1", port)
                assert await asyncio.wait_for(r5.read(), 2.0) == b""
            assert any("client limit 4" in m for m in caplog.messages)
            assert srv.link.stats.refused == 1
            for _, w in extra + [(r5, w5)]:
                w.close()
            rr = await client.read_holding_registers(0x0100, count=4, device_id=1)
            assert rr.registers[:2] == p1_words()
            client.close()
            assert srv.stats.internal_errors == 0 and srv.stats.malformed == 1
        finally:
            await srv.close()

    asyncio.run(main())


def test_tcp_server_idle_timeout_is_passed_to_its_link() -> None:
    """``idle_timeout`` reaches the TcpServer (default: none): a client that stays silent
    after its answer is dropped, a fresh one is served."""
    assert ModbusTcpServer("keller-idle", keller_target()).link.idle_timeout is None

    async def main() -> None:
        srv = ModbusTcpServer("keller-idle", keller_target(), port=0, idle_timeout=0.2)
        assert srv.link.idle_timeout == 0.2
        _, port = await srv.start()
        try:
            r, w = await asyncio.open_connection("127.0.0.1", port)
            w.write(tcp(pdu_read(0x0002, 2), tid=5))
            head = await asyncio.wait_for(r.readexactly(6), 2.0)
            assert parse_tcp(head + await r.readexactly(struct.unpack(">H", head[4:6])[0]))[0] == 5
            assert await asyncio.wait_for(r.read(), 5.0) == b""  # idle: dropped by the server
            w.close()
            reply = await _tcp_roundtrip(port, tcp(pdu_read(0x0002, 2), tid=6))
            assert parse_tcp(reply)[0] == 6 and regs(parse_tcp(reply)[2]) == p1_words()
        finally:
            await srv.close()

    asyncio.run(main())


def _pty_exchange(path: str, frame: bytes, wait: float) -> bytes:
    """Write a frame to the pty like a serial master and collect what comes back in ``wait`` s."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        os.write(fd, frame)
        out = b""
        end = time.monotonic() + wait
        while time.monotonic() < end:
            try:
                out += os.read(fd, 256)
            except BlockingIOError:
                time.sleep(0.002)
        return out
    finally:
        os.close(fd)


def test_rtu_server_on_pty(tmp_path: Path) -> None:
    """A pymodbus RTU master opens the path as a serial port; bad CRCs get silence,
    the server keeps answering; replies take at least their time on the wire."""
    async def main() -> None:
        from pymodbus.client import AsyncModbusSerialClient
        from pymodbus.framer import FramerType

        srv = ModbusRtuServer("keller-rtu", tmp_path / "keller.tty", [keller_target()], baudrate=9600, parity="E")
        path = await srv.start()
        try:
            # a pty carries no parity bit (some kernels even refuse PARENB on one): the client
            # opens it 8N1; the server's parity only sets its byte time (11 bits for 8E1)
            client = AsyncModbusSerialClient(path, framer=FramerType.RTU, baudrate=9600, parity="N",
                                             timeout=1, retries=0)
            await client.connect()
            rr = await client.read_holding_registers(0x0002, count=2, device_id=1)
            assert rr.registers == p1_words()
            client.close()
            loop = asyncio.get_running_loop()
            bad = bytearray(rtu(pdu_read(0x0002, 2)))
            bad[3] ^= 1
            assert await loop.run_in_executor(None, _pty_exchange, path, bytes(bad), 0.3) == b""
            assert srv.stats.crc_errors == 1
            t0 = time.monotonic()
            reply = await loop.run_in_executor(None, _pty_exchange, path, rtu(pdu_read(0x0100, 4)), 0.4)
            assert regs(parse_rtu(reply)[1])[:2] == p1_words()
            assert time.monotonic() - t0 >= len(reply) * 11 / 9600  # 8E1: 11 bits a byte
            # garbage, then a good frame after the line went quiet
            await loop.run_in_executor(None, _pty_exchange, path, os.urandom(40), 0.05)
            reply = await loop.run_in_executor(None, _pty_exchange, path, rtu(bytes([0x41, 0])), 0.3)
            assert parse_rtu(reply) == (1, bytes([0xC1, 0x01]))
            assert srv.stats.internal_errors == 0
        finally:
            await srv.close()
        assert not (tmp_path / "keller.tty").exists()

    asyncio.run(main())


def test_rtu_server_on_pty_answers_requests_written_together(tmp_path: Path) -> None:
    """A master writes requests to two devices and a third, back to back, in one os.write:
    the server reads them in one chunk and sends every reply, in order (pyserial reads them)."""
    import serial

    pairs = [TWO_DEVICES[0], TWO_DEVICES[1], ONE_DEVICE[1]]
    requests = b"".join(req for req, _ in pairs)
    expected = b"".join(rep for _, rep in pairs)

    def master(path: str) -> bytes:
        with serial.Serial(path, baudrate=9600, timeout=2.0) as port:
            assert os.write(port.fileno(), requests) == len(requests)
            return port.read(len(expected))

    async def main() -> None:
        srv = ModbusRtuServer("line", tmp_path / "line.tty", [keller_target(), wit_target()], baudrate=9600)
        chunks: list[int] = []
        on_data = srv.link.on_data
        assert on_data is not None

        def spy(data: bytes) -> None:
            chunks.append(len(data))
            on_data(data)

        srv.link.on_data = spy
        path = await srv.start()
        try:
            got = await asyncio.get_running_loop().run_in_executor(None, master, path)
            assert got == expected
            assert chunks[0] == len(requests)  # the server did get the requests in one read
            assert srv.stats.replies == 3 and srv.stats.crc_errors == 0 and srv.stats.internal_errors == 0
        finally:
            await srv.close()

    asyncio.run(main())


def test_flood_does_not_starve_a_poller() -> None:
    """Clients pipelining requests as fast as they can, and clients sending garbage:
    a poller at 100 Hz still gets every answer, promptly (generous bound, not a benchmark)."""
    async def main() -> None:
        srv = ModbusTcpServer("flood", keller_target(), port=0, max_clients=16)
        _, port = await srv.start()
        stop = asyncio.Event()

        async def flooder(garbage: bool) -> None:
            burst = os.urandom(512) if garbage else tcp(pdu_read(0x0000, 12)) * 40
            for _ in range(10_000):
                if stop.is_set():
                    return
                try:
                    r, w = await asyncio.open_connection("127.0.0.1", port)
                    for _ in range(200):
                        if stop.is_set():
                            break
                        w.write(burst)
                        await w.drain()
                        if not garbage:
                            await r.readexactly(len(burst) // 17 * 33)  # 40 replies of 33 bytes
                    w.close()
                except (ConnectionError, asyncio.IncompleteReadError):
                    await asyncio.sleep(0.001)

        tasks = [asyncio.ensure_future(flooder(i >= 4)) for i in range(6)]
        await asyncio.sleep(0.1)
        r, w = await asyncio.open_connection("127.0.0.1", port)
        rtts = []
        for i in range(100):
            t0 = time.perf_counter()
            w.write(tcp(pdu_read(0x0002, 2), tid=i))
            head = await asyncio.wait_for(r.readexactly(6), 2.0)
            body = await r.readexactly(struct.unpack(">H", head[4:6])[0])
            rtts.append(time.perf_counter() - t0)
            assert parse_tcp(head + body)[0] == i and regs(body[1:]) == p1_words()
            await asyncio.sleep(max(0.0, 0.01 - rtts[-1]))
        stop.set()
        w.close()
        await asyncio.gather(*tasks, return_exceptions=True)
        await srv.close()
        rtts.sort()
        print(f"flood: poller p50 {rtts[50] * 1e3:.2f} ms p99 {rtts[98] * 1e3:.2f} ms, {srv.stats.replies} replies")
        assert rtts[98] < 0.25, f"p99 {rtts[98] * 1e3:.1f} ms"  # starvation, not a benchmark
        assert srv.stats.internal_errors == 0 and srv.stats.replies > 1000
        assert srv.stats.throttled >= 4  # every flooder went over its 1000 requests/s budget

    asyncio.run(main())
