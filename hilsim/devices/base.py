"""The contract between the bridge and an emulated device, and the base classes devices build on.

A device is built from one ``[[devices]]`` table of the scenario::

    [[devices]]
    name = "sonar_ddf"        # shown in the endpoints table
    protocol = "ddf-stream"   # picks the class (hilsim.devices.REGISTRY)
    sensor = "sonar"          # other keys are the device's OPTIONS
    port = 0                  # 0: a free port is picked

The bridge calls ``await start()`` once (the device opens its links, registers
its periodic work with :meth:`Device.every` and returns its endpoints), reads
``status()`` for the status line, and ``await close()`` at shutdown. Devices
never block the event loop: sonar frames are rendered in the worker process
through ``await ctx.render(...)``. A device talks to the bridge only through
its :class:`~hilsim.devices.context.DeviceContext`.

A device *declares* what it needs and offers, so the runtime never names a
protocol: ``needs_renderer`` (the bridge starts the render worker),
``clock_master`` (it drives the simulation clock in lockstep), ``records``
(file suffixes ``hilsim run --record FILE`` may hand it), ``FAULTS`` (the faults
the timeline and the console may inject), and its links (:meth:`Device.links`),
whose own faults (``bit_errors`` on a serial line, ``silent`` on a CAN bus) it
offers too.

The base classes own the shared plumbing: :class:`Device` (options, periodic work,
owned links closed in reverse order, counters, faults), and
:class:`TcpServerDevice`, :class:`PtyDevice`, :class:`CanDevice` for the three
link kinds (start, close, status and the link's counters); a device keeps only
what is its own.

Errors: a peer sending something bad is counted and answered as the real
device would (never an exception out of a device); a bug of ours raises. An
option the device refuses raises :class:`OptionError` naming the option.
"""

from __future__ import annotations

import dataclasses
import difflib
import logging
import math
from abc import ABC, abstractmethod
from collections import Counter
from pathlib import Path
from typing import Any, Callable, ClassVar, Mapping

from hilsim.devices.context import (DeviceContext, Endpoint, OptionError, Periodic, RenderedFrame, RenderFailed,
                                    VehicleView)

__all__ = ["CanDevice", "Device", "DeviceContext", "Endpoint", "NoiseFault", "OptionError", "Periodic", "PtyDevice",
           "RenderedFrame", "RenderFailed", "SensorFaults", "TcpServerDevice", "VehicleView"]

from hilsim.devices.canbus import acquire_bus, bus_location, check_can_options

log = logging.getLogger(__name__)


class Device(ABC):
    """An emulated device. Subclasses set ``protocol`` and ``OPTIONS`` (key -> default).

    Option errors: raise :class:`OptionError` naming the option (:meth:`option_error` builds one);
    :meth:`option_pty_path` and :meth:`option_output_path` check a path option, :meth:`option_number`
    and :meth:`option_int` a number.
    """

    protocol: ClassVar[str]
    OPTIONS: ClassVar[Mapping[str, Any]] = {}
    #: device-level faults this device can show (``inject_fault``); its links add their own
    FAULTS: ClassVar[tuple[str, ...]] = ()
    #: sonar frames are rendered for it: the bridge starts the render worker
    needs_renderer: ClassVar[bool] = False
    #: it drives the simulation clock (ArduPilot's lockstep): ``await ctx.advance(dt)``
    clock_master: ClassVar[bool] = False
    #: file suffixes (".ddf") ``hilsim run --record FILE`` may hand to :meth:`record_to`
    records: ClassVar[tuple[str, ...]] = ()
    #: counters shown from the start (at 0) in :meth:`status`; others appear once counted
    COUNTERS: ClassVar[tuple[str, ...]] = ()

    def __init__(self, name: str, options: Mapping[str, Any], ctx: DeviceContext) -> None:
        self.name = name
        self.ctx = ctx
        unknown = [k for k in options if k not in self.OPTIONS]
        if unknown:
            k = unknown[0]
            close = difflib.get_close_matches(k, list(self.OPTIONS), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else f"; valid: {', '.join(self.OPTIONS)}"
            raise OptionError(k, f"unknown option {k!r}{hint}", f"device {name!r} ({self.protocol})")
        self.options: dict[str, Any] = {**self.OPTIONS, **options}
        self.counters: Counter[str] = Counter({k: 0 for k in self.COUNTERS})
        self._periodic: list[Periodic] = []
        self._owned: list[Any] = []      # links closed by close(), in reverse order
        self._links: list[Any] = []      # links whose faults this device offers (owned or shared)
        self._closed = False

    # -- options -------------------------------------------------------------------

    def option_error(self, key: str, message: str) -> OptionError:
        return OptionError(key, message, f"device {self.name!r}")

    def option_number(self, key: str, lo: float | None = None, hi: float | None = None, *,
                      lo_open: bool = False) -> float:
        """The option ``key`` as a float within [lo, hi] (``lo_open``: above lo); OptionError otherwise."""
        v = self.options[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.option_error(key, f"{key} must be a number, got {v!r}")
        x = float(v)
        if (lo is not None and (x <= lo if lo_open else x < lo)) or (hi is not None and x > hi) or x != x:
            lo_s = "-inf" if lo is None else f"{lo:g}"
            hi_s = "inf" if hi is None else f"{hi:g}"
            raise self.option_error(key, f"{key} {v} outside {'(' if lo_open else '['}{lo_s}, {hi_s}]")
        return x

    def option_int(self, key: str, lo: int | None = None, hi: int | None = None) -> int:
        """The option ``key`` as an int within [lo, hi]; OptionError otherwise."""
        v = self.options[key]
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.option_error(key, f"{key} must be an integer, got {v!r}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self.option_error(key, f"{key} {v} outside {lo}..{hi}")
        return v

    def option_pty_path(self, key: str, default: str) -> Path:
        """``ctx.pty_path`` of the option ``key`` (``default`` when unset); a path the run
        folder refuses raises :class:`OptionError` naming ``key``."""
        try:
            return self.ctx.pty_path(self._path_option(key) or None, default)
        except ValueError as exc:
            raise self.option_error(key, str(exc)) from None

    def option_output_path(self, key: str) -> Path:
        """``ctx.output_path`` of the option ``key``; a refused path raises :class:`OptionError`."""
        try:
            return self.ctx.output_path(self._path_option(key))
        except ValueError as exc:
            raise self.option_error(key, str(exc)) from None

    def _path_option(self, key: str) -> str:
        value = self.options[key]
        if value is not None and not isinstance(value, str):
            raise self.option_error(key, f"expected a relative path, got {value!r}")
        return value or ""

    def sensor_mount(self, kind: str, key: str = "sensor") -> Any:
        """The scenario sensor mount named by option ``key``, which must be of ``kind`` (``sonar``,
        ``dvl``, ``gnss``, ``echosounder`` ...); OptionError naming ``key`` otherwise."""
        try:
            mount = self.ctx.scenario.sensor(str(self.options[key]))
        except KeyError as exc:
            raise self.option_error(key, str(exc.args[0])) from None
        if mount.kind != kind:
            raise self.option_error(key, f"sensor {mount.name!r} is a {mount.kind}, not a {kind}")
        return mount

    def sonar_mount(self, key: str = "sensor") -> str:
        """The name of the scenario sonar named by option ``key`` (see :meth:`sensor_mount`)."""
        return str(self.sensor_mount("sonar", key).name)

    # -- lifecycle -----------------------------------------------------------------

    @abstractmethod
    async def start(self) -> list[Endpoint]:
        """Open links, register periodic work; return the endpoints."""

    async def close(self) -> None:
        """Stop the periodic work, close the links this device owns (last opened first), then
        :meth:`on_close`. Idempotent; a link that fails to close is logged, the rest still close."""
        if self._closed:
            return
        self._closed = True
        for p in self._periodic:
            p.cancel()
        self._periodic.clear()
        try:
            await self.on_close()
        finally:
            for link in reversed(self._owned):
                try:
                    result = link.close()
                    if result is not None:
                        await result
                except Exception:  # noqa: BLE001 - close the rest regardless
                    log.exception("%s: closing %r", self.name, link)
            self._owned.clear()

    async def on_close(self) -> None:
        """A subclass's own shutdown (flush a recording, cancel tasks); runs before the links close."""

    def every(self, what: str, period: float, callback: Callable[[float], Any], *, offset: float = 0.0,
              priority: int = 20, tolerance: float | None = None) -> Periodic:
        """``ctx.every`` named ``<device>.<what>``, cancelled by :meth:`close`."""
        handle = self.ctx.every(f"{self.name}.{what}", period, callback, offset=offset, priority=priority,
                                tolerance=tolerance)
        self._periodic.append(handle)
        return handle

    def own(self, link: Any) -> Any:
        """Register a link (anything with ``close()``, sync or async) to close with the device;
        its faults (``FAULTS`` / ``set_fault``) are offered too. Returns it."""
        self._owned.append(link)
        self.use(link)
        return link

    def use(self, link: Any) -> Any:
        """A link the device uses but does not own (a shared CAN bus): its faults are offered."""
        if getattr(link, "FAULTS", ()) and link not in self._links:
            self._links.append(link)
        return link

    def links(self) -> list[Any]:
        """The links whose faults this device offers."""
        return list(self._links)

    def record_to(self, path: Path) -> None:
        """Record what this device serves to ``path`` (one of ``records``); before :meth:`start`."""
        raise ValueError(f"device {self.name!r} ({self.protocol}) does not record")

    # -- observation ---------------------------------------------------------------

    def observed(self, kind: str) -> bool:
        """Whether anything listens to this device's ``kind`` topic (``sonar``, ``reading``, ``command``)."""
        return self.ctx.observed(f"{kind}/{self.name}")

    def publish(self, kind: str, message: Mapping[str, Any]) -> None:
        """Publish on ``<kind>/<device name>`` (check :meth:`observed` first when the message costs)."""
        self.ctx.publish(f"{kind}/{self.name}", message)

    # -- status --------------------------------------------------------------------

    def status(self) -> dict[str, float]:
        """Counters for the status line and the run summary (clients, frames sent, drops, errors ...)."""
        return {k: float(v) for k, v in self.counters.items()}

    # -- faults --------------------------------------------------------------------

    def fault_kinds(self) -> tuple[str, ...]:
        """Every fault this device can show: its own, then its links'."""
        kinds = list(self.FAULTS)
        for link in self._links:
            kinds += [f for f in link.FAULTS if f not in kinds]
        return tuple(kinds)

    def set_fault(self, fault: str, on: bool, params: Mapping[str, Any]) -> None:
        """Start (``on``) or end ``fault``: the device's own, or applied to each of its links that
        has it. ValueError for a fault it cannot show."""
        if fault in self.FAULTS:
            if on:
                self.inject_fault(fault, params)
            else:
                self.clear_fault(fault)
            return
        links = [x for x in self._links if fault in x.FAULTS]
        if not links:
            can = self.fault_kinds()
            raise ValueError(f"device {self.name!r} ({self.protocol}) has no fault {fault!r}"
                             + (f"; it has: {', '.join(can)}" if can else ""))
        for link in links:
            link.set_fault(fault, on, params)

    def inject_fault(self, fault: str, params: Mapping[str, Any]) -> None:
        """Show one of ``FAULTS`` on the wire as the real device would, until :meth:`clear_fault`."""
        raise ValueError(f"device {self.name!r} ({self.protocol}) has no fault {fault!r}")

    def clear_fault(self, fault: str) -> None:
        """End ``fault``; the device behaves normally again."""


class TcpServerDevice(Device):
    """A device serving TCP clients through one :class:`~hilsim.links.tcp.TcpServer`.

    :meth:`serve` starts it with the options every TCP device has (``max_clients``,
    ``idle_timeout_s``, ``evict_grace_s``: when the server is full, a newcomer evicts the client
    that has gone longest without progress if that exceeds this many seconds; 0: never) and the
    subclass's ``on_connect`` / ``on_data`` / ``on_disconnect``;
    ``vendor_port=True`` falls back to a free port when a vendor's fixed port is taken.
    :meth:`status` adds the server's counters.
    """

    OPTIONS: ClassVar[Mapping[str, Any]] = {"port": 0, "max_clients": 16, "idle_timeout_s": 0, "evict_grace_s": 5.0}
    #: its clients are expected to send (commands, requests, keep-alives): one that has sent nothing
    #: and taken nothing for ``evict_grace_s`` is idle (evictable when full); False for a stream whose
    #: clients only listen (then only a client that stops taking what it is sent is evictable)
    COMMAND_CHANNEL: ClassVar[bool] = True

    def __init__(self, name: str, options: Mapping[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.option_int("port", 0, 65535)
        self.option_int("max_clients", 1, 10_000)
        self.option_number("idle_timeout_s", 0.0)
        self.option_number("evict_grace_s", 0.0)
        self.server: Any = None
        self.host, self.port = ctx.bind, 0

    async def serve(self, *, vendor_port: bool = False, **kw: Any) -> tuple[str, int]:
        """Listen on the ``port`` option; ``kw`` go to TcpServer (queue_len, write_buffer, ...)."""
        from hilsim.links.tcp import TcpServer, serve_with_fallback

        def make(port: int) -> Any:
            kw.setdefault("idle_timeout", float(self.options["idle_timeout_s"]))
            kw.setdefault("evict_grace", float(self.options["evict_grace_s"]))
            kw.setdefault("command_channel", self.COMMAND_CHANNEL)
            for cb in ("on_connect", "on_data", "on_disconnect"):
                if hasattr(self, cb):
                    kw.setdefault(cb, getattr(self, cb))
            return TcpServer(self.name, self.ctx.bind, port, max_clients=int(self.options["max_clients"]), **kw)

        port = int(self.options["port"])
        if vendor_port:
            self.server, self.host, self.port = await serve_with_fallback(self.name, make, port)
        else:
            self.server = make(port)
            self.host, self.port = await self.server.start()
        self.own(self.server)
        return self.host, self.port

    @property
    def clients(self) -> list[Any]:
        return list(self.server.clients.values()) if self.server is not None else []

    def status(self) -> dict[str, float]:
        st = self.server.stats if self.server is not None else None
        base = {"clients": float(st.connected), "sent": float(st.messages_sent),
                "dropped": float(st.messages_dropped), "refused": float(st.refused)} if st else {"clients": 0.0}
        if st is not None and st.evicted:
            base["evicted"] = float(st.evicted)
        return {**base, **super().status()}


class PtyDevice(Device):
    """A device on one or more emulated serial ports (:class:`~hilsim.links.pty.PtyLink`).

    :meth:`open_pty` opens one (path from the option ``path``, default the device's name, inside
    the run folder) at the ``baudrate`` option; :meth:`status` adds its byte counters.
    """

    OPTIONS: ClassVar[Mapping[str, Any]] = {"path": None, "baudrate": 115200}
    BAUDRATES: ClassVar[tuple[int, ...]] = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400,
                                            460800, 921600)

    def __init__(self, name: str, options: Mapping[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        baud = self.option_int("baudrate", 1)
        if baud not in self.BAUDRATES:
            raise self.option_error("baudrate", f"baudrate {baud} is not a serial rate "
                                    f"({', '.join(map(str, self.BAUDRATES))})")
        self.path = self.option_pty_path("path", name)
        self.link: Any = None

    async def open_pty(self, on_data: Callable[[bytes], None], *, path: Path | None = None,
                       baudrate: int | None = None, **kw: Any) -> Any:
        """Open a pty at ``path`` (default the ``path`` option) and ``baudrate`` (default the option);
        the first one opened is ``self.link``."""
        from hilsim.links.pty import PtyLink

        link = PtyLink(self.name, path or self.path, baudrate=int(baudrate or self.options["baudrate"]),
                       on_data=on_data, **kw)
        await link.start()
        self.own(link)
        if self.link is None:
            self.link = link
        return link

    def status(self) -> dict[str, float]:
        base = {}
        if self.link is not None:
            base = {"bytes_in": float(self.link.bytes_in), "bytes_out": float(self.link.bytes_out)}
        return {**base, **super().status()}


class CanDevice(Device):
    """A device on a CAN bus, shared with every device naming the same bus: options ``transport``
    (socketcand | slcan | socketcan | virtual), ``channel``, ``port`` (socketcand), ``path`` (slcan pty),
    ``bitrate``, ``max_clients`` and ``evict_grace_s`` (socketcand: a full server evicts a client gone
    that long without progress for a newcomer; 0: never). :meth:`attach` acquires the bus and subscribes;
    :meth:`status` adds the bus's counters; :meth:`endpoint` names it."""

    OPTIONS: ClassVar[Mapping[str, Any]] = {"transport": "socketcand", "channel": "can0", "port": 0, "path": None,
                                            "bitrate": 1_000_000, "max_clients": 8, "evict_grace_s": 5.0}

    def __init__(self, name: str, options: Mapping[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        check_can_options(self)
        bus_location(ctx, self.options)  # a pty path that leaves the run folder fails here, naming the option
        self.bus: Any = None

    async def attach(self, on_frame: Callable[[Any], None]) -> Any:
        self.bus = self.use(await acquire_bus(self.ctx, self.name, self.options))
        self.own(_Unsubscribe(self.bus.subscribe(on_frame)))
        return self.bus

    def endpoint(self, **extra: Any) -> Endpoint:
        return Endpoint(self.name, self.protocol, self.bus.transport, self.bus.address, {**self.bus.extra, **extra})

    def status(self) -> dict[str, float]:
        base = {}
        if self.bus is not None:
            bs = self.bus.status()
            base = {k: float(bs[k]) for k in ("clients", "frames_in", "dropped_in", "dropped_out") if k in bs}
        return {**base, **super().status()}


class NoiseFault:
    """The ``noise`` fault of a sensor device: some figures of its sensor model's profile (a frozen
    dataclass), ``fields``, multiplied by a factor.

    :meth:`inject` sets ``sensor.profile`` to the clean profile (the one the sensor had when the
    fault was first injected) with each of ``fields`` multiplied by ``params["factor"]`` (default
    10; ValueError unless finite and >= 0): injected again, the factor applies to the clean
    profile, not on top. :meth:`clear` puts the clean profile back."""

    def __init__(self, *fields: str) -> None:
        self.fields = fields
        self.clean: Any = None

    def inject(self, sensor: Any, params: Mapping[str, Any]) -> None:
        factor = float(params.get("factor", 10.0))
        if not (factor >= 0 and math.isfinite(factor)):
            raise ValueError(f"noise factor must be >= 0, got {factor}")
        if self.clean is None:
            self.clean = sensor.profile
        p = self.clean
        sensor.profile = dataclasses.replace(p, **{f: getattr(p, f) * factor for f in self.fields})

    def clear(self, sensor: Any) -> None:
        if self.clean is not None:
            sensor.profile = self.clean


class SensorFaults(Device):
    """The faults of a device over one sensor model, ``self.sim``: every fault of ``FAULTS`` injected
    stays in ``self.faults`` (its parameters) until cleared, for the device's sampling to look at
    (``"stuck" in self.faults``); ``noise`` scales the figures ``NOISE_FIELDS`` of the model's
    profile (:class:`NoiseFault`, ``self.noise``). A device puts it before its link's base class
    (``class DvlDevice(SensorFaults, TcpServerDevice)``) and extends :meth:`inject_fault` and
    :meth:`clear_fault` for faults that act on more than its own output."""

    NOISE_FIELDS: ClassVar[tuple[str, ...]] = ()
    sim: Any

    def __init__(self, name: str, options: Mapping[str, Any], ctx: DeviceContext) -> None:
        super().__init__(name, options, ctx)
        self.faults: dict[str, Any] = {}
        self.noise = NoiseFault(*self.NOISE_FIELDS)

    def inject_fault(self, fault: str, params: Mapping[str, Any]) -> None:
        if fault == "noise":
            self.noise.inject(self.sim, params)
        elif fault not in self.FAULTS:
            super().inject_fault(fault, params)
        self.faults[fault] = dict(params)

    def clear_fault(self, fault: str) -> None:
        self.faults.pop(fault, None)
        if fault == "noise":
            self.noise.clear(self.sim)


class _Unsubscribe:
    """A bus subscription as an owned link: closing it unsubscribes."""

    def __init__(self, fn: Callable[[], None]) -> None:
        self._fn = fn

    def close(self) -> None:
        self._fn()
