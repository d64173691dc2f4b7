"""CAN links: one test class run against every transport with an unmodified python-can client
(python-can style), plus what is particular to the socketcand server and the slcan pty.

The bus runs in an asyncio loop on a background thread; the python-can clients are
ordinary blocking code in the test thread, as they would be in a user's program.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import threading
import time
import uuid
from typing import Any, Callable

import can
import pytest

from hilsim.links.can import TRANSPORTS, CanBus, create_bus, socketcan_available
from hilsim.protocols.can import CanFrame

SOCKETCAN_OK, SOCKETCAN_WHY = socketcan_available()


class LoopThread:
    """An asyncio loop on a daemon thread; ``run(coro)`` waits for a result from the test thread."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()

    def run(self, coro: Any, timeout: float = 20.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def call(self, fn: Callable[..., Any], *args: Any) -> Any:
        async def go() -> Any:
            return fn(*args)
        return self.run(go())

    def close(self) -> None:
        async def drain() -> None:
            tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        try:
            self.run(drain(), 10)
        finally:
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(10)
            self.loop.close()


def wait_for(cond: Callable[[], bool], timeout: float = 10.0, step: float = 0.01) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(step)
    return cond()


def recv_matching(client: can.BusABC, pred: Callable[[can.Message], bool], timeout: float = 10.0) -> can.Message:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = client.recv(0.2)
        if msg is not None and pred(msg):
            return msg
    raise AssertionError("no matching frame received")


def as_frame(msg: can.Message) -> CanFrame:
    return CanFrame(msg.arbitration_id, bytes(msg.data), msg.is_extended_id)


@pytest.fixture
def loop_thread():
    lt = LoopThread()
    yield lt
    lt.close()


def make_bus(lt: LoopThread, transport: str, tmp_path, **kw: Any) -> CanBus:
    if transport == "slcan":
        kw.setdefault("path", str(tmp_path / "slcan0"))
    if transport == "virtual":
        kw.setdefault("channel", f"hilsim-test-{uuid.uuid4().hex[:8]}")
    if transport == "socketcan":
        kw.setdefault("channel", "vcan0")

    async def start() -> CanBus:
        bus = create_bus(transport, f"test-{transport}", **kw)
        await bus.start()
        return bus
    return lt.run(start())  # type: ignore[no-any-return]


def open_client(bus: CanBus) -> can.BusABC:
    """An unmodified python-can client for the bus, from the bus's own endpoint description."""
    kw = dict(bus.extra)
    kw.pop("bus", None)
    if kw["interface"] == "slcan":
        kw["sleep_after_open"] = 0
    return can.Bus(**kw)


TRANSPORT_PARAMS = [
    pytest.param("socketcand"), pytest.param("slcan"), pytest.param("virtual"),
    pytest.param("socketcan", marks=pytest.mark.skipif(not SOCKETCAN_OK, reason=f"SocketCAN: {SOCKETCAN_WHY}")),
]


@pytest.mark.parametrize("transport", TRANSPORT_PARAMS)
class TestEveryTransport:
    """The same behaviour whatever carries the frames."""

    def _bus_and_client(self, lt, transport, tmp_path, **kw):
        bus = make_bus(lt, transport, tmp_path, **kw)
        got: list[CanFrame] = []
        lt.call(bus.subscribe, got.append)
        client = open_client(bus)
        if transport == "socketcand":
            assert lt.run(bus.wait_clients(1))
        return bus, client, got

    def test_frames_both_ways(self, loop_thread, transport, tmp_path):
        bus, client, got = self._bus_and_client(loop_thread, transport, tmp_path)
        try:
            sent = [CanFrame(0x0117, bytes.fromhex("0000C738")), CanFrame(0x123, b"\x01\x02", False),
                    CanFrame(0x7FF, b"", False), CanFrame(0x1FFFFFFF, bytes(range(8)))]
            for f in sent:
                client.send(can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=f.is_extended))
            assert wait_for(lambda: len(got) >= len(sent))
            assert got == sent
            out = CanFrame((9 << 8) | 3, bytes.fromhex("ffff9d90007bfe0c"))
            loop_thread.call(bus.send, out)
            msg = recv_matching(client, lambda m: m.arbitration_id == out.arbitration_id)
            assert as_frame(msg) == out
            st = bus.status()
            assert st["frames_in"] == len(sent) and st["frames_out"] == 1 and st["dropped_in"] == 0
        finally:
            client.shutdown()
            loop_thread.run(bus.close())

    def test_flood_is_dropped_and_counted_then_commands_apply(self, loop_thread, transport, tmp_path):
        # 125 kbit/s with 20 ms of credit: about 950 frames/s, a burst of about 19
        bus, client, got = self._bus_and_client(loop_thread, transport, tmp_path, bitrate=125_000, burst=0.02)
        try:
            n = 1500
            t0 = time.monotonic()
            for i in range(n):
                client.send(can.Message(arbitration_id=0x100, data=i.to_bytes(2, "big"), is_extended_id=False))
            elapsed = time.monotonic() - t0
            st = lambda: bus.status()  # noqa: E731
            assert wait_for(lambda: st()["frames_in"] + st()["dropped_in"] >= n)
            s = st()
            assert s["frames_in"] + s["dropped_in"] == n
            # the bus never took more than its capacity over the flood (plus the initial burst)
            assert s["frames_in"] <= 19 + 1 + (elapsed + 0.5) * 125_000 / CanFrame(0x100, b"12", False).bits_on_wire
            if elapsed < 0.5:  # the client really flooded (a slow machine may not)
                assert s["dropped_in"] > 0
            time.sleep(0.1)  # the budget refills; a well-behaved command gets through
            client.send(can.Message(arbitration_id=0x0301, data=b"\x00\x00\x13\x88", is_extended_id=True))
            assert wait_for(lambda: any(f.arbitration_id == 0x0301 for f in got))
        finally:
            client.shutdown()
            loop_thread.run(bus.close())


def test_transport_table_is_lazy_and_complete():
    assert set(TRANSPORTS) == {"socketcand", "slcan", "socketcan", "virtual"}
    with pytest.raises(KeyError, match="did you mean 'slcan'"):
        create_bus("slcn", "x")


@pytest.mark.skipif(SOCKETCAN_OK, reason="this machine has SocketCAN")
def test_socketcan_unavailable_is_a_clear_error(loop_thread):
    bus = create_bus("socketcan", "sc", channel="vcan0")
    with pytest.raises(OSError, match="SocketCAN unavailable"):
        loop_thread.run(bus.start())
    loop_thread.run(bus.close())


# ---------------------------------------------------------------- socketcand server specifics


def raw_handshake(port: int, channel: str = "can0") -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    assert s.recv(256) == b"< hi >"
    s.sendall(f"< open {channel} >".encode())
    reply = s.recv(256)
    if reply != b"< ok >":
        s.close()
        raise ConnectionError(reply.decode())
    s.sendall(b"< rawmode >")
    assert s.recv(256) == b"< ok >"
    return s


def test_socketcand_hub_forwards_between_clients_without_echo(loop_thread, tmp_path):
    bus = make_bus(loop_thread, "socketcand", tmp_path)
    a, b = open_client(bus), open_client(bus)
    try:
        assert loop_thread.run(bus.wait_clients(2))
        a.send(can.Message(arbitration_id=0x42, data=b"\xaa", is_extended_id=False))
        assert as_frame(recv_matching(b, lambda m: True)) == CanFrame(0x42, b"\xaa", False)
        assert a.recv(0.3) is None  # no echo to the sender
        assert bus.status()["forwarded"] == 1
    finally:
        a.shutdown()
        b.shutdown()
        loop_thread.run(bus.close())


def test_socketcand_wrong_channel_and_exact_replies(loop_thread, tmp_path):
    bus = make_bus(loop_thread, "socketcand", tmp_path, channel="can0")
    try:
        with pytest.raises(ConnectionError, match="could not open bus"):
            raw_handshake(bus.extra["port"], "vcan7")
        s = raw_handshake(bus.extra["port"])
        s.sendall(b"< echo >")
        assert s.recv(256) == b"< echo >"
        s.close()
        with pytest.raises(can.CanError):
            can.Bus(interface="socketcand", channel="vcan7", host="127.0.0.1", port=bus.extra["port"])
    finally:
        loop_thread.run(bus.close())


def test_socketcand_client_limit_logs_and_refuses(loop_thread, tmp_path, caplog):
    bus = make_bus(loop_thread, "socketcand", tmp_path, max_clients=2)
    clients = [open_client(bus), open_client(bus)]
    try:
        assert loop_thread.run(bus.wait_clients(2))
        with caplog.at_level(logging.WARNING):
            s = socket.create_connection(("127.0.0.1", bus.extra["port"]), timeout=5)
            assert s.recv(256) == b""  # closed at once
            s.close()
            assert wait_for(lambda: "client limit 2 reached" in caplog.text)
        assert bus.status()["refused"] == 1
        # the clients already connected keep working
        clients[0].send(can.Message(arbitration_id=0x1, data=b"\x01", is_extended_id=False))
        assert as_frame(recv_matching(clients[1], lambda m: True)) == CanFrame(0x1, b"\x01", False)
    finally:
        for c in clients:
            c.shutdown()
        loop_thread.run(bus.close())


def test_socketcand_flooder_does_not_starve_a_well_behaved_client(loop_thread, tmp_path):
    bus = make_bus(loop_thread, "socketcand", tmp_path, bitrate=125_000, burst=0.02)
    got: list[CanFrame] = []
    loop_thread.call(bus.subscribe, got.append)
    flooder, good = raw_handshake(bus.extra["port"]), open_client(bus)
    try:
        assert loop_thread.run(bus.wait_clients(2))
        flood = b"< send 100 2 1 2 >" * 20000
        t = threading.Thread(target=flooder.sendall, args=(flood,), daemon=True)
        t.start()
        for i in range(10):  # 10 Hz, far below the bus capacity
            good.send(can.Message(arbitration_id=0x200, data=bytes([i]), is_extended_id=False))
            time.sleep(0.1)
        t.join(30)
        assert wait_for(lambda: sum(f.arbitration_id == 0x200 for f in got) == 10)
        assert bus.status()["dropped_in"] > 0
    finally:
        flooder.close()
        good.shutdown()
        loop_thread.run(bus.close())


# ---------------------------------------------------------------- slcan pty specifics


def test_slcan_slow_host_gets_whole_lines_only(loop_thread, tmp_path):
    import serial

    from hilsim.protocols.slcan import parse_frame_line

    bus = make_bus(loop_thread, "slcan", tmp_path)
    port = serial.Serial(bus.address, 115200, timeout=0.2)
    try:
        port.write(b"O\r")
        assert port.read(1) == b"\r"
        done = threading.Event()

        async def burst() -> None:
            for k in range(60):  # bursts of 24 frames every 5 ms: faster than the host reads
                for i in range(24):
                    bus.send(CanFrame((9 << 8) | (i % 8 + 1), k.to_bytes(2, "big") * 4))
                await asyncio.sleep(0.005)
            done.set()
        fut = asyncio.run_coroutine_threadsafe(burst(), loop_thread.loop)
        data = b""
        for _ in range(100000):  # a slow host: small reads, with pauses, part-way through lines
            chunk = port.read(13)
            data += chunk
            if not chunk and done.is_set():
                break
            time.sleep(0.002)
        fut.result(10)
        lines = data.split(b"\r")
        assert lines[-1] == b""
        bad = [ln for ln in lines[:-1] if not isinstance(parse_frame_line(ln), CanFrame)]
        assert bad == []  # no line was cut
        st = bus.status()
        assert st["dropped_out"] > 0 and len(lines) - 1 + st["dropped_out"] == 60 * 24
    finally:
        port.close()
        loop_thread.run(bus.close())


def test_slcan_survives_client_reopen_and_drops_frames_while_closed(loop_thread, tmp_path):
    bus = make_bus(loop_thread, "slcan", tmp_path)
    got: list[CanFrame] = []
    loop_thread.call(bus.subscribe, got.append)
    try:
        for round_ in range(2):
            client = open_client(bus)
            client.send(can.Message(arbitration_id=0x10 + round_, data=b"", is_extended_id=False))
            assert wait_for(lambda: len(got) == round_ + 1)
            loop_thread.call(bus.send, CanFrame(0x20 + round_, b"\x05", False))
            assert recv_matching(client, lambda m: True).arbitration_id == 0x20 + round_
            client.shutdown()  # python-can sends C: the channel closes
            assert wait_for(lambda: bus.status()["channel_open"] == 0.0)
        assert [f.arbitration_id for f in got] == [0x10, 0x11]
        loop_thread.call(bus.send, CanFrame(0x30, b"", False))  # nobody listening: not delivered, no error
        assert bus.status()["errors"] == 0
    finally:
        loop_thread.run(bus.close())
