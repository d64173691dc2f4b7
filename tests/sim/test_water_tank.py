"""The paper's water tank: at A only the cuboid's front face is ensonified, at B
front and top, at C only the top (paper section 4, Fig. 4).

The expectation is computed here independently of the simulator's ray
casting: rays over the sonar's aperture are intersected analytically with the
floor plane and the cuboid (slab method), using only the geometry read from
the scenario file and the sonar profile.
"""

from __future__ import annotations

import numpy as np
import pytest

from hilsim.resources import find_scenario
from hilsim.sim.geometry import rpy_to_matrix
from hilsim.sim.rig import build_sonar
from hilsim.sim.scenario import load_scenario
from hilsim.sim.state import VehicleState


@pytest.fixture(scope="module")
def tank():
    s = load_scenario(find_scenario("water_tank"))
    return s, s.build_world(), build_sonar(s, s.sensor("sonar"))


def analytic_face_hits(origin, rot, az_lim, el_lim, r_min, r_max, box_lo, box_hi, floor_z, n_az=96, n_el=400):
    """Count rays whose first hit in [r_min, r_max] is the box's south face / up face / the floor."""
    az = np.linspace(az_lim[0], az_lim[1], n_az)
    el = np.linspace(el_lim[0], el_lim[1], n_el)
    A, E = np.meshgrid(az, el, indexing="ij")
    d_s = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), -np.sin(E)], -1).reshape(-1, 3)
    d = d_s @ rot.T
    # floor plane z = floor_z (NED, below the sonar)
    t_floor = np.where(d[:, 2] > 0, (floor_z - origin[2]) / np.where(d[:, 2] > 0, d[:, 2], 1), np.inf)
    # slab method for the box
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (box_lo - origin) / d
        t2 = (box_hi - origin) / d
    tn = np.minimum(t1, t2)
    tf = np.maximum(t1, t2)
    t_enter = np.nanmax(tn, axis=1)
    t_exit = np.nanmin(tf, axis=1)
    entry_axis = np.nanargmax(tn, axis=1)
    box_hit = (t_enter <= t_exit) & (t_enter > 0)
    t_box = np.where(box_hit, t_enter, np.inf)
    first = np.minimum(t_box, t_floor)
    in_window = (first >= r_min) & (first <= r_max)
    on_box = in_window & (t_box < t_floor)
    south = on_box & (entry_axis == 0) & (d[:, 0] > 0)
    up = on_box & (entry_axis == 2) & (d[:, 2] > 0)
    other = on_box & ~south & ~up
    n = len(d)
    return {"south": south.sum() / n, "up": up.sum() / n, "other": other.sum() / n}


@pytest.mark.parametrize("label,expected", [("A", {"south"}), ("B", {"south", "up"}), ("C", {"up"})])
def test_positions_a_b_c(tank, label, expected):
    scenario, world, sonar = tank
    mount = scenario.sensor("sonar").mount
    p = scenario.positions[label]
    state = VehicleState(position=np.array(p.position), attitude=np.array([0.0, 0.0, p.yaw]))
    pose = state.pose @ mount
    frame = sonar.render(world, pose, sonar.settings.realism_off(), frame_index=0)

    cuboid = world.objects[world.object_index("cuboid")].mesh
    floor = world.objects[world.object_index("floor")].mesh
    prof = sonar.profile
    predicted = analytic_face_hits(
        pose.position, rpy_to_matrix(*pose.rpy()), prof.azimuth_limits, prof.elevation_limits,
        frame.range_min, frame.range_max, cuboid.bounds[0], cuboid.bounds[1], floor.bounds[1][2])
    assert {k for k, v in predicted.items() if v > 0} == expected, "scenario geometry no longer gives A/B/C"

    got = frame.hit_counts.get("cuboid", {})
    faces = {k for k, v in got.items() if k != "total" and v > 0}
    assert faces == expected
    # and in proportion: the share of rays on each face matches the analytic count
    for face in expected:
        share = got[face] / frame.n_rays
        assert share == pytest.approx(predicted[face], rel=0.05, abs=2e-3), face
    # the cuboid's echo shows in the image at the ranges the geometry predicts
    rng = np.linalg.norm(cuboid.vertices - pose.position, axis=1)
    assert frame.image[(frame.ranges > rng.min() - 0.05) & (frame.ranges < rng.max() + 0.05)].max() > 0
