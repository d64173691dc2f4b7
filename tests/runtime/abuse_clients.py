"""Clients of a running bridge, well-behaved and abusive, for tests/runtime/test_abuse.py,
tests/runtime/test_soak.py and benchmarks/soak.py.

Every client is a daemon thread with plain sockets or pyserial; every loop is bounded by a
stop event, socket timeouts and deadlines. Wire formats are packed and parsed here with
struct at the offsets of protocols/*.md (hilsim's encoders only for the Oculus fire and the
ARIS commands and frame parts, as tests/devices does; dronecan's own code for DroneCAN).

Well-behaved clients count what they get in :class:`Stats`: ``received`` frames or replies,
``lost`` requests never answered (request/response protocols), ``gaps`` frame numbers
missing from a numbered stream, ``rtts`` [s] round trips. Abusive clients are functions
that open sockets and hand them back (the caller holds or closes them) or threads that
blast bytes until stopped.
"""

from __future__ import annotations

import os
import random
import re
import socket
import struct
import threading
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

# ------------------------------------------------------------------ the bridge process


def proc_stats(pid: int) -> tuple[float, int]:
    """(RSS [MB], open file descriptors) of process ``pid`` (psutil if installed, else /proc)."""
    try:
        import psutil

        p = psutil.Process(pid)
        return p.memory_info().rss / 1e6, p.num_fds()
    except ImportError:
        rss = 0.0
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) * 1024 / 1e6
        return rss, len(os.listdir(f"/proc/{pid}/fd"))


def accept_backlog(addresses: list[str]) -> dict[str, int]:
    """Connections waiting in each listening socket's accept queue (``/proc/net/tcp``: a LISTEN
    row's rx_queue). A connection reset before the server accepted it stays in that queue and is
    accepted later, taking a client slot until its first read fails: after a connect flood the
    servers are only settled once these queues are empty."""
    ports = {int(host_port(a)[1]): a for a in addresses}
    out = {a: 0 for a in addresses}
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            port = int(f[1].rsplit(":", 1)[1], 16)
            if f[3] == "0A" and port in ports:  # 0A: TCP_LISTEN
                out[ports[port]] += int(f[4].split(":")[1], 16)
    return out


def cpu_seconds(pid: int) -> float:
    """User + system CPU time [s] process ``pid`` has used (its own threads, not its children)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


STATUS_RE = re.compile(r"t=([0-9.]+)s depth .*?\| late ticks (\d+), skipped (\d+) \| (.*)$")
DEVICE_RE = re.compile(r"(\w+)(?:\(([^)]*)\))?")


def parse_status(line: str) -> dict[str, Any] | None:
    """A bridge status line -> {"t": s, "late_ticks": n, "skipped_ticks": n, "devices": {name: {counter: value}}}."""
    m = STATUS_RE.search(line)
    if m is None:
        return None
    devices: dict[str, dict[str, float]] = {}
    for name, body in DEVICE_RE.findall(m.group(4)):
        counters: dict[str, float] = {}
        for part in filter(None, body.split(", ")):
            k, _, v = part.rpartition(" ")
            try:
                counters[k] = float(v)
            except ValueError:
                pass
        devices[name] = counters
    return {"t": float(m.group(1)), "late_ticks": int(m.group(2)), "skipped_ticks": int(m.group(3)),
            "devices": devices}


def last_status(log_text: str) -> dict[str, Any] | None:
    for line in reversed(log_text.splitlines()):
        st = parse_status(line)
        if st is not None:
            return st
    return None


def host_port(address: str) -> tuple[str, int]:
    host, port = address.rsplit(":", 1)
    return host, int(port)


# ------------------------------------------------------------------ base


@dataclass
class Stats:
    sent: int = 0        # requests or commands sent
    received: int = 0    # replies or frames received
    lost: int = 0        # requests never answered
    gaps: int = 0        # numbered frames missing from the stream
    bad: int = 0         # replies that did not parse or check
    reconnects: int = 0
    rtts: list[float] = field(default_factory=list)
    last_value: float = float("nan")  # protocol-specific (an rpm, a depth)

    def snapshot(self) -> tuple[int, float]:
        return self.received, time.monotonic()


class Client(threading.Thread):
    """A well-behaved client: ``start()``, then ``stop()``; ``error`` holds the first thing that
    went wrong. With ``restart`` it reconnects after an error (counted in ``stats.reconnects``,
    every error kept in ``errors``), as a long-running client would."""

    kind = "client"
    restart = False

    def __init__(self, name: str) -> None:
        super().__init__(name=name, daemon=True)
        self.stats = Stats()
        self.stopping = threading.Event()
        self.error: str | None = None
        self.errors: list[str] = []

    def run(self) -> None:
        for _ in range(1000):  # bounded: a client that keeps failing gives up
            try:
                self.body()
                return
            except Exception as exc:  # noqa: BLE001 - reported by the test
                if self.stopping.is_set():
                    return
                self.errors.append(f"{time.strftime('%H:%M:%S')} {type(exc).__name__}: {exc}")
                self.error = self.error or self.errors[-1]
                if not self.restart:
                    return
                self.stats.reconnects += 1
                self.stopping.wait(0.5)

    def body(self) -> None:
        raise NotImplementedError

    def stop(self, timeout: float = 5.0) -> None:
        self.stopping.set()
        self.join(timeout)

    def paced(self, rate_hz: float) -> Iterable[int]:
        """Yield at ``rate_hz`` on an absolute schedule (a late tick resets it) until stopped."""
        period = 1.0 / rate_hz
        t_next = time.monotonic()
        i = 0
        while not self.stopping.is_set():
            yield i
            i += 1
            t_next += period
            now = time.monotonic()
            if t_next < now - period:
                t_next = now
            self.stopping.wait(max(0.0, t_next - now))


def recv_exact(sock: socket.socket, n: int, deadline: float) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        sock.settimeout(max(0.01, deadline - time.monotonic()))
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise EOFError(f"closed after {len(buf)} of {n} bytes")
        buf += chunk
    return bytes(buf)


# ------------------------------------------------------------------ sonars


class DdfReader(Client):
    """The DIDSON-like stream: file header, then frames; counts frames and frame-number gaps."""

    kind = "ddf"

    def __init__(self, address: str, rate_hz: float | None = 8.0, beams: int = 96, samples: int = 512) -> None:
        super().__init__("ddf-reader")
        self.address, self.rate, self.frame = address, rate_hz, 1024 + beams * samples
        self.numbers: list[int] = []

    def body(self) -> None:
        with socket.create_connection(host_port(self.address), timeout=10) as s:
            if self.rate:
                s.sendall(f"RATE {self.rate:g}\n".encode())
            assert recv_exact(s, 1024, time.monotonic() + 10)[:4] == b"DDF\x04"
            last = None
            while not self.stopping.is_set():
                try:
                    raw = recv_exact(s, self.frame, time.monotonic() + 5)
                except (socket.timeout, TimeoutError):
                    continue  # no frame for 5 s: the rate check will show it
                n = struct.unpack_from("<i", raw, 0)[0]
                if last is not None and n > last + 1:
                    self.stats.gaps += n - last - 1
                last = n
                self.numbers.append(n)
                self.stats.received += 1


class OculusFirer(Client):
    """Oculus: fire (v2, HF, 3 m, ping rate code ``rate``), count the SimplePingResults."""

    kind = "oculus"

    def __init__(self, address: str, rate: int = 3) -> None:  # 3: low, 5 Hz
        super().__init__("oculus-firer")
        self.address, self.rate = address, rate

    def body(self) -> None:
        from hilsim.protocols import oculus as oc

        fire = oc.encode_fire(oc.Fire(master_mode=oc.MODE_HF, ping_rate=self.rate, flags=0x09, range=3.0,
                                      gain=100.0, version=2))
        with socket.create_connection(host_port(self.address), timeout=10) as s:
            s.sendall(fire)
            self.stats.sent += 1
            while not self.stopping.is_set():
                try:
                    head = recv_exact(s, 16, time.monotonic() + 5)
                except (socket.timeout, TimeoutError):
                    continue
                if struct.unpack_from("<H", head, 0)[0] != 0x4F53:
                    self.stats.bad += 1
                    raise ValueError("lost step in the Oculus stream")
                size = struct.unpack_from("<I", head, 10)[0]
                recv_exact(s, size, time.monotonic() + 10)
                if struct.unpack_from("<H", head, 6)[0] == 0x23:
                    self.stats.received += 1


def udp_socket(rcvbuf: int | None = None) -> socket.socket:
    u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    if rcvbuf:
        u.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    u.bind(("127.0.0.1", 0))
    return u


def aris_setup(sock: socket.socket, udp_port: int, frame_rate: float = 5.0, cookie: int = 7) -> None:
    from hilsim.protocols import aris as ar

    s = ar.AcousticSettings.for_window(0.83, 5.83, 512, 1482.0, frame_rate=frame_rate, cookie=cookie)
    for c in (ar.SetFrameStreamReceiver(udp_port), ar.SetDateTime("2024-Jan-01 00:00:00"), ar.SetAcoustics(s),
              ar.SetSalinity(0), ar.SetFocus(2.0), ar.Ping()):
        sock.sendall(ar.encode_command(c))


class ArisClient(Client):
    """ARIS: settings + a UDP receiver, PING every 0.5 s; counts assembled frames."""

    kind = "aris"

    def __init__(self, address: str, frame_rate: float = 5.0) -> None:
        super().__init__("aris-client")
        self.address, self.frame_rate = address, frame_rate

    def body(self) -> None:
        from hilsim.protocols import aris as ar

        udp = udp_socket(1 << 20)
        asm = ar.FrameAssembler()
        try:
            with socket.create_connection(host_port(self.address), timeout=10) as s:
                aris_setup(s, udp.getsockname()[1], self.frame_rate)
                last_ping = time.monotonic()
                udp.settimeout(0.2)
                while not self.stopping.is_set():
                    if time.monotonic() - last_ping > 0.5:
                        s.sendall(ar.encode_command(ar.Ping()))
                        self.stats.sent += 1
                        last_ping = time.monotonic()
                    try:
                        dgram = udp.recv(65536)
                    except (socket.timeout, TimeoutError):
                        continue
                    for ev in asm.receive_datagram(dgram):
                        if isinstance(ev, ar.AssembledFrame):
                            self.stats.received += 1
        finally:
            udp.close()


# ------------------------------------------------------------------ Modbus


def crc16_modbus(data: bytes) -> int:
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def rtu_request(unit: int, address: int, count: int, fc: int = 3) -> bytes:
    f = struct.pack(">BBHH", unit, fc, address, count)
    return f + struct.pack("<H", crc16_modbus(f))


def mbap_request(tid: int, unit: int, address: int, count: int, fc: int = 3) -> bytes:
    return struct.pack(">HHHBBHH", tid & 0xFFFF, 0, 6, unit, fc, address, count)


class DvlReader(Client):
    """A DVL driver: reads the JSON report lines (written from Water Linked's documented API, not
    from hilsim's encoder); ``received`` counts velocity reports, ``bad`` lines that do not parse."""

    kind = "dvl"

    def __init__(self, address: str) -> None:
        super().__init__("dvl-reader")
        self.address = address

    def body(self) -> None:
        import json

        host, port = host_port(self.address)
        with socket.create_connection((host, port), timeout=5) as s:
            buf = b""
            while not self.stopping.is_set():
                chunk = s.recv(65536)
                if not chunk:
                    raise ConnectionError("the DVL closed the connection")
                buf += chunk
                *lines, buf = buf.split(b"\n")
                for line in lines:
                    if not line.strip():
                        continue
                    try:
                        report = json.loads(line)
                    except ValueError:
                        self.stats.bad += 1
                        continue
                    if report.get("type") == "velocity":
                        self.stats.received += 1


class ModbusTcpPoller(Client):
    """Reads ``count`` holding registers every 1 / ``rate_hz`` s; a reply not back within
    ``timeout`` s is lost (the connection is then reopened to resync)."""

    kind = "modbus-tcp"

    def __init__(self, address: str, unit: int, register: int, count: int, rate_hz: float = 100.0,
                 timeout: float = 2.0, name: str = "modbus-tcp") -> None:
        super().__init__(name)
        self.address, self.unit, self.register, self.count = address, unit, register, count
        self.rate, self.timeout = rate_hz, timeout

    def _connect(self) -> socket.socket:
        s = socket.create_connection(host_port(self.address), timeout=10)
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return s

    def body(self) -> None:
        s = self._connect()
        n = 9 + 2 * self.count
        try:
            for i in self.paced(self.rate):
                tid = i & 0xFFFF
                t0 = time.perf_counter()
                s.sendall(mbap_request(tid, self.unit, self.register, self.count))
                self.stats.sent += 1
                try:
                    reply = recv_exact(s, n, time.monotonic() + self.timeout)
                except (socket.timeout, TimeoutError, EOFError, ConnectionError):
                    self.stats.lost += 1
                    s.close()
                    s = self._connect()
                    self.stats.reconnects += 1
                    continue
                self.stats.rtts.append(time.perf_counter() - t0)
                t_id, pid, length, unit, fc, nbytes = struct.unpack_from(">HHHBBB", reply)
                if (t_id, pid, length, unit, fc, nbytes) != (tid, 0, 3 + 2 * self.count, self.unit, 3, 2 * self.count):
                    self.stats.bad += 1
                else:
                    self.stats.received += 1
        finally:
            s.close()


class ModbusRtuPoller(Client):
    """Modbus RTU on the pty: one read every 1 / ``rate_hz`` s, the reply's CRC checked."""

    kind = "modbus-rtu"

    def __init__(self, path: str, unit: int, register: int, count: int, baudrate: int = 9600,
                 rate_hz: float = 10.0, timeout: float = 1.0, name: str = "modbus-rtu") -> None:
        super().__init__(name)
        self.path, self.unit, self.register, self.count = path, unit, register, count
        self.baudrate, self.rate, self.timeout = baudrate, rate_hz, timeout

    def body(self) -> None:
        import serial

        n = 5 + 2 * self.count
        req = rtu_request(self.unit, self.register, self.count)
        with serial.Serial(self.path, self.baudrate, timeout=0.05) as port:
            for _ in self.paced(self.rate):
                t0 = time.perf_counter()
                port.write(req)
                self.stats.sent += 1
                reply = read_serial(port, n, time.monotonic() + self.timeout)
                if len(reply) < n:
                    self.stats.lost += 1
                    time.sleep(0.02)
                    port.reset_input_buffer()
                    continue
                self.stats.rtts.append(time.perf_counter() - t0)
                ok = reply[:3] == bytes([self.unit, 3, 2 * self.count]) and \
                    struct.unpack("<H", reply[-2:])[0] == crc16_modbus(reply[:-2])
                self.stats.received += ok
                self.stats.bad += not ok


def read_serial(port: Any, n: int, deadline: float) -> bytes:
    buf = b""
    while len(buf) < n and time.monotonic() < deadline:
        buf += port.read(n - len(buf))
    return buf


# ------------------------------------------------------------------ thrusters on serial


def vesc_packet(payload: bytes) -> bytes:
    crc = 0  # CRC-16/XMODEM
    for b in payload:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return bytes([2, len(payload)]) + payload + struct.pack(">H", crc) + b"\x03"


class VescUartPoller(Client):
    """VESC UART: COMM_GET_VALUES every 1 / ``rate_hz`` s; the 74-byte reply's rpm in last_value."""

    kind = "vesc-uart"

    def __init__(self, path: str, baudrate: int = 115200, rate_hz: float = 20.0, timeout: float = 1.0) -> None:
        super().__init__("vesc-uart-poller")
        self.path, self.baudrate, self.rate, self.timeout = path, baudrate, rate_hz, timeout

    def body(self) -> None:
        import serial

        with serial.Serial(self.path, self.baudrate, timeout=0.05) as port:
            for _ in self.paced(self.rate):
                t0 = time.perf_counter()
                port.write(vesc_packet(b"\x04"))
                self.stats.sent += 1
                reply = read_serial(port, 79, time.monotonic() + self.timeout)
                if len(reply) < 79:
                    self.stats.lost += 1
                    time.sleep(0.02)
                    port.reset_input_buffer()
                    continue
                self.stats.rtts.append(time.perf_counter() - t0)
                if reply[:3] == b"\x02\x4a\x04" and reply[-1] == 3 and vesc_packet(reply[2:76]) == reply:
                    self.stats.received += 1
                    self.stats.last_value = struct.unpack_from(">i", reply, 2 + 23)[0]
                else:
                    self.stats.bad += 1


def vrcsr_request(powers: list[float], reply_node: int, flags: int = 2, node: int = 0x81) -> bytes:
    header = struct.pack("<HBBBB", 0x5FF5, node, flags, 0xF0, 2 + 4 * len(powers))
    payload = struct.pack("<BB", 0xAA, reply_node) + b"".join(struct.pack("<f", p) for p in powers)
    return header + struct.pack("<I", zlib.crc32(header)) + payload + struct.pack("<I", zlib.crc32(payload))


class VrcsrPoller(Client):
    """VRCSR: a propulsion command to one thruster's node id (``power`` on motor ``motor``)
    asking for the standard response, every 1 / ``rate_hz`` s; its rpm in last_value."""

    kind = "vrcsr"

    def __init__(self, path: str, motor: int = 7, power: float = 0.2, baudrate: int = 115200,
                 rate_hz: float = 20.0, timeout: float = 1.0) -> None:
        super().__init__("vrcsr-poller")
        self.path, self.motor, self.power = path, motor, power
        self.baudrate, self.rate, self.timeout = baudrate, rate_hz, timeout

    def body(self) -> None:
        import serial

        node = self.motor + 1
        req = vrcsr_request([0.0] * self.motor + [self.power], reply_node=node, node=node)
        with serial.Serial(self.path, self.baudrate, timeout=0.05) as port:
            for _ in self.paced(self.rate):
                t0 = time.perf_counter()
                port.write(req)
                self.stats.sent += 1
                resp = read_serial(port, 32, time.monotonic() + self.timeout)
                if len(resp) < 32:
                    self.stats.lost += 1
                    time.sleep(0.02)
                    port.reset_input_buffer()
                    continue
                self.stats.rtts.append(time.perf_counter() - t0)
                f = struct.unpack("=HBBBBIBffffBI", resp)
                if f[0] == 0x0FF0 and f[1] == node and f[12] == zlib.crc32(resp[10:28]):
                    self.stats.received += 1
                    self.stats.last_value = f[7]
                else:
                    self.stats.bad += 1


# ------------------------------------------------------------------ CAN


def vesc_can_id(command: int, controller: int) -> int:
    return (command << 8) | controller


SET_RPM, STATUS_1 = 3, 9


def socketcand_send(ident: int, data: bytes) -> bytes:
    return f"< send {ident:08X} {len(data):X} {' '.join(f'{b:x}' for b in data)} >".encode()


def socketcand_handshake(sock: socket.socket, channel: str = "can0", deadline: float = 10.0) -> bytes:
    """``< hi >``, open, rawmode; returns bytes received after the last ``< ok >``."""
    end = time.monotonic() + deadline
    buf = b""

    def expect(token: bytes) -> None:
        nonlocal buf
        while token not in buf:
            sock.settimeout(max(0.01, end - time.monotonic()))
            chunk = sock.recv(4096)
            if not chunk:
                raise EOFError(f"socketcand closed while waiting for {token!r} (got {buf!r})")
            buf += chunk
        buf = buf[buf.index(token) + len(token):]

    expect(b"< hi >")
    sock.sendall(f"< open {channel} >".encode())
    expect(b"< ok >")
    sock.sendall(b"< rawmode >")
    expect(b"< ok >")
    return buf


class SocketcandCommander(Client):
    """VESC CAN over socketcand: SET_RPM ``erpm`` to ``controller`` at ``rate_hz``, counts every
    frame and that controller's STATUS_1 (its ERPM in last_value)."""

    kind = "socketcand"

    def __init__(self, address: str, controller: int = 2, erpm: int = 3000, rate_hz: float = 20.0) -> None:
        super().__init__("socketcand-commander")
        self.address, self.controller, self.erpm, self.rate = address, controller, erpm, rate_hz
        self.frames = 0

    def body(self) -> None:
        status_id = f"{vesc_can_id(STATUS_1, self.controller):08X}".encode()
        status_re = re.compile(rb"< frame " + status_id + rb" [0-9.]+ ([0-9A-F]{16}) >")
        cmd = socketcand_send(vesc_can_id(SET_RPM, self.controller), struct.pack(">i", self.erpm))
        with socket.create_connection(host_port(self.address), timeout=10) as s:
            buf = socketcand_handshake(s)
            s.settimeout(0.02)
            next_cmd = 0.0
            while not self.stopping.is_set():
                if time.monotonic() >= next_cmd:
                    s.sendall(cmd)
                    self.stats.sent += 1
                    next_cmd = time.monotonic() + 1.0 / self.rate
                try:
                    chunk = s.recv(1 << 16)
                except (socket.timeout, TimeoutError):
                    continue
                if not chunk:
                    raise EOFError("socketcand closed the connection")
                buf += chunk
                end = buf.rfind(b">")
                if end < 0:
                    continue
                done = buf[:end + 1]
                self.frames += done.count(b"< frame ")  # C speed: a flood forwarded to us costs little
                for data in status_re.findall(done):
                    self.stats.received += 1
                    self.stats.last_value = struct.unpack(">i", bytes.fromhex(data[:8].decode()))[0]
                buf = buf[end + 1:]


ESC_STATUS_DTID, NODE_STATUS_DTID = 1034, 341


class SlcanCommander(Client):
    """DroneCAN over the slcan pty: esc.RawCommand ``[value]`` (ESC 0 only) at ``rate_hz``;
    counts esc.Status frames from node 20, acks and BELs; ESC 0's rpm (decoded with
    dronecan's own code) in last_value."""

    kind = "slcan"

    def __init__(self, path: str, value: int = 2000, rate_hz: float = 20.0, node_id: int = 11) -> None:
        super().__init__("slcan-commander")
        self.path, self.value, self.rate, self.node_id = path, value, rate_hz, node_id
        self.acks = 0
        self.bels = 0
        self.status_frames = 0

    def command_lines(self, tid: int) -> bytes:
        import dronecan
        from dronecan.transport import Transfer

        t = Transfer(payload=dronecan.uavcan.equipment.esc.RawCommand(cmd=[self.value]),
                     source_node_id=self.node_id, transfer_id=tid % 32, transfer_priority=20)
        return b"".join(f"T{f.message_id:08X}{len(f.bytes)}{bytes(f.bytes).hex().upper()}\r".encode()
                        for f in t.to_frames())

    def body(self) -> None:
        import serial

        with serial.Serial(self.path, 115200, timeout=0.02) as port:
            port.write(b"C\rS8\rO\r")
            buf = b""
            pending: list[tuple[int, bytes]] = []
            next_cmd, tid = 0.0, 0
            while not self.stopping.is_set():
                if time.monotonic() >= next_cmd:
                    port.write(self.command_lines(tid))
                    tid += 1
                    self.stats.sent += 1
                    next_cmd = time.monotonic() + 1.0 / self.rate
                buf += port.read(max(1, min(port.in_waiting, 1 << 16)))
                last = max(buf.rfind(b"\r"), buf.rfind(b"\a"))
                if last < 0:
                    buf = buf[-256:]
                    continue
                complete, buf = buf[:last + 1], buf[last + 1:]
                self.bels += complete.count(b"\a")
                for ln in re.split(rb"[\r\a]", complete)[:-1]:
                    self._line(ln, pending)

    def _line(self, ln: bytes, pending: list[tuple[int, bytes]]) -> None:
        if ln in (b"z", b"Z"):
            self.acks += 1
            return
        if not ln.startswith(b"T") or len(ln) < 10:
            return
        try:
            ident, dlc = int(ln[1:9], 16), int(ln[9:10], 16)
            data = bytes.fromhex(ln[10:10 + 2 * dlc].decode())
        except ValueError:
            self.stats.bad += 1
            return
        if (ident >> 8) & 0xFFFF != ESC_STATUS_DTID or ident & 0x7F != 20:
            return
        self.status_frames += 1
        tail = data[-1]
        if tail & 0x80:  # start of transfer
            pending.clear()
        pending.append((ident, data))
        if tail & 0x40 and pending:  # end of transfer
            self._transfer(pending)
            pending.clear()

    def _transfer(self, frames: list[tuple[int, bytes]]) -> None:
        from dronecan.transport import Frame, Transfer

        try:
            tr = Transfer()
            tr.from_frames([Frame(i, bytearray(d)) for i, d in frames])
        except Exception:  # noqa: BLE001 - a transfer cut by a dropped frame
            self.stats.bad += 1
            return
        self.stats.received += 1
        if tr.payload.esc_index == 0:
            self.stats.last_value = tr.payload.rpm


# ------------------------------------------------------------------ abusive clients


def connect_flood(address: str, n: int, deadline: float) -> dict[str, int]:
    """``n`` connects, each closed at once with a reset, until ``deadline`` (monotonic)."""
    out = {"connected": 0, "failed": 0}
    host, port = host_port(address)
    for _ in range(n):
        if time.monotonic() > deadline:
            break
        try:
            s = socket.create_connection((host, port), timeout=1.0)
        except OSError:
            out["failed"] += 1
            continue
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        s.close()
        out["connected"] += 1
    return out


def open_many(address: str, n: int, rcvbuf: int | None = 4096) -> list[socket.socket]:
    """``n`` connections opened at once (small receive buffers: they may never read)."""
    host, port = host_port(address)
    socks = []
    for _ in range(n):
        s = socket.socket()
        if rcvbuf:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        s.settimeout(2.0)
        try:
            s.connect((host, port))
        except OSError:
            s.close()
            continue
        socks.append(s)
    return socks


def refused(sock: socket.socket) -> bool:
    """Whether the server closed this connection (EOF or reset, nothing else pending)."""
    timeout = sock.gettimeout()
    sock.setblocking(False)  # with a timeout set, recv would first wait for data
    try:
        data = sock.recv(1, socket.MSG_PEEK)
    except BlockingIOError:
        return False
    except OSError:
        return True
    finally:
        sock.settimeout(timeout)
    return data == b""


def reset(sock: socket.socket) -> None:
    """Close with RST."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    except OSError:
        pass
    sock.close()


def _oculus_fire(rate_code: int) -> bytes:
    from hilsim.protocols import oculus as oc

    return oc.encode_fire(oc.Fire(master_mode=oc.MODE_HF, ping_rate=rate_code, flags=0x09, range=3.0,
                                  gain=100.0, version=2))


def _aris_ping() -> bytes:
    from hilsim.protocols import aris as ar

    return ar.encode_command(ar.Ping())


def _modbus_pipeline(sock: socket.socket) -> None:
    try:  # pipelined requests whose replies are never read
        sock.send(b"".join(mbap_request(i, 1, 2, 2) for i in range(100)), socket.MSG_DONTWAIT)
    except OSError:
        pass


@dataclass(frozen=True)
class WireKit:
    """How abuse clients speak one TCP protocol:

    partial: the first bytes of a valid client message (then the client vanishes);
    huge: a valid header announcing a huge (or the largest valid) length, without its body;
    never_reading(sock, udp, rate_code, frame_rate): make the server send to ``sock`` (which then
    never reads): the sonars with the well-behaved clients' settings (so they share their renders);
    junk: bytes that are not the protocol, costly for its decoder (64 KiB)."""

    partial: Callable[[], bytes]
    huge: Callable[[], bytes]
    never_reading: Callable[..., None]
    junk: Callable[[], bytes]


_MODBUS = WireKit(
    partial=lambda: mbap_request(1, 1, 2, 2)[:9],
    huge=lambda: struct.pack(">HHHB", 1, 0, 254, 1) + b"\x10\x00\x00",  # MBAP length 254, 3 of 253 bytes
    never_reading=lambda sock, udp, rate_code, frame_rate: _modbus_pipeline(sock),
    junk=lambda: random.Random(1).randbytes(65536))

#: one kit per TCP protocol the bridge serves; a TCP device without one is an error of the tests
#: (tests/runtime/test_abuse.py checks every TCP endpoint of the default scenario has a kit)
WIRE: dict[str, WireKit] = {
    "ddf-stream": WireKit(
        partial=lambda: b"RATE 1",
        huge=lambda: b"RATE " + b"9" * 20000,  # a command line that never ends
        never_reading=lambda sock, udp, rate_code, frame_rate: None,  # frames come by themselves
        junk=lambda: b"RATE 8\n" * 9362),  # valid commands, as fast as TCP carries them
    "oculus": WireKit(
        partial=lambda: _oculus_fire(0)[:30],
        huge=lambda: struct.pack("<HHHHHIH", 0x4F53, 0, 0, 0x15, 2, 0xFFFFFFF0, 0) + b"\x01\x02",
        never_reading=lambda sock, udp, rate_code, frame_rate: sock.sendall(_oculus_fire(rate_code)),
        junk=lambda: b"SO" * 32768),  # an id every two bytes
    "aris": WireKit(
        partial=lambda: _aris_ping()[:3],
        huge=lambda: struct.pack(">I", 0xFFFFFFF0) + b"\x08\x01",
        never_reading=lambda sock, udp, rate_code, frame_rate: aris_setup(sock, udp.getsockname()[1],
                                                                          frame_rate=frame_rate),
        junk=lambda: bytes(65536)),  # zero-length commands: every offset a candidate while resyncing
    "socketcand": WireKit(
        partial=lambda: b"< open ca",
        huge=lambda: b"< send 123 8 " + b"11 " * 3000,  # a message that never closes
        never_reading=lambda sock, udp, rate_code, frame_rate: socketcand_handshake(sock),
        junk=lambda: random.Random(1).randbytes(65536)),
    "modbus-keller": _MODBUS,
    "modbus-witmotion": _MODBUS,
    "dvl-json": WireKit(
        partial=lambda: b'{"command": "get_con',
        huge=lambda: b'{"command": "' + b"x" * 20000,  # a JSON line that never ends
        never_reading=lambda sock, udp, rate_code, frame_rate: None,  # reports come by themselves
        junk=lambda: b"{\n" * 32768),  # a malformed JSON line every two bytes, each answered
}


def kit(protocol: str) -> WireKit:
    """The abuse kit of ``protocol``; KeyError naming what to add for a TCP protocol without one."""
    if protocol not in WIRE:
        raise KeyError(f"no abuse kit for the TCP protocol {protocol!r}: add one to WIRE in "
                       f"tests/runtime/abuse_clients.py")
    return WIRE[protocol]


def partial_message(protocol: str) -> bytes:
    """The first bytes of a valid client message of ``protocol`` (then the client vanishes)."""
    return kit(protocol).partial()


def huge_header(protocol: str) -> bytes:
    """A valid header announcing a huge (or the largest valid) length, without its body."""
    return kit(protocol).huge()


def start_never_reading(protocol: str, sock: socket.socket, udp: socket.socket | None = None, *,
                        rate_code: int = 3, frame_rate: float = 5.0) -> None:
    """Make the server send to ``sock`` (which then never reads)."""
    kit(protocol).never_reading(sock, udp, rate_code, frame_rate)


def junk(protocol: str) -> bytes:
    """Bytes that are not the protocol, costly for its decoder (64 KiB)."""
    return kit(protocol).junk()


class Blaster(threading.Thread):
    """Sends ``data`` over and over to ``address`` until stopped (reconnecting when closed)."""

    def __init__(self, address: str, data: bytes, reconnect: bool = True) -> None:
        super().__init__(daemon=True, name=f"blaster-{address}")
        self.address, self.data, self.reconnect = address, data, reconnect
        self.stopping = threading.Event()
        self.sent = 0
        self.connections = 0

    def run(self) -> None:
        while not self.stopping.is_set():
            try:
                with socket.create_connection(host_port(self.address), timeout=1.0) as s:
                    self.connections += 1
                    s.settimeout(0.2)
                    while not self.stopping.is_set():
                        try:
                            self.sent += s.send(self.data)
                        except (socket.timeout, TimeoutError):
                            pass
            except OSError:
                pass
            if not self.reconnect:
                return
            self.stopping.wait(0.05)

    def stop(self, timeout: float = 5.0) -> None:
        self.stopping.set()
        self.join(timeout)


def close_all(socks: Iterable[socket.socket], rst: bool = True) -> None:
    for s in socks:
        try:
            reset(s) if rst else s.close()
        except OSError:
            pass


def wait_until(cond: Callable[[], bool], timeout: float, step: float = 0.1) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(step)
    return cond()


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    v = sorted(values)
    return v[min(len(v) - 1, int(q / 100.0 * len(v)))]


class ModbusFlooder(threading.Thread):
    """Pipelines ``in_flight`` requests as fast as replies come back (each client is held to its
    request budget by the server); counts the replies."""

    def __init__(self, address: str, unit: int = 1, register: int = 2, count: int = 2, in_flight: int = 32) -> None:
        super().__init__(daemon=True, name=f"modbus-flooder-{address}")
        self.address, self.unit, self.register, self.count, self.in_flight = address, unit, register, count, in_flight
        self.stopping = threading.Event()
        self.sent = 0
        self.replies = 0
        self.error: str | None = None

    def run(self) -> None:
        size = 9 + 2 * self.count
        try:
            with socket.create_connection(host_port(self.address), timeout=5) as s:
                s.sendall(b"".join(mbap_request(i, self.unit, self.register, self.count)
                                   for i in range(self.in_flight)))
                self.sent = self.in_flight
                s.settimeout(0.2)
                got = 0
                while not self.stopping.is_set():
                    try:
                        data = s.recv(1 << 16)
                    except (socket.timeout, TimeoutError):
                        continue
                    if not data:
                        raise EOFError("the server closed a flooder")
                    n, got = divmod(got + len(data), size)
                    self.replies += n
                    if n:
                        s.sendall(b"".join(mbap_request(self.sent + i, self.unit, self.register, self.count)
                                           for i in range(n)))
                        self.sent += n
        except Exception as exc:  # noqa: BLE001
            if not self.stopping.is_set():
                self.error = f"{type(exc).__name__}: {exc}"

    def stop(self, timeout: float = 5.0) -> None:
        self.stopping.set()
        self.join(timeout)


def _proc_tree(pid: int) -> list[int]:
    """``pid`` and its descendants (from /proc)."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d.name))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += children.get(p, [])
    return out


def inet_sockets(pid: int) -> list[tuple[str, str, int, str]]:
    """Every IPv4/IPv6 socket of process ``pid`` and its children: (tcp|udp, local address,
    local port, LISTEN|ESTABLISHED|...), from /proc (Linux)."""
    inodes: set[str] = set()
    for p in _proc_tree(pid):
        try:
            for fd in os.listdir(f"/proc/{p}/fd"):
                try:
                    target = os.readlink(f"/proc/{p}/fd/{fd}")
                except OSError:
                    continue
                if target.startswith("socket:["):
                    inodes.add(target[8:-1])
        except OSError:
            continue
    states = {"0A": "LISTEN", "01": "ESTABLISHED", "07": "CLOSE"}
    out = []
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        try:
            lines = Path(f"/proc/net/{proto}").read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            if f[9] not in inodes:
                continue
            addr_hex, port_hex = f[1].split(":")
            raw = bytes.fromhex(addr_hex)
            if len(raw) == 4:
                addr = socket.inet_ntop(socket.AF_INET, raw[::-1])
            else:  # 4 little-endian 32-bit words
                addr = socket.inet_ntop(socket.AF_INET6, b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4)))
            out.append((proto.rstrip("6"), addr, int(port_hex, 16), states.get(f[3], f[3])))
    return out


# ------------------------------------------------------------------ abuse in turns (benchmarks/soak.py)


ABUSE_KINDS = ("flood", "hold", "blast", "modbus-flood", "can-flood")
BLAST_TARGETS = ("aris", "oculus", "ddf-stream", "socketcand")


def tcp_servers(endpoints: list[dict]) -> list[dict]:
    """The TCP servers among ``endpoints`` that the abuse kits speak to (every one, in the default
    scenario: test_abuse checks it)."""
    out = []
    for e in endpoints:
        proto = "socketcand" if e["transport"] == "socketcand" else e["protocol"]
        if e["transport"] in ("tcp", "socketcand") and proto in WIRE:
            out.append({"protocol": proto, "address": e["address"]})
    return out


def tcp_without_kit(endpoints: list[dict]) -> list[str]:
    """TCP endpoints no abuse kit speaks to (should be none)."""
    return [f"{e['device']} ({e['protocol']})" for e in endpoints
            if e["transport"] == "tcp" and e["protocol"] not in WIRE]


def run_abuse(kind: str, endpoints: list[dict], seconds: float, turn: int) -> dict[str, Any]:
    """Run one kind of abuse for about ``seconds``, then release everything; returns figures."""
    servers = tcp_servers(endpoints)
    by_proto = {s["protocol"]: s for s in servers}
    t0 = time.monotonic()
    end = t0 + seconds
    out: dict[str, Any] = {"kind": kind}
    if kind == "flood":
        def one(s: dict) -> None:
            connect_flood(s["address"], 150, end)
            for _ in range(10):
                try:
                    c = socket.create_connection(host_port(s["address"]), timeout=1.0)
                    c.sendall(partial_message(s["protocol"]))
                    reset(c)
                except OSError:
                    pass
        threads = [threading.Thread(target=one, args=(s,), daemon=True) for s in servers]
        for t in threads:
            t.start()
        for t in threads:
            t.join(seconds + 5)
        out["connects"] = 160 * len(servers)
    elif kind == "hold":
        held: list[socket.socket] = []
        udps: list[socket.socket] = []
        for s in servers:
            n = 2 if s["protocol"] == "aris" else 4  # leave the well-behaved room to reconnect
            for i, k in enumerate(open_many(s["address"], n)):
                held.append(k)
                try:
                    if i == 0:
                        k.sendall(huge_header(s["protocol"]))
                    elif i == 1:
                        udps.append(udp_socket(4096))
                        start_never_reading(s["protocol"], k, udps[-1], rate_code=4, frame_rate=3.0)
                    elif i == 2:
                        k.shutdown(socket.SHUT_WR)
                except OSError:
                    pass
        time.sleep(max(0.0, end - time.monotonic()))
        out["held"] = len(held)
        close_all(held)
        close_all(udps, rst=False)
    elif kind == "blast":
        target = BLAST_TARGETS[turn % len(BLAST_TARGETS)]
        b = Blaster(by_proto[target]["address"], junk(target))
        b.start()
        time.sleep(max(0.0, end - time.monotonic()))
        b.stop()
        out.update(target=target, mb=round(b.sent / 1e6, 1))
    elif kind == "modbus-flood":
        flooders = [ModbusFlooder(by_proto[p]["address"], *args)
                    for p, args in (("modbus-keller", (1, 2, 2)), ("modbus-witmotion", (0x50, 0x34, 13)))
                    for _ in range(4)]
        for f in flooders:
            f.start()
        time.sleep(max(0.0, end - time.monotonic()))
        for f in flooders:
            f.stop()
        out["replies"] = sum(f.replies for f in flooders)
    elif kind == "can-flood":
        s = socket.create_connection(host_port(by_proto["socketcand"]["address"]), timeout=5)
        sent = 0
        try:
            socketcand_handshake(s)
            burst = b"< send 100 2 1 2 >" * 5000
            s.settimeout(0.2)
            while time.monotonic() < end:
                try:
                    sent += s.send(burst)
                except (socket.timeout, TimeoutError):
                    pass
        finally:
            reset(s)
        out["frames"] = sent // 19
    return out


def abuse_child(kind: str, endpoints: list[dict], seconds: float, turn: int, q: Any) -> None:
    try:
        q.put(run_abuse(kind, endpoints, seconds, turn))
    except Exception as exc:  # noqa: BLE001 - reported in the table
        q.put({"kind": kind, "error": f"{type(exc).__name__}: {exc}"})


def abuse_every_server(endpoints: list[dict], hold: int, flood: int, resets: int, hold_s: float, go: Any,
                       q: Any, blast: bool = False) -> None:
    """tests/runtime/test_abuse.py's abusers, in a child process so that their CPU does not
    compete with the well-behaved clients' interpreter. Reports on ``q``:

    1. ("flooded", {server: counts}, seconds): ``flood`` connects reset at once and ``resets``
       half messages + reset, on every TCP server at once; then waits for ``go``;
    2. ("holding", accepted, refused): ``hold`` connections opened at once per server; those
       accepted become, in turn, stalled-huge-header, never-reading, half-closed and idle
       clients; a second, smaller connect flood runs meanwhile (and with ``blast`` an ARIS
       byte blaster, which takes a core of its own);
    3. ("released", {"blaster_mb": ...}) after ``hold_s`` seconds, everything reset.
    """
    try:
        servers = tcp_servers(endpoints)
        t0 = time.monotonic()
        floods: dict[str, dict[str, int]] = {}

        def one(s: dict, n: int, r: int, deadline: float) -> None:
            out = connect_flood(s["address"], n, deadline)
            for _ in range(r):
                if time.monotonic() > deadline:
                    break
                try:
                    c = socket.create_connection(host_port(s["address"]), timeout=1.0)
                    c.sendall(partial_message(s["protocol"]))
                    reset(c)
                except OSError:
                    pass
            key = s["address"]
            floods[key] = {k: floods.get(key, {}).get(k, 0) + v for k, v in out.items()}

        def flood_all(n: int, r: int, seconds: float) -> None:
            start = time.monotonic()
            threads = [threading.Thread(target=one, args=(s, n, r, start + seconds), daemon=True) for s in servers]
            for t in threads:
                t.start()
            for t in threads:
                t.join(seconds + 5)

        flood_all(flood, resets, 15.0)
        q.put(("flooded", dict(floods), time.monotonic() - t0))
        go.wait(30)
        held: list[socket.socket] = []
        udps: list[socket.socket] = []
        # ARIS drops a client that sends nothing for its keep-alive time (3 s): open its batch last, so
        # that on a slow machine the others' batches do not use that time up before the count below
        opened = {s["address"]: open_many(s["address"], hold)
                  for s in sorted(servers, key=lambda s: s["protocol"] == "aris")}
        for socks in opened.values():
            held += socks
        time.sleep(1.0)
        accepted: dict[str, int] = {}
        refused_: dict[str, int] = {}
        for s in servers:
            socks = opened[s["address"]]
            ok = [k for k in socks if not refused(k)]
            accepted[s["address"]], refused_[s["address"]] = len(ok), len(socks) - len(ok)
            for i, k in enumerate(ok):
                try:
                    if i % 4 == 0:
                        k.sendall(huge_header(s["protocol"]))
                    elif i % 4 == 1:
                        udps.append(udp_socket(4096))
                        start_never_reading(s["protocol"], k, udps[-1], rate_code=4, frame_rate=3.0)
                    elif i % 4 == 2:
                        k.shutdown(socket.SHUT_WR)  # half-closed: FIN sent, still open
                    # i % 4 == 3: idle, sends nothing
                except OSError:
                    pass  # the server may already have dropped it (a bad header, a keep-alive)
        aris = next(s for s in servers if s["protocol"] == "aris")
        b = Blaster(aris["address"], junk("aris"))
        if blast:
            b.start()
        again = threading.Thread(target=flood_all, args=(flood // 3, 0, hold_s), daemon=True)
        again.start()
        q.put(("holding", accepted, refused_))
        time.sleep(hold_s)
        if blast:
            b.stop()
        again.join(10)
        close_all(held)
        close_all(udps, rst=False)
        q.put(("released", {"blaster_mb": round(b.sent / 1e6, 1), "floods": floods}))
    except Exception as exc:  # noqa: BLE001 - reported to the test
        q.put(("error", f"{type(exc).__name__}: {exc}", None))
