"""slcan adapter codec: the open sequences of python-can and dronecan, frames, errors, bounds."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from hilsim.protocols import slcan
from hilsim.protocols.can import CanFrame


def run(data: bytes, adapter: slcan.SlcanAdapter | None = None, one: bool = False):
    a = adapter or slcan.SlcanAdapter()
    events = []
    for chunk in ([bytes([b]) for b in data] if one else [data]):
        a.receive_data(chunk)
        for _ in range(10000):
            ev = a.next_event()
            if ev is slcan.NEED_DATA:
                break
            events.append(ev)
    return events, a.data_to_send(), a


frames = st.builds(
    lambda ext, ident, data: CanFrame(ident if ext else ident & 0x7FF, data, ext),
    st.booleans(), st.integers(0, 0x1FFFFFFF), st.binary(max_size=8))


def test_python_can_open_sequence():
    # python-can slcanBus(bitrate=1_000_000): C, S8, "" (no data bitrate), O, then O again
    events, replies, a = run(b"C\rS8\r\rO\rO\r")
    assert replies == b"\r" * 5
    assert events == [slcan.BitrateSet(1_000_000), slcan.Opened(False)] and a.is_open


def test_dronecan_open_sequence():
    events, replies, a = run(b"\rC\rS8\rO\rF\r")
    assert replies == b"\r\r\r\rF00\r" and a.is_open and a.bitrate == 1_000_000


def test_transmit_acks_and_errors():
    frame = CanFrame(0x0117, bytes.fromhex("0000C738"))
    line = slcan.format_frame(frame)
    assert line == b"T0000011740000C738\r"
    assert run(line)[1] == b"\a"                                     # closed: refused
    events, replies, a = run(b"O\r" + line + b"t1230\r")
    assert events[1:] == [slcan.Transmit(frame), slcan.Transmit(CanFrame(0x123, b"", False))]
    assert replies == b"\rZ\rz\r"
    events, replies, _ = run(b"L\r" + line)                            # listen-only: refused
    assert replies == b"\r\a"
    assert run(b"O\rS6\r")[1] == b"\r\a"                              # bitrate while open: refused


def test_reject_transmit_answers_bel():
    a = slcan.SlcanAdapter()
    a.receive_data(b"O\rt1231AA\rt1231BB\r")
    assert isinstance(a.next_event(), slcan.Opened)
    assert isinstance(a.next_event(), slcan.Transmit)
    a.reject_transmit()
    assert isinstance(a.next_event(), slcan.Transmit)  # acknowledged OK when the next event is asked for
    assert a.next_event() is slcan.NEED_DATA
    assert a.data_to_send() == b"\r\az\r"


def test_info_commands_and_unknown_ones():
    _, replies, _ = run(b"V\rN\rZ0\rZ1\rM00000000\rm00000000\rs031C\rX\rS9\r")
    assert replies == b"V1013\rNA123\r\r\a\r\r\r\a\a"


def test_frames_from_the_bus_only_while_open():
    a = slcan.SlcanAdapter()
    f = CanFrame(0x1F, b"\x01\x02", False)
    assert a.encode_frame(f) == b""
    run(b"O\r", a)
    assert a.encode_frame(f) == b"t01F20102\r"


@given(frames, st.booleans())
def test_frame_line_round_trip_upper_and_lower_case(frame, lower):
    line = slcan.format_frame(frame, lowercase=lower)
    assert slcan.parse_frame_line(line[:-1]) == frame
    events, replies, _ = run(b"O\r" + line)
    assert events[-1] == slcan.Transmit(frame) and replies.endswith(b"Z\r" if frame.is_extended else b"z\r")


def test_remote_frames():
    assert slcan.parse_frame_line(b"r1233") == CanFrame(0x123, b"", False, True, 3)
    assert slcan.format_frame(CanFrame(0x1ABCDE, b"", True, True, 8)) == b"R001ABCDE8\r"
    assert isinstance(slcan.parse_frame_line(b"r12331122"), str)


def test_bad_frame_lines():
    for line in (b"t12", b"t1239" + b"00" * 9, b"t123200", b"tXYZ0", b"T2000000000", b"t8000"):
        assert isinstance(slcan.parse_frame_line(line), str), line


@settings(max_examples=100)
@given(st.lists(frames, min_size=1, max_size=6))
def test_byte_at_a_time_equals_whole(fs):
    data = b"O\r" + b"".join(slcan.format_frame(f) for f in fs)
    assert run(data) == run(data, one=True)[:2] + (run(data)[2],)


@settings(max_examples=200)
@given(st.binary(max_size=3000))
def test_random_bytes_never_raise_and_the_line_buffer_is_bounded(data):
    events, _, a = run(b"O\r" + data)
    assert len(a._buf) <= slcan.MAX_LINE
    f = CanFrame(0x42, b"\x01", False)
    ev, replies, _ = run(b"\rO\r" + slcan.format_frame(f), a)  # a CR ends whatever was pending
    assert ev[-1] == slcan.Transmit(f) and replies.endswith(b"\rz\r")


def test_overlong_line_is_discarded_and_answered_bel():
    events, replies, a = run(b"O\r" + b"T" * 5000 + b"\rt1230\r")
    assert replies == b"\r\az\r" and a.stats.overlong == 1
    assert isinstance(events[1], slcan.BadLine) and events[2] == slcan.Transmit(CanFrame(0x123, b"", False))
