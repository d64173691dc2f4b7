"""The TCP server link: whole messages, bounded queues, client limits, rude clients."""

from __future__ import annotations

import asyncio
import socket
import struct

import pytest

from hilsim.links.tcp import TcpServer

MSG = 50_000  # bytes per message, like a sonar frame


def message(i: int) -> bytes:
    body = bytes([i % 251]) * (MSG - 8)
    return struct.pack("<II", 0xC0FFEE, i) + body


async def read_message(reader: asyncio.StreamReader) -> int:
    data = await reader.readexactly(MSG)
    magic, i = struct.unpack_from("<II", data)
    assert magic == 0xC0FFEE
    assert data[8:] == bytes([i % 251]) * (MSG - 8), "a message arrived torn or mixed"
    return i


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 30))


def test_fast_clients_get_every_message_and_slow_ones_lose_whole_messages():
    async def main():
        srv = TcpServer("t", queue_len=4, write_buffer=64 * 1024)
        host, port = await srv.start()
        fast = [await asyncio.open_connection(host, port) for _ in range(3)]
        # a client that never reads, with a tiny receive buffer
        slow = socket.socket()
        slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        slow.connect((host, port))
        while srv.stats.connected < 4:
            await asyncio.sleep(0.01)
        n = 200  # 10 MB: more than the kernel buffers of a client that never reads
        got = [[] for _ in fast]

        async def consume(k, r):
            while len(got[k]) < n:
                got[k].append(await read_message(r))

        readers = [asyncio.ensure_future(consume(k, r)) for k, (r, _) in enumerate(fast)]
        for i in range(n):
            srv.broadcast(message(i))
            await asyncio.sleep(0.002)
        await asyncio.wait_for(asyncio.gather(*readers), 20)
        for g in got:
            assert g == list(range(n))
        slow_port = slow.getsockname()[1]
        slow_client = [c for c in srv.clients.values() if c.peer.endswith(f":{slow_port}")][0]
        assert slow_client.dropped > 0
        # what the slow client did receive is whole messages in order
        slow.setblocking(True)
        slow.settimeout(2)
        buf = b""
        try:
            while True:
                chunk = slow.recv(1 << 20)
                if not chunk:
                    break
                buf += chunk
                if len(buf) >= slow_client.sent * MSG:
                    break
        except socket.timeout:
            pass
        k = len(buf) // MSG
        ids = [struct.unpack_from("<II", buf, j * MSG)[1] for j in range(k)]
        assert ids == sorted(ids) and len(set(ids)) == len(ids)
        slow.close()
        for _, w in fast:
            w.close()
        await srv.close()

    run(main())


def test_client_limit_refuses_with_a_count_and_keeps_serving():
    async def main():
        srv = TcpServer("t", max_clients=2)
        host, port = await srv.start()
        a = await asyncio.open_connection(host, port)
        b = await asyncio.open_connection(host, port)
        while srv.stats.connected < 2:
            await asyncio.sleep(0.01)
        r3, w3 = await asyncio.open_connection(host, port)
        assert await asyncio.wait_for(r3.read(10), 5) == b""  # refused: closed at once
        assert srv.stats.refused == 1
        srv.broadcast(message(7))
        assert await read_message(a[0]) == 7
        assert await read_message(b[0]) == 7
        for _, w in (a, b):
            w.close()
        w3.close()
        await srv.close()

    run(main())


def test_disconnect_mid_message_and_reset_leave_the_server_serving():
    async def main():
        received = []
        srv = TcpServer("t", on_data=lambda c, d: received.append(d))
        host, port = await srv.start()
        for _ in range(20):
            s = socket.socket()
            s.connect((host, port))
            s.sendall(b"partial comm")
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            s.close()  # RST
        good_r, good_w = await asyncio.open_connection(host, port)
        while srv.stats.connected != 1:
            await asyncio.sleep(0.01)
        srv.broadcast(message(3))
        assert await read_message(good_r) == 3
        good_w.write(b"hello")
        await good_w.drain()
        for _ in range(100):
            if b"hello" in b"".join(received):
                break
            await asyncio.sleep(0.01)
        assert b"hello" in b"".join(received)
        good_w.close()
        await srv.close()
        assert srv.stats.connected == 0

    run(main())


def test_a_device_error_on_one_client_does_not_stop_the_server():
    def boom(client, data):
        if data.startswith(b"crash"):
            raise RuntimeError("device bug")

    async def main():
        srv = TcpServer("t", on_data=boom)
        host, port = await srv.start()
        r1, w1 = await asyncio.open_connection(host, port)
        w1.write(b"crash now")
        await w1.drain()
        assert await asyncio.wait_for(r1.read(10), 5) == b""
        r2, w2 = await asyncio.open_connection(host, port)
        while srv.stats.connected != 1:
            await asyncio.sleep(0.01)
        srv.broadcast(message(1))
        assert await read_message(r2) == 1
        w2.close()
        await srv.close()

    run(main())


def test_idle_and_never_reading_clients_are_dropped_and_active_ones_kept(caplog):
    """idle_timeout: nothing either way -> dropped; a client that talks, or one that only listens to
    a stream it reads, stays. stall_timeout: a client that takes nothing it is sent -> dropped."""
    async def main():
        srv = TcpServer("t", idle_timeout=1.0, stall_timeout=1.0, write_buffer=16 * 1024, sndbuf=4096,
                        on_data=lambda c, d: None)
        host, port = await srv.start()
        idle = socket.create_connection((host, port))
        talker_r, talker_w = await asyncio.open_connection(host, port)
        listener_r, _ = await asyncio.open_connection(host, port)
        deaf = socket.socket()
        deaf.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        deaf.connect((host, port))
        while srv.stats.connected < 4:
            await asyncio.sleep(0.01)
        ports = {"idle": idle.getsockname()[1], "deaf": deaf.getsockname()[1],
                 "talker": talker_w.get_extra_info("sockname")[1]}
        quiet = {f":{ports['idle']}", f":{ports['talker']}"}   # sent nothing by the server
        deadline = asyncio.get_running_loop().time() + 3.0
        i = 0
        while asyncio.get_running_loop().time() < deadline:
            talker_w.write(b"x")                       # the talker sends, the listener reads a stream
            srv.broadcast(message(i), only=lambda c: not c.peer.endswith(tuple(quiet)))
            i += 1
            try:
                while True:
                    await asyncio.wait_for(read_message(listener_r), 0.01)
            except asyncio.TimeoutError:
                pass
            await asyncio.sleep(0.1)
        left = sorted(int(c.peer.rsplit(":", 1)[1]) for c in srv.clients.values())
        assert ports["idle"] not in left and ports["deaf"] not in left, left
        assert srv.stats.connected == 2 and srv.stats.idle_drops == 1 and srv.stats.stall_drops == 1
        # the dropped idle client sees the connection closed
        idle.settimeout(2)
        assert idle.recv(10) == b""
        for s in (idle, deaf):
            s.close()
        talker_w.close()
        await srv.close()

    with caplog.at_level("INFO", logger="hilsim.links.tcp"):
        run(main())
    text = caplog.text
    assert "(idle): dropped" in text and "(not reading): dropped" in text


def test_accepted_connections_use_tcp_keepalive():
    """A peer gone without FIN or RST (half-open) is found by keep-alive probes, not left forever."""
    async def main():
        srv = TcpServer("t", keepalive=20.0)
        host, port = await srv.start()
        _, w = await asyncio.open_connection(host, port)
        while srv.stats.connected < 1:
            await asyncio.sleep(0.01)
        sock = next(iter(srv.clients.values())).writer.get_extra_info("socket")
        assert sock.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE) == 1
        if hasattr(socket, "TCP_KEEPIDLE"):
            assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE) == 20
            assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT) == 3
        w.close()
        await srv.close()

    run(main())


def _port_of(c) -> int:
    return int(c.peer.rsplit(":", 1)[1])


async def _refused(reader: asyncio.StreamReader, within: float = 1.0) -> bool:
    """Whether the server closed this fresh connection (EOF or reset) within ``within`` [s]."""
    try:
        return await asyncio.wait_for(reader.read(1), within) == b""
    except asyncio.TimeoutError:
        return False
    except (ConnectionError, OSError):
        return True


def test_a_full_server_evicts_the_client_longest_without_progress(caplog):
    """Full server (3 slots): an idle client (connected first, nothing either way), a deaf one
    (never reads what it is sent: stalled) and a talker. Past the grace, a newcomer evicts the
    idle one (longest without progress), the next the deaf one; the talker is never evicted, and
    once only clients making progress are left a newcomer is refused."""
    grace = 0.5

    async def main():
        srv = TcpServer("t", max_clients=3, evict_grace=grace, write_buffer=16 * 1024, sndbuf=4096,
                        stall_timeout=None, on_data=lambda c, d: None)
        host, port = await srv.start()
        idle = socket.create_connection((host, port))
        deaf = socket.socket()
        deaf.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        deaf.connect((host, port))
        talker_r, talker_w = await asyncio.open_connection(host, port)
        while srv.stats.connected < 3:
            await asyncio.sleep(0.01)
        deaf_port = deaf.getsockname()[1]
        for i in range(4):  # 200 kB for the deaf one: far more than its buffers take
            srv.broadcast(message(i), only=lambda c: _port_of(c) == deaf_port)
        talking = True

        async def talk():
            while talking:
                talker_w.write(b"x")
                await asyncio.sleep(0.05)
        talk_task = asyncio.ensure_future(talk())
        # within the grace nobody is evicted: the newcomer is refused
        r0, w0 = await asyncio.open_connection(host, port)
        assert await _refused(r0)
        assert srv.stats.evicted == 0 and srv.stats.refused == 1
        await asyncio.sleep(grace + 0.2)
        stale = {_port_of(c): srv.stale_for(c) for c in srv.clients.values()}
        assert stale[idle.getsockname()[1]][1] == "idle" and stale[deaf_port][1] == "stalled", stale
        assert stale[idle.getsockname()[1]][0] > stale[deaf_port][0] > grace, stale
        assert stale[talker_w.get_extra_info("sockname")[1]][0] < 0.3, stale  # it talks every 50 ms
        newcomers = []
        for expect_gone in (idle, deaf):
            r, w = await asyncio.open_connection(host, port)
            newcomers.append(w)
            assert not await _refused(r, 0.3)  # admitted: left open
            w.write(b"hello")  # and talks, so it is not idle itself
            left = {_port_of(c) for c in srv.clients.values()}
            assert expect_gone.getsockname()[1] not in left, left
            assert talker_w.get_extra_info("sockname")[1] in left
        assert srv.stats.evicted == 2
        idle.settimeout(2)
        assert idle.recv(10) == b""  # the evicted client sees its connection closed
        # only clients making progress now (talker + two newcomers, fresh): refused again
        r9, w9 = await asyncio.open_connection(host, port)
        assert await _refused(r9)
        assert srv.stats.evicted == 2 and srv.stats.refused == 2 and srv.stats.connected == 3
        talking = False
        await talk_task
        for s in (idle, deaf):
            s.close()
        for w in (w0, w9, talker_w, *newcomers):
            w.close()
        await srv.close()

    with caplog.at_level("INFO", logger="hilsim.links.tcp"):
        run(main())
    text = caplog.text
    assert "evicted (idle: sent nothing and took nothing but keep-alives for" in text
    assert "evicted (stalled: has taken nothing it was sent for" in text
    assert text.count("evicted (") == 2


def test_a_full_server_of_clients_making_progress_refuses_and_drops_none():
    """Every slot held by a client that talks or reads: past the grace a newcomer is still
    refused and every held client keeps being served."""
    async def main():
        srv = TcpServer("t", max_clients=2, evict_grace=0.3, on_data=lambda c, d: None)
        host, port = await srv.start()
        talker_r, talker_w = await asyncio.open_connection(host, port)
        reader_r, reader_w = await asyncio.open_connection(host, port)
        while srv.stats.connected < 2:
            await asyncio.sleep(0.01)
        got: list[int] = []
        for i in range(12):  # 1.2 s, four times the grace
            talker_w.write(b"x")
            srv.broadcast(message(i), only=lambda c: _port_of(c) == reader_w.get_extra_info("sockname")[1])
            got.append(await asyncio.wait_for(read_message(reader_r), 5))
            await asyncio.sleep(0.1)
            if i in (5, 11):
                r, w = await asyncio.open_connection(host, port)
                assert await _refused(r)
                w.close()
        assert got == list(range(12))
        assert srv.stats.evicted == 0 and srv.stats.refused == 2 and srv.stats.connected == 2
        for w in (talker_w, reader_w):
            w.close()
        await srv.close()

    run(main())


def test_a_stream_listener_with_nothing_to_read_is_not_idle():
    """command_channel=False (a stream whose clients only listen): a client the server has
    nothing to send is waiting on the server, not idle; it keeps its slot. With evict_grace
    None the server never evicts (the old behaviour)."""
    async def main():
        for kw in ({"command_channel": False, "evict_grace": 0.2}, {"evict_grace": None}):
            srv = TcpServer("t", max_clients=1, **kw)
            host, port = await srv.start()
            listener = socket.create_connection((host, port))
            while srv.stats.connected < 1:
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.5)
            r, w = await asyncio.open_connection(host, port)
            assert await _refused(r), kw
            assert srv.stats.evicted == 0 and srv.stats.connected == 1, kw
            w.close()
            listener.close()
            await srv.close()

    run(main())


def test_keep_alives_do_not_make_an_idle_client_less_idle():
    """A command channel's keep-alives (sent with progress=False: the kernel takes small messages
    for a peer that hung as well as for one that reads) leave a silent client idle, evictable past
    the grace; a client that takes real messages (a listener of its pings) is making progress."""
    async def main():
        srv = TcpServer("t", max_clients=2, evict_grace=0.4)
        host, port = await srv.start()
        silent = socket.create_connection((host, port))        # never fired: only keep-alives
        listener_r, listener_w = await asyncio.open_connection(host, port)  # gets real messages
        while srv.stats.connected < 2:
            await asyncio.sleep(0.01)
        lport = listener_w.get_extra_info("sockname")[1]
        got = 0
        for i in range(8):  # 0.8 s: twice the grace
            for c in list(srv.clients.values()):
                if _port_of(c) == lport:
                    srv.send(c, message(i))
                else:
                    srv.send(c, b"keep-alive", progress=False)
            got += await read_message(listener_r) == i
            await asyncio.sleep(0.1)
        assert got == 8
        ages = {_port_of(c): srv.stale_for(c) for c in srv.clients.values()}
        assert ages[silent.getsockname()[1]][1] == "idle" and ages[silent.getsockname()[1]][0] > 0.4, ages
        assert ages[lport][0] < 0.3, ages
        r, w = await asyncio.open_connection(host, port)
        assert not await _refused(r, 0.3)  # admitted: the silent one was evicted, the listener kept
        left = {_port_of(c) for c in srv.clients.values()}
        assert silent.getsockname()[1] not in left and lport in left
        assert srv.stats.evicted == 1
        for x in (listener_w, w):
            x.close()
        silent.close()
        await srv.close()

    run(main())
