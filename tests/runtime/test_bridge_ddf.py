"""``hilsim run`` on the water tank with the DIDSON-like stream (issue: live bridge).

Clients here are plain sockets; frames are parsed with struct at the offsets of
protocols/ddf-stream.md, not with hilsim's decoder.
"""

from __future__ import annotations

import re

import math
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.runtime.bridge_helpers import (FILE_HDR, FRAME_HDR, parse_frame, read_file_header, read_frame,
                                          recv_exact, start_bridge)

BEAMS, SAMPLES = 96, 512
FRAME = FRAME_HDR + BEAMS * SAMPLES


@pytest.fixture(scope="module")
def bridge(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bridge")
    b = start_bridge(tmp, "--status-interval", "1")
    yield b
    b.stop()


def connect(bridge) -> socket.socket:
    s = socket.create_connection(bridge.tcp("ddf-stream"), timeout=20)
    return s


def test_endpoints_json(bridge):
    e = bridge.endpoint("ddf-stream")
    assert e["transport"] == "tcp" and e["address"].startswith("127.0.0.1:")
    assert {"device", "protocol", "transport", "address"} <= set(e)


def predicted_cuboid_band(depth: float) -> tuple[float, float]:
    """Range band [m] of the cuboid's front face in the centre beam, from the scenario geometry.

    Sonar 0.3 m below the body origin and 0.4 m ahead, tilted 45 deg down with
    +-7 deg elevation; the vehicle at x = -1.75; the cuboid's front face at x = 0
    spans z = 2.7..3.0 (floor top z = 3.0).
    """
    z_s, d = depth + 0.3, 1.75 - 0.4
    tan_lo, tan_hi = math.tan(math.radians(38)), math.tan(math.radians(52))
    z_top = max(2.7, z_s + d * tan_lo)   # highest point of the face a ray reaches
    z_bot = min(3.0, z_s + d * tan_hi)
    return math.hypot(d, z_top - z_s), math.hypot(d, z_bot - z_s)


def test_twenty_frames_parse_and_show_the_cuboid(bridge):
    s = connect(bridge)
    # 8 Hz leaves the renderer headroom on a loaded 2-core CI machine, so no ping is
    # skipped and the frame numbers a client sees are contiguous
    s.sendall(b"RATE 8\n")
    fh = read_file_header(s)
    assert fh["signature"] == b"DDF\x04" and fh["numframes"] == 0
    assert (fh["numbeams"], fh["samples"]) == (BEAMS, SAMPLES)
    read_frame(s, BEAMS, SAMPLES)  # the frame that carries the reply to RATE
    frames = [read_frame(s, BEAMS, SAMPLES) for _ in range(20)]
    s.sendall(b"RATE 15\n")
    s.close()
    numbers = [f.number for f in frames]
    assert numbers == list(range(numbers[0], numbers[0] + 20)), f"gaps in frame numbers: {numbers}"
    times = [f.time_us for f in frames]
    assert all(b > a for a, b in zip(times, times[1:]))
    # the sim's platform values: 1.5 m deep (rising slowly on its 2.5 N buoyancy), 1.5 m above the floor
    assert all(1.3 < f.depth <= 1.5 + 1e-6 for f in frames)
    assert all(abs(f.depth + f.altitude - 3.0) < 1e-3 for f in frames)
    # window: start code 2 x 0.419 m, length code 2 = 5 m (HF extended)
    start, length = frames[0].window_start * 0.419, [1.25, 2.5, 5.0, 10.0][frames[0].window_length]
    ranges = start + (np.arange(SAMPLES) + 0.5) * length / SAMPLES
    f = frames[-1]
    img = np.frombuffer(f.samples, dtype=np.uint8).reshape(SAMPLES, BEAMS).astype(float)
    lo, hi = predicted_cuboid_band(f.depth)
    centre = img[:, BEAMS // 2 - 8: BEAMS // 2 + 8]     # |azimuth| < 2.4 deg: on the cuboid
    edges = np.hstack([img[:, :10], img[:, -10:]])       # |azimuth| > 11.5 deg: beside it
    band = (ranges > lo + 0.01) & (ranges < hi - 0.01)
    shadow = (ranges > hi + 0.04) & (ranges < 1.9)
    # the cuboid's front face echoes in its band; behind it the centre beams are in its
    # shadow while the beams beside the cuboid still see the floor at those ranges
    # (fixed gain maps 80 dB log-linearly onto 0..255: 3.19 levels per dB)
    per_db = 255 / 80
    assert centre[band].mean() > edges[shadow].mean() - 6 * per_db      # as bright as the floor
    assert edges[shadow].mean() - centre[shadow].mean() > 15 * per_db  # >= 15 dB darker: the shadow
    assert centre[band].mean() - centre[shadow].mean() > 15 * per_db


def test_eight_clients_get_identical_frames(bridge):
    socks = [connect(bridge) for _ in range(8)]
    for s in socks:
        read_file_header(s)
    got: list[dict[int, bytes]] = [{} for _ in socks]

    def reader(k: int, s: socket.socket) -> None:
        for _ in range(12):
            fr = read_frame(s, BEAMS, SAMPLES)
            got[k][fr.number] = fr.raw

    threads = [threading.Thread(target=reader, args=(k, s)) for k, s in enumerate(socks)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    for s in socks:
        s.close()
    common = set.intersection(*(set(g) for g in got))
    assert len(common) >= 8
    for n in common:
        assert len({g[n] for g in got}) == 1, f"frame {n} differs between clients"


def test_a_stalled_client_loses_whole_frames_without_slowing_others(bridge):
    goods = [connect(bridge) for _ in range(2)]
    for g in goods:
        read_file_header(g)

    def read_n(n: int) -> tuple[list[list[int]], float]:
        seqs: list[list[int]] = [[], []]
        t0 = time.monotonic()

        def reader(k: int) -> None:
            for _ in range(n):
                seqs[k].append(read_frame(goods[k], BEAMS, SAMPLES).number)

        ts = [threading.Thread(target=reader, args=(k,)) for k in range(2)]
        for t in ts:
            t.start()
        for t in ts:
            t.join(60)
        return seqs, time.monotonic() - t0

    _, before = read_n(15)                                   # baseline rate
    stalled = connect(bridge)
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    seqs, during = read_n(30)                                # 2 s at 15 Hz while it stalls
    # the good clients lose nothing of their own: both got the same frames, in order
    # (a ping the renderer could not keep up with is skipped for everyone, and counted)
    assert seqs[0] == seqs[1] and seqs[0] == sorted(seqs[0])
    # (rates compared within one run; generous for a shared, loaded 2-core machine)
    assert 30 / during > 0.4 * (15 / before), "a stalled client slowed the others down"
    # the stalled client now reads what it was sent: a valid file of whole frames, some skipped
    time.sleep(0.5)
    fh = read_file_header(stalled)
    assert fh["signature"] == b"DDF\x04"
    stalled.settimeout(15)
    # what it holds is bounded (queue + capped buffers: a few frames), so within a few
    # frames it jumps to live ones (reading slowly: its 4 kB window throttles TCP)
    seen = [read_frame(stalled, BEAMS, SAMPLES).number for _ in range(6)]
    stalled.close()
    for g in goods:
        g.close()
    assert seen and seen == sorted(seen)
    assert set(seqs[0]) - set(seen), "the stalled client lost no frame?"


def test_client_disconnecting_mid_frame_leaves_the_server_serving(bridge):
    for _ in range(5):
        s = connect(bridge)
        recv_exact(s, FILE_HDR + 3000)  # mid-frame
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        s.close()
    s = connect(bridge)
    read_file_header(s)
    a = read_frame(s, BEAMS, SAMPLES)
    b = read_frame(s, BEAMS, SAMPLES)
    assert b.number == a.number + 1
    s.close()


def test_commands_change_the_stream_and_bad_ones_get_an_error(bridge):
    s = connect(bridge)
    read_file_header(s)
    s.sendall(b"WINDOW 3 1\nFROB 7\nRATE 10\n")
    replies, window = b"", None
    for _ in range(40):
        fr = read_frame(s, BEAMS, SAMPLES)
        replies += fr.raw[768:1024].rstrip(b"\0")
        window = (fr.window_start, fr.window_length)
        if window == (3, 1) and replies.count(b"\n") >= 3:
            break
    lines = replies.decode().splitlines()
    assert lines[0].startswith("OK") and lines[1].startswith("ERR") and lines[2].startswith("OK"), lines
    assert window == (3, 1)
    # frames keep flowing at the new rate; set it back for the other tests
    s.sendall(b"RATE 15\nWINDOW 2 2\n")
    for _ in range(3):
        read_frame(s, BEAMS, SAMPLES)
    s.close()


def test_status_line_reports_clients_and_frames(bridge):
    time.sleep(1.2)
    log = bridge.log()
    assert "sonar_ddf(clients" in log and "frames" in log
    assert re.search(r"\| late ticks \d+, skipped \d+ \|", log)


def test_record_and_capture_are_byte_identical(tmp_path):
    rec = tmp_path / "rec.ddf"
    b = start_bridge(tmp_path, "--record", str(rec), "--status-interval", "0")
    try:
        s = connect(b)
        read_file_header(s)
        captured = {}
        for _ in range(10):
            fr = read_frame(s, BEAMS, SAMPLES)
            captured[fr.number] = fr.raw
        s.close()
    finally:
        assert b.stop() == 0
    data = rec.read_bytes()
    assert data[:4] == b"DDF\x04"
    n = struct.unpack_from("<i", data, 4)[0]
    assert n == (len(data) - FILE_HDR) // FRAME and (len(data) - FILE_HDR) % FRAME == 0
    recorded = {}
    for k in range(n):
        raw = data[FILE_HDR + k * FRAME: FILE_HDR + (k + 1) * FRAME]
        recorded[struct.unpack_from("<i", raw, 0)[0]] = raw
    assert set(captured) <= set(recorded)
    for num, raw in captured.items():
        assert raw == recorded[num], f"frame {num} differs between the recording and the stream"


def test_record_command_is_deterministic(tmp_path):
    outs = []
    for k in range(2):
        out = tmp_path / f"r{k}.ddf"
        proc = subprocess.run([sys.executable, "-m", "hilsim", "record", "--out", str(out), "--frames", "4",
                               "--epoch", "1700000000", "--seed", "7"], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]
    assert struct.unpack_from("<i", outs[0], 4)[0] == 4
    # the same seed gives the same bytes; the frame times follow the virtual clock from the epoch
    t0 = struct.unpack_from("<Q", outs[0], FILE_HDR + 4)[0]
    assert abs(t0 / 1e6 - 1700000000) < 1.0


def test_sigterm_while_streaming_exits_cleanly(tmp_path):
    runtmp = tmp_path / "tmp"
    runtmp.mkdir()
    b = start_bridge(tmp_path, env={"TMPDIR": str(runtmp)})
    host, port = b.tcp("ddf-stream")
    s = socket.create_connection((host, port), timeout=10)
    read_file_header(s)
    read_frame(s, BEAMS, SAMPLES)
    t0 = time.monotonic()
    b.proc.send_signal(signal.SIGTERM)
    code = b.proc.wait(10)
    took = time.monotonic() - t0
    s.close()
    assert code == 0, b.log()
    assert took < 2.0, f"shutdown took {took:.2f} s"
    with pytest.raises(OSError):
        socket.create_connection((host, port), timeout=2)
    assert list(runtmp.iterdir()) == [], "the bridge left files behind"
