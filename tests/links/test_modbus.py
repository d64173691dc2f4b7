"""Modbus servers: request handling and exception codes, TCP and RTU framing fed
whole and byte at a time, random/mutated/truncated input (hypothesis), and the
real servers on loopback TCP and a pty (client limit, bad CRC, floods)."""

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

from hilsim.links.modbus import ModbusRtuServer, ModbusTarget, ModbusTcpServer, RtuSession, TcpSession
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
    assert s.receive_data(bytes(bad)) == [] and s.stats.crc_errors == 1 and not s.pending
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
