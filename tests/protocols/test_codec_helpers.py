"""The shared helpers of the codec contract: ByteBuffer, CountedJunk; and CanFrame.hex_id."""

from __future__ import annotations

import dataclasses

import pytest

from hilsim.protocols import codec
from hilsim.protocols.can import CanFrame


class Consumer(codec.ByteBuffer):
    """Consumes ``n`` bytes at a time, remembering each consumed run's stream offset."""

    def take(self, n: int) -> tuple[int, bytes]:
        at = self._base + self._pos
        out = bytes(self._buf[self._pos:self._pos + n])
        self._pos += len(out)
        return at, out


def test_byte_buffer_keeps_what_is_not_consumed_and_the_stream_offsets() -> None:
    b = Consumer()
    assert b.buffered_bytes == 0
    b.receive_data(b"")
    assert b.buffered_bytes == 0
    stream = bytes(range(200))
    got = []
    for i in range(0, 200, 7):
        chunk = stream[i:i + 7]
        b.receive_data(chunk)
        # consumed bytes are dropped once they are half the buffer: fewer are kept than are pending
        assert b._pos == 0 or b._pos < b.buffered_bytes - len(chunk)
        got.append(b.take(5))
        assert b.buffered_bytes == len(b._buf) - b._pos
    rest = b.take(10_000)
    seen = b"".join(x for _, x in got) + rest[1]
    assert seen == stream and b.buffered_bytes == 0
    for at, x in got + [rest]:
        assert stream[at:at + len(x)] == x


def test_counted_junk() -> None:
    class MyJunk(codec.CountedJunk):
        DEFAULT_REASON = "bytes before the marker"

    j = MyJunk(3)
    assert (j.n_bytes, j.reason) == (3, "bytes before the marker")
    assert isinstance(j, codec.Junk) and j == MyJunk(3) and hash(j) == hash(MyJunk(3))
    assert j != codec.CountedJunk(3) and j != MyJunk(4)
    assert MyJunk(2, "other").reason == "other"
    assert codec.CountedJunk(1).reason == "bytes skipped while resynchronising"
    assert dataclasses.replace(j, n_bytes=5) == MyJunk(5)
    assert repr(j).endswith("MyJunk(reason='bytes before the marker', n_bytes=3)")
    with pytest.raises(dataclasses.FrozenInstanceError):
        j.n_bytes = 4  # type: ignore[misc]


@pytest.mark.parametrize("frame, text", [(CanFrame(0x12, b"", False), "012"), (CanFrame(0x7FF, b"", False), "7FF"),
                                         (CanFrame(0x12), "00000012"), (CanFrame(0x1FFFFFFF), "1FFFFFFF")])
def test_can_hex_id(frame: CanFrame, text: str) -> None:
    assert frame.hex_id == text
    assert repr(frame).startswith(f"CanFrame({text} [")
