"""``--record-mcap`` and ``--foxglove``: a live bridge recorded, read back with the independent
``mcap`` reader (messages decoded with protobuf from the schemas inside the file), and a client
speaking the Foxglove WebSocket protocol subscribed to the sonar channel.

One run of the default scenario in real time for a few seconds, with a DDF client reading the
stream, a CAN client commanding a thruster, and a fault injected and cleared.
"""

from __future__ import annotations

import asyncio
import base64
import json
import math
import struct
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

mcap_reader = pytest.importorskip("mcap.reader")
aiohttp = pytest.importorskip("aiohttp")
can = pytest.importorskip("can")
cantools = pytest.importorskip("cantools")

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory  # noqa: E402

from hilsim.protocols.vesc_can import dbc_path  # noqa: E402
from hilsim.resources import find_scenario  # noqa: E402
from hilsim.runtime.bridge import Bridge  # noqa: E402

RUN_S = 4.0
FILE_HDR, FRAME_HDR = 1024, 1024


def message_class(schema_name: str, schema_data: bytes):
    """A protobuf class built from the FileDescriptorSet a channel carries (not from the writer's code)."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(schema_data)
    pool = descriptor_pool.DescriptorPool()
    pending = list(fds.file)
    while pending:  # add each file after its dependencies
        for fd in list(pending):
            try:
                pool.Add(fd)
                pending.remove(fd)
            except TypeError:
                continue
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


async def ddf_client(host: str, port: int, frames: dict, stop: asyncio.Event) -> None:
    r, w = await asyncio.open_connection(host, port)
    try:
        hdr = await r.readexactly(FILE_HDR)
        nb, ns = struct.unpack_from("<i", hdr, 16)[0], struct.unpack_from("<i", hdr, 24)[0]
        while not stop.is_set():
            raw = await asyncio.wait_for(r.readexactly(FRAME_HDR + nb * ns), 5)
            number = struct.unpack_from("<i", raw, 0)[0]
            wire = np.frombuffer(raw[FRAME_HDR:], np.uint8).reshape(ns, nb)
            frames[number] = wire[:, ::-1].copy()  # the wire's beam 0 is starboard; the topics' is port
    except (asyncio.IncompleteReadError, asyncio.TimeoutError, ConnectionError):
        pass
    finally:
        w.close()


async def foxglove_client(url: str, topic: str, got: list, stop: asyncio.Event) -> None:
    """The Foxglove WebSocket protocol (foxglove.sdk.v1): serverInfo/advertise, subscribe, binary messageData."""
    async with aiohttp.ClientSession() as s, s.ws_connect(url, protocols=("foxglove.sdk.v1",)) as ws:
        channels: dict[int, dict] = {}
        subscribed = False
        while not stop.is_set():
            try:
                msg = await asyncio.wait_for(ws.receive(), 0.5)
            except asyncio.TimeoutError:
                continue
            if msg.type == aiohttp.WSMsgType.TEXT:
                m = json.loads(msg.data)
                if m.get("op") == "advertise":
                    for c in m["channels"]:
                        channels[c["id"]] = c
                    sonar = [c for c in channels.values() if c["topic"] == topic]
                    if sonar and not subscribed:
                        await ws.send_str(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": 7, "channelId": sonar[0]["id"]}]}))
                        subscribed = True
            elif msg.type == aiohttp.WSMsgType.BINARY and msg.data[0] == 0x01:
                sub_id, ts = struct.unpack_from("<IQ", msg.data, 1)
                c = next(c for c in channels.values() if c["topic"] == topic)
                got.append((sub_id, ts, c, bytes(msg.data[13:])))
            elif msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR):
                return


def can_commands(endpoint, stop: threading.Event) -> None:
    dbc = cantools.database.load_file(str(dbc_path()))
    m = dbc.get_message_by_name("VESC1_SET_DUTY")
    bus = can.Bus(interface="socketcand", channel=endpoint.extra["channel"], host=endpoint.extra["host"],
                  port=endpoint.extra["port"])
    try:
        time.sleep(0.3)
        while not stop.is_set():
            bus.send(can.Message(arbitration_id=m.frame_id, data=m.encode({"duty": 0.3}), is_extended_id=True))
            time.sleep(0.05)
    finally:
        bus.shutdown()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    out = tmp_path_factory.mktemp("mcap") / "run.mcap"
    result: dict = {"ddf": {}, "fox": []}

    async def go() -> None:
        b = Bridge(find_scenario(None), record_mcap=out, foxglove=0, status_interval=0)
        await b.start()
        stop, cstop = asyncio.Event(), threading.Event()
        try:
            ep = {(e.device, e.transport): e for e in b.endpoints}
            host, port = ep[("sonar_ddf", "tcp")].address.rsplit(":", 1)
            fox = ep[("foxglove", "tcp")].extra["url"]
            tasks = [asyncio.ensure_future(ddf_client(host, int(port), result["ddf"], stop)),
                     asyncio.ensure_future(foxglove_client(fox, "/sonar/sonar_ddf/polar", result["fox"], stop))]
            th = threading.Thread(target=can_commands, args=(ep[("vesc_can", "socketcand")], cstop))
            th.start()
            b.at(1.0, lambda t: b.faults.inject("depth", "dropout", {}))
            b.at(2.0, lambda t: b.faults.clear("depth", "dropout"))
            await b.run(RUN_S)
            cstop.set()
            stop.set()
            await asyncio.gather(*tasks)
            await asyncio.get_running_loop().run_in_executor(None, th.join)
            result["status"] = b.status()["devices"]
            result["counts"] = dict(b.attached.recorder.counts)
            result["pose_ticks"] = next(ev.stats.ticks for ev in b.scheduler.events if ev.name == "record-pose")
        finally:
            cstop.set()
            await b.close()

    asyncio.run(asyncio.wait_for(go(), 90))
    result["path"] = out
    return result


def read(path: Path):
    by_topic: dict[str, list] = defaultdict(list)
    with open(path, "rb") as f:
        reader = mcap_reader.make_reader(f)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            by_topic[channel.topic].append((schema, channel, message))
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    return by_topic, meta


def test_every_topic_is_in_the_file_with_its_schema(recorded):
    topics, meta = read(recorded["path"])
    expect = {"/tf": "foxglove.FrameTransforms", "/vehicle/pose": "foxglove.PoseInFrame",
              "/world": "foxglove.SceneUpdate", "/sonar/sonar_ddf/polar": "foxglove.RawImage",
              "/sonar/sonar_ddf/fan": "foxglove.RawImage", "/camera/camera": "foxglove.CompressedImage"}
    for topic, schema in expect.items():
        assert topics.get(topic), f"{topic} missing; topics: {sorted(topics)}"
        assert topics[topic][0][0].name == schema
    for topic in ("/vehicle/state", "/sonar/sonar_ddf/info", "/reading/depth", "/reading/imu",
                  "/command/vesc_can", "/faults"):
        assert topics.get(topic), f"{topic} missing; topics: {sorted(topics)}"
        assert topics[topic][0][1].message_encoding == "json"
    assert float(meta["hilsim"]["epoch_s"]) > 1e9


def test_counts_equal_what_the_devices_served(recorded):
    topics, _ = read(recorded["path"])
    st = recorded["status"]
    assert len(topics["/sonar/sonar_ddf/polar"]) == len(topics["/sonar/sonar_ddf/fan"])
    assert len(topics["/sonar/sonar_ddf/polar"]) == st["sonar_ddf"]["frames"] >= 10
    assert len(topics["/reading/depth"]) == st["depth"]["samples"] > 0
    assert len(topics["/reading/imu"]) == st["imu"]["samples"] > 0
    assert len(topics["/command/vesc_can"]) == st["vesc_can"]["commands"] > 10
    faults = [json.loads(m.data) for _, _, m in topics["/faults"]]
    assert [(f["target"], f["fault"], f["on"]) for f in faults] == [("depth", "dropout", True), ("depth", "dropout", False)]
    assert {k: len(v) for k, v in topics.items()} == recorded["counts"]


def test_log_times_are_simulation_time_and_monotonic(recorded):
    topics, meta = read(recorded["path"])
    epoch = float(meta["hilsim"]["epoch_s"])
    for topic, msgs in topics.items():
        times = [m.log_time for _, _, m in msgs]
        assert times == sorted(times), f"{topic}: log times go back"
        # t = log_time / 1e9 - epoch in doubles: near 1.7e9 s one ULP is 0.24 us, so the first
        # message (t = 0) may read back a fraction of a microsecond before the epoch
        off = [t / 1e9 - epoch for t in times]
        assert all(-1e-6 <= x <= RUN_S + 0.5 for x in off), (topic, min(off), max(off))
    poses = [json.loads(m.data)["t"] for _, _, m in topics["/vehicle/state"]]
    assert poses[-1] - poses[0] == pytest.approx(RUN_S, abs=0.2)
    # 50 Hz of simulated time; on a loaded machine the scheduler skips late grid points (counted)
    assert len(poses) == recorded["pose_ticks"] and 2 * RUN_S <= len(poses) <= 50 * RUN_S + 1


def test_sonar_images_decode_to_the_frames_a_ddf_client_received(recorded):
    topics, _ = read(recorded["path"])
    ddf = recorded["ddf"]
    assert len(ddf) >= 5
    polar = topics["/sonar/sonar_ddf/polar"]
    info = topics["/sonar/sonar_ddf/info"]
    schema = polar[0][0]
    RawImage = message_class(schema.name, schema.data)
    matched = 0
    for (_, _, m), (_, _, mi) in zip(polar, info):
        img = RawImage.FromString(m.data)
        index = json.loads(mi.data)["frame_index"]
        assert img.encoding == "mono8" and img.step == img.width
        a = np.frombuffer(img.data, np.uint8).reshape(img.height, img.width)
        if index in ddf:
            np.testing.assert_array_equal(a, ddf[index])
            matched += 1
    assert matched >= 0.8 * len(ddf), (matched, len(ddf))
    fan = RawImage.FromString(topics["/sonar/sonar_ddf/fan"][-1][2].data)
    f = np.frombuffer(fan.data, np.uint8).reshape(fan.height, fan.width)
    assert f.max() > 100 and (f == 0).mean() > 0.3    # a bright echo inside, black outside the fan


def test_the_camera_and_the_world_decode(recorded):
    from io import BytesIO

    from PIL import Image

    topics, _ = read(recorded["path"])
    schema = topics["/camera/camera"][0][0]
    CompressedImage = message_class(schema.name, schema.data)
    pic = CompressedImage.FromString(topics["/camera/camera"][-1][2].data)
    assert pic.format == "jpeg"
    with Image.open(BytesIO(pic.data)) as im:
        assert 100 < im.size[0] <= 240
    schema = topics["/world"][0][0]
    SceneUpdate = message_class(schema.name, schema.data)
    scene = SceneUpdate.FromString(topics["/world"][0][2].data)
    ids = {e.id for e in scene.entities}
    assert {"cuboid", "floor", "vehicle"} <= ids
    cuboid = next(e for e in scene.entities if e.id == "cuboid")
    pts = np.array([[p.x, p.y, p.z] for p in cuboid.triangles[0].points])
    assert pts.shape == (36, 3) and pts[:, 0].min() == pytest.approx(0.0, abs=1e-6)   # front face at x = 0
    schema = topics["/tf"][0][0]
    FrameTransforms = message_class(schema.name, schema.data)
    children = [[tf.child_frame_id for tf in FrameTransforms.FromString(m.data).transforms] for _, _, m in topics["/tf"]]
    assert sum("ned" in c for c in children) >= RUN_S - 1        # the fixed frames again each second (live viewers)
    assert all("base_link" in c for c in children[1:]) and {"sonar", "camera"} <= set(children[0])
    schema = topics["/vehicle/pose"][0][0]
    PoseInFrame = message_class(schema.name, schema.data)
    first = PoseInFrame.FromString(topics["/vehicle/pose"][0][2].data)
    assert first.frame_id == "ned" and first.pose.position.x == pytest.approx(-1.75, abs=0.05)


def test_a_foxglove_websocket_client_receives_sonar_frames(recorded):
    got = recorded["fox"]
    assert len(got) >= 5, "no sonar frames over the Foxglove WebSocket"
    sub_id, ts, channel, payload = got[-1]
    assert sub_id == 7 and channel["schemaName"] == "foxglove.RawImage" and channel["encoding"] == "protobuf"
    RawImage = message_class(channel["schemaName"], base64.b64decode(channel["schema"]))
    img = RawImage.FromString(payload)
    assert (img.width, img.height, img.encoding) == (96, 512, "mono8") and len(img.data) == 96 * 512
    assert ts / 1e9 > 1e9


def test_the_vehicle_fix_is_its_geodetic_position(recorded):
    """Where the scenario gives a geodetic origin, /vehicle/fix (LocationFix) carries the vehicle's
    position on the Earth: checked against a local flat-Earth conversion written here from the
    WGS84 radii of curvature (not hilsim's GNSS code)."""
    from hilsim.sim.scenario import load_scenario

    origin = load_scenario(find_scenario("water_tank")).origin
    assert origin is not None
    topics, _ = read(recorded["path"])
    schema = topics["/vehicle/fix"][0][0]
    assert schema.name == "foxglove.LocationFix"
    LocationFix = message_class(schema.name, schema.data)
    PoseInFrame = message_class(topics["/vehicle/pose"][0][0].name, topics["/vehicle/pose"][0][0].data)
    fix = LocationFix.FromString(topics["/vehicle/fix"][0][2].data)
    pose = PoseInFrame.FromString(topics["/vehicle/pose"][0][2].data).pose.position
    a, e2 = 6378137.0, 6.69437999014e-3
    lat0 = math.radians(origin.lat_deg)
    rm = a * (1 - e2) / (1 - e2 * math.sin(lat0) ** 2) ** 1.5
    rn = a / math.sqrt(1 - e2 * math.sin(lat0) ** 2)
    assert fix.latitude == pytest.approx(origin.lat_deg + math.degrees(pose.x / rm), abs=1e-7)
    assert fix.longitude == pytest.approx(origin.lon_deg + math.degrees(pose.y / (rn * math.cos(lat0))), abs=1e-7)
    assert fix.altitude == pytest.approx(origin.alt_m - pose.z, abs=1e-3)
    assert len(topics["/vehicle/fix"]) == len(topics["/vehicle/pose"])
