"""CAN buses reached through python-can: SocketCAN (the kernel's vcan0/can0) and python-can's
in-process ``virtual`` bus (for tests).

A background thread reads the python-can bus (``recv`` with a short timeout)
and hands each frame to the asyncio loop; at most ``max_pending`` frames
wait in that hand-off, more are dropped and counted. Sending is python-can's
``send``; a full kernel transmit queue counts as ``dropped_out``.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import socket
import threading
from typing import Any

from hilsim.links.can.bus import CanBus
from hilsim.protocols.can import CanFrame

log = logging.getLogger(__name__)


def socketcan_available() -> tuple[bool, str]:
    """(True, "") if a raw CAN socket can be opened here, else (False, why not)."""
    family = getattr(socket, "AF_CAN", None)
    if family is None:
        return False, "socket.AF_CAN is missing (not Linux, or Python built without CAN support)"
    try:
        s = socket.socket(family, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as exc:
        why = "the kernel has no CAN support" if exc.errno == errno.EAFNOSUPPORT else str(exc)
        return False, f"cannot open a SocketCAN socket: {why} (errno {exc.errno})"
    s.close()
    return True, ""


class PythonCanBus(CanBus):
    """A python-can bus of ``interface`` on ``channel``; unlimited bitrate by default (the
    real bus limits itself)."""

    interface = ""

    def __init__(self, name: str, channel: str = "can0", *, bitrate: int | None = None, burst: float = 0.05,
                 max_pending: int = 10_000, poll: float = 0.05) -> None:
        super().__init__(name, channel, bitrate=bitrate, burst=burst)
        self.max_pending = max_pending
        self.poll = poll
        self._bus: Any = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._pending = 0
        self._lock = threading.Lock()
        self._budget = self.new_budget()

    @property
    def address(self) -> str:
        return self.channel

    def _open(self) -> Any:
        import can

        return can.Bus(interface=self.interface, channel=self.channel, receive_own_messages=False)

    async def _start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._bus = self._open()
        self.stats.clients = 1
        self._thread = threading.Thread(target=self._reader, name=f"{self.name}-reader", daemon=True)
        self._thread.start()

    async def _close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, 2.0)
        if self._bus is not None:
            try:
                self._bus.shutdown()
            except Exception:  # noqa: BLE001 - shutting down regardless
                log.exception("%s: shutdown", self.name)
            self._bus = None

    def _reader(self) -> None:
        assert self._loop is not None
        while not self._stop.is_set():
            try:
                msg = self._bus.recv(self.poll)
            except Exception as exc:  # noqa: BLE001 - the interface went away
                log.warning("%s: receive failed: %s", self.name, exc)
                self._stop.wait(0.5)
                continue
            if msg is None or msg.is_error_frame or msg.is_fd:
                continue
            try:
                frame = CanFrame(msg.arbitration_id, bytes(msg.data) if not msg.is_remote_frame else b"",
                                 msg.is_extended_id, msg.is_remote_frame, msg.dlc)
            except ValueError:
                self.stats.errors += 1
                continue
            with self._lock:
                if self._pending >= self.max_pending:
                    self.stats.dropped_in += 1
                    continue
                self._pending += 1
            try:
                self._loop.call_soon_threadsafe(self._deliver, frame)
            except RuntimeError:  # loop closed
                return

    def _deliver(self, frame: CanFrame) -> None:
        with self._lock:
            self._pending -= 1
        if not self._closed:
            self.from_peer(frame, None, self._budget)

    def _to_peers(self, frame: CanFrame, exclude: Any) -> None:
        import can

        if self._bus is None:
            return
        msg = can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=frame.is_extended,
                          is_remote_frame=frame.is_remote, dlc=frame.dlc)
        try:
            self._bus.send(msg, timeout=0.0)
        except Exception:  # noqa: BLE001 - can.CanOperationError: the transmit queue is full
            self.stats.dropped_out += 1


class SocketCanBus(PythonCanBus):
    """The kernel's SocketCAN interface ``channel`` (vcan0, can0). Raises OSError with the
    reason where this machine has no SocketCAN."""

    transport = "socketcan"
    interface = "socketcan"

    def _open(self) -> Any:
        ok, why = socketcan_available()
        if not ok:
            raise OSError(f"{self.name}: SocketCAN unavailable: {why}")
        return super()._open()


class VirtualBus(PythonCanBus):
    """python-can's in-process ``virtual`` bus named ``channel`` (tests): clients open
    ``can.Bus(interface="virtual", channel=channel)`` in the same process."""

    transport = "virtual"
    interface = "virtual"
