"""socketcand server codec: the handshake python-can expects, frames both ways with python-can's
own converters as the independent peer, byte-at-a-time, garbage, bounds."""

from __future__ import annotations

import can
from can.interfaces.socketcand.socketcand import (
    convert_ascii_message_to_can_message,
    convert_can_message_to_ascii_message,
)
from hypothesis import given, settings
from hypothesis import strategies as st

from hilsim.protocols import socketcand as sc
from hilsim.protocols.can import CanFrame

frames = st.builds(
    lambda ext, ident, data: CanFrame(ident if ext else ident & 0x7FF, data, ext),
    st.booleans(), st.integers(0, 0x1FFFFFFF), st.binary(max_size=8))


def run(data: bytes, server: sc.SocketcandServer | None = None, one: bool = False):
    s = server or sc.SocketcandServer()
    events, replies = [], []
    for chunk in ([bytes([b]) for b in data] if one else [data]):
        s.receive_data(chunk)
        for _ in range(10000):
            ev = s.next_event()
            if ev is sc.NEED_DATA:
                break
            events.append(ev)
        replies += s.replies()
    return events, replies, s


def test_handshake_as_python_can_does_it():
    s = sc.SocketcandServer(frozenset({"can0"}))
    assert s.greeting() == b"< hi >"
    events, replies, _ = run(b"< open can0 >", s)
    assert events == [sc.BusOpened("can0")] and replies == [b"< ok >"]
    events, replies, _ = run(b"< rawmode >", s)
    assert events == [sc.RawModeEntered()] and replies == [b"< ok >"] and s.mode is sc.Mode.RAW


def test_wrong_bus_and_commands_before_open():
    events, replies, s = run(b"< open vcan9 >< send 123 0 >< echo >")
    assert [type(e) for e in events] == [sc.BadMessage, sc.BadMessage] and s.mode is sc.Mode.NO_BUS
    assert replies[0].startswith(b"< error ") and replies[2] == b"< echo >"


def test_frames_go_to_raw_clients_only():
    s = sc.SocketcandServer()
    f = CanFrame(0x123, b"\x01\x02", False)
    assert s.encode_frame(f, 1.5) == b""
    run(b"< open can0 >< rawmode >", s)
    assert s.encode_frame(f, 1.5) == b"< frame 123 1.500000 0102 >"
    run(b"< bcmmode >", s)
    assert s.encode_frame(f, 1.5) == b""


def test_empty_frame_format_parses_in_python_can():
    text = sc.format_frame(CanFrame(0x123, b"", False), 12.25)
    assert text == b"< frame 123 12.250000  >"
    msg = convert_ascii_message_to_can_message(text.decode())
    assert msg.arbitration_id == 0x123 and not msg.is_extended_id and msg.data == bytearray()


@settings(max_examples=200)
@given(frames, st.floats(0, 2e9))
def test_server_frames_parse_in_python_can(frame, ts):
    msg = convert_ascii_message_to_can_message(sc.format_frame(frame, ts).decode())
    assert (msg.arbitration_id, bytes(msg.data), msg.is_extended_id) == (
        frame.arbitration_id, frame.data, frame.is_extended)
    assert abs(msg.timestamp - ts) <= 1e-6 + 1e-15 * ts
    assert sc.parse_frame_message(sc.format_frame(frame, ts)) == frame


@settings(max_examples=200)
@given(frames)
def test_python_can_sends_parse_here(frame):
    text = convert_can_message_to_ascii_message(can.Message(
        arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=frame.is_extended))
    assert text.encode() == sc.format_send(frame)
    events, replies, _ = run(b"< open can0 >< rawmode >" + text.encode())
    assert events[-1] == sc.SendFrame(frame) and replies == [b"< ok >", b"< ok >"]


@settings(max_examples=100)
@given(st.lists(frames, max_size=6), st.lists(st.sampled_from([b" ", b"\n", b"junk", b">", b"x>y"]), max_size=6))
def test_byte_at_a_time_and_garbage_between_messages(fs, junk):
    parts = [b"< open can0 >", b"< rawmode >"] + [sc.format_send(f) for f in fs]
    data = b"".join(p + (junk[i % len(junk)] if junk else b"") for i, p in enumerate(parts))
    whole, one = run(data), run(data, one=True)
    assert whole[:2] == one[:2]
    assert [e.frame for e in whole[0] if isinstance(e, sc.SendFrame)] == fs


def test_overlong_message_is_dropped_and_bounded():
    s = sc.SocketcandServer()
    events, replies, _ = run(b"< open can0 >< rawmode >< " + b"x" * 100000, s)
    assert len(s._buf) <= sc.MAX_MESSAGE and isinstance(events[-1], sc.BadMessage)
    assert replies[-1] == b"< error message too long >"
    events, replies, _ = run(b" >< send 123 1 ff >", s)
    assert events == [sc.SendFrame(CanFrame(0x123, b"\xff", False))]


@settings(max_examples=200)
@given(st.binary(max_size=3000))
def test_random_bytes_never_raise(data):
    events, replies, s = run(b"< open can0 >< rawmode >" + data)
    assert len(s._buf) <= sc.MAX_MESSAGE
    ev, _, _ = run(b">< send 00000117 4 0 0 c7 38 >", s)
    assert ev[-1] == sc.SendFrame(CanFrame(0x117, bytes.fromhex("0000c738")))


def test_bad_sends():
    for text in (b"< send 123 >", b"< send 123 2 1 >", b"< send 800 0 >", b"< send zz 0 >", b"< send 123 9 " +
                 b"1 " * 9 + b">", b"< frob >"):
        events, replies, _ = run(b"< open can0 >< rawmode >" + text)
        assert isinstance(events[-1], sc.BadMessage), text
        assert replies[-1].startswith(b"< error ")
