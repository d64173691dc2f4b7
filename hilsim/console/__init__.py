"""The live browser console (``hilsim run`` serves it) and how the bridge attaches its observers.

:func:`prepare` builds whatever the command line asked for: the console (an aiohttp server
on the bridge's loop, :mod:`hilsim.console.server`), the MCAP recording and the Foxglove
WebSocket server (:mod:`hilsim.record`), and the camera feed they share (pictures rendered
only while a page shows them or a recording asks). The bridge calls it in ``start`` before
its devices start (the recorder hears their first readings), starts it once they listen, and
closes it in ``close``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

log = logging.getLogger("hilsim.console")


class Attached:
    """What the bridge attaches: :func:`prepare` before its devices start (the recorder listens
    from the first reading), ``await start()`` once they listen (the sinks open, the console
    serves; returns the endpoints to add to the table), ``await close()`` at shutdown."""

    def __init__(self, bridge: Any, console_port: int | None, max_pages: int) -> None:
        self.bridge = bridge
        self.console_port = console_port
        self.max_pages = max_pages
        self.console: Any = None
        self.recorder: Any = None
        self.camera: Any = None
        self.endpoints: list[Any] = []

    @property
    def url(self) -> str | None:
        return self.console.url if self.console is not None else None

    async def start(self) -> list[Any]:
        from hilsim.devices.base import Endpoint

        try:
            if self.recorder is not None:
                self.endpoints.extend(self.recorder.start())
            if self.console_port is not None:
                from hilsim.console.server import Console

                self.console = Console(self.bridge, port=self.console_port, max_pages=self.max_pages,
                                       camera=self.camera)
                for e in self.endpoints:  # the recorder's rows show its counts
                    self.console.hub.extra_status[e.device] = self.recorder.status
                url = await self.console.start()
                self.endpoints.insert(0, Endpoint("console", "http", "tcp", url.split("//", 1)[1].rstrip("/"),
                                                  {"url": url, "max_pages": self.max_pages}))
        except BaseException:
            await self.close()
            raise
        return self.endpoints

    async def close(self) -> None:
        if self.recorder is not None:
            try:
                self.recorder.close()
            except Exception:  # noqa: BLE001 - close the rest regardless
                log.exception("closing the recorder")
        if self.console is not None:
            try:
                await self.console.close()
            except Exception:  # noqa: BLE001
                log.exception("closing the console")
        if self.camera is not None:
            await self.camera.close()


def prepare(bridge: Any, *, console_port: int | None = 0, record_mcap: Path | str | None = None,
            foxglove_port: int | None = None, max_pages: int = 8) -> Attached | None:
    """Before the bridge's devices start: the console (``console_port``: 0 a free port, None
    none), the MCAP recording (``record_mcap``) and the Foxglove server (``foxglove_port``: 0 a
    free port, None none); None when nothing is asked for. Call ``await start()`` on the result
    once the devices listen."""
    from hilsim.console.camera import CameraFeed

    if console_port is None and record_mcap is None and foxglove_port is None:
        return None
    out = Attached(bridge, console_port, max_pages)
    out.camera = CameraFeed(bridge)
    if record_mcap is not None or foxglove_port is not None:
        from hilsim.record.recorder import Recorder

        out.recorder = Recorder(bridge, mcap_path=record_mcap, foxglove_port=foxglove_port, camera=out.camera)
        out.recorder.subscribe()
    return out


async def attach(bridge: Any, **options: Any) -> Attached | None:
    """:func:`prepare` and start at once (on a bridge whose devices already listen)."""
    out = prepare(bridge, **options)
    if out is not None:
        await out.start()
    return out
