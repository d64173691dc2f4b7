"""What a device may ask of the bridge: the device context, a typed interface on the devices' side.

Devices import nothing from :mod:`hilsim.runtime`; the runtime's bridge implements
:class:`DeviceContext` and is handed to every device. Everything a device needs
goes through here:

* time: :meth:`~DeviceContext.now` (simulation time), :meth:`~DeviceContext.wall_time`
  (the UNIX time stamped on the wire);
* periodic work on the simulation clock: :meth:`~DeviceContext.every` returns a
  :class:`Periodic` handle (``cancel()``); :meth:`~DeviceContext.at` runs once; a
  callback that must await (a render) returns :meth:`~DeviceContext.defer`\\(coro);
* the world and the vehicle: :attr:`~DeviceContext.scenario`,
  :attr:`~DeviceContext.vehicle` (a :class:`VehicleView`), :attr:`~DeviceContext.world`
  (the main process's ray-cast scene for short queries: DVL beams, an altimeter, a
  scanning sonar's single beam) and :meth:`~DeviceContext.render` (a sonar frame
  rendered in the worker process);
* lockstep: a device that is the simulation's clock master (ArduPilot's JSON
  backend) declares ``clock_master = True`` and awaits :meth:`~DeviceContext.advance`
  per step it is asked for (the bridge then runs on a lockstep clock: simulated time
  stands still between steps while every link keeps serving);
* places: :meth:`~DeviceContext.pty_path`, :meth:`~DeviceContext.output_path`;
  shared links: :meth:`~DeviceContext.shared`;
* observation: :meth:`~DeviceContext.publish` puts what a device served or received
  (a sonar frame, a reading, a command) on a topic for the console and the MCAP
  recorder; :meth:`~DeviceContext.observed` says whether anyone listens, so a device
  builds nothing for nobody.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Awaitable, Callable, Mapping, Protocol, TypeVar

if TYPE_CHECKING:
    from hilsim.sim.scenario import Scenario
    from hilsim.sim.sonar import SonarFrame
    from hilsim.sim.sonar_profile import SonarProfile, SonarSettings
    from hilsim.sim.state import VehicleState
    from hilsim.sim.thrusters import ThrusterSet
    from hilsim.sim.world import World

T = TypeVar("T")


@dataclass(frozen=True)
class Endpoint:
    """Where a client reaches a device.

    protocol: short lower-case name (``ddf-stream``, ``vesc-can``, ``modbus-keller``);
    transport: ``tcp``, ``udp``, ``pty``, ``socketcand``, ``slcan``, ``socketcan``, ``http``, ...;
    address: ``"127.0.0.1:PORT"`` for TCP/UDP, a path for a pty; extra: what else a
    client needs (``{"channel": "can0"}``, ``{"baudrate": 115200}``).
    """

    device: str
    protocol: str
    transport: str
    address: str
    extra: Mapping[str, Any] = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.extra is None:
            object.__setattr__(self, "extra", {})

    def to_json(self) -> dict[str, Any]:
        return {"device": self.device, "protocol": self.protocol, "transport": self.transport,
                "address": self.address, **dict(self.extra)}


@dataclass(frozen=True)
class RenderedFrame:
    """A sonar frame rendered in the worker, with the state it was pinged at.

    frame: the simulator's frame (``image`` (n_samples, n_beams) uint8, ``intensity``
    float, ``ranges``, ``azimuths``, beams ascending from port); state: the vehicle
    state at the ping; render_s: [s] wall time the render took; altitude: [m] from the
    vehicle straight down to the first surface (inf if none); rays: elevation rays per
    beam the worker used (it lowers them when frames would miss their period).
    """

    frame: "SonarFrame"
    state: "VehicleState"
    render_s: float
    altitude: float = float("inf")
    rays: int = 0


class RenderFailed(RuntimeError):
    """The render worker could not produce a frame (it crashed or hung and is being restarted)."""


class OptionError(ValueError):
    """A device option the device refuses. ``option`` names the key, so the bridge can report the
    scenario's file, line and ``[devices.<name>.<option>]``; ``message`` says what is wrong
    (``str()`` puts ``context`` first, e.g. "device 'depth'", for use outside a scenario)."""

    def __init__(self, option: str, message: str, context: str | None = None) -> None:
        super().__init__(f"{context}: {message}" if context else message)
        self.option = option
        self.message = message


class Periodic(Protocol):
    """A handle on periodic work registered with :meth:`DeviceContext.every`."""

    def cancel(self) -> None:
        """Stop it; its pending tick is dropped. Idempotent."""


class VehicleView(Protocol):
    """The vehicle as devices see it."""

    @property
    def state(self) -> "VehicleState":
        """The state at the last physics tick."""

    @property
    def thrusters(self) -> "ThrusterSet | None":
        """The thruster set (commands in, telemetry out), None for a vehicle without thrusters."""


class DeviceContext(Protocol):
    """What the bridge gives every device."""

    scenario: "Scenario"
    vehicle: VehicleView
    world: "World"                  # the main process's scene for short ray queries (moves included)
    bind: str                       # host servers listen on (127.0.0.1 unless told otherwise)
    broadcast: str                  # destination of UDP status/beacons (loopback by default)
    run_dir: Path                   # default folder for pty symlinks
    seed: int
    fast: bool                      # virtual (as-fast-as-possible) clock

    def now(self) -> float:
        """[s] simulation time."""

    def wall_time(self, sim_time: float) -> float:
        """UNIX time [s] stamped on the wire for a simulation time [s]."""

    def every(self, name: str, period: float, callback: Callable[[float], Any], *, offset: float = 0.0,
              priority: int = 20, tolerance: float | None = None) -> Periodic:
        """Run ``callback(t)`` every ``period`` [s] of simulation time from ``offset`` [s] (``t``: the
        tick's scheduled time). Priority orders callbacks due together (physics 0, sensors 10,
        devices 20+). A callback may return :meth:`defer`'s result."""

    def at(self, t: float, callback: Callable[[float], Any], name: str = "at") -> None:
        """Run ``callback(t)`` once at simulation time ``t`` [s] (now if already past)."""

    def defer(self, coro: Awaitable[Any]) -> Awaitable[Any] | None:
        """For a periodic callback that must await: return ``ctx.defer(coro)``. In fast mode and
        in lockstep the clock waits for it; in real time it runs as a task and the tick returns
        at once."""

    async def advance(self, dt: float) -> None:
        """Lockstep (only for a device with ``clock_master = True``): run the simulation ``dt`` [s]
        forward now (physics, thrusters, every device's schedule); returns when that is done and
        ``vehicle.state`` is the state at the new time."""

    def reset_vehicle(self) -> None:
        """Put the vehicle back at the scenario's start, at rest (a clock master that restarted)."""

    def sonar_profile(self, name: str) -> "SonarProfile":
        """Load a sonar profile by reference (``didson_hf``, ``sonars/oculus_m750d``)."""

    async def render(self, mount: str, profile: str, settings: "SonarSettings | None" = None, *,
                     frame_index: int = 0, budget_s: float | None = None) -> RenderedFrame:
        """Render a sonar frame from the sensor mount ``mount`` at the current state, with the
        sonar profile ``profile`` and ``settings``; raises :class:`RenderFailed`. ``budget_s`` [s]:
        the frame's period; when frames would miss it the worker casts fewer elevation rays per
        beam (the profile's ``adaptive_rays``), and ``RenderedFrame.rays`` says how many."""

    async def altitude(self) -> float:
        """[m] from the vehicle straight down to the first surface (inf if none)."""

    def pty_path(self, option: "str | Path | None", default: str) -> Path:
        """A device's pty symlink path: inside the run folder (absolute paths and ``..`` refused)."""

    def output_path(self, option: "str | Path") -> Path:
        """A file a scenario asks a device to write: inside the scenario's folder."""

    async def shared(self, key: tuple[Any, ...], factory: Callable[[], Awaitable[T]]) -> T:
        """A link shared by several devices (a CAN bus): created once by ``factory``, closed
        by the bridge at shutdown (it must have ``async close()``)."""

    def observed(self, topic: str) -> bool:
        """Whether anything listens to ``topic`` (build a message only then)."""

    def publish(self, topic: str, message: Mapping[str, Any]) -> None:
        """Put ``message`` (``t`` [s] simulation time, then the topic's fields) on ``topic``:
        ``sonar/<device>`` for a frame served, ``reading/<device>`` for a sensor reading served,
        ``command/<device>`` for a command received. Listeners must not block."""
