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
from pathlib import Path
from typing import Any, ClassVar, Mapping

from hilsim.devices.context import DeviceContext, Endpoint, Periodic, RenderedFrame, RenderFailed, VehicleView

__all__ = ["Device", "DeviceContext", "Endpoint", "OptionError", "Periodic", "RenderedFrame", "RenderFailed",
           "VehicleView"]


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
