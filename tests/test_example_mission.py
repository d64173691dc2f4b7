"""End to end: the reference control stack (examples/) against a real ``hilsim run --time-scale 4``.

``examples/demo.py`` starts the bridge, runs ``examples/mission.py`` (dive to
1.8 m, turn to 20 deg and back to 0, approach the cuboid until its sonar
shadow edge is 1.25 m away, hold) and stops the bridge with SIGTERM. This
test checks the mission's own summary, and watches the run from outside
with its own clients: a DDF stream client (frame headers: the simulator's
depth and heading; images: its own edge measurement) and a Modbus client on
the Keller depth sensor. The geometry comes from the scenario and profile
TOML files: the sonar 0.4 m ahead of and 0.3 m below the body origin, tilted
45 deg down with a +-7 deg aperture; the floor at 3.0 m; the cuboid's front
face at x = 0, 0.30 m tall. No hilsim import: the stack and this test see
the bridge only through its wire protocols.
"""

from __future__ import annotations

import csv
import importlib
import json
import math
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.alone  # missions load both cores: make test runs these after the others, one at a time

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
SCENARIO = ROOT / "scenarios" / "water_tank" / "scenario.toml"
SONAR_PROFILE = ROOT / "devices" / "sonars" / "didson_hf.toml"
GNSS_PROFILE = ROOT / "devices" / "sensors" / "gnss_single.toml"

TIME_SCALE = 4
DEPTH = 1.8          # [m] the mission's defaults, passed explicitly
HOLD_RANGE = 1.25    # [m]
HOLD_TIME = 15.0     # [s]
RHO = 998.0


def _geometry() -> dict[str, float]:
    sc = tomllib.loads(SCENARIO.read_text())
    objects = {o["name"]: o for o in sc["objects"]}
    floor, cuboid = objects["floor"], objects["cuboid"]
    sonar = next(s for s in sc["sensors"] if s["kind"] == "sonar")
    dvl = next(s for s in sc["sensors"] if s["kind"] == "dvl")
    gnss = next(s for s in sc["sensors"] if s["kind"] == "gnss")
    prof = tomllib.loads(SONAR_PROFILE.read_text())
    gnss_prof = tomllib.loads(GNSS_PROFILE.read_text())["sensor"]
    assert gnss["profile"] == "gnss_single"
    return {
        "floor_top": floor["position_m"][2] - floor["size_m"][2] / 2,          # 3.0
        "front_face_x": cuboid["position_m"][0] - cuboid["size_m"][0] / 2,     # 0.0
        "cuboid_height": cuboid["size_m"][2],                                  # 0.30
        "mount_x": sonar["position_m"][0], "mount_z": sonar["position_m"][2],  # 0.4, 0.3
        "tilt": -sonar["orientation_deg"][1],                                  # 45
        "half_elevation": prof["beams"]["elevation_limits"]["value"][1],       # 7
        "half_azimuth": prof["beams"]["azimuth_limits"]["value"][1],           # 14.5
        "x_A": sc["positions"]["A"]["position_m"][0], "x_C": sc["positions"]["C"]["position_m"][0],
        "dvl_z": dvl["position_m"][2],                                          # 0.35 below the body origin
        "gnss_x": gnss["position_m"][0], "mast": -gnss["position_m"][2],        # -0.3, 0.6
        "origin_lat": sc["world"]["origin"]["lat_deg"], "origin_lon": sc["world"]["origin"]["lon_deg"],
        "time_to_fix": gnss_prof["time_to_fix"]["value"], "gnss_noise": gnss_prof["horizontal_noise"]["value"],
    }


GEO = _geometry()


def _first_band(profile: np.ndarray, thr: float) -> tuple[int, int] | None:
    """First and last sample of the first run of ``profile >= thr`` (gaps of <= 4 samples bridged)."""
    idx = np.nonzero(profile >= thr)[0]
    if len(idx) == 0:
        return None
    cut = np.nonzero(np.diff(idx) > 5)[0]
    return int(idx[0]), int(idx[cut[0]] if len(cut) else idx[-1])


def edges(img: np.ndarray, ranges: np.ndarray) -> dict[str, float]:
    """This test's own look at one frame (n_samples, n_beams): per beam, the first echo band above
    80 % of the brightest outer-beam level; medians over the centre beams (|az| <= 2 deg) and over
    the outer beams (|az| >= 12.5 deg, ranges scaled by cos az to the centre line)."""
    n_beams = img.shape[1]
    az = np.linspace(GEO["half_azimuth"], -GEO["half_azimuth"], n_beams)
    outer = np.nonzero(np.abs(az) >= 12.5)[0]
    centre = np.nonzero(np.abs(az) <= 2.0)[0]
    smooth = np.apply_along_axis(lambda c: np.convolve(c, np.ones(5) / 5, mode="same"), 0, img.astype(float))
    thr = 0.8 * float(smooth[:, outer].max())
    out: dict[str, list[float]] = {"near": [], "far": [], "floor_far": []}
    for b in centre:
        band = _first_band(smooth[:, b], thr)
        if band:
            out["near"].append(ranges[band[0]])
            out["far"].append(ranges[band[1]])
    for b in outer:
        band = _first_band(smooth[:, b], thr)
        if band:
            out["floor_far"].append(ranges[band[1]] * math.cos(math.radians(az[b])))
    return {k: float(np.median(v)) if v else math.nan for k, v in out.items()}


class Observer(threading.Thread):
    """Connects to the bridge once the endpoints file exists; per DDF frame records its time [s since
    the epoch], the header's depth and heading, the Keller depth read over Modbus right then, and
    ``edges`` of the image. Stops at the end of the stream (the bridge shutting down)."""

    def __init__(self, endpoints: Path) -> None:
        super().__init__(daemon=True)
        self.endpoints = endpoints
        self.rows: list[dict[str, float]] = []
        self.error: str | None = None
        self.stop = False

    def run(self) -> None:
        from pymodbus.client import ModbusTcpClient

        try:
            deadline = time.monotonic() + 90
            while not self.endpoints.exists():
                if self.stop or time.monotonic() > deadline:
                    return
                time.sleep(0.05)
            ep = json.loads(self.endpoints.read_text())
            addr = {e["protocol"]: e["address"] for e in ep if e["transport"] == "tcp"}
            host, port = addr["ddf-stream"].rsplit(":", 1)
            mb_host, mb_port = addr["modbus-keller"].rsplit(":", 1)
            keller = ModbusTcpClient(mb_host, port=int(mb_port), timeout=2)
            assert keller.connect()
            with socket.create_connection((host, int(port)), timeout=30) as s:
                fh = self._read(s, 1024)
                n_beams, n_samples = struct.unpack_from("<i", fh, 16)[0], struct.unpack_from("<i", fh, 24)[0]
                while not self.stop:
                    hdr = self._read(s, 1024)
                    data = self._read(s, n_beams * n_samples)
                    if hdr is None or data is None:
                        return
                    start_code, length_code = struct.unpack_from("<ii", hdr, 52)
                    start, length = start_code * 0.419, [1.25, 2.5, 5.0, 10.0][length_code]  # HF extended windows
                    ranges = start + (np.arange(n_samples) + 0.5) * length / n_samples
                    rr = keller.read_holding_registers(0x0002, count=2, device_id=1)
                    p1 = math.nan if rr.isError() else struct.unpack(">f", struct.pack(">HH", *rr.registers))[0]
                    row = {"t": struct.unpack_from("<Q", hdr, 4)[0] / 1e6,
                           "hdr_depth": struct.unpack_from("<f", hdr, 128)[0],
                           "hdr_heading": struct.unpack_from("<f", hdr, 152)[0],
                           "modbus_depth": (p1 * 1e5 - 101325.0) / (RHO * 9.80665)}
                    row.update(edges(np.frombuffer(data, np.uint8).reshape(n_samples, n_beams), ranges))
                    self.rows.append(row)
            keller.close()
        except Exception as e:  # noqa: BLE001 - reported by the tests
            self.error = repr(e)

    @staticmethod
    def _read(s: socket.socket, n: int) -> bytes | None:
        buf = bytearray()
        while len(buf) < n:
            try:
                chunk = s.recv(n - len(buf))
            except OSError:
                return None
            if not chunk:
                return None
            buf += chunk
        return bytes(buf)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> dict:
    tmp = tmp_path_factory.mktemp("mission")
    out, run_dir = tmp / "out", tmp / "run"
    obs = Observer(run_dir / "endpoints.json")
    obs.start()
    t_start = time.monotonic()
    with open(tmp / "demo.log", "w") as log:
        proc = subprocess.Popen(
            [sys.executable, str(EXAMPLES / "demo.py"), "--time-scale", str(TIME_SCALE), "--out", str(out),
             "--run-dir", str(run_dir), "--", "--depth", str(DEPTH), "--hold-range", str(HOLD_RANGE),
             "--hold-time", str(HOLD_TIME), "--rho", str(RHO), "--surface"],
            stdout=log, stderr=subprocess.STDOUT, cwd=tmp)
        try:
            proc.wait(timeout=180)
        except subprocess.TimeoutExpired:  # SIGTERM: the demo stops the mission, then the bridge
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    wall = time.monotonic() - t_start
    obs.stop = True
    obs.join(timeout=10)
    summary_path = out / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    bridge_summary_path = run_dir / "summary.json"  # the bridge's own, beside its endpoints file
    bridge_summary = json.loads(bridge_summary_path.read_text()) if bridge_summary_path.exists() else {}
    return {"rc": proc.returncode, "out": out, "log": (tmp / "demo.log").read_text(errors="replace"),
            "bridge_summary": bridge_summary,
            "bridge_log": (out / "bridge.log").read_text(errors="replace") if (out / "bridge.log").exists() else "",
            "summary": summary, "obs": obs, "wall": wall}


def _diag(run: dict) -> str:
    """The bridge's own view of a bad run: its timing report and any client it throttled (a starved
    host makes the bridge late; a throttled CAN client's commands arrive late and the ESC watchdog
    stops the thrusters)."""
    lines = [ln for ln in run["bridge_log"].splitlines()
             if ln.startswith(("physics:", "status:")) or "more slowly" in ln or "late ticks" in ln][-6:]
    return "\nbridge: " + "\n".join(lines)


def _phase(summary: dict, name: str) -> dict:
    return next(p for p in summary["phases"] if p["name"] == name)


def _hold_rows(run: dict) -> list[dict]:
    """The observer's frames pinged during the mission's hold phase (the summary's times are seconds from
    its t0, a frame time)."""
    s = run["summary"]
    hold = _phase(s, "hold")
    t0 = s["timing"]["t0_unix"]
    return [r for r in run["obs"].rows if t0 + hold["start_s"] + 1.0 <= r["t"] <= t0 + hold["end_s"]]


def test_the_demo_completes_the_mission_and_stops_the_bridge_cleanly(run):
    assert run["rc"] == 0, run["log"][-3000:]
    assert "bridge stopped cleanly (exit 0)" in run["log"]
    assert "SIGTERM: shutting down" in run["bridge_log"] and "bridge stopped at" in run["bridge_log"]
    assert "Traceback" not in run["log"] + run["bridge_log"]
    s = run["summary"]
    assert s["success"] and s["failure"] is None
    assert [p["name"] for p in s["phases"]] == ["dive", "turn_20", "turn_0", "approach", "hold", "surface"]
    assert [p["outcome"] for p in s["phases"]] == ["settled"] * 4 + ["completed", "gnss fix"]
    assert s["timing"]["time_scale_estimate"] == pytest.approx(TIME_SCALE, rel=0.1)
    for name in ("summary.json", "mission_log.csv", "sonar_log.csv", "depth.png", "heading.png", "range.png",
                 "thrusters.png", "overview.png"):
        assert name in s["files"] and (run["out"] / name).stat().st_size > 0, name
        if name.endswith(".png"):
            assert (run["out"] / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the live status: one line per second of simulation time (a stalled, starved machine loses a few)
    status = [ln for ln in run["log"].splitlines() if ln.startswith("t=")]
    assert 0.8 * s["duration_s"] - 2 <= len(status) <= s["duration_s"] + 2, len(status)
    assert run["obs"].error is None and len(run["obs"].rows) > 20
    # no fault injected: the stack's ESC health check flags nothing and every depth reading was valid
    assert s["thrusters"]["faults"] == [] and s["depth"]["invalid_readings"] == 0
    print(f"\nend to end: {run['wall']:.1f} s wall for {s['duration_s']} s of simulation, "
          f"{len(run['obs'].rows)} frames seen by the observer")


def test_the_vehicle_reaches_and_holds_the_commanded_depth(run):
    s = run["summary"]
    after = s["depth"]["after_dive"]
    assert after["n"] > 100 and abs(after["mean"]) < 0.01 and after["rms"] < 0.02 and after["max_abs"] < 0.05, \
        str(after) + _diag(run)
    assert s["depth"]["dive_time_s"] < 40
    # independently: the Keller over Modbus and the simulator's own depth in the frame headers
    t0 = s["timing"]["t0_unix"]
    rows = [r for r in run["obs"].rows if t0 + _phase(s, "dive")["end_s"] + 1.0 <= r["t"] <= t0 + _phase(s, "hold")["end_s"]]
    assert len(rows) > 10
    for key in ("modbus_depth", "hdr_depth"):
        d = np.array([r[key] for r in rows])
        assert np.all(np.abs(d - DEPTH) < 0.05), f"{key} {d.min()} {d.max()}" + _diag(run)
        assert abs(d.mean() - DEPTH) < 0.01, key


def test_the_heading_settles_at_each_commanded_heading(run):
    s = run["summary"]
    for turn, to in zip(s["heading"]["turns"], (20.0, 0.0)):
        assert turn["to_deg"] == to
        assert turn["settle_s"] < 30 and abs(turn["final_error_deg"]) < 2.0 and turn["overshoot_deg"] < 5.0
    hold = s["heading"]["hold"]
    assert hold["rms"] < 1.0 and hold["max_abs"] < 3.0, str(hold) + _diag(run)
    # the simulator's true heading (frame headers) in the hold: 0 within the IMU's bias (about 0.5 deg)
    hdg = np.array([(r["hdr_heading"] + 180.0) % 360.0 - 180.0 for r in _hold_rows(run)])
    assert len(hdg) >= 3 and abs(np.median(hdg)) < 1.5 and np.all(np.abs(hdg) < 3.0), hdg
    # and 20 deg was reached: some frame during turn_20 shows a heading near 20
    t0, turn = s["timing"]["t0_unix"], _phase(s, "turn_20")
    seen = [r["hdr_heading"] for r in run["obs"].rows if t0 + turn["start_s"] <= r["t"] <= t0 + turn["end_s"]]
    assert seen and min(abs(h - 20.0) for h in seen) < 2.5


def test_the_sonar_sees_the_target_and_the_hold_range_is_the_requested_one(run):
    s = run["summary"]["sonar"]
    assert s["detections"] > 10 and s["frames_lost"] == 0
    assert s["detection_after_approach_start_s"] is not None and s["detection_after_approach_start_s"] < 30
    hold = s["hold"]
    assert hold["frames"] >= 3 and hold["detections"] >= 0.8 * hold["frames"]
    assert abs(hold["range_m"]["mean"] - HOLD_RANGE) < 0.04 and hold["range_m"]["std"] < 0.02, \
        str(hold["range_m"]) + _diag(run)
    # the observer's own measurement of the shadow edge in the hold
    far = np.array([r["far"] for r in _hold_rows(run)])
    assert np.all(np.isfinite(far)) and abs(np.median(far) - HOLD_RANGE) < 0.05, str(far) + _diag(run)


def test_the_hold_echo_is_the_cuboids_front_face_where_the_geometry_puts_it(run):
    """With the sonar h = floor - (depth + 0.3) above the floor (the frame header's depth, the ping's):
    the floor band's far edge is at h / sin(45 - 7); the shadow edge is the slant range to the front
    face's foot, sqrt(d^2 + h^2); the nearest return is the top ray (38 deg down) on the front face,
    d / cos(38): both give the same horizontal distance d, and the face's hit lies within its 0.30 m."""
    g = GEO
    rows = _hold_rows(run)
    assert len(rows) >= 3
    lo = math.radians(g["tilt"] - g["half_elevation"])
    for r in rows:
        h = g["floor_top"] - (r["hdr_depth"] + g["mount_z"])  # the depth at the ping
        assert r["floor_far"] == pytest.approx(h / math.sin(lo), abs=0.04), "floor band vs depth and tilt"
        d_foot = math.sqrt(r["far"] ** 2 - h ** 2)
        d_top = r["near"] * math.cos(lo)
        assert d_foot == pytest.approx(d_top, abs=0.05), (r["near"], r["far"], h)
        hit_height = h - r["near"] * math.sin(lo)
        assert -0.03 < hit_height < g["cuboid_height"] + 0.03
        # the vehicle's position this implies lies between positions A and C of the scenario
        x = g["front_face_x"] - (g["mount_x"] + d_foot)
        assert g["x_A"] < x < g["x_C"], x


def _mission_log(run: dict) -> dict[str, np.ndarray]:
    with open(run["out"] / "mission_log.csv") as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([float(r[k]) if r[k] not in ("", "nan") else math.nan for r in rows]) for k in rows[0]}


def test_the_dvl_flies_the_approach_and_the_hold(run):
    """The stack's surge speed and floor come from the DVL (Water Linked JSON API): its reports have bottom
    lock, its altitude in the hold is the floor's height below the DVL (floor - depth - 0.35 m, from the
    scenario), and its surge velocity there is zero."""
    s = run["summary"]
    dvl = s["dvl"]
    assert dvl["reports"] > 200 and dvl["valid"] >= 0.95 * dvl["reports"], dvl
    expect = GEO["floor_top"] - (DEPTH + GEO["dvl_z"])                      # 0.85 m
    assert dvl["hold_altitude_m"]["mean"] == pytest.approx(expect, abs=0.02), str(dvl) + _diag(run)
    assert abs(dvl["hold_vx_m_s"]["mean"]) < 0.01 and dvl["hold_vx_m_s"]["max_abs"] < 0.05, dvl
    c = _mission_log(run)
    ap = _phase(s, "approach")
    sel = (c["t"] >= ap["start_s"]) & (c["t"] < ap["end_s"]) & np.isfinite(c["dvl_vx"])
    assert sel.sum() > 20
    # the approach creeps forward at most at its speed limit, as the DVL measures it
    assert 0.0 < np.median(c["dvl_vx"][sel]) <= 0.05 + 0.01
    # the floor the stack tracks is the DVL's: depth + 0.35 + altitude
    assert np.nanmedian(c["floor_depth"][sel]) == pytest.approx(GEO["floor_top"], abs=0.02)


def test_the_mission_surfaces_and_logs_gnss_fixes_where_the_vehicle_is(run):
    """The surfacing phase: the stack rises until the mast is out of the water and completes on its third
    GNSS fix, which comes no sooner than the receiver's time to fix; the fixes' mean position is the
    antenna's, converted from the scenario's [world] origin with the standard degree lengths, within the
    profile's noise."""
    s = run["summary"]
    surf = _phase(s, "surface")
    assert surf["outcome"] == "gnss fix"
    g = s["gnss"]
    assert g["fixes"] >= 3 and g["quality"] == 1 and g["satellites"] >= 4
    assert g["after_surfacing_start_s"] >= GEO["time_to_fix"]
    assert s["depth"]["surface"]["final_m"] < GEO["mast"]                   # the antenna out of the water
    # where the vehicle held: from the observer's own sonar measurement in the hold
    lo = math.radians(GEO["tilt"] - GEO["half_elevation"])
    xs = []
    for r in _hold_rows(run):
        h = GEO["floor_top"] - (r["hdr_depth"] + GEO["mount_z"])
        xs.append(GEO["front_face_x"] - (GEO["mount_x"] + math.sqrt(r["far"] ** 2 - h ** 2)))
    north = float(np.median(xs)) + GEO["gnss_x"]
    phi = math.radians(GEO["origin_lat"])
    m_lat = 111132.954 - 559.822 * math.cos(2 * phi) + 1.175 * math.cos(4 * phi)       # [m / deg]
    m_lon = 111412.84 * math.cos(phi) - 93.5 * math.cos(3 * phi) + 0.118 * math.cos(5 * phi)
    tol = 4 * GEO["gnss_noise"] / math.sqrt(g["fixes"]) + 0.5                          # noise + drift at the surface
    assert (g["lat_deg"] - GEO["origin_lat"]) * m_lat == pytest.approx(north, abs=tol)
    assert (g["lon_deg"] - GEO["origin_lon"]) * m_lon == pytest.approx(0.0, abs=tol)


def _example(name: str):
    """A module of examples/ (the stack's pure parts), imported from its folder."""
    if str(EXAMPLES) not in sys.path:
        sys.path.insert(0, str(EXAMPLES))
    return importlib.import_module(name)


def test_the_example_imports_no_hilsim():
    files = sorted(EXAMPLES.glob("*.py"))
    assert {"mission.py", "demo.py"} <= {f.name for f in files}
    for f in files:
        text = f.read_text()
        assert "import hilsim" not in text and "from hilsim" not in text, f.name


def test_vesc_frames_by_dbc_and_by_hand_agree():
    m = _example("auv_io")
    cantools = pytest.importorskip("cantools")
    for kind, values in (("duty", [0.0, 0.12345, -0.5, 1.0]), ("rpm", [0.0, 1234.0, -25200.0]),
                         ("current", [0.0, 3.5, -24.0])):
        by_dbc = m.VescCan.__new__(m.VescCan)   # encode() only: no bus
        by_hand = m.VescCan.__new__(m.VescCan)
        by_dbc.kind, by_dbc.db = kind, cantools.database.load_file(str(ROOT / "protocols" / "vesc_can.dbc"))
        by_hand.kind, by_hand.db = kind, None
        for cid in range(1, 9):
            for v in values:
                assert by_dbc.encode(cid, v) == by_hand.encode(cid, v), (kind, cid, v)


def test_the_mixing_matrix_gives_the_requested_wrench():
    m = _example("auv_vehicle")
    alloc = m.allocation_matrix()
    dirs = np.array([d for _, _, _, d in m.THRUSTERS]).T
    moments = np.array([np.cross(p, d) for _, _, p, d in m.THRUSTERS]).T
    for wrench in ([10, 0, 0, 0, 0, 0], [0, 5, 0, 0, 0, 0], [0, 0, 8, 0, 0, 0], [0, 0, 0, 0, 0, 3],
                   [10, -2, 3, 0, 0, -1]):
        t = alloc @ np.array(wrench, float)
        np.testing.assert_allclose(np.concatenate([dirs @ t, moments @ t])[[0, 1, 2, 5]],
                                   np.array(wrench, float)[[0, 1, 2, 5]], atol=1e-9)
    t = m.allocate(alloc, 1000.0, 0.0, 0.0, 0.0, limit=25.0)
    assert np.max(np.abs(t)) == pytest.approx(25.0) and np.all(t[4:] == 0)


def test_the_mission_touches_nothing(run):
    """The bridge's ground truth: the hull never touched the floor, a wall or the cuboid."""
    b = run["bridge_summary"]
    assert b, "no summary.json beside the bridge's endpoints file"
    assert b["contacts"] == {"count": 0, "events": []}, b["contacts"]
    truth = Path(b["truth"])
    assert truth.exists() and truth.stat().st_size > 0
    assert b["sim_time_s"] >= run["summary"]["duration_s"] - 1.0
