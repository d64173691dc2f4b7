"""ARIS constants shared by the command channel, the beacon and the frame stream (``protocols/aris.md``)."""

from __future__ import annotations

from typing import Final

BEACON_PORT: Final = 56124
COMMAND_PORT: Final = 56888
MAX_DATAGRAM: Final = 1500
MAX_COMMAND_LENGTH: Final = 1024  # real commands are < 100 bytes
MAX_FRAME_DATA: Final = 128 * 4096  # beams x samples [bytes]
HEADER_SIZE: Final = 1024
FILE_VERSION: Final = 0x05464444  # "DDF\x05"

SYSTEM_1800: Final = 0
SYSTEM_3000: Final = 1
SYSTEM_1200: Final = 2

(SET_DATETIME, SET_FRAMESTREAM_RECEIVER, SET_FRAMESTREAM_SETTINGS, SET_ACOUSTICS, SET_SALINITY,
 SET_TELEPHOTO, SET_FOCUS) = range(7)
PING: Final = 14
FREQ_LOW: Final = 0
FREQ_HIGH: Final = 1
SALINITIES: Final = (0, 15, 35)
