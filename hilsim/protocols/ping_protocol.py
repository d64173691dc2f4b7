"""Blue Robotics ping-protocol (the Ping1D echosounder and the Ping360 scanning sonar), sans-I/O.

Spec: ``protocols/ping-protocol.md``, from bluerobotics/ping-protocol's message
definitions (``src/definitions/common.json``, ``ping1d.json``, ``ping360.json``). A packet::

    'B' 'R'  payload_length u16  message_id u16  src_device_id u8  dst_device_id u8
    payload (payload_length bytes)  checksum u16

all little-endian; the checksum is the sum of every preceding byte of the packet
(header and payload) modulo 2^16.

The message table :data:`MESSAGES` (id -> :class:`MessageDef`: name, ``struct``
format of the fixed fields, field names, and a variable tail) is the one place
that knows layouts; a new device's messages are new rows (:func:`register`).

:class:`PingDecoder` is incremental: any cut of the byte stream gives the same
events. Events: :class:`Message` (a known id whose payload fits its layout, or a
zero-length payload: the protocol's "legacy request" for that id), and the
bad-input events :class:`~hilsim.protocols.codec.Junk` (bytes skipped looking for
``BR``), :class:`~hilsim.protocols.codec.Oversize` (a length beyond
``max_payload``; the decoder skips the ``B`` and resynchronises),
:class:`BadChecksum`, :class:`UnknownMessage` and :class:`BadPayload` (all
:class:`~hilsim.protocols.codec.BadFrame` carrying ``message_id``, which a
device answers with a NACK). A frame with a bad checksum is consumed whole, as
the device's own byte-by-byte parser does.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any, Final, Mapping, Union

from hilsim.protocols.codec import NEED_DATA, BadFrame, ByteBuffer, Junk, NeedData, Oversize

HEADER: Final = struct.Struct("<2sHHBB")   # 'BR', payload_length, message_id, src, dst
START: Final = b"BR"
HEADER_LEN: Final = 8
CHECKSUM_LEN: Final = 2
MAX_PAYLOAD: Final = 8192   # bytes; Ping1D profiles are ~230 B, Ping360 data frames up to ~1.2 kB


@dataclass(frozen=True)
class MessageDef:
    """One message layout: ``fmt`` is the ``struct`` format (little-endian, no ``<``) of the fixed
    fields named ``fields``; ``tail``: ``None``, ``"chars"`` (the rest of the payload is text, no
    length field: nack, ascii_text) or ``"u16_u8s"`` (a u16 count then that many u8: profile data),
    named ``tail_name``."""

    id: int
    name: str
    fmt: str
    fields: tuple[str, ...]
    tail: str | None = None
    tail_name: str = ""

    @property
    def fixed_size(self) -> int:
        return struct.calcsize("<" + self.fmt)


MESSAGES: dict[int, MessageDef] = {}
NAMES: dict[str, int] = {}


def register(*defs: MessageDef) -> None:
    """Add message layouts to the table (a new device's messages); an id or name defined twice
    with a different layout raises."""
    for d in defs:
        old = MESSAGES.get(d.id)
        if old is not None and old != d:
            raise ValueError(f"ping-protocol id {d.id} already defined as {old.name}")
        if struct.calcsize("<" + d.fmt) and len(d.fields) != len(struct.Struct("<" + d.fmt).unpack(
                bytes(struct.calcsize("<" + d.fmt)))):
            raise ValueError(f"{d.name}: {len(d.fields)} names for format {d.fmt!r}")
        MESSAGES[d.id] = d
        NAMES[d.name] = d.id


M = MessageDef
register(
    # common.json: general
    M(1, "ack", "H", ("acked_id",)),
    M(2, "nack", "H", ("nacked_id",), tail="chars", tail_name="nack_message"),
    M(3, "ascii_text", "", (), tail="chars", tail_name="ascii_message"),
    M(6, "general_request", "H", ("requested_id",)),
    # common.json: get
    M(4, "device_information", "BBBBBB", ("device_type", "device_revision", "firmware_version_major",
                                          "firmware_version_minor", "firmware_version_patch", "reserved")),
    M(5, "protocol_version", "BBBB", ("version_major", "version_minor", "version_patch", "reserved")),
    # common.json: set
    M(100, "set_device_id", "B", ("device_id",)),
    # ping1d.json: set
    M(1000, "ping1d_set_device_id", "B", ("device_id",)),
    M(1001, "set_range", "II", ("scan_start", "scan_length")),
    M(1002, "set_speed_of_sound", "I", ("speed_of_sound",)),
    M(1003, "set_mode_auto", "B", ("mode_auto",)),
    M(1004, "set_ping_interval", "H", ("ping_interval",)),
    M(1005, "set_gain_setting", "B", ("gain_setting",)),
    M(1006, "set_ping_enable", "B", ("ping_enabled",)),
    M(1007, "set_oss_profile_configuration", "HBB", ("number_of_points", "normalization_enabled",
                                                      "enhance_enabled")),
    # ping1d.json: control
    M(1100, "goto_bootloader", "", ()),
    M(1400, "continuous_start", "H", ("id",)),
    M(1401, "continuous_stop", "H", ("id",)),
    # ping1d.json: get
    M(1200, "firmware_version", "BBHH", ("device_type", "device_model", "firmware_version_major",
                                         "firmware_version_minor")),
    M(1201, "device_id", "B", ("device_id",)),
    M(1202, "voltage_5", "H", ("voltage_5",)),
    M(1203, "speed_of_sound", "I", ("speed_of_sound",)),
    M(1204, "range", "II", ("scan_start", "scan_length")),
    M(1205, "mode_auto", "B", ("mode_auto",)),
    M(1206, "ping_interval", "H", ("ping_interval",)),
    M(1207, "gain_setting", "I", ("gain_setting",)),
    M(1208, "transmit_duration", "H", ("transmit_duration",)),
    M(1210, "general_info", "HHHHBB", ("firmware_version_major", "firmware_version_minor", "voltage_5",
                                       "ping_interval", "gain_setting", "mode_auto")),
    M(1211, "distance_simple", "IB", ("distance", "confidence")),
    M(1212, "distance", "IHHIIII", ("distance", "confidence", "transmit_duration", "ping_number",
                                    "scan_start", "scan_length", "gain_setting")),
    M(1213, "processor_temperature", "H", ("processor_temperature",)),
    M(1214, "pcb_temperature", "H", ("pcb_temperature",)),
    M(1215, "ping_enable", "B", ("ping_enabled",)),
    M(1300, "profile", "IHHIIII", ("distance", "confidence", "transmit_duration", "ping_number", "scan_start",
                                   "scan_length", "gain_setting"), tail="u16_u8s", tail_name="profile_data"),
    M(1301, "oss_profile_configuration", "HBB", ("number_of_points", "normalization_enabled",
                                                  "enhance_enabled")),
    # ping360.json (ids and units named in hilsim.protocols.ping360); its set_device_id (2000) is
    # named ping360_set_device_id here, the common one (100) keeping the plain name
    M(2000, "ping360_set_device_id", "BB", ("id", "reserved")),
    M(2300, "device_data", "BBHHHHH", ("mode", "gain_setting", "angle", "transmit_duration", "sample_period",
                                       "transmit_frequency", "number_of_samples"), tail="u16_u8s", tail_name="data"),
    M(2301, "auto_device_data", "BBHHHHHHBBH", ("mode", "gain_setting", "angle", "transmit_duration",
                                                "sample_period", "transmit_frequency", "start_angle", "stop_angle",
                                                "num_steps", "delay", "number_of_samples"),
      tail="u16_u8s", tail_name="data"),
    M(2600, "reset", "BB", ("bootloader", "reserved")),
    M(2601, "transducer", "BBHHHHHBB", ("mode", "gain_setting", "angle", "transmit_duration", "sample_period",
                                        "transmit_frequency", "number_of_samples", "transmit", "reserved")),
    M(2602, "auto_transmit", "BBHHHHHHBB", ("mode", "gain_setting", "transmit_duration", "sample_period",
                                            "transmit_frequency", "number_of_samples", "start_angle", "stop_angle",
                                            "num_steps", "delay")),
    M(2903, "motor_off", "", ()),
)
del M

# the ids a Ping1D answers as "get" messages (a request for one of these is answered with it)
PING1D_GET_IDS: Final = frozenset({4, 5, 1200, 1201, 1202, 1203, 1204, 1205, 1206, 1207, 1208, 1210, 1211, 1212,
                                   1213, 1214, 1215, 1300, 1301})


def checksum(data: bytes) -> int:
    """Sum of ``data`` modulo 2^16."""
    return sum(data) & 0xFFFF


def pack_payload(d: MessageDef, fields: Mapping[str, Any]) -> bytes:
    """The payload of message ``d`` from its field values (KeyError for a missing field)."""
    out = struct.pack("<" + d.fmt, *(fields[n] for n in d.fields)) if d.fmt else b""
    if d.tail == "chars":
        text = fields.get(d.tail_name, b"")
        out += text.encode("ascii", "replace") if isinstance(text, str) else bytes(text)
    elif d.tail == "u16_u8s":
        data = bytes(fields.get(d.tail_name, b""))
        out += struct.pack("<H", len(data)) + data
    return out


def encode_raw(message_id: int, payload: bytes = b"", src: int = 0, dst: int = 0) -> bytes:
    """A whole packet for any id and payload (0 <= len < 65536)."""
    head = HEADER.pack(START, len(payload), message_id & 0xFFFF, src & 0xFF, dst & 0xFF) + payload
    return head + struct.pack("<H", checksum(head))


def encode(message: int | str, fields: Mapping[str, Any] | None = None, src: int = 0, dst: int = 0) -> bytes:
    """A packet of a known message (id or name) from its field values; ``fields`` None: a zero-length
    payload (the protocol's request for that message)."""
    mid = message if isinstance(message, int) else NAMES[message]
    payload = b"" if fields is None else pack_payload(MESSAGES[mid], fields)
    return encode_raw(mid, payload, src, dst)


def unpack_payload(d: MessageDef, payload: bytes) -> dict[str, Any] | str:
    """Field values of ``payload`` for layout ``d``, or why it does not fit."""
    n = d.fixed_size
    if len(payload) < n or (d.tail is None and len(payload) != n):
        return f"{d.name}: payload of {len(payload)} bytes, layout needs {n}"
    out: dict[str, Any] = dict(zip(d.fields, struct.unpack_from("<" + d.fmt, payload))) if d.fmt else {}
    rest = payload[n:]
    if d.tail == "chars":
        out[d.tail_name] = rest.split(b"\0", 1)[0].decode("ascii", "replace")
    elif d.tail == "u16_u8s":
        if len(rest) < 2:
            return f"{d.name}: no profile length"
        count = struct.unpack_from("<H", rest)[0]
        if len(rest) != 2 + count:
            return f"{d.name}: profile length {count} but {len(rest) - 2} bytes"
        out[d.tail_name] = bytes(rest[2:])
    return out


@dataclass(frozen=True)
class Message:
    """A decoded packet of a known id. ``fields``: the field values (empty for a request, i.e. a
    zero-length payload of a message that has fields: ``is_request``)."""

    message_id: int
    name: str
    src: int
    dst: int
    fields: dict[str, Any] = field(default_factory=dict)
    payload: bytes = b""

    @property
    def is_request(self) -> bool:
        """A request for a message: ``general_request`` (id 6), or an empty packet of an id whose
        layout has fields (the protocol's legacy request)."""
        d = MESSAGES[self.message_id]
        return self.message_id == 6 or (not self.payload and (bool(d.fields) or d.tail is not None))


@dataclass(frozen=True)
class BadChecksum(BadFrame):
    """A whole packet whose checksum is wrong."""

    message_id: int = 0


@dataclass(frozen=True)
class UnknownMessage(BadFrame):
    """A packet with a good checksum and an id not in :data:`MESSAGES`."""

    message_id: int = 0


@dataclass(frozen=True)
class BadPayload(BadFrame):
    """A packet of a known id whose payload does not fit the layout."""

    message_id: int = 0


Event = Union[Message, Junk, Oversize, BadChecksum, UnknownMessage, BadPayload]


class PingDecoder(ByteBuffer):
    """Incremental ping-protocol decoder (sans-I/O; see the module docstring).

    Memory: at most ``HEADER_LEN + max_payload + CHECKSUM_LEN`` bytes plus the last chunk."""

    def __init__(self, max_payload: int = MAX_PAYLOAD) -> None:
        super().__init__()
        self.max_payload = int(max_payload)
        self.messages = 0
        self.errors = 0

    def _skip(self, n: int) -> Junk:
        self._pos += n
        self.errors += 1
        return Junk("bytes before 'BR'", n)

    def next_event(self) -> Union[Event, NeedData]:
        buf, pos = self._buf, self._pos
        avail = len(buf) - pos
        if avail == 0:
            return NEED_DATA
        start = buf.find(START, pos)
        if start < 0:
            # keep a trailing 'B' that may begin the next packet
            keep = 1 if buf[-1] == 0x42 else 0
            if avail - keep > 0:
                return self._skip(avail - keep)
            return NEED_DATA
        if start > pos:
            return self._skip(start - pos)
        if avail < HEADER_LEN:
            return NEED_DATA
        length, mid, src, dst = struct.unpack_from("<HHBB", buf, pos + 2)
        if length > self.max_payload:
            self._pos += 1
            self.errors += 1
            return Oversize(f"payload length {length} > {self.max_payload}", length)
        total = HEADER_LEN + length + CHECKSUM_LEN
        if avail < total:
            return NEED_DATA
        frame = bytes(buf[pos:pos + total])
        self._pos += total
        want = struct.unpack_from("<H", frame, total - CHECKSUM_LEN)[0]
        if checksum(frame[:-CHECKSUM_LEN]) != want:
            self.errors += 1
            return BadChecksum(f"checksum {checksum(frame[:-2]):04x} != {want:04x}", frame[:64], mid)
        d = MESSAGES.get(mid)
        if d is None:
            self.errors += 1
            return UnknownMessage(f"unknown message id {mid}", frame[:64], mid)
        payload = frame[HEADER_LEN:HEADER_LEN + length]
        if not payload:
            self.messages += 1
            return Message(mid, d.name, src, dst, {}, b"")
        fields = unpack_payload(d, payload)
        if isinstance(fields, str):
            self.errors += 1
            return BadPayload(fields, frame[:64], mid)
        self.messages += 1
        return Message(mid, d.name, src, dst, fields, payload)


__all__ = ["BadChecksum", "BadPayload", "MAX_PAYLOAD", "MESSAGES", "Message", "MessageDef", "NAMES",
           "PING1D_GET_IDS", "PingDecoder", "UnknownMessage", "checksum", "encode", "encode_raw", "pack_payload",
           "register", "unpack_payload"]
