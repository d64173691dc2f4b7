"""Navigation sensors on Modbus TCP (pymodbus), the Water Linked DVL's TCP JSON API, an NMEA 0183 GNSS
on a serial port (pyserial), thrusters on VESC CAN through socketcand (python-can, cantools), and the
bridge's endpoints file.
"""

from __future__ import annotations

import functools
import json
import math
import operator
import socket
import struct
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

from auv_vehicle import THRUSTERS, G


class ModbusSensors:
    """Keller depth and WitMotion attitude over Modbus TCP (pymodbus)."""

    def __init__(self, depth_addr: tuple[str, int], depth_id: int, imu_addr: tuple[str, int], imu_id: int,
                 rho: float) -> None:
        from pymodbus.client import ModbusTcpClient

        self.keller = ModbusTcpClient(depth_addr[0], port=depth_addr[1], timeout=1.0, retries=1)
        self.imu = ModbusTcpClient(imu_addr[0], port=imu_addr[1], timeout=1.0, retries=1)
        for c, what in ((self.keller, "depth"), (self.imu, "imu")):
            if not c.connect():
                raise ConnectionError(f"cannot connect to the {what} sensor (Modbus TCP)")
        self.depth_id, self.imu_id, self.rho = depth_id, imu_id, rho
        self.errors = 0

    def depth(self) -> float:
        """[m] positive down, from P1 [bar abs] (float32 at 0x0002, high word first); NaN on error."""
        try:
            rr = self.keller.read_holding_registers(0x0002, count=2, device_id=self.depth_id)
            if rr.isError():
                raise IOError(str(rr))
            p1 = float(self.keller.convert_from_registers(rr.registers, self.keller.DATATYPE.FLOAT32))
        except Exception:  # noqa: BLE001 - pymodbus raises several types; the caller holds the last value
            self.errors += 1
            return math.nan
        if not math.isfinite(p1):
            self.errors += 1  # NaN = channel error on a Keller
        return (p1 * 1e5 - 101325.0) / (self.rho * G)

    def attitude(self) -> tuple[float, float]:
        """(NED heading [deg] 0..360, NED yaw rate [deg/s]) from WitMotion Yaw (0x3F) and GZ (0x39):
        int16, Z-up sensor frame, so both are negated."""
        try:
            rr = self.imu.read_holding_registers(0x37, count=9, device_id=self.imu_id)  # GX..Yaw
            if rr.isError():
                raise IOError(str(rr))
        except Exception:  # noqa: BLE001
            self.errors += 1
            return math.nan, math.nan
        regs = [r - 65536 if r >= 32768 else r for r in rr.registers]
        gz = regs[0x39 - 0x37] * 2000.0 / 32768.0
        yaw = regs[0x3F - 0x37] * 180.0 / 32768.0
        return (-yaw) % 360.0, -gz

    def close(self) -> None:
        self.keller.close()
        self.imu.close()


class DvlClient:
    """Water Linked DVL A50 over its TCP JSON API (Water Linked's "DVL A50/A125 TCP JSON API": one JSON
    object per line; ``"type": "velocity"`` reports carry vx, vy, vz [m/s] in the DVL's frame, altitude
    [m] and velocity_valid; time_of_validity is the ping's Unix time [us]). A reader thread keeps the
    latest velocity report; :meth:`latest` gives it while it is fresh."""

    def __init__(self, host: str, port: int) -> None:
        self.sock = socket.create_connection((host, port), timeout=5.0)
        self.sock.settimeout(0.5)
        self.reports = 0
        self.valid = 0
        self.errors = 0
        self._last: tuple[float, dict[str, Any]] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                chunk = self.sock.recv(65536)
            except socket.timeout:
                continue
            except OSError:
                break
            if not chunk:
                break
            buf += chunk
            *lines, buf = buf.split(b"\n")
            for line in lines:
                try:
                    msg = json.loads(line)
                except ValueError:
                    self.errors += 1
                    continue
                if isinstance(msg, dict) and msg.get("type") == "velocity":
                    self.reports += 1
                    self.valid += bool(msg.get("velocity_valid"))
                    self._last = (time.monotonic(), msg)

    def latest(self, max_age: float = 0.5) -> dict[str, Any] | None:
        """The last velocity report if it arrived less than ``max_age`` [s of wall time] ago."""
        last = self._last
        if last is None or time.monotonic() - last[0] > max_age:
            return None
        return last[1]

    def close(self) -> None:
        self._stop.set()
        try:
            self.sock.close()
        finally:
            self._thread.join(timeout=2.0)


def nmea_fields(line: bytes) -> list[str] | None:
    """The fields of one NMEA 0183 sentence (``$..*HH``) if its checksum (XOR of the bytes between
    ``$`` and ``*``) is right, else None."""
    line = line.strip()
    if not line.startswith(b"$") or len(line) < 4 or line[-3:-2] != b"*":
        return None
    body = line[1:-3]
    try:
        if functools.reduce(operator.xor, body, 0) != int(line[-2:], 16):
            return None
        return body.decode("ascii").split(",")
    except (ValueError, UnicodeDecodeError):
        return None


def parse_gga(fields: list[str]) -> dict[str, float] | None:
    """GGA fields -> {quality, lat_deg, lon_deg, alt_m, satellites, hdop, utc_s}; None if not a GGA."""
    if len(fields) < 10 or not fields[0].endswith("GGA"):
        return None
    out = {"quality": float(fields[6] or 0), "satellites": float(fields[7] or 0),
           "hdop": float(fields[8]) if fields[8] else math.nan, "lat_deg": math.nan, "lon_deg": math.nan,
           "alt_m": float(fields[9]) if fields[9] else math.nan, "utc_s": math.nan}
    if fields[1]:
        out["utc_s"] = int(fields[1][:2]) * 3600 + int(fields[1][2:4]) * 60 + float(fields[1][4:])
    if fields[2] and fields[4]:
        lat = int(fields[2][:2]) + float(fields[2][2:]) / 60.0
        lon = int(fields[4][:3]) + float(fields[4][3:]) / 60.0
        out["lat_deg"] = -lat if fields[3] == "S" else lat
        out["lon_deg"] = -lon if fields[5] == "W" else lon
    return out


class GnssReader:
    """An NMEA 0183 GNSS receiver on a serial port (pyserial): a reader thread parses the GGA
    sentences (checksum checked); :meth:`take` hands over those received since the last call."""

    def __init__(self, path: str, baudrate: int) -> None:
        import serial

        self.port = serial.Serial(path, baudrate, timeout=0.2)
        self.sentences = 0
        self.bad = 0
        self._fixes: deque[dict[str, float]] = deque(maxlen=100)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                buf += self.port.read(self.port.in_waiting or 1)
            except Exception:  # noqa: BLE001 - the port went away (the bridge stopped)
                break
            *lines, buf = buf.split(b"\n")
            for line in lines:
                fields = nmea_fields(line)
                if fields is None:
                    self.bad += bool(line.strip())
                    continue
                self.sentences += 1
                gga = parse_gga(fields)
                if gga is not None:
                    self._fixes.append(gga)

    def take(self) -> list[dict[str, float]]:
        out = []
        while self._fixes:
            out.append(self._fixes.popleft())
        return out

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.port.close()


VESC_COMMANDS = {"duty": (0, "SET_DUTY", "duty", 1e-5), "current": (1, "SET_CURRENT", "current", 1e-3),
                 "rpm": (3, "SET_RPM", "erpm", 1.0)}
VESC_STATUS_1 = 9


class VescCan:
    """VESC commands onto a socketcand CAN bus (python-can); STATUS_1 (ERPM) read back in python-can's
    Notifier thread. Encoded with cantools from the DBC when given, else packed per the DBC by hand:
    extended id (command << 8) | controller id, big-endian int32 value / scale."""

    def __init__(self, host: str, port: int, channel: str, kind: str, dbc: Path | None) -> None:
        import logging

        import can

        # python-can's socketcand client warns each time a TCP read ends inside a message: routine here
        logging.getLogger("can.interfaces.socketcand").setLevel(logging.ERROR)
        self.can = can
        self.kind = kind
        self.db = None
        if dbc is not None and dbc.is_file():
            import cantools

            self.db = cantools.database.load_file(str(dbc))
        self.bus = can.Bus(interface="socketcand", host=host, port=port, channel=channel)
        self.erpm: dict[int, float] = {}   # last STATUS_1 ERPM per controller id
        self.status_frames = 0
        self.sent = 0
        self.notifier = can.Notifier(self.bus, [self._on_message], timeout=0.2)

    def encode(self, controller: int, value: float) -> tuple[int, bytes]:
        cmd, name, signal_name, scale = VESC_COMMANDS[self.kind]
        if self.db is not None:
            msg = self.db.get_message_by_name(f"VESC{controller}_{name}")
            return msg.frame_id, bytes(msg.encode({signal_name: value}))
        return (cmd << 8) | controller, struct.pack(">i", int(round(value / scale)))

    def send(self, values: list[float]) -> None:
        """One command per thruster, in THRUSTERS order."""
        for (_, cid, _, _), v in zip(THRUSTERS, values):
            arb, data = self.encode(cid, v)
            self.bus.send(self.can.Message(arbitration_id=arb, data=data, is_extended_id=True))
            self.sent += 1

    def _on_message(self, msg: Any) -> None:
        if msg.is_extended_id and (msg.arbitration_id >> 8) == VESC_STATUS_1 and len(msg.data) >= 4:
            self.erpm[msg.arbitration_id & 0xFF] = struct.unpack_from(">i", bytes(msg.data))[0]
            self.status_frames += 1

    def close(self) -> None:
        self.notifier.stop(timeout=1.0)
        self.bus.shutdown()


class EscHealth:
    """Flags a thruster whose ESC reports a stopped rotor (|ERPM| < ``min_erpm`` in STATUS_1) while a
    thruster asked for no more thrust spins: a failed motor, a fouled propeller, a dead ESC. Comparing
    with the others keeps small demands inside the ESCs' dead band (every rotor stopped) from counting.
    Ticks with that evidence add up (a tick where the thruster spins starts over); ``hold_s`` seconds of
    it flag the thruster. What a real stack does next is its own business; this one reports it (a
    warning line, the summary) and keeps flying on the others (its integrators absorb the loss)."""

    def __init__(self, names: list[str], min_erpm: float = 50.0, hold_s: float = 1.5) -> None:
        self.names = names
        self.min_erpm, self.hold_s = min_erpm, hold_s
        self.evidence = [0.0] * len(names)            # [s] of stalled-while-peers-spin
        self.faults: list[dict[str, Any]] = []        # {"thruster", "controller", "t_s"} in detection order
        self.flagged: set[int] = set()

    def update(self, t: float, dt: float, thrusts: list[float], erpm: list[float]) -> list[str]:
        """One control tick of ``dt`` [s]: demanded thrust [N] and reported ERPM per thruster (NaN: no
        telemetry yet). Returns the names newly flagged at this tick."""
        spinning = [math.isfinite(e) and abs(e) >= self.min_erpm for e in erpm]
        new = []
        for i, (f, e) in enumerate(zip(thrusts, erpm)):
            if not math.isfinite(e) or i in self.flagged:
                continue
            if spinning[i]:
                self.evidence[i] = 0.0
                continue
            if abs(f) > 0 and any(spinning[j] and abs(thrusts[j]) <= abs(f) * 1.05 for j in range(len(erpm))
                                  if j != i):
                self.evidence[i] += dt
                if self.evidence[i] >= self.hold_s:
                    self.flagged.add(i)
                    self.faults.append({"thruster": self.names[i], "controller": THRUSTERS[i][1],
                                        "t_s": round(t, 2)})
                    new.append(self.names[i])
        return new


def load_endpoints(path: Path) -> dict[str, dict[str, Any]]:
    """The bridge's endpoints JSON (a list of {device, protocol, transport, address, ...}) by protocol:
    TCP / socketcand entries, and the NMEA GNSS on its serial port (pty)."""
    out: dict[str, dict[str, Any]] = {}
    for e in json.loads(path.read_text()):
        if e.get("transport") in ("tcp", "socketcand") or e.get("protocol") == "nmea-gnss":
            out.setdefault(e["protocol"], e)
    need = ["ddf-stream", "modbus-keller", "modbus-witmotion", "vesc-can"]
    missing = [n for n in need if n not in out]
    if missing:
        raise ValueError(f"{path}: no endpoint for {', '.join(missing)}")
    return out


def host_port(address: str) -> tuple[str, int]:
    host, port = address.rsplit(":", 1)
    return host, int(port)
