"""The console's data side: what the devices publish, kept as the latest value, sent to pages.

The hub listens on the bridge's observers: thruster commands (who commanded each last),
faults and contacts always (small, kept bounded), object moves (the scene a page's ``hello``
holds is updated, and open pages get the objects again in a ``scene`` message); readings, sonar frames and camera
pictures only while a page is open. A listener only stores a reference to the latest message (the device's call
returns at once); the hub's own tick, 10 times a second of wall time and only while
a page is open, builds one state message and encodes each sonar head's newest frame
once, and offers them to every page. A page keeps one slot per kind: a newer item
replaces an unsent one (counted as dropped), so a slow page gets fewer frames and
never a queue.

Binary messages to a page: 4-byte big-endian header length, the JSON header
(``{"type": "sonar" | "camera", ...}``), then the payload (the sonar image, n_samples
rows of n_beams uint8, beam 0 port; or a JPEG).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import struct
import time
from collections import deque
from typing import Any, Callable, Mapping

import numpy as np

from hilsim.console.commands import active_faults
from hilsim.console.scene import object_outlines, scene_description, world_objects

log = logging.getLogger("hilsim.console")

TICK_S = 0.1            # [s] wall time between page updates (<= 10 Hz)
MAX_ROWS = 400          # sonar images to a page: at most this many range rows ...
MAX_BEAMS = 256         # ... and beams (max-pooled: a bright echo is never lost)


def pack(header: Mapping[str, Any], payload: bytes) -> bytes:
    """A binary page message: header length (uint32 BE), JSON header, payload."""
    h = json.dumps(header, separators=(",", ":")).encode()
    return struct.pack(">I", len(h)) + h + payload


def _pool(a: np.ndarray, k: int, axis: int) -> np.ndarray:
    """Max over groups of ``k`` along ``axis`` (the last partial group too)."""
    if k <= 1:
        return a
    n = a.shape[axis]
    pad = (-n) % k
    if pad:
        widths = [(0, 0)] * a.ndim
        widths[axis] = (0, pad)
        a = np.pad(a, widths, mode="edge")
    shape = list(a.shape)
    shape[axis:axis + 1] = [shape[axis] // k, k]
    return a.reshape(shape).max(axis=axis + 1)


def encode_sonar(device: str, msg: Mapping[str, Any]) -> bytes:
    """A ``sonar/<device>`` message as a page's binary message (reduced to MAX_ROWS x MAX_BEAMS)."""
    img = np.asarray(msg["image"], dtype=np.uint8)
    az = np.asarray(msg["azimuths"], dtype=float).reshape(-1)
    kr = -(-img.shape[0] // MAX_ROWS)
    kb = -(-img.shape[1] // MAX_BEAMS)
    img = _pool(_pool(img, kr, 0), kb, 1)
    if kb > 1:
        pad = (-len(az)) % kb
        az = np.concatenate([az, np.full(pad, az[-1])]).reshape(-1, kb).mean(axis=1)
    header = {"type": "sonar", "device": device, "t": round(float(msg.get("t", 0.0)), 4),
              "frame_index": int(msg.get("frame_index", 0)), "shape": list(img.shape),
              "range_min": float(msg["range_min"]), "range_max": float(msg["range_max"]),
              "azimuths": [round(float(a), 5) for a in az], "gain_db": _num(msg.get("gain_db"))}
    return pack(header, np.ascontiguousarray(img).tobytes())


def _num(v: Any) -> Any:
    """A JSON-safe number (or list of numbers, or short string) from a reading's value."""
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return round(f, 4) if math.isfinite(f) else None
    if isinstance(v, str):
        return v[:80]
    if isinstance(v, (list, tuple, np.ndarray)) and len(v) <= 16:
        return [_num(x) for x in v]
    return None


class LastErrors(logging.Handler):
    """The last warning or error line the log said about each device (a line starting with its
    name, as the devices and their links write them), for the endpoints table."""

    def __init__(self, names: list[str]) -> None:
        super().__init__(logging.WARNING)
        self.names = sorted(names, key=len, reverse=True)   # "depth_rtu" before "depth"
        self.lines: dict[str, str] = {}

    def emit(self, record: logging.LogRecord) -> None:
        try:
            msg = record.getMessage()
        except Exception:  # noqa: BLE001 - a bad log call is not ours to raise
            return
        for name in self.names:
            if msg.startswith(name) and msg[len(name):len(name) + 1] in (":", " "):
                self.lines[name] = msg[:200]
                return


class Hub:
    """Latest values from the bridge's topics, and the pages they go to."""

    def __init__(self, bridge: Any, camera: Any | None = None) -> None:
        self.bridge = bridge
        self.camera = camera
        self.pages: set[Any] = set()
        self.sonar: dict[str, Mapping[str, Any]] = {}
        self._sonar_sent: dict[str, int] = {}
        self._sonar_seq: dict[str, int] = {}
        self._bad_sonar: set[str] = set()
        self.readings: dict[str, dict[str, Any]] = {}
        self.commands: dict[int, dict[str, Any]] = {}
        self.faults: deque[dict[str, Any]] = deque(maxlen=20)
        self.contacts: deque[dict[str, Any]] = deque(maxlen=20)
        self.track: deque[list[float]] = deque(maxlen=1200)
        self.last_errors = LastErrors([])
        self._unsub: list[Callable[[], None]] = []
        self._page_unsub: list[Callable[[], None]] = []
        self._tick_task: asyncio.Task[None] | None = None
        self._track_handle: Any = None
        self.ticks = 0
        self._tick_error_logged = -1e9
        self.tick_seconds = 0.0   # [s] of the loop spent building and offering page updates
        #: more rows for the endpoints table: name -> status() (the console itself, the recorder)
        self.extra_status: dict[str, Callable[[], Mapping[str, Any]]] = {}
        self._scene: dict[str, Any] | None = None
        self.scene_updates = 0

    def scene(self) -> dict[str, Any]:
        """The scene part of a page's ``hello`` (:func:`scene_description`), kept up to date."""
        if self._scene is None:
            self._scene = scene_description(self.bridge)
        return self._scene

    # -- subscriptions ----------------------------------------------------------
    def start(self) -> None:
        self.last_errors = LastErrors([d.name for d in self.bridge.devices] + ["console"])
        logging.getLogger("hilsim").addHandler(self.last_errors)
        obs = self.bridge.observers
        self._unsub = [obs.subscribe("command/*", self._on_command), obs.subscribe("fault", self._on_event),
                       obs.subscribe("contact", self._on_event), obs.subscribe("world", self._on_world)]
        self._track_handle = self.bridge.every("console-track", 0.5, self._on_track, priority=90, tolerance=0.5)

    def _on_command(self, topic: str, msg: Mapping[str, Any]) -> None:
        i = msg.get("thruster")
        if isinstance(i, (int, np.integer)):
            self.commands[int(i)] = {"value": _num(msg.get("value")), "kind": str(msg.get("kind", ""))[:20],
                                     "source": str(msg.get("source", topic.split("/", 1)[-1]))[:40],
                                     "t": _num(msg.get("t"))}

    def _on_reading(self, topic: str, msg: Mapping[str, Any]) -> None:
        self.readings[topic.split("/", 1)[-1]] = dict(msg)

    def _on_event(self, topic: str, msg: Mapping[str, Any]) -> None:
        ev = {k: _num(v) for k, v in msg.items()}
        (self.faults if topic == "fault" else self.contacts).append(ev)

    def _on_world(self, topic: str, msg: Mapping[str, Any]) -> None:
        """An object moved: its outlines again (where the bridge's world has it now), and every
        open page gets the scene's objects in a ``scene`` message."""
        name = msg.get("object")
        if self._scene is None and not self.pages:
            return  # the first hello builds the scene as it is then
        scene = self.scene()
        if isinstance(name, str):
            new = {o["name"]: o for o in object_outlines(world_objects(self.bridge, name))}
            scene["objects"] = [new.get(o["name"], o) for o in scene["objects"]]
        self.scene_updates += 1
        data = json.dumps({"type": "scene", "t": _num(msg.get("t")), "object": str(name)[:80],
                           "objects": scene["objects"]}, separators=(",", ":"))
        for p in list(self.pages):
            p.offer("scene", data)

    def _on_sonar(self, topic: str, msg: Mapping[str, Any]) -> None:
        dev = topic.split("/", 1)[-1]
        self.sonar[dev] = msg
        self._sonar_seq[dev] = self._sonar_seq.get(dev, 0) + 1

    def _on_camera(self, topic: str, msg: Mapping[str, Any]) -> None:
        data = pack({"type": "camera", "mount": msg.get("mount", topic.split("/", 1)[-1]),
                     "t": _num(msg.get("t"))}, bytes(msg["jpeg"]))
        for p in list(self.pages):
            if p.show_camera:
                p.offer("camera", data)

    def _on_track(self, t: float) -> None:
        p = self.bridge.vehicle.state.position
        self.track.append([round(float(p[0]), 3), round(float(p[1]), 3), round(float(p[2]), 3)])

    # -- pages --------------------------------------------------------------------
    def add_page(self, page: Any) -> None:
        self.pages.add(page)
        if len(self.pages) == 1:
            obs = self.bridge.observers
            self._page_unsub = [obs.subscribe("sonar/*", self._on_sonar), obs.subscribe("camera/*", self._on_camera),
                                obs.subscribe("reading/*", self._on_reading)]
            self._tick_task = asyncio.ensure_future(self._tick_loop())

    def remove_page(self, page: Any) -> None:
        self.pages.discard(page)
        if self.camera is not None:
            self.camera.unwant(page)
        if not self.pages:
            for u in self._page_unsub:
                u()
            self._page_unsub = []
            self.sonar.clear()
            self.readings.clear()
            if self._tick_task is not None:
                self._tick_task.cancel()
                self._tick_task = None

    def show_camera(self, page: Any, show: bool) -> None:
        page.show_camera = show
        if self.camera is not None:
            if show:
                self.camera.want(page, 4.0)
            else:
                self.camera.unwant(page)

    async def _tick_loop(self) -> None:
        while self.pages:
            t0 = time.monotonic()
            try:
                self.tick()
            except Exception:  # noqa: BLE001 - a console bug must not stop the bridge
                if t0 - self._tick_error_logged >= 10.0:   # said at most every 10 s
                    self._tick_error_logged = t0
                    log.exception("console tick failed")
            used = time.monotonic() - t0
            self.tick_seconds += used
            await asyncio.sleep(max(0.0, TICK_S - used))

    def tick(self) -> None:
        """Offer the state and each new sonar frame to every page."""
        self.ticks += 1
        state = json.dumps(self.state(), separators=(",", ":"), allow_nan=False)
        for p in list(self.pages):
            p.offer("state", state)
        for dev, seq in list(self._sonar_seq.items()):
            if self._sonar_sent.get(dev) == seq or dev not in self.sonar:
                continue
            self._sonar_sent[dev] = seq
            try:
                data = encode_sonar(dev, self.sonar[dev])
            except (KeyError, ValueError, TypeError, IndexError) as exc:  # a frame we cannot draw
                if dev not in self._bad_sonar:
                    self._bad_sonar.add(dev)
                    log.warning("console: cannot show the frames of %s: %s", dev, exc)
                continue
            for p in list(self.pages):
                p.offer("sonar:" + dev, data)

    def state(self) -> dict[str, Any]:
        b = self.bridge
        s = b.vehicle.state
        pos, att, vel = (np.asarray(x, dtype=float) for x in (s.position, s.attitude, s.velocity))
        vehicle = {"t": round(float(s.time), 3), "position": [round(float(v), 3) for v in pos],
                   "rpy_deg": [round(math.degrees(float(a)), 2) for a in att],
                   "depth_m": round(float(pos[2]), 3), "altitude_m": self._altitude(pos),
                   "heading_deg": round(math.degrees(float(att[2])) % 360.0, 1),
                   "speed_m_s": round(float(np.linalg.norm(vel)), 3)}
        vehicle = {k: _num(v) for k, v in vehicle.items()}   # NaN/inf -> null
        thrusters = []
        ts = b.vehicle.thrusters
        if ts is not None:
            for i, name in enumerate(ts.names):
                tel = ts.telemetry(i)
                cmd = self.commands.get(i, {})
                thrusters.append({"name": name, "rpm": _num(round(float(tel.rpm), 1)),
                                  "max_rpm": _num(ts.thrusters[i].profile.max_rpm), "timed_out": bool(tel.timed_out),
                                  **cmd})
        devices = {}
        for d in b.devices:
            try:
                devices[d.name] = {k: _num(v) for k, v in d.status().items()}
            except Exception as exc:  # noqa: BLE001 - one device's status bug shows as text
                devices[d.name] = {"status_error": str(exc)[:80]}
        for name, fn in self.extra_status.items():
            try:
                devices[name] = {k: _num(v) for k, v in fn().items()}
            except Exception as exc:  # noqa: BLE001
                devices[name] = {"status_error": str(exc)[:80]}
        for name, line in self.last_errors.lines.items():
            if name in devices:
                devices[name]["last_error"] = line
        readings = {dev: {k: _num(v) for k, v in r.items() if k != "t" and _num(v) is not None}
                    for dev, r in self.readings.items()}
        try:
            faults = active_faults(b)
        except Exception as exc:  # noqa: BLE001
            faults = [{"target": "?", "fault": f"faults unavailable: {str(exc)[:60]}"}]
        return {"type": "state", "vehicle": vehicle, "thrusters": thrusters, "devices": devices,
                "readings": readings, "faults": faults, "fault_events": list(self.faults),
                "contacts": list(self.contacts), "pages": len(self.pages)}

    def _altitude(self, pos: np.ndarray) -> float | None:
        try:
            hits = self.bridge.world.cast(pos.reshape(1, 3), np.array([[0.0, 0.0, 1.0]]))
            a = float(hits.t[0])
        except Exception:  # noqa: BLE001 - no world, no altitude
            return None
        return round(a, 3) if math.isfinite(a) else None

    async def close(self) -> None:
        logging.getLogger("hilsim").removeHandler(self.last_errors)
        for u in self._unsub + self._page_unsub:
            u()
        self._unsub, self._page_unsub = [], []
        if self._track_handle is not None:
            self._track_handle.cancel()
        if self._tick_task is not None:
            self._tick_task.cancel()
            await asyncio.gather(self._tick_task, return_exceptions=True)
