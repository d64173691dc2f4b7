"""Camera pictures on demand: rendered only while someone shows or records them.

The scenario's camera mounts are rendered in the bridge's render worker
(``bridge.render_camera``), at a reduced width and a low rate, only while at
least one consumer wants them (a page showing the camera, an MCAP recording).
Each picture is published on ``camera/<mount>`` of the bridge's observers as
``{"t" [s], "rgb" (h, w, 3) uint8, "jpeg" bytes, "mount"}``, so the console and
the recorder get the same picture.
"""

from __future__ import annotations

import asyncio
import io
import logging
import time
from typing import Any

import numpy as np

log = logging.getLogger("hilsim.console.camera")


def encode_jpeg(rgb: np.ndarray, quality: int = 80) -> bytes:
    """(h, w, 3) uint8 -> JPEG bytes."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8), "RGB").save(buf, "JPEG", quality=quality)
    return buf.getvalue()


class CameraFeed:
    """Renders the scenario's cameras while anyone asks (``want``/``unwant`` by consumer key).

    rate_hz: the most pictures per second per camera a consumer may ask for (the feed runs at
    the highest rate asked); max_width [px]: pictures are rendered at most this wide (same
    field of view). 240 px (43 k rays, about 15 ms) rather than 320 px (77 k rays): above about
    64 k rays Embree goes multi-threaded and, on a busy 2-core machine, takes 8 times as long,
    which the sonar frames queued behind it in the render worker would pay."""

    #: the most of the render worker's time camera pictures may take (the sonars come first)
    SHARE = 0.1

    def __init__(self, bridge: Any, *, max_width: int = 240) -> None:
        self.bridge = bridge
        self.max_width = int(max_width)
        self.mounts = [s.name for s in bridge.scenario.sensors if s.kind == "camera"]
        self._wants: dict[Any, float] = {}
        self._task: asyncio.Task[None] | None = None
        self._wake = asyncio.Event()
        self.frames = 0
        self.failures = 0
        self.last_error = ""

    @property
    def active(self) -> bool:
        return bool(self._wants) and bool(self.mounts)

    def want(self, who: Any, rate_hz: float) -> None:
        self._wants[who] = max(0.1, min(float(rate_hz), 15.0))
        self._wake.set()
        if self.mounts and (self._task is None or self._task.done()):
            self._task = asyncio.ensure_future(self._run())

    def unwant(self, who: Any) -> None:
        self._wants.pop(who, None)

    async def _run(self) -> None:
        while self._wants:
            t0 = time.monotonic()
            cold = self.bridge.worker.pid is None  # this render starts the worker (about 1 s): not a render's cost
            for mount in self.mounts:
                await self._one(mount)
            if not self._wants:
                break
            used = time.monotonic() - t0
            # at the highest rate asked, but at most SHARE of the render worker's time
            period = 1.0 / max(self._wants.values())
            if not cold:
                period = max(period, used / self.SHARE)
            self._wake.clear()
            delay = period - used
            if delay > 0:
                try:  # a new, faster consumer wakes the loop early
                    await asyncio.wait_for(self._wake.wait(), delay)
                except asyncio.TimeoutError:
                    pass

    async def _one(self, mount: str) -> None:
        from hilsim.devices.base import RenderFailed

        # the sonars first: a picture waits (up to half a second) until the render worker is idle
        lock = getattr(getattr(self.bridge, "worker", None), "_lock", None)
        deadline = time.monotonic() + 0.5
        while lock is not None and lock.locked() and time.monotonic() < deadline:
            await asyncio.sleep(0.005)
        try:
            rgb, state = await self.bridge.render_camera(mount, max_width=self.max_width)
        except RenderFailed as exc:
            self.failures += 1
            self.last_error = str(exc)
            log.warning("camera %s: %s", mount, exc)
            await asyncio.sleep(0.5)
            return
        self.frames += 1
        topic = f"camera/{mount}"
        if self.bridge.observers.observed(topic):
            self.bridge.observers.publish(topic, {"t": float(state.time), "mount": mount, "rgb": rgb,
                                                  "jpeg": encode_jpeg(rgb)})

    async def close(self) -> None:
        self._wants.clear()
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
