"""ping-protocol codec against brping (PyPI bluerobotics-ping), Blue Robotics' own implementation."""

from __future__ import annotations

import struct

import pytest

from hilsim.protocols import ping_protocol as pp
from hilsim.protocols.codec import NEED_DATA, Junk, Oversize, drain

brping = pytest.importorskip("brping", reason="bluerobotics-ping (test extra) is the independent peer")
from brping import definitions, pingmessage  # noqa: E402


def _brping_parse(data: bytes) -> list["pingmessage.PingMessage"]:
    parser = pingmessage.PingParser()
    out = []
    for b in data:
        if parser.parse_byte(b) == pingmessage.PingParser.NEW_MESSAGE:
            out.append(parser.rx_msg)
    return out


# brping 0.2.5 (PyPI) was generated from an older revision of the definitions: some field names differ
# (set_speed_of_sound.sos_mm_per_sec, distance_simple.altitude_mm, ...; names never reach the wire) and
# processor_temperature is a u32 there but a u16 in bluerobotics/ping-protocol's ping1d.json, which we follow.
BRPING_LAYOUT_DIFFERS = {1213: ("I", "H")}


def test_table_matches_brping_definitions() -> None:
    """Every id's struct format and number of fields is brping's (its definitions are generated from
    bluerobotics/ping-protocol's JSON); the one layout difference is listed above."""
    for mid, d in pp.MESSAGES.items():
        ref = definitions.payload_dict_all[mid]
        fmt = d.fmt + ("H" if d.tail == "u16_u8s" else "")
        n_fields = len(d.fields) + (2 if d.tail == "u16_u8s" else 1 if d.tail else 0)
        if mid in BRPING_LAYOUT_DIFFERS:
            assert (ref["format"], fmt) == BRPING_LAYOUT_DIFFERS[mid]
        else:
            assert ref["format"] == fmt, d.name
        assert len(ref["field_names"]) == n_fields, d.name
    for mid in (1, 2, 4, 5, 6, 1002, 1003, 1004, 1005, 1006, 1203, 1211, 1212, 1300, 1400, 1401):
        assert mid in pp.MESSAGES


def test_our_packets_parse_in_brping() -> None:
    profile = bytes(range(200))
    fields = {"distance": 1234, "confidence": 97, "transmit_duration": 100, "ping_number": 7,
              "scan_start": 0, "scan_length": 5000, "gain_setting": 3}
    stream = (pp.encode("distance", fields, src=1, dst=0)
              + pp.encode("profile", {**fields, "profile_data": profile}, src=1)
              + pp.encode("nack", {"nacked_id": 999, "nack_message": "unknown id"}, src=1)
              + pp.encode("device_information", {"device_type": 1, "device_revision": 2,
                                                 "firmware_version_major": 3, "firmware_version_minor": 25,
                                                 "firmware_version_patch": 1, "reserved": 0}, src=1)
              + pp.encode("distance_simple", {"distance": 4321, "confidence": 55}))
    msgs = _brping_parse(stream)
    assert [m.message_id for m in msgs] == [1212, 1300, 2, 4, 1211]
    assert msgs[0].distance == 1234 and msgs[0].confidence == 97 and msgs[0].scan_length == 5000
    assert msgs[0].src_device_id == 1
    assert bytes(msgs[1].profile_data) == profile and msgs[1].ping_number == 7
    assert msgs[2].nacked_id == 999 and bytes(msgs[2].nack_message) == b"unknown id"
    assert msgs[3].firmware_version_minor == 25
    assert (msgs[4].altitude_mm, msgs[4].quality) == (4321, 55)   # brping 0.2.5 names of distance_simple


def _brping_packet(mid: int, *values: object) -> bytes:
    """brping packs message ``mid`` with ``values`` in field order (its own field names)."""
    m = pingmessage.PingMessage(mid)
    for k, v in zip(m.payload_field_names, values):
        setattr(m, k, v)
    m.pack_msg_data()
    return bytes(m.msg_data)


def _legacy_request(mid: int) -> bytes:
    """A zero-length packet of the requested id, as brping.Ping1D.legacyRequest sends it."""
    head = struct.pack("<2sHHBB", b"BR", 0, mid, 0, 0)
    return head + struct.pack("<H", sum(head) & 0xFFFF)


def test_brping_packets_decode() -> None:
    stream = (_brping_packet(definitions.COMMON_GENERAL_REQUEST, 1211)
              + _brping_packet(definitions.PING1D_SET_SPEED_OF_SOUND, 1_482_000)
              + _brping_packet(definitions.PING1D_CONTINUOUS_START, 1300)
              + _brping_packet(definitions.PING1D_SET_RANGE, 100, 8000)
              + _legacy_request(1212))
    evs = list(drain(pp.PingDecoder(), stream))
    assert [type(e) for e in evs] == [pp.Message] * 5
    assert evs[0].fields == {"requested_id": 1211}
    assert evs[1].fields == {"speed_of_sound": 1_482_000} and not evs[1].is_request
    assert evs[2].name == "continuous_start" and evs[2].fields == {"id": 1300}
    assert evs[3].fields == {"scan_start": 100, "scan_length": 8000}
    assert evs[4].message_id == 1212 and evs[4].is_request


def test_bad_input_events_and_cuts() -> None:
    good = pp.encode("general_request", {"requested_id": 5})
    bad_sum = bytearray(good)
    bad_sum[-1] ^= 0xFF
    unknown = pp.encode_raw(4242, b"\x01\x02")
    short = pp.encode_raw(1002, b"\x01")           # set_speed_of_sound needs 4 bytes
    huge = b"BR" + struct.pack("<HHBB", 60000, 1, 0, 0)
    stream = b"\x00junkB" + good + bytes(bad_sum) + unknown + short + huge + good + b"B"
    whole = list(drain(pp.PingDecoder(), stream))
    kinds = [type(e).__name__ for e in whole]
    assert kinds[0] == "Junk" and "Message" in kinds
    assert [k for k in kinds if k != "Junk"] == ["Message", "BadChecksum", "UnknownMessage", "BadPayload",
                                                 "Oversize", "Message"]
    bad = [e for e in whole if isinstance(e, (pp.BadChecksum, pp.UnknownMessage, pp.BadPayload))]
    assert [e.message_id for e in bad] == [6, 4242, 1002]
    assert sum(e.n_bytes for e in whole if isinstance(e, Junk)) == len(b"\x00junkB") + len(huge) - 1
    dec = pp.PingDecoder()
    cut = [e for i in range(len(stream)) for e in drain(dec, stream[i:i + 1])]
    strip = lambda evs: [e for e in evs if not isinstance(e, Junk)]  # noqa: E731
    assert strip(cut) == strip(whole)
    assert sum(e.n_bytes for e in cut if isinstance(e, Junk)) == sum(e.n_bytes for e in whole if isinstance(e, Junk))
    assert dec.buffered_bytes == 1 and dec.next_event() is NEED_DATA   # the trailing 'B' may start a packet
    assert any(isinstance(e, Oversize) and e.length == 60000 for e in whole)


def test_register_extends_and_refuses_conflicts() -> None:
    with pytest.raises(ValueError):
        pp.register(pp.MessageDef(1211, "something_else", "I", ("x",)))
    with pytest.raises(ValueError):
        pp.register(pp.MessageDef(9999, "two_names_one_field", "II", ("x",)))
    assert 9999 not in pp.MESSAGES
