"""Render campaigns: labelled sonar frames at sampled poses, checked against the sonar and the world."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hilsim.campaign.labels import sonar_labels
from hilsim.campaign.results import read_table
from hilsim.campaign.runner import run_campaign
from hilsim.resources import find_scenario
from hilsim.sim.rig import build_sonar
from hilsim.sim.scenario import load_scenario
from hilsim.sim.state import VehicleState

N = 50
BOX_MIN, BOX_MAX = (-2.2, -0.5, 1.3), (-0.6, 0.5, 1.7)
CAMPAIGN = f"""name = "frames"
kind = "render"
scenario = "water_tank"
seed = 7

[render]
count = {N}
elevation_rays = 200
realism = false
chunk = 13

[render.poses]
mode = "box"
min_m = {list(BOX_MIN)}
max_m = {list(BOX_MAX)}
yaw_deg = [-25.0, 25.0]
"""


@pytest.fixture(scope="module")
def tank() -> tuple:
    sc = load_scenario(find_scenario("water_tank"))
    return sc, sc.build_world(), sc.sensor("sonar")


@pytest.mark.parametrize("where, spread", [((-1.75, 0.0, 1.5), True), ((-1.33, 0.0, 1.5), True),
                                           ((-0.83, 0.1, 1.4), True), ((-1.33, 0.0, 1.5), False)])
def test_labels_bin_the_echoes_as_the_sonar_does(tank: tuple, where: tuple, spread: bool) -> None:
    sc, world, mount = tank
    sonar = build_sonar(sc, mount)
    s = sonar.settings.replace(speckle=False, noise=False, beam_pattern=False, spread=spread)
    pose = VehicleState(position=np.array(where), attitude=np.zeros(3)).pose @ mount.mount
    frame = sonar.render(world, pose, s, frame_index=0)
    lab = sonar_labels(world, sonar, pose, s)
    # the summed echoes are the sonar's pre-gain intensity, cell by cell
    np.testing.assert_allclose(lab.intensity, frame.intensity, rtol=1e-5, atol=1e-9 * frame.intensity.max())  # float32 rays
    assert np.array_equal(lab.object >= 0, frame.intensity > 0)
    assert lab.hits == {k: v["total"] for k, v in frame.hit_counts.items()}
    # each label's material is its object's
    mats = {o.name: o.material.name for o in world.objects}
    on = lab.object >= 0
    names = np.array(lab.object_names)[lab.object[on]]
    assert all(np.array(lab.material_names)[lab.material[on]] == np.array([mats[n] for n in names]))
    # the cuboid stands on the floor: it hides part of the floor, and the hidden cells are beyond it
    if "cuboid" in lab.cells:
        assert lab.shadow.any()
        assert not (lab.shadow & on).any()
        cub = world.object_index("cuboid")
        for b in np.flatnonzero(lab.shadow.any(axis=0)):
            hit_rows = np.flatnonzero(lab.object[:, b] == cub)
            if hit_rows.size:
                assert np.flatnonzero(lab.shadow[:, b]).min() > hit_rows.min()


def test_a_render_campaign_of_50_poses_writes_50_labelled_frames(tmp_path: Path, tank: tuple) -> None:
    (tmp_path / "c.toml").write_text(CAMPAIGN)
    o = run_campaign(tmp_path / "c.toml", out=tmp_path / "out", workers=2)
    assert o.ok and o.table is not None and o.table.name.startswith("index.")
    rows = read_table(o.table)
    assert len(rows) == N and sorted(r["frame"] for r in rows) == list(range(N))
    assert (o.out / "report.html").is_file()
    sc, world, mount = tank
    sonar = build_sonar(sc, mount)
    s = sonar.settings.replace(elevation_rays=200, speckle=False, noise=False, beam_pattern=False)
    objects = world.object_names
    with_cuboid = 0
    for r in rows:
        pose = (r["x_m"], r["y_m"], r["z_m"])
        assert all(lo <= v <= hi for lo, v, hi in zip(BOX_MIN, pose, BOX_MAX)) and -25 <= r["yaw_deg"] <= 25
        npz = o.out / r["files.npz"]
        assert (o.out / r["files.png"]).is_file() and (o.out / r["files.labels_png"]).is_file()
        with np.load(npz) as z:
            label, shadow, intensity = z["label_object"], z["shadow"], z["intensity"]
            names, image = list(z["object_names"]), z["image"]
            np.testing.assert_allclose(z["vehicle_pose"], [*pose, r["roll_deg"], r["pitch_deg"], r["yaw_deg"]])
        assert names == objects and label.shape == image.shape == (s.n_samples, sonar.profile.n_beams)
        # the world's hit counts for the same pose, from the sonar's own render
        st = VehicleState(position=np.array(pose), attitude=np.radians([r["roll_deg"], r["pitch_deg"], r["yaw_deg"]]))
        frame = sonar.render(world, st.pose @ mount.mount, s, frame_index=0)
        world_hits = {k: v["total"] for k, v in frame.hit_counts.items()}
        index_hits = {k[5:]: int(v) for k, v in r.items() if k.startswith("hits.")}
        assert set(index_hits) == set(objects)   # every object has its column, 0 when not hit
        assert {k: v for k, v in index_hits.items() if v} == world_hits
        # the label mask: an echo cell is labelled, by an object the world says was hit
        assert np.array_equal(label >= 0, intensity > 0)
        labelled = {objects[i] for i in np.unique(label[label >= 0])}
        assert labelled <= set(world_hits)
        cells = {k[6:]: int(v) for k, v in r.items() if k.startswith("cells.")}
        assert cells == {name: int(np.count_nonzero(label == i)) for i, name in enumerate(objects)}
        assert not (shadow & (label >= 0)).any() and r["shadow_cells"] == int(shadow.sum())
        with_cuboid += "cuboid" in labelled
    assert with_cuboid >= 5   # the box is drawn around the cuboid: many frames see it


def test_resume_renders_only_the_missing_frames(tmp_path: Path) -> None:
    (tmp_path / "c.toml").write_text(CAMPAIGN.replace(f"count = {N}", "count = 6").replace("chunk = 13", "chunk = 2"))
    first = run_campaign(tmp_path / "c.toml", out=tmp_path / "out", workers=1)
    journal = first.out / "results.jsonl"
    lines = journal.read_text().splitlines()
    journal.write_text("\n".join(lines[:4]) + "\n")
    again = run_campaign(tmp_path / "c.toml", out=tmp_path / "out", workers=1, resume=True)
    assert again.ran == 1 and len(again.rows) == 6   # 2 frames missing: one chunk of 2
    assert sorted(r["frame"] for r in again.rows) == list(range(6))


def test_poses_along_a_path_in_a_box_and_listed() -> None:
    from hilsim.campaign.render import sample_poses
    from hilsim.campaign.spec import Poses

    path = Poses("path", waypoints_m=((0.0, 0.0, 1.0), (3.0, 0.0, 1.0), (3.0, 4.0, 1.0)))
    ps = sample_poses(path, 8, seed=1)   # 7 m long: a pose every metre, heading along the leg
    assert [p[0] for p in ps] == list(range(8))
    np.testing.assert_allclose([p[1:4] for p in ps], [(0, 0, 1), (1, 0, 1), (2, 0, 1), (3, 0, 1), (3, 1, 1),
                                                     (3, 2, 1), (3, 3, 1), (3, 4, 1)], atol=1e-12)
    assert [round(p[6]) for p in ps] == [0, 0, 0, 90, 90, 90, 90, 90]
    box = Poses("box", min_m=(-1.0, -2.0, 1.0), max_m=(1.0, 2.0, 1.5), yaw_deg=(-10.0, 10.0))
    a, b = sample_poses(box, 200, seed=3), sample_poses(box, 200, seed=3)
    assert a == b and a != sample_poses(box, 200, seed=4)   # drawn from the seed
    xyz = np.array([p[1:4] for p in a])
    assert (xyz.min(0) >= (-1, -2, 1)).all() and (xyz.max(0) <= (1, 2, 1.5)).all()
    assert np.ptp(xyz[:, 0]) > 1.5 and all(-10 <= p[6] <= 10 and p[4] == p[5] == 0 for p in a)
    listed = Poses("list", listed=((1.0, 2.0, 3.0, 0.0, 5.0, 45.0),))
    assert sample_poses(listed, 1, seed=0) == [(0, 1.0, 2.0, 3.0, 0.0, 5.0, 45.0)]


def test_a_render_campaign_with_the_camera_labels_its_pixels(tmp_path: Path, tank: tuple) -> None:
    (tmp_path / "c.toml").write_text("""name = "cam"
kind = "render"
scenario = "water_tank"
[render]
camera = true
elevation_rays = 50
[render.poses]
list = [{ position_m = [-1.33, 0.0, 1.5] }, { position_m = [-0.83, 0.2, 1.5], yaw_deg = 15.0 }]
""")
    o = run_campaign(tmp_path / "c.toml", out=tmp_path / "out", workers=1)
    rows = read_table(o.table)
    assert len(rows) == 2
    sc, world, _ = tank
    for r in rows:
        assert (o.out / r["files.camera_png"]).is_file()
        with np.load(o.out / r["files.npz"]) as z:
            obj, rgb = z["camera_object"], z["camera_rgb"]
        cub = world.object_index("cuboid")
        assert rgb.shape[:2] == obj.shape and (obj == cub).sum() > 100   # the cuboid is in view
        # a pixel labelled with the cuboid shows the cuboid's blue plastic more than the grey floor's
        assert rgb[obj == cub][:, 2].mean() > rgb[obj == world.object_index("floor")][:, 2].mean()


def test_each_cell_is_labelled_with_the_object_of_its_strongest_echo(tank: tuple) -> None:
    """The per-ray echo parts (whose sums the test above holds equal to the sonar's intensity), searched for
    each cell's strongest one in plain Python."""
    from hilsim.campaign import labels as L

    sc, world, mount = tank
    sonar = build_sonar(sc, mount)
    s = sonar.settings.replace(elevation_rays=40, speckle=False, noise=False, beam_pattern=False)
    pose = VehicleState(position=np.array([-1.33, 0.0, 1.5]), attitude=np.zeros(3)).pose @ mount.mount
    lab = sonar_labels(world, sonar, pose, s)
    dirs_s, ddphi_s, beam, dphi = L.ray_fan(sonar, s)
    rot = np.asarray(pose.rotation)
    dirs = dirs_s @ rot.T
    hits = world.cast(np.tile(pose.position, (len(dirs), 1)), dirs, t_min=s.range_min, t_max=s.range_max)
    hit = np.flatnonzero(hits.tri >= 0)
    ray, k, share = L._shares(sonar, s, world, rot, dirs_s[hit], ddphi_s[hit], dphi, hits.t[hit], hits.obj[hit],
                              hits.normal[hit])
    best: dict[tuple[int, int], tuple[float, int]] = {}
    for r_, k_, e in zip(ray.tolist(), k.tolist(), share.tolist()):
        cell = (k_, int(beam[hit[r_]]))
        obj = int(hits.obj[hit[r_]])
        if cell not in best or e > best[cell][0]:
            best[cell] = (e, obj)
    expect = np.full(lab.object.shape, -1)
    for (row, col), (_, obj) in best.items():
        expect[row, col] = obj
    assert len(set(best.values())) > 100 and {o for _, o in best.values()} == {world.object_index("floor"), world.object_index("cuboid")}
    assert np.array_equal(lab.object, expect)
