"""DroneCAN v0 codec: the RawCommand vector, the dronecan package as an independent peer, reassembly."""

from __future__ import annotations

import dronecan
import pytest
from dronecan.transport import Frame as DcFrame
from dronecan.transport import Transfer as DcTransfer
from hypothesis import given, settings
from hypothesis import strategies as st

from hilsim.protocols import dronecan as dc
from hilsim.protocols.can import CanFrame

ESC = dronecan.uavcan.equipment.esc


def to_dronecan(frames: list[CanFrame]):
    t = DcTransfer()
    t.from_frames([DcFrame(f.arbitration_id, f.data) for f in frames])
    return t


def from_dronecan(payload, source: int, tid: int, prio: int) -> list[CanFrame]:
    t = DcTransfer(payload=payload, source_node_id=source, transfer_id=tid, transfer_priority=prio)
    return [CanFrame(f.message_id, bytes(f.bytes)) for f in t.to_frames()]


def receive_all(frames: list[CanFrame], rx: dc.TransferReceiver | None = None) -> list[dc.Transfer]:
    rx = rx or dc.TransferReceiver()
    out = []
    for f in frames:
        t = rx.receive(f, 0.0)
        if t is not None:
            out.append(t)
    return out


def test_known_vector_raw_command():
    frames = dc.encode_message(dc.RawCommand((8191, -8192, 0, 4000)), source_node=10, transfer_id=0, priority=20)
    assert [(f.arbitration_id, f.data.hex()) for f in frames] == [(0x1404060A, "ff7c020000280fc0")]
    (t,) = receive_all([CanFrame(0x1404060A, bytes.fromhex("ff7c020000280fc0"))])
    assert (t.dtid, t.source_node, t.priority, t.transfer_id) == (1030, 10, 20, 0)
    assert dc.decode_message(t.dtid, t.payload) == dc.RawCommand((8191, -8192, 0, 4000))


def test_signatures_and_ids_match_dronecan():
    for cls, dtid, sig in [(ESC.RawCommand, 1030, dc.RAW_COMMAND_SIGNATURE), (ESC.Status, 1034, dc.ESC_STATUS_SIGNATURE),
                           (dronecan.uavcan.protocol.NodeStatus, 341, dc.NODE_STATUS_SIGNATURE)]:
        t = dronecan.get_dronecan_data_type(cls())
        assert (t.default_dtid, t.get_data_type_signature()) == (dtid, sig)
        assert t.base_crc == dc.crc16(sig.to_bytes(8, "little"))


def test_crc_check_value():
    assert dc.crc16(b"123456789") == 0x29B1  # CRC-16/CCITT-FALSE check value


def test_multi_frame_tail_bytes():
    frames = dc.encode_message(dc.RawCommand(tuple(range(-4, 4))), source_node=5, transfer_id=31, priority=3)
    tails = [f.data[-1] for f in frames]  # 8 x 14 bits = 14 bytes + 2 CRC = 16 -> 3 frames
    assert tails == [0x80 | 31, 0x20 | 31, 0x40 | 31]
    assert all(len(f.data) == 8 for f in frames[:-1])


@settings(max_examples=150)
@given(cmd=st.lists(st.integers(-8192, 8191), max_size=20), source=st.integers(1, 127), tid=st.integers(0, 31),
       prio=st.integers(0, 31))
def test_raw_command_both_ways_with_dronecan(cmd, source, tid, prio):
    ours = dc.encode_message(dc.RawCommand(tuple(cmd)), source, tid, prio)
    t = to_dronecan(ours)
    assert list(t.payload.cmd) == cmd and t.source_node_id == source and t.transfer_id == tid
    theirs = from_dronecan(ESC.RawCommand(cmd=cmd), source, tid, prio)
    assert theirs == ours
    (back,) = receive_all(theirs)
    assert dc.decode_message(back.dtid, back.payload) == dc.RawCommand(tuple(cmd))


finite16 = st.floats(-65504, 65504, width=16)


@settings(max_examples=150)
@given(err=st.integers(0, 2 ** 32 - 1), v=finite16, i=finite16, temp=finite16, rpm=st.integers(-(2 ** 17), 2 ** 17 - 1),
       pct=st.integers(0, 127), idx=st.integers(0, 31), tid=st.integers(0, 31))
def test_esc_status_both_ways_with_dronecan(err, v, i, temp, rpm, pct, idx, tid):
    status = dc.EscStatus(err, v, i, temp, rpm, pct, idx)
    ours = dc.encode_message(status, 20, tid)
    assert len(ours) == 3  # 14 bytes: always a multi-frame transfer
    p = to_dronecan(ours).payload
    assert (p.error_count, p.voltage, p.current, p.temperature, p.rpm, p.power_rating_pct, p.esc_index) == (
        err, v, i, temp, rpm, pct, idx)
    theirs = from_dronecan(ESC.Status(error_count=err, voltage=v, current=i, temperature=temp, rpm=rpm,
                                      power_rating_pct=pct, esc_index=idx), 20, tid, 16)
    assert theirs == ours
    (back,) = receive_all(theirs)
    assert dc.decode_message(back.dtid, back.payload) == status


def test_node_status_matches_dronecan():
    ns = dc.NodeStatus(uptime_sec=123456, health=1, mode=2, sub_mode=3, vendor_specific_status_code=0xBEEF)
    ours = dc.encode_message(ns, 42, 7, priority=24)
    assert len(ours) == 1 and ours[0].arbitration_id == (24 << 24) | (341 << 8) | 42
    p = to_dronecan(ours).payload
    assert (p.uptime_sec, p.health, p.mode, p.sub_mode, p.vendor_specific_status_code) == (123456, 1, 2, 3, 0xBEEF)
    assert dc.NodeStatus.decode(ours[0].data[:-1]) == ns


def test_status_values_saturate():
    s = dc.EscStatus.decode(dc.EscStatus(-5, 1e9, -1e9, float("inf"), 10 ** 9, 500, 3).encode())
    assert s == dc.EscStatus(0, 65504.0, -65504.0, float("inf"), 2 ** 17 - 1, 127, 3)


def test_transfer_ids_wrap_per_type_and_source():
    ids = dc.TransferIds()
    assert [ids.next(1034, 20) for _ in range(34)][-3:] == [31, 0, 1]
    assert ids.next(341, 20) == 0 and ids.next(1034, 21) == 0


def _status_frames(source=20, tid=3, idx=1):
    return dc.encode_message(dc.EscStatus(0, 16.0, 1.0, 300.0, 1000, 10, idx), source, tid)


def test_interleaved_transfers_from_two_nodes():
    a, b = _status_frames(20, 1, 1), _status_frames(21, 9, 2)
    got = receive_all([a[0], b[0], a[1], b[1], b[2], a[2]])
    assert [(t.source_node, dc.decode_message(t.dtid, t.payload).esc_index) for t in got] == [(21, 2), (20, 1)]


def test_broken_transfers_are_counted_and_dropped():
    f = _status_frames()
    rx = dc.TransferReceiver()
    assert receive_all([f[0], f[2]], rx) == [] and rx.stats.bad_frames == 1          # lost middle frame
    assert receive_all([f[1], f[2]], rx) == []                                      # start missed
    bad = CanFrame(f[1].arbitration_id, f[1].data[:-1] + bytes([f[1].data[-1] ^ 0x20]))
    assert receive_all([f[0], bad, f[2]], rx) == []                                 # toggle wrong
    corrupt = CanFrame(f[1].arbitration_id, bytes([f[1].data[0] ^ 1]) + f[1].data[1:])
    assert receive_all([f[0], corrupt, f[2]], rx) == [] and rx.stats.crc_errors == 1
    assert len(receive_all(f, rx)) == 1                                              # and it recovers


def test_sessions_and_payloads_are_bounded():
    rx = dc.TransferReceiver(max_sessions=4, max_payload=16)
    for node in range(1, 50):
        rx.receive(_status_frames(node)[0], 0.0)
    assert rx.open_sessions == 4 and rx.stats.evicted == 45
    # a transfer that never ends is cut at max_payload
    ident = dc.message_id(16, 1030, 7)
    rx.receive(CanFrame(ident, bytes(7) + b"\x80"), 0.0)
    toggle = 1
    for _ in range(10):
        rx.receive(CanFrame(ident, bytes(7) + bytes([toggle << 5])), 0.0)
        toggle ^= 1
    assert rx.stats.too_long == 1


def test_stale_sessions_time_out():
    f = _status_frames()
    rx = dc.TransferReceiver(timeout=2.0)
    rx.receive(f[0], 0.0)
    assert rx.receive(f[1], 5.0) is None and rx.stats.timeouts == 1
    rx.receive(f[0], 10.0), rx.receive(f[1], 10.1)
    assert rx.receive(f[2], 10.2) is not None


def test_ignored_frames():
    rx = dc.TransferReceiver()
    for f in [CanFrame(0x123, b"\xc0", is_extended=False), CanFrame((16 << 24) | (1030 << 8) | 0x80 | 5, b"\xc0"),
              CanFrame((16 << 24) | (1030 << 8), b"\xc0"), CanFrame(dc.message_id(16, 999, 3), b"\xc0")]:
        assert rx.receive(f, 0.0) is None
    assert rx.stats.ignored == 4


@settings(max_examples=300)
@given(st.lists(st.tuples(st.integers(0, 0x1FFFFFFF), st.binary(max_size=8)), max_size=40))
def test_random_frames_never_raise(frames):
    rx = dc.TransferReceiver(max_sessions=8)
    for ident, data in frames:
        t = rx.receive(CanFrame(ident, data), 0.0)
        if t is not None:
            dc.decode_message(t.dtid, t.payload)
    assert rx.open_sessions <= 8


@given(st.binary(max_size=60))
def test_random_payloads_decode_or_give_none(payload):
    for dtid in (1030, 1034, 341, 5):
        dc.decode_message(dtid, payload)


def test_raw_command_from_fractions():
    rc = dc.raw_command_values([1.0, -1.0, 0.5, 2.0])
    assert rc.cmd == (8191, -8191, 4096, 8191)
    assert rc.normalized(0) == 1.0 and rc.normalized(4) is None
    assert dc.RawCommand((-8192,)).normalized(0) == -1.0
    with pytest.raises(ValueError):
        dc.RawCommand((9000,)).encode()
