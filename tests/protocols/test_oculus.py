"""Oculus codec: the real liboculus capture, struct offsets from the reference, round trips,
and a stream reader that survives whatever a peer sends (reference/sonar-protocols.md section 3)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilsim.protocols import oculus as oc

DATA = Path(__file__).resolve().parents[1] / "data"
CAPTURE = (DATA / "oculus_one_ping_8bit.raw").read_bytes()


# ------------------------------------------------------------- real capture


def test_capture_decodes_as_the_reference_describes():
    p = oc.decode_message(CAPTURE)
    assert isinstance(p, oc.PingResult), p
    assert (p.n_beams, p.n_ranges) == (256, 703)
    assert p.fire.version == 0 and p.fire.flags == 0x19 and p.src_device_id == 7892
    assert p.image.dtype == np.uint8 and p.image_offset == 2048 and p.gains is None
    # bearings span +-30 deg, ascending
    assert p.bearings[0] == -3000 and p.bearings[-1] == 3000
    assert np.all(np.diff(p.bearings) > 0)
    assert p.fire.range == pytest.approx(2.0)
    assert p.n_ranges * p.range_resolution == pytest.approx(p.fire.range, rel=1e-3)
    # the size invariant, read with struct at the reference's offsets
    payload = struct.unpack_from("<I", CAPTURE, 10)[0]
    ioff, isize, msize = struct.unpack_from("<III", CAPTURE, 110)
    assert 16 + payload == ioff + isize == msize == len(CAPTURE)
    # the image bytes are the capture's, row by row
    assert p.image.tobytes() == CAPTURE[2048:2048 + 703 * 256]


def test_capture_round_trips_through_our_encoder():
    p = oc.decode_message(CAPTURE)
    assert isinstance(p, oc.PingResult)
    again = oc.decode_message(oc.encode_ping_result(p))
    assert isinstance(again, oc.PingResult)
    np.testing.assert_array_equal(again.image, p.image)
    np.testing.assert_array_equal(again.bearings, p.bearings)
    assert again.fire == p.fire and again.range_resolution == p.range_resolution


def test_capture_streamed_byte_by_byte_after_junk():
    r = oc.OculusReader(oc.MAX_CLIENT_PAYLOAD)
    events = []
    for b in b"\x00\x53garbage\x53" + CAPTURE[:4000]:
        r.receive_data(bytes([b]))
        events += r.events()
    r.receive_data(CAPTURE[4000:])
    events += r.events()
    pings = [e for e in events if isinstance(e, oc.PingResult)]
    assert len(pings) == 1 and pings[0].n_ranges == 703
    assert sum(e.n_bytes for e in events if isinstance(e, oc.Junk)) == 10


# -------------------------------------------------- layouts at reference offsets


def test_fire_v1_and_v2_layouts():
    f1 = oc.Fire(master_mode=1, ping_rate=3, network_speed=255, gamma=127, flags=0x0B, range=12.5,
                 gain=60.0, speed_of_sound=1480.0, salinity=35.0, version=1, src_device_id=5)
    b1 = oc.encode_fire(f1)
    assert len(b1) == 53 and b1[:2] == b"\x53\x4f"
    assert struct.unpack_from("<HHHHHIH", b1, 0) == (0x4F53, 5, 0, 0x15, 1, 37, 0)
    assert b1[16:21] == bytes([1, 3, 255, 127, 0x0B])
    assert struct.unpack_from("<4d", b1, 21) == (12.5, 60.0, 1480.0, 35.0)
    f2 = oc.Fire(flags=0x4F, range=30.0, gain=10.0, version=2, ext_flags=0x200)
    b2 = oc.encode_fire(f2)
    assert len(b2) == 89 and struct.unpack_from("<H", b2, 8)[0] == 2
    assert struct.unpack_from("<I", b2, 53)[0] == 0x200 and b2[57:89] == bytes(32)
    assert oc.decode_message(b1) == f1 and oc.decode_message(b2) == f2
    assert f2.data_size == oc.DATA_32BIT and f2.n_beams_requested == 512 and f2.send_gain


def _ping(version: int, flags: int, dtype: type, gains: bool, ext: int = 0) -> oc.PingResult:
    rng = np.random.default_rng(version * 100 + flags)
    img = rng.integers(0, np.iinfo(dtype).max, (7, 5), dtype=dtype, endpoint=True)
    fire = oc.Fire(flags=flags, version=version, ext_flags=ext, range=3.5)
    return oc.PingResult(fire=fire, image=img, bearings=np.array([-200, -100, 0, 100, 200], np.int16),
                         range_resolution=0.5, gains=np.arange(7, dtype=np.float32) + 0.5 if gains else None,
                         ping_id=42, frequency=1.2e6, speed_of_sound_used=1490.0, ping_start_time=12.0)


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("bits16", [False, True])
@pytest.mark.parametrize("gains", [False, True])
def test_ping_result_layout_and_round_trip(version, bits16, gains):
    flags = 0x09 | (0x02 if bits16 else 0) | (0x04 if gains else 0)
    p = _ping(version, flags, np.uint16 if bits16 else np.uint8, gains)
    b = oc.encode_ping_result(p)
    size = 202 if version == 2 else 122
    nr, nb, width = 7, 5, 2 if bits16 else 1
    if version == 2:
        ds, rres, nranges, nbeams = struct.unpack_from("<BdHH", b, 161)
        ioff, isize, msize = struct.unpack_from("<III", b, 190)
        assert struct.unpack_from("<I", b, 89)[0] == 42 and struct.unpack_from("<d", b, 97)[0] == 1.2e6
        assert struct.unpack_from("<d", b, 145)[0] == 1490.0 and struct.unpack_from("<d", b, 153)[0] == 12.0
    else:
        ds, rres, nranges, nbeams = struct.unpack_from("<BdHH", b, 97)
        ioff, isize, msize = struct.unpack_from("<III", b, 110)
        assert struct.unpack_from("<I", b, 53)[0] == 42 and struct.unpack_from("<d", b, 85)[0] == 1490.0
    assert (ds, rres, nranges, nbeams) == (1 if bits16 else 0, 0.5, nr, nb)
    assert struct.unpack_from("<5h", b, size) == (-200, -100, 0, 100, 200)
    assert ioff == size + 2 * nb
    assert 16 + struct.unpack_from("<I", b, 10)[0] == ioff + isize == msize == len(b)
    row = nb * width + (4 if gains else 0)
    assert isize == nr * row
    first = b[ioff:ioff + row]
    if gains:
        assert struct.unpack_from("<f", first, 0)[0] == 0.5
        first = first[4:]
    assert first == p.image[0].astype(p.image.dtype.newbyteorder("<")).tobytes()
    assert oc.decode_message(b) == p.__class__(**{**p.__dict__, "image_offset": ioff, "image_size": isize,
                                                  "message_size": msize})


def test_32_bit_v2_and_mismatched_dtype():
    p = _ping(2, 0x09, np.uint32, False, ext=0x200)
    q = oc.decode_message(oc.encode_ping_result(p))
    assert isinstance(q, oc.PingResult) and q.image.dtype == np.uint32
    np.testing.assert_array_equal(q.image, p.image)
    with pytest.raises(ValueError):
        oc.encode_ping_result(_ping(2, 0x09, np.uint16, False))  # 16-bit image, 8-bit fire


def test_status_layout():
    s = oc.Status(device_id=77, part_number=1032, status=3, ip="127.0.0.1", ip_mask="255.0.0.0",
                  connected_ip="127.0.0.2", mac=b"\x01\x02\x03\x04\x05\x06", temperatures=tuple(range(8)),
                  pressure=1.5, version_info=(1, 2, 3, 4, 5, 6), src_device_id=77)
    b = oc.encode_status(s)
    assert len(b) == 142 and b[:2] == b"\x53\x4f"
    assert struct.unpack_from("<IHHI", b, 16) == (77, 1, 1032, 3)
    assert struct.unpack_from("<6I", b, 28) == (1, 2, 3, 4, 5, 6)
    assert b[52:56] == bytes([127, 0, 0, 1]) and b[56:60] == bytes([255, 0, 0, 0])
    assert b[60:64] == bytes([127, 0, 0, 2]) and b[64:70] == bytes(range(1, 7))
    assert struct.unpack_from("<d", b, 134)[0] == 1.5
    assert oc.decode_status(b) == s and s.main_run
    assert isinstance(oc.decode_status(b[:-1]), oc.BadMessage)
    assert isinstance(oc.decode_status(b"\x00" * 142), oc.BadMessage)


def test_beam_halving_and_widening():
    img = np.array([[0, 2, 255, 255, 10, 11]], np.uint8)
    merged, az = oc.halve_beams(img, [0.0, 2.0, 4.0, 6.0, 8.0, 10.0])
    assert merged.tolist() == [[1, 255, 11]] and az.tolist() == [1.0, 5.0, 9.0]
    assert oc.widen_samples(img, oc.DATA_16BIT).max() == 65535
    assert oc.bearings_from_azimuths(np.radians([-30.0, 0.0, 0.3])).tolist() == [-3000, 0, 30]


# ------------------------------------------------------------------ robustness

FIRE = oc.encode_fire(oc.Fire(version=2))
DUMMY = oc.encode_message(oc.MSG_DUMMY)


def _drain(r: oc.OculusReader) -> list:
    out = []
    for _ in range(100_000):
        ev = r.next_event()
        if ev is oc.NEED_DATA:
            return out
        out.append(ev)
    raise AssertionError("reader did not reach NEED_DATA")


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=400), st.integers(1, 64))
def test_random_bytes_then_a_valid_fire(junk, chunk):
    r = oc.OculusReader()
    stream = junk + FIRE
    events = []
    for i in range(0, len(stream), chunk):
        r.receive_data(stream[i:i + chunk])
        events += _drain(r)
    assert events and events[-1] == oc.decode_message(FIRE)
    assert r.buffered_bytes <= 16 + r.max_payload


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_mutations_and_truncations_never_raise(data):
    msg = bytearray(data.draw(st.sampled_from([FIRE, DUMMY, oc.encode_fire(oc.Fire(version=1)), CAPTURE[:300]])))
    for _ in range(data.draw(st.integers(0, 8))):
        i = data.draw(st.integers(0, len(msg) - 1))
        msg[i] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(msg)))
    for blob in (bytes(msg), bytes(msg[:cut])):
        assert isinstance(oc.decode_message(blob), (oc.Fire, oc.PingResult, oc.OtherMessage, oc.BadMessage))
        assert isinstance(oc.decode_status(blob), (oc.Status, oc.BadMessage))
        # a false start swallows at most 16 + max_payload bytes; then the reader is in step
        r = oc.OculusReader()
        r.receive_data(blob + FIRE * (2 + (16 + r.max_payload) // len(FIRE)))
        assert _drain(r)[-1] == oc.decode_message(FIRE)
        assert r.buffered_bytes == 0


def test_oversize_length_allocates_nothing_and_resyncs():
    huge = struct.pack("<HHHHHIH", 0x4F53, 0, 0, 0x15, 2, 0xFFFFFFFF, 0)
    r = oc.OculusReader()
    r.receive_data(huge)
    events = _drain(r)
    assert isinstance(events[0], oc.Oversize) and events[0].header.payload_size == 0xFFFFFFFF
    assert r.buffered_bytes < 16
    r.receive_data(FIRE)
    assert _drain(r)[-1] == oc.decode_message(FIRE)


def test_a_fire_of_the_wrong_size_is_a_bad_message():
    bad = oc.encode_message(oc.MSG_FIRE, bytes(30), version=2)
    r = oc.OculusReader()
    r.receive_data(bad + DUMMY + FIRE + FIRE)
    kinds = [type(e).__name__ for e in _drain(r)]
    assert kinds == ["BadMessage", "Junk", "OtherMessage", "Fire", "Fire"]
    assert r.stats.bad == 1 and r.stats.messages == 3
