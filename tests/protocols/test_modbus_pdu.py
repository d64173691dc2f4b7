"""The Modbus PDU codec (hilsim.protocols.modbus_pdu) against the Modbus specifications.

Expected bytes come from the specs' own examples (Modbus Application Protocol V1.1b3,
section 6: the request/response examples of 03, 04, 06, 16; section 7: the exception
example; Modbus over Serial Line V1.02, appendix B: the CRC example), from widely published
RTU frames (``01 03 00 00 00 0A C5 CD``; the Simply Modbus examples for slave 0x11), from
the CRC catalogue's check value, and from crcmod's CRC-16/MODBUS (an independent
implementation). None of them was printed by the code under test.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import crcmod.predefined
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hilsim.protocols import modbus_pdu as pdu
from hilsim.protocols.registers import ILLEGAL_FUNCTION, ILLEGAL_VALUE, ModbusError

H = bytes.fromhex
CRCMOD_MODBUS = crcmod.predefined.mkCrcFun("modbus")


# ------------------------------------------------------------------ CRC-16/MODBUS


def test_crc_serial_line_spec_example() -> None:
    """Modbus over Serial Line V1.02, appendix B: the frame 02 07 has CRC 0x1241, sent 41 12."""
    assert pdu.crc16(H("0207")) == 0x1241
    assert pdu.rtu_frame(0x02, H("07")) == H("02074112")


def test_crc_catalogue_check_value() -> None:
    """CRC-16/MODBUS of ASCII "123456789" is 0x4B37 (the CRC catalogue's check)."""
    assert pdu.crc16(b"123456789") == 0x4B37


def test_crc_table_from_the_spec() -> None:
    """The serial line spec's tables (appendix B: auchCRCHi 00 C1 81 40 ... 81 40, auchCRCLo
    00 C0 C1 01 ... 80 40) are the two bytes of each entry; the entry for 0x80 is the
    polynomial itself (seven shifts, then one that shifts out a 1)."""
    assert pdu.CRC_TABLE[:4] == (0x0000, 0xC0C1, 0xC181, 0x0140)
    assert pdu.CRC_TABLE[0x80] == 0xA001 and pdu.CRC_TABLE[0xFF] == 0x4040 and len(pdu.CRC_TABLE) == 256


@given(st.binary(max_size=300))
def test_crc_agrees_with_crcmod(data: bytes) -> None:
    assert pdu.crc16(data) == CRCMOD_MODBUS(data)


@given(st.binary(max_size=40), st.binary(min_size=1, max_size=40), st.binary(max_size=40))
def test_crc_ok_in_place(before: bytes, body: bytes, after: bytes) -> None:
    good = body + CRCMOD_MODBUS(body).to_bytes(2, "little")
    buf = bytearray(before + good + after)
    start, end = len(before), len(before) + len(good)
    assert pdu.crc_ok(buf, start, end)
    assert pdu.crc16(buf, start, end - 2) == CRCMOD_MODBUS(body)
    swapped = body + CRCMOD_MODBUS(body).to_bytes(2, "big")
    assert pdu.crc_ok(swapped, 0, len(swapped)) == (swapped == good)  # high byte first: wrong
    for i in range(len(good)):  # any single-bit error is caught
        bad = bytearray(good)
        bad[i] ^= 0x10
        assert not pdu.crc_ok(bad, 0, len(bad))


# ------------------------------------------------------------------ RTU and MBAP frames


@pytest.mark.parametrize("unit, body, adu", [
    (0x01, "030000000A", "01030000000AC5CD"),                      # read 10 holding registers from 0
    (0x01, "0600010003", "010600010003980B"),                      # write 3 to register 1
    (0x11, "03006B0003", "1103006B00037687"),                      # Simply Modbus: read holding
    (0x11, "0400080001", "110400080001B298"),                      # read input
    (0x11, "0600010003", "1106000100039A9B"),                      # write single
    (0x11, "10000100020400 0A0102", "1110000100020400 0A0102C6F0"),  # write 000A, 0102 to 1..2
])
def test_rtu_frames(unit: int, body: str, adu: str) -> None:
    assert pdu.rtu_frame(unit, H(body)) == H(adu)
    assert pdu.crc_ok(H(adu), 0, len(H(adu)))


def test_mbap_frame() -> None:
    """Modbus Messaging on TCP/IP Implementation Guide V1.0b, 3.1.3: transaction id, protocol id
    0, length of the bytes that follow (unit id + PDU), unit id, then the PDU."""
    assert pdu.mbap_frame(0x1234, 0x11, H("03006B0003")) == H("1234 0000 0006 11 03006B0003")
    assert pdu.mbap_frame(0xFFFF, 0xFF, H("8302")) == H("FFFF 0000 0003 FF 8302")


# ------------------------------------------------------------------ request PDUs (spec section 6)


def test_decode_spec_requests() -> None:
    assert pdu.decode_request(H("03 006B 0003")) == pdu.ReadRegisters(3, 0x006B, 3)         # 6.3
    assert pdu.decode_request(H("04 0008 0001")) == pdu.ReadRegisters(4, 0x0008, 1)         # 6.4
    assert pdu.decode_request(H("06 0001 0003")) == pdu.WriteRegisters(6, 0x0001, (3,))     # 6.6
    assert pdu.decode_request(H("10 0001 0002 04 000A 0102")) == \
        pdu.WriteRegisters(16, 0x0001, (0x000A, 0x0102))                                    # 6.12
    assert pdu.decode_request(bytearray(H("03 FFFF 007D"))) == pdu.ReadRegisters(3, 0xFFFF, 125)


def test_spec_responses() -> None:
    """The responses of the spec's examples, built from the decoded requests."""
    assert pdu.read_response(3, [0x022B, 0x0000, 0x0064]) == H("03 06 022B 0000 0064")     # 6.3
    assert pdu.read_response(4, [0x000A]) == H("04 02 000A")                                # 6.4
    assert pdu.write_response(pdu.WriteRegisters(6, 1, (3,))) == H("06 0001 0003")          # 6.6: the echo
    assert pdu.write_response(pdu.decode_request(H("10 0001 0002 04 000A 0102"))) == H("10 0001 0002")  # 6.12
    assert pdu.read_response(3, [0xFFFF] * 125)[:2] == H("03 FA") and len(pdu.read_response(3, [0] * 125)) == 252


def test_exception_response() -> None:
    """Spec section 7: read coils (01) of a nonexistent address gives 81 02."""
    assert pdu.exception_response(0x01, 0x02) == H("8102")
    assert pdu.exception_response(0x83, 0x03) == H("8303")  # already flagged: stays one flag
    r = pdu.Response(7, H("8102"))
    assert r.is_exception and r.exception_code == 2
    r = pdu.Response(7, H("04 02 000A"))
    assert not r.is_exception and r.exception_code == 0


def code_of(request: bytes) -> int:
    with pytest.raises(ModbusError) as info:
        pdu.decode_request(request)
    return info.value.code


@pytest.mark.parametrize("request_hex", [
    "01 0000 0001", "02 0000 0001", "05 0000 FF00", "0F 0000 0001 01 01", "07", "08 0000 1234",
    "11", "16 0000 FFFF 0000", "17 0000 0001 0000 0001 02 0000", "2B 0E 01 00", "14 00", "18 0000",
    "00", "41", "83 02", "FF", "",
])
def test_every_other_function_is_unsupported(request_hex: str) -> None:
    assert code_of(H(request_hex)) == ILLEGAL_FUNCTION


@pytest.mark.parametrize("request_hex", [
    "03 0000 0000", "03 0000 007E", "04 0000 0000", "04 0000 FFFF",   # quantity outside 1..125
    "03 0000 00", "03 0000 0001 00", "04", "06 0001", "06 0001 0003 00",  # wrong length
    "10 0000 0000 00", "10 0000 007C F8" + "00" * 248,                   # quantity outside 1..123
    "10 0000 0002 02 0000 0000", "10 0000 0001 02 00", "10 0000 0001 02 0000 00",  # count, byte count, length
    "10 0000 0001", "10",
])
def test_malformed_requests_are_illegal_value(request_hex: str) -> None:
    assert code_of(H(request_hex)) == ILLEGAL_VALUE


def test_limits_accepted() -> None:
    assert pdu.decode_request(H("04 0000 0001")).count == 1  # type: ignore[union-attr]
    words = tuple(range(123))
    req = H("10 0100 007B F6") + b"".join(w.to_bytes(2, "big") for w in words)
    assert pdu.decode_request(req) == pdu.WriteRegisters(16, 0x0100, words)


@given(st.binary(max_size=300))
def test_decode_request_never_raises_anything_else(data: bytes) -> None:
    try:
        req = pdu.decode_request(data)
    except ModbusError as exc:
        assert exc.code in (ILLEGAL_FUNCTION, ILLEGAL_VALUE)
        return
    assert data[0] in (3, 4, 6, 16)
    if isinstance(req, pdu.ReadRegisters):
        assert req.count == int.from_bytes(data[3:5], "big") and req.address == int.from_bytes(data[1:3], "big")
    else:
        assert pdu.write_response(req)[:3] == data[:3]


# ------------------------------------------------------------------ sans-I/O


def test_importing_the_modbus_codecs_leaves_io_out() -> None:
    """The sans-I/O layer: importing the Modbus codecs in a fresh interpreter brings in no
    asyncio, socket, ssl or pymodbus (the modules they import alone are checked first, so a
    failure names the culprit)."""
    script = textwrap.dedent("""
        import importlib, sys
        IO = ("asyncio", "socket", "ssl", "pymodbus")
        for name in ("hilsim.protocols.codec", "hilsim.protocols.registers", "hilsim.protocols.modbus_pdu",
                     "hilsim.protocols.modbus", "hilsim.protocols.modbus_device"):
            importlib.import_module(name)
            bad = sorted(m for m in sys.modules if m.split(".")[0] in IO)
            print(name, " ".join(bad) or "-")
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True, timeout=60)
    lines = out.stdout.split("\n")[:-1]
    assert len(lines) == 5 and all(line.endswith(" -") for line in lines), out.stdout
