"""Resynchronising decoders (VESC UART, VRCSR, ARIS commands): linear work however the bytes are cut.

A decoder that judges its whole buffer again on every byte is quadratic in the
longest length a header may claim: a peer sending, one byte at a time, a start
with a large length that never completes, then near-miss headers that each
need a check, got about 2 kB/s through. These tests count work, not time
(shared machines are noisy): checksum computations, protobuf parses, and all
function calls (``sys.setprofile``) per byte fed, on such input. And they check
that the incremental decoders give exactly what the obvious quadratic rules
give (a reference that judges everything again on every call), however the
input is cut.
"""

from __future__ import annotations

import struct
import sys
from typing import Any, Callable

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hilsim.protocols import aris as ar
from hilsim.protocols import framing
from hilsim.protocols import vesc_uart as vu
from hilsim.protocols import vrcsr as vr

N_BYTES = 30_000
WORK_PER_BYTE = 20     # checksum/parse bytes per byte fed (the old decoders: hundreds)
CALLS_PER_BYTE = 100   # function calls per byte fed (now 15-30; the old decoders: 400-4000)


def repeat_to(unit: bytes, n: int = N_BYTES) -> bytes:
    return (unit * (n // len(unit) + 1))[:n]


def vrcsr_header(n: int, node: int = 0x81) -> bytes:
    head = vr.SYNC_REQUEST + bytes([node, 2, 0xF0, n])
    return head + struct.pack("<I", vr.crc32(head))


# A long-form VESC start claiming 512 payload bytes (518 in all: the decoder must wait for them), then
# short-form starts whose end byte is right (each needs a CRC: bad), then a wrong end byte for the first.
VESC_CRAFTED = repeat_to(b"\x03\x02\x00" + b"\x02\x03" * 257 + b"\x00")
VESC_CRAFTED_SHORT = repeat_to(b"\x02\xff" + b"\x02\x03" * 129)
# A VRCSR header with a good CRC claiming 255 bytes (269 in all), then a sync every 2 bytes (header CRCs).
VRCSR_CRAFTED = repeat_to(vrcsr_header(255) + vr.SYNC_REQUEST * 129 + b"\x00")
# ARIS out of sync (a 4 GB length), then a length of max_length and zeros: every offset holds a complete
# empty frame to parse (not a Command), behind a frame that needs 1028 bytes.
ARIS_CRAFTED = repeat_to(b"\xff\xff\xff\xff" + struct.pack(">I", ar.MAX_COMMAND_LENGTH)
                         + bytes(ar.MAX_COMMAND_LENGTH + 8))

VESC_VALID = vu.frame(vu.encode_command(vu.SetRpm(5000)))
VRCSR_VALID = vr.propulsion_request([0.5, -0.25], reply_node_id=3)
ARIS_VALID = ar.encode_command(ar.Ping())


def drain(dec: Any, need: object) -> list[Any]:
    out = []
    while (ev := dec.next_event()) is not need:
        out.append(ev)
    return out


def feed(dec: Any, need: object, data: bytes, chunk: int = 0, after_each: Callable[[], None] | None = None
         ) -> list[Any]:
    """Hand ``data`` over in ``chunk``-byte pieces (0: whole), draining after each."""
    out: list[Any] = []
    step = chunk or max(1, len(data))
    for i in range(0, len(data), step):
        dec.receive_data(data[i:i + step])
        out += drain(dec, need)
        if after_each is not None:
            after_each()
    return out


class Budget(Exception):
    pass


class Counter:
    """Counts calls of a module function and the bytes handed to it; raises Budget past ``limit`` bytes
    (so a quadratic decoder fails at once instead of running for minutes)."""

    def __init__(self, fn: Callable[..., Any], limit: int, size: Callable[..., int]) -> None:
        self.fn, self.limit, self.size = fn, limit, size
        self.calls = self.bytes = 0

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        self.calls += 1
        self.bytes += self.size(*args)
        if self.bytes > self.limit:
            raise Budget(f"{self.calls} calls, {self.bytes} bytes")
        return self.fn(*args, **kwargs)


def count_work(monkeypatch: pytest.MonkeyPatch, module: Any, name: str, limit: int) -> Counter:
    counter = Counter(getattr(module, name), limit, lambda data, *_: len(data))
    monkeypatch.setattr(module, name, counter)
    return counter


# ------------------------------------------------------------------ work is linear


@pytest.mark.parametrize("data", [VESC_CRAFTED, VESC_CRAFTED_SHORT], ids=["long-claim", "short-claim"])
def test_vesc_crafted_input_byte_at_a_time_costs_linear_crc_work(monkeypatch, data):
    crc = count_work(monkeypatch, vu, "crc16", WORK_PER_BYTE * len(data))
    dec = vu.PacketDecoder()
    assert feed(dec, vu.NEED_DATA, data, 1) == []
    assert crc.calls <= len(data)  # each start judged complete at most twice, one start every other byte
    assert dec.stats.crc_errors > len(data) // 3  # the CRCs were needed: each bait is a CRC error
    dec.receive_data(VESC_VALID * 2)
    assert drain(dec, vu.NEED_DATA)[-1:] == [VESC_VALID[2:-3]]


def test_vrcsr_crafted_input_byte_at_a_time_costs_linear_crc_work(monkeypatch):
    crc = count_work(monkeypatch, vr, "crc32", WORK_PER_BYTE * len(VRCSR_CRAFTED))
    dec = vr.PacketDecoder()
    assert feed(dec, vr.NEED_DATA, VRCSR_CRAFTED, 1) == []
    assert crc.calls <= 2 * len(VRCSR_CRAFTED)
    assert dec.stats.header_crc_errors > len(VRCSR_CRAFTED) // 3
    dec.receive_data(VRCSR_VALID * 2)
    assert drain(dec, vr.NEED_DATA)[-1].payload == VRCSR_VALID[10:-4]


def test_aris_crafted_input_byte_at_a_time_costs_linear_parse_work(monkeypatch):
    parse = Counter(ar.parse_command, 2 * len(ARIS_CRAFTED), lambda payload, *_, **__: 1)  # limit: parses
    monkeypatch.setattr(ar.commands, "parse_command", parse)  # where CommandReader looks it up
    r = ar.CommandReader()
    events = feed(r, ar.NEED_DATA, ARIS_CRAFTED, 1)
    assert events and all(isinstance(e, (ar.Oversize, ar.Junk, ar.BadCommand)) for e in events)
    assert parse.calls <= len(ARIS_CRAFTED)  # each offset parsed at most once
    r.receive_data(ARIS_VALID * 300)  # past a frame that may still wait for max_length bytes
    assert r.events()[-1] == ar.Ping()


class CallCounter:
    """Every Python and C function call while active (sys.setprofile): a count of work, not of time."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, frame: Any, event: str, arg: Any) -> None:
        if event == "call" or event == "c_call":
            self.calls += 1

    def run(self, fn: Callable[[], Any]) -> Any:
        previous = sys.getprofile()
        sys.setprofile(self)
        try:
            return fn()
        finally:
            sys.setprofile(previous)


CASES = {
    "vesc-uart": (vu.PacketDecoder, vu.NEED_DATA, VESC_CRAFTED),
    "vesc-uart-short": (vu.PacketDecoder, vu.NEED_DATA, VESC_CRAFTED_SHORT),
    "vrcsr": (vr.PacketDecoder, vr.NEED_DATA, VRCSR_CRAFTED),
    "aris-commands": (ar.CommandReader, ar.NEED_DATA, ARIS_CRAFTED),
}


@pytest.mark.parametrize("name", list(CASES))
def test_function_calls_per_byte_stay_bounded(name):
    """All work, including scanning for start markers and re-reading headers, counted as calls."""
    make, need, data = CASES[name]
    dec = make()
    counter = CallCounter()

    def go() -> None:
        for i in range(0, len(data), 1000):  # in slices, so a quadratic decoder stops early
            feed(dec, need, data[i:i + 1000], 1)
            assert counter.calls <= CALLS_PER_BYTE * (i + 1000), f"{counter.calls} calls for {i + 1000} bytes"

    counter.run(go)


@pytest.mark.parametrize("cls", [vu.PacketDecoder, vr.PacketDecoder])
def test_a_waiting_candidate_is_not_judged_again_until_its_bytes_are_there(cls, monkeypatch):
    vesc = cls is vu.PacketDecoder
    head, total, need = (b"\x03\x01\x00", 262, vu.NEED_DATA) if vesc else (vrcsr_header(255), 269, vr.NEED_DATA)
    judged: list[int] = []
    original = cls._judge

    def judge(self: Any, buf: bytearray, i: int) -> framing.Verdict:
        judged.append(i)
        return original(self, buf, i)

    monkeypatch.setattr(cls, "_judge", judge)
    dec = cls()
    assert feed(dec, need, head, 1) == []
    assert judged == [0, 0]  # header incomplete, then complete: the length is known from here on
    judged.clear()
    assert feed(dec, need, bytes(total - len(head) - 1), 1) == []  # no start in these: nothing to judge
    assert judged == [] and dec.buffered_bytes == total - 1
    dec.receive_data(b"\x00")  # complete: judged once more (a wrong end byte / payload CRC)
    assert drain(dec, need) == [] and judged == [0]


def test_aris_in_sync_frame_is_not_parsed_until_complete(monkeypatch):
    parse = Counter(ar.parse_command, 10, lambda payload, *_, **__: 1)
    monkeypatch.setattr(ar.commands, "parse_command", parse)  # where CommandReader looks it up
    r = ar.CommandReader()
    wire = ar.encode_command(ar.SetAcoustics(ar.AcousticSettings(cookie=5)))
    assert feed(r, ar.NEED_DATA, wire[:-1], 1) == [] and parse.calls == 0
    r.receive_data(wire[-1:])
    assert r.events() == [ar.SetAcoustics(ar.AcousticSettings(cookie=5))] and parse.calls == 1


# ------------------------------------------------------------------ the same results


@pytest.mark.parametrize("name", list(CASES))
def test_crafted_input_then_valid_is_decoded_the_same_however_cut(name):
    make, need, data = CASES[name]
    valid = {"vrcsr": VRCSR_VALID, "aris-commands": ARIS_VALID}.get(name, VESC_VALID)
    stream = data[:3000] + valid * 400  # more than any claimed length, so the valid ones come through
    results = []
    for chunk in (0, 1, 7, 300):
        dec = make()
        events = feed(dec, need, stream, chunk)
        if name == "aris-commands":
            events = [e for e in events if not isinstance(e, ar.Junk)]  # Junk sizes depend on the cut
        assert events, f"{name}: nothing decoded with chunk {chunk}"
        results.append((events, dec.buffered_bytes))  # counters differ: what is dropped unjudged depends
    assert all(r == results[0] for r in results)


# Reference decoders: the same rules applied the obvious way, judging everything again on every call.


def naive(cls: type) -> type:
    """``cls`` with its framing loop replaced by the quadratic one it replaces (same judge and counters)."""

    class Naive(cls):
        def _next_frame(self) -> Any:
            buf = self._buf  # _pos stays 0: consumed bytes are deleted
            while buf:
                s = self._find_start(buf, 0)
                if s < 0:
                    n = len(buf) - self._partial_start(buf, 0)
                    del buf[:n]
                    self._skipped(n)
                    return None
                del buf[:s]
                self._skipped(s)
                kind, n = self._judge(buf, 0)
                if kind == framing.OK:
                    ev = self._event(buf, 0, n)
                    del buf[:n]
                    return ev
                if kind == framing.NEED:
                    q = self._find_start(buf, 1)
                    while q >= 0 and self._judge(buf, q)[0] != framing.OK:
                        q = self._find_start(buf, q + 1)
                    if q < 0:
                        return None
                    self._dropped()
                    del buf[:q]
                    self._skipped(q)
                    continue
                self._rejected(kind)
                del buf[:1]
                self._skipped(1)
            return None

    return Naive


class NaiveCommandReader(ar.CommandReader):
    def _next_synced(self) -> Any:
        buf = self._buf
        if len(buf) < 4:
            return None
        (length,) = struct.unpack_from(">I", buf, 0)
        if length > self.max_length:
            self._synced = False
            del buf[:1]
            return ar.Oversize(length)
        if len(buf) < 4 + length:
            return None
        ev = ar.parse_command(bytes(buf[4:4 + length]))
        del buf[:1 if isinstance(ev, ar.BadCommand) else 4 + length]
        self._synced = not isinstance(ev, ar.BadCommand)
        return ev

    def _resync(self) -> Any:
        buf, first_waiting = self._buf, -1
        for j in range(len(buf) - 3):
            (length,) = struct.unpack_from(">I", buf, j)
            if length > self.max_length:
                continue
            if j + 4 + length > len(buf):
                first_waiting = j if first_waiting < 0 else first_waiting
                continue
            ev = ar.parse_command(bytes(buf[j + 4:j + 4 + length]), strict=True)
            if isinstance(ev, ar.BadCommand):
                continue
            del buf[:j + 4 + length]
            self._synced = True
            if j:
                self._pending.append(ev)
                self.commands += 1
                return ar.Junk(j)
            return ev
        keep_from = first_waiting if first_waiting >= 0 else max(0, len(buf) - 3)
        del buf[:keep_from]
        return ar.Junk(keep_from) if keep_from else None


VESC_PIECES = [VESC_VALID, vu.frame(bytes(300)), vu.frame(b"\x02\x03"), b"\x02", b"\x03", b"\x02\xff",
               b"\x03\x02\x00", b"\x03\x01\x00", b"\x02\x03", b"\x00", b"\xff"]
VRCSR_PIECES = [VRCSR_VALID, vr.Packet(1, 2, 3, b"").encode(), vr.Packet(1, 2, 3, b"abc").encode(),
                vr.response(1, 2, 3, b"xy"), vrcsr_header(60), vrcsr_header(5), b"\xf5", b"\x5f", b"\xf5\x5f",
                b"\x00", b"\x06"]
ARIS_PIECES = [ARIS_VALID, ar.encode_command(ar.SetSalinity(15)), ar.frame_command(b"\x08\x03"),
               struct.pack(">I", 5), struct.pack(">I", 40), b"\xff\xff\xff\xff", b"\x00", b"\x08\x0e",
               b"\x00\x00\x00\x02\x08\x0e", b"\x00\x00\x04\x00"]


def streams(pieces: list[bytes]) -> st.SearchStrategy[bytes]:
    return st.lists(st.one_of(st.sampled_from(pieces), st.binary(max_size=12)), max_size=60).map(b"".join)


cuts = st.lists(st.integers(1, 40), max_size=5)
SAME = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def same_as_reference(make: Callable[[], Any], make_ref: Callable[[], Any], need: object, data: bytes,
                      sizes: list[int], state: Callable[[Any], Any]) -> None:
    """Fed the same pieces, the decoder and the reference give the same events and state after each."""
    dec, ref = make(), make_ref()
    pos, k = 0, 0
    while pos < len(data):
        n = sizes[k % len(sizes)] if sizes else len(data)
        for d in (dec, ref):
            d.receive_data(data[pos:pos + n])
        assert drain(dec, need) == drain(ref, need)
        assert (state(dec), dec.buffered_bytes) == (state(ref), ref.buffered_bytes)
        pos, k = pos + n, k + 1


@SAME
@given(streams(VESC_PIECES), cuts, st.sampled_from([vu.MAX_PAYLOAD, 300, 4]))
def test_vesc_uart_decodes_like_the_reference(data, sizes, max_payload):
    same_as_reference(lambda: vu.PacketDecoder(max_payload), lambda: naive(vu.PacketDecoder)(max_payload),
                      vu.NEED_DATA, data, sizes, lambda d: d.stats)


@SAME
@given(streams(VRCSR_PIECES), cuts, st.booleans())
def test_vrcsr_decodes_like_the_reference(data, sizes, responses):
    same_as_reference(lambda: vr.PacketDecoder(responses), lambda: naive(vr.PacketDecoder)(responses),
                      vr.NEED_DATA, data, sizes, lambda d: d.stats)


@SAME
@given(streams(ARIS_PIECES), cuts, st.sampled_from([ar.MAX_COMMAND_LENGTH, 50, 3]))
def test_aris_command_reader_decodes_like_the_reference(data, sizes, max_length):
    same_as_reference(lambda: ar.CommandReader(max_length), lambda: NaiveCommandReader(max_length), ar.NEED_DATA,
                      data, sizes, lambda r: (r.errors, r.commands, r._synced))


def test_the_reference_comparison_sees_a_decoder_that_forgets(monkeypatch):
    """The comparison is sharp: a framer that forgets the later starts it is waiting on differs."""
    original = framing.ResyncFramer._find_later

    def forgetful(self: Any, candidate: int) -> int:
        self._later.clear()
        return original(self, candidate)

    monkeypatch.setattr(framing.ResyncFramer, "_find_later", forgetful)
    # a long claim, then a valid packet cut so that the search sees it incomplete, then the rest
    data = b"\x03\x02\x00" + VESC_VALID + b"\x00" * 20
    with pytest.raises(AssertionError):
        same_as_reference(vu.PacketDecoder, naive(vu.PacketDecoder), vu.NEED_DATA, data, [5, 1],
                          lambda d: d.stats)
