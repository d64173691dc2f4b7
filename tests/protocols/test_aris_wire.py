"""The ARIS wire as the vendor's files define it (issue #20, parts 1 and 2).

1. A strict decoder: :data:`VENDOR` is the table (message, field number) -> (wire type, kind),
   written from Sound Metrics' published ``availability.proto``, ``commands.proto`` and
   ``frame_stream.proto`` (ARIS Integration SDK, ``common/protobuf/``; the 2017 proto2 and the
   2018+ proto3 files give the same table), not from our .proto files. It walks every beacon,
   command and FramePart our encoders emit, raw protobuf wire parsing recursing into nested
   messages, and fails on a wire-type mismatch or an unknown field, as protobuf-c does.
2. Commands from proto3 clients (defaults omitted, hand-built bytes) and from proto2 clients
   (everything set) read the same, for every command type.
"""

from __future__ import annotations

import asyncio
import socket
import struct
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hilsim.protocols import aris as ar
from hilsim.protocols.aris_file import ArisReader

ROOT = Path(__file__).resolve().parents[2]


def _udp() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(30.0)
    return s

VARINT, I64, LEN, I32 = 0, 1, 2, 5

# (message, field number) -> (wire type, kind): kind is "varint", "float", "string", "bytes" or the
# nested message's name. From the vendor's files: uint32/int32/bool/enum -> varint, float -> 32-bit,
# string/bytes/message -> length-delimited (repeated strings: one record per element).
VENDOR: dict[tuple[str, int], tuple[int, str]] = {
    # availability.proto, message Availability
    **{("Availability", n): (VARINT, "varint") for n in (1, 2, 4, 6, 7, 9, 11, 12)},
    ("Availability", 3): (LEN, "SoftwareVersion"),
    ("Availability", 5): (LEN, "Capabilities"),
    ("Availability", 8): (I32, "float"),
    ("Availability", 10): (I32, "float"),
    ("Availability", 13): (LEN, "SystemVariants"),
    **{("SoftwareVersion", n): (VARINT, "varint") for n in (1, 2, 3)},
    ("Capabilities", 1): (LEN, "string"),
    ("SystemVariants", 1): (LEN, "string"),
    # commands.proto, message Command and its nested messages
    ("Command", 1): (VARINT, "varint"),
    **{("Command", n): (LEN, name) for n, name in enumerate((
        "SetDateTime", "SetFrameStreamReceiver", "SetFrameStreamSettings", "SetAcousticSettings", "SetSalinity",
        "SetTelephotoLens", "SetFocusPosition", "ForceFocus", "HomeFocus", "SetRotatorMount", "SetRotatorVelocity",
        "SetRotatorAcceleration", "SetRotatorPosition", "StopRotator", "Ping", "SetSyslogReceiver", "PowerDown",
        "Reserved1"), start=2)},
    ("SetDateTime", 1): (LEN, "string"),
    ("SetFrameStreamReceiver", 1): (VARINT, "varint"),
    ("SetFrameStreamReceiver", 2): (LEN, "string"),
    ("SetFrameStreamSettings", 1): (LEN, "SetInterpacketDelay"),
    ("SetFrameStreamSettings", 2): (VARINT, "varint"),
    ("SetInterpacketDelay", 1): (VARINT, "varint"),
    ("SetInterpacketDelay", 2): (VARINT, "varint"),
    **{("SetAcousticSettings", n): (VARINT, "varint") for n in (1, 3, 4, 5, 6, 7, 8, 9, 10, 11)},
    ("SetAcousticSettings", 2): (I32, "float"),
    ("SetAcousticSettings", 12): (I32, "float"),
    ("SetSalinity", 1): (VARINT, "varint"),
    ("SetTelephotoLens", 1): (VARINT, "varint"),
    ("SetFocusPosition", 1): (VARINT, "varint"),
    ("SetFocusPosition", 2): (I32, "float"),
    ("ForceFocus", 1): (VARINT, "varint"),
    ("SetRotatorMount", 1): (VARINT, "varint"),
    **{(m, 1): (VARINT, "varint") for m in ("SetRotatorVelocity", "SetRotatorAcceleration", "SetRotatorPosition",
                                            "StopRotator")},
    **{(m, 2): (I32, "float") for m in ("SetRotatorVelocity", "SetRotatorAcceleration", "SetRotatorPosition")},
    ("SetSyslogReceiver", 1): (LEN, "string"),
    # frame_stream.proto
    **{("FramePart", n): (VARINT, "varint") for n in (1, 2, 5, 6)},
    ("FramePart", 3): (LEN, "bytes"),
    ("FramePart", 4): (LEN, "bytes"),
    ("FramePartAck", 1): (VARINT, "varint"),
    ("FramePartAck", 2): (VARINT, "varint"),
}


def _varint(b: bytes, i: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        if i >= len(b) or shift > 63:
            raise ValueError(f"varint runs past the end at {i}")
        byte = b[i]
        value |= (byte & 0x7F) << shift
        i, shift = i + 1, shift + 7
        if not byte & 0x80:
            return value, i


def strict_decode(message: str, b: bytes) -> list[tuple[int, object]]:
    """(field number, value) in wire order; nested messages decoded the same way. ValueError on a
    field the vendor's message lacks, a wire type other than the vendor's, bad framing or a string
    that is not UTF-8."""
    out: list[tuple[int, object]] = []
    i = 0
    while i < len(b):
        key, i = _varint(b, i)
        number, wire = key >> 3, key & 7
        if (message, number) not in VENDOR:
            raise ValueError(f"{message}: unknown field {number} (wire type {wire})")
        want, kind = VENDOR[(message, number)]
        if wire != want:
            raise ValueError(f"{message}.{number}: wire type {wire}, the vendor's is {want}")
        if wire == VARINT:
            value, i = _varint(b, i)
            out.append((number, value))
        elif wire == I32:
            if i + 4 > len(b):
                raise ValueError(f"{message}.{number}: 32-bit value runs past the end")
            out.append((number, struct.unpack_from("<f", b, i)[0]))
            i += 4
        else:
            n, i = _varint(b, i)
            if i + n > len(b):
                raise ValueError(f"{message}.{number}: {n} bytes run past the end")
            raw, i = b[i:i + n], i + n
            if kind == "string":
                out.append((number, raw.decode("utf-8")))
            elif kind == "bytes":
                out.append((number, raw))
            else:
                out.append((number, strict_decode(kind, raw)))
    return out


def test_the_strict_decoder_refuses_what_protobuf_c_refuses() -> None:
    """The old beacon (field 13 as a varint, 68 00) and an unknown field are refused."""
    old = bytes([0x08, 0, 0x10, 0, 0x1A, 6, 0x08, 0, 0x10, 0, 0x18, 0, 0x20, 0, 0x68, 0])
    with pytest.raises(ValueError, match="Availability.13: wire type 0"):
        strict_decode("Availability", old)
    with pytest.raises(ValueError, match="unknown field 20"):
        strict_decode("Command", bytes([0x08, 14, 0xA0, 0x01, 0]))
    assert strict_decode("Availability", old[:-2] + b"\x6a\x00")[-1] == (13, [])


@pytest.mark.parametrize("kw", [{}, {"connection_state": 1}, {"serial_number": 0, "system_type": 2},
                                {"system_variants": ("DF", "VG")}, {"software_version": (2, 8, 4107)}])
def test_every_beacon_passes_the_strict_decoder(kw: dict) -> None:
    a = ar.Availability(**{"serial_number": 1098, **kw})
    fields = strict_decode("Availability", ar.encode_availability(a))
    assert [n for n, _ in fields] == [1, 2, 3, 4, 13]
    assert dict(fields)[13] == [(1, v) for v in a.system_variants]
    assert dict(fields)[3] == [(1, a.software_version[0]), (2, a.software_version[1]), (3, a.software_version[2])]


COMMANDS = [ar.SetDateTime("2026-Nov-24 11:01:02"), ar.SetFrameStreamReceiver(5000),
            ar.SetFrameStreamReceiver(5001, "127.0.0.2"), ar.SetAcoustics(ar.AcousticSettings(cookie=3)),
            ar.SetAcoustics(ar.AcousticSettings(cookie=0, frame_rate=0.0, enable_transmit=False, frequency=0)),
            ar.SetSalinity(0), ar.SetSalinity(35), ar.SetFocus(2.5), ar.SetFocus(None, 400), ar.SetFocus(),
            ar.Ping()]


@pytest.mark.parametrize("cmd", COMMANDS, ids=repr)
def test_every_command_we_encode_passes_the_strict_decoder(cmd: ar.Command) -> None:
    wire = ar.encode_command(cmd)
    assert struct.unpack(">I", wire[:4])[0] == len(wire) - 4
    fields = strict_decode("Command", wire[4:])
    assert fields[0][0] == 1 and len(fields) == 2  # type, then the command's one message


def test_every_frame_part_passes_the_strict_decoder() -> None:
    header = ar.encode_frame_header({"FrameIndex": 4, "PingMode": 3, "SamplesPerBeam": 600, "ReorderedSamples": 1})
    samples = (np.arange(96 * 600) % 253).astype(np.uint8).tobytes()
    data = bytearray(len(samples))
    for k, part in enumerate(ar.split_frame(5, header, samples)):
        f = dict(strict_decode("FramePart", part))
        assert set(f) == ({1, 2, 3, 4, 5, 6} if k == 0 else {1, 2, 4, 5, 6})
        assert f[1] == 5 and f[2] == len(samples) and f[6] == 0
        data[f[5]:f[5] + len(f[4])] = f[4]  # type: ignore[arg-type, index, operator]
    assert bytes(data) == samples


# ------------------------------------------------------------------ commands, proto3 and proto2 clients


def key(number: int, wire: int) -> bytes:
    return _encode_varint(number << 3 | wire)


def _encode_varint(v: int) -> bytes:
    out = bytearray()
    while True:
        out.append((v & 0x7F) | (0x80 if v > 0x7F else 0))
        v >>= 7
        if not v:
            return bytes(out)


def vi(number: int, value: int) -> bytes:
    return key(number, VARINT) + _encode_varint(value)


def f32(number: int, value: float) -> bytes:
    return key(number, I32) + struct.pack("<f", value)


def ld(number: int, body: bytes) -> bytes:
    return key(number, LEN) + _encode_varint(len(body)) + body


def proto3(number: int, kind: str, value: object) -> bytes:
    """A proto3 client's field: nothing at all when the value is the default."""
    if not value:
        return b""
    return {"v": vi, "f": f32}[kind](number, value) if kind in "vf" else ld(number, value)  # type: ignore[arg-type, operator]


def command(type_: int, body_field: int | None, body: bytes, *, way: str) -> bytes:
    t = proto3(1, "v", type_) if way == "proto3" else vi(1, type_)
    return t + (ld(body_field, body) if body_field is not None else b"")


S = ar.AcousticSettings(cookie=0, frame_rate=12.5, samples_per_beam=1200, sample_start_delay=930, cycle_period=0,
                        sample_period=8, pulse_width=12, ping_mode=3, enable_transmit=False, frequency=ar.FREQ_LOW,
                        enable_150_volts=True, receiver_gain=0.0)


def settings_body(s: ar.AcousticSettings, way: str) -> bytes:
    values = [("v", s.cookie), ("f", s.frame_rate), ("v", s.samples_per_beam), ("v", s.sample_start_delay),
              ("v", s.cycle_period), ("v", s.sample_period), ("v", s.pulse_width), ("v", s.ping_mode),
              ("v", int(s.enable_transmit)), ("v", s.frequency), ("v", int(s.enable_150_volts)), ("f", s.receiver_gain)]
    if way == "proto3":
        return b"".join(proto3(n, k, v) for n, (k, v) in enumerate(values, start=1))
    return b"".join((vi if k == "v" else f32)(n, v) for n, (k, v) in enumerate(values, start=1))  # type: ignore[operator]


def cases(way: str) -> list[tuple[str, bytes, object]]:
    """(label, payload, expected event) for every command type, encoded ``way``."""
    p3 = way == "proto3"
    date = "2026-Nov-24 11:01:02"
    focus = f32(2, 2.5) if p3 else vi(1, 0) + f32(2, 2.5)
    return [
        ("SET_DATETIME", command(ar.SET_DATETIME, 2, ld(1, date.encode()), way=way), ar.SetDateTime(date)),
        ("SET_FRAMESTREAM_RECEIVER", command(1, 3, vi(1, 5000) + (b"" if p3 else ld(2, b"127.0.0.1")), way=way),
         ar.SetFrameStreamReceiver(5000, None if p3 else "127.0.0.1")),
        ("SET_FRAMESTREAM_SETTINGS", command(2, 4, ld(1, vi(1, 1) + vi(2, 100)) + (b"" if p3 else vi(2, 0)), way=way),
         ar.Unsupported(2)),
        ("SET_ACOUSTICS", command(3, 5, settings_body(S, way), way=way), ar.SetAcoustics(S)),
        ("SET_SALINITY fresh", command(4, 6, b"" if p3 else vi(1, 0), way=way), ar.SetSalinity(0)),
        ("SET_SALINITY brackish", command(4, 6, vi(1, 15), way=way), ar.SetSalinity(15)),
        ("SET_TELEPHOTO", command(5, 7, b"" if p3 else vi(1, 0), way=way), ar.Unsupported(5)),
        ("SET_FOCUS", command(6, 8, focus, way=way), ar.SetFocus(2.5, None if p3 else 0)),
        ("FORCE_FOCUS", command(7, 9, vi(1, 1), way=way), ar.Unsupported(7)),
        ("HOME_FOCUS", command(8, 10, b"", way=way), ar.Unsupported(8)),
        ("SET_ROTATOR_MOUNT", command(9, 11, b"" if p3 else vi(1, 0), way=way), ar.Unsupported(9)),
        *[(name, command(t, t + 2, (b"" if p3 else vi(1, 0)) + f32(2, 1.5), way=way), ar.Unsupported(t))
          for t, name in ((10, "SET_ROTATOR_VELOCITY"), (11, "SET_ROTATOR_ACCELERATION"), (12, "SET_ROTATOR_POSITION"))],
        ("STOP_ROTATOR", command(13, 15, b"" if p3 else vi(1, 0), way=way), ar.Unsupported(13)),
        ("PING", command(ar.PING, 16, b"", way=way), ar.Ping()),
        ("SET_SYSLOG_RECEIVER", command(15, 17, ld(1, b"127.0.0.1"), way=way), ar.Unsupported(15)),
        ("POWER_DOWN", command(16, 18, b"", way=way), ar.Unsupported(16)),
        ("RESERVED_1", command(17, 19, b"", way=way), ar.Unsupported(17)),
    ]


@pytest.mark.parametrize("way", ["proto3", "proto2"])
def test_every_command_type_reads_the_same_from_proto3_and_proto2_clients(way: str) -> None:
    for label, payload, expected in cases(way):
        strict_decode("Command", payload)  # the test's bytes are the vendor's wire
        assert ar.parse_command(payload) == expected, label
    stream = b"".join(ar.frame_command(p) for _, p, _ in cases(way))
    r = ar.CommandReader()
    r.receive_data(stream)
    assert r.events() == [e for _, _, e in cases(way)] and r.errors == 0


def test_the_issue_s_proto3_set_date_time() -> None:
    """``00 00 00 18 | 12 16 0a 14 "2026-Nov-24 11:01:02"``: no ``type`` on the wire (SET_DATETIME is 0)."""
    wire = bytes.fromhex("00000018" "1216" "0a14") + b"2026-Nov-24 11:01:02"
    r = ar.CommandReader()
    r.receive_data(wire + ar.encode_command(ar.Ping()))
    assert r.events() == [ar.SetDateTime("2026-Nov-24 11:01:02"), ar.Ping()] and r.errors == 0


def test_what_stays_a_bad_command() -> None:
    """A type the vendor's enum lacks, and a command type without its message (message fields keep
    their presence in proto3 too)."""
    assert isinstance(ar.parse_command(vi(1, 99) + ld(2, b"")), ar.BadCommand)
    assert isinstance(ar.parse_command(b""), ar.BadCommand)        # SET_DATETIME without dateTime
    assert isinstance(ar.parse_command(vi(1, 3)), ar.BadCommand)   # SET_ACOUSTICS without settings


# ------------------------------------------------------------------ through the device, on the wire


def test_the_device_s_beacons_and_frame_parts_pass_and_it_reads_proto3_clients(tmp_path: Path) -> None:
    """A bridge with the ARIS device on the water tank, recording: what it sends over UDP (beacons,
    FrameParts) passes the strict decoder; a client that writes its commands the proto3 way (no
    ``type`` for SetDateTime, defaults omitted) configures it without one bad command; the .aris
    recording (written through a stream the device opens) reads back."""
    from hilsim.runtime.bridge import Bridge

    text = (ROOT / "scenarios" / "water_tank" / "scenario.toml").read_text().split("\n[[devices]]")[0]
    beacons, frames_sock = _udp(), _udp()
    text += (f'\n[[devices]]\nname = "aris"\nprotocol = "aris"\nport = 0\nbeacon_port = {beacons.getsockname()[1]}\n'
             'beacon_interval_s = 0.2\nrecord = "rec.aris"\nsensor = "sonar"\n')
    (tmp_path / "scenario.toml").write_text(text)
    ready: dict[str, Any] = {}
    started = threading.Event()

    def serve() -> None:
        async def main() -> None:
            b = Bridge(tmp_path / "scenario.toml", status_interval=0)
            try:
                ready.update(endpoints=await b.start(), bridge=b, loop=asyncio.get_running_loop())
            finally:
                started.set()
            try:
                await b.run()
            finally:
                await b.close()

        asyncio.run(main())

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    assert started.wait(120) and "bridge" in ready, "bridge did not start"
    bridge, loop = ready["bridge"], ready["loop"]
    try:
        device = next(d for d in bridge.devices if d.protocol == "aris")
        for _ in range(3):
            fields = dict(strict_decode("Availability", beacons.recv(2048)))
            assert fields[13] == [] and fields[2] == ar.SYSTEM_1800
        port = int(next(e for e in ready["endpoints"] if e.protocol == "aris").address.rsplit(":", 1)[1])
        s = ar.AcousticSettings.for_window(0.83, 5.83, 512, 1482.0, frame_rate=8.0, cookie=0)  # cookie 0: omitted
        with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
            for payload in (command(1, 3, vi(1, frames_sock.getsockname()[1]), way="proto3"),
                            command(ar.SET_DATETIME, 2, ld(1, b"2026-Nov-24 11:01:02"), way="proto3"),
                            command(3, 5, settings_body(s, "proto3"), way="proto3"),
                            command(4, 6, b"", way="proto3"), command(ar.PING, 16, b"", way="proto3")):
                sock.sendall(ar.frame_command(payload))
            asm, got, deadline = ar.FrameAssembler(), [], time.monotonic() + 30
            while len(got) < 2 or not device.counters["recorded"]:
                assert time.monotonic() < deadline, f"no frames: {got}, {dict(device.counters)}"
                sock.sendall(ar.frame_command(command(ar.PING, 16, b"", way="proto3")))
                dgram = frames_sock.recv(65536)
                part = dict(strict_decode("FramePart", dgram))
                assert part[6] == 0 and 0 <= part[5] <= part[2]  # type: ignore[operator]
                got += [e for e in asm.receive_datagram(dgram) if isinstance(e, ar.AssembledFrame)]
            assert device.counters["bad_commands"] == 0
            h = ar.decode_frame_header(got[-1].header)
            assert h["SamplesPerBeam"] == 512 and h["AppliedSettings"] == 0 and h["InvalidSettings"] == 0
    finally:
        loop.call_soon_threadsafe(bridge.stop)
        th.join(30)
        beacons.close()
        frames_sock.close()
    with open(tmp_path / "rec.aris", "rb") as f, ArisReader(f) as rec:
        assert len(rec) >= 1 and rec.serial_number == int(device.options["serial_number"])
