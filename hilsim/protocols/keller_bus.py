"""The KELLER bus protocol of the Series 30 digital pressure transmitters (sans-I/O).

Source: KELLER "Communication protocol Serie30" (chapters 3 and 5; also printed as the
Xylem 7060/7070 user guide); the spec with byte diagrams is ``protocols/keller-bus.md``.

A frame on the line (master and slave alike)::

    DevAddr | Function | n parameter/data bytes | CRC16_H | CRC16_L

The CRC is CRC-16/MODBUS (polynomial 0xA001 reflected, initial 0xFFFF) over every byte
before it, sent **high byte first** (Modbus RTU sends the same CRC low byte first). The
same RS485 line serves Modbus RTU as well: "Both protocols are active ... the implemented
MODBUS function codes are not used in the KELLER protocol", so a request is told from a
Modbus one by its function code (:func:`is_keller_function`). Only the KELLER bus needs
initialising: after power-up every function but F48 answers exception 32 until F48 was
sent (Modbus needs none).

Here:

* :func:`crc16`, :func:`encode_frame` (CRC appended high byte first), :func:`crc_ok`;
* :func:`keller_request_length`: a request's length by its function code, with the
  contract of the Modbus RTU length rule (``0`` need more bytes, ``-1`` cannot tell);
* :class:`KellerRequestDecoder`: bytes in, :class:`KellerRequest` / :class:`WrongLength`
  / :class:`~hilsim.protocols.codec.BadFrame` / :class:`~hilsim.protocols.codec.Junk`
  out; :meth:`KellerRequestDecoder.silence` ends a frame when the line goes idle;
* reply encoders (:func:`encode_f48` ... :func:`encode_exception`);
* :class:`KellerResponder`: the slave's protocol state (initialised or not, its address,
  the transparent address 250, broadcast 0) answering requests from callables that give
  the device's values; it never raises on peer input.
"""

from __future__ import annotations

import math
import struct
from collections import deque
from dataclasses import dataclass
from typing import Callable, Final, Optional, Union

from hilsim.protocols.codec import NEED_DATA, BadFrame, ByteBuffer, Junk, NeedData
from hilsim.protocols.modbus_pdu import crc16  # KELLER frames carry the CRC-16/MODBUS (high byte first)

BROADCAST: Final = 0
TRANSPARENT: Final = 250          # every device answers it (stand-alone use only)
MAX_ADDRESS: Final = 249          # bus addresses 1..249

EXC_FUNCTION: Final = 1           # non-implemented function
EXC_PARAMETER: Final = 2          # incorrect parameter
EXC_LENGTH: Final = 3             # erroneous data / message length
EXC_CHANNEL: Final = 4            # F74: channel in overflow/underflow/inactive
EXC_NOT_INITIALISED: Final = 32   # KELLER bus only: F48 not yet sent since power-up

# Request lengths (address + function + parameters + CRC) per function, from chapter 5.
REQUEST_LENGTHS: Final[dict[int, tuple[int, ...]]] = {
    30: (5,),      # read coefficient: Nr
    31: (9,),      # write coefficient: Nr, float32
    32: (5,),      # read configuration: Nr
    33: (6,),      # write configuration: Nr, byte
    48: (4,),      # initialise and release
    66: (5,),      # write and read device address: NewAddr
    69: (4,),      # read serial number
    73: (5,),      # read channel, float: CH
    74: (5,),      # read channel, int32: CH
    95: (5, 9),    # zero point: CMD [, float32 setpoint]
    100: (5,),     # read configuration (5 bytes): index
    101: (10,),    # write configuration: index, 5 bytes
}
MAX_REQUEST: Final = 10
MAX_COEFFICIENT: Final = 111      # F30/F31: "exception 2 if no. > 111"
# F30 coefficients (IEEE754, bar / deg C): 64 offset P1, 65 gain P1, 66/67 P2, 70/71 CH0,
# 80/81 min/max pressure of P1, 82/83 of P2, 84/85 min/max T, 86/87 TOB1, 88/89 TOB2, 100-111 free.
COEFF_OFFSET_P1: Final = 64
COEFF_GAIN_P1: Final = 65
COEFF_P1_MIN: Final = 80
COEFF_P1_MAX: Final = 81
MIN_FRAME: Final = 4              # "the length of a message from the master is at least 4 bytes"
MAX_FRAME: Final = 16             # a burst longer than this with no frame in it is hunted through

NEED_MORE: Final = 0              # keller_request_length: more bytes are needed to tell
UNDELIMITED: Final = -1           # keller_request_length: not a KELLER function (ends at silence)

# F73/F74 channels: number -> (name, unit on the wire); STAT bit = channel number.
CHANNELS: Final = {0: ("CH0", "bar"), 1: ("P1", "bar"), 2: ("P2", "bar"), 3: ("T", "degC"),
                   4: ("TOB1", "degC"), 5: ("TOB2", "degC")}
STAT_POWER_UP: Final = 0x80       # /STD: power-up mode (else standard mode)
STAT_ERR2: Final = 0x40           # analogue output computation error


def crc_ok(buf: Union[bytes, bytearray], start: int, end: int) -> bool:
    """``buf[start:end]`` ends with the CRC of the bytes before it, high byte first (KELLER order)."""
    if end - start < 3:
        return False
    crc = crc16(buf, start, end - 2)
    return buf[end - 2] == crc >> 8 and buf[end - 1] == crc & 0xFF


def encode_frame(address: int, function: int, data: bytes = b"") -> bytes:
    """``address | function | data | CRC16_H | CRC16_L`` (a request or a reply)."""
    body = bytes((address & 0xFF, function & 0xFF)) + bytes(data)
    crc = crc16(body)
    return body + bytes((crc >> 8, crc & 0xFF))


def is_keller_function(function: int) -> bool:
    """Whether a request with this function code is a KELLER bus request (else Modbus, or unknown)."""
    return function in REQUEST_LENGTHS


def keller_request_length(buf: Union[bytes, bytearray], pos: int = 0) -> int:
    """Length of the KELLER request at ``buf[pos]`` by its function code: :data:`NEED_MORE`
    until enough bytes are there to tell, :data:`UNDELIMITED` for a function code that is
    not the KELLER bus's. F95 is 5 bytes, or 9 with a setpoint: 5 when those 5 carry a
    good CRC, else 9."""
    avail = len(buf) - pos
    if avail < 2:
        return NEED_MORE
    lengths = REQUEST_LENGTHS.get(buf[pos + 1])
    if lengths is None:
        return UNDELIMITED
    if len(lengths) == 1:
        return lengths[0]
    if avail < lengths[0]:
        return NEED_MORE
    return lengths[0] if crc_ok(buf, pos, pos + lengths[0]) else lengths[1]


# ----------------------------------------------------------------------------- events

@dataclass(frozen=True)
class KellerRequest:
    """A request with a good CRC: ``address`` (0 broadcast, 250 transparent), ``function``,
    ``data`` (the parameter bytes between the function and the CRC). A function the
    protocol does not have comes this way too (the slave answers exception 1)."""

    address: int
    function: int
    data: bytes = b""


@dataclass(frozen=True)
class WrongLength(BadFrame):
    """A frame with a good CRC whose length is wrong for its function (exception 3)."""

    address: int = 0
    function: int = 0


KellerEvent = Union[KellerRequest, WrongLength, BadFrame, Junk]


class KellerRequestDecoder(ByteBuffer):
    """Requests from a master on a KELLER-only line (sans-I/O; :mod:`hilsim.protocols.codec`).

    Frames are delimited by the length their function code defines, so requests sent
    back to back are each decoded. A frame whose CRC fails at that length may be longer
    (a wrong length) or garbage: it is held until the line goes idle (:meth:`silence`, a
    gap of 3.5 characters on a serial line): then the burst is one frame, as the device
    takes it: a good CRC gives :class:`WrongLength` (known function) or a
    :class:`KellerRequest` (unknown function: exception 1); a bad one is searched for
    frames the length rules delimit and the rest is dropped (:class:`Junk`; a burst with
    no frame in it at all: one :class:`BadFrame`, discarded as the device does). Without
    a gap, more than :data:`MAX_FRAME` bytes with no frame at their start are hunted
    through byte by byte (:class:`Junk`). Memory: at most :data:`MAX_FRAME` bytes plus
    the last chunk.
    """

    def __init__(self) -> None:
        super().__init__()
        self._queue: deque[KellerEvent] = deque()
        self._junk = 0          # bytes skipped and not yet reported
        self._hunting = False   # sync lost (no gap since): only frames the rules delimit are looked for
        self.requests = 0
        self.crc_errors = 0
        self.junk_bytes = 0

    def next_event(self) -> Union[KellerEvent, NeedData]:
        if self._queue:
            return self._queue.popleft()
        ev = self._parse(final=False)
        return NEED_DATA if ev is None else ev

    def silence(self) -> list[KellerEvent]:
        """The line went idle: what is buffered ends here (the next byte starts a frame).
        Returns every event left, in order (they are no longer queued)."""
        out: list[KellerEvent] = []
        for _ in range(4 * self.buffered_bytes + 4 + len(self._queue)):  # bounded: each pass consumes
            if self._queue:
                out.append(self._queue.popleft())
                continue
            ev = self._parse(final=True)
            if ev is None:
                break
            out.append(ev)
        self._hunting = False
        return out

    # -- framing --

    def _take(self, n: int) -> bytes:
        frame = bytes(self._buf[self._pos:self._pos + n])
        self._pos += n
        return frame

    def _skip(self, n: int = 1) -> None:
        self._pos += n
        self._junk += n
        self.junk_bytes += n

    def _emit(self, ev: Optional[KellerEvent]) -> Optional[KellerEvent]:
        """``ev``, after a :class:`Junk` for the bytes skipped before it (if any)."""
        if self._junk:
            n, self._junk = self._junk, 0
            if ev is not None:
                self._queue.append(ev)
            return Junk("bytes outside any frame", n)
        return ev

    def _frame_at(self, buf: bytearray, pos: int) -> int:
        """Length of a complete frame with a good CRC at ``pos`` by the length rules, or 0."""
        lengths = REQUEST_LENGTHS.get(buf[pos + 1]) if len(buf) - pos >= 2 else None
        for n in lengths or ():
            if len(buf) - pos >= n and crc_ok(buf, pos, pos + n):
                return n
        return 0

    def _parse(self, final: bool) -> Optional[KellerEvent]:
        buf = self._buf
        for _ in range(len(buf) + 2):  # bounded: each pass consumes a byte or returns
            pos = self._pos
            avail = len(buf) - pos
            if not avail:
                return self._emit(None)
            n = self._frame_at(buf, pos)
            if n:
                frame = self._take(n)
                self._hunting = False
                self.requests += 1
                return self._emit(KellerRequest(frame[0], frame[1], frame[2:-2]))
            if final:  # the line is idle: the burst is one frame
                ev = self._burst()
                if ev is not None:
                    return self._emit(ev)
                continue  # a frame was found inside: skipped up to it
            lengths = REQUEST_LENGTHS.get(buf[pos + 1]) if avail >= 2 else None
            if lengths is not None and avail < max(lengths):
                return None  # a frame still arriving
            if avail < 2 or not (self._hunting or avail > MAX_FRAME):
                return None  # the gap decides (a wrong length, an unknown function or garbage)
            self._hunting = True  # no frame starts here and no gap came: look one byte on
            self._skip()
        return None

    def _burst(self) -> Optional[KellerEvent]:
        """The buffer at a gap, with no frame by the length rules at its start: the event, or
        None when frames were found inside (the bytes before the first one skipped)."""
        buf, pos = self._buf, self._pos
        avail = len(buf) - pos
        if avail >= MIN_FRAME and crc_ok(buf, pos, len(buf)):
            frame = self._take(avail)
            if is_keller_function(frame[1]):
                return WrongLength(f"F{frame[1]}: {len(frame)} bytes", frame[:32], frame[0], frame[1])
            self.requests += 1
            return KellerRequest(frame[0], frame[1], frame[2:-2])
        for i in range(1, avail - MIN_FRAME + 1):  # frames inside a garbled burst
            if self._frame_at(buf, pos + i):
                self._skip(i)
                return None
        self.crc_errors += 1
        frame = self._take(avail)
        return BadFrame("bad CRC or too short (discarded)", frame[:32])


def request_from_frame(frame: bytes) -> Union[KellerRequest, WrongLength]:
    """A whole frame whose CRC checked out (from a line shared with Modbus) as the event the
    responder takes: a length its function does not have is :class:`WrongLength`."""
    lengths = REQUEST_LENGTHS.get(frame[1], ())
    if lengths and len(frame) not in lengths:
        return WrongLength(f"F{frame[1]}: {len(frame)} bytes", bytes(frame[:32]), frame[0], frame[1])
    return KellerRequest(frame[0], frame[1], bytes(frame[2:-2]))


class KellerDialect:
    """The KELLER bus as the dialect of a Modbus RTU line (:class:`hilsim.protocols.modbus.RtuDialect`)."""

    def owns(self, function: int) -> bool:
        return is_keller_function(function)

    def request_length(self, buf: Union[bytes, bytearray], pos: int) -> int:
        return keller_request_length(buf, pos)

    def crc_ok(self, buf: Union[bytes, bytearray], start: int, end: int) -> bool:
        return crc_ok(buf, start, end)


DIALECT: Final = KellerDialect()


# ----------------------------------------------------------------------------- replies

def encode_exception(address: int, function: int, code: int) -> bytes:
    """Exception reply: ``address | function | 0x80 | code | CRC``."""
    return encode_frame(address, (function | 0x80) & 0xFF, bytes((code & 0xFF,)))


def encode_f48(address: int, device_class: int, group: int, year: int, week: int, buffer: int,
               state: int) -> bytes:
    """F48 reply: class, group, firmware year and week, receive buffer length, state
    (0: first F48 since power-up, 1: already initialised)."""
    return encode_frame(address, 48, bytes((device_class, group, year, week, buffer, state)))


def encode_f66(address: int, actual_address: int) -> bytes:
    """F66 reply: the device's address after the request."""
    return encode_frame(address, 66, bytes((actual_address,)))


def encode_f69(address: int, serial_number: int) -> bytes:
    """F69 reply: the serial number as uint32, most significant byte first."""
    return encode_frame(address, 69, struct.pack(">I", serial_number & 0xFFFFFFFF))


def encode_f73(address: int, value: float, status: int) -> bytes:
    """F73 reply: the channel's value as IEEE-754 float32, high byte first (bar or deg C), then STAT."""
    return encode_frame(address, 73, struct.pack(">fB", value, status & 0xFF))


def encode_f74(address: int, value: int, status: int) -> bytes:
    """F74 reply: int32, high byte first (Pa, or 0.01 deg C), then STAT."""
    return encode_frame(address, 74, struct.pack(">iB", value, status & 0xFF))


def encode_f95(address: int) -> bytes:
    """F95 reply: ``address | 95 | 0 | CRC``."""
    return encode_frame(address, 95, b"\x00")


# ----------------------------------------------------------------------------- the slave

class KellerError(Exception):
    """Raised by a device callback to answer an exception ``code``."""

    def __init__(self, code: int, reason: str = "") -> None:
        super().__init__(reason or f"exception {code}")
        self.code = code


@dataclass(frozen=True)
class Identity:
    """What F48 tells: class 5 = Series 30 digital transmitter, group 20 = from 2002 on;
    firmware year/week; the receive buffer length [bytes]."""

    device_class: int = 5
    group: int = 20
    year: int = 10
    week: int = 40
    buffer: int = MAX_REQUEST


class KellerResponder:
    """The KELLER bus side of one Series 30 transmitter: requests in, reply frames out.

    The device supplies its state through callables, so a Modbus side on the same device
    shares it: ``get_address()``/``set_address(new) -> bool`` (False: refused, the
    address stays), ``serial_number()``, ``read_channel(ch) -> SI value`` (Pa for CH0,
    P1, P2; K for T, TOB1, TOB2; NaN = channel error or not fitted), ``set_zero(cmd,
    setpoint_pa)`` (F95: cmd 0/2/6 set zero of P1/P2/CH0 so the value reads the setpoint
    [Pa] (0 without one), 1/3/7 reset; may raise :class:`KellerError`). ``active``: the
    channels fitted (their STAT bits flag a NaN). ``coefficient(nr)``: F30's value in its wire
    unit (bar, deg C; None: what F31 stored, 0 if nothing); ``write_coefficient(nr, value)``:
    F31, True when the device acts on it (else the value is only stored). Power-up state:
    not initialised.
    """

    def __init__(self, *, get_address: Callable[[], int], set_address: Callable[[int], bool],
                 serial_number: Callable[[], int], read_channel: Callable[[int], float],
                 set_zero: Callable[[int, Optional[float]], None], identity: Identity = Identity(),
                 active: frozenset[int] = frozenset({1, 3, 4}),
                 coefficient: Optional[Callable[[int], Optional[float]]] = None,
                 write_coefficient: Optional[Callable[[int, float], bool]] = None) -> None:
        self.coefficient = coefficient or (lambda nr: None)
        self.write_coefficient = write_coefficient or (lambda nr, value: False)
        self.stored: dict[int, float] = {}  # coefficients written that the device does not act on
        self.get_address = get_address
        self.set_address = set_address
        self.serial_number = serial_number
        self.read_channel = read_channel
        self.set_zero = set_zero
        self.identity = identity
        self.active = active
        self.initialised = False
        self.requests = 0
        self.exceptions = 0
        self.ignored = 0
        self.internal_errors = 0

    def power_up(self) -> None:
        """Supply switched on again: F48 is needed before anything else."""
        self.initialised = False

    def answers(self, address: int) -> bool:
        """A request to ``address`` is ours (broadcast 0 is executed without a reply)."""
        return address in (self.get_address(), TRANSPARENT, BROADCAST)

    def handle_frame(self, frame: bytes) -> Optional[bytes]:
        """The reply to a whole frame from a shared line (its CRC already checked), or None."""
        return self.handle(request_from_frame(frame))

    def handle(self, event: Union[KellerRequest, WrongLength]) -> Optional[bytes]:
        """The reply frame to ``event``, or None (another device's address, or broadcast)."""
        address = event.address
        if not self.answers(address):
            self.ignored += 1
            return None
        self.requests += 1
        function = event.function
        try:
            lengths = REQUEST_LENGTHS.get(function, ())
            if isinstance(event, WrongLength) or (lengths and len(event.data) + 4 not in lengths):
                if function != 48 and not self.initialised:
                    raise KellerError(EXC_NOT_INITIALISED)
                raise KellerError(EXC_LENGTH, f"F{function}: wrong length")
            reply = self._dispatch(address, function, event.data)
        except KellerError as exc:
            reply = encode_exception(address, function, exc.code)
            self.exceptions += 1
        except Exception:  # a bug of ours: answer nothing rather than stop the device
            self.internal_errors += 1
            return None
        return None if address == BROADCAST else reply

    def _status(self) -> int:
        stat = 0
        for ch in self.active:
            if not math.isfinite(self.read_channel(ch)):
                stat |= 1 << ch
        return stat

    def _dispatch(self, address: int, function: int, data: bytes) -> bytes:
        if function == 48:
            state = 1 if self.initialised else 0
            self.initialised = True
            i = self.identity
            return encode_f48(address, i.device_class, i.group, i.year, i.week, i.buffer, state)
        if not self.initialised:
            raise KellerError(EXC_NOT_INITIALISED)
        if function == 69:
            return encode_f69(address, self.serial_number())
        if function in (73, 74):
            ch = data[0]
            if ch not in CHANNELS:
                raise KellerError(EXC_PARAMETER, f"channel {ch}")
            si = self.read_channel(ch)
            if function == 73:
                return encode_f73(address, _to_wire(ch, si), self._status())
            if not math.isfinite(si) or ch not in self.active:
                raise KellerError(EXC_CHANNEL, f"channel {ch} invalid")
            raw = round(si if ch <= 2 else (si - 273.15) * 100.0)
            if not -2**31 <= raw < 2**31:
                raise KellerError(EXC_CHANNEL, f"channel {ch} overflow")
            return encode_f74(address, raw, self._status())
        if function == 66:
            new = data[0]
            if 1 <= new <= MAX_ADDRESS and new != self.get_address():
                self.set_address(new)  # refused: the old address is confirmed
            return encode_f66(address, self.get_address())
        if function == 95:
            cmd = data[0]
            if cmd not in (0, 1, 2, 3, 6, 7):
                raise KellerError(EXC_PARAMETER, f"F95 command {cmd}")
            setpoint = None
            if cmd in (0, 2, 6):
                setpoint = struct.unpack(">f", data[1:5])[0] * 1e5 if len(data) == 5 else 0.0
            elif len(data) != 1:
                raise KellerError(EXC_LENGTH, f"F95 command {cmd} takes no setpoint")
            self.set_zero(cmd, setpoint)
            return encode_f95(address)
        if function in (30, 31):
            nr = data[0]
            if nr > MAX_COEFFICIENT:
                raise KellerError(EXC_PARAMETER, f"coefficient {nr}")
            if function == 30:
                value = self.coefficient(nr)
                return encode_frame(address, 30, struct.pack(">f", self.stored.get(nr, 0.0) if value is None
                                                             else value))
            value = struct.unpack(">f", data[1:5])[0]
            if not self.write_coefficient(nr, value):
                self.stored[nr] = value
            return encode_frame(address, 31, b"\x00")
        raise KellerError(EXC_FUNCTION, f"F{function} not implemented")


def _to_wire(channel: int, si: float) -> float:
    """SI (Pa, K) -> the channel's wire unit (bar, deg C)."""
    return si / 1e5 if channel <= 2 else si - 273.15


__all__ = ["BROADCAST", "CHANNELS", "EXC_CHANNEL", "EXC_FUNCTION", "EXC_LENGTH", "EXC_NOT_INITIALISED",
           "EXC_PARAMETER", "Identity", "KellerError", "KellerRequest", "KellerRequestDecoder", "KellerResponder",
           "MAX_FRAME", "NEED_MORE", "REQUEST_LENGTHS", "TRANSPARENT", "UNDELIMITED", "WrongLength", "crc16",
           "crc_ok", "encode_exception", "encode_f48", "encode_f66", "encode_f69", "encode_f73", "encode_f74",
           "encode_f95", "encode_frame", "is_keller_function", "keller_request_length", "DIALECT", "KellerDialect",
           "request_from_frame", "COEFF_GAIN_P1", "COEFF_OFFSET_P1", "COEFF_P1_MAX", "COEFF_P1_MIN", "MAX_COEFFICIENT"]
