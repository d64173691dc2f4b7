"""The live browser console (``hilsim run`` serves it) and how the bridge attaches its observers.

:func:`attach` starts, on a running bridge, whatever the command line asked for: the console
(an aiohttp server on the bridge's loop, :mod:`hilsim.console.server`), the MCAP recording
and the Foxglove WebSocket server (:mod:`hilsim.record`), and the camera feed they share
(pictures rendered only while a page shows them or a recording asks). The bridge calls it
in ``start`` and closes what it returns in ``close``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

log = logging.getLogger("hilsim.console")


class Attached:
    """What :func:`attach` started: ``endpoints`` to add to the table, ``await close()``."""

    def __init__(self) -> None:
        self.console: Any = None
        self.recorder: Any = None
        self.camera: Any = None
        self.endpoints: list[Any] = []

    @property
    def url(self) -> str | None:
        return self.console.url if self.console is not None else None

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


async def attach(bridge: Any, *, console_port: int | None = 0, record_mcap: Path | str | None = None,
                 foxglove_port: int | None = None, max_pages: int = 8) -> Attached:
    """Start the console (``console_port``: 0 a free port, None none), the MCAP recording
    (``record_mcap``) and the Foxglove server (``foxglove_port``: 0 a free port, None none)."""
    from hilsim.console.camera import CameraFeed
    from hilsim.devices.base import Endpoint

    out = Attached()
    if console_port is None and record_mcap is None and foxglove_port is None:
        return out
    out.camera = CameraFeed(bridge)
    try:
        if record_mcap is not None or foxglove_port is not None:
            from hilsim.record.recorder import Recorder

            out.recorder = Recorder(bridge, mcap_path=record_mcap, foxglove_port=foxglove_port, camera=out.camera)
            out.endpoints.extend(out.recorder.start())
        if console_port is not None:
            from hilsim.console.server import Console

            out.console = Console(bridge, port=console_port, max_pages=max_pages, camera=out.camera)
            url = await out.console.start()
            out.endpoints.insert(0, Endpoint("console", "http", "tcp", url.split("//", 1)[1].rstrip("/"),
                                             {"url": url, "max_pages": max_pages}))
    except BaseException:
        await out.close()
        raise
    return out
