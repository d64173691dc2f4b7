"""A full server never locks out a real client (issue #15 part 1), on a running bridge.

``hilsim run`` on the default scenario (a subprocess) with small client limits, for every
TCP server kind it has (DDF stream, Oculus, ARIS command channel, Modbus TCP, socketcand):

* every slot taken by stale connections (DDF: clients that never read the frames, so
  their writes stall; the command channels: connections that send nothing, some of the
  Oculus ones after a fire whose pings they never read): a well-behaved client that
  connects, and connects again when refused, as a real one does, is served within the
  eviction grace plus a second (plus, for the DDF stream, the half second its frames take
  to fill a never-reading client's buffers, and for the sonars one ping period for the
  first ping), and the log names each eviction with its reason;
* every slot taken by well-behaved clients: past the grace a newcomer is still refused,
  and every one of them keeps being served, none evicted or reconnected.

Clients are plain sockets (tests/runtime/abuse_clients.py); nothing of hilsim's own
serves them but the bridge under test.
"""

from __future__ import annotations

import re
import socket
import struct
import time
from typing import Callable

import pytest

from tests.runtime import abuse_clients as ac
from tests.runtime.bridge_helpers import ROOT, start_bridge

pytestmark = pytest.mark.timeout(120)

GRACE = 1.5        # [s] evict_grace_s of every device here (default 5)
LIMITS = {"ddf-stream": 3, "oculus": 3, "aris": 2, "modbus-keller": 3, "socketcand": 3}
DEVICES = {"ddf-stream": "sonar_ddf", "oculus": "sonar_oculus", "aris": "sonar_aris", "modbus-keller": "depth",
           "socketcand": "vesc_can"}
FIRST_RESPONSE = {"ddf-stream": 0.5 + 1 / 15.0, "oculus": 1 / 5.0, "aris": 1 / 5.0, "modbus-keller": 0.0,
                  "socketcand": 0.0}  # [s] beyond the grace + 1 s: stall onset, the first ping
OCULUS_RATE = 3    # ping rate code: 5 Hz
# ARIS drops a client silent for keepalive_timeout_s (3 s) by itself: here longer than the
# grace, so that the eviction is what frees the slot
EXTRA = {"aris": "keepalive_timeout_s = 30\n"}


def scenario(tmp) -> str:
    """The default scenario with free ports, the small client limits and the grace above, and EXTRA."""
    text = (ROOT / "scenarios" / "water_tank" / "scenario.toml").read_text()
    for old, new in (("port = 52100", "port = 0"), ("port = 56888", "port = 0")):
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    for proto, device in DEVICES.items():
        head = f'[[devices]]\nname = "{device}"\n'
        assert text.count(head) == 1, head
        text = text.replace(head, head + f"max_clients = {LIMITS[proto]}\nevict_grace_s = {GRACE}\n"
                            + EXTRA.get(proto, ""))
    path = tmp / "scenario.toml"
    path.write_text(text)
    return str(path)


@pytest.fixture(scope="module")
def bridge(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("eviction")
    b = start_bridge(tmp, scenario(tmp), "--status-interval", "1")
    yield b
    b.stop()


def address(bridge, proto: str) -> str:
    device = DEVICES[proto]
    return next(e["address"] for e in bridge.endpoints
                if e["device"] == device and e["transport"] in ("tcp", "socketcand"))


def log_name(proto: str) -> str:
    return "socketcand:can0" if proto == "socketcand" else DEVICES[proto]


# ------------------------------------------------------------------ one attempt at being served


def _serve_ddf(s: socket.socket, end: float) -> bool:
    return ac.recv_exact(s, 1024, end)[:4] == b"DDF\x04" and len(ac.recv_exact(s, 1024 + 96 * 512, end)) > 0


def _serve_oculus(s: socket.socket, end: float) -> bool:
    from hilsim.protocols import oculus as oc

    s.sendall(oc.encode_fire(oc.Fire(master_mode=oc.MODE_HF, ping_rate=OCULUS_RATE, flags=0x09, range=3.0,
                                     gain=100.0, version=2)))
    while True:
        head = ac.recv_exact(s, 16, end)
        assert struct.unpack_from("<H", head, 0)[0] == 0x4F53
        ac.recv_exact(s, struct.unpack_from("<I", head, 10)[0], end)
        if struct.unpack_from("<H", head, 6)[0] == 0x23:  # SimplePingResult
            return True


def _serve_aris(s: socket.socket, end: float) -> bool:
    from hilsim.protocols import aris as ar

    udp = ac.udp_socket(1 << 20)
    try:
        ac.aris_setup(s, udp.getsockname()[1], frame_rate=5.0)
        asm = ar.FrameAssembler()
        udp.settimeout(0.05)
        while time.monotonic() < end:
            if ac.refused(s):
                return False
            try:
                dgram = udp.recv(65536)
            except (socket.timeout, TimeoutError):
                continue
            if any(isinstance(ev, ar.AssembledFrame) for ev in asm.receive_datagram(dgram)):
                return True
        return False
    finally:
        udp.close()


def _serve_modbus(s: socket.socket, end: float) -> bool:
    s.sendall(ac.mbap_request(7, 1, 0x0002, 2))
    reply = ac.recv_exact(s, 13, end)
    return struct.unpack_from(">HHHBBB", reply) == (7, 0, 7, 1, 3, 4)


def _serve_socketcand(s: socket.socket, end: float) -> bool:
    ac.socketcand_handshake(s, deadline=max(0.1, end - time.monotonic()))
    return True


SERVE: dict[str, Callable[[socket.socket, float], bool]] = {
    "ddf-stream": _serve_ddf, "oculus": _serve_oculus, "aris": _serve_aris, "modbus-keller": _serve_modbus,
    "socketcand": _serve_socketcand}


def served_within(proto: str, addr: str, seconds: float) -> tuple[float | None, int]:
    """Connect, and again after each refusal (EOF or reset), until served; returns the time
    [s] it took (None: not within ``seconds``) and the refused attempts."""
    t0 = time.monotonic()
    refusals = 0
    while time.monotonic() - t0 < seconds:
        try:
            with socket.create_connection(ac.host_port(addr), timeout=2.0) as s:
                if SERVE[proto](s, min(time.monotonic() + 2.0, t0 + seconds)):
                    return time.monotonic() - t0, refusals
        except (EOFError, ConnectionError, socket.timeout, TimeoutError, AssertionError, OSError):
            pass
        refusals += 1
        time.sleep(0.1)
    return None, refusals


def refused_now(addr: str, within: float = 2.0) -> bool:
    """A fresh connection is closed by the server at once (within ``within`` [s], for a loaded machine)."""
    with socket.create_connection(ac.host_port(addr), timeout=2.0) as s:
        return ac.wait_until(lambda: ac.refused(s), within, 0.02)


# ------------------------------------------------------------------ tests


@pytest.mark.parametrize("proto", list(LIMITS))
def test_stale_connections_give_way_to_a_well_behaved_client(bridge, proto):
    addr = address(bridge, proto)
    limit = LIMITS[proto]
    udps: list[socket.socket] = []
    held = ac.open_many(addr, limit + 2)  # more than the limit: every slot taken
    try:
        for i, k in enumerate(held):
            try:
                if proto == "ddf-stream" or (proto == "oculus" and i % 2 == 0):
                    udps.append(ac.udp_socket(4096))
                    ac.start_never_reading(proto, k, udps[-1], rate_code=OCULUS_RATE)
            except OSError:
                pass  # refused: beyond the limit
        t_fill = time.monotonic()
        time.sleep(0.3)
        assert sum(not ac.refused(k) for k in held) == limit, "the stale connections did not fill the server"
        # (within the grace: the stale ones are not evictable yet)
        assert refused_now(addr, within=0.8), "a full server with fresh connections must refuse"
        bound = GRACE + 1.0 + FIRST_RESPONSE[proto]
        took, refusals = served_within(proto, addr, bound + 5.0 - (time.monotonic() - t_fill))
        waited = time.monotonic() - t_fill
    finally:
        ac.close_all(held)
        ac.close_all(udps, rst=False)
    print(f"\n{proto}: served {waited:.2f} s after the fill ({refusals} refused attempts; bound {bound:.2f} s)")
    assert took is not None, f"{proto}: not served within {bound + 5.0:.1f} s of the fill"
    assert waited <= bound, f"{proto}: served only {waited:.2f} s after the fill (grace {GRACE} s)"
    assert refusals >= 1  # it was full: the first attempts within the grace were refused
    log = bridge.log()
    lines = re.findall(re.escape(log_name(proto)) + r": client 127\.0\.0\.1:\d+ evicted \((stalled|idle): ", log)
    assert lines, f"{proto}: no eviction in the log"
    if proto == "ddf-stream":
        assert "stalled" in lines


def healthy_clients(proto: str, addr: str, n: int) -> list[ac.Client]:
    if proto == "ddf-stream":
        return [ac.DdfReader(addr, rate_hz=None) for _ in range(n)]
    if proto == "oculus":
        return [ac.OculusFirer(addr, rate=OCULUS_RATE) for _ in range(n)]
    if proto == "aris":
        return [ac.ArisClient(addr, frame_rate=5.0) for _ in range(n)]
    if proto == "modbus-keller":
        return [ac.ModbusTcpPoller(addr, 1, 0x0002, 2, rate_hz=10.0) for _ in range(n)]
    return [ac.SocketcandCommander(addr, controller=2, erpm=3000, rate_hz=10.0) for _ in range(n)]


@pytest.mark.parametrize("proto", list(LIMITS))
def test_a_server_full_of_well_behaved_clients_refuses_and_drops_none(bridge, proto):
    addr = address(bridge, proto)
    clients = healthy_clients(proto, addr, LIMITS[proto])
    evictions = re.compile(re.escape(log_name(proto)) + r": client \S+ evicted")
    before = len(evictions.findall(bridge.log()))
    try:
        for c in clients:
            c.start()
        assert ac.wait_until(lambda: all(c.stats.received >= 2 for c in clients), 15), \
            [(c.stats.received, c.error) for c in clients]
        counts = [c.stats.received for c in clients]
        time.sleep(GRACE + 0.5)  # every held client well past the grace
        attempts = 4
        refused = 0
        for _ in range(attempts):  # still refused, every time
            refused += refused_now(addr)
            time.sleep(0.2)
        grew = [c.stats.received - n for c, n in zip(clients, counts)]
    finally:
        for c in clients:
            c.stop()
    log = bridge.log()
    print(f"\n{proto}: {refused} of {attempts} newcomers refused past the grace; the held clients received "
          f"{grew} meanwhile")
    assert refused == attempts, (refused, attempts)
    for c in clients:
        assert c.error is None and c.stats.reconnects == 0 and c.stats.bad == 0 and c.stats.lost == 0, \
            (c.name, c.error, c.stats)
    assert all(g > 0 for g in grew), grew
    assert len(evictions.findall(log)) == before, "a well-behaved client was evicted"
