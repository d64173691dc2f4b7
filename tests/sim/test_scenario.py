"""Scenario files: loading, mesh formats, materials by name, and clear errors."""

from __future__ import annotations

import logging
import os
import textwrap
from pathlib import Path

import numpy as np
import pytest
import trimesh

from hilsim.config import ConfigError
from hilsim.resources import find_scenario
from hilsim.sim.scenario import load_scenario

BASE = """
name = "t"
[materials.steel]
impedance_Pa_s_m = 4.5e7
color = [0.8, 0.8, 0.8]
[materials.rock]
impedance_Pa_s_m = 7.0e6
"""


def write(folder: Path, text: str) -> Path:
    p = folder / "scenario.toml"
    p.write_text(textwrap.dedent(text))
    return p


def test_default_scenario_loads_with_the_paper_values():
    s = load_scenario(find_scenario(None))
    assert s.name == "water_tank"
    assert s.water.impedance == pytest.approx(1.5e6)
    w = s.build_world()
    mats = {o.name: o.material for o in w.objects}
    assert mats["floor"].impedance == pytest.approx(8.0e6)
    assert mats["cuboid"].impedance == pytest.approx(3.5e6)
    assert {"A", "B", "C"} <= set(s.positions)
    sonar = s.sensor("sonar")
    # tilted 45 deg down: boresight has equal forward and downward components
    bore = sonar.mount.apply_dirs(np.array([[1.0, 0, 0]]))[0]
    assert bore[0] == pytest.approx(np.sqrt(0.5)) and bore[2] == pytest.approx(np.sqrt(0.5))
    assert not s.warnings


def test_primitives_are_placed_in_ned(tmp_path):
    write(tmp_path, BASE + """
    [[objects]]
    name = "b"
    primitive = "box"
    material = "steel"
    size_m = [2, 1, 0.5]
    position_m = [10, -3, 4]
    orientation_deg = [0, 0, 90]
    [[objects]]
    name = "ground"
    primitive = "terrain"
    material = "rock"
    size_m = [10, 10]
    resolution_m = 0.5
    relief_m = 0.3
    seed = 4
    position_m = [0, 0, 20]
    """)
    s = load_scenario(tmp_path / "scenario.toml")
    box = s.objects[0].mesh
    # yawed 90 deg: the 2 m side now lies along east (y)
    assert np.allclose(box.bounds, [[9.5, -4.0, 3.75], [10.5, -2.0, 4.25]])
    ground = s.objects[1].mesh
    assert abs(ground.vertices[:, 2].mean() - 20.0) < 0.3
    # terrain faces point up (-z in NED)
    assert np.mean(ground.face_normals[:, 2] < 0) > 0.99
    # seeded: the same seed gives the same terrain
    again = load_scenario(tmp_path / "scenario.toml").objects[1].mesh
    assert np.array_equal(ground.vertices, again.vertices)


def _gltf_scene() -> trimesh.Scene:
    hull = trimesh.creation.box((1.0, 1.0, 1.0))
    hull.visual = trimesh.visual.TextureVisuals(material=trimesh.visual.material.PBRMaterial(name="HullPaint"))
    rock = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    rock.visual = trimesh.visual.TextureVisuals(material=trimesh.visual.material.PBRMaterial(name="Stone"))
    sc = trimesh.Scene()
    # glTF is Y-up: this node sits 2 m above the origin and 3 m along +x
    sc.add_geometry(hull, node_name="Wreck", geom_name="WreckMesh",
                    transform=trimesh.transformations.translation_matrix([3.0, 2.0, 0.0]))
    sc.add_geometry(rock, node_name="Boulder", geom_name="BoulderMesh")
    return sc


def test_gltf_materials_matched_by_node_or_material_name(tmp_path):
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "site.glb").write_bytes(_gltf_scene().export(file_type="glb"))
    write(tmp_path, BASE + """
    [[objects]]
    name = "site"
    mesh = "meshes/site.glb"
    position_m = [0, 0, 10]
    materials = { Wreck = "steel", Stone = "rock" }
    """)
    s = load_scenario(tmp_path / "scenario.toml")
    by_mat = {o.material.name: o for o in s.objects}
    assert set(by_mat) == {"steel", "rock"}
    wreck = by_mat["steel"].mesh
    # Y-up +2 m becomes NED z = 10 - 2 = 8; x stays x
    assert np.allclose(wreck.centroid, [3.0, 0.0, 8.0], atol=1e-9)
    # a mirroring axis change must not turn normals inward
    assert wreck.is_watertight and wreck.volume > 0


def test_blender_style_obj_with_mtl(tmp_path):
    # What Blender's OBJ exporter writes: objects, usemtl per material, an .mtl beside it.
    (tmp_path / "scene.mtl").write_text("newmtl Concrete\nKd 0.5 0.5 0.5\nnewmtl Plastic\nKd 0.1 0.2 0.9\n")
    v = trimesh.creation.box((1, 1, 1)).vertices
    f = trimesh.creation.box((1, 1, 1)).faces
    lines = ["mtllib scene.mtl"]
    for k, (name, mat, dx) in enumerate([("Floor", "Concrete", 0.0), ("Basket", "Plastic", 5.0)]):
        lines.append(f"o {name}")
        lines += [f"v {x + dx} {y} {z}" for x, y, z in v]
        lines.append(f"usemtl {mat}")
        lines += [f"f {a + 1 + 8 * k} {b + 1 + 8 * k} {c + 1 + 8 * k}" for a, b, c in f]
    (tmp_path / "scene.obj").write_text("\n".join(lines) + "\n")
    write(tmp_path, BASE + """
    [[objects]]
    name = "tank"
    mesh = "scene.obj"
    materials = { Concrete = "rock", Plastic = "steel" }
    """)
    s = load_scenario(tmp_path / "scenario.toml")
    by_mat = {o.material.name: o.mesh for o in s.objects}
    assert set(by_mat) == {"rock", "steel"}
    # Z-up OBJ: x stays, the basket sits 5 m north
    assert by_mat["steel"].centroid[0] == pytest.approx(5.0)
    assert by_mat["rock"].centroid[0] == pytest.approx(0.0)


@pytest.mark.parametrize("fmt", ["stl", "ply"])
def test_single_material_mesh_formats(tmp_path, fmt):
    trimesh.creation.cylinder(radius=0.3, height=1.0).export(tmp_path / f"pipe.{fmt}")
    write(tmp_path, BASE + f"""
    [[objects]]
    name = "pipe"
    mesh = "pipe.{fmt}"
    material = "steel"
    scale = 2.0
    """)
    s = load_scenario(tmp_path / "scenario.toml")
    ext = s.objects[0].mesh.extents
    assert sorted(ext) == pytest.approx(sorted([1.2, 1.2, 2.0]), rel=1e-6)


# ---- broken scenarios give clear errors ----

def error_of(tmp_path: Path, text: str) -> ConfigError:
    write(tmp_path, text)
    with pytest.raises(ConfigError) as ei:
        load_scenario(tmp_path / "scenario.toml")
    return ei.value


def test_unknown_key_suggests_the_closest(tmp_path):
    e = error_of(tmp_path, BASE + """
    [[objects]]
    name = "b"
    primitive = "box"
    material = "steel"
    size_m = [1, 1, 1]
    positon_m = [0, 0, 1]
    """)
    msg = str(e)
    assert "positon_m" in msg and "did you mean 'position_m'" in msg
    assert "scenario.toml" in msg
    # the line of the typo is named
    lines = (tmp_path / "scenario.toml").read_text().splitlines()
    assert e.line is not None and "positon_m" in lines[e.line - 1]


def test_unknown_top_level_table(tmp_path):
    e = error_of(tmp_path, BASE + "\n[vehicel]\nprofile = 'cyclops'\n")
    assert "did you mean 'vehicle'" in str(e)


def test_unknown_material_suggests(tmp_path):
    e = error_of(tmp_path, BASE + """
    [[objects]]
    name = "b"
    primitive = "box"
    material = "steal"
    size_m = [1, 1, 1]
    """)
    assert "unknown material 'steal'" in str(e) and "did you mean 'steel'" in str(e)


def test_syntax_error_names_the_line(tmp_path):
    e = error_of(tmp_path, 'name = "x"\n[water]\nimpedance_Pa_s_m = = 3\n')
    assert e.line == 3 and "not valid TOML" in str(e)


def test_missing_mesh_file(tmp_path):
    e = error_of(tmp_path, BASE + """
    [[objects]]
    name = "m"
    mesh = "nothere.stl"
    material = "steel"
    """)
    assert "not found" in str(e) and "nothere.stl" in str(e) and e.key == "objects.m.mesh"


@pytest.mark.parametrize("path", ["../outside.stl", "/etc/passwd", "sub/../../outside.stl"])
def test_mesh_paths_that_leave_the_folder_are_refused(tmp_path, path):
    inner = tmp_path / "scn"
    inner.mkdir()
    trimesh.creation.box().export(tmp_path / "outside.stl")
    e = error_of(inner, BASE + f"""
    [[objects]]
    name = "m"
    mesh = "{path}"
    material = "steel"
    """)
    assert "leaves the scenario folder" in str(e) or "absolute" in str(e)


def test_symlink_out_of_the_folder_is_refused(tmp_path):
    inner = tmp_path / "scn"
    inner.mkdir()
    trimesh.creation.box().export(tmp_path / "outside.stl")
    os.symlink(tmp_path / "outside.stl", inner / "link.stl")
    e = error_of(inner, BASE + """
    [[objects]]
    name = "m"
    mesh = "link.stl"
    material = "steel"
    """)
    assert "leaves the scenario folder" in str(e)


def test_non_watertight_mesh_is_a_warning(tmp_path, caplog):
    open_box = trimesh.creation.box()
    open_box.update_faces(np.arange(len(open_box.faces)) > 1)  # drop two faces: a hole
    open_box.export(tmp_path / "open.stl")
    write(tmp_path, BASE + """
    [[objects]]
    name = "crate"
    mesh = "open.stl"
    material = "steel"
    """)
    with caplog.at_level(logging.WARNING):
        s = load_scenario(tmp_path / "scenario.toml")
    assert len(s.warnings) == 1 and "not watertight" in s.warnings[0] and "crate" in s.warnings[0]
    assert any("not watertight" in r.message for r in caplog.records)


def test_bad_values_are_refused(tmp_path):
    e = error_of(tmp_path, BASE + """
    [[objects]]
    name = "b"
    primitive = "box"
    material = "steel"
    size_m = [1, -1, 1]
    """)
    assert "sizes must be > 0" in str(e)
    e = error_of(tmp_path, BASE.replace("color = [0.8, 0.8, 0.8]", "color = [2, 0, 0]"))
    assert "colour" in str(e) and "materials.steel.color" in str(e)
    one_box = "\n[[objects]]\nname='b'\nprimitive='box'\nmaterial='steel'\nsize_m=[1,1,1]\n"
    e = error_of(tmp_path, BASE + one_box + "\n[[sensors]]\nname='s'\nkind='lidar'\nprofile='x'\n")
    assert "unknown sensor kind 'lidar'" in str(e)


def test_no_objects_is_an_error(tmp_path):
    e = error_of(tmp_path, BASE)
    assert "no objects" in str(e)
