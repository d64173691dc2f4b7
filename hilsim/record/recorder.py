"""The run as Foxglove channels: to an MCAP file (``--record-mcap``), live over the Foxglove
WebSocket protocol (``--foxglove``), or both, through the foxglove-sdk.

One ``foxglove.Context`` holds the channels; the MCAP writer and the WebSocket server are
its sinks, so a message is built and logged once for both. Log time [ns] of every message
is the simulation time on the wire's clock: ``epoch + t`` (the UNIX time the devices stamp
for simulation time ``t``; ``hilsim run --epoch`` fixes it); the file's ``hilsim`` metadata
record holds the epoch, so ``t = log_time / 1e9 - epoch``.

Frames: ``world`` (z up, for viewers) -> ``ned`` (x north, y east, z down: the simulation's)
-> ``base_link`` (the body, x forward, y starboard, z down) -> one frame per sensor mount.

Topics (schema):

- ``/sonar/<device>/polar`` (RawImage mono8: n_samples rows of n_beams, beam 0 port, the
  samples the device served), ``/sonar/<device>/fan`` (RawImage mono8: the same frame as a
  fan, apex at the bottom), ``/sonar/<device>/info`` (JSON: frame index, range window,
  azimuths, gain)
- ``/camera/<mount>`` (CompressedImage jpeg), while the recording asks for pictures
- ``/tf`` (FrameTransforms), ``/vehicle/pose`` (PoseInFrame), ``/vehicle/state`` (JSON:
  velocity, attitude, thruster speeds) -- the ground truth at ``pose_rate_hz``
- ``/world`` (SceneUpdate: every object's triangles, and the hull), at the start and again, whole,
  whenever an object moves (a timeline ``move``), stamped with the move's time: a viewer seeking
  anywhere gets the scene as it was then from the last ``/world`` before
- ``/reading/<device>``, ``/command/<device>``, ``/faults``, ``/contacts`` (JSON)

- ``/vehicle/fix`` (LocationFix): the vehicle's true geodetic position, where the scenario gives
  a ``[world] origin`` (the same conversion as the GNSS receiver's, without its noise or outages).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from hilsim.record.convert import FanMapper, fan_key, jsonable, quaternion, time_ns

log = logging.getLogger("hilsim.record")


class Recorder:
    """Subscribes to the bridge's topics and logs them to Foxglove channels.

    mcap_path: write an MCAP file there; foxglove_port: serve live (0 picks a free port;
    None: no server); camera: a :class:`~hilsim.console.camera.CameraFeed` to ask for
    pictures while recording (``camera_rate_hz``)."""

    def __init__(self, bridge: Any, *, mcap_path: Path | str | None = None, foxglove_port: int | None = None,
                 camera: Any | None = None, pose_rate_hz: float = 50.0, camera_rate_hz: float = 2.0,
                 allow_overwrite: bool = True) -> None:
        import foxglove

        self.bridge = bridge
        self.mcap_path = Path(mcap_path) if mcap_path is not None else None
        self.foxglove_port = foxglove_port
        self.camera = camera
        self.pose_rate_hz = float(pose_rate_hz)
        self.camera_rate_hz = float(camera_rate_hz)
        self.allow_overwrite = allow_overwrite
        self.ctx = foxglove.Context()
        self.writer: Any = None
        self.server: Any = None
        self.channels: dict[str, Any] = {}
        self.counts: dict[str, int] = {}
        self._fans: dict[str, tuple[tuple[Any, ...], FanMapper]] = {}
        self._unsub: list[Callable[[], None]] = []
        self._handles: list[Any] = []
        self._epoch = 0.0
        self._open = False
        self._scene: Any = None
        self._entities: list[tuple[str, Any]] = []   # the scene's entities by id (SceneUpdate hides its fields)
        self._static_next = 1.0   # [s] simulation time the fixed frames are logged again
        self._scene_next = 10.0   # ... and the scene, for live viewers
        self._pending: list[tuple[Callable[[str, Mapping[str, Any]], None], str, Mapping[str, Any]]] = []
        self._closed = False

    # -- lifecycle ------------------------------------------------------------------
    def subscribe(self) -> None:
        """Listen to the bridge's topics now (before the devices start: a reading served at start
        counts); messages wait in memory until :meth:`start` opens the sinks."""
        obs = self.bridge.observers
        for pattern, fn in (("sonar/*", self._on_sonar), ("reading/*", self._on_json), ("command/*", self._on_json),
                            ("fault", self._on_json), ("contact", self._on_json), ("camera/*", self._on_camera),
                            ("world", self._on_world)):
            self._unsub.append(obs.subscribe(pattern, self._early(fn)))

    def _early(self, fn: Callable[[str, Mapping[str, Any]], None]) -> Callable[[str, Mapping[str, Any]], None]:
        def listener(topic: str, msg: Mapping[str, Any]) -> None:
            if self._open:
                fn(topic, msg)
            elif len(self._pending) < 10000:
                self._pending.append((fn, topic, msg))
        return listener

    def start(self) -> list[Any]:
        """Open the sinks (the epoch is final now), log the static scene and what waited; returns
        the endpoints (the file, the server)."""
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        from hilsim.devices.base import Endpoint

        if not self._unsub:
            self.subscribe()
        self._epoch = float(self.bridge.wall_time(0.0))
        self._make_channels()
        endpoints: list[Any] = []
        if self.mcap_path is not None:
            self.mcap_path.parent.mkdir(parents=True, exist_ok=True)
            opts = MCAPWriteOptions(compression=MCAPCompression.Lz4, compression_threads=0)
            self.writer = foxglove.open_mcap(self.mcap_path, allow_overwrite=self.allow_overwrite,
                                             context=self.ctx, writer_options=opts)
            endpoints.append(Endpoint("mcap", "mcap", "file", str(self.mcap_path)))
            self.writer.write_metadata("hilsim", {"scenario": str(self.bridge.scenario.name),
                                                  "epoch_s": repr(self._epoch), "seed": str(self.bridge.seed),
                                                  "log_time": "epoch_s + simulation time"})
        if self.foxglove_port is not None:
            host = getattr(self.bridge, "bind", "127.0.0.1")
            name = f"hilsim {self.bridge.scenario.name}"
            try:
                self.server = foxglove.start_server(name=name, host=host, port=int(self.foxglove_port),
                                                    context=self.ctx)
            except RuntimeError as exc:  # the port is taken (another bridge): a free one, said loudly
                if int(self.foxglove_port) == 0:
                    raise
                log.warning("Foxglove port %s is taken (%s); serving on a free port instead", self.foxglove_port, exc)
                self.server = foxglove.start_server(name=name, host=host, port=0, context=self.ctx)
            endpoints.append(Endpoint("foxglove", "foxglove-ws", "tcp", f"{host}:{self.server.port}",
                                      {"url": f"ws://{host}:{self.server.port}"}))
            log.info("Foxglove WebSocket server on ws://%s:%d", host, self.server.port)
        self._log_static(0.0)
        self._open = True
        for fn, topic, msg in self._pending:
            fn(topic, msg)
        self._pending.clear()
        self._handles.append(self.bridge.every("record-pose", 1.0 / self.pose_rate_hz, self._on_pose,
                                               priority=90, tolerance=1.0))
        if self.camera is not None and self.camera.mounts and self.writer is not None:
            self.camera.want(self, self.camera_rate_hz)
        return endpoints

    def _make_channels(self) -> None:
        import foxglove
        from foxglove import channels as ch

        c = self.ctx
        self.channels["/tf"] = ch.FrameTransformsChannel("/tf", context=c)
        self.channels["/vehicle/pose"] = ch.PoseInFrameChannel("/vehicle/pose", context=c)
        self.channels["/vehicle/state"] = foxglove.Channel("/vehicle/state", context=c)
        self.channels["/world"] = ch.SceneUpdateChannel("/world", context=c)
        if getattr(self.bridge.scenario, "origin", None) is not None:
            self.channels["/vehicle/fix"] = ch.LocationFixChannel("/vehicle/fix", context=c)
        for s in self.bridge.scenario.sensors:
            if s.kind == "camera":
                self.channels[f"/camera/{s.name}"] = ch.CompressedImageChannel(f"/camera/{s.name}", context=c)

    def _channel(self, topic: str, kind: str = "json") -> Any:
        chan = self.channels.get(topic)
        if chan is None:
            import foxglove
            from foxglove import channels as ch

            if kind == "raw":
                chan = ch.RawImageChannel(topic, context=self.ctx)
            else:
                chan = foxglove.Channel(topic, context=self.ctx)
            self.channels[topic] = chan
        return chan

    def _log(self, topic: str, chan: Any, msg: Any, t: float) -> None:
        chan.log(msg, log_time=time_ns(self._epoch, t))
        self.counts[topic] = self.counts.get(topic, 0) + 1

    # -- the scene --------------------------------------------------------------------
    def _tf(self, parent: str, child: str, position: Any, rotation: Any, stamp: Any) -> Any:
        from foxglove.messages import FrameTransform, Quaternion, Vector3

        x, y, z, w = quaternion(rotation)
        p = [float(v) for v in position]
        return FrameTransform(timestamp=stamp, parent_frame_id=parent, child_frame_id=child,
                              translation=Vector3(x=p[0], y=p[1], z=p[2]), rotation=Quaternion(x=x, y=y, z=z, w=w))

    def _stamp(self, t: float) -> Any:
        from foxglove.messages import Timestamp

        ns = time_ns(self._epoch, t)
        return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)

    def _object_entity(self, o: Any, stamp: Any) -> Any:
        """A world object (its triangles where they are now, in ``ned``) as a SceneEntity."""
        from foxglove.messages import Color, Point3, Pose, Quaternion, SceneEntity, TriangleListPrimitive, Vector3

        identity = Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
        tri = np.asarray(o.mesh.triangles, dtype=float).reshape(-1, 3)[: 3 * 200_000]
        r, g, b = (float(v) for v in o.material.color[:3])
        return SceneEntity(timestamp=stamp, frame_id="ned", id=o.name, triangles=[TriangleListPrimitive(
            pose=identity, points=[Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in tri],
            color=Color(r=r, g=g, b=b, a=0.9))])

    def _log_static(self, t: float) -> None:
        from foxglove.messages import (Color, CubePrimitive, FrameTransforms, Pose, Quaternion, SceneEntity,
                                       SceneUpdate, Vector3)

        stamp = self._stamp(t)
        self._log("/tf", self.channels["/tf"], FrameTransforms(transforms=self._static_tfs(stamp)), t)
        from hilsim.console.scene import hull_box, world_objects

        objects = world_objects(self.bridge)
        entities = [self._object_entity(o, stamp) for o in objects]

        ts = self.bridge.vehicle.thrusters
        hull = hull_box([list(map(float, th.position)) for th in ts.thrusters] if ts is not None else None)
        lo, hi = np.asarray(hull["min"]), np.asarray(hull["max"])
        c, size = (lo + hi) / 2, hi - lo
        entities.append(SceneEntity(timestamp=stamp, frame_id="base_link", id="vehicle", frame_locked=True, cubes=[
            CubePrimitive(pose=Pose(position=Vector3(x=float(c[0]), y=float(c[1]), z=float(c[2])),
                                    orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                          size=Vector3(x=float(size[0]), y=float(size[1]), z=float(size[2])),
                          color=Color(r=0.95, g=0.72, b=0.29, a=1.0))]))
        self._entities = [(o.name, e) for o, e in zip(objects, entities)] + [
            ("vehicle", entities[-1])]
        self._scene = SceneUpdate(entities=entities)
        self._log("/world", self.channels["/world"], self._scene, t)

    def _on_world(self, topic: str, msg: Mapping[str, Any]) -> None:
        """An object moved: the whole scene again (a viewer seeking after it reads only the last
        ``/world`` before), the moved object's parts rebuilt from the bridge's world."""
        from foxglove.messages import SceneUpdate

        from hilsim.console.scene import world_objects

        name = msg.get("object")
        if self._scene is None or not isinstance(name, str):
            return
        t = float(msg.get("t", self.bridge.now()))
        stamp = self._stamp(t)
        moved = {o.name: o for o in world_objects(self.bridge, name)}
        self._entities = [(i, self._object_entity(moved[i], stamp) if i in moved else e) for i, e in self._entities]
        self._scene = SceneUpdate(entities=[e for _, e in self._entities])
        self._log("/world", self.channels["/world"], self._scene, t)

    def _static_tfs(self, stamp: Any) -> list[Any]:
        """world -> ned (z up for viewers) and base_link -> each sensor mount."""
        tfs = [self._tf("world", "ned", (0, 0, 0), np.diag([1.0, -1.0, -1.0]), stamp)]
        for s in self.bridge.scenario.sensors:
            tfs.append(self._tf("base_link", s.name, s.mount.position, s.mount.rotation, stamp))
        return tfs

    # -- listeners (called in the publishing device's call: no blocking, no await) -------
    def _on_pose(self, t: float) -> None:
        from foxglove.messages import FrameTransforms, Pose, PoseInFrame, Quaternion, Vector3

        s = self.bridge.vehicle.state
        t = float(s.time)
        pose = s.pose
        stamp = self._stamp(t)
        tfs = [self._tf("ned", "base_link", pose.position, pose.rotation, stamp)]
        if t >= self._static_next:  # again once a second: a viewer that joins live gets the fixed frames too
            self._static_next = t + 1.0
            tfs = self._static_tfs(stamp) + tfs
            if self.server is not None and t >= self._scene_next and self._scene is not None:
                self._scene_next = t + 10.0
                self._log("/world", self.channels["/world"], self._scene, t)
        self._log("/tf", self.channels["/tf"], FrameTransforms(transforms=tfs), t)
        x, y, z, w = quaternion(pose.rotation)
        p = [float(v) for v in pose.position]
        self._log("/vehicle/pose", self.channels["/vehicle/pose"], PoseInFrame(
            timestamp=stamp, frame_id="ned", pose=Pose(position=Vector3(x=p[0], y=p[1], z=p[2]),
                                                        orientation=Quaternion(x=x, y=y, z=z, w=w))), t)
        state: dict[str, Any] = {"t": t, "position_m": p, "rpy_rad": jsonable(s.attitude),
                                 "velocity_m_s": jsonable(s.velocity), "angular_velocity_rad_s": jsonable(s.angular_velocity)}
        ts = self.bridge.vehicle.thrusters
        if ts is not None:
            state["thruster_rpm"] = [round(float(ts.telemetry(i).rpm), 1) for i in range(len(ts))]
            state["thruster_names"] = list(ts.names)
        self._log("/vehicle/state", self.channels["/vehicle/state"], state, t)
        fix = self.channels.get("/vehicle/fix")
        if fix is not None:
            from foxglove.messages import LocationFix

            from hilsim.sim.gnss import ned_to_geodetic

            lat, lon, alt = (float(v) for v in ned_to_geodetic(np.asarray(p), self.bridge.scenario.origin)[0])
            self._log("/vehicle/fix", fix, LocationFix(timestamp=stamp, frame_id="base_link", latitude=lat,
                                                       longitude=lon, altitude=alt), t)

    def _on_sonar(self, topic: str, msg: Mapping[str, Any]) -> None:
        from foxglove.messages import RawImage

        dev = topic.split("/", 1)[1]
        t = float(msg.get("t", self.bridge.now()))
        img = np.ascontiguousarray(np.asarray(msg["image"], dtype=np.uint8))
        stamp = self._stamp(t)
        ns, nb = img.shape
        base = f"/sonar/{dev}"
        self._log(base + "/polar", self._channel(base + "/polar", "raw"), RawImage(
            timestamp=stamp, frame_id=self._sensor_frame(dev), width=nb, height=ns, encoding="mono8", step=nb,
            data=img.tobytes()), t)
        key = fan_key(msg)
        cached = self._fans.get(dev)
        if cached is None or cached[0] != key:
            cached = self._fans[dev] = (key, FanMapper(ns, np.asarray(msg["azimuths"]), float(msg["range_min"]),
                                                       float(msg["range_max"])))
        fan = cached[1](img)
        self._log(base + "/fan", self._channel(base + "/fan", "raw"), RawImage(
            timestamp=stamp, frame_id=self._sensor_frame(dev), width=fan.shape[1], height=fan.shape[0],
            encoding="mono8", step=fan.shape[1], data=fan.tobytes()), t)
        info = {k: jsonable(v) for k, v in msg.items() if k != "image"}
        self._log(base + "/info", self._channel(base + "/info"), info, t)

    def _sensor_frame(self, device: str) -> str:
        d = next((d for d in self.bridge.devices if d.name == device), None)
        sensor = getattr(d, "options", {}).get("sensor") if d is not None else None
        return str(sensor) if isinstance(sensor, str) else "base_link"

    def _on_camera(self, topic: str, msg: Mapping[str, Any]) -> None:
        from foxglove.messages import CompressedImage

        mount = str(msg.get("mount", topic.split("/", 1)[1]))
        t = float(msg.get("t", 0.0))
        self._log(f"/camera/{mount}", self._channel(f"/camera/{mount}"), CompressedImage(
            timestamp=self._stamp(t), frame_id=mount, data=bytes(msg["jpeg"]), format="jpeg"), t)

    def _on_json(self, topic: str, msg: Mapping[str, Any]) -> None:
        name = {"fault": "/faults", "contact": "/contacts"}.get(topic, "/" + topic)
        t = float(msg.get("t", self.bridge.now()))
        self._log(name, self._channel(name), jsonable(dict(msg)), t)

    def status(self) -> dict[str, Any]:
        """Counters for the console's endpoints table: messages logged, topics, the file's size."""
        out: dict[str, Any] = {"sent": sum(self.counts.values()), "topics": len(self.counts)}
        if self.mcap_path is not None and self.mcap_path.exists():
            out["mcap_bytes"] = self.mcap_path.stat().st_size
        return out

    # -- shutdown ------------------------------------------------------------------------
    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for u in self._unsub:
            u()
        for h in self._handles:
            h.cancel()
        if self.camera is not None:
            self.camera.unwant(self)
        if self.writer is not None:
            self.writer.close()
            log.info("MCAP recording %s: %d messages on %d topics", self.mcap_path, sum(self.counts.values()),
                     len(self.counts))
        if self.server is not None:
            self.server.stop()
