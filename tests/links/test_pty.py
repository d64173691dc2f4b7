"""The pty serial link: a real serial client (pyserial) on the symlink."""

from __future__ import annotations

import asyncio
import os
import time

import serial

from hilsim.links.pty import PtyLink


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 30))


def test_echo_through_pyserial_and_reopen(tmp_path):
    async def main():
        got = []
        link = PtyLink("test", tmp_path / "port", baudrate=115200)
        link.on_data = lambda b: (got.append(b), link.write(b.upper()))
        path = await link.start()
        assert os.path.islink(path)

        def client(msg: bytes) -> bytes:
            with serial.Serial(path, 115200, timeout=2) as s:
                s.write(msg)
                return s.read(len(msg))

        for round_ in range(3):  # the client closes and reopens: the port keeps working
            reply = await asyncio.to_thread(client, b"hello %d" % round_)
            assert reply == b"HELLO %d" % round_
        await link.close()
        assert not os.path.lexists(path)
        assert b"".join(got) == b"hello 0hello 1hello 2"

    run(main())


def test_output_is_paced_at_the_baud_rate(tmp_path):
    async def main():
        link = PtyLink("slow", tmp_path / "p", baudrate=9600)
        path = await link.start()

        def client() -> float:
            with serial.Serial(path, 9600, timeout=3) as s:
                t0 = time.monotonic()
                link_loop.call_soon_threadsafe(link.write, bytes(480))
                data = s.read(480)
                assert len(data) == 480
                return time.monotonic() - t0

        link_loop = asyncio.get_running_loop()
        took = await asyncio.to_thread(client)
        # 480 bytes x 10 bits at 9600 baud = 0.5 s; never faster than the line
        assert took >= 0.45
        await link.close()

    run(main())


def test_a_client_that_does_not_read_gets_bounded_backlog_then_fresh_bytes(tmp_path):
    async def main():
        link = PtyLink("t", tmp_path / "q", baudrate=0)
        path = await link.start()
        s = serial.Serial(path, 115200, timeout=0.5)  # open, but not reading
        for _ in range(20):  # 20 kB of replies the client does not read
            link.write(b"x" * 1000)
            await link.drain()
        link.write(b"FRESH")
        await link.drain()
        data = await asyncio.to_thread(s.read, 100000)
        s.close()
        # like a UART driver buffer: a bounded backlog, then the newest bytes, never blocked
        assert data.endswith(b"FRESH") and len(data) <= 4096 + 5
        await link.close()

    run(main())
