"""Sound Metrics ARIS: command channel, availability beacon, frame stream, frame header (sans-I/O).

A package by concern: :mod:`.constants`, :mod:`.headers` (frame and file headers, sample
order), :mod:`.settings` (acoustic settings and their checks), :mod:`.commands` (the command
channel), :mod:`.stream` (beacon and frame stream). Every public name is re-exported here, so
``from hilsim.protocols import aris; aris.X`` works for all of them.

The spec is ``protocols/aris.md``; the messages are ``protocols/aris/*.proto``
(generated modules in :mod:`hilsim.protocols.aris_pb`).

* UDP beacon (sonar -> anyone, 1 Hz): protobuf ``Availability``
  (:func:`encode_availability`, every field written even when zero).
* TCP command channel (client -> sonar): each command is a 4-byte
  big-endian length then a serialized ``Command``; :class:`CommandReader`
  turns the byte stream into events and never raises or allocates more than
  ``max_length + 4`` bytes plus what was fed.
* UDP frame stream (sonar -> receiver): each frame as ``FramePart`` datagrams
  of at most 1500 bytes (:func:`split_frame`); :class:`FrameAssembler` puts
  them back together on the client side.
* The 1024-byte frame header (also the .aris file's): :data:`FRAME_HEADER_LAYOUT`,
  :func:`encode_frame_header`, :func:`decode_frame_header`.

Sample order: with ``ReorderedSamples = 1`` the samples are ``sample * numBeams +
beam`` with beam 0 the rightmost (starboard) beam; the simulator's frames have
beam 0 at port, so :func:`samples_to_wire` / :func:`samples_from_wire` reverse
the beams (nothing else needs to know).
"""

from __future__ import annotations

from hilsim.protocols.aris_pb import aris_availability_pb2 as pb_avail
from hilsim.protocols.aris_pb import aris_commands_pb2 as pb_cmd
from hilsim.protocols.aris_pb import aris_frame_stream_pb2 as pb_frame
from hilsim.protocols.codec import NEED_DATA
from hilsim.protocols.aris.commands import (
    BadCommand,
    Command,
    CommandEvent,
    CommandReader,
    Junk,
    Oversize,
    Ping,
    SetAcoustics,
    SetDateTime,
    SetFocus,
    SetFrameStreamReceiver,
    SetSalinity,
    Unsupported,
    command_message,
    encode_command,
    frame_command,
    parse_command,
)
from hilsim.protocols.aris.constants import (
    BEACON_PORT,
    COMMAND_PORT,
    FILE_VERSION,
    FREQ_HIGH,
    FREQ_LOW,
    HEADER_SIZE,
    MAX_COMMAND_LENGTH,
    MAX_DATAGRAM,
    MAX_FRAME_DATA,
    PING,
    SALINITIES,
    SET_ACOUSTICS,
    SET_DATETIME,
    SET_FOCUS,
    SET_FRAMESTREAM_RECEIVER,
    SET_FRAMESTREAM_SETTINGS,
    SET_SALINITY,
    SET_TELEPHOTO,
    SYSTEM_1200,
    SYSTEM_1800,
    SYSTEM_3000,
)
from hilsim.protocols.aris.headers import (
    FILE_HEADER_LAYOUT,
    FILE_OFFSETS,
    FRAME_HEADER_LAYOUT,
    FRAME_OFFSETS,
    HeaderValue,
    decode_file_header,
    decode_frame_header,
    encode_file_header,
    encode_frame_header,
    samples_from_wire,
    samples_to_wire,
)
from hilsim.protocols.aris.settings import (
    AcousticSettings,
    CYCLE_PERIOD_MARGIN,
    CYCLE_PERIOD_RANGE,
    FRAME_RATE_RANGE,
    PINGS_PER_FRAME,
    PULSE_WIDTH_RANGE,
    RECEIVER_GAIN_RANGE,
    SAMPLES_PER_BEAM_RANGE,
    SAMPLE_PERIOD_RANGE,
    SAMPLE_START_DELAY_RANGE,
    SettingsCheck,
    VALID_PING_MODES,
    beams_for_ping_mode,
    check_settings,
)
from hilsim.protocols.aris.stream import (
    AssembledFrame,
    AssemblerEvent,
    Availability,
    BadDatagram,
    DroppedFrame,
    FrameAssembler,
    decode_availability,
    encode_availability,
    split_frame,
)

__all__ = [
    "AcousticSettings",
    "AssembledFrame",
    "AssemblerEvent",
    "Availability",
    "BEACON_PORT",
    "BadCommand",
    "BadDatagram",
    "COMMAND_PORT",
    "CYCLE_PERIOD_MARGIN",
    "CYCLE_PERIOD_RANGE",
    "Command",
    "CommandEvent",
    "CommandReader",
    "DroppedFrame",
    "FILE_HEADER_LAYOUT",
    "FILE_OFFSETS",
    "FILE_VERSION",
    "FRAME_HEADER_LAYOUT",
    "FRAME_OFFSETS",
    "FRAME_RATE_RANGE",
    "FREQ_HIGH",
    "FREQ_LOW",
    "FrameAssembler",
    "HEADER_SIZE",
    "HeaderValue",
    "Junk",
    "MAX_COMMAND_LENGTH",
    "MAX_DATAGRAM",
    "MAX_FRAME_DATA",
    "NEED_DATA",
    "Oversize",
    "PING",
    "PINGS_PER_FRAME",
    "PULSE_WIDTH_RANGE",
    "Ping",
    "RECEIVER_GAIN_RANGE",
    "SALINITIES",
    "SAMPLES_PER_BEAM_RANGE",
    "SAMPLE_PERIOD_RANGE",
    "SAMPLE_START_DELAY_RANGE",
    "SET_ACOUSTICS",
    "SET_DATETIME",
    "SET_FOCUS",
    "SET_FRAMESTREAM_RECEIVER",
    "SET_FRAMESTREAM_SETTINGS",
    "SET_SALINITY",
    "SET_TELEPHOTO",
    "SYSTEM_1200",
    "SYSTEM_1800",
    "SYSTEM_3000",
    "SetAcoustics",
    "SetDateTime",
    "SetFocus",
    "SetFrameStreamReceiver",
    "SetSalinity",
    "SettingsCheck",
    "Unsupported",
    "VALID_PING_MODES",
    "beams_for_ping_mode",
    "check_settings",
    "command_message",
    "decode_availability",
    "decode_file_header",
    "decode_frame_header",
    "encode_availability",
    "encode_command",
    "encode_file_header",
    "encode_frame_header",
    "frame_command",
    "parse_command",
    "pb_avail",
    "pb_cmd",
    "pb_frame",
    "samples_from_wire",
    "samples_to_wire",
    "split_frame",
]
