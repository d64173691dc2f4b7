"""Security defaults of ``hilsim run`` (subprocesses on copies of the default scenario).

* every server binds 127.0.0.1 unless ``--bind`` says otherwise, the endpoints table shows
  what is exposed, and the bridge has no socket on any other address (read from /proc);
* ``--bind 127.0.0.2`` (a loopback alias) moves every TCP server there, and the UDP
  status/beacon still go to loopback (``--broadcast`` default), sent from the bind address;
* scenario and profile files are data: a malformed file, an unknown option, a pty path, a
  recording, a mesh or a profile reference that leaves the scenario's folder all stop
  ``hilsim run`` with exit code 1 and one clear line naming the file, the line and the key,
  never a traceback.

The scenario copies use free TCP ports and send the UDP status/beacon to sockets this
test bound, so parallel runs do not collide.
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.runtime import abuse_clients as ac
from tests.runtime.bridge_helpers import ROOT, start_bridge

pytestmark = pytest.mark.timeout(180)

DEFAULT = (ROOT / "scenarios" / "water_tank" / "scenario.toml").read_text()


def udp_capture() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(10)
    return s


def scenario_copy(tmp: Path, status_port: int, beacon_port: int, text: str = DEFAULT) -> Path:
    """The default scenario with free TCP ports and the status/beacon ports given."""
    for old, new in (("port = 52100", "port = 0"), ("port = 56888", "port = 0"),
                     ("status_port = 52102", f"status_port = {status_port}\nstatus_interval_s = 0.2"),
                     ("beacon_port = 56124", f"beacon_port = {beacon_port}\nbeacon_interval_s = 0.2")):
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    path = tmp / "scenario.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def udp_ports():
    socks = (udp_capture(), udp_capture())
    yield socks
    for s in socks:
        s.close()


def check_udp(status_sock: socket.socket, beacon_sock: socket.socket, source: str) -> None:
    """The Oculus status and the ARIS beacon arrive on loopback from ``source``."""
    from hilsim.protocols import aris as ar

    for sock in (status_sock, beacon_sock):  # drop what an earlier bridge sent
        sock.setblocking(False)
        try:
            while sock.recv(4096):
                pass
        except BlockingIOError:
            pass
        sock.settimeout(10)
    data, addr = status_sock.recvfrom(2048)
    assert addr[0] == source and len(data) == 142 and data[:2] == b"\x53\x4f"
    assert ".".join(str(b) for b in data[52:56]) == source  # the address clients must connect to
    data, addr = beacon_sock.recvfrom(2048)
    assert addr[0] == source and isinstance(ar.decode_availability(data), ar.Availability)


def test_default_run_exposes_only_loopback_and_keeps_ptys_in_the_run_folder(tmp_path, udp_ports):
    status_sock, beacon_sock = udp_ports
    path = scenario_copy(tmp_path, status_sock.getsockname()[1], beacon_sock.getsockname()[1])
    b = start_bridge(tmp_path, str(path), "--status-interval", "0")
    try:
        eps = b.endpoints
        table = b.log()
        for e in eps:
            if e["transport"] in ("tcp", "socketcand"):
                assert e["address"].startswith("127.0.0.1:"), e
                assert re.search(rf"\b{re.escape(e['address'])}\b", table), e  # the printed table shows it
            for k in ("status", "beacon"):
                if k in e:
                    assert e[k].startswith("udp 127.0.0.1:"), e
        ptys = [e for e in eps if e["transport"] in ("pty", "slcan")]
        assert len(ptys) >= 10   # every serial device of the default scenario (Modbus, KELLER bus, WitMotion UART,
        # slcan, VESC UART, VRCSR, DVL, GNSS, Ping1D, ...): the count grows with the scenario
        run_dirs = {Path(e["address"]).parent for e in ptys}
        assert len(run_dirs) == 1  # one run folder, a fresh temporary one
        run_dir = run_dirs.pop()
        assert run_dir.name.startswith("hilsim-")
        for e in ptys:
            p = Path(e["address"])
            assert p.is_symlink() and os.readlink(p).startswith("/dev/pts/"), e
        # nothing of the bridge (or its render worker) listens or sends from another address
        socks = ac.inet_sockets(b.proc.pid)
        listening = {(proto, addr, port) for proto, addr, port, _ in socks}
        assert socks and all(addr == "127.0.0.1" for _, addr, _, _ in socks), socks
        tcp_ports = {int(e["address"].rsplit(":", 1)[1]) for e in eps if e["transport"] in ("tcp", "socketcand")}
        assert tcp_ports == {port for proto, _, port, state in socks if proto == "tcp" and state == "LISTEN"}, listening
        check_udp(status_sock, beacon_sock, "127.0.0.1")
    finally:
        assert b.stop() == 0
    assert not run_dir.exists(), "the run folder was left behind"


def test_bind_moves_every_tcp_server_and_udp_still_goes_to_loopback(tmp_path, udp_ports):
    alias = "127.0.0.2"
    try:
        probe = socket.socket()
        probe.bind((alias, 0))
        probe.close()
    except OSError as exc:
        pytest.skip(f"no loopback alias {alias}: {exc}")
    status_sock, beacon_sock = udp_ports
    path = scenario_copy(tmp_path, status_sock.getsockname()[1], beacon_sock.getsockname()[1])
    b = start_bridge(tmp_path, str(path), "--bind", alias, "--status-interval", "0")
    try:
        servers = [e for e in b.endpoints if e["transport"] in ("tcp", "socketcand")]
        assert len(servers) == 8  # seven devices (the DVL too) and the console
        wrong = [e["device"] for e in servers if not e["address"].startswith(alias + ":")]
        assert not wrong, f"devices ignoring --bind in the endpoints table: {wrong}"
        for e in servers:
            host, port = ac.host_port(e["address"])
            socket.create_connection((host, port), timeout=5).close()  # it listens there
            with pytest.raises(OSError):
                socket.create_connection(("127.0.0.1", port), timeout=2).close()  # and only there
        assert all(e.get("host", alias) == alias for e in servers)  # socketcand's python-can arguments
        socks = ac.inet_sockets(b.proc.pid)
        assert socks and all(addr == alias for _, addr, _, _ in socks), socks
        check_udp(status_sock, beacon_sock, alias)
    finally:
        assert b.stop() == 0


# ------------------------------------------------------------------ scenario files are data

def _after(text: str, anchor: str, old: str, new: str) -> str:
    """Replace the first ``old`` after ``anchor``."""
    i = text.index(anchor)
    j = text.index(old, i)
    return text[:j] + new + text[j + len(old):]


def _lines_of(text: str, needle: str) -> int:
    return text[:text.index(needle)].count("\n") + 1


def _cases() -> list:
    t = DEFAULT
    dev = lambda name, old, new: _after(t, f'name = "{name}"', old, new)  # noqa: E731
    return [
        pytest.param("malformed-toml", _after(t, 'name = "sonar_ddf"', 'sensor = "sonar"', 'sensor = "sonar'),
                     r"scenario\.toml:(?P<line>\d+): not valid TOML", 'sensor = "sonar\n', id="malformed-toml"),
        pytest.param("unknown-option", dev("sonar_ddf", "port = 0", "frame_rate = 10\nport = 0"),
                     r"scenario\.toml:(?P<line>\d+): \[devices\.sonar_ddf(\.frame_rate)?\]: .*unknown option "
                     r"'frame_rate'; did you mean 'frame_rate_hz'\?", "frame_rate = 10",
                     id="unknown-option"),
        pytest.param("pty-dotdot", dev("vesc_uart", "controller_id = 1", 'controller_id = 1\npath = "../escape"'),
                     r"scenario\.toml:(?P<line>\d+): \[devices\.vesc_uart(\.path)?\]: .*'\.\./escape' leaves",
                     'path = "../escape"', id="pty-dotdot"),
        pytest.param("pty-absolute", dev("vrcsr", "group_id = 0x81", 'group_id = 0x81\npath = "/etc/x"'),
                     r"scenario\.toml:(?P<line>\d+): \[devices\.vrcsr(\.path)?\]: .*'/etc/x' is absolute",
                     'path = "/etc/x"', id="pty-absolute"),
        pytest.param("slcan-absolute", dev("dronecan_esc", "node_id = 20", 'node_id = 20\npath = "/tmp/slcan0"'),
                     r"scenario\.toml:(?P<line>\d+): \[devices\.dronecan_esc(\.path)?\]: .*'/tmp/slcan0' is absolute",
                     'path = "/tmp/slcan0"', id="slcan-absolute"),
        pytest.param("modbus-rtu-dotdot", dev("depth", "device_id = 1 ", 'path = "../../depth.tty"\ndevice_id = 1 '),
                     r"scenario\.toml:(?P<line>\d+): \[devices\.depth(\.path)?\]: .*'\.\./\.\./depth\.tty' leaves",
                     'path = "../../depth.tty"', id="modbus-rtu-dotdot"),
        pytest.param("aris-record", t.replace('# record = "out/sonar.aris"       # optional .aris recording',
                                              'record = "../../x.aris"'),
                     r"scenario\.toml:(?P<line>\d+): \[devices\.sonar_aris(\.record)?\]: .*'\.\./\.\./x\.aris' leaves",
                     'record = "../../x.aris"', id="aris-record"),
        pytest.param("mesh-escape", t.replace('primitive = "box"\nmaterial = "plastic"',
                                              'mesh = "../../../etc/passwd"\nmaterial = "plastic"'),
                     r"scenario\.toml:(?P<line>\d+): \[objects\.cuboid\.mesh\]: path '\.\./\.\./\.\./etc/passwd' "
                     r"leaves the scenario folder", 'mesh = "../../../etc/passwd"', id="mesh-escape"),
        pytest.param("profile-dotdot", t.replace('profile = "cyclops"', 'profile = "../../outside/cyclops"'),
                     r"scenario\.toml:(?P<line>\d+): \[vehicle\.profile\]: .*leaves",
                     'profile = "../../outside/cyclops"', id="profile-dotdot"),
        pytest.param("profile-absolute", t.replace('profile = "didson_hf"', 'profile = "{outside}/mysonar"'),
                     r"scenario\.toml:(?P<line>\d+): \[sensors\.sonar\.profile\]: .*absolute",
                     'profile = "{outside}/mysonar"', id="profile-absolute"),
        pytest.param("profile-bad-key", t.replace('profile = "didson_hf"', 'profile = "mysonar"'),
                     r"mysonar\.toml:(?P<line>\d+): \[window\.sampels\]: .*(did you mean|valid keys)",
                     "sampels", id="profile-bad-key"),
    ]


@pytest.fixture(scope="module")
def error_runs(tmp_path_factory):
    """Every case run at once (each ``hilsim run`` stops at load): id -> (rc, stderr, scenario text)."""
    root = tmp_path_factory.mktemp("bad")
    outside = root / "outside"
    (outside / "sonars").mkdir(parents=True)
    (outside / "vehicles").mkdir()
    (outside / "cyclops.toml").write_text((ROOT / "devices" / "vehicles" / "cyclops.toml").read_text())
    sonar = (ROOT / "devices" / "sonars" / "didson_hf.toml").read_text()
    (outside / "mysonar.toml").write_text(sonar)
    procs = {}
    for p in _cases():
        case_id, text = p.values[0], p.values[1]
        folder = root / "scenarios" / case_id
        folder.mkdir(parents=True)
        (folder / "sonars").mkdir()
        (folder / "sonars" / "mysonar.toml").write_text(sonar.replace("\nsamples   =", "\nsampels   ="))
        text = text.replace("{outside}", str(outside))
        (folder / "scenario.toml").write_text(text)
        procs[case_id] = (subprocess.Popen(
            [sys.executable, "-m", "hilsim", "run", str(folder / "scenario.toml"), "--fast", "--duration", "0.2",
             "--status-interval", "0", "--pty-dir", str(folder / "run")],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=folder), text, folder)
    out = {}
    deadline = time.monotonic() + 120
    for case_id, (proc, text, folder) in procs.items():
        try:
            stdout, stderr = proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            stdout, stderr = proc.communicate()
        out[case_id] = (proc.returncode, stderr, text, folder)
    return out


@pytest.mark.parametrize("case_id, text, pattern, where", _cases())
def test_bad_scenario_stops_with_file_line_and_key(error_runs, case_id, text, pattern, where):
    rc, stderr, text, folder = error_runs[case_id]
    assert "Traceback" not in stderr, stderr
    assert rc == 1, (rc, stderr[-2000:])
    errors = [ln for ln in stderr.splitlines() if ln.startswith("hilsim run: error:")]
    assert len(errors) == 1, stderr[-2000:]
    m = re.search(pattern, errors[0])
    assert m is not None, errors[0]
    if case_id != "profile-bad-key":  # the line in the scenario file
        where = where.replace("{outside}", str(folder.parent.parent / "outside"))
        assert int(m.group("line")) == _lines_of(text, where), errors[0]


def test_a_device_that_cannot_start_is_named_with_its_line(tmp_path, udp_ports):
    """An error when a device opens its link (here a Modbus TCP port already taken) is one
    line naming the scenario, the device's entry and the cause, and nothing is left behind."""
    status_sock, beacon_sock = udp_ports
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        text = _after(DEFAULT, 'name = "depth"', "port = 0", f"port = {port}")
        path = scenario_copy(tmp_path, status_sock.getsockname()[1], beacon_sock.getsockname()[1], text)
        run_dir = tmp_path / "run"
        proc = subprocess.run(
            [sys.executable, "-m", "hilsim", "run", str(path), "--fast", "--duration", "0.2",
             "--status-interval", "0", "--pty-dir", str(run_dir)],
            capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 1, (proc.returncode, proc.stderr[-2000:])
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("hilsim run: error:")]
    assert len(errors) == 1, proc.stderr[-2000:]
    m = re.search(r"scenario\.toml:(?P<line>\d+): \[devices\.depth\]: cannot start: ", errors[0])
    assert m is not None, errors[0]
    written = path.read_text()
    entry = written[:written.index('name = "depth"')].rstrip("\n")
    assert int(m.group("line")) == entry.count("\n") + 1  # the entry's [[devices]] line
    assert written.splitlines()[int(m.group("line")) - 1] == "[[devices]]"
    assert not list(run_dir.glob("*")), "pty symlinks left behind"
