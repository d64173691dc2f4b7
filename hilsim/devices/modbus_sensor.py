"""Navigation sensors with a Modbus output: a Keller Series 30 depth sensor and a
WitMotion HWT905 IMU, on Modbus TCP and/or Modbus RTU on a pty.

A device = a sensor model from ``devices/sensors/`` (hilsim.sim.navigation) + a
register map from ``protocols/`` (hilsim.protocols.registers) + servers from
hilsim.links.modbus. The sensor is sampled on the scheduler at its rate and
each sample is encoded into the device's one :class:`RegisterImage`, which
every server of the device reads on each request. Scenario example::

    [[devices]]
    name = "depth"
    protocol = "modbus-keller"
    transport = ["tcp", "rtu"]   # either or both
    port = 0                     # TCP port, 0: a free one
    path = ""                    # RTU: the pty symlink ("": <run_dir>/<name>.tty)
    baudrate = 9600
    parity = "N"
    device_id = 1

Options: transport, port, path, baudrate, parity, stop_bits, device_id (0: the
map's default), map (a file in ``protocols/`` or the scenario folder), sensor
(a profile reference, ``keller_serie30``), rate [Hz] (0: the profile's), mount
(a scenario ``[[sensors]]`` name whose position is the pressure port's lever
arm; "" the body origin), max_clients (per TCP server), max_client_rate [requests/s]
per TCP client (0: no limit; a client over it is read more slowly, nothing is lost),
idle_timeout_s (a TCP client that sends no request for this long is disconnected, as
Modbus TCP gateways do; default 60, 0: never), evict_grace_s (a full TCP server admits a
newcomer by evicting the client that has sent no request for longer than this; 0: never).

The sensors' native serial dialects (:mod:`hilsim.devices.serial_dialects`) share the
same register image: the Keller serves the KELLER bus beside Modbus on its RTU line
(told by function code, as the Series 30 does), and with transport ``"rtu-tcp"`` that
line over TCP on ``rtu_tcp_port`` (both protocols, as a serial device server passes
them); the IMU with transport ``"uart"`` streams the WitMotion UART packets on a pty of
its own (``uart_path``, "": ``<run_dir>/<name>_uart.tty``; ``uart_baudrate``, 115200).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path
from typing import Any, ClassVar, Mapping

from hilsim.devices.base import Device, DeviceContext, Endpoint, NoiseFault, OptionError
from hilsim.devices.serial_dialects import KellerBus, WitUart
from hilsim.links.modbus import (ModbusRtuServer, ModbusTarget, ModbusTcpServer, RtuSession, SerialLineTcpServer,
                                 WriteAction)
from hilsim.protocols import keller_bus, witmotion_uart
from hilsim.protocols.registers import DEVICE_FAILURE, ModbusError, Register, RegisterImage, RegisterMap, load_map
from hilsim.resources import data_path, find_profile
from hilsim.sim.navigation import (
    Imu,
    ImuReading,
    PressureReading,
    PressureSensor,
    Sensor,
    load_imu_profile,
    load_pressure_profile,
)

log = logging.getLogger(__name__)

TRANSPORTS = ("tcp", "rtu")


def find_map(name: str, base: Path | None = None) -> Path:
    """A register map by name (``keller_serie30``): the scenario folder ``base`` first, then ``protocols/``."""
    rel = name if name.endswith(".toml") else name + ".toml"
    if Path(rel).is_absolute() or ".." in Path(rel).parts:
        raise ValueError(f"register map {name!r}: give a name in protocols/ or the scenario folder, not a path")
    candidates = ([base / rel] if base is not None else []) + [data_path("protocols", rel)]
    for c in candidates:
        if c.is_file():
            return c.resolve()
    known = sorted(p.stem for p in data_path("protocols").glob("*.toml"))
    raise FileNotFoundError(f"register map {name!r} not found (bundled maps: {', '.join(known) or 'none'})")


def pressure_signals(reading: PressureReading, zero: float = 0.0) -> dict[str, float]:
    """Signals of a pressure reading: ``pressure`` [Pa] (minus ``zero`` [Pa]), ``temperature`` [K]."""
    return {"pressure": reading.pressure - zero, "temperature": reading.temperature}


def imu_signals(reading: ImuReading) -> dict[str, float]:
    """Signals of an IMU reading (SI, body frame x fwd, y stbd, z down): ``specific_force.x`` ...,
    ``angular_velocity.*``, ``magnetic_field.*``, ``attitude.roll|pitch|yaw``, ``quaternion.w|x|y|z``,
    ``temperature``."""
    out: dict[str, float] = {"temperature": reading.temperature}
    for key in ("specific_force", "angular_velocity", "magnetic_field"):
        vec = getattr(reading, key)
        for axis, v in zip("xyz", vec):
            out[f"{key}.{axis}"] = float(v)
    for axis, v in zip(("roll", "pitch", "yaw"), reading.attitude):
        out[f"attitude.{axis}"] = float(v)
    for axis, v in zip("wxyz", reading.quaternion):
        out[f"quaternion.{axis}"] = float(v)
    return out


class ModbusSensorDevice(Device):
    """Base of the Modbus sensors: options, servers, sampling. Subclasses build the
    sensor (:meth:`make_sensor`) and turn its readings into signals (:meth:`signals`)."""

    DEFAULT_MAP: ClassVar[str]
    DEFAULT_SENSOR: ClassVar[str]
    SIGNALS: ClassVar[frozenset[str]]
    TRANSPORTS: ClassVar[tuple[str, ...]] = TRANSPORTS
    OPTIONS: ClassVar[Mapping[str, Any]] = {
        "transport": ["tcp", "rtu"], "port": 0, "path": "", "baudrate": 9600, "parity": "N", "stop_bits": 1,
        "device_id": 0, "map": "", "sensor": "", "rate": 0.0, "mount": "", "max_clients": 32,
        "max_client_rate": 1000.0, "idle_timeout_s": 60.0, "evict_grace_s": 5.0,
    }

    def __init__(self, name: str, options: Mapping[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        o = self.options
        transport = o["transport"]
        self.transports = (transport,) if isinstance(transport, str) else tuple(transport)
        bad = [t for t in self.transports if t not in self.TRANSPORTS]
        if bad or not self.transports:
            raise self.option_error("transport", f"transport must be a list of {self.TRANSPORTS}, got {transport!r}")
        if str(o["parity"]).upper() not in ("N", "E", "O"):
            raise self.option_error("parity", f"parity must be \"N\", \"E\" or \"O\", got {o['parity']!r}")
        self.option_int("baudrate", 1)
        self.option_int("stop_bits", 1, 2)
        self.option_int("device_id", 0, 247)
        self.option_int("port", 0, 65535)
        self.option_int("max_clients", 1, 10_000)
        self.option_number("max_client_rate", 0.0)
        self.option_number("idle_timeout_s", 0.0)
        self.option_number("evict_grace_s", 0.0)
        self.option_number("rate", 0.0)
        if o["path"]:  # a path that leaves the run folder fails here, with the scenario line, not at start
            self.option_pty_path("path", "")
        scenario = getattr(ctx, "scenario", None)
        self._base: Path | None = scenario.folder if scenario is not None else None
        try:
            self.map: RegisterMap = load_map(find_map(str(o["map"] or self.DEFAULT_MAP), self._base))
        except (ValueError, OSError) as exc:
            raise self.option_error("map", str(exc)) from None
        unknown = self.map.sources - self.SIGNALS
        if unknown:
            raise self.option_error("map", f"map {self.map.name!r} shows signals {sorted(unknown)} that a "
                                    f"{self.protocol} device does not have (it has {', '.join(sorted(self.SIGNALS))})")
        self.image = RegisterImage(self.map)
        try:
            self.sensor: Sensor[Any] = self.make_sensor()
        except (ValueError, KeyError, OSError) as exc:
            if isinstance(exc, OptionError):
                raise
            raise self.option_error("sensor", str(exc.args[0] if exc.args else exc)) from None
        self.target = ModbusTarget(self.image, o["device_id"] or None, actions=self.actions(), name=name)
        self.tcp: ModbusTcpServer | None = None
        self.rtu: ModbusRtuServer | None = None
        self.samples = 0
        self.last_reading: Any = None

    # -- what subclasses provide --

    def make_sensor(self) -> Sensor[Any]:
        raise NotImplementedError

    def signals(self, reading: Any) -> dict[str, float]:
        raise NotImplementedError

    def actions(self) -> dict[str, WriteAction]:
        """Write actions (map ``on_write`` names) this device implements."""
        return {}

    # -- Device contract --

    def _profile_path(self) -> Path:
        return find_profile("sensors", str(self.options["sensor"] or self.DEFAULT_SENSOR), self._base)

    def _rate(self, profile_rate: float) -> float:
        rate = float(self.options["rate"] or profile_rate)
        if not rate > 0:
            raise self.option_error("rate", f"rate must be > 0 Hz, got {rate}")
        return rate

    # -- fault injection ---------------------------------------------------------
    # dropout: the sensor stops answering (RTU: silence; TCP: gateway exception 0B),
    #   except the Keller, which reports its channel error as NaN (see KellerDevice);
    # stuck: the registers keep their last values; noise: every noise figure of the
    #   sensor's profile multiplied by ``factor``.
    FAULTS = ("dropout", "stuck", "noise")
    stuck = False
    _noise: NoiseFault | None = None

    def inject_fault(self, fault: str, params: Mapping[str, Any]) -> None:
        if fault == "dropout":
            self.target.silent = True
        elif fault == "stuck":
            self.stuck = True
        elif fault == "noise":
            if self._noise is None:  # every numeric noise figure of the sensor's profile
                p = self.sensor.profile
                self._noise = NoiseFault(*(f.name for f in dataclasses.fields(p)
                                           if "noise" in f.name and isinstance(getattr(p, f.name), (int, float))))
            self._noise.inject(self.sensor, params)
        else:
            super().inject_fault(fault, params)

    def clear_fault(self, fault: str) -> None:
        if fault == "dropout":
            self.target.silent = False
        elif fault == "stuck":
            self.stuck = False
        elif fault == "noise" and self._noise is not None:
            self._noise.clear(self.sensor)

    def sample(self, t: float = math.nan) -> None:
        """Sample the sensor at the vehicle's current state and publish it to the registers."""
        if self.stuck:
            return
        state = self.ctx.vehicle.state
        reading = self.sensor.sample(state)
        self.last_reading = reading
        signals = self.signals(reading)
        self.image.update(signals, state.time)
        self.samples += 1
        if self.observed("reading"):
            self.publish("reading", {"t": float(state.time), **self.reading_fields(signals)})

    def reading_fields(self, signals: Mapping[str, float]) -> dict[str, Any]:
        """The served reading for observers: the signals, named with their units."""
        return dict(signals)

    async def start(self) -> list[Endpoint]:
        o = self.options
        endpoints: list[Endpoint] = []
        self.sample()
        self.every("sample", self.sensor.period, self.sample, priority=10)
        extra = {"device_id": self.target.device_id, "map": self.map.name}
        if "tcp" in self.transports:
            self.tcp = self.own(ModbusTcpServer(self.name, self.target, self.ctx.bind, int(o["port"]),
                                                max_clients=int(o["max_clients"]),
                                                max_rate=float(o["max_client_rate"]),
                                                idle_timeout=float(o["idle_timeout_s"]) or None,
                                                evict_grace=float(o["evict_grace_s"])))
            host, port = await self.tcp.start()
            endpoints.append(Endpoint(self.name, self.protocol, "tcp", f"{host}:{port}", extra))
        if "rtu" in self.transports:
            serial = {"baudrate": int(o["baudrate"]), "parity": str(o["parity"]).upper(),
                      "stop_bits": int(o["stop_bits"])}
            await self._start_rtu(serial)
            assert self.rtu is not None
            self.use(self.rtu.link)  # its line's faults (bit errors)
            endpoints.append(Endpoint(self.name, self.protocol, "pty", self.rtu.path,
                                      {**serial, **extra, "framing": "rtu"}))
        return endpoints

    async def _start_rtu(self, serial: dict[str, Any]) -> None:
        path = str(self.options["path"])
        if not path:  # a line of its own
            self.rtu = self.own(ModbusRtuServer(self.name, self.ctx.pty_path(None, f"{self.name}.tty"),
                                                [self.target], **serial))
            await self.rtu.start()
            return
        # an explicit path: devices naming the same one share the line (an RS-485 bus)
        full = self.ctx.pty_path(path, path)

        async def factory() -> ModbusRtuServer:
            srv = ModbusRtuServer(f"modbus-rtu:{full.name}", full, [], **serial)
            await srv.start()
            return srv

        self.rtu = rtu = await self.ctx.shared(("modbus-rtu", str(full)), factory)
        line = {"baudrate": rtu.baudrate, "parity": rtu.link.parity, "stop_bits": rtu.link.stop_bits}
        if line != serial:
            raise self.option_error("path", f"RTU line {full} is already open with {line}, not {serial}")
        rtu.attach(self.target)
        self.own(_Detach(rtu, self.target))

    def status(self) -> dict[str, float]:
        s = self.target.stats
        out: dict[str, float] = {"samples": self.samples, "requests": s.requests, "exceptions": s.exceptions,
                                 "device_id": self.target.device_id}
        if self.tcp is not None:
            out["clients"] = self.tcp.link.stats.connected
            out["refused"] = self.tcp.link.stats.refused
            out["tcp_malformed"] = self.tcp.stats.malformed
            out["throttled"] = self.tcp.stats.throttled
        if self.rtu is not None:
            out["crc_errors"] = self.rtu.stats.crc_errors
            out["rtu_ignored"] = self.rtu.stats.ignored
        if s.internal_errors:
            out["internal_errors"] = s.internal_errors
        return {**out, **super().status()}


class _Detach:
    """A device's place on a shared RTU line, as an owned link: closing it detaches the device."""

    def __init__(self, rtu: ModbusRtuServer, target: ModbusTarget) -> None:
        self.rtu, self.target = rtu, target

    def close(self) -> None:
        self.rtu.detach(self.target)


class KellerDevice(ModbusSensorDevice):
    """Keller Series 30 pressure transmitter: P1 [bar abs] and TOB1 [deg C] in float32,
    P1 in int32 1/100 mbar; "set zero P1" (0xFF00) makes P1 read zero at the current
    pressure; ``channel_error = True`` makes the pressure channels read NaN."""

    protocol = "modbus-keller"
    DEFAULT_MAP = "keller_serie30"
    DEFAULT_SENSOR = "keller_serie30"
    SIGNALS = frozenset({"pressure", "temperature"})
    TRANSPORTS = (*TRANSPORTS, "rtu-tcp")
    OPTIONS = {**ModbusSensorDevice.OPTIONS, "rtu_tcp_port": 0}

    def __init__(self, name: str, options: Mapping[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.option_int("rtu_tcp_port", 0, 65535)
        profile = self.sensor.profile  # type: ignore[attr-defined]
        self.keller = KellerBus(name, self.image, self.target, self.zero_p1, offset=lambda: self.zero,
                                set_offset=self._set_offset, pressure_range=(profile.range_min, profile.range_max))
        self.line_tcp: SerialLineTcpServer | None = None

    async def start(self) -> list[Endpoint]:
        """Modbus as the base class serves it, plus the KELLER bus on the same RTU line (and on
        that line over TCP): after start the protocol is in its power-up state (F48 first)."""
        endpoints = await super().start()
        extra = {"device_id": self.target.device_id, "also": "modbus-rtu"}
        line: RtuSession | None = None
        if self.rtu is not None:
            self.keller.line_targets = self.rtu.session.targets
            self.rtu.add_dialect(keller_bus.DIALECT, self.keller.handle_frame)
            self.own(_RemoveDialect(self.rtu, self.keller.handle_frame))
            line = self.rtu.session
            rtu_ep = next(e for e in endpoints if e.transport == "pty")
            endpoints.append(Endpoint(self.name, "keller-bus", "pty", rtu_ep.address,
                                      {"connect": f"uart://{rtu_ep.address}:{rtu_ep.extra['baudrate']}",
                                       **{k: rtu_ep.extra[k] for k in ("baudrate", "parity", "stop_bits")}, **extra}))
        if "rtu-tcp" in self.transports:
            if line is None:  # no pty: a line of its own for the TCP clients
                line = RtuSession([self.target])
                line.add_dialect(keller_bus.DIALECT, self.keller.handle_frame)
            self.line_tcp = self.own(SerialLineTcpServer(f"{self.name}-line", line, self.ctx.bind,
                                                         int(self.options["rtu_tcp_port"]),
                                                         idle_timeout=float(self.options["idle_timeout_s"]) or None))
            host, port = await self.line_tcp.start()
            endpoints.append(Endpoint(self.name, "keller-bus", "tcp", f"{host}:{port}",
                                      {"connect": f"tcp://{host}:{port}", **extra,
                                       "framing": "serial line (raw: KELLER bus and Modbus RTU frames)"}))
        return endpoints

    def zero_p1(self, setpoint: float | None) -> None:
        """Zero P1 so that it reads ``setpoint`` [Pa] now (None: back to the factory zero);
        ValueError when the channel is in error or out of range."""
        if setpoint is None:
            self.zero = 0.0
        else:
            raw = self.last_reading.pressure if self.last_reading is not None else math.nan
            if not math.isfinite(raw) or self.channel_error or not math.isfinite(setpoint):
                raise ValueError("cannot zero a channel in error or out of range")
            self.zero = raw - setpoint
        log.info("%s: P1 zero point %.5f bar", self.name, self.zero / 1e5)
        if self.last_reading is not None:  # the registers show the zeroed value at once
            self.image.update(self.signals(self.last_reading), self.image.time)

    def _set_offset(self, offset: float) -> None:
        """[Pa] the P1 zero point as KELLER coefficient 64 writes it (P1 = raw - offset)."""
        self.zero = float(offset)
        if self.last_reading is not None:
            self.image.update(self.signals(self.last_reading), self.image.time)

    def status(self) -> dict[str, float]:
        r = self.keller.responder
        out = super().status()
        out.update({"keller_requests": r.requests, "keller_exceptions": r.exceptions})
        return out

    zero: float = 0.0            # [Pa] subtracted from P1 since the last "set zero"
    channel_error: bool = False  # fault injection: P1 reads NaN

    def make_sensor(self) -> PressureSensor:
        profile = load_pressure_profile(self._profile_path())
        profile = dataclasses.replace(profile, rate=self._rate(profile.rate))
        scenario = getattr(self.ctx, "scenario", None)
        density = scenario.water.density if scenario is not None else 1025.0
        mount: tuple[float, ...] = (0.0, 0.0, 0.0)
        if self.options["mount"]:
            if scenario is None:
                raise self.option_error("mount", f"mount {self.options['mount']!r} needs a scenario")
            try:
                mount = tuple(float(x) for x in scenario.sensor(str(self.options["mount"])).mount.position)
            except KeyError as exc:
                raise self.option_error("mount", str(exc.args[0])) from None
        return PressureSensor(profile, seed=self.ctx.seed, name=self.name, water_density=density, mount=mount)

    def signals(self, reading: PressureReading) -> dict[str, float]:
        out = pressure_signals(reading, self.zero)
        if self.channel_error:
            out["pressure"] = math.nan
        return out

    def actions(self) -> dict[str, WriteAction]:
        return {"set_zero": self._set_zero}

    def reading_fields(self, signals: Mapping[str, float]) -> dict[str, float]:
        return {"pressure_bar": signals["pressure"] / 1e5, "temperature_c": signals["temperature"] - 273.15}

    def inject_fault(self, fault: str, params: Mapping[str, Any]) -> None:
        """A Keller shows a failed pressure channel as NaN (its documented channel error)."""
        if fault == "dropout":
            self.channel_error = True
            if self.last_reading is not None:
                self.image.update(self.signals(self.last_reading), self.image.time)
        else:
            super().inject_fault(fault, params)

    def clear_fault(self, fault: str) -> None:
        if fault == "dropout":
            self.channel_error = False
        else:
            super().clear_fault(fault)

    def _set_zero(self, register: Register, value: float) -> None:
        try:
            self.zero_p1(0.0)
        except ValueError as exc:
            raise ModbusError(DEVICE_FAILURE, str(exc)) from None


class _RemoveDialect:
    """The KELLER bus's place on an RTU line, as an owned link: closing it takes the handler off."""

    def __init__(self, rtu: ModbusRtuServer, handler: Any) -> None:
        self.rtu, self.handler = rtu, handler

    def close(self) -> None:
        self.rtu.remove_dialect(self.handler)


class WitMotionDevice(ModbusSensorDevice):
    """WitMotion HWT905-485 IMU: acceleration, angular rate, magnetic field, angles,
    temperature, quaternion as int16 in the sensor's own Z-up axes."""

    protocol = "modbus-witmotion"
    DEFAULT_MAP = "witmotion_hwt905"
    DEFAULT_SENSOR = "witmotion_hwt905"
    SIGNALS = frozenset({"temperature"} | {f"{k}.{a}" for k in ("specific_force", "angular_velocity",
                                                              "magnetic_field") for a in "xyz"}
                        | {f"attitude.{a}" for a in ("roll", "pitch", "yaw")}
                        | {f"quaternion.{a}" for a in "wxyz"})

    TRANSPORTS = (*TRANSPORTS, "uart")
    OPTIONS = {**ModbusSensorDevice.OPTIONS, "uart_path": "", "uart_baudrate": 115200}

    def __init__(self, name: str, options: Mapping[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        baud = self.option_int("uart_baudrate", 1)
        if baud not in witmotion_uart.BAUD_CODES:
            raise self.option_error("uart_baudrate", f"uart_baudrate must be one of {sorted(witmotion_uart.BAUD_CODES)}"
                                                     f", got {baud}")
        self.uart: WitUart | None = None
        if "uart" in self.transports:
            path = self.option_pty_path("uart_path", f"{name}_uart.tty")
            self.uart = WitUart(name, ctx, self.image, path, baud, silent=lambda: self.target.silent)

    async def start(self) -> list[Endpoint]:
        """Modbus as the base class serves it, plus the UART stream on its own pty."""
        endpoints = await super().start()
        if self.uart is not None:
            self.own(self.uart)
            path = await self.uart.start()
            self.use(self.uart.link)  # its line's faults (bit errors)
            cfg = self.uart.config
            endpoints.append(Endpoint(self.name, "witmotion-uart", "pty", path,
                                      {"connect": f"uart://{path}:{cfg.baudrate}", "baudrate": cfg.baudrate,
                                       "rate_hz": cfg.rate,
                                       "content": [hex(k) for k in witmotion_uart.content_kinds(cfg.rsw)]}))
        return endpoints

    def status(self) -> dict[str, float]:
        out = super().status()
        if self.uart is not None:
            out.update({"uart_packets": self.uart.packets, "uart_rate_hz": self.uart.config.rate,
                        "uart_commands": self.uart.config.commands})
        return out

    def make_sensor(self) -> Imu:
        profile = load_imu_profile(self._profile_path())
        profile = dataclasses.replace(profile, rate=self._rate(profile.rate))
        return Imu(profile, seed=self.ctx.seed, name=self.name)

    def signals(self, reading: ImuReading) -> dict[str, float]:
        return imu_signals(reading)

    def reading_fields(self, signals: Mapping[str, float]) -> dict[str, Any]:
        return {"rpy_deg": [math.degrees(signals[f"attitude.{a}"]) for a in ("roll", "pitch", "yaw")],
                "accel_m_s2": [signals[f"specific_force.{a}"] for a in "xyz"],
                "gyro_deg_s": [math.degrees(signals[f"angular_velocity.{a}"]) for a in "xyz"],
                "temperature_c": signals["temperature"] - 273.15}


__all__ = ["KellerDevice", "ModbusSensorDevice", "WitMotionDevice", "find_map", "imu_signals", "pressure_signals"]
