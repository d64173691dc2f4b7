"""What a link delivers, read off a fuzzer's byte stream: datagrams and CAN frames.

:class:`Datagrams`: a 2-byte big-endian length before each datagram. :class:`CanRecords`:
SocketCAN's 16-byte ``struct can_frame`` records. Both give ``units(data) -> [(unit, pause [s])]``
and keep a partial unit (``buffered_bytes``).
"""

from __future__ import annotations

import struct

from hilsim.protocols.can import CanFrame


class Datagrams:
    """Bytes -> datagrams, each a 2-byte big-endian length then that many bytes."""

    def __init__(self) -> None:
        self._partial = bytearray()

    @property
    def buffered_bytes(self) -> int:
        return len(self._partial)

    def datagrams(self, data: bytes) -> list[bytes]:
        self._partial += data
        out, pos = [], 0
        while len(self._partial) - pos >= 2:
            n = int.from_bytes(self._partial[pos : pos + 2], "big")
            if len(self._partial) - pos - 2 < n:
                break
            out.append(bytes(self._partial[pos + 2 : pos + 2 + n]))
            pos += 2 + n
        del self._partial[:pos]
        return out

    def units(self, data: bytes) -> list[tuple[bytes, float]]:
        return [(d, 0.0) for d in self.datagrams(data)]


def datagram(d: bytes) -> bytes:
    return len(d).to_bytes(2, "big") + d


CAN_EFF_FLAG, CAN_RTR_FLAG, CAN_ERR_FLAG = 0x80000000, 0x40000000, 0x20000000
CAN_RECORD = struct.Struct("<IBxBx8s")  # struct can_frame: can_id, len, __pad, __res0, len8_dlc, data[8]
CAN_RECORD_SIZE = CAN_RECORD.size
PAUSE_UNIT = 0.02  # [s] per unit of __res0, read here as the pause before the frame


def can_record(frame: CanFrame) -> bytes:
    """A frame as SocketCAN's ``struct can_frame`` (can_id little-endian, as on x86)."""
    can_id = frame.arbitration_id | (CAN_EFF_FLAG if frame.is_extended else 0) | (
        CAN_RTR_FLAG if frame.is_remote else 0)
    return CAN_RECORD.pack(can_id, frame.dlc, 0, frame.data.ljust(8, b"\0"))


class CanRecords:
    """Bytes -> (CanFrame, pause [s]). Error frames and lengths over 8 are dropped (the kernel
    refuses them); ``__res0`` (0 from the kernel) is the bus's silence before the frame in
    PAUSE_UNIT steps, so a fuzzer can reach the receivers' timeouts."""

    def __init__(self) -> None:
        self._partial = bytearray()

    @property
    def buffered_bytes(self) -> int:
        return len(self._partial)

    def units(self, data: bytes) -> list[tuple[CanFrame, float]]:
        self._partial += data
        n = len(self._partial) // CAN_RECORD_SIZE
        out = []
        for i in range(n):
            can_id, length, pause, payload = CAN_RECORD.unpack_from(self._partial, i * CAN_RECORD_SIZE)
            if can_id & CAN_ERR_FLAG or length > 8:
                continue
            ext, rtr = bool(can_id & CAN_EFF_FLAG), bool(can_id & CAN_RTR_FLAG)
            ident = can_id & (0x1FFFFFFF if ext else 0x7FF)
            frame = CanFrame(ident, b"", ext, True, length) if rtr else CanFrame(ident, bytes(payload[:length]), ext)
            out.append((frame, pause * PAUSE_UNIT))
        del self._partial[: n * CAN_RECORD_SIZE]
        return out
