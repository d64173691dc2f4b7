"""The CAN bus devices attach to, and what every transport shares.

A :class:`CanBus` is one CAN network as the emulated devices see it: they
``send(frame)`` onto it and ``subscribe(callback)`` to the frames its peers
put on it. The peers are whatever the transport connects: TCP clients of the
socketcand server, the host on the slcan pty, the kernel's SocketCAN
interface, or python-can ``virtual`` buses in the same process.

The base class owns the control flow; a transport fills in ``_start``,
``_close`` and ``_to_peers`` (python-can's pattern). Flow control, the same for
every transport:

* a frame from a peer costs its bits on the wire from that peer's own
  budget (a token bucket at ``bitrate`` [bit/s] with ``burst`` [s] of
  credit); beyond it the frame is dropped and counted (``dropped_in``), so
  a flooding client cannot starve a well-behaved one;
* subscribers are called synchronously, in the order they subscribed; an
  exception in one is logged and counted (``subscriber_errors``), never
  propagated into the transport;
* frames to peers that cannot take them (full queue, closed channel) are
  dropped and counted (``dropped_out``).

Devices on one bus do not hear each other's frames (only the peers' ones).
"""

from __future__ import annotations

import logging
import time
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass
from typing import Any, Callable, ClassVar

from hilsim.protocols.can import CanFrame

log = logging.getLogger(__name__)

Subscriber = Callable[[CanFrame], None]


@dataclass
class BusStats:
    """Counters of one bus (frames unless named otherwise)."""

    frames_in: int = 0            # accepted from peers
    frames_out: int = 0           # sent by devices
    dropped_in: int = 0           # from peers, beyond their budget
    dropped_out: int = 0          # to peers that could not take them (counted per peer)
    forwarded: int = 0            # peer -> other peers (hub transports)
    errors: int = 0               # malformed input from peers (bad lines / messages)
    subscriber_errors: int = 0    # exceptions in device callbacks (our bugs)
    silenced: int = 0             # frames lost while the bus was silent (fault injection)
    clients: int = 0              # peers connected now


class TokenBucket:
    """``rate`` units per second with ``capacity`` units of credit; ``take(n)`` spends n if it can."""

    def __init__(self, rate: float, capacity: float, clock: Callable[[], float] = time.monotonic) -> None:
        if rate <= 0 or capacity <= 0:
            raise ValueError("a token bucket needs a positive rate and capacity")
        self.rate = float(rate)
        self.capacity = float(capacity)
        self._clock = clock
        self._tokens = float(capacity)
        self._t = clock()

    def take(self, n: float) -> bool:
        now = self._clock()
        self._tokens = min(self.capacity, self._tokens + (now - self._t) * self.rate)
        self._t = now
        if self._tokens >= n:
            self._tokens -= n
            return True
        return False


class CanBus(ABC):
    """One CAN network the devices attach to (see the module doc).

    name: for logs; channel: the bus name clients open (``can0``); bitrate
    [bit/s]: the bus's capacity per peer (None: unlimited); burst [s]: credit
    a peer may spend at once.
    """

    transport: ClassVar[str] = ""
    silent = False  # fault injection: the bus carries nothing (a cut or unpowered bus)
    FAULTS = ("silent",)

    def set_fault(self, fault: str, on: bool, params: Any = None) -> None:
        """``silent``: the bus carries nothing, either way, while on."""
        if fault != "silent":
            raise ValueError(f"a CAN bus has no fault {fault!r}")
        self.silent = on

    def __init__(self, name: str, channel: str = "can0", *, bitrate: int | None = 1_000_000,
                 burst: float = 0.05) -> None:
        self.name = name
        self.channel = channel
        self.bitrate = bitrate
        self.burst = burst
        self.stats = BusStats()
        self._subscribers: list[Subscriber] = []
        self._started = False
        self._closed = False

    # -- what devices use ---------------------------------------------------------

    def subscribe(self, callback: Subscriber) -> Callable[[], None]:
        """Call ``callback(frame)`` for every frame a peer puts on the bus; returns an unsubscribe."""
        self._subscribers.append(callback)

        def unsubscribe() -> None:
            if callback in self._subscribers:
                self._subscribers.remove(callback)
        return unsubscribe

    def send(self, frame: CanFrame) -> None:
        """Put a device's frame on the bus (to every peer)."""
        if self._closed:
            return
        if self.silent:
            self.stats.silenced += 1
            return
        self.stats.frames_out += 1
        self._to_peers(frame, None)

    @property
    def has_listeners(self) -> bool:
        """False when no peer could receive a frame now (devices may then skip encoding telemetry)."""
        return True

    @property
    @abstractmethod
    def address(self) -> str:
        """Where a client connects (``host:port``, a tty path, an interface name)."""

    @property
    def extra(self) -> dict[str, Any]:
        """Keyword arguments for ``can.Bus(**extra)`` that reach this bus from a client."""
        return {"interface": self.transport, "channel": self.channel}

    def status(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self.stats).items()}

    async def start(self) -> None:
        if self._started:
            return
        self._started = True
        await self._start()

    async def close(self) -> None:
        """Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._subscribers.clear()
        if self._started:
            await self._close()

    # -- what transports use -----------------------------------------------------

    def new_budget(self) -> TokenBucket | None:
        """A fresh per-peer budget (None when the bus is unlimited)."""
        if not self.bitrate:
            return None
        return TokenBucket(self.bitrate, self.bitrate * self.burst)

    def from_peer(self, frame: CanFrame, peer: Any = None, budget: TokenBucket | None = None) -> bool:
        """A frame a peer put on the bus: charge its budget, hand it to the devices and
        (hub transports) to the other peers. False if dropped over budget."""
        if self.silent:
            self.stats.silenced += 1
            return False
        if budget is not None and not budget.take(frame.bits_on_wire):
            self.stats.dropped_in += 1
            return False
        self.stats.frames_in += 1
        for cb in list(self._subscribers):
            try:
                cb(frame)
            except Exception:  # noqa: BLE001 - a device bug must not take the bus down
                self.stats.subscriber_errors += 1
                log.exception("%s: subscriber failed on %r", self.name, frame)
        if peer is not None:
            self._forward(frame, peer)
        return True

    def _forward(self, frame: CanFrame, source: Any) -> None:
        """Hub transports pass a peer's frame on to the other peers (default: nothing)."""

    # -- what a transport implements -------------------------------------------

    @abstractmethod
    async def _start(self) -> None:
        """Open the transport (bind, create the pty, open the interface)."""

    @abstractmethod
    async def _close(self) -> None:
        """Release the transport."""

    @abstractmethod
    def _to_peers(self, frame: CanFrame, exclude: Any) -> None:
        """Deliver ``frame`` to every peer except ``exclude``; count what cannot be delivered."""
