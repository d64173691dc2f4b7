"""Every decoder of peer input: one test class re-run for each (the table in tests/fuzz/targets.py).

Properties, for each target:

1. random bytes, in random chunks, never raise (the DDF reader's documented
   ProtocolError is an event), and the bytes retained stay within the bound
   (both checked after every chunk, in every property, with every event's
   fields fitting their annotations);
2. valid messages with mutated bytes: the same, then a valid message is decoded;
3. truncated messages: the same, and a truncated message followed by a full
   valid one still yields the valid one (where the protocol can resynchronise;
   the targets that cannot are skipped with the reason);
4. a head claiming a huge length (4 GB, or the field's largest value), then
   128 KiB that keep coming: retained bytes within the bound, tracemalloc
   peak under 1 MiB, and afterwards a valid message is decoded;
5. a valid stream fed byte at a time, in random chunks and whole gives the
   same events, and every message is recognised in order;
6. garbage then a valid message: the valid message is decoded;
7. any bytes (garbage with valid messages in it) give the same events whole,
   byte at a time and in chunks, except where the table says why not.

``HILSIM_ROBUST_PROFILE=deep`` runs 20 times more examples (not for CI).
The same targets run under atheris: tests/fuzz/README.md.
"""

from __future__ import annotations

import os
import tracemalloc
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hilsim.protocols import aris
from tests.fuzz.targets import TARGETS, Reply, Target

settings.register_profile(
    "hilsim-robust-ci", max_examples=100, deadline=None, print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.register_profile("hilsim-robust-deep", settings.get_profile("hilsim-robust-ci"), max_examples=2000)
PROFILE = settings.get_profile("hilsim-robust-" + os.environ.get("HILSIM_ROBUST_PROFILE", "ci"))

NAMES = list(TARGETS)
MEMORY_LIMIT = 1 << 20  # [bytes] tracemalloc peak while a huge length claim is fed
FILLER_CHUNKS = 32      # x 4 KiB after the claim


def skip_unless(t: Target, why_not: str) -> None:
    """Skip, with the table's reason, where the target cannot have the property."""
    reason = getattr(t, why_not)
    if reason:
        pytest.skip(f"{t.name}: {reason}")


chunk_sizes = st.lists(st.integers(1, 300), max_size=6)


def pick(t: Target, data: st.DataObject) -> int:
    return data.draw(st.integers(0, len(t.samples()) - 1), label="sample")


def in_order(t: Target, events: list[Any], indices: list[int]) -> bool:
    it = iter(events)
    return all(any(t.samples()[i].expect(e) for e in it) for i in indices)


@pytest.mark.parametrize("name", NAMES)
class TestEveryDecoder:
    """The properties of the module docstring; a target that cannot have one is skipped with its reason."""

    @PROFILE
    @given(data=st.data(), chunks=chunk_sizes, with_prefix=st.booleans())
    def test_random_bytes_never_raise(self, name: str, data: st.DataObject, chunks: list[int],
                                      with_prefix: bool) -> None:
        t = TARGETS[name]
        raw = data.draw(st.binary(max_size=t.random_size), label="bytes")
        d = t.make()
        t.run(d, (t.prefix if with_prefix else b"") + raw, chunks)
        t.finish(d)
        assert t.buffered(d) <= t.bound

    @PROFILE
    @given(data=st.data(), chunks=chunk_sizes,
           mutations=st.lists(st.tuples(st.integers(0, 1 << 20), st.integers(0, 255)), min_size=1, max_size=8))
    def test_mutated_messages_never_raise(self, name: str, data: st.DataObject, chunks: list[int],
                                          mutations: list[tuple[int, int]]) -> None:
        t = TARGETS[name]
        picks = data.draw(st.lists(st.integers(0, len(t.samples()) - 1), min_size=1, max_size=4), label="picks")
        wire = bytearray(t.prefix + b"".join(t.samples()[i].wire for i in picks))
        for pos, byte in mutations:
            wire[pos % len(wire)] = byte
        d = t.make()
        t.run(d, bytes(wire), chunks)
        if t.no_resync is None:
            t.expect_resync(d, pick(t, data), chunks)
        else:
            t.finish(d)

    @PROFILE
    @given(data=st.data(), k=st.integers(0, 1 << 16), chunks=chunk_sizes)
    def test_truncations_never_raise(self, name: str, data: st.DataObject, k: int, chunks: list[int]) -> None:
        t = TARGETS[name]
        wire = t.samples()[pick(t, data)].wire
        d = t.make()
        t.run(d, t.prefix + t.cut(wire, k % len(wire)), chunks)
        t.finish(d)
        assert t.buffered(d) <= t.bound

    def test_oversize_lengths_allocate_nothing(self, name: str) -> None:
        t = TARGETS[name]
        for head, fill in t.oversize():
            d = t.make()
            tracemalloc.start()
            try:
                base = tracemalloc.get_traced_memory()[0]
                t.run(d, head)
                for _ in range(FILLER_CHUNKS):
                    t.run(d, fill)  # events dropped: only what the decoder keeps counts
                peak = tracemalloc.get_traced_memory()[1] - base
            finally:
                tracemalloc.stop()
            assert peak < MEMORY_LIMIT, f"{name}: {peak} bytes allocated for {head[:16].hex()}..."
            assert t.buffered(d) <= t.bound
            if t.no_resync is None:
                t.expect_resync(d, 0, [])

    @PROFILE
    @given(data=st.data(), chunks=chunk_sizes)
    def test_byte_at_a_time_equals_whole(self, name: str, data: st.DataObject, chunks: list[int]) -> None:
        t = TARGETS[name]
        n = len(t.samples())
        indices = sorted(data.draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=4, unique=True),
                                   label="messages"))
        bursts = [t.samples()[i].wire for i in indices]
        if t.pipelined:
            bursts = [b"".join(bursts)]

        def feed(sizes: list[int]) -> list[Any]:
            d = t.make()
            out = t.run(d, t.prefix, sizes)
            for burst in bursts:
                out += t.run(d, burst, sizes)
                if t.gap is not None:
                    out += t.gap(d)
            return out + t.finish(d)

        whole = feed([])
        assert in_order(t, whole, indices), f"{name}: not every message recognised: {whole[:8]}"
        assert t.normalize(feed([1])) == t.normalize(whole)
        assert t.normalize(feed(chunks)) == t.normalize(whole)


    def test_any_bytes_give_the_same_events_however_cut(self, name: str) -> None:
        """Garbage with valid messages in it, whole, byte at a time and in chunks (h11's rule, for any input)."""
        t = TARGETS[name]
        skip_unless(t, "chunking_matters")
        samples = t.samples()

        @PROFILE
        @given(data=st.data(), chunk=st.integers(1, 40), with_prefix=st.booleans())
        def prop(data: st.DataObject, chunk: int, with_prefix: bool) -> None:
            garbage = data.draw(st.binary(max_size=t.random_size), label="garbage")
            picks = data.draw(st.lists(st.integers(0, len(samples) - 1), max_size=3), label="messages")
            at = data.draw(st.integers(0, len(garbage)), label="at")
            stream = ((t.prefix if with_prefix else b"") + garbage[:at] + b"".join(samples[i].wire for i in picks)
                      + garbage[at:])
            results = []
            for chunks in ([], [1], [chunk]):
                d = t.make()
                results.append(t.normalize(t.run(d, stream, chunks) + t.finish(d)))
            assert results[1] == results[0] and results[2] == results[0]

        prop()

    def test_truncated_then_valid_is_decoded(self, name: str) -> None:
        t = TARGETS[name]
        skip_unless(t, "no_resync_after_truncation")

        @PROFILE
        @given(data=st.data(), k=st.integers(0, 1 << 16), chunks=chunk_sizes)
        def prop(data: st.DataObject, k: int, chunks: list[int]) -> None:
            first = pick(t, data)
            wire = t.samples()[first].wire
            d = t.make()
            t.run(d, t.prefix + t.cut(wire, k % len(wire)), chunks)
            t.expect_resync(d, max(first, pick(t, data)), chunks)  # a later sample: frame indexes only grow

        prop()

    def test_garbage_then_valid_is_decoded(self, name: str) -> None:
        t = TARGETS[name]
        skip_unless(t, "no_resync")

        @PROFILE
        @given(data=st.data(), chunks=chunk_sizes, with_prefix=st.booleans())
        def prop(data: st.DataObject, chunks: list[int], with_prefix: bool) -> None:
            garbage = data.draw(st.binary(max_size=t.random_size), label="garbage")
            d = t.make()
            t.run(d, (t.prefix if with_prefix else b"") + t.garbage(garbage), chunks)
            t.expect_resync(d, pick(t, data), chunks)

        prop()


def test_every_decoder_has_a_target() -> None:
    """The issue's list, once: DDF (stream and commands), Oculus, ARIS (commands, frames), socketcand,
    slcan, VESC CAN and UART, DroneCAN, VRCSR, Modbus TCP and RTU requests."""
    assert set(TARGETS) == {"ddf-stream", "ddf-commands", "oculus", "aris-commands", "aris-frames", "socketcand",
                            "slcan", "vesc-uart", "vrcsr", "vesc-can", "dronecan", "modbus-tcp", "modbus-rtu",
                            "keller-bus", "witmotion-commands", "witmotion-packets",  # issue #17
                            "dvl-json", "dvl-serial", "nmea", "ping-protocol",         # the navigation suite
                            "ping360"}                                                 # issue #20
    for t in TARGETS.values():
        assert t.samples() and t.oversize() and t.bound > 0 and t.measure


# -- regressions: bugs the robustness work found ---------------------------------------------


def _frame_part(offset: int, data: bytes, total: int, header: bool = False) -> bytes:
    m = aris.pb_frame.FramePart()
    m.frame_index, m.total_data_size, m.data, m.data_offset = 1, total, data, offset
    if header:
        m.header = b"\x01"
    return m.SerializeToString()


def test_frame_assembler_memory_does_not_grow_with_the_number_of_parts() -> None:
    """It kept a set of every part offset: 4096 empty parts held about 240 KB for a 4 KB frame
    (1 M parts of a 1 MiB frame, 12 MB of traffic, about 75 MB)."""
    asm = aris.FrameAssembler(max_data=4096)
    parts = [_frame_part(off, b"", 4096) for off in range(4096)]
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        for p in parts:
            assert asm.receive_datagram(p) == []
        held = tracemalloc.get_traced_memory()[0] - base
    finally:
        tracemalloc.stop()
    assert held < 3 * 4096 + 4096


def test_frame_assembler_overlapping_parts_leave_no_hole() -> None:
    """It counted the bytes of every new offset, so overlapping parts completed a frame with holes."""
    asm = aris.FrameAssembler()
    assert asm.receive_datagram(_frame_part(0, b"BBBBB", 10, header=True)) == []
    assert asm.receive_datagram(_frame_part(1, b"CCCCC", 10)) == []  # 6 of 10 bytes, not 10
    assert asm.receive_datagram(_frame_part(1, b"CCCCC", 10)) == []  # a duplicate adds nothing
    [frame] = asm.receive_datagram(_frame_part(6, b"DDDD", 10))
    assert isinstance(frame, aris.AssembledFrame) and frame.data == b"BCCCCCDDDD"


def test_aris_command_strings_that_are_not_utf8_are_bad_commands() -> None:
    """proto2 does not check strings: invalid UTF-8 came back as bytes in SetDateTime.text and
    SetFrameStreamReceiver.ip (a 4-byte one passed the device's 127.0.0.0/8 check as a packed address)."""
    m = aris.pb_cmd.Command()
    m.type = aris.SET_FRAMESTREAM_RECEIVER  # type: ignore[assignment]
    m.frameStreamReceiver.port = 5000
    m.frameStreamReceiver.ip = "x"
    raw = m.SerializeToString().replace(b"\x12\x01x", b"\x12\x04\x7f\x80\x80\x80")
    assert isinstance(aris.parse_command(raw), aris.BadCommand)
    m = aris.pb_cmd.Command()
    m.type = aris.SET_DATETIME  # type: ignore[assignment]
    m.dateTime.dateTime = "2014-Jan-31 23:58:15"
    raw = m.SerializeToString().replace(b"2014", b"\x80014")
    assert isinstance(aris.parse_command(raw), aris.BadCommand)
    reader = aris.CommandReader()
    reader.receive_data(aris.frame_command(raw) + aris.encode_command(aris.Ping()))
    assert [type(e) for e in reader.events()][:1] == [aris.BadCommand] and reader.commands == 1
