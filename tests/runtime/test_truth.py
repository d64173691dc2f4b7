"""The ground truth file and the contact events of a run: a VehicleLoop on a virtual clock,
the water-tank world, read back with the csv module and checked against the geometry."""

from __future__ import annotations

import csv
import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest

from hilsim.runtime.clock import VirtualClock
from hilsim.runtime.scheduler import Scheduler, VehicleLoop
from hilsim.runtime.truth import BASE_COLUMNS, ContactEvents, TruthRecorder, run_summary, write_summary
from hilsim.sim.contact import ContactInfo
from hilsim.sim.scenario import load_scenario
from hilsim.sim.state import VehicleState
from hilsim.sim.vehicle import Vehicle, load_vehicle_profile

ROOT = Path(__file__).resolve().parents[2]
PROFILE = load_vehicle_profile(ROOT / "devices" / "vehicles" / "cyclops.toml")
TANK = load_scenario(ROOT / "scenarios" / "water_tank" / "scenario.toml")
WORLD = TANK.build_world()
FLOOR, HALF_H = 3.0, PROFILE.hull.size[2] / 2
VERTICAL = [4, 5, 6, 7]


def dive(tmp_path: Path, seconds: float, rate_hz: float | None = 20.0, start=(-3.0, 2.0, 1.5),
         commands=(0, 0, 0, 0, 1, 1, 1, 1)) -> tuple[VehicleLoop, TruthRecorder, list[dict[str, str]]]:
    ts = PROFILE.thruster_set()
    loop = VehicleLoop(Vehicle(PROFILE), ts, VehicleState(position=np.array(start, dtype=float)), world=WORLD)
    rec = TruthRecorder(tmp_path / "truth.csv", loop, rate_hz).attach()
    sched = Scheduler(VirtualClock())
    sched.add("control", 0.1, lambda t: ts.command_all("normalized", commands, t), priority=-1)
    loop.attach(sched)
    sched.run(until=seconds)
    rec.close()
    with open(tmp_path / "truth.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    return loop, rec, rows


def test_full_down_thrust_the_truth_shows_one_floor_contact(tmp_path: Path) -> None:
    loop, rec, rows = dive(tmp_path, 12.0)
    header = (tmp_path / "truth.csv").read_text().splitlines()[0].split(",")
    assert header == list(BASE_COLUMNS) + [f"thrust_N.{n}" for n in loop.thrusters.names] + [
        "contact", "contact_object", "contact_force_N", "penetration_m", "clearance_m", "altitude_m",
        "faults", "surfaced"]
    t = np.array([float(r["time_s"]) for r in rows])
    assert np.allclose(np.diff(t), 0.05, atol=1e-6)        # 20 Hz of the 200 Hz physics
    down = np.array([float(r["down_m"]) for r in rows])
    contact = np.array([int(r["contact"]) for r in rows])
    assert np.count_nonzero(np.diff(contact) == 1) == 1 and contact[-1] == 1   # one contact, lasting
    assert {r["contact_object"] for r in rows if r["contact"] == "1"} == {"floor"}
    assert down[-1] == pytest.approx(FLOOR - HALF_H, abs=0.01)
    free = contact == 0
    # altitude: body origin straight down to the floor; clearance: hull bottom to the floor (the
    # nearest object here: the walls are >= 2.6 m away)
    alt = np.array([float(r["altitude_m"]) for r in rows])
    clr = np.array([float(r["clearance_m"]) for r in rows])
    assert np.allclose(alt, FLOOR - down, atol=1e-6)
    assert np.allclose(clr[free], FLOOR - HALF_H - down[free], atol=1e-6)
    assert np.all(clr[~free] == 0.0)
    thrust = np.array([[float(r[f"thrust_N.{n}"]) for n in loop.thrusters.names] for r in rows])
    assert np.all(thrust[-1, :4] == 0.0) and np.allclose(thrust[-1, 4:], loop.thrusters.max_thrust[4:], rtol=1e-6)
    force = float(rows[-1]["contact_force_N"])
    assert force == pytest.approx(thrust[-1].sum() + PROFILE.params["heave"].constant_force, rel=2e-3)
    assert 0.0 <= float(rows[-1]["penetration_m"]) <= 0.01
    # the event
    s = rec.events.summary()
    assert s["count"] == 1
    ev = s["events"][0]
    assert ev["object"] == "floor"
    # a rigid impact: the momentum m_w w stopped within one 5 ms physics tick (plus that tick's thrust)
    m_w = PROFILE.params["heave"].mass
    assert ev["peak_force_N"] == pytest.approx(m_w * ev["impact_speed_m_s"] * 200.0 + force, rel=0.02)
    first = t[np.argmax(contact)]
    assert ev["start_s"] <= first and ev["start_s"] > first - 0.05
    assert 0.2 < ev["impact_speed_m_s"] < 1.0 and ev["max_penetration_m"] <= 0.01
    assert ev["end_s"] == pytest.approx(12.0)


def test_full_rate_on_request_and_added_columns(tmp_path: Path) -> None:
    ts = PROFILE.thruster_set()
    loop = VehicleLoop(Vehicle(PROFILE), ts, VehicleState(position=np.array([-3.0, 0.0, 1.5])), world=WORLD)
    rec = TruthRecorder(tmp_path / "truth.csv", loop, rate_hz=None)
    rec.add_columns(["pwm_us.1", "pwm_us.2"], lambda s: [1500, 1500 + int(100 * s.time)])
    with pytest.raises(ValueError):
        rec.add_columns(["down_m"], lambda s: [0])
    rec.attach()
    sched = Scheduler(VirtualClock())
    loop.attach(sched)
    sched.run(until=1.0)
    with pytest.raises(RuntimeError):
        rec.add_columns(["late"], lambda s: [0])
    rec.close()
    rows = list(csv.DictReader(open(tmp_path / "truth.csv", newline="")))
    assert len(rows) == 200 and rows[-1]["pwm_us.2"] == "1600"
    assert [float(r["time_s"]) for r in rows[:3]] == pytest.approx([0.005, 0.01, 0.015])


def test_floating_at_the_surface_is_not_a_contact(tmp_path: Path) -> None:
    _, rec, rows = dive(tmp_path, 15.0, start=(-3.0, 0.0, 0.5), commands=(0,) * 8)
    assert rows[-1]["surfaced"] == "1" and rows[-1]["contact"] == "0"
    assert float(rows[-1]["down_m"]) == pytest.approx(HALF_H, abs=1e-3)
    assert rec.events.count == 0


def info(*names: str, force: float = 10.0) -> ContactInfo:
    n = len(names)
    return ContactInfo(names, (force,) * n, (0.3,) * n, (0.002,) * n, 0.001)


def test_events_hold_short_lift_offs_and_log_one_line_each(caplog: pytest.LogCaptureFixture) -> None:
    seen = []
    ev = ContactEvents(hold_s=0.2, on_event=lambda kind, e: seen.append((kind, e["object"])))
    caplog.set_level(logging.INFO, logger="hilsim.contact")
    script = [(0.0, ()), (1.0, ("floor",)), (1.1, ()), (1.15, ("floor",)), (1.2, ("floor", "cuboid")),
              (1.3, ()), (1.6, ()), (2.0, ("cuboid",)), (2.5, ())]
    for t, names in script:
        ev.update(t, info(*names, force=5.0 + t))
    ev.close()
    s = ev.summary()
    assert [(e["object"], e["start_s"], e["end_s"]) for e in s["events"]] == [
        ("floor", 1.0, 1.2), ("cuboid", 1.2, 1.2), ("cuboid", 2.0, 2.0)]
    assert s["events"][0]["peak_force_N"] == pytest.approx(6.2)
    assert seen == [("start", "floor"), ("start", "cuboid"), ("end", "floor"), ("end", "cuboid"),
                    ("start", "cuboid"), ("end", "cuboid")]
    lines = [r.getMessage() for r in caplog.records if r.name == "hilsim.contact"]
    assert len(lines) == 6 and sum(m.startswith("contact start") for m in lines) == 3


def test_the_summary_json_has_the_agreed_keys(tmp_path: Path) -> None:
    _, rec, _ = dive(tmp_path, 6.0)
    summary = run_summary(scenario="water_tank", seed=1, sim_time_s=6.0, wall_s=0.5, late_ticks=0,
                          skipped_ticks=0, devices={"depth": {"replies": 3}}, recorder=rec)
    write_summary(tmp_path / "summary.json", summary)
    back = json.loads((tmp_path / "summary.json").read_text())
    assert set(back) == {"scenario", "seed", "sim_time_s", "wall_s", "late_ticks", "skipped_ticks", "devices",
                         "contacts", "faults", "truth"}
    assert back["contacts"]["count"] == 1
    assert set(back["contacts"]["events"][0]) == {"start_s", "end_s", "object", "peak_force_N",
                                                  "impact_speed_m_s", "max_penetration_m"}
    assert back["truth"] == str(tmp_path / "truth.csv") and back["faults"] == []
    assert not math.isnan(back["contacts"]["events"][0]["impact_speed_m_s"])


WIRE_DEVICES = """
[[devices]]
name = "vesc_can"
protocol = "vesc-can"
transport = "socketcand"
channel = "can0"
port = 0
status_rate_hz = 20

[[devices]]
name = "depth"
protocol = "modbus-keller"
transport = "tcp"
port = 0
device_id = 1
"""


def test_on_the_wire_full_down_thrust_stops_at_the_floor_and_the_truth_has_one_contact(tmp_path: Path) -> None:
    """A client commands full down thrust over VESC CAN (python-can on the socketcand server); the
    Keller depth it reads over Modbus TCP (pymodbus) stops at the floor; the truth file and the
    summary written at shutdown record exactly one contact, with the floor."""
    can = pytest.importorskip("can")
    cantools = pytest.importorskip("cantools")
    pymodbus_client = pytest.importorskip("pymodbus.client")
    import time

    from hilsim.protocols.vesc_can import dbc_path
    from tests.runtime.bridge_helpers import start_bridge

    text = (ROOT / "scenarios" / "water_tank" / "scenario.toml").read_text()
    (tmp_path / "scenario.toml").write_text(text[:text.find("[[devices]]")] + WIRE_DEVICES)
    rho = 998.0
    bp = start_bridge(tmp_path, str(tmp_path / "scenario.toml"), "--time-scale", "4", "--status-interval", "1")
    try:
        ep = {e["device"]: e for e in bp.endpoints}
        ex = ep["vesc_can"]  # the extra fields are flattened into the entry
        bus = can.Bus(interface="socketcand", channel=ex["channel"], host=ex["host"], port=int(ex["port"]))
        host, port = ep["depth"]["address"].rsplit(":", 1)
        mb = pymodbus_client.ModbusTcpClient(host, port=int(port), timeout=2)
        assert mb.connect()
        db = cantools.database.load_file(str(dbc_path()))
        depths: list[tuple[float, float]] = []
        t0 = time.monotonic()
        try:
            while time.monotonic() - t0 < 30.0:
                for cid in (5, 6, 7, 8):  # the vertical thrusters push down (+z)
                    m = db.get_message_by_name(f"VESC{cid}_SET_DUTY")
                    bus.send(can.Message(arbitration_id=m.frame_id, data=m.encode({"duty": 1.0}), is_extended_id=True))
                rr = mb.read_holding_registers(0x0002, count=2, device_id=1)
                p1 = mb.convert_from_registers(rr.registers, mb.DATATYPE.FLOAT32)
                depths.append((time.monotonic() - t0, (p1 * 1e5 - 101325) / (rho * 9.80665)))
                now = depths[-1][0]
                last = [d for t, d in depths if t > now - 0.5]
                before = [d for t, d in depths if now - 1.0 < t <= now - 0.5]
                if now > 2.0 and before and abs(np.mean(last) - np.mean(before)) < 0.002:
                    break  # it stopped (the Keller's noise is a few mm)
                time.sleep(0.05)
        finally:
            bus.shutdown()
            mb.close()
    finally:
        assert bp.stop() == 0, bp.log()[-3000:]
    print(f"wall {depths[-1][0]:.1f} s, {len(depths)} readings, last {depths[-1][1]:.4f} m")
    d = np.array([x for _, x in depths])
    assert d[0] < 1.6 and np.mean(d[-5:]) == pytest.approx(FLOOR - HALF_H, abs=0.02), d[-20:]
    assert d.max() <= FLOOR - HALF_H + 0.03
    rows = list(csv.DictReader(open(tmp_path / "truth.csv", newline="")))   # beside the endpoints file
    contact = [int(r["contact"]) for r in rows]
    assert sum(1 for a, b in zip(contact, contact[1:]) if (a, b) == (0, 1)) == 1 and contact[-1] == 1
    assert {r["contact_object"] for r in rows if r["contact"] == "1"} == {"floor"}
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["contacts"]["count"] == 1 and summary["contacts"]["events"][0]["object"] == "floor"
    assert summary["truth"] == str(tmp_path / "truth.csv") and summary["scenario"] == "water_tank"
    assert summary["devices"]["vesc_can"] and "contact start" in bp.log() and "contacts 1" in bp.log()


def test_the_bridge_publishes_contacts_counts_them_and_records_faults(tmp_path: Path) -> None:
    """An in-process bridge on the virtual clock (the tank without devices): full down thrust, a
    thruster fault injected and cleared through the bridge's fault table; the 'contact' topic,
    the status count, the truth's faults column and the summary's fault history."""
    import asyncio

    from hilsim.runtime.bridge import Bridge

    text = (ROOT / "scenarios" / "water_tank" / "scenario.toml").read_text()
    (tmp_path / "scenario.toml").write_text(text[:text.find("[[devices]]")])
    seen: list[dict] = []

    async def main() -> tuple[dict, dict]:
        b = Bridge(tmp_path / "scenario.toml", fast=True, run_dir=tmp_path / "run", status_interval=0)
        b.summary_path = tmp_path / "summary.json"
        b.observers.subscribe("contact", lambda topic, m: seen.append(dict(m)))
        await b.start()
        ts = b.vehicle.thrusters
        b.every("control", 0.1, lambda t: ts.command_all("normalized", [0, 0, 0, 0, 1, 1, 1, 1], t), priority=-1)
        b.at(1.0, lambda t: b.faults.inject("thruster:front_left", "fail"))
        b.at(2.0, lambda t: b.faults.clear("thruster:front_left", "fail"))
        await b.run(9.0)
        status = b.status()
        await b.close()
        return status, json.loads((tmp_path / "summary.json").read_text())

    status, summary = asyncio.run(main())
    assert status["contacts"] == 1
    assert [(m["event"], m["object"]) for m in seen] == [("start", "floor"), ("end", "floor")]
    assert set(seen[0]) == {"t", "event", "object", "force_N", "speed_m_s"} and seen[0]["speed_m_s"] > 0.2
    rows = list(csv.DictReader(open(tmp_path / "run" / "truth.csv", newline="")))  # the run folder's
    faulty = [float(r["time_s"]) for r in rows if r["faults"] == "thruster:front_left:fail"]
    assert faulty and 1.0 <= min(faulty) < 1.06 and 1.9 < max(faulty) < 2.0
    assert summary["faults"] == [{"t_s": 1.0, "target": "thruster:front_left", "fault": "fail", "on": True},
                                 {"t_s": 2.0, "target": "thruster:front_left", "fault": "fail", "on": False}]
    assert summary["contacts"]["count"] == 1 and summary["sim_time_s"] == pytest.approx(9.0)


def test_a_truth_file_that_cannot_be_written_fails_at_start_and_a_failing_disk_never_stops_the_run(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    ts = PROFILE.thruster_set()
    loop = VehicleLoop(Vehicle(PROFILE), ts, VehicleState(position=np.array([-3.0, 0.0, 1.5])), world=WORLD)
    (tmp_path / "file").write_text("")
    with pytest.raises(OSError):
        TruthRecorder(tmp_path / "file" / "truth.csv", loop).open()   # a folder that is a file
    rec = TruthRecorder(tmp_path / "truth.csv", loop, rate_hz=None).attach()
    sched = Scheduler(VirtualClock())
    loop.attach(sched)
    sched.run(until=0.5)
    rec._file.close()  # the disk fills up under the recorder: every write raises OSError (ENOSPC)
    rec._file = open("/dev/full", "w", buffering=1)
    rec._writer = csv.writer(rec._file)
    caplog.set_level(logging.ERROR, logger="hilsim.truth")
    sched.run(until=1.0)  # the physics goes on
    assert loop.state.time == pytest.approx(1.0)
    assert sum("cannot write" in r.getMessage() for r in caplog.records) == 1
    rec.close()
