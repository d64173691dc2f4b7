"""Contacts against physics: the hull stops at floors, walls and the cuboid; closed-form
terminal speeds, Coulomb deceleration, the floating height; stability at 50 and 200 Hz.

Geometry is checked independently of the contact code: axis-aligned boxes by their
intervals, terrain by Embree rays. Worlds are the water-tank scenario (real meshes,
Embree) or boxes built here with trimesh."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from hilsim.config import ConfigError
from hilsim.sim.contact import ContactModel, Hull, inverse_mass
from hilsim.sim.scenario import load_scenario
from hilsim.sim.state import VehicleState
from hilsim.sim.vehicle import DofParameters, Vehicle, load_vehicle_profile
from hilsim.sim.world import Material, World, WorldObject

ROOT = Path(__file__).resolve().parents[2]
CYCLOPS = load_vehicle_profile(ROOT / "devices" / "vehicles" / "cyclops.toml")
TANK = load_scenario(ROOT / "scenarios" / "water_tank" / "scenario.toml")
HALF = np.array(CYCLOPS.hull.size) / 2            # (0.45, 0.4, 0.3) m
FLOOR_TOP, WALL_NORTH = 3.0, 10.0                  # the tank's floor top and north wall face [m]
CUBOID_LO, CUBOID_HI = np.array([0.0, -0.2, 2.7]), np.array([0.55, 0.2, 3.0])
TANK_WORLD = TANK.build_world()


def full(names: list[str]) -> np.ndarray:
    """(6,) body wrench of these Cyclops thrusters at their full forward thrust."""
    ts = CYCLOPS.thruster_set()
    thrust = np.array([ts.max_thrust[i] if n in names else 0.0 for i, n in enumerate(ts.names)])
    return ts.matrix @ thrust


HORIZONTAL = ["front_left", "front_right", "rear_left", "rear_right"]
VERTICAL = ["vertical_front_left", "vertical_front_right", "vertical_rear_left", "vertical_rear_right"]


def simulate(profile, world, state: VehicleState, wrench, seconds: float, rate: float = 200.0,
             every=None) -> tuple[VehicleState, ContactModel]:
    vehicle = Vehicle(profile)
    cm = ContactModel.for_profile(profile, world)
    dt = 1.0 / rate
    for _ in range(int(round(seconds * rate))):
        new = cm.step(state, vehicle.step(state, dt, wrench), dt)
        if every is not None:
            every(state, new, cm)
        state = new
    return state, cm


def overlap(pos: np.ndarray, lo: np.ndarray, hi: np.ndarray, yaw: float = 0.0) -> float:
    """[m] how deep the hull (yaw a multiple of 90 deg) overlaps the box [lo, hi] (<= 0: apart)."""
    h = HALF if round(yaw / (math.pi / 2)) % 2 == 0 else HALF[[1, 0, 2]]
    return float(np.min(np.minimum(pos + h - lo, hi - (pos - h))))


def box(name: str, lo, hi, friction: float = 0.5) -> WorldObject:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    mesh = trimesh.creation.box(extents=hi - lo)
    mesh.apply_translation((lo + hi) / 2)
    return WorldObject(name, mesh, Material(name, 3e6, friction=friction))


@pytest.mark.parametrize("rate", [200.0, 50.0])
def test_full_down_thrust_stops_on_the_floor(rate: float) -> None:
    wrench = full(VERTICAL)
    deepest = []
    end, cm = simulate(CYCLOPS, TANK_WORLD, VehicleState(position=np.array([-3.0, 2.0, 1.5])), wrench, 12.0,
                       rate, every=lambda a, b, c: deepest.append(b.position[2]))
    # depth = floor depth - the hull's half height, within 1 cm, at every tick and at rest
    assert max(deepest) <= FLOOR_TOP - HALF[2] + 0.01
    assert end.position[2] == pytest.approx(FLOOR_TOP - HALF[2], abs=0.01)
    assert np.allclose(end.velocity, 0.0, atol=1e-9)
    assert cm.last.objects == ("floor",)
    # pressed by the thrust less the net buoyancy (W_w = -2.5 N): Newton's third law (within
    # the damping of the velocity one step builds before the contact takes it away:
    # k_w dt / (2 m_w) = 0.1 % at 50 Hz)
    assert cm.last.force == pytest.approx(wrench[2] + CYCLOPS.params["heave"].constant_force, rel=2e-3)
    assert cm.last.penetration <= 0.01


@pytest.mark.parametrize("rate", [200.0, 50.0])
def test_full_surge_into_the_north_wall_stops_at_the_wall(rate: float) -> None:
    start = VehicleState(position=np.array([7.0, 0.0, 1.5]))
    xs = []
    end, cm = simulate(CYCLOPS, TANK_WORLD, start, full(HORIZONTAL) + [0, 0, 2.5, 0, 0, 0], 25.0, rate,
                       every=lambda a, b, c: xs.append(b.position[0]))
    assert max(xs) <= WALL_NORTH - HALF[0] + 0.01
    assert end.position[0] == pytest.approx(WALL_NORTH - HALF[0], abs=0.01)
    assert abs(end.velocity[0]) < 1e-9
    assert cm.last.objects == ("wall_north",)


def test_a_negatively_buoyant_vehicle_sinks_at_table1_terminal_speed_then_rests() -> None:
    # Cyclops made 30 N heavy: m_w w' = W - k_w w - k_w|w| w|w| (Table 1). Closed form with the
    # roots w+ > 0 > w- of k_ww w^2 + k_w w - W: (w - w+)/(w - w-) = (w+/w-) exp(-lambda t),
    # lambda = k_ww (w+ - w-) / m_w.
    weight = 30.0
    m, k, q = 639.6, 65.6, 296.8
    heavy = replace(CYCLOPS, params={**CYCLOPS.params, "heave": DofParameters(m, k, q, weight)})
    wp = (-k + math.sqrt(k * k + 4 * q * weight)) / (2 * q)
    wm = (-k - math.sqrt(k * k + 4 * q * weight)) / (2 * q)
    lam = q * (wp - wm) / m
    floor = 40.0
    world = World([box("floor", [-5, -5, floor], [5, 5, floor + 1])])
    samples = []
    end, cm = simulate(heavy, world, VehicleState(position=np.array([0.0, 0.0, 1.0])), [0.0] * 6, 200.0,
                       every=lambda a, b, c: samples.append((b.time, b.velocity[2], b.position[2], c.last.touching)))
    t, w, z, touch = (np.array(v) for v in zip(*samples))
    free = ~np.cumsum(touch).astype(bool)
    a = (wp / wm) * np.exp(-lam * t[free])
    assert np.allclose(w[free], (wp - a * wm) / (1 - a), rtol=1e-6, atol=1e-9)
    assert w[free][-1] == pytest.approx(wp, rel=1e-4)      # it reached the terminal speed
    assert end.position[2] == pytest.approx(floor - HALF[2], abs=0.01)
    assert abs(end.velocity[2]) < 1e-9 and cm.last.force == pytest.approx(weight, rel=1e-3)
    assert np.all(w[t > t[~free][0]] >= -1e-12)             # no bounce after touching down


def test_a_glancing_approach_slides_along_the_wall_with_coulomb_deceleration() -> None:
    # sway damping off, so that the slide is Coulomb's alone: dv/dt = -mu F / m_v
    mu, press = 0.6, 80.0
    m_v = CYCLOPS.params["sway"].mass
    slick = replace(CYCLOPS, params={**CYCLOPS.params, "sway": DofParameters(m_v, 0.0, 0.0)})
    world = World([box("wall", [10, -20, -1], [11, 20, 10], friction=mu)])
    rows = []
    start = VehicleState(position=np.array([9.5, 0.0, 2.0]), velocity=np.array([0.2, 0.2, 0.0]))  # 45 deg
    simulate(slick, world, start, [press, 0, 0, 0, 0, 0], 20.0,
             every=lambda a, b, c: rows.append((b.time, b.position[0], b.velocity[1], c.last.touching)))
    t, x, v, touch = (np.array(r) for r in zip(*rows))
    first = t[np.argmax(touch)]
    on = touch & (v > 0.02) & (t > first + 0.1)  # sliding, after the impact's own impulse
    assert on.sum() > 100
    slope = np.polyfit(t[on], v[on], 1)[0]
    assert slope == pytest.approx(-mu * press / m_v, rel=1e-3)
    assert np.all(x <= 10.0 - HALF[0] + 0.01)
    assert v[-1] == 0.0  # Coulomb friction stops the slide (and never reverses it)


@pytest.mark.parametrize("yaw_deg", [0, 90, 180, 270, 45, 135])
def test_nothing_passes_through_the_cuboid_from_any_side(yaw_deg: float) -> None:
    yaw = math.radians(yaw_deg)
    centre = (CUBOID_LO + CUBOID_HI) / 2
    # start 1.5 m from the cuboid's centre, facing it, low enough to hit its side (hull bottom 2.9 m)
    pos = np.array([centre[0] - 1.5 * math.cos(yaw), centre[1] - 1.5 * math.sin(yaw), 2.6])
    worst = []

    def check(a, b, c):
        if yaw_deg % 90 == 0:
            worst.append(overlap(b.position, CUBOID_LO, CUBOID_HI, b.attitude[2]))
        worst.append(-c.clearance(b)[0] if c.last.objects == () else 0.0)

    end, cm = simulate(CYCLOPS, TANK_WORLD, VehicleState(position=pos, attitude=np.array([0, 0, yaw])),
                       full(HORIZONTAL) + [0, 0, 2.5, 0, 0, 0], 10.0, every=check)
    assert max(worst) <= 0.01
    assert "cuboid" in cm.last.objects
    along = (end.position[:2] - pos[:2]) @ [math.cos(yaw), math.sin(yaw)]
    assert along < 1.5  # it stopped before the cuboid's centre


def test_nothing_passes_through_the_cuboid_from_above() -> None:
    pos = np.array([0.275, 0.0, 1.5])
    end, cm = simulate(CYCLOPS, TANK_WORLD, VehicleState(position=pos), full(VERTICAL), 10.0)
    assert end.position[2] == pytest.approx(CUBOID_LO[2] - HALF[2], abs=0.01)
    assert cm.last.objects == ("cuboid",)


def test_a_buoyant_vehicle_floats_with_the_hull_top_at_the_surface() -> None:
    up = -full(VERTICAL)  # reversed: the reverse thrust is weaker, but it still pushes up
    ts = CYCLOPS.thruster_set()
    up = ts.matrix @ np.array([0.0] * 4 + [ts.min_thrust[i] for i in range(4, 8)])
    assert up[2] < 0
    for wrench in (up, np.zeros(6)):  # W_w alone rises at 3.5 cm/s
        end, cm = simulate(CYCLOPS, None, VehicleState(position=np.array([0.0, 0.0, 0.6])), wrench, 25.0)
        assert HALF[2] - 1e-3 - 1e-9 <= end.position[2] <= HALF[2]  # the top at z = 0, within 1 mm
        assert cm.last.surfaced and not cm.last.touching


@pytest.mark.parametrize("rate", [200.0, 50.0])
def test_stable_with_every_thruster_at_full_power_in_a_corner(rate: float) -> None:
    # all 8 at full: surge and dive into the floor/north wall corner, then hold there
    wrench = full(HORIZONTAL + VERTICAL)
    rows = []
    end, cm = simulate(CYCLOPS, TANK_WORLD, VehicleState(position=np.array([8.5, 0.0, 2.0])), wrench, 20.0, rate,
                       every=lambda a, b, c: rows.append((b.position, b.velocity)))
    pos = np.array([r[0] for r in rows])
    assert np.all(np.isfinite(pos))
    assert pos[:, 0].max() <= WALL_NORTH - HALF[0] + 0.01
    assert pos[:, 2].max() <= FLOOR_TOP - HALF[2] + 0.01
    assert end.position[0] == pytest.approx(WALL_NORTH - HALF[0], abs=0.01)
    assert end.position[2] == pytest.approx(FLOOR_TOP - HALF[2], abs=0.01)
    assert np.abs(np.array([r[1] for r in rows[-int(rate):]])).max() < 1e-9  # at rest, no jitter
    assert set(cm.last.objects) == {"floor", "wall_north"}


def kinetic(state: VehicleState, minv: np.ndarray) -> float:
    v = np.asarray(state.velocity)
    return 0.5 * float(v @ np.linalg.inv(minv) @ v)


@pytest.mark.parametrize("rate", [200.0, 50.0])
def test_the_contact_step_never_adds_energy(rate: float) -> None:
    """Every tick: the kinetic energy after the contact step <= before it (no bounce, ever)."""
    minv = inverse_mass(CYCLOPS)
    vehicle = Vehicle(CYCLOPS)
    cm = ContactModel.for_profile(CYCLOPS, TANK_WORLD)
    dt = 1.0 / rate
    rng = np.random.default_rng(7)
    state = VehicleState(position=np.array([8.0, 3.5, 2.2]), velocity=np.array([0.6, 0.4, 0.3]))
    hits = 0
    for k in range(int(30 * rate)):
        if k % int(rate) == 0:
            wrench = np.r_[rng.uniform(-150, 150, 3), 0, 0, rng.uniform(-20, 20)]
        free = vehicle.step(state, dt, wrench)
        new = cm.step(state, free, dt)
        hits += cm.last.touching
        assert kinetic(new, minv) <= kinetic(free, minv) + 1e-12
        state = new
    assert hits > 100


def test_the_imu_acceleration_shows_the_impact() -> None:
    rate = 200.0
    world = World([box("wall", [10, -20, -1], [11, 20, 10])])
    start = VehicleState(position=np.array([9.5, 0.0, 2.0]), velocity=np.array([0.3, 0.0, 0.0]))
    seen = []
    simulate(CYCLOPS, world, start, np.zeros(6), 1.0, rate,
             every=lambda a, b, c: seen.append((a.velocity[0], b.acceleration[0], c.last)))
    k = next(i for i, s in enumerate(seen) if s[2].touching)
    u_before = seen[k][0]
    assert seen[k][1] == pytest.approx(-u_before * rate, rel=0.02)   # the velocity lost in one tick
    assert seen[k][2].speeds[0] == pytest.approx(u_before, rel=0.02)  # the impact speed


def test_a_moved_object_is_collided_with_where_it_is_now() -> None:
    world = TANK.build_world()
    start = VehicleState(position=np.array([-3.0, 3.0, 2.6]))
    wrench = full(HORIZONTAL) + [0, 0, 2.5, 0, 0, 0]
    end, _ = simulate(CYCLOPS, world, start, wrench, 0.5)
    pose = np.eye(4)
    pose[:3, 3] = [-1.0, 3.0, 2.85]
    world.place("cuboid", pose, TANK.object_placement("cuboid").matrix())
    end, cm = simulate(CYCLOPS, world, end, wrench, 12.0)
    assert end.position[0] == pytest.approx(-1.0 - 0.275 - HALF[0], abs=0.01)
    assert cm.last.objects == ("cuboid",)


def test_terrain_holds_the_hull_up_checked_by_rays() -> None:
    from hilsim.config import Doc
    from hilsim.sim.scenario import _terrain  # the scenario's own terrain generator

    doc = Doc(TANK.folder / "scenario.toml", "", {})
    mesh = _terrain(doc, {"size_m": [8.0, 8.0], "resolution_m": 0.25, "relief_m": 0.6, "seed": 3}, "t")
    mesh.apply_translation([0.0, 0.0, 5.0])
    world = World([WorldObject("seabed", mesh, Material("sand", 2e6, friction=0.8), watertight=False)])
    for x0, y0 in [(1.3, -0.7), (-2.0, 1.5)]:
        end, cm = simulate(CYCLOPS, world, VehicleState(position=np.array([x0, y0, 3.6])), full(VERTICAL), 8.0)
        # the highest ground under the hull's footprint, by rays cast up from below
        gx, gy = np.meshgrid(np.linspace(-HALF[0], HALF[0], 25), np.linspace(-HALF[1], HALF[1], 25))
        org = np.column_stack([end.position[0] + gx.ravel(), end.position[1] + gy.ravel(), np.full(gx.size, 9.0)])
        hits = world.cast(org, np.tile([0.0, 0.0, -1.0], (len(org), 1)))
        ground = float((9.0 - hits.t[np.isfinite(hits.t)]).min())
        bottom = end.position[2] + HALF[2]
        assert bottom <= ground + 0.01          # the hull does not sink into the ground
        assert bottom >= ground - 0.05          # and rests on it (the lowest corner may hang over a dip)
        assert cm.last.objects == ("seabed",)


def test_far_from_everything_the_state_passes_unchanged() -> None:
    cm = ContactModel.for_profile(CYCLOPS, TANK_WORLD)
    vehicle = Vehicle(CYCLOPS)
    s = VehicleState(position=np.array([-3.0, 0.0, 1.5]))
    for _ in range(50):
        new = vehicle.step(s, 0.005, [10.0, 0, 0, 0, 0, 0])
        assert cm.step(s, new, 0.005) is new
        s = new


def test_materials_friction_is_read_and_checked(tmp_path: Path) -> None:
    text = (ROOT / "scenarios" / "water_tank" / "scenario.toml").read_text()
    text = text.replace("[materials.plastic]\n", "[materials.plastic]\nfriction = 0.3\n")
    (tmp_path / "scenario.toml").write_text(text)
    sc = load_scenario(tmp_path / "scenario.toml")
    mats = {o.name: o.material.friction for o in sc.objects}
    assert mats["cuboid"] == 0.3 and mats["floor"] == Material.friction == 0.5
    (tmp_path / "scenario.toml").write_text(text.replace("friction = 0.3", "friction = -1"))
    with pytest.raises(ConfigError, match="friction"):
        load_scenario(tmp_path / "scenario.toml")


def test_profiles_carry_a_hull_with_sources() -> None:
    for name in ("cyclops", "bluerov2_heavy", "bluerov2"):
        p = load_vehicle_profile(ROOT / "devices" / "vehicles" / f"{name}.toml")
        assert isinstance(p.hull, Hull) and min(p.hull.size) > 0.2
        assert p.hull.sources["hull.size"]
        # every thruster lies inside the hull
        for t in p.thrusters:
            assert np.all(np.abs(np.asarray(t.position) - p.hull.centre) <= np.array(p.hull.size) / 2)


@pytest.mark.parametrize("name", ["bluerov2_heavy", "bluerov2"])
def test_the_6dof_bluerovs_rest_on_the_floor_too(name: str) -> None:
    """The contact step is the same for the 6-DOF model (hilsim.sim.vehicle6dof)."""
    prof = load_vehicle_profile(ROOT / "devices" / "vehicles" / f"{name}.toml")
    ts = prof.thruster_set()
    vertical = np.array([abs(t.direction[2]) > 0.9 for t in prof.thrusters])
    wrench = ts.matrix @ np.where(vertical, ts.max_thrust, 0.0)
    end, cm = simulate(prof, TANK_WORLD, VehicleState(position=np.array([-3.0, 2.0, 2.0])), wrench, 6.0)
    assert end.position[2] == pytest.approx(FLOOR_TOP - prof.hull.size[2] / 2, abs=0.01)
    assert np.allclose(end.velocity, 0.0, atol=1e-6) and np.allclose(end.attitude[:2], 0.0, atol=1e-3)
    assert cm.last.objects == ("floor",)
    # within the damping of one step's velocity, k_w dt / (2 m_w) = 0.26 % for the BlueROV
    assert cm.last.force == pytest.approx(wrench[2] + prof.hydrostatics.net_down, rel=5e-3)


def test_sliding_across_a_meshs_internal_edge_does_not_snag() -> None:
    """A plane primitive is two triangles meeting on a diagonal: pressed onto it and driven across
    that diagonal without friction, the vehicle moves exactly as on a box floor (no internal edge),
    never pushed sideways or up."""
    plane = trimesh.Trimesh(np.array([[-10.0, -10, 5], [10, -10, 5], [10, 10, 5], [-10, 10, 5]]),
                            np.array([[0, 3, 1], [1, 3, 2]]), process=False)  # normals up (-z)
    assert np.allclose(plane.face_normals, [0, 0, -1])
    sheet = World([WorldObject("sheet", plane, Material("ice", 1e6, friction=0.0), watertight=False)])
    slab = World([box("slab", [-10, -10, 5], [10, 10, 6], friction=0.0)])
    wrench = full(VERTICAL) + full(HORIZONTAL)          # down and forward; yawed 45 deg to cross the diagonal
    start = VehicleState(position=np.array([-3.0, 0.0, 4.7]), attitude=np.array([0.0, 0.0, math.radians(-45)]))
    runs = []
    for world in (sheet, slab):
        rows = []
        simulate(CYCLOPS, world, start, wrench, 8.0, every=lambda a, b, c: rows.append(b.flat()))
        runs.append(np.array(rows))
    a, b = runs
    crossed = (a[:, 1] - a[:, 0] > 0).any() and (a[:, 1] - a[:, 0] < 0).any()
    assert crossed                                          # it went over the diagonal y = x
    assert np.allclose(a[:, 2], 5.0 - HALF[2], atol=1.5e-3)   # on the surface all along
    assert np.allclose(a[:, :3], b[:, :3], atol=1e-6) and np.allclose(a[:, 6:9], b[:, 6:9], atol=1e-6)


def test_the_glancing_slide_with_table1_sway_damping_follows_the_reference_ode() -> None:
    """With Cyclops' own sway damping (Table 1): m_v dv/dt = -k_v v - k_v|v| v|v| - mu F while it
    slides, solved by scipy from the velocity just after the impact."""
    from scipy.integrate import solve_ivp

    mu, press = 0.6, 80.0
    m_v, k_v, q_v = (CYCLOPS.params["sway"].mass, CYCLOPS.params["sway"].linear_damping,
                     CYCLOPS.params["sway"].quadratic_damping)
    world = World([box("wall", [10, -20, -1], [11, 20, 10], friction=mu)])
    rows = []
    start = VehicleState(position=np.array([9.5, 0.0, 2.0]), velocity=np.array([0.2, 0.3, 0.0]))
    simulate(CYCLOPS, world, start, [press, 0, 0, 0, 0, 0], 6.0,
             every=lambda a, b, c: rows.append((b.time, b.velocity[1], c.last.touching)))
    t, v, touch = (np.array(r) for r in zip(*rows))
    k0 = int(np.argmax(touch)) + 1                           # the tick after the impact
    moving = v > 1e-3
    end = int(np.argmin(moving[k0:])) + k0                   # the slide stops
    assert end - k0 > 40 and np.all(touch[k0:end])
    ref = solve_ivp(lambda _, y: [(-k_v * y[0] - q_v * y[0] * abs(y[0]) - mu * press) / m_v],
                    (t[k0], t[end - 1]), [v[k0]], t_eval=t[k0:end], rtol=1e-10, atol=1e-12)
    # within the O(dt) of applying friction after each dynamics step (damping acts first): 0.3 % of v0
    assert np.allclose(v[k0:end], ref.y[0], atol=5e-4)
