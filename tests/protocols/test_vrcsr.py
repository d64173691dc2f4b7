"""VRCSR codec: packets built independently with struct + zlib, round trips, resync, bounds."""

from __future__ import annotations

import struct
import zlib

from hypothesis import given, settings
from hypothesis import strategies as st

from hilsim.protocols import vrcsr


def independent_request(powers, reply_node, flags=2, node=0x81) -> bytes:
    """The request as videoray/Thruster's example builds it (little-endian, zlib CRC32)."""
    header = struct.pack("<HBBBB", 0x5FF5, node, flags, 0xF0, 2 + 4 * len(powers))
    payload = struct.pack("<BB", 0xAA, reply_node) + b"".join(struct.pack("<f", p) for p in powers)
    return header + struct.pack("<I", zlib.crc32(header)) + payload + struct.pack("<I", zlib.crc32(payload))


def drain(dec):
    out = []
    for _ in range(10000):
        ev = dec.next_event()
        if ev is vrcsr.NEED_DATA:
            return out
        out.append(ev)
    raise AssertionError("decoder did not settle")


def feed(data: bytes, one: bool = False, responses: bool = False):
    dec = vrcsr.PacketDecoder(responses=responses)
    out = []
    for chunk in ([bytes([b]) for b in data] if one else [data]):
        dec.receive_data(chunk)
        out += drain(dec)
    return out, dec


def test_request_bytes_match_the_independent_construction():
    powers = [0.5, -0.25, 0.0, 1.0]
    wire = independent_request(powers, reply_node=3)
    assert wire[:2] == b"\xf5\x5f" and wire[2:6] == bytes([0x81, 0x02, 0xF0, 18])
    assert vrcsr.propulsion_request(powers, reply_node_id=3) == wire
    (pkt,), _ = feed(wire)
    assert (pkt.node_id, pkt.flags, pkt.address) == (0x81, 2, 0xF0)
    assert vrcsr.PropulsionCommand.decode(pkt.payload) == vrcsr.PropulsionCommand(3, (0.5, -0.25, 0.0, 1.0))


def test_standard_response_layout():
    body = vrcsr.StandardResponse(2, 1234.5, 15.9, 2.5, 21.0, 0).payload()
    wire = vrcsr.response(3, 0x02, 0xF0, body)
    # the example client unpacks exactly this ('=HBBBB I BffffB I')
    f = struct.unpack("=HBBBBIBffffBI", wire)
    assert f[0] == 0x0FF0 and f[1:5] == (3, 2, 0xF0, 18) and f[6:12] == (2, 1234.5, 15.899999618530273, 2.5, 21.0, 0)
    assert f[5] == zlib.crc32(wire[:6]) and f[12] == zlib.crc32(body)
    (pkt,), _ = feed(wire, responses=True)
    assert vrcsr.StandardResponse.decode(pkt.payload) == vrcsr.StandardResponse(2, 1234.5, f[8], 2.5, 21.0, 0)


def test_requests_and_responses_do_not_mix():
    assert feed(vrcsr.response(1, 2, 0xF0, b"x"))[0] == []
    assert feed(independent_request([0.1], 1), responses=True)[0] == []


@given(node=st.integers(0, 255), flags=st.integers(0, 255), addr=st.integers(0, 255), payload=st.binary(max_size=255))
def test_packet_round_trip_whole_and_byte_at_a_time(node, flags, addr, payload):
    pkt = vrcsr.Packet(node, flags, addr, payload)
    wire = pkt.encode()
    assert feed(wire)[0] == [pkt]
    assert feed(wire, one=True)[0] == [pkt]


@settings(max_examples=150)
@given(st.lists(st.tuples(st.binary(max_size=30), st.lists(st.floats(-1, 1, width=32), max_size=8)),
                min_size=1, max_size=5), st.binary(max_size=30))
def test_garbage_between_packets(parts, tail):
    wire = b"".join(g + independent_request(p, 1) for g, p in parts) + tail
    for one in (False, True):
        got, dec = feed(wire, one)
        assert [vrcsr.PropulsionCommand.decode(p.payload).powers for p in got][:len(parts)] == [
            tuple(p) for _, p in parts]
        assert dec.buffered_bytes <= 6 + 4 + 255 + 4


def test_bad_crcs_and_truncation_are_counted():
    good = independent_request([0.5], 2)
    bad_header = bytearray(good)
    bad_header[3] ^= 1
    bad_payload = bytearray(good)
    bad_payload[12] ^= 1
    got, dec = feed(bytes(bad_header) + bytes(bad_payload) + good[:-3] + good)
    assert len(got) == 1 and vrcsr.PropulsionCommand.decode(got[0].payload).powers == (0.5,)
    assert dec.stats.header_crc_errors >= 1 and dec.stats.payload_crc_errors >= 1


@settings(max_examples=200)
@given(st.binary(max_size=1500))
def test_random_bytes_never_raise_then_a_valid_packet_decodes(data):
    good = independent_request([0.75, -0.75], 9)
    got, dec = feed(data + good)
    assert got and got[-1].payload == good[10:-4]
    assert dec.buffered_bytes <= 269


@given(st.binary(max_size=40))
def test_random_payloads_never_raise(payload):
    vrcsr.PropulsionCommand.decode(payload)
    vrcsr.StandardResponse.decode(payload)


def test_propulsion_payload_rules():
    assert vrcsr.PropulsionCommand.decode(b"\xaa\x01" + bytes(3)) is None      # not whole floats
    assert vrcsr.PropulsionCommand.decode(b"\xab\x01") is None                 # not the propulsion command
    assert vrcsr.PropulsionCommand(1, (2.0, -3.0)).payload()[2:] == struct.pack("<ff", 1.0, -1.0)  # clamped


@settings(max_examples=200)
@given(st.lists(st.floats(-1, 1, width=32), max_size=8), st.integers(0, 200), st.binary(min_size=1, max_size=4),
       st.integers(0, 40))
def test_mutated_and_truncated_packets_never_raise_and_resync(powers, index, mutation, cut):
    wire = bytearray(independent_request(powers, 4))
    i = index % len(wire)
    wire[i:i + len(mutation)] = mutation
    wire = wire[:max(1, len(wire) - cut)]
    good = independent_request([0.25], 5)
    for one in (False, True):
        got, _ = feed(bytes(wire) + good, one)
        if got[-1].payload == good[:6] and wire[5:6] == b"\x06":
            # inherent to VRCSR framing: a cut packet whose header announces a 6-byte payload
            # takes the next packet's 6-byte header as that payload, and the next 4 bytes (that
            # header's own CRC32 of the same 6 bytes) validate it -- a real device does the same
            continue
        assert got[-1].payload == good[10:-4]
