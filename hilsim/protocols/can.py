"""A classic CAN 2.0 frame, the unit every CAN codec and CAN link here exchanges.

Only classic CAN: 11-bit (standard) or 29-bit (extended) identifiers, 0..8
data bytes, optional remote (RTR) frames whose ``dlc`` is the requested
length. CAN FD is not modelled.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Final

STANDARD_ID_MAX: Final = 0x7FF
EXTENDED_ID_MAX: Final = 0x1FFFFFFF
MAX_DATA: Final = 8


@dataclass(frozen=True, slots=True)
class CanFrame:
    """One CAN frame.

    arbitration_id: 11-bit (``is_extended`` False) or 29-bit identifier;
    data: 0..8 bytes (empty for a remote frame); is_remote: an RTR frame asking
    for ``dlc`` bytes; timestamp: [s] when it was received (0 if unknown; not
    part of equality).
    """

    arbitration_id: int
    data: bytes = b""
    is_extended: bool = True
    is_remote: bool = False
    dlc: int = -1
    timestamp: float = field(default=0.0, compare=False)

    def __post_init__(self) -> None:
        limit = EXTENDED_ID_MAX if self.is_extended else STANDARD_ID_MAX
        if not 0 <= self.arbitration_id <= limit:
            kind = "extended" if self.is_extended else "standard"
            raise ValueError(f"{kind} CAN id {self.arbitration_id:#x} out of range 0..{limit:#x}")
        if len(self.data) > MAX_DATA:
            raise ValueError(f"CAN frame data is {len(self.data)} bytes; classic CAN carries at most 8")
        if not isinstance(self.data, bytes):
            object.__setattr__(self, "data", bytes(self.data))
        if self.is_remote and self.data:
            raise ValueError("a remote frame carries no data")
        dlc = len(self.data) if self.dlc < 0 else self.dlc
        if not 0 <= dlc <= MAX_DATA or (not self.is_remote and dlc != len(self.data)):
            raise ValueError(f"bad dlc {self.dlc} for {len(self.data)} data bytes")
        object.__setattr__(self, "dlc", dlc)

    def __repr__(self) -> str:
        body = f"RTR dlc={self.dlc}" if self.is_remote else self.data.hex(" ")
        return f"CanFrame({self.hex_id} [{body}])"

    @property
    def hex_id(self) -> str:
        """The identifier in upper-case hex, 8 digits if extended, else 3 (as slcan, socketcand
        and candump write it)."""
        return f"{self.arbitration_id:08X}" if self.is_extended else f"{self.arbitration_id:03X}"

    @property
    def bits_on_wire(self) -> int:
        """Approximate bits this frame occupies on the bus, with worst-case-ish bit stuffing.

        Standard frame: 47 overhead bits + 8 per data byte; extended: 67 + 8 per byte;
        about one stuff bit per 5 of the stuffable part, plus 3 bits of interframe space.
        """
        n = 0 if self.is_remote else len(self.data)
        base = (67 if self.is_extended else 47) + 8 * n
        stuffable = base - 13  # CRC delimiter, ACK, EOF are not stuffed
        return base + stuffable // 5 + 3
