"""Valid messages for every fuzz target, built with the codecs' own encoders (and the reference's
known vectors), each with a predicate recognising its event; and heads claiming huge lengths."""

from __future__ import annotations

import struct
from dataclasses import dataclass, replace
from functools import cache
from typing import Any, Callable

import numpy as np
from pymodbus.framer import FramerRTU

from hilsim.protocols import aris, ddf, ddf_commands, dronecan, oculus, slcan, socketcand, vesc_can, vesc_uart, vrcsr
from hilsim.protocols import modbus as mb
from hilsim.protocols.can import CanFrame
from tests.fuzz.adapters import KELLER_TRANSPARENT, Reply
from tests.fuzz.links import CAN_EFF_FLAG, CAN_RECORD, Datagrams, can_record, datagram

Predicate = Callable[[Any], bool]


@dataclass(frozen=True)
class Sample:
    """A valid message on the wire and how to recognise its event."""

    wire: bytes
    expect: Predicate
    label: str


def equals(expected: object) -> Predicate:
    return lambda ev: bool(ev == expected)


def item_equals(index: int, expected: object) -> Predicate:
    """For adapters whose events are tuples (raw packet, decoded message)."""
    return lambda ev: bool(ev[index] == expected)


@cache
def filler() -> bytes:
    """4 KiB of fixed pseudo-random bytes: what keeps arriving after a huge length claim."""
    return np.random.default_rng(2024).integers(0, 256, 4096, dtype=np.uint8).tobytes()


def text_oversize(head: bytes, byte: bytes) -> Callable[[], list[tuple[bytes, bytes]]]:
    """A message that never ends (no line end, no ``>``)."""
    return lambda: [(head, byte * 4096)]


DDF_BEAMS, DDF_SAMPLES = 4, 8  # small frames, so random bytes make many of them


# ----------------------------------------------------------------- DDF stream (client side)


@cache
def ddf_prefix() -> bytes:
    header = ddf.FileHeader(numbeams=DDF_BEAMS, samplesperchannel=DDF_SAMPLES, idstring="fuzz")
    return ddf.encode_file_header(header)


@cache
def ddf_samples() -> list[Sample]:
    out = []
    rng = np.random.default_rng(7)
    for n in range(3):
        header = ddf.FrameHeader(framenumber=n, time=1.7e9 + n / 10, replies=b"OK PING\n" if n == 1 else b"")
        image = rng.integers(0, 256, (DDF_SAMPLES, DDF_BEAMS), dtype=np.uint8)
        wire = ddf.encode_frame(header, image)
        expected = ddf.FrameEvent(header, image)
        out.append(Sample(wire, equals(expected), f"frame {n}"))
    return out


def ddf_oversize() -> list[tuple[bytes, bytes]]:
    def header(beams: int, samples: int) -> bytes:
        raw = bytearray(ddf_prefix())
        struct.pack_into("<i", raw, 16, beams)     # numbeams
        struct.pack_into("<i", raw, 24, samples)   # samplesperchannel
        return bytes(raw)
    return [(header(0x7FFFFFFF, 0x7FFFFFFF), b"\0" * 4096), (header(-1, 1), b"\0" * 4096),
            (header(ddf.MAX_NUMBEAMS + 1, 1), b"\0" * 4096)]


# ----------------------------------------------------------------- DDF command lines (server side)


@cache
def ddf_command_samples() -> list[Sample]:
    cmds: list[ddf_commands.Command] = [ddf_commands.SetRate(12.5), ddf_commands.SetWindow(2, 2),
                                        ddf_commands.SetGain(20), ddf_commands.Ping()]
    out = [Sample(ddf_commands.encode_command(c), equals(c), ddf_commands.command_text(c)) for c in cmds]
    out.append(Sample(b"\tgain 7\r\n", equals(ddf_commands.SetGain(7)), "lower case, tab, CRLF"))
    return out


# ----------------------------------------------------------------- Oculus (sonar side: client -> sonar)


@cache
def oculus_samples() -> list[Sample]:
    out = []
    for f in (oculus.Fire(range=10.0, gain=50.0, version=2, ext_flags=0x200, src_device_id=3),
              oculus.Fire(master_mode=oculus.MODE_LF, ping_rate=oculus.PING_RATE_HIGH, flags=0x0D, range=35.5,
                          gain=80.0, speed_of_sound=1480.0, salinity=35.0, version=1)):
        out.append(Sample(oculus.encode_fire(f), equals(f), f"fire v{f.version}"))
    fire = oculus.Fire(flags=oculus.FLAG_RANGE_METRES | oculus.FLAG_SIMPLE | oculus.FLAG_SEND_GAIN, version=2)
    image = np.arange(3 * 4, dtype=np.uint8).reshape(3, 4)
    ping = oculus.PingResult(fire=fire, image=image, bearings=np.array([-300, -100, 100, 300], np.int16),
                             range_resolution=0.02, gains=np.ones(3, np.float32), ping_id=42)
    offset, size = oculus.PING_V2_SIZE + 2 * 4, 3 * (4 + 4)  # bearings table; rows of a gain + 4 samples
    decoded = replace(ping, image_offset=offset, image_size=size, message_size=offset + size)
    out.append(Sample(oculus.encode_ping_result(ping), equals(decoded), "simple ping result v2"))
    dummy = oculus.Header(oculus.MSG_DUMMY, 0)
    out.append(Sample(oculus.encode_header(dummy), equals(oculus.OtherMessage(dummy, b"")), "dummy keep-alive"))
    return out


def oculus_oversize() -> list[tuple[bytes, bytes]]:
    fill = filler()
    return [(oculus.encode_header(oculus.Header(oculus.MSG_FIRE, 0xFFFFFFFF)), fill),
            (oculus.encode_header(oculus.Header(oculus.MSG_SIMPLE_PING_RESULT, oculus.MAX_SERVER_PAYLOAD + 1)), fill),
            (oculus.encode_header(oculus.Header(oculus.MSG_DUMMY, oculus.MAX_SERVER_PAYLOAD)), fill)]


# ----------------------------------------------------------------- ARIS command channel (sonar side)


@cache
def aris_samples() -> list[Sample]:
    cmds: list[aris.Command] = [
        aris.Ping(), aris.SetSalinity(15), aris.SetDateTime("2014-Jan-31 23:58:15"),
        aris.SetFrameStreamReceiver(56888, "127.0.0.1"), aris.SetFrameStreamReceiver(700),
        aris.SetAcoustics(aris.AcousticSettings(cookie=7)), aris.SetFocus(2.5, None), aris.SetFocus(None, 1200)]
    return [Sample(aris.encode_command(c), equals(c), type(c).__name__) for c in cmds]


def aris_oversize() -> list[tuple[bytes, bytes]]:
    fill = filler()
    return [(b"\xff\xff\xff\xff", fill), (struct.pack(">I", aris.MAX_COMMAND_LENGTH + 1), fill),
            (struct.pack(">I", aris.MAX_COMMAND_LENGTH), fill)]


# ----------------------------------------------------------------- ARIS frame stream (client side, UDP)


@cache
def assembler_samples() -> list[Sample]:
    out = []
    for index, size in ((1, 3000), (2, 10), (5, 0), (9, 1490)):
        data = bytes((i * 7 + index) & 0xFF for i in range(size))
        header = aris.encode_frame_header({"FrameIndex": index, "SamplesPerBeam": 100, "PingMode": 3})
        parts = aris.split_frame(index, header, data)
        wire = b"".join(datagram(p) for p in parts)
        frame = aris.AssembledFrame(index, header.rstrip(b"\0").ljust(aris.HEADER_SIZE, b"\0"), data)
        out.append(Sample(wire, equals(frame), f"frame {index} ({len(parts)} parts)"))
    return out


def _split_datagrams(wire: bytes) -> list[bytes]:
    return Datagrams().datagrams(wire)


def assembler_cut(wire: bytes, k: int) -> bytes:
    """Parts lost: keep the datagrams that start before byte k (at least the first is dropped or kept whole)."""
    parts = _split_datagrams(wire)
    kept: list[bytes] = []
    pos = 0
    for p in parts:
        if pos >= k or len(kept) == len(parts) - 1:
            break
        kept.append(p)
        pos += 2 + len(p)
    return b"".join(datagram(p) for p in kept)


def assembler_oversize() -> list[tuple[bytes, bytes]]:
    def part(**kw: int) -> bytes:
        m = aris.pb_frame.FramePart()
        m.frame_index = kw.get("index", 3)
        m.total_data_size = kw["total"]
        m.data = b"\x01\x02"
        m.data_offset = kw.get("offset", 0)
        return datagram(m.SerializeToString())
    fill = datagram(b"\x08\x03\x10\xff\xff\xff\xff\x07\x22\x01\x00") * 256  # total 2**31-1, garbage data
    return [(part(total=2**31 - 1), fill), (part(total=-1), fill), (part(total=100, offset=2**31 - 2), fill),
            (part(total=aris.MAX_FRAME_DATA * 2 + 1), fill)]


# ----------------------------------------------------------------- socketcand (server side)


@cache
def socketcand_samples() -> list[Sample]:
    frames = [CanFrame(0x301, bytes([0, 0, 0x13, 0x88]), True), CanFrame(0x123, b"", False),
              CanFrame(0x7FF, bytes(range(8)), False)]
    out = [Sample(socketcand.format_send(f), equals(socketcand.SendFrame(f)), repr(f)) for f in frames]
    assert out[0].wire == b"< send 00000301 4 0 0 13 88 >"  # reference/thruster-protocols.md
    return out


# ----------------------------------------------------------------- slcan (adapter side)


@cache
def slcan_samples() -> list[Sample]:
    out = []
    for f, lower in ((CanFrame(0x123, b"\x11\x22", False), False), (CanFrame(0x1ABCDEF, bytes(range(8))), False),
                     (CanFrame(0x7FF, b"", False, True, 4), False), (CanFrame(0x0A0B0C0D, b"\xfe"), True)):
        out.append(Sample(slcan.format_frame(f, lowercase=lower), equals(slcan.Transmit(f)),
                          repr(f) + (" lower case" if lower else "")))
    return out


# ----------------------------------------------------------------- VESC UART (ESC side)


@cache
def vesc_uart_samples() -> list[Sample]:
    V = vesc_uart
    cmds: list[V.Command] = [V.SetDuty(0.5), V.SetCurrent(-12.5), V.SetCurrentBrake(3.0), V.SetRpm(3000.0),
                             V.GetValues(), V.GetValues(0x3FFFFF), V.GetFwVersion(), V.Alive(),
                             V.ForwardCan(5, V.SetCurrent(1.0))]
    out = [Sample(V.frame(V.encode_command(c)), item_equals(1, c), type(c).__name__) for c in cmds]
    long_payload = V.encode_values(V.Values(temp_fet=31.5, rpm=1200.0)) + bytes(300)
    out.append(Sample(V.frame(long_payload), item_equals(0, long_payload), "long form, 3xx bytes"))
    return out


def vesc_uart_seeds() -> list[bytes]:
    """Packets whose payload is too short for its command, an unknown command, nested FORWARD_CAN."""
    V = vesc_uart
    return [V.frame(p) for p in (b"\x05\x00", b"\x32\x01", b"\x22", b"\x22\x05\x22\x05\x04", b"\xfe")]


# ----------------------------------------------------------------- VRCSR (thruster side)


@cache
def vrcsr_samples() -> list[Sample]:
    out = []
    for powers, node in (([0.5, -0.25, 0.0, 1.0], 3), ([], 1), ([-1.0] * 63, 9)):
        wire = vrcsr.propulsion_request(powers, reply_node_id=node)
        cmd = vrcsr.PropulsionCommand(node, tuple(powers))
        out.append(Sample(wire, item_equals(1, cmd), f"propulsion x{len(powers)}"))
    pkt = vrcsr.Packet(0x81, vrcsr.FLAG_NONE, 0x10, b"")
    out.append(Sample(pkt.encode(), item_equals(0, pkt), "empty payload"))
    return out


def vrcsr_oversize() -> list[tuple[bytes, bytes]]:
    header = vrcsr.SYNC_REQUEST + bytes([0x81, 2, 0xF0, 255])
    return [(header + struct.pack("<I", vrcsr.crc32(header)), filler())]


# ----------------------------------------------------------------- VESC CAN (ESC side)


def close_to(expected: object) -> Predicate:
    """Same type and fields, floats within 1e-6 (the DBC's scaling)."""
    def check(ev: Any) -> bool:
        if type(ev) is not type(expected):
            return False
        for k, v in vars(expected).items():
            w = getattr(ev, k)
            if isinstance(v, float) and abs(w - v) > 1e-6 * max(1.0, abs(v)) or not isinstance(v, float) and w != v:
                return False
        return True
    return check


@cache
def vesc_can_samples() -> list[Sample]:
    V = vesc_can
    msgs: list[V.VescMessage] = [
        V.VescCommand(23, "SET_CURRENT", 51.0), V.VescCommand(1, "SET_DUTY", -0.25),
        V.VescCommand(255, "SET_RPM", 12000.0), V.VescCommand(0, "SET_CURRENT_BRAKE", 4.5),
        V.VescCommand(7, "SET_CURRENT_REL", 0.5), V.Status1(3, 1500.0, 2.5, 0.25),
        V.Status4(3, 30.5, 40.0, 1.5, 90.0), V.Status5(3, 123456, 16.8)]
    out = []
    for m in msgs:
        frame = V.encode(m)
        out.append(Sample(can_record(frame), close_to(m), repr(m)))
    known = V.encode(msgs[0])  # reference/thruster-protocols.md: 51 A to ID 23 = ID 0x0117, data 00 00 C7 38
    assert (known.arbitration_id, known.data) == (0x0117, bytes.fromhex("0000C738"))
    return out


def vesc_can_oversize() -> list[tuple[bytes, bytes]]:
    bad_len = CAN_RECORD.pack(CAN_EFF_FLAG | 0x0117, 15, 0, bytes(8))  # DLC 15: no length field beyond it
    return [(bad_len, filler())]


# ----------------------------------------------------------------- DroneCAN (ESC side)


def transfer_of(message: dronecan.Message, node: int, tid: int) -> Predicate:
    return lambda ev: bool(ev[0].source_node == node and ev[0].transfer_id == tid and ev[1] == message)


@cache
def dronecan_samples() -> list[Sample]:
    D = dronecan
    msgs: list[tuple[D.Message, int, int]] = [
        (D.RawCommand((8191, -8192, 0, 4000)), 10, 0), (D.RawCommand(tuple(range(-10, 10))), 11, 31),
        (D.EscStatus(3, 16.5, 2.25, 300.0, -1500, 40, 2), 20, 5), (D.NodeStatus(12345, mode=1), 20, 6),
        (D.RawCommand(()), 12, 1)]
    out = []
    for m, node, tid in msgs:
        frames = D.encode_message(m, source_node=node, transfer_id=tid)
        wire = b"".join(can_record(f) for f in frames)
        out.append(Sample(wire, transfer_of(m, node, tid), f"{type(m).__name__} ({len(frames)} frames)"))
    return out


def dronecan_seeds() -> list[bytes]:
    """Frames the receiver ignores or rejects: a service frame, an anonymous one, a bad transfer CRC,
    a transfer interrupted by 2.4 s of silence, a toggle error."""
    D = dronecan
    frames = D.encode_message(D.RawCommand(tuple(range(8))), source_node=7, transfer_id=3)
    bad_crc = [CanFrame(frames[0].arbitration_id, bytes([frames[0].data[0] ^ 1]) + frames[0].data[1:])] + frames[1:]
    paused = [can_record(frames[0])] + [CAN_RECORD.pack(CAN_EFF_FLAG | f.arbitration_id, len(f.data), 120,
                                                        f.data.ljust(8, b"\0")) for f in frames[1:]]
    toggled = frames[:1] + frames[2:]
    return [can_record(CanFrame((16 << 24) | (55 << 16) | 0x8000 | 0x80 | (3 << 8) | 7, b"\xc0"))
            + can_record(CanFrame(D.message_id(16, D.RAW_COMMAND_DTID, 1) & ~0x7F, b"\x00\xc0")),
            b"".join(map(can_record, bad_crc)), b"".join(paused), b"".join(map(can_record, toggled))]


def dronecan_oversize() -> list[tuple[bytes, bytes]]:
    """A transfer that never ends (start, then middle frames forever) and one per source node."""
    ident = dronecan.message_id(16, dronecan.RAW_COMMAND_DTID, 42)
    start = can_record(CanFrame(ident, bytes(7) + b"\x80"))
    middles = b"".join(can_record(CanFrame(ident, bytes(7) + bytes([(t << 5)]))) for t in (1, 0) * 128)
    many = b"".join(can_record(CanFrame(dronecan.message_id(16, dronecan.ESC_STATUS_DTID, node), bytes(7) + b"\x80"))
                    for node in range(1, 128))
    return [(start, middles), (b"", many)]


# ----------------------------------------------------------------- Modbus (device side)


def pdus() -> list[bytes]:
    return [struct.pack(">BHH", 3, 0x0002, 2), struct.pack(">BHH", 4, 0x0100, 4),
            struct.pack(">BHH", 6, 0xFF00, 0), struct.pack(">BHHBH", 16, 0x020D, 1, 2, 1),
            struct.pack(">BHH", 3, 0x0C00, 2), bytes([0x2B, 0x0E, 0x01, 0x00])]


def mbap(pdu: bytes, unit: int, tid: int) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def tcp_reply(tid: int, fc: int) -> Predicate:
    """A reply with the request's transaction id and function (or its exception)."""
    return lambda ev: isinstance(ev, Reply) and ev.data[:2] == tid.to_bytes(2, "big") and ev.data[7] & 0x7F == fc


@cache
def tcp_samples() -> list[Sample]:
    out = []
    for tid, pdu in enumerate(pdus(), 1):
        unit = KELLER_TRANSPARENT if tid % 2 else 1
        out.append(Sample(mbap(pdu, unit, tid), tcp_reply(tid, pdu[0]), f"fc {pdu[0]} tid {tid}"))
    return out


def tcp_oversize() -> list[tuple[bytes, bytes]]:
    return [(struct.pack(">HHHB", 1, 0, 0xFFFF, 1), filler()),
            (struct.pack(">HHHB", 1, 0, mb.MAX_TCP_LENGTH, 1) + bytes([16, 0, 0, 0, 0x7F, 0xFE]), filler())]


def rtu_frame(pdu: bytes, unit: int) -> bytes:
    f = bytes([unit]) + pdu
    return f + FramerRTU.compute_CRC(f).to_bytes(2, "big")


def rtu_reply(unit: int, fc: int) -> Predicate:
    return lambda ev: isinstance(ev, Reply) and ev.data[0] == unit and ev.data[1] & 0x7F == fc


@cache
def rtu_samples() -> list[Sample]:
    out = []
    for pdu in pdus()[:5]:  # the last one (fc 43) is answered only after silence
        out.append(Sample(rtu_frame(pdu, KELLER_TRANSPARENT), rtu_reply(KELLER_TRANSPARENT, pdu[0]), f"fc {pdu[0]}"))
    return out


def rtu_seeds() -> list[bytes]:
    """Frames answered with nothing: a broadcast write, another device's read, a bad CRC; and a
    function the length rules cannot delimit (answered after silence)."""
    read = struct.pack(">BHH", 3, 0x0002, 2)
    bad = bytearray(rtu_frame(read, 1))
    bad[-1] ^= 0xFF
    return [rtu_frame(struct.pack(">BHH", 6, 0xFF00, 0), 0), rtu_frame(read, 2), bytes(bad),
            rtu_frame(bytes([0x41, 1, 2, 3]), 1), rtu_frame(struct.pack(">BHH", 1, 0, 1), 1)]


def rtu_oversize() -> list[tuple[bytes, bytes]]:
    head = bytes([1, 16, 0, 0, 0, 0x7F, 0xFE])  # write 127 registers, 254 bytes
    return [(head, filler()), (b"", b"\x01" * 4096)]
