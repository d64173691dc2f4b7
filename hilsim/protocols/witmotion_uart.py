"""The WitMotion UART stream of the WT901C / HWT905 TTL-RS232 IMUs (sans-I/O).

Sources: WitMotion's HWT905-TTL datasheet (v20-0707, "Communication Protocol": output data
format, config commands, return content, return rate, baud rate), the "WIT Standard
Communication Protocol" (register table, unlock within 10 s, save) and WitMotion's C SDK
(``REG.h``: register numbers, RSW bits, RRATE/BAUD codes; ``wit_c_sdk.c``: the packet
checksum and which registers each packet carries). The spec with byte diagrams is
``protocols/witmotion-uart.md``.

Device to host, 11-byte packets::

    0x55 | type | D0L D0H | D1L D1H | D2L D2H | D3L D3H | SUM      SUM = (sum of the 10 bytes before) & 0xFF

Each packet is four int16 registers, little-endian (:data:`PACKET_REGISTERS`): 0x50 time
(YYMM DDHH MMSS MS), 0x51 acceleration AX AY AZ (/32768 x 16 g) + TEMP (/100 deg C), 0x52
angular rate GX GY GZ (/32768 x 2000 deg/s) + TEMP, 0x53 angles Roll Pitch Yaw (/32768 x 180
deg) + VERSION, 0x54 magnetic field HX HY HZ + TEMP, 0x59 quaternion q0..q3 (/32768); 0x5F
answers a register read (four registers from the one asked for).

Host to device, 5-byte commands ``0xFF 0xAA reg dataL dataH``: unlock ``FF AA 69 88 B5``
(KEY = 0xB588; configuration is accepted for 10 s after it), save ``FF AA 00 00 00`` (SAVE:
0 save, 1 factory defaults, 0xFF restart), CALSW 0x01, RSW 0x02 (output content: bit
``type - 0x50``), RRATE 0x03 (:data:`RRATE_HZ`), BAUD 0x04 (:data:`BAUD_RATES`), READADDR
0x27 (read: ``FF AA 27 reg 00``). The device answers nothing to a write.

Here: :func:`encode_packet`, :func:`encode_command`, :class:`PacketDecoder` (host side),
:class:`CommandDecoder` (device side) and :class:`WitConfig` (the device's command handling
over its register store: the lock, content, rate, baud, save/restart/factory reset, reads).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Callable, Final, Optional, Sequence, Union

from hilsim.protocols.codec import NEED_DATA, BadFrame, ByteBuffer, Junk, NeedData

HEADER: Final = 0x55
COMMAND_HEAD: Final = b"\xff\xaa"
PACKET_SIZE: Final = 11
COMMAND_SIZE: Final = 5

# packet types (REG.h OUTPUTHEAD)
TIME, ACC, GYRO, ANGLE, MAG, PORT, PRESS, GPS, VELOCITY, QUATERNION, GSA = range(0x50, 0x5B)
REGVALUE: Final = 0x5F

# registers (REG.h)
SAVE, CALSW, RSW, RRATE, BAUD = 0x00, 0x01, 0x02, 0x03, 0x04
IICADDR: Final = 0x1A
READADDR: Final = 0x27
VERSION: Final = 0x2E
YYMM, DDHH, MMSS, MS = 0x30, 0x31, 0x32, 0x33
AX, GX, HX, ROLL, TEMP, Q0 = 0x34, 0x37, 0x3A, 0x3D, 0x40, 0x51
KEY: Final = 0x69
REGISTER_COUNT: Final = 0x90
KEY_UNLOCK: Final = 0xB588
UNLOCK_WINDOW: Final = 10.0  # [s] configuration accepted after an unlock

SAVE_PARAMS, SAVE_FACTORY, SAVE_RESTART = 0x0000, 0x0001, 0x00FF

# The four registers each packet type carries.
PACKET_REGISTERS: Final[dict[int, tuple[int, int, int, int]]] = {
    TIME: (YYMM, DDHH, MMSS, MS),
    ACC: (AX, AX + 1, AX + 2, TEMP),
    GYRO: (GX, GX + 1, GX + 2, TEMP),
    ANGLE: (ROLL, ROLL + 1, ROLL + 2, VERSION),
    MAG: (HX, HX + 1, HX + 2, TEMP),
    QUATERNION: (Q0, Q0 + 1, Q0 + 2, Q0 + 3),
}
SUPPORTED_CONTENT: Final = sum(1 << (t - TIME) for t in PACKET_REGISTERS)  # RSW bits this model sends
DEFAULT_RSW: Final = 0x001E          # acceleration, angular rate, angles, magnetic field
DEFAULT_RRATE: Final = 0x06          # 10 Hz

RRATE_HZ: Final[dict[int, float]] = {0x01: 0.2, 0x02: 0.5, 0x03: 1.0, 0x04: 2.0, 0x05: 5.0, 0x06: 10.0,
                                     0x07: 20.0, 0x08: 50.0, 0x09: 100.0, 0x0A: 125.0, 0x0B: 200.0}
RRATE_SINGLE: Final = 0x0C           # one output, then none
RRATE_NONE: Final = 0x0D             # no output
BAUD_RATES: Final[dict[int, int]] = {0x01: 4800, 0x02: 9600, 0x03: 19200, 0x04: 38400, 0x05: 57600,
                                     0x06: 115200, 0x07: 230400, 0x08: 460800, 0x09: 921600}
BAUD_CODES: Final = {v: k for k, v in BAUD_RATES.items()}

# Scales of the registers (SI <-> counts)
G: Final = 9.80665
ACC_SCALE: Final = 16.0 * G / 32768.0        # [m/s^2 per count]
GYRO_SCALE: Final = 2000.0 / 32768.0         # [deg/s per count]
ANGLE_SCALE: Final = 180.0 / 32768.0         # [deg per count]
QUAT_SCALE: Final = 1.0 / 32768.0


def checksum(data: Union[bytes, bytearray], start: int = 0) -> int:
    """Low byte of the sum of the 10 bytes ``data[start:start+10]``."""
    return sum(data[start:start + 10]) & 0xFF


def encode_packet(kind: int, words: Sequence[int]) -> bytes:
    """An 11-byte packet of type ``kind`` carrying four 16-bit registers (signed or not)."""
    if len(words) != 4:
        raise ValueError("a packet carries four registers")
    body = bytes((HEADER, kind & 0xFF)) + struct.pack("<4H", *(int(w) & 0xFFFF for w in words))
    return body + bytes((checksum(body),))


def encode_command(register: int, value: int) -> bytes:
    """``FF AA reg valueL valueH`` (a host's configuration write or read)."""
    return COMMAND_HEAD + struct.pack("<BH", register & 0xFF, value & 0xFFFF)


def content_kinds(rsw: int) -> list[int]:
    """Packet types an RSW value asks for that this model sends, in the order they go out."""
    return [t for t in sorted(PACKET_REGISTERS) if rsw >> (t - TIME) & 1]


def to_int16(value: int) -> int:
    """A 16-bit register as signed."""
    value &= 0xFFFF
    return value - 0x10000 if value & 0x8000 else value


# ----------------------------------------------------------------------------- events

@dataclass(frozen=True)
class Packet:
    """A packet with a good checksum: ``kind`` (0x50...), ``words`` the four registers as int16."""

    kind: int
    words: tuple[int, int, int, int]


@dataclass(frozen=True)
class Command:
    """A host command: write ``value`` (uint16) to ``register`` (READADDR: read ``value``)."""

    register: int
    value: int


@dataclass(frozen=True)
class PartialCommand(BadFrame):
    """A command cut short: the next ``FF AA`` came inside it, or the line went idle."""


class PacketDecoder(ByteBuffer):
    """Host side: the device's packet stream in, :class:`Packet` events out. Bytes before a
    0x55 are :class:`Junk`; a bad checksum gives :class:`BadFrame` and the search goes on
    from the next byte (as WitMotion's SDK does). Memory: one packet plus the last chunk."""

    def __init__(self) -> None:
        super().__init__()
        self.packets = 0
        self.bad_checksums = 0

    def next_event(self) -> Union[Packet, BadFrame, Junk, NeedData]:
        buf, pos = self._buf, self._pos
        start = buf.find(HEADER, pos)
        if start < 0:
            self._pos = len(buf)
            return Junk("no 0x55", len(buf) - pos) if len(buf) > pos else NEED_DATA
        if start > pos:
            self._pos = start
            return Junk("bytes before 0x55", start - pos)
        if len(buf) - pos < PACKET_SIZE:
            return NEED_DATA
        if checksum(buf, pos) != buf[pos + 10]:
            self._pos = pos + 1
            self.bad_checksums += 1
            return BadFrame("bad checksum", bytes(buf[pos:pos + PACKET_SIZE]))
        self._pos = pos + PACKET_SIZE
        self.packets += 1
        return Packet(buf[pos + 1], struct.unpack_from("<4h", buf, pos + 2))


class CommandDecoder(ByteBuffer):
    """Device side: the host's ``FF AA reg lo hi`` commands in, :class:`Command` out.

    Bytes before ``FF AA`` are :class:`Junk`. A command whose three bytes after the head
    hold the start of the next head (``FF AA``; no register is numbered 0xFF, and the
    value 0xAAFF in the last two) is a cut one: :class:`PartialCommand`, and decoding goes
    on at that head. :meth:`silence` (the line idle) drops a command still incomplete.
    Memory: one command plus the last chunk.
    """

    def __init__(self) -> None:
        super().__init__()
        self.commands = 0
        self.partial = 0

    def next_event(self) -> Union[Command, PartialCommand, Junk, NeedData]:
        buf, pos = self._buf, self._pos
        start = buf.find(COMMAND_HEAD, pos)
        if start < 0:
            keep = 1 if buf.endswith(b"\xff") and len(buf) > pos else 0  # maybe a head arriving
            end = len(buf) - keep
            self._pos = end
            return Junk("no FF AA", end - pos) if end > pos else NEED_DATA
        if start > pos:
            self._pos = start
            return Junk("bytes before FF AA", start - pos)
        if len(buf) - pos < COMMAND_SIZE:
            return NEED_DATA
        for cut in (2, 3):
            if buf[pos + cut] == 0xFF and buf[pos + cut + 1] == 0xAA:
                self._pos = pos + cut
                self.partial += 1
                return PartialCommand("command cut by the next FF AA", bytes(buf[pos:pos + cut]))
        self._pos = pos + COMMAND_SIZE
        self.commands += 1
        register, value = struct.unpack_from("<BH", buf, pos + 2)
        return Command(register, value)

    def silence(self) -> list[Union[Command, PartialCommand, Junk]]:
        """The line went idle: the events left, then an incomplete command is dropped."""
        out: list[Union[Command, PartialCommand, Junk]] = []
        for _ in range(self.buffered_bytes + 1):
            ev = self.next_event()
            if ev is NEED_DATA:
                break
            out.append(ev)
        rest = bytes(self._buf[self._pos:])
        self._pos = len(self._buf)
        if rest:
            if rest.startswith(COMMAND_HEAD):
                self.partial += 1
                out.append(PartialCommand("command cut by the line going idle", rest))
            else:
                out.append(Junk("bytes outside any command", len(rest)))
        return out


# ----------------------------------------------------------------------------- the device's side

class WitConfig:
    """How the device takes commands, over its register store (shared with its Modbus side).

    ``read(reg) -> uint16`` and ``write(reg, value)`` are the device's registers (RSW,
    RRATE, BAUD, CALSW, offsets, KEY... stored there; the device's own callbacks act on
    them). ``handle(cmd, now)`` [s] returns the reply bytes (a 0x5F packet for a read) or
    ``b""``. Writes count only within :data:`UNLOCK_WINDOW` of an unlock (else ignored and
    counted in ``locked``); reads are answered at any time. SAVE 0 keeps the running
    configuration as the saved one, 0xFF restarts (the saved configuration back, the lock
    closed), 1 restores the factory defaults (saved too). RSW, RRATE and BAUD take effect
    at once (as WitMotion's SDK and the community drivers expect: they set content and
    rate without a restart).
    """

    CONFIG: Final = (RSW, RRATE, BAUD, CALSW)

    def __init__(self, read: Callable[[int], int], write: Callable[[int, int], None], *,
                 defaults: Optional[dict[int, int]] = None) -> None:
        self.read = read
        self.write = write
        self.defaults = {RSW: DEFAULT_RSW, RRATE: DEFAULT_RRATE, BAUD: BAUD_CODES[115200], CALSW: 0,
                         **(defaults or {})}
        for reg, value in self.defaults.items():
            self.write(reg, value)
        self.saved = dict(self.defaults)
        self.unlocked_until = -1.0
        self.commands = 0
        self.locked = 0        # writes ignored: not unlocked
        self.rejected = 0      # writes ignored: a value the register does not take

    @property
    def rsw(self) -> int:
        return self.read(RSW)

    @property
    def rate_code(self) -> int:
        return self.read(RRATE)

    @property
    def rate(self) -> float:
        """[Hz] output rate (0: none; :data:`RRATE_SINGLE` counts as none once sent)."""
        return RRATE_HZ.get(self.rate_code, 0.0)

    @property
    def baudrate(self) -> int:
        return BAUD_RATES.get(self.read(BAUD), 115200)

    def valid(self, register: int, value: int) -> bool:
        """Whether the device takes ``value`` for ``register``."""
        if register == RRATE:
            return value in RRATE_HZ or value in (RRATE_SINGLE, RRATE_NONE)
        if register == BAUD:
            return value in BAUD_RATES
        if register == RSW:
            return value <= 0x0FFF
        if register == SAVE:
            return value in (SAVE_PARAMS, SAVE_FACTORY, SAVE_RESTART)
        return 0 <= register < REGISTER_COUNT and register != READADDR

    def handle(self, cmd: Command, now: float) -> bytes:
        self.commands += 1
        if cmd.register == READADDR:
            start = cmd.value & 0xFF
            words = [self.read(r) if r < REGISTER_COUNT else 0 for r in range(start, start + 4)]
            return encode_packet(REGVALUE, words)
        if cmd.register == KEY:
            if cmd.value == KEY_UNLOCK:
                self.unlocked_until = now + UNLOCK_WINDOW
            return b""
        if now > self.unlocked_until:
            self.locked += 1
            return b""
        if not self.valid(cmd.register, cmd.value):
            self.rejected += 1
            return b""
        if cmd.register == SAVE:
            if cmd.value == SAVE_PARAMS:
                self.saved = {r: self.read(r) for r in self.CONFIG}
            else:
                if cmd.value == SAVE_FACTORY:
                    self.saved = dict(self.defaults)
                for reg, value in self.saved.items():
                    self.write(reg, value)
                self.unlocked_until = -1.0
            return b""
        self.write(cmd.register, cmd.value)
        return b""


__all__ = ["ACC", "ANGLE", "BAUD", "BAUD_CODES", "BAUD_RATES", "CALSW", "Command", "CommandDecoder",
           "DEFAULT_RRATE", "DEFAULT_RSW", "GYRO", "KEY", "KEY_UNLOCK", "MAG", "PACKET_REGISTERS", "Packet",
           "PacketDecoder", "PartialCommand", "QUATERNION", "READADDR", "REGVALUE", "RRATE", "RRATE_HZ",
           "RRATE_NONE", "RRATE_SINGLE", "RSW", "SAVE", "TIME", "WitConfig", "checksum", "content_kinds",
           "encode_command", "encode_packet", "to_int16"]
