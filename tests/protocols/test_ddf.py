"""DDF_04 stream codec: headers, window codes, frames, reader/writer, commands.

Offsets below are hardcoded from the DDF_04 tables in
shared/reference/sonar-protocols.md (and, for bytes 92..123 that the table
skips, the field order of the public DDF_04 MATLAB reader), never taken from
the encoder, so a layout slip in the codec fails here.
"""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilsim.protocols.ddf import (
    NEED_DATA,
    DdfReader,
    DdfWriter,
    EndOfStream,
    FileHeader,
    FileHeaderEvent,
    FrameEvent,
    FrameHeader,
    ProtocolError,
    codes_for_window,
    decode_file_header,
    decode_frame,
    decode_frame_header,
    encode_file_header,
    encode_frame,
    encode_frame_header,
    transmit_flags,
    window_from_codes,
)
from hilsim.protocols.ddf_commands import (
    MAX_LINE_BYTES,
    BadCommand,
    CommandDecoder,
    Ping,
    Reply,
    SetGain,
    SetRate,
    SetWindow,
    decode_replies,
    encode_command,
    encode_reply,
    pack_replies,
)
from hilsim.protocols.ddf_file import read_ddf_file, write_ddf_file

T0 = 1715000000.123456  # 2024-05-06T12:53:20.123456Z

# ------------------------------------------------------------------ helpers

i32 = st.integers(-(2**31), 2**31 - 1)
f32 = st.floats(allow_nan=False, width=32)
f64 = st.floats(allow_nan=False)


def text(max_size: int) -> st.SearchStrategy[str]:
    return st.text(st.characters(min_codepoint=1, max_codepoint=127), max_size=max_size)


def drain(decoder: DdfReader | CommandDecoder) -> list[object]:
    events = []
    while (event := decoder.next_event()) is not NEED_DATA:
        events.append(event)
        if isinstance(event, EndOfStream):
            break
    return events


def sim_frame(n_samples: int, n_beams: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n_samples, n_beams), dtype=np.uint8)


def stream(numbeams: int = 8, samples: int = 16, n_frames: int = 3) -> tuple[bytes, list[object]]:
    """A DDF byte stream and the events a reader should produce for it."""
    fh = FileHeader(numbeams=numbeams, samplesperchannel=samples, idstring="test")
    writer = DdfWriter()
    events: list[object] = [FileHeaderEvent(fh)]
    data = writer.send(FileHeaderEvent(fh))
    for k in range(n_frames):
        ev = FrameEvent(FrameHeader(framenumber=k, time=T0 + k / 10, depth=k), sim_frame(samples, numbeams, k))
        events.append(ev)
        data += writer.send(ev)
    return data, events


# ----------------------------------------------------------------- file header


def test_file_header_is_1024_bytes_with_signature() -> None:
    data = encode_file_header(FileHeader())
    assert len(data) == 1024
    assert data[:4] == bytes([0x44, 0x44, 0x46, 0x04])
    assert struct.unpack_from("<I", data, 0)[0] == 0x04464444
    assert decode_file_header(data) == FileHeader()


def test_file_header_fields_at_reference_offsets() -> None:
    ints = [
        "numframes", "framerate", "resolution", "numbeams", None, "samplesperchannel",
        "receivergain", "windowstart", "windowlength", "reverse", "serialnumber",
    ]  # fmt: skip
    tail = [
        "id1", "id2", "id3", "id4", "startframe", "endframe", "timelapse", "recordinterval",
        "radioseconds", "frameinterval", "flags", "auxflags", "sspd", "flags3d",
    ]  # fmt: skip
    values = {name: 100 + k for k, name in enumerate(ints + tail) if name}
    h = FileHeader(**values, samplerate=1234.5, date="2024-05-06_125320", idstring="tank A")
    data = encode_file_header(h)
    for k, name in enumerate(ints):
        if name:
            assert struct.unpack_from("<i", data, 4 + 4 * k)[0] == values[name], name
    assert struct.unpack_from("<f", data, 20)[0] == 1234.5
    assert data[48:80] == b"2024-05-06_125320".ljust(32, b"\0")
    assert data[80:336] == b"tank A".ljust(256, b"\0")
    for k, name in enumerate(tail):
        assert struct.unpack_from("<i", data, 336 + 4 * k)[0] == values[name], name
    assert data[392:] == bytes(1024 - 392)


@settings(max_examples=60, deadline=None)
@given(
    ints=st.fixed_dictionaries({f.name: i32 for f in dataclasses.fields(FileHeader) if f.type == "int"}),
    samplerate=f32,
    date=text(31),
    idstring=text(255),
)
def test_file_header_round_trip(ints: dict[str, int], samplerate: float, date: str, idstring: str) -> None:
    h = FileHeader(**ints, samplerate=samplerate, date=date, idstring=idstring)
    data = encode_file_header(h)
    assert len(data) == 1024
    assert decode_file_header(data) == h


@pytest.mark.parametrize(
    ("data", "words"),
    [
        (b"DDF\x05" + bytes(1020), "version 5"),
        (b"DDF\x03" + bytes(1020), "version 3"),
        (b"GET / HTTP/1.1\r\n" + bytes(1008), "44 44 46 04"),
        (b"DDF\x04" + bytes(10), "1024 bytes"),
    ],
)
def test_file_header_rejects_bad_input_clearly(data: bytes, words: str) -> None:
    with pytest.raises(ProtocolError, match=words):
        decode_file_header(data)
    assert issubclass(ProtocolError, ValueError)


@pytest.mark.parametrize(
    "change",
    [{"numframes": 2**31}, {"date": "x" * 32}, {"idstring": "café"}, {"date": "a\0b"}, {"samplerate": 1e39}],
)
def test_encode_file_header_rejects_unencodable_values(change: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        encode_file_header(dataclasses.replace(FileHeader(), **change))


# ---------------------------------------------------------------- frame header

PLATFORM = ["velocity", "depth", "altitude", "pitch", "pitchrate", "roll", "rollrate", "heading", "headingrate"]


def test_frame_header_fields_at_reference_offsets() -> None:
    platform = {name: 1.5 + k for k, name in enumerate(PLATFORM)}
    h = FrameHeader(
        framenumber=77, time=T0, status=5, transmit=transmit_flags(True), windowstart=2,
        windowlength=3, threshold=11, intensity=12, receivergain=13, degc1=14, degc2=15,
        humidity=16, focus=17, battery=18, status1="st1", status2="st2", panwcom=-1.25,
        tiltwcom=2.25, sonarpan=3.5, sonartilt=-4.5, sonarroll=5.5, latitude=59.912345678,
        longitude=10.75, sonarposition=0.5, configflags=2, replies=b"OK PING\n", **platform,
    )  # fmt: skip
    data = encode_frame_header(h)
    assert len(data) == 1024
    u = lambda fmt, off: struct.unpack_from("<" + fmt, data, off)[0]  # noqa: E731
    assert u("i", 0) == 77
    assert u("Q", 4) == 1715000000123456  # frametime: uint64 microseconds since epoch
    assert data[12:16] == b"DDF\x04"
    assert u("i", 16) == 5
    assert struct.unpack_from("<7i", data, 20) == (2024, 5, 6, 12, 53, 20, 12)
    assert u("i", 48) == 0b011  # HF + enable
    assert (u("i", 52), u("i", 56)) == (2, 3)
    assert struct.unpack_from("<8i", data, 60) == (11, 12, 13, 14, 15, 16, 17, 18)
    assert data[92:108] == b"st1".ljust(16, b"\0") and data[108:116] == b"st2".ljust(8, b"\0")
    assert (u("f", 116), u("f", 120)) == (-1.25, 2.25)
    for k, name in enumerate(PLATFORM):
        assert u("f", 124 + 4 * k) == platform[name], name
    assert struct.unpack_from("<3f", data, 160) == (3.5, -4.5, 5.5)
    assert (u("d", 172), u("d", 180)) == (59.912345678, 10.75)
    assert u("f", 188) == 0.5
    assert u("i", 192) == 2
    assert data[196:768] == bytes(768 - 196)
    assert data[768:] == b"OK PING\n".ljust(256, b"\0")
    assert decode_frame_header(data) == h


frame_headers = st.builds(
    FrameHeader,
    framenumber=i32,
    time=st.integers(0, 2**52).map(lambda us: us / 1e6),
    version=st.binary(min_size=4, max_size=4),
    status=i32, transmit=i32, windowstart=i32, windowlength=i32, threshold=i32,
    intensity=i32, receivergain=i32, degc1=i32, degc2=i32, humidity=i32, focus=i32, battery=i32,
    status1=text(15), status2=text(7), panwcom=f32, tiltwcom=f32, velocity=f32, depth=f32,
    altitude=f32, pitch=f32, pitchrate=f32, roll=f32, rollrate=f32, heading=f32,
    headingrate=f32, sonarpan=f32, sonartilt=f32, sonarroll=f32, latitude=f64, longitude=f64,
    sonarposition=f32, configflags=i32,
    replies=st.binary(max_size=255).map(lambda b: b.replace(b"\0", b"x")),
)  # fmt: skip


@settings(max_examples=80, deadline=None)
@given(frame_headers)
def test_frame_header_round_trip(h: FrameHeader) -> None:
    data = encode_frame_header(h)
    assert len(data) == 1024
    assert decode_frame_header(data) == h


@settings(max_examples=80, deadline=None)
@given(st.floats(0, 4e9))
def test_frame_time_fills_frametime_and_calendar_from_one_instant(t: float) -> None:
    data = encode_frame_header(FrameHeader(time=t))
    us = struct.unpack_from("<Q", data, 4)[0]
    assert us == round(t * 1e6)
    y, mo, d, h, mi, s, hs = struct.unpack_from("<7i", data, 20)
    import calendar

    assert calendar.timegm((y, mo, d, h, mi, s)) == us // 1_000_000
    assert hs == us % 1_000_000 // 10_000
    assert abs(decode_frame_header(data).time - t) <= 0.5e-6 + 1e-15 * t


def test_frame_time_from_calendar_when_frametime_means_something_else() -> None:
    data = bytearray(encode_frame_header(FrameHeader(time=T0)))
    struct.pack_into("<Q", data, 4, 0)  # a foreign file with no usable frametime
    assert decode_frame_header(bytes(data)).time == pytest.approx(1715000000.12, abs=1e-9)
    struct.pack_into("<7i", data, 20, 0, 0, 0, 0, 0, 0, 0)  # no calendar either
    struct.pack_into("<Q", data, 4, 42)
    assert decode_frame_header(bytes(data)).time == 42e-6


def test_frame_header_accepts_numpy_scalars_from_the_sim() -> None:
    h = FrameHeader(framenumber=np.int64(5), time=np.float64(T0), depth=np.float32(2.5), windowstart=np.int32(3))
    back = decode_frame_header(encode_frame_header(h))
    assert (back.framenumber, back.depth, back.windowstart) == (5, 2.5, 3)
    assert type(back.framenumber) is int and type(back.depth) is float


@pytest.mark.parametrize(
    "change",
    [{"time": -1.0}, {"time": float("nan")}, {"framenumber": -(2**31) - 1}, {"depth": 1e39},
     {"status1": "x" * 16}, {"replies": b"x" * 256}, {"version": b"DDF"}],
)  # fmt: skip
def test_encode_frame_header_rejects_unencodable_values(change: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        encode_frame_header(dataclasses.replace(FrameHeader(), **change))


# ---------------------------------------------------------------- window codes


def test_paper_window_is_start_code_2_length_code_2_at_hf() -> None:
    start, length = window_from_codes(2, 2, high_freq=True)
    assert start == pytest.approx(0.838) and length == 5.0  # the paper's 0.83-5.83 m
    assert codes_for_window(0.83, 5.0, high_freq=True) == (2, 2)
    assert FrameHeader(windowstart=2, windowlength=2).window_m == pytest.approx((0.838, 5.0))


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        ((1, 0, True), (0.419, 1.25)),
        ((31, 3, True), (12.989, 10.0)),
        ((1, 0, False), (0.838, 5.0)),  # LF: start step doubled, lengths shifted by 2
        ((31, 3, False), (25.978, 40.0)),
        ((2, 2, True, False), (0.75, 4.5)),  # classic windows
        ((2, 0, False, False), (1.5, 4.5)),
        ((2, 3, True, True, True), (0.838, 20.0)),  # long-range model, extended
        ((2, 3, False, False, True), (1.5, 72.0)),  # long-range model, classic, LF
    ],
)
def test_window_codes_table(args: tuple[int, int, bool], expected: tuple[float, float]) -> None:
    assert window_from_codes(*args) == pytest.approx(expected)


@pytest.mark.parametrize(("start", "length"), [(0, 0), (32, 0), (1, -1), (1, 4)])
def test_window_codes_out_of_range(start: int, length: int) -> None:
    with pytest.raises(ValueError, match="out of range"):
        window_from_codes(start, length, True)


@pytest.mark.parametrize("hf", [True, False])
@pytest.mark.parametrize("extended", [True, False])
def test_codes_for_window_inverts_window_from_codes(hf: bool, extended: bool) -> None:
    for s in range(1, 32):
        for ln in range(4):
            assert codes_for_window(*window_from_codes(s, ln, hf, extended), hf, extended) == (s, ln)
    assert codes_for_window(0.0, 0.1, hf, extended) == (1, 0)  # clamps
    assert codes_for_window(1e3, 1e3, hf, extended) == (31, 3)


def test_frame_header_window_follows_transmit_and_configflags() -> None:
    lf = FrameHeader(transmit=transmit_flags(False), windowstart=3, windowlength=1)
    assert lf.window_m == pytest.approx((3 * 0.838, 10.0))
    classic = dataclasses.replace(lf, configflags=1)
    assert classic.window_m == pytest.approx((3 * 0.75, 9.0))
    assert transmit_flags(True, enabled=False, two_mhz=True) == 0b101


# ---------------------------------------------------------------------- frames


def test_port_beam_marker_is_last_on_the_wire() -> None:
    samples = np.zeros((512, 96), np.uint8)
    samples[100, 0] = 200  # sim beam 0 = most negative azimuth = port
    samples[7, 95] = 99  # sim beam 95 = starboard
    data = encode_frame(FrameHeader(), samples)
    assert len(data) == 1024 + 96 * 512
    block = data[1024:]
    assert block[100 * 96 + 95] == 200
    assert block[7 * 96 + 0] == 99
    assert sum(1 for b in block if b) == 2


def test_wire_index_is_sample_times_numbeams_plus_beam() -> None:
    ns, nb = 40, 12
    samples = sim_frame(ns, nb, 1)
    block = encode_frame(FrameHeader(), samples)[1024:]
    for s in range(ns):
        for sim_beam in range(nb):
            assert block[s * nb + (nb - 1 - sim_beam)] == samples[s, sim_beam]


def test_decode_frame_returns_sim_order() -> None:
    samples = sim_frame(512, 96, 2)
    h = FrameHeader(framenumber=9, time=T0, heading=271.5)
    header, back = decode_frame(encode_frame(h, samples), 96, 512)
    assert header == h
    assert back.shape == (512, 96) and back.dtype == np.uint8
    np.testing.assert_array_equal(back, samples)
    back[0, 0] = 1  # a writable copy


def test_frame_input_checks() -> None:
    with pytest.raises(ValueError, match="uint8"):
        encode_frame(FrameHeader(), np.zeros((4, 4), np.float32))  # type: ignore[arg-type]
    with pytest.raises(ProtocolError, match="needs 1088 bytes"):
        decode_frame(bytes(1000), 4, 16)


# -------------------------------------------------------------------- DdfReader


def test_reader_whole_stream_and_byte_at_a_time_agree() -> None:
    data, expected = stream()
    whole = DdfReader()
    whole.receive_data(data)
    assert drain(whole) == expected
    slow = DdfReader()
    events: list[object] = []
    for k in range(len(data)):
        slow.receive_data(data[k : k + 1])
        events += drain(slow)
        assert slow.buffered_bytes < 1024 + 8 * 16
    assert events == expected
    for reader in (whole, slow):
        reader.receive_data(b"")
        assert drain(reader) == [EndOfStream(0)]
        assert reader.next_event() == EndOfStream(0)


def test_reader_full_size_didson_frames() -> None:
    data, expected = stream(96, 512, 2)
    assert len(data) == 1024 + 2 * (1024 + 49152)
    reader = DdfReader()
    events: list[object] = []
    for k in range(0, len(data), 997):
        reader.receive_data(data[k : k + 997])
        events += drain(reader)
    assert events == expected
    assert reader.file_header == expected[0].header  # type: ignore[attr-defined]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(1, 600), max_size=60))
def test_reader_any_chunking_gives_the_same_events(cuts: list[int]) -> None:
    data, expected = stream(8, 16, 3)
    reader = DdfReader()
    events: list[object] = []
    pos = 0
    for n in cuts + [len(data)]:
        if data[pos : pos + n]:  # b"" would mean end of stream
            reader.receive_data(data[pos : pos + n])
        pos += n
        events += drain(reader)
    assert events == expected


def test_reader_truncated_stream_needs_data_then_reports_the_tail() -> None:
    data, expected = stream()
    reader = DdfReader()
    reader.receive_data(data[:-5])
    assert drain(reader) == expected[:-1]
    assert reader.next_event() is NEED_DATA
    assert reader.buffered_bytes == 1024 + 8 * 16 - 5
    reader.receive_data(b"")
    assert reader.next_event() == EndOfStream(trailing_bytes=1024 + 8 * 16 - 5)
    with pytest.raises(ValueError):
        reader.receive_data(b"more")


def test_reader_truncated_file_header_needs_data() -> None:
    reader = DdfReader()
    reader.receive_data(encode_file_header(FileHeader())[:500])
    assert reader.next_event() is NEED_DATA
    reader.receive_data(b"")
    with pytest.raises(ProtocolError, match="inside the 1024-byte file header"):
        reader.next_event()


@pytest.mark.parametrize(
    ("first", "words"),
    [(b"X", "not a DDF version 4 stream"), (b"DDF\x05", "version 5"), (b"\x00\x00\x00\x00", "44 44 46 04")],
)
def test_reader_bad_signature_fails_fast_and_stays_failed(first: bytes, words: str) -> None:
    reader = DdfReader()
    reader.receive_data(first)
    with pytest.raises(ProtocolError, match=words):
        reader.next_event()
    reader.receive_data(encode_file_header(FileHeader()))
    with pytest.raises(ProtocolError, match=words):
        reader.next_event()


@pytest.mark.parametrize("change", [{"numbeams": 0}, {"numbeams": 10**6}, {"samplesperchannel": -1}])
def test_reader_rejects_absurd_frame_sizes(change: dict[str, int]) -> None:
    reader = DdfReader()
    reader.receive_data(encode_file_header(dataclasses.replace(FileHeader(), **change)))
    with pytest.raises(ProtocolError, match="out of range"):
        reader.next_event()


def test_writer_checks_order_and_shape() -> None:
    writer = DdfWriter()
    frame = FrameEvent(FrameHeader(), np.zeros((512, 96), np.uint8))
    with pytest.raises(ValueError, match="FileHeaderEvent"):
        writer.send(frame)
    assert len(writer.send(FileHeaderEvent(FileHeader()))) == 1024
    with pytest.raises(ValueError, match="already"):
        writer.send(FileHeaderEvent(FileHeader()))
    with pytest.raises(ValueError, match="shape"):
        writer.send(FrameEvent(FrameHeader(), np.zeros((512, 48), np.uint8)))
    assert len(writer.send(frame)) == 1024 + 96 * 512


def test_file_round_trip_and_nc_style_truncated_capture(tmp_path: Path) -> None:
    data, expected = stream(96, 512, 3)
    path = tmp_path / "rec.ddf"
    frames = [e for e in expected if isinstance(e, FrameEvent)]
    with open(path, "wb") as sink:
        assert write_ddf_file(sink, FileHeader(idstring="test"), frames) == 3
    with open(path, "rb") as f:
        header, back = read_ddf_file(f)
    assert header.numframes == 3 and struct.unpack_from("<i", path.read_bytes(), 4)[0] == 3
    assert back == frames
    capture = tmp_path / "capture.ddf"
    capture.write_bytes(data[:-100])  # nc killed mid-frame; numframes stays 0 (live)
    header, back = read_ddf_file(capture.read_bytes())
    assert header.numframes == 0 and back == frames[:2]
    with pytest.raises(ProtocolError, match="incomplete last frame"), open(capture, "rb") as f:
        read_ddf_file(f, strict=True)
    (tmp_path / "bad.ddf").write_bytes(b"RIFF" + bytes(2000))
    with pytest.raises(ProtocolError, match="not a DDF"):
        read_ddf_file((tmp_path / "bad.ddf").read_bytes())


# ------------------------------------------------------------- CommandDecoder


def commands(data: bytes) -> list[object]:
    decoder = CommandDecoder()
    decoder.receive_data(data)
    return drain(decoder)


def test_valid_commands_lf_and_crlf() -> None:
    data = b"RATE 10\nrate 2.5\r\nWINDOW 2 2\r\n  gain\t20  \nPING\r\nWindow 31 0\nRATE .5\nRATE 30.\n"
    assert commands(data) == [
        SetRate(10.0), SetRate(2.5), SetWindow(2, 2), SetGain(20), Ping(), SetWindow(31, 0),
        SetRate(0.5), SetRate(30.0),
    ]  # fmt: skip


def test_blank_lines_are_ignored_and_partial_lines_wait() -> None:
    decoder = CommandDecoder()
    decoder.receive_data(b"\n\r\n   \nPI")
    assert decoder.next_event() is NEED_DATA
    assert decoder.buffered_bytes == 2
    decoder.receive_data(b"NG\n")
    assert drain(decoder) == [Ping()]


SESSION = (
    b"RATE 10\r\n\x00\x01garbage\xff\nFOO bar\nWINDOW 2\nWINDOW 40 1\nWINDOW 2 9\n"
    b"GAIN 12.5\nGAIN 41\nRATE 0.05\nRATE 31\nRATE 1e1\nRATE nan\nRATE -1\nPING now\n"
    + b"A" * 5000 + b"\nGAIN 7\n" + "WINDOW 2 2 \u00e9\n".encode() + b"RATE 1_0\nPING\n"
)


def test_garbage_and_out_of_range_values_are_bad_commands_with_reasons() -> None:
    events = commands(SESSION)
    assert events[0] == SetRate(10.0)
    assert events[-1] == Ping()
    assert SetGain(7) in events
    bad = [e for e in events if isinstance(e, BadCommand)]
    reasons = [b.reason for b in bad]
    expected = [
        "control byte 0x00 at column 1", "unknown command", "WINDOW takes 2 argument",
        "start code \"40\" out of range 1..31", "length code \"9\" out of range 0..3",
        "GAIN \"12.5\" is not a non-negative integer", "GAIN \"41\" out of range 0..40",
        "RATE \"0.05\" out of range", "RATE \"31\" out of range", "RATE \"1e1\" is not a decimal",
        "RATE \"nan\" is not a decimal", "RATE \"-1\" is not a decimal", "PING takes 0 argument",
        f"line longer than {MAX_LINE_BYTES} bytes", "non-ASCII byte 0xC3 at column 12",
        "RATE \"1_0\" is not a decimal",
    ]  # fmt: skip
    assert len(reasons) == len(expected)
    for reason, words in zip(reasons, expected):
        assert words in reason
    assert bad[1].line == b"FOO bar"
    assert bad[13].line == b"A" * MAX_LINE_BYTES
    for reason in reasons:  # every reason fits one reply line
        assert encode_reply(False, reason).startswith(b"ERR ")


def test_byte_at_a_time_equals_whole_feed() -> None:
    decoder = CommandDecoder()
    events: list[object] = []
    for k in range(len(SESSION)):
        decoder.receive_data(SESSION[k : k + 1])
        events += drain(decoder)
        assert decoder.buffered_bytes <= MAX_LINE_BYTES
    assert events == commands(SESSION)


def test_one_megabyte_without_newline_keeps_memory_bounded() -> None:
    blob = bytes(range(256)) * 4096  # 1 MiB, no LF... except one byte in each 256
    blob = blob.replace(b"\n", b"x")
    decoder = CommandDecoder()
    decoder.receive_data(blob)
    assert decoder.buffered_bytes <= MAX_LINE_BYTES and decoder.pending_lines == 1
    for k in range(0, len(blob), 4096):
        decoder.receive_data(blob[k : k + 4096])
        assert decoder.buffered_bytes <= MAX_LINE_BYTES
        assert decoder.pending_lines <= 1
    decoder.receive_data(b"still the same line\nGAIN 3\n")
    events = drain(decoder)
    assert len(events) == 2 and isinstance(events[0], BadCommand)
    assert "longer than" in events[0].reason
    assert events[1] == SetGain(3)


def test_line_of_exactly_the_bound_is_accepted() -> None:
    line = b"PING" + b" " * (MAX_LINE_BYTES - 4)
    assert commands(line + b"\n") == [Ping()]
    assert isinstance(commands(line + b" \n")[0], BadCommand)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=2000), st.lists(st.integers(1, 300), max_size=30))
def test_random_bytes_never_raise_and_chunking_does_not_matter(data: bytes, cuts: list[int]) -> None:
    decoder = CommandDecoder()
    events: list[object] = []
    pos = 0
    for n in cuts + [len(data)]:
        decoder.receive_data(data[pos : pos + n])
        pos += n
        assert decoder.buffered_bytes <= MAX_LINE_BYTES
        events += drain(decoder)
    assert events == commands(data)
    for e in events:
        assert isinstance(e, (SetRate, SetWindow, SetGain, Ping, BadCommand))


valid_commands = st.one_of(
    st.floats(0.1, 30.0).map(SetRate),
    st.builds(SetWindow, st.integers(1, 31), st.integers(0, 3)),
    st.integers(0, 40).map(SetGain),
    st.just(Ping()),
)


@settings(max_examples=100, deadline=None)
@given(st.lists(valid_commands, max_size=10))
def test_encode_command_round_trips(cmds: list[object]) -> None:
    data = b"".join(encode_command(c) for c in cmds)  # type: ignore[arg-type]
    assert commands(data) == cmds


def test_encode_command_rejects_out_of_range() -> None:
    assert encode_command(SetRate(12.5)) == b"RATE 12.5\n"
    assert encode_command(SetRate(10)) == b"RATE 10\n"
    with pytest.raises(ValueError, match="out of range"):
        encode_command(SetWindow(0, 2))


# --------------------------------------------------------------------- replies


def test_reply_lines() -> None:
    assert encode_reply(True, "RATE 10") == b"OK RATE 10\n"
    assert encode_reply(False, "unknown command") == b"ERR unknown command\n"
    assert encode_reply(True) == b"OK\n"
    long = encode_reply(False, "x" * 500)
    assert len(long) == 127 and long.endswith(b"...\n")
    with pytest.raises(ValueError):
        encode_reply(True, "two\nlines")


def test_replies_ride_in_frame_headers() -> None:
    lines = [encode_reply(True, "PING"), encode_reply(False, "y" * 120), encode_reply(False, "z" * 120)]
    first, n = pack_replies(lines)
    assert n == 2 and len(first) <= 255
    second, m = pack_replies(lines[n:])
    assert m == 1
    data = encode_frame_header(FrameHeader(replies=first))
    got = decode_replies(decode_frame_header(data).replies)
    assert got == [Reply(True, "PING"), Reply(False, "y" * 120)]
    assert decode_replies(decode_frame_header(encode_frame_header(FrameHeader())).replies) == []
    with pytest.raises(ProtocolError):
        decode_replies(b"HELLO\n")
