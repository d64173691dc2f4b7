"""ARIS codecs: the real .aris recording, frame-header offsets from the reference, protobuf
wire bytes checked by hand, the command reader under hostile input, FramePart size and
reassembly (reference/sonar-protocols.md section 2)."""

from __future__ import annotations

import importlib.util
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilsim.protocols import aris as ar
from hilsim.protocols.aris_file import ArisFileError, ArisReader, ArisWriter

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "tests" / "data" / "aris_sample.aris"


# ------------------------------------------------------------------ .aris file


def test_reader_opens_the_real_recording():
    with open(SAMPLE, "rb") as f, ArisReader(f) as r:
        assert (r.n_beams, r.n_samples, len(r)) == (48, 2000, 6)
        assert r.serial_number == 1098 and r.trailing_bytes == 0
        frames = list(r)
    raw = SAMPLE.read_bytes()
    for i, f in enumerate(frames):
        assert f.samples.shape == (2000, 48) and f.reordered
        off = 1024 + i * (1024 + 96000)
        assert f.header["FrameIndex"] == struct.unpack_from("<I", raw, off)[0] == i
        assert f.header["SamplesPerBeam"] == 2000 and f.header["PingMode"] == 1
        # sample s of wire beam b (b = 0 starboard) is sim beam 47 - b
        data = raw[off + 1024: off + 1024 + 96000]
        assert f.samples[1000, 47] == data[1000 * 48 + 0] and f.samples[7, 0] == data[7 * 48 + 47]
    h = frames[0].header
    assert h["TheSystemType"] == 2 and h["SonarSerialNumber"] == 1098
    assert h["SoundSpeed"] == pytest.approx(1435.93, abs=0.01)
    # the window the header states is the one the timing fields give (within the sonar's rounding)
    s = ar.AcousticSettings(samples_per_beam=2000, sample_start_delay=int(h["SampleStartDelay"]),  # type: ignore[arg-type]
                            sample_period=int(h["SamplePeriod"]))  # type: ignore[arg-type]
    start, end = s.window(float(h["SoundSpeed"]))  # type: ignore[arg-type]
    assert start == pytest.approx(h["WindowStart"], abs=0.1)
    assert end - start == pytest.approx(h["WindowLength"], abs=0.3)


def test_writer_round_trip_and_frame_count(tmp_path):
    out = tmp_path / "copy.aris"
    with open(SAMPLE, "rb") as f, ArisReader(f) as r, open(out, "wb") as sink, ArisWriter(sink, {"SN": 1098}) as w:
        for f in r:
            w.write_frame(f.header, f.samples)
    raw = out.read_bytes()
    assert raw[:4] == b"DDF\x05" and struct.unpack_from("<I", raw, 4)[0] == 6
    assert struct.unpack_from("<I", raw, 16)[0] == 48 and struct.unpack_from("<I", raw, 24)[0] == 2000
    assert struct.unpack_from("<I", raw, 44)[0] == 1098
    with ArisReader(out.read_bytes()) as a, ArisReader(SAMPLE.read_bytes()) as b:
        for fa, fb in zip(a, b):
            np.testing.assert_array_equal(fa.samples, fb.samples)
            assert fa.header["WindowStart"] == fb.header["WindowStart"]


def test_reader_rejects_other_files(tmp_path):
    p = tmp_path / "x.aris"
    p.write_bytes(b"DDF\x04" + bytes(2000))
    with pytest.raises(ArisFileError):
        ArisReader(p.read_bytes())
    p.write_bytes(b"DDF")
    with pytest.raises(ArisFileError), open(p, "rb") as f:
        ArisReader(f)


# --------------------------------------------------------------- frame header


def test_frame_header_offsets():
    b = ar.encode_frame_header({"FrameIndex": 9, "FrameTime": 2**40 + 5, "sonarTimeStamp": 7, "WindowStart": 1.5,
                                "WindowLength": 5.0, "PingMode": 3, "FrequencyHiLow": 1, "SamplePeriod": 13,
                                "SoundSpeed": 1482.0, "SamplesPerBeam": 512, "SampleStartDelay": 1122,
                                "LargeLens": 0, "TheSystemType": 0, "SonarSerialNumber": 1800,
                                "ReorderedSamples": 1, "AppliedSettings": 7, "ConstrainedSettings": 8,
                                "InvalidSettings": 9, "Version": ar.FILE_VERSION})
    assert len(b) == 1024
    assert struct.unpack_from("<IQI", b, 0) == (9, 2**40 + 5, 0x05464444)
    assert struct.unpack_from("<Q", b, 20)[0] == 7
    assert struct.unpack_from("<ff", b, 52) == (1.5, 5.0)
    for off, v in ((436, 3), (440, 1), (452, 13), (468, 512), (476, 1122), (480, 0), (484, 0), (488, 1800),
                   (516, 1), (680, 7), (684, 8), (688, 9)):
        assert struct.unpack_from("<I", b, off)[0] == v, off
    assert struct.unpack_from("<f", b, 464)[0] == 1482.0
    assert ar.decode_frame_header(b)["InvalidSettings"] == 9
    with pytest.raises(ValueError):
        ar.encode_frame_header({"NoSuchField": 1})


# ------------------------------------------------------------ protobuf bytes


def test_availability_writes_zero_fields():
    b = ar.encode_availability(ar.Availability(serial_number=0, system_type=0, software_version=(0, 0, 0),
                                               connection_state=0, system_variants=()))
    # field 1 varint 0, field 2 varint 0, field 3 {1: 0, 2: 0, 3: 0}, field 4 varint 0, field 13: the vendor's
    # SystemVariants message (wire type 2, tag 6a), empty (issue #20: it was a varint, 68 00)
    assert b == bytes([0x08, 0, 0x10, 0, 0x1A, 6, 0x08, 0, 0x10, 0, 0x18, 0, 0x20, 0, 0x6A, 0])
    defender = ar.encode_availability(ar.Availability(7, system_variants=("DF",)))
    assert defender.endswith(bytes([0x6A, 4, 0x0A, 2]) + b"DF")  # SystemVariants { enabled: "DF" }
    assert ar.decode_availability(defender) == ar.Availability(7, system_variants=("DF",))
    a = ar.decode_availability(ar.encode_availability(ar.Availability(1234, connection_state=1)))
    assert a == ar.Availability(1234, connection_state=1)
    assert isinstance(ar.decode_availability(b"\xff\xff"), ar.BadCommand)


def test_ping_command_bytes():
    # 4-byte big-endian length, then type = 14 (field 1) and the empty ping message (field 16)
    assert ar.encode_command(ar.Ping()) == b"\x00\x00\x00\x05" + bytes([0x08, 14, 0x82, 0x01, 0x00])


def test_settings_command_writes_every_field():
    s = ar.AcousticSettings(cookie=0, frame_rate=0.0, samples_per_beam=0, sample_start_delay=0, cycle_period=0,
                            sample_period=0, pulse_width=0, ping_mode=0, enable_transmit=False, frequency=0,
                            enable_150_volts=False, receiver_gain=0.0)
    payload = ar.encode_command(ar.SetAcoustics(s))[4:]
    inner = payload[payload.index(0x2A) + 2:]  # field 5, length-delimited
    tags = [inner[i] for i in range(0, len(inner)) if i in _tag_positions(inner)]
    assert [t >> 3 for t in tags] == list(range(1, 13))


def _tag_positions(b: bytes) -> set[int]:
    pos, i = set(), 0
    while i < len(b):
        pos.add(i)
        wire = b[i] & 7
        i += 1
        if wire == 0:
            while b[i] & 0x80:
                i += 1
            i += 1
        elif wire == 5:
            i += 4
    return pos


def test_commands_round_trip_whole_and_byte_by_byte():
    cmds = [ar.SetFrameStreamReceiver(5000), ar.SetFrameStreamReceiver(5001, "127.0.0.2"),
            ar.SetDateTime("2014-Jan-31 23:58:15"), ar.SetAcoustics(ar.AcousticSettings(cookie=3)),
            ar.SetSalinity(35), ar.SetFocus(2.5), ar.SetFocus(None, 400), ar.Ping()]
    stream = b"".join(ar.encode_command(c) for c in cmds)
    r = ar.CommandReader()
    r.receive_data(stream)
    assert r.events() == cmds
    r = ar.CommandReader()
    got = []
    for b in stream:
        r.receive_data(bytes([b]))
        got += r.events()
    assert got == cmds and r.buffered_bytes == 0


def test_unsupported_and_bad_commands():
    from hilsim.protocols.aris_pb import aris_commands_pb2 as pb

    m = pb.Command()
    m.type = 5  # type: ignore[assignment]  # SET_TELEPHOTO: well-formed, not handled
    r = ar.CommandReader()
    r.receive_data(ar.frame_command(m.SerializeToString()) + ar.frame_command(b"\x08\x03") + ar.encode_command(ar.Ping()))
    evs = r.events()
    assert evs[0] == ar.Unsupported(5)
    assert isinstance(evs[1], ar.BadCommand)  # SET_ACOUSTICS without settings
    assert evs[-1] == ar.Ping()


# ------------------------------------------------------------------ robustness

PING = ar.encode_command(ar.Ping())
SETTINGS = ar.encode_command(ar.SetAcoustics(ar.AcousticSettings(cookie=11)))


def _drain(r: ar.CommandReader) -> list:
    out = []
    for _ in range(100_000):
        ev = r.next_event()
        if ev is ar.NEED_DATA:
            return out
        out.append(ev)
    raise AssertionError("reader did not settle")


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=300), st.integers(1, 50))
def test_random_bytes_then_valid_commands(junk, chunk):
    r = ar.CommandReader()
    stream = junk + SETTINGS + PING
    events = []
    for i in range(0, len(stream), chunk):
        r.receive_data(stream[i:i + chunk])
        events += _drain(r)
    assert events and events[-1] == ar.Ping()
    assert r.buffered_bytes <= r.max_length + 4


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_mutated_and_truncated_commands_never_raise(data):
    msg = bytearray(data.draw(st.sampled_from([PING, SETTINGS, ar.encode_command(ar.SetDateTime("x"))])))
    for _ in range(data.draw(st.integers(0, 6))):
        msg[data.draw(st.integers(0, len(msg) - 1))] = data.draw(st.integers(0, 255))
    blob = bytes(msg[:data.draw(st.integers(0, len(msg)))])
    assert isinstance(ar.parse_command(blob[4:]), (ar.Ping, ar.SetAcoustics, ar.SetDateTime, ar.Unsupported,
                                                   ar.BadCommand))
    r = ar.CommandReader()
    # a false start holds at most max_length + 4 bytes; valid commands after that decode
    r.receive_data(blob + PING * (2 + (r.max_length + 4) // len(PING)))
    assert _drain(r)[-1] == ar.Ping()


def test_four_gigabyte_length_allocates_nothing():
    r = ar.CommandReader()
    r.receive_data(b"\xff\xff\xff\xff")
    evs = _drain(r)
    assert evs[0] == ar.Oversize(0xFFFFFFFF) and r.buffered_bytes <= 4
    r.receive_data(PING)
    assert _drain(r)[-1] == ar.Ping()


def test_valid_header_with_big_length_then_stall_is_bounded():
    r = ar.CommandReader()
    r.receive_data(struct.pack(">I", r.max_length) + b"\x08")  # plausible, incomplete
    assert _drain(r) == []  # waits for the rest, holding at most one command's bytes
    assert r.buffered_bytes <= r.max_length + 4


# -------------------------------------------------------------- frame stream


def test_split_frame_datagrams_and_reassembly():
    header = ar.encode_frame_header({"FrameIndex": 0, "PingMode": 3, "SamplesPerBeam": 2000,
                                     "ReorderedSamples": 1})
    samples = (np.arange(96 * 2000) % 251).astype(np.uint8).tobytes()
    parts = ar.split_frame(1, header, samples)
    assert all(len(p) <= 1500 for p in parts) and len(parts) > 100
    from hilsim.protocols.aris_pb import aris_frame_stream_pb2 as pb

    offsets = []
    for i, p in enumerate(parts):
        m = pb.FramePart()
        m.ParseFromString(p)
        for f in ("frame_index", "total_data_size", "data", "data_offset", "ack_port"):
            assert m.HasField(f), f  # written explicitly, even ack_port = 0 and data_offset = 0
        assert m.HasField("header") == (i == 0) and m.frame_index == 1 and m.total_data_size == len(samples)
        offsets.append(m.data_offset)
    assert offsets[0] == 0 and offsets == sorted(offsets)
    fa = ar.FrameAssembler()
    rng = np.random.default_rng(0)
    out = []
    for i in rng.permutation(len(parts)):
        out += fa.receive_datagram(parts[i])
    assert len(out) == 1 and isinstance(out[0], ar.AssembledFrame)
    assert out[0].data == samples and out[0].header == header
    # a newer frame drops an incomplete older one
    fa = ar.FrameAssembler()
    assert fa.receive_datagram(parts[0]) == []
    new = ar.split_frame(2, header, samples[:100])
    evs = fa.receive_datagram(new[0])
    assert isinstance(evs[0], ar.DroppedFrame) and isinstance(evs[1], ar.AssembledFrame)
    assert isinstance(fa.receive_datagram(b"\xff" * 10)[0], ar.BadDatagram)


def test_samples_wire_order():
    img = np.arange(6, dtype=np.uint8).reshape(2, 3)  # beam 0 = port
    assert ar.samples_to_wire(img) == bytes([2, 1, 0, 5, 4, 3])
    np.testing.assert_array_equal(ar.samples_from_wire(ar.samples_to_wire(img), 3, 2), img)


# ------------------------------------------------------------------- settings


def test_settings_check_applied_constrained_invalid():
    ok = ar.AcousticSettings.for_window(0.83, 5.83, 512, 1482.0, frame_rate=10.0)
    assert ar.check_settings(ok).outcome == "applied"
    start, end = ok.window(1482.0)
    assert start == pytest.approx(0.83, abs=0.01) and end == pytest.approx(5.83, abs=0.2)
    # 512 x 10 us after a 930 us delay needs a 6410 us cycle: 2000 is raised, the rate kept
    short = ar.check_settings(ar.AcousticSettings(samples_per_beam=512, sample_period=10, cycle_period=2000))
    assert short.outcome == "constrained" and short.settings.cycle_period == 930 + 5120 + 360
    assert short.settings.frame_rate == 10.0
    fast = ar.check_settings(ar.AcousticSettings(frame_rate=30.0, receiver_gain=40.0))
    assert fast.outcome == "constrained"
    assert fast.settings.frame_rate == 15.0 and fast.settings.receiver_gain == 24.0
    # 4000 samples x 100 us cannot fit the longest (150 ms) cycle
    assert ar.check_settings(ar.AcousticSettings(samples_per_beam=4000, sample_period=100)).outcome == "invalid"
    for bad in (dict(samples_per_beam=5), dict(sample_period=2), dict(ping_mode=9), dict(ping_mode=1),
                dict(sample_start_delay=10)):
        assert ar.check_settings(ar.AcousticSettings(**bad)).outcome == "invalid", bad  # type: ignore[arg-type]


# ------------------------------------------------------ generated modules


@pytest.mark.skipif(importlib.util.find_spec("grpc_tools") is None, reason="grpcio-tools not installed")
def test_generated_modules_match_the_proto_files(tmp_path):
    subprocess.run([sys.executable, "-m", "grpc_tools.protoc", f"-I{ROOT / 'protocols' / 'aris'}",
                    f"--python_out={tmp_path}", *map(str, sorted((ROOT / "protocols" / "aris").glob("*.proto")))],
                   check=True)
    for gen in tmp_path.glob("*_pb2.py"):
        committed = (ROOT / "hilsim" / "protocols" / "aris_pb" / gen.name).read_text()
        serialized = [line for line in gen.read_text().splitlines() if "AddSerializedFile" in line]
        assert serialized and serialized[0] in committed, gen.name
