"""CAN transports: one :class:`CanBus` interface, several ways for clients to reach it.

Transports load lazily from :data:`TRANSPORTS` (name -> "module:Class"), as
python-can loads its interfaces:

    socketcand  a socketcand-compatible TCP server (python-can's ``socketcand`` client connects)
    slcan       an slcan (Lawicel) adapter on a pty (python-can's and dronecan's ``slcan``)
    socketcan   the kernel's SocketCAN (vcan0/can0), through python-can; Linux with CAN only
    virtual     python-can's in-process ``virtual`` bus, for tests

``create_bus(transport, name, **options)`` builds one (then ``await bus.start()``).
"""

from __future__ import annotations

import difflib
import importlib
from typing import Any

from hilsim.links.can.bus import BusStats, CanBus, TokenBucket

TRANSPORTS: dict[str, str] = {
    "socketcand": "hilsim.links.can.socketcand:SocketcandBus",
    "slcan": "hilsim.links.can.slcan:SlcanBus",
    "socketcan": "hilsim.links.can.pycan:SocketCanBus",
    "virtual": "hilsim.links.can.pycan:VirtualBus",
}

__all__ = ["BusStats", "CanBus", "TokenBucket", "TRANSPORTS", "bus_class", "create_bus", "socketcan_available"]


def bus_class(transport: str) -> type[CanBus]:
    """The bus class of a transport name; KeyError names the known ones."""
    if transport not in TRANSPORTS:
        close = difflib.get_close_matches(transport, list(TRANSPORTS), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise KeyError(f"unknown CAN transport {transport!r}{hint} (known: {', '.join(TRANSPORTS)})")
    module, _, cls = TRANSPORTS[transport].partition(":")
    return getattr(importlib.import_module(module), cls)  # type: ignore[no-any-return,unused-ignore]


def create_bus(transport: str, name: str, **options: Any) -> CanBus:
    """A bus of ``transport`` (not started yet)."""
    return bus_class(transport)(name, **options)


def socketcan_available() -> tuple[bool, str]:
    """Whether this machine can open SocketCAN, and why not."""
    from hilsim.links.can.pycan import socketcan_available as check

    return check()
