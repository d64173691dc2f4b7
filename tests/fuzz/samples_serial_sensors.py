"""Fuzz samples of the serial dialects of the depth and IMU sensors (KELLER bus requests,
WitMotion UART commands and packets), built with the codecs' own encoders and the KELLER
document's frames; kept apart from ``samples.py`` so the entries stay one import."""

from __future__ import annotations

import struct

from hilsim.protocols import keller_bus as kb
from hilsim.protocols import witmotion_uart as wu
from tests.fuzz.samples import Sample, equals, filler


def keller_samples() -> list[Sample]:
    return [
        Sample(bytes([250, 73, 1, 161, 167]), equals(kb.KellerRequest(250, 73, b"\x01")), "F73 P1 (the manual's frame)"),
        Sample(bytes([250, 48, 4, 67]), equals(kb.KellerRequest(250, 48)), "F48 (the manual's frame)"),
        Sample(kb.encode_frame(1, 95, b"\x00" + struct.pack(">f", 1.5)),
               equals(kb.KellerRequest(1, 95, b"\x00" + struct.pack(">f", 1.5))), "F95 set zero with a setpoint"),
        Sample(kb.encode_frame(7, 66, b"\x09"), equals(kb.KellerRequest(7, 66, b"\x09")), "F66 new address"),
    ]


def keller_oversize() -> list[tuple[bytes, bytes]]:
    # no length field: a F101 head (the longest request) then bytes that never make a frame
    return [(bytes([1, 101]), filler())]


def witmotion_command_samples() -> list[Sample]:
    return [
        Sample(wu.encode_command(wu.KEY, wu.KEY_UNLOCK), equals(wu.Command(wu.KEY, wu.KEY_UNLOCK)), "unlock"),
        Sample(wu.encode_command(wu.RRATE, 0x09), equals(wu.Command(wu.RRATE, 0x09)), "rate 100 Hz"),
        Sample(wu.encode_command(wu.RSW, 0x0208), equals(wu.Command(wu.RSW, 0x0208)), "content angles+quaternion"),
    ]


def witmotion_packet_samples() -> list[Sample]:
    return [
        Sample(wu.encode_packet(wu.ANGLE, [1820, -910, 16384, 0x1234]),
               equals(wu.Packet(wu.ANGLE, (1820, -910, 16384, 0x1234))), "angles"),
        Sample(wu.encode_packet(wu.ACC, [0, 0, 2048, 2512]), equals(wu.Packet(wu.ACC, (0, 0, 2048, 2512))),
               "acceleration"),
    ]


def head_oversize(head: bytes) -> list[tuple[bytes, bytes]]:
    return [(head, filler())]
