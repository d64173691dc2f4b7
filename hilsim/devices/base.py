"""The contract between the bridge and an emulated device.

A device is built from one ``[[devices]]`` table of the scenario::

    [[devices]]
    name = "sonar_ddf"        # shown in the endpoints table
    protocol = "ddf-stream"   # picks the class (hilsim.devices.REGISTRY)
    sensor = "sonar"          # other keys are the device's OPTIONS
    port = 0                  # 0: a free port is picked

The bridge calls ``await start()`` once (the device opens its links, adds its
periodic events to ``ctx.scheduler`` and returns its endpoints), reads
``status()`` for the status line, and ``await close()`` at shutdown. Devices
never block the event loop: sonar frames are rendered in the worker process
through ``await ctx.render(...)``.

Errors: a peer sending something bad is counted and answered as the real
device would (never an exception out of a device); a bug of ours raises.
"""

from __future__ import annotations

import difflib
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Awaitable, Callable, ClassVar, Mapping, Protocol, TypeVar

if TYPE_CHECKING:
    from hilsim.runtime.scheduler import Scheduler, VehicleLoop
    from hilsim.sim.scenario import Scenario
    from hilsim.sim.sonar import SonarFrame
    from hilsim.sim.sonar_profile import SonarProfile, SonarSettings
    from hilsim.sim.state import VehicleState

T = TypeVar("T")


@dataclass(frozen=True)
class Endpoint:
    """Where a client reaches a device.

    protocol: short lower-case name (``ddf-stream``, ``vesc-can``, ``modbus-keller``);
    transport: ``tcp``, ``udp``, ``pty``, ``socketcand``, ``slcan``, ``socketcan``, ...;
    address: ``"127.0.0.1:PORT"`` for TCP/UDP, a path for a pty; extra: what else a
    client needs (``{"channel": "can0"}``, ``{"baudrate": 115200}``).
    """

    device: str
    protocol: str
    transport: str
    address: str
    extra: Mapping[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"device": self.device, "protocol": self.protocol, "transport": self.transport,
                "address": self.address, **dict(self.extra)}


@dataclass(frozen=True)
class RenderedFrame:
    """A sonar frame rendered in the worker, with the state it was pinged at.

    frame: the simulator's frame (``image`` (n_samples, n_beams) uint8, ``intensity``
    float, ``ranges``, ``azimuths``, beams ascending from port); state: the vehicle
    state at the ping; render_s: [s] wall time the render took; altitude: [m] from the
    vehicle straight down to the first surface (inf if none).
    """

    frame: "SonarFrame"
    state: "VehicleState"
    render_s: float
    altitude: float = float("inf")


class RenderFailed(RuntimeError):
    """The render worker could not produce a frame (it crashed or hung and is being restarted)."""


class DeviceContext(Protocol):
    """What the bridge gives every device."""

    scenario: "Scenario"
    scheduler: "Scheduler"
    vehicle: "VehicleLoop"          # .state: VehicleState, .thrusters: ThrusterSet | None
    bind: str                       # host servers listen on (127.0.0.1 unless told otherwise)
    broadcast: str                  # destination of UDP status/beacons (loopback by default)
    run_dir: Path                   # default folder for pty symlinks
    seed: int
    fast: bool                      # virtual (as-fast-as-possible) clock

    def now(self) -> float:
        """[s] simulation time."""

    def wall_time(self, sim_time: float) -> float:
        """UNIX time [s] stamped on the wire for a simulation time [s]."""

    def sonar_profile(self, name: str) -> "SonarProfile":
        """Load a sonar profile by reference (``didson_hf``, ``sonars/oculus_m750d``)."""

    async def render(self, mount: str, profile: str, settings: "SonarSettings | None" = None, *,
                     frame_index: int = 0) -> RenderedFrame:
        """Render a sonar frame from the sensor mount ``mount`` at the current state, with the
        sonar profile ``profile`` and ``settings``; raises :class:`RenderFailed`."""

    def pty_path(self, option: "str | Path | None", default: str) -> Path:
        """A device's pty symlink path: inside the run folder (absolute paths and ``..`` refused)."""

    def output_path(self, option: "str | Path") -> Path:
        """A file a scenario asks a device to write: inside the scenario's folder."""

    async def shared(self, key: tuple[Any, ...], factory: Callable[[], Awaitable[T]]) -> T:
        """A link shared by several devices (a CAN bus): created once by ``factory``, closed
        by the bridge at shutdown (it must have ``async close()``)."""


class OptionError(ValueError):
    """A device option the device refuses. ``option`` names the key, so the bridge can report the
    scenario's file, line and ``[devices.<name>.<option>]``; ``message`` says what is wrong
    (``str()`` puts ``context`` first, e.g. "device 'depth'", for use outside a scenario)."""

    def __init__(self, option: str, message: str, context: str | None = None) -> None:
        super().__init__(f"{context}: {message}" if context else message)
        self.option = option
        self.message = message


class Device(ABC):
    """An emulated device. Subclasses set ``protocol`` and ``OPTIONS`` (key -> default).

    Option errors: raise :class:`OptionError` naming the option (or ValueError for one that
    concerns several); :meth:`option_pty_path` and :meth:`option_output_path` check a path option.
    """

    protocol: ClassVar[str]
    OPTIONS: ClassVar[Mapping[str, Any]] = {}

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

    def option_pty_path(self, key: str, default: str) -> Path:
        """``ctx.pty_path`` of the option ``key`` (``default`` when unset); a path the run
        folder refuses raises :class:`OptionError` naming ``key``."""
        try:
            return self.ctx.pty_path(self._path_option(key) or None, default)
        except ValueError as exc:
            raise OptionError(key, str(exc), f"device {self.name!r}") from None

    def option_output_path(self, key: str) -> Path:
        """``ctx.output_path`` of the option ``key``; a refused path raises :class:`OptionError`."""
        try:
            return self.ctx.output_path(self._path_option(key))
        except ValueError as exc:
            raise OptionError(key, str(exc), f"device {self.name!r}") from None

    def _path_option(self, key: str) -> str:
        value = self.options[key]
        if value is not None and not isinstance(value, str):
            raise OptionError(key, f"expected a relative path, got {value!r}", f"device {self.name!r}")
        return value or ""

    @abstractmethod
    async def start(self) -> list[Endpoint]:
        """Open links, register periodic events; return the endpoints."""

    @abstractmethod
    async def close(self) -> None:
        """Close links; flush recordings. Idempotent."""

    def status(self) -> dict[str, float]:
        """Counters for the status line (clients, frames sent, drops, errors ...)."""
        return {}

    #: device-level faults this device can show (``inject_fault``); link faults
    #: (``bit_errors`` on a serial line, ``silent`` on a CAN bus) are the bridge's.
    FAULTS: ClassVar[tuple[str, ...]] = ()

    def inject_fault(self, fault: str, params: Mapping[str, Any]) -> None:
        """Show ``fault`` on the wire as the real device would, until :meth:`clear_fault`."""
        raise ValueError(f"device {self.name!r} ({self.protocol}) has no fault {fault!r}"
                         + (f"; it has: {', '.join(self.FAULTS)}" if self.FAULTS else ""))

    def clear_fault(self, fault: str) -> None:
        """End ``fault``; the device behaves normally again."""
