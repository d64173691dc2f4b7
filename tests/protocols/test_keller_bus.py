"""KELLER bus protocol (Communication protocol Serie30): our decoder, encoders and responder
against an independent codec written here from KELLER's document, and against KELLER's own
client package ``keller-protocol`` over a real pty pair.

The reference codec below follows the document, not hilsim: the CRC16 as its appendix
describes it (bitwise, polynomial 0xA001, init 0xFFFF), sent high byte first (chapter 3.2);
the function layouts of chapter 5 (F48 10-byte reply, F69 SN3..SN0, F73 B3..B0 + STAT, F95
``DevAddr 95 0``, F66 ``DevAddr 66 ActAddr``, exceptions ``DevAddr F|0x80 code``); the
manual's own frames ``250 73 1 161 167`` and ``250 48 4 67`` (chapter 5.1).
"""

from __future__ import annotations

import math
import os
import select
import struct
import termios
import threading
import tty
from typing import Iterator, Optional

import pytest

from hilsim.protocols import keller_bus as kb
from hilsim.protocols.codec import BadFrame, Junk, drain


# ----------------------------------------------------------------------------- reference codec

def ref_crc(data: bytes) -> int:
    """The document's CRC16 (appendix): bitwise, 0xA001, initial 0xFFFF."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            lsb = crc & 1
            crc >>= 1
            if lsb:
                crc ^= 0xA001
    return crc


def ref_frame(*body: int) -> bytes:
    crc = ref_crc(bytes(body))
    return bytes(body) + bytes([crc >> 8, crc & 0xFF])  # KELLER: CRC16_H first


def ref_parse_reply(frame: bytes) -> tuple[int, int, bytes]:
    """(address, function, data) of a slave's reply; asserts the KELLER CRC."""
    assert len(frame) >= 4
    crc = ref_crc(frame[:-2])
    assert frame[-2:] == bytes([crc >> 8, crc & 0xFF]), f"bad KELLER CRC on {frame.hex()}"
    return frame[0], frame[1], frame[2:-2]


def test_manual_frames_and_crc() -> None:
    assert ref_frame(250, 73, 1) == bytes([250, 73, 1, 161, 167])   # chapter 5.1
    assert ref_frame(250, 48) == bytes([250, 48, 4, 67])
    for body in (b"\xfa\x49\x01", b"\x01\x30", bytes(range(9))):
        assert kb.crc16(body) == ref_crc(body)
        assert kb.encode_frame(body[0], body[1], body[2:]) == ref_frame(*body)


def test_the_manuals_example_exchanges() -> None:
    """Chapter 5.1's table of requests and responses, byte for byte (values as printed there)."""
    assert ref_frame(1, 73, 1) == bytes([1, 73, 1, 80, 214])
    assert ref_frame(250, 73, 4) == bytes([250, 73, 4, 162, 103])
    assert ref_frame(1, 48) == bytes([1, 48, 52, 0])
    assert kb.encode_f73(250, struct.unpack(">f", bytes([63, 109, 186, 172]))[0], 0) == \
        bytes([250, 73, 63, 109, 186, 172, 0, 26, 27])                   # 0.9286296 bar
    assert kb.encode_f73(250, struct.unpack(">f", bytes([65, 201, 184, 0]))[0], 0) == \
        bytes([250, 73, 65, 201, 184, 0, 0, 224, 204])                   # 25.21484 deg C
    assert struct.unpack(">f", bytes([63, 109, 186, 172]))[0] == pytest.approx(0.9286296, abs=1e-7)
    reply = kb.encode_f48(1, 5, 20, 5, 50, 10, 1)                        # "FW=5.20-5.50, Buffer=10,
    assert reply[:4] == bytes([1, 48, 5, 20]) and ref_parse_reply(reply)[2] == bytes([5, 20, 5, 50, 10, 1])


def test_request_lengths_and_dispatch_rule() -> None:
    assert kb.keller_request_length(ref_frame(250, 48)) == 4
    assert kb.keller_request_length(ref_frame(250, 73, 1)) == 5
    assert kb.keller_request_length(bytes([250])) == kb.NEED_MORE
    f95a = ref_frame(1, 95, 0)
    f95b = ref_frame(1, 95, 0, *struct.pack(">f", 1.5))
    assert kb.keller_request_length(f95a) == 5
    assert kb.keller_request_length(f95b) == 9
    assert kb.keller_request_length(f95b[:4]) == kb.NEED_MORE
    # Modbus function codes are not KELLER functions: the same line tells them apart by code
    for fc in (3, 4, 6, 8, 16):
        assert not kb.is_keller_function(fc)
        assert kb.keller_request_length(bytes([1, fc, 0, 0])) == kb.UNDELIMITED
    for fc in (30, 31, 32, 33, 48, 66, 69, 73, 74, 95, 100, 101):
        assert kb.is_keller_function(fc)


# ----------------------------------------------------------------------------- decoder

def decode(data: bytes, cut: int = 0) -> list[object]:
    dec = kb.KellerRequestDecoder()
    events: list[object] = []
    if cut:
        for i in range(0, len(data), cut):
            events += drain(dec, data[i:i + cut])
    else:
        events += drain(dec, data)
    return events + dec.silence()


def test_back_to_back_requests_however_cut() -> None:
    stream = (ref_frame(250, 48) + ref_frame(1, 73, 1) + ref_frame(1, 95, 0, *struct.pack(">f", 0.25))
              + ref_frame(1, 95, 1) + ref_frame(7, 69) + ref_frame(250, 66, 0))
    want = [kb.KellerRequest(250, 48), kb.KellerRequest(1, 73, b"\x01"),
            kb.KellerRequest(1, 95, b"\x00" + struct.pack(">f", 0.25)), kb.KellerRequest(1, 95, b"\x01"),
            kb.KellerRequest(7, 69), kb.KellerRequest(250, 66, b"\x00")]
    for cut in (0, 1, 2, 3, 7):
        assert decode(stream, cut) == want


def test_wrong_length_is_one_frame_at_the_gap() -> None:
    events = decode(ref_frame(250, 48, 9))          # F48 with a parameter it does not take
    assert len(events) == 1 and isinstance(events[0], kb.WrongLength)
    assert (events[0].address, events[0].function) == (250, 48)
    # an unknown function with a good CRC is a request (answered exception 1)
    assert decode(ref_frame(250, 77, 1, 2)) == [kb.KellerRequest(250, 77, b"\x01\x02")]


def test_garbage_bad_crc_and_resync() -> None:
    good = ref_frame(1, 73, 4)
    bad = bytearray(good)
    bad[2] ^= 0xFF
    events = decode(bytes(bad))
    assert len(events) == 1 and isinstance(events[0], BadFrame)
    # garbage in the same burst as a request: skipped, the request found
    for cut in (0, 1):
        events = decode(b"\x13\x37\x00" + good, cut)
        assert [e for e in events if not isinstance(e, Junk)] == [kb.KellerRequest(1, 73, b"\x04")]
        assert sum(e.n_bytes for e in events if isinstance(e, Junk)) == 3
    # a long garbage flood with no gap: hunted through, the next request still found, memory bounded
    dec = kb.KellerRequestDecoder()
    flood = bytes((i * 37 + 11) % 256 for i in range(5000))
    events = list(drain(dec, flood))
    assert dec.buffered_bytes <= kb.MAX_FRAME
    events += list(drain(dec, good)) + dec.silence()
    assert events[-1] == kb.KellerRequest(1, 73, b"\x04")
    assert all(isinstance(e, (Junk, kb.KellerRequest, BadFrame)) for e in events)


# ----------------------------------------------------------------------------- responder

class Sensor:
    """A device state for the responder: P1 [Pa abs], TOB1 [K], one address, zero offset."""

    def __init__(self) -> None:
        self.address = 1
        self.pressure = 2.5e5
        self.temperature = 288.15
        self.zero = 0.0
        self.serial = 1234567

    def channel(self, ch: int) -> float:
        return {1: self.pressure - self.zero, 3: self.temperature, 4: self.temperature}.get(ch, math.nan)

    def set_zero(self, cmd: int, setpoint: Optional[float]) -> None:
        if cmd == 0:
            self.zero = self.pressure - (setpoint or 0.0)
        elif cmd == 1:
            self.zero = 0.0

    def set_address(self, new: int) -> bool:
        self.address = new
        return True

    def responder(self) -> kb.KellerResponder:
        return kb.KellerResponder(get_address=lambda: self.address, set_address=self.set_address,
                                  serial_number=lambda: self.serial, read_channel=self.channel,
                                  set_zero=self.set_zero)


def ask(resp: kb.KellerResponder, *body: int) -> Optional[tuple[int, int, bytes]]:
    """Send a reference-encoded request through our decoder and responder; parse the reply
    with the reference decoder."""
    events = decode(ref_frame(*body))
    assert len(events) == 1
    reply = resp.handle(events[0])  # type: ignore[arg-type]
    return None if reply is None else ref_parse_reply(reply)


def test_power_up_rule_exception_32_until_f48() -> None:
    dev = Sensor()
    resp = dev.responder()
    for body in ((1, 73, 1), (1, 69), (1, 95, 0), (1, 66, 5), (250, 74, 1), (1, 30, 0)):
        assert ask(resp, *body) == (body[0], body[1] | 0x80, bytes([32]))
    assert dev.address == 1 and dev.zero == 0.0      # nothing was done
    assert ask(resp, 1, 48) == (1, 48, bytes([5, 20, 10, 40, 10, 0]))  # state 0: first since power-up
    assert ask(resp, 1, 48) == (1, 48, bytes([5, 20, 10, 40, 10, 1]))  # state 1: already initialised
    assert ask(resp, 1, 69) == (1, 69, struct.pack(">I", 1234567))
    resp.power_up()
    assert ask(resp, 1, 69) == (1, 69 | 0x80, bytes([32]))


def test_f73_values_status_and_exceptions() -> None:
    dev = Sensor()
    resp = dev.responder()
    ask(resp, 250, 48)
    addr, fn, data = ask(resp, 1, 73, 1)  # type: ignore[misc]
    value, stat = struct.unpack(">fB", data)
    assert (addr, fn, stat) == (1, 73, 0)
    assert value == pytest.approx(2.5, rel=1e-7)                     # bar
    _, _, data = ask(resp, 250, 73, 4)  # type: ignore[misc]
    assert struct.unpack(">fB", data)[0] == pytest.approx(15.0, abs=1e-5)  # deg C
    _, _, data = ask(resp, 1, 74, 1)  # type: ignore[misc]
    assert struct.unpack(">iB", data) == (250000, 0)                # Pa
    assert ask(resp, 1, 73, 6) == (1, 73 | 0x80, bytes([2]))          # CH > 5
    assert ask(resp, 1, 74, 2) == (1, 74 | 0x80, bytes([4]))          # P2 not fitted
    dev.pressure = math.nan                                           # channel error: P1 bit in STAT
    _, _, data = ask(resp, 1, 73, 1)  # type: ignore[misc]
    value, stat = struct.unpack(">fB", data)
    assert math.isnan(value) and stat == 0b0000_0010
    assert ask(resp, 1, 48, 0) is not None and ask(resp, 1, 48, 0)[1] == 48 | 0x80  # type: ignore[index]
    assert ask(resp, 1, 48, 0)[2] == bytes([3])  # type: ignore[index]           # wrong length


def test_f95_f66_addressing() -> None:
    dev = Sensor()
    resp = dev.responder()
    ask(resp, 1, 48)
    assert ask(resp, 1, 95, 0) == (1, 95, b"\x00")
    _, _, data = ask(resp, 1, 73, 1)  # type: ignore[misc]
    assert struct.unpack(">f", data[:4])[0] == pytest.approx(0.0, abs=1e-9)
    assert ask(resp, 1, 95, 0, *struct.pack(">f", 1.0)) == (1, 95, b"\x00")   # setpoint 1 bar
    _, _, data = ask(resp, 1, 73, 1)  # type: ignore[misc]
    assert struct.unpack(">f", data[:4])[0] == pytest.approx(1.0, rel=1e-6)
    assert ask(resp, 1, 95, 1) == (1, 95, b"\x00")
    assert ask(resp, 1, 95, 5) == (1, 95 | 0x80, bytes([2]))
    assert ask(resp, 2, 69) is None                                   # another device's address
    assert ask(resp, 250, 66, 0) == (250, 66, bytes([1]))             # read the address
    assert ask(resp, 1, 66, 9) == (1, 66, bytes([9]))                 # answered from the old address
    assert dev.address == 9 and ask(resp, 1, 69) is None
    assert ask(resp, 9, 66, 251) == (9, 66, bytes([9]))               # out of 1..249: refused, confirmed
    assert ask(resp, 0, 95, 0) is None                                # broadcast: done, no reply
    assert ask(resp, 9, 32, 0) == (9, 32 | 0x80, bytes([1]))            # configuration: not modelled


def test_f30_f31_coefficients() -> None:
    """F30 reads a coefficient as float32 (64: P1 offset [bar], 80/81: P1 range); > 111 is
    exception 2; F31 writes one (64 moves the zero point), answered ``DevAddr 31 0``."""
    dev = Sensor()
    offset = [0.0]

    def write(nr: int, value: float) -> bool:
        if nr == 64:
            offset[0] = value
            dev.zero = value * 1e5
            return True
        return False

    resp = kb.KellerResponder(get_address=lambda: dev.address, set_address=dev.set_address,
                              serial_number=lambda: dev.serial, read_channel=dev.channel, set_zero=dev.set_zero,
                              coefficient=lambda nr: {64: offset[0], 80: 0.0, 81: 30.0}.get(nr),
                              write_coefficient=write)
    ask(resp, 1, 48)
    assert ask(resp, 1, 30, 81) == (1, 30, struct.pack(">f", 30.0))
    assert ask(resp, 1, 30, 112) == (1, 30 | 0x80, bytes([2]))
    assert ask(resp, 1, 31, 64, *struct.pack(">f", 0.5)) == (1, 31, b"\x00")
    assert ask(resp, 1, 30, 64) == (1, 30, struct.pack(">f", 0.5))
    _, _, data = ask(resp, 1, 73, 1)  # type: ignore[misc]
    assert struct.unpack(">f", data[:4])[0] == pytest.approx(2.0, rel=1e-6)   # 2.5 bar - 0.5
    assert ask(resp, 1, 31, 105, *struct.pack(">f", 7.25)) == (1, 31, b"\x00")  # a customer coefficient
    assert ask(resp, 1, 30, 105) == (1, 30, struct.pack(">f", 7.25))


# ----------------------------------------------------------------------------- peer: keller-protocol

@pytest.fixture
def pty_device() -> Iterator[tuple[str, Sensor]]:
    """Our decoder + responder serving the master side of a real pty pair (a thread);
    yields the slave path for the peer and the device state."""
    master, slave = os.openpty()
    for fd in (master, slave):
        tty.setraw(fd, termios.TCSANOW)
    path = os.ttyname(slave)
    dev = Sensor()
    resp = dev.responder()
    dec = kb.KellerRequestDecoder()
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            ready, _, _ = select.select([master], [], [], 0.004)  # 4 ms idle: a gap (3.5 chars at 9600)
            events: list[object] = []
            if ready:
                try:
                    events += drain(dec, os.read(master, 256))
                except OSError:
                    continue
            else:
                events += dec.silence()
            for ev in events:
                if isinstance(ev, (kb.KellerRequest, kb.WrongLength)):
                    reply = resp.handle(ev)
                    if reply:
                        os.write(master, reply)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield path, dev
    finally:
        stop.set()
        thread.join(2)
        os.close(master)
        os.close(slave)


def test_keller_protocol_package_over_a_pty(pty_device: tuple[str, Sensor]) -> None:
    kp = pytest.importorskip("keller_protocol.keller_protocol", reason="pip install keller-protocol")
    path, dev = pty_device
    bus = kp.KellerProtocol(path, 9600, echo=False)
    with pytest.raises(Exception, match=f"Device Error number: {73 | 0x80}"):
        bus.f73(250, 1)                                  # power-up: exception 32 until F48
    assert bus.f48(250) == "5.20-10.40"
    assert bus.f69(250) == dev.serial
    assert bus.f73(250, 1) == pytest.approx(dev.pressure / 1e5, rel=1e-6)
    assert bus.f73(1, 4) == pytest.approx(dev.temperature - 273.15, abs=1e-4)
    assert bus.f74(1, 1) == round(dev.pressure)
    bus.f95(1, 0)                                        # set zero P1
    assert bus.f73(1, 1) == pytest.approx(0.0, abs=1e-6)
    bus.f95(1, 0, 1.25)                                  # zero so that P1 reads 1.25 bar
    assert bus.f73(1, 1) == pytest.approx(1.25, rel=1e-6)
    bus.f95(1, 1)                                        # reset the zero point
    assert bus.f73(1, 1) == pytest.approx(dev.pressure / 1e5, rel=1e-6)
    assert bus.f66(250, 0) == 1                          # read the address (transparent)
    assert bus.f66(1, 42) == 42
    assert dev.address == 42 and bus.f69(42) == dev.serial
    with pytest.raises(ConnectionRefusedError):
        bus.f69(1)                                       # the old address is silent now


# ----------------------------------------------------------------------------- one line, two protocols

def test_keller_bus_beside_modbus_on_one_rtu_line() -> None:
    """The Series 30 serves both protocols on one line, told by function code: a Modbus RTU
    read (CRC low byte first) and KELLER bus requests (CRC high byte first) in one stream."""
    from hilsim.protocols.modbus_device import ModbusTarget, RtuSession
    from hilsim.protocols.registers import RegisterImage, load_map
    from hilsim.resources import data_path

    image = RegisterImage(load_map(data_path("protocols", "keller_serie30.toml")))
    image.update({"pressure": 2.5e5, "temperature": 288.15})
    target = ModbusTarget(image, actions={"set_zero": lambda register, value: None})
    dev = Sensor()
    resp = dev.responder()
    session = RtuSession([target])
    session.add_dialect(kb.DIALECT, resp.handle_frame)

    def modbus(*body: int) -> bytes:
        crc = ref_crc(bytes(body))
        return bytes(body) + bytes([crc & 0xFF, crc >> 8])     # Modbus: CRC low byte first

    read_p1 = modbus(1, 3, 0x00, 0x02, 0x00, 0x02)
    stream = read_p1 + ref_frame(250, 73, 1) + ref_frame(250, 48) + ref_frame(1, 73, 1) + read_p1
    for cut in (len(stream), 1, 5):
        resp.power_up()
        replies: list[bytes] = []
        for i in range(0, len(stream), cut):
            replies += session.receive_data(stream[i:i + cut])
        replies += session.silence()
        assert len(replies) == 5
        m = replies[0]
        assert m[:3] == bytes([1, 3, 4]) and ref_crc(m[:-2]) == m[-2] | m[-1] << 8  # Modbus CRC order
        assert struct.unpack(">f", m[3:7])[0] == pytest.approx(2.5, rel=1e-6)   # Modbus needs no F48
        assert ref_parse_reply(replies[1]) == (250, 73 | 0x80, bytes([32]))       # KELLER: not yet
        assert ref_parse_reply(replies[2])[1] == 48
        _, fn, data = ref_parse_reply(replies[3])
        assert fn == 73 and struct.unpack(">f", data[:4])[0] == pytest.approx(2.5, rel=1e-6)
        assert replies[4] == m


def test_wrong_length_on_the_shared_line_answers_exception_3() -> None:
    """A KELLER frame of the wrong length on the line shared with Modbus is one frame at the gap,
    as the transmitter takes it: exception 3 (32 before F48); a garbled one stays silent."""
    from hilsim.protocols.modbus_device import RtuSession

    dev = Sensor()
    resp = dev.responder()
    session = RtuSession([])
    session.add_dialect(kb.DIALECT, resp.handle_frame)
    for cut in (1, 100):
        resp.power_up()
        stream = ref_frame(1, 69, 7)
        got = [r for i in range(0, len(stream), cut) for r in session.receive_data(stream[i:i + cut])]
        got += session.silence()
        assert [ref_parse_reply(r) for r in got] == [(1, 69 | 0x80, bytes([32]))]
        got = session.receive_data(ref_frame(1, 48)) + session.silence()
        got += session.receive_data(ref_frame(1, 69, 7)) + session.silence()
        assert ref_parse_reply(got[1]) == (1, 69 | 0x80, bytes([3]))
        garbled = bytearray(ref_frame(1, 73, 1))
        garbled[2] ^= 0x10
        assert session.receive_data(bytes(garbled)) + session.silence() == []
        assert session.stats.crc_errors >= 1
