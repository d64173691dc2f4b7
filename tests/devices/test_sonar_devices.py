"""The three sonar protocols served by one running bridge on the water tank.

One test class runs against each protocol (DIDSON-like DDF stream, Oculus,
ARIS): connect, configure, receive frames, check geometry and that the echo
sits where the tank's geometry puts it. Clients are plain sockets; header
fields are read with struct at the offsets of reference/sonar-protocols.md.
Every packet stays on 127.0.0.1; the UDP status/beacon ports are ephemeral
ports the test bound, so parallel runs do not collide.
"""

from __future__ import annotations

import asyncio
import importlib.util
import math
import re
import socket
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hilsim.protocols import aris as ar
from hilsim.protocols import oculus as oc
from tests.runtime.bridge_helpers import recv_exact

pytest.importorskip("hilsim.runtime.bridge")
HAVE_DDF = importlib.util.find_spec("hilsim.devices.ddf_stream") is not None
ROOT = Path(__file__).resolve().parents[2]
TIMEOUT = 30.0

# Geometry (scenarios/water_tank/scenario.toml): the vehicle 1.5 m deep at x = -1.75, the
# sonar 0.3 m below it and tilted 45 deg down, the floor top at z = 3.0 and the cuboid's
# front face at x = 0. The boresight meets the floor (1.2 m below the sonar) 1.2 m ahead,
# just short of the cuboid: first surface at 1.2 / sin 45 deg = 1.70 m. The rays of the
# centre beams hit floor and face between about 1.5 and 1.85 m; nothing is nearer.
BORESIGHT_RANGE = 1.2 / math.sin(math.radians(45.0))


def _udp() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(TIMEOUT)
    return s


@dataclass
class Running:
    endpoints: dict[str, Any]
    status_sock: socket.socket
    beacon_sock: socket.socket
    bridge: Any
    loop: asyncio.AbstractEventLoop

    def tcp(self, protocol: str) -> tuple[str, int]:
        host, port = self.endpoints[protocol].address.rsplit(":", 1)
        return host, int(port)

    def device(self, protocol: str) -> Any:
        return next(d for d in self.bridge.devices if d.protocol == protocol)


@pytest.fixture(scope="module")
def running(tmp_path_factory):
    from hilsim.runtime.bridge import Bridge

    tmp = tmp_path_factory.mktemp("sonars")
    text = (ROOT / "scenarios" / "water_tank" / "scenario.toml").read_text()
    text = text.split("\n[[devices]]")[0]
    text = re.sub(r"(\[vehicle\]\nprofile = \"cyclops\"\nposition_m = )\[[^\]]*\]", r"\1[-1.75, 0.0, 1.5]", text)
    status_sock, beacon_sock = _udp(), _udp()
    devices = [
        ("oculus", f'protocol = "oculus"\nport = 0\nstatus_port = {status_sock.getsockname()[1]}\n'
                   "status_interval_s = 0.25\n"),
        ("aris", f'protocol = "aris"\nport = 0\nbeacon_port = {beacon_sock.getsockname()[1]}\n'
                 "beacon_interval_s = 0.25\nkeepalive_timeout_s = 2.0\n"),
    ]
    if HAVE_DDF:
        devices.insert(0, ("ddf", 'protocol = "ddf-stream"\nport = 0\n'))
    for name, body in devices:
        text += f'\n[[devices]]\nname = "{name}"\n{body}sensor = "sonar"\n'
    (tmp / "scenario.toml").write_text(text)

    ready: dict[str, Any] = {}
    started = threading.Event()

    def serve() -> None:
        async def main() -> None:
            b = Bridge(tmp / "scenario.toml", status_interval=0)
            try:
                eps = await b.start()
                ready.update(bridge=b, loop=asyncio.get_running_loop(), endpoints={e.protocol: e for e in eps})
            except BaseException as exc:  # noqa: BLE001 - reported to the test thread
                ready["error"] = exc
                started.set()
                raise
            started.set()
            try:
                await b.run()
            finally:
                await b.close()

        asyncio.run(main())

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    assert started.wait(120), "bridge did not start"
    if "error" in ready:
        raise ready["error"]
    r = Running(ready["endpoints"], status_sock, beacon_sock, ready["bridge"], ready["loop"])
    yield r
    r.loop.call_soon_threadsafe(r.bridge.stop)
    th.join(30)
    status_sock.close()
    beacon_sock.close()


# ------------------------------------------------------------------ clients


@dataclass
class Frame:
    image: np.ndarray  # (n_samples, n_beams) uint8, beam 0 = port
    range_min: float
    range_max: float


class DdfClient:
    beams, samples = 96, 512

    def __init__(self, running: Running) -> None:
        self.sock = socket.create_connection(running.tcp("ddf-stream"), timeout=TIMEOUT)

    def configure(self) -> None:
        self.sock.sendall(b"RATE 8\n")
        h = recv_exact(self.sock, 1024)
        assert h[:4] == b"DDF\x04"
        self.beams, self.samples = struct.unpack_from("<i", h, 16)[0], struct.unpack_from("<i", h, 24)[0]

    def frames(self, n: int) -> list[Frame]:
        from hilsim.protocols.ddf import window_from_codes

        out = []
        for _ in range(n):
            raw = recv_exact(self.sock, 1024 + self.beams * self.samples)
            start, length = window_from_codes(struct.unpack_from("<i", raw, 52)[0],
                                              struct.unpack_from("<i", raw, 56)[0], True)
            img = np.frombuffer(raw, np.uint8, offset=1024).reshape(self.samples, self.beams)[:, ::-1]
            out.append(Frame(img, start, start + length))
        return out

    def geometry(self, f: Frame) -> None:
        assert f.image.shape == (512, 96)

    def close(self) -> None:
        self.sock.close()


class OculusClient:
    def __init__(self, running: Running) -> None:
        data, _ = running.status_sock.recvfrom(2048)  # discovery: the status datagram
        assert len(data) == 142 and data[:2] == b"\x53\x4f"
        assert struct.unpack_from("<I", data, 24)[0] & 7 == 3  # main run
        ip = ".".join(str(b) for b in data[52:56])
        assert ip == "127.0.0.1"
        self.sock = socket.create_connection((ip, running.tcp("oculus")[1]), timeout=TIMEOUT)
        self.reader = oc.OculusReader(oc.MAX_CLIENT_PAYLOAD)
        self.pending: list[bytes] = []

    def configure(self, range_m: float = 4.0, version: int = 2, flags: int = 0x09, rate: int = 0) -> None:
        self.sock.sendall(oc.encode_fire(oc.Fire(master_mode=oc.MODE_HF, ping_rate=rate, flags=flags,
                                                 range=range_m, gain=100.0, version=version)))

    def raw_pings(self, n: int) -> list[bytes]:
        out: list[bytes] = []
        buf = bytearray()
        while len(out) < n:
            buf += self.sock.recv(1 << 20)
            while len(buf) >= 16:
                size = 16 + struct.unpack_from("<I", buf, 10)[0]
                if len(buf) < size:
                    break
                if struct.unpack_from("<H", buf, 6)[0] == 0x23:
                    out.append(bytes(buf[:size]))
                del buf[:size]
        return out

    def frames(self, n: int) -> list[Frame]:
        out = []
        for raw in self.raw_pings(n):
            v2 = struct.unpack_from("<H", raw, 8)[0] == 2
            nr, nb = struct.unpack_from("<HH", raw, 170 if v2 else 106)
            rres = struct.unpack_from("<d", raw, 162 if v2 else 98)[0]
            ioff = struct.unpack_from("<I", raw, 190 if v2 else 110)[0]
            img = np.frombuffer(raw, np.uint8, nr * nb, ioff).reshape(nr, nb)
            out.append(Frame(img, 0.0, nr * rres))
        return out

    def geometry(self, f: Frame) -> None:
        assert f.image.shape[1] == 256 and f.range_min == 0.0
        assert f.range_max == pytest.approx(4.0, rel=1e-6)

    def close(self) -> None:
        self.sock.close()


class ArisClient:
    def __init__(self, running: Running) -> None:
        data, addr = running.beacon_sock.recvfrom(2048)  # discovery: the beacon's source address
        a = ar.decode_availability(data)
        assert isinstance(a, ar.Availability) and a.system_type == ar.SYSTEM_1800
        assert addr[0] == "127.0.0.1"
        self.sock = socket.create_connection((addr[0], running.tcp("aris")[1]), timeout=TIMEOUT)
        self.frames_sock = _udp()
        self.asm = ar.FrameAssembler()
        self.last_ping = 0.0

    def configure(self, cookie: int = 5) -> None:
        s = ar.AcousticSettings.for_window(0.83, 5.83, 512, 1482.0, frame_rate=8.0, cookie=cookie)
        for c in (ar.SetFrameStreamReceiver(self.frames_sock.getsockname()[1]), ar.SetDateTime("2024-Jan-01 00:00:00"),
                  ar.SetAcoustics(s), ar.SetSalinity(0), ar.SetFocus(2.0), ar.Ping()):
            self.sock.sendall(ar.encode_command(c))
        self.last_ping = time.monotonic()

    def ping(self) -> None:
        if time.monotonic() - self.last_ping > 0.4:
            self.sock.sendall(ar.encode_command(ar.Ping()))
            self.last_ping = time.monotonic()

    def assembled(self, n: int) -> list[ar.AssembledFrame]:
        out: list[ar.AssembledFrame] = []
        self.frames_sock.settimeout(0.2)  # keep pinging while frames are slow to come
        deadline = time.monotonic() + TIMEOUT
        while len(out) < n:
            assert time.monotonic() < deadline, "no frames"
            self.ping()
            try:
                dgram = self.frames_sock.recv(65536)
            except socket.timeout:
                continue
            assert len(dgram) <= 1500
            out += [e for e in self.asm.receive_datagram(dgram) if isinstance(e, ar.AssembledFrame)]
        return out

    def frames(self, n: int) -> list[Frame]:
        out = []
        for f in self.assembled(n):
            h = f.header
            assert struct.unpack_from("<I", h, 516)[0] == 1  # ReorderedSamples
            beams = ar.beams_for_ping_mode(struct.unpack_from("<I", h, 436)[0])
            samples = struct.unpack_from("<I", h, 468)[0]
            start, length = struct.unpack_from("<ff", h, 52)
            img = np.frombuffer(f.data, np.uint8).reshape(samples, beams)[:, ::-1]
            out.append(Frame(img, start, start + length))
        return out

    def geometry(self, f: Frame) -> None:
        assert f.image.shape == (512, 96)
        assert f.range_min == pytest.approx(0.83, abs=0.01) and f.range_max == pytest.approx(5.83, abs=0.2)

    def close(self) -> None:
        self.sock.close()
        self.frames_sock.close()


CLIENTS = {"ddf-stream": DdfClient, "oculus": OculusClient, "aris": ArisClient}
PROTOCOLS = [pytest.param("ddf-stream", marks=pytest.mark.skipif(not HAVE_DDF, reason="no ddf-stream device")),
             "oculus", "aris"]


@pytest.mark.parametrize("protocol", PROTOCOLS)
class TestSonarProtocol:
    """The same client story against every sonar protocol."""

    def test_connect_configure_receive_geometry(self, running, protocol):
        c = CLIENTS[protocol](running)
        try:
            c.configure()
            frames = c.frames(6)[1:]  # the first may predate the configuration
        finally:
            c.close()
        assert len(frames) == 5
        for f in frames:
            c.geometry(f)
            assert f.image.dtype == np.uint8

    def test_echo_at_the_predicted_range(self, running, protocol):
        c = CLIENTS[protocol](running)
        try:
            c.configure()
            f = c.frames(3)[-1]
        finally:
            c.close()
        n_samples, n_beams = f.image.shape
        centre = f.image[:, n_beams // 2 - max(1, n_beams // 40): n_beams // 2 + max(1, n_beams // 40)]
        profile = centre.astype(float).mean(axis=1)
        dr = (f.range_max - f.range_min) / n_samples
        ranges = f.range_min + (np.arange(n_samples) + 0.5) * dr
        peak = ranges[int(np.argmax(profile))]
        assert profile.max() > 20, "no echo in the centre beams"
        assert BORESIGHT_RANGE - 0.3 < peak < BORESIGHT_RANGE + 0.3, (peak, BORESIGHT_RANGE)
        near = profile[ranges < 1.3]
        assert near.size == 0 or near.max() < 0.2 * profile.max(), "echo nearer than the first surface"


# ------------------------------------------------------------ Oculus specifics


def test_oculus_versions_data_sizes_gain_rows_and_invariant(running):
    c = OculusClient(running)
    try:
        for version, flags, width, gains in ((1, 0x09, 1, False), (2, 0x0B, 2, False), (2, 0x0D, 1, True),
                                             (0, 0x4F, 2, True)):
            c.configure(range_m=3.0, version=version, flags=flags)
            raw = None
            for _ in range(20):  # pings of the previous fire may still be queued
                p = c.raw_pings(1)[0]
                if struct.unpack_from("<B", p, 20)[0] == flags and struct.unpack_from("<H", p, 8)[0] == version:
                    raw = p
                    break
            assert raw is not None, (version, flags)
            v2 = version == 2
            nr, nb = struct.unpack_from("<HH", raw, 170 if v2 else 106)
            ioff, isize, msize = struct.unpack_from("<III", raw, 190 if v2 else 110)
            assert 16 + struct.unpack_from("<I", raw, 10)[0] == ioff + isize == msize == len(raw)
            assert isize == nr * (nb * width + (4 if gains else 0))
            assert struct.unpack_from("<B", raw, 161 if v2 else 97)[0] == (1 if width == 2 else 0)
            assert nb == (512 if flags & 0x40 else 256)
            bearings = struct.unpack_from(f"<{nb}h", raw, 202 if v2 else 122)
            assert bearings[0] < 0 < bearings[-1] and list(bearings) == sorted(bearings)
            assert -3500 <= bearings[0] and bearings[-1] <= 3500  # the HF aperture: 70 deg
    finally:
        c.close()


def _oculus_messages(sock: socket.socket, seconds: float) -> list[tuple[int, int, int, int, bytes]]:
    """Whole messages read for ``seconds``: (msgId, srcDeviceId, dstDeviceId, payloadSize, message),
    split by the 16-byte header of protocols/oculus.md (oculusId 0x4F53, src, dst, msgId, version,
    payloadSize), independently of hilsim's reader."""
    out, buf = [], bytearray()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        sock.settimeout(max(0.01, end - time.monotonic()))
        try:
            chunk = sock.recv(1 << 20)
        except socket.timeout:
            break
        if not chunk:
            break
        buf += chunk
        while len(buf) >= 16:
            oid, src, dst, mid, _ver, size = struct.unpack_from("<HHHHHI", buf, 0)
            assert oid == 0x4F53, buf[:16].hex()
            if len(buf) < 16 + size:
                break
            out.append((mid, src, dst, size, bytes(buf[:16 + size])))
            del buf[:16 + size]
    sock.settimeout(TIMEOUT)
    return out


def test_oculus_standby_stops_pings_and_junk_is_tolerated(running):
    """Standby stops the pings; the sonar acknowledges it with a dummy message (id 0xFF, header only,
    from its device id) and keeps the idle connection alive with more of them; junk is tolerated."""
    c = OculusClient(running)
    try:
        c.sock.sendall(b"\x00junk\x53\x4f" + oc.encode_message(oc.MSG_FIRE, bytes(7), version=2))
        c.configure(range_m=2.0)
        c.configure(range_m=2.0)  # a repeated fire just keeps pinging
        assert len(c.raw_pings(2)) == 2
        c.configure(range_m=2.0, rate=oc.PING_RATE_STANDBY)
        first = _oculus_messages(c.sock, 0.4)  # pings already queued may come first; then the dummy
        dummies = [m for m in first if m[0] == 0xFF]
        assert dummies, [m[0] for m in first]
        mid, src, dst, size, _ = dummies[0]
        assert size == 0 and src == running.device("oculus").device_id
        later = _oculus_messages(c.sock, 2.5)
        assert [m[0] for m in later] and all(m[0] == 0xFF for m in later), [m[0] for m in later]
        assert len(later) >= 2  # a steady cadence (1 s by default): the driver's ~10 s watchdog stays fed
    finally:
        c.close()
    dev = running.device("oculus")
    assert dev.counters["bad_messages"] >= 1 and dev.counters["junk_bytes"] >= 5


def test_oculus_idle_connection_gets_dummies_and_pinging_one_gets_none(running):
    c = OculusClient(running)
    try:
        idle = _oculus_messages(c.sock, 2.3)  # connected, never fired
        assert len(idle) >= 2 and {m[0] for m in idle} == {0xFF}
        c.configure(range_m=2.0, rate=2)  # pinging: pings only
        _oculus_messages(c.sock, 0.5)
        busy = _oculus_messages(c.sock, 2.2)
        kinds = [m[0] for m in busy]
        assert kinds.count(0x23) >= 2 and 0xFF not in kinds, kinds
    finally:
        c.close()


def _hf_ping(c: OculusClient, gain: float) -> bytes:
    c.sock.sendall(oc.encode_fire(oc.Fire(master_mode=oc.MODE_HF, ping_rate=0, flags=0x0D, range=3.0,
                                          gain=gain, version=2)))
    for _ in range(30):  # pings of the previous fire may still be queued
        p = c.raw_pings(1)[0]
        if struct.unpack_from("<B", p, 20)[0] == 0x0D and abs(_echoed_gain(p) - (40 + 0.6 * gain)) < 1e-6:
            return p
    raise AssertionError(f"no ping echoing the HF gain law for {gain} %")


def _echoed_gain(raw: bytes) -> float:
    # SimpleFire v2 (protocols/oculus.md): header 16, masterMode 1, pingRate 1, networkSpeed 1, gammaCorrection 1,
    # flags 1, range f64 at 21, gainPercent f64 at 29
    return struct.unpack_from("<d", raw, 29)[0]


def test_oculus_hf_gain_law_echoed_and_applied(running):
    """In HF (master mode 2) the M-series forces the gain into 40-100 %: 40 + 0.6 x requested, echoed in
    the ping's fire message (drivers rescale it back) and applied to the image."""
    c = OculusClient(running)
    try:
        rows = {}
        for gain in (50.0, 100.0):
            raw = _hf_ping(c, gain)
            assert _echoed_gain(raw) == pytest.approx(40 + 0.6 * gain)
            nr, nb = struct.unpack_from("<HH", raw, 170)
            ioff = struct.unpack_from("<I", raw, 190)[0]
            table = np.frombuffer(raw, np.uint8, nr * (4 + nb), ioff).reshape(nr, 4 + nb)
            rows[gain] = table[:, :4].copy().view("<f4").reshape(nr).astype(float)
        # the applied gain differs by 20 log10(70/100) dB (not 20 log10(50/100) as requested)
        diff = 20 * np.log10(rows[50.0] / rows[100.0])
        assert np.allclose(diff, 20 * math.log10(0.70), atol=1e-3), diff[:4]
        # LF echoes the request unchanged
        c.sock.sendall(oc.encode_fire(oc.Fire(master_mode=oc.MODE_LF, ping_rate=0, flags=0x0D, range=3.0,
                                              gain=50.0, version=2)))
        for _ in range(30):
            p = c.raw_pings(1)[0]
            if struct.unpack_from("<B", p, 16)[0] == oc.MODE_LF:
                assert _echoed_gain(p) == pytest.approx(50.0)
                break
        else:
            raise AssertionError("no LF ping")
    finally:
        c.close()


def test_oculus_stalled_huge_header_does_not_hurt_others(running):
    bad = socket.create_connection(running.tcp("oculus"), timeout=TIMEOUT)
    bad.sendall(struct.pack("<HHHHHIH", 0x4F53, 0, 0, 0x15, 2, 0xFFFFFFF0, 0) + b"\x01\x02")
    good = OculusClient(running)
    try:
        good.configure(range_m=2.0)
        assert len(good.raw_pings(3)) == 3
    finally:
        good.close()
        bad.close()


# -------------------------------------------------------------- ARIS specifics


def test_aris_no_settings_no_frames(running):
    c = ArisClient(running)
    try:
        c.sock.sendall(ar.encode_command(ar.SetFrameStreamReceiver(c.frames_sock.getsockname()[1])))
        c.sock.sendall(ar.encode_command(ar.Ping()))
        c.frames_sock.settimeout(1.0)
        with pytest.raises(socket.timeout):
            c.frames_sock.recv(2000)
    finally:
        c.close()


def test_aris_silent_client_is_dropped(running):
    c = ArisClient(running)
    try:
        c.sock.sendall(ar.encode_command(ar.Ping()))
        c.sock.settimeout(10.0)
        t0 = time.monotonic()
        assert c.sock.recv(100) == b""  # closed by the sonar (keepalive_timeout_s = 2)
        assert time.monotonic() - t0 < 9.0
    finally:
        c.close()


def test_aris_malformed_commands_ignored_invalid_settings_reported(running):
    c = ArisClient(running)
    try:
        c.sock.sendall(b"\xff\xff\xff\xff" + bytes(range(40)) + ar.frame_command(b"\x08\x03"))
        c.configure(cookie=21)
        first = c.assembled(2)[-1]
        assert struct.unpack_from("<I", first.header, 680)[0] == 21  # AppliedSettings
        bad = ar.AcousticSettings(cookie=22, samples_per_beam=5)
        c.sock.sendall(ar.encode_command(ar.SetAcoustics(bad)))
        for _ in range(60):
            f = c.assembled(1)[-1]
            if struct.unpack_from("<I", f.header, 688)[0] == 22:  # InvalidSettings
                break
        else:
            pytest.fail("the invalid settings' cookie never showed in InvalidSettings")
        assert struct.unpack_from("<I", f.header, 680)[0] == 21  # still the old settings
        assert struct.unpack_from("<I", f.header, 468)[0] == 512
    finally:
        c.close()
    assert running.device("aris").counters["bad_commands"] >= 1


def test_aris_receiver_outside_loopback_refused(running):
    c = ArisClient(running)
    try:
        c.sock.sendall(ar.encode_command(ar.SetFrameStreamReceiver(9, "192.0.2.1")))
        c.sock.sendall(ar.encode_command(ar.Ping()))
        for _ in range(50):
            if running.device("aris").counters["refused_receivers"]:
                break
            time.sleep(0.05)
        assert running.device("aris").counters["refused_receivers"] >= 1
    finally:
        c.close()
