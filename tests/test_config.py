"""Where data-file errors point (``Doc.line_of``) and which profile references are refused."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from hilsim.config import ConfigError, Doc, load_toml, resolve_inside
from hilsim.resources import check_profile_ref, data_path, find_profile

TEXT = """\
name = "t"
seed = 3

[vehicle]
profile = "cyclops"

[[sensors]]
name = "sonar"
profile = "didson_hf"

[[sensors]]
name = "camera"
profile = "tank_camera"

[[devices]]
name = "depth"
protocol = "modbus-keller"
port = 0

[[devices]]
name = "vesc_uart"
protocol = "vesc-uart"
path = "uart"

[devices.mapping]
"1" = 0

[materials.steel]
impedance = { value = 4.5e7, unit = "Pa*s/m", source = "x" }
"""


@pytest.fixture
def doc(tmp_path: Path) -> Doc:
    (tmp_path / "s.toml").write_text(TEXT)
    return load_toml(tmp_path / "s.toml")


def line(text: str, needle: str, after: str = "") -> int:
    start = text.index(after) if after else 0
    return text[:text.index(needle, start)].count("\n") + 1


@pytest.mark.parametrize("key, needle, after", [
    ("seed", "seed = 3", ""),
    ("vehicle", "[vehicle]", ""),
    ("vehicle.profile", 'profile = "cyclops"', ""),
    ("sensors.sonar.profile", 'profile = "didson_hf"', ""),
    ("sensors.camera.profile", 'profile = "tank_camera"', ""),
    ("sensors.1.profile", 'profile = "tank_camera"', ""),          # by index
    ("devices.vesc_uart.path", 'path = "uart"', ""),
    ("devices.vesc_uart.protocol", "protocol =", 'name = "vesc_uart"'),
    ("devices.depth", "[[devices]]", ""),                           # the entry itself
    ("devices.depth.path", "[[devices]]", ""),                      # a default: the entry's header
    ("devices.vesc_uart.mapping.1", '"1" = 0', ""),                 # a sub-table of the entry
    ("materials.steel.impedance.unit", "impedance =", ""),          # inside an inline table
])
def test_line_of_finds_the_key_in_its_table(doc, key, needle, after):
    assert doc.line_of(key) == line(TEXT, needle, after)


def test_an_error_names_file_line_and_key(doc):
    e = doc.error("devices.depth.port", "bad port")
    assert isinstance(e, ConfigError) and e.line == line(TEXT, "port = 0")
    assert str(e) == f"{doc.path}:{e.line}: [devices.depth.port]: bad port"


# ------------------------------------------------------------------ profile references

def test_plain_names_resolve_in_the_scenario_folder_then_devices(tmp_path):
    (tmp_path / "sonars").mkdir()
    own = tmp_path / "sonars" / "mysonar.toml"
    own.write_text("")
    assert find_profile("sonars", "mysonar", base=tmp_path) == own.resolve()
    assert find_profile("sonars", "sonars/mysonar.toml", base=tmp_path) == own.resolve()
    assert find_profile("sonars", "didson_hf", base=tmp_path) == data_path("devices", "sonars", "didson_hf.toml").resolve()
    assert find_profile("vehicles", "vehicles/cyclops") == data_path("devices", "vehicles", "cyclops.toml").resolve()


@pytest.mark.parametrize("ref, why, why_without_scenario", [
    ("../outside/cyclops", "leaves the scenario folder", "leaves devices/"),
    ("sub/../../cyclops", "leaves the scenario folder", "leaves devices/"),
    ("/etc/passwd", "is absolute", "is absolute"),
    ("", "expected a vehicle profile name", "expected a vehicle profile name"),
])
def test_references_that_leave_the_folder_are_refused(tmp_path, ref, why, why_without_scenario):
    base = tmp_path / "scn"
    base.mkdir()
    (tmp_path / "outside").mkdir()
    (tmp_path / "outside" / "cyclops.toml").write_text("")
    with pytest.raises(ValueError, match=why):
        find_profile("vehicles", ref, base=base)
    with pytest.raises(ValueError, match=why_without_scenario):  # devices/ bounds it too
        find_profile("vehicles", ref)


def test_a_symlink_out_of_the_scenario_folder_is_refused(tmp_path):
    base = tmp_path / "scn"
    (base / "sonars").mkdir(parents=True)
    (tmp_path / "elsewhere.toml").write_text("")
    os.symlink(tmp_path / "elsewhere.toml", base / "sonars" / "link.toml")
    with pytest.raises(ValueError, match="leaves the scenario folder"):
        find_profile("sonars", "link", base=base)
    assert resolve_inside(base, "sonars/link.toml") is None
    assert resolve_inside(base, "sonars/x.toml") == (base / "sonars" / "x.toml").resolve()


def test_with_a_doc_the_refusal_is_a_config_error_at_the_key(doc):
    with pytest.raises(ConfigError) as ei:
        check_profile_ref("sonars", "/abs/sonar", doc.path.parent, doc=doc, key="sensors.sonar.profile")
    assert ei.value.line == line(TEXT, 'profile = "didson_hf"') and ei.value.key == "sensors.sonar.profile"
    assert "is absolute" in str(ei.value)


@pytest.mark.parametrize("ref", ["../../outside/t200", "/etc/t200"])
def test_a_vehicle_profiles_thruster_reference_is_refused_at_its_line(tmp_path, ref):
    """A vehicle profile is data too: a thruster profile reference leaving its folder is refused with
    the vehicle file's line and key."""
    from hilsim.sim.vehicle import load_vehicle_profile

    text = data_path("devices", "vehicles", "cyclops.toml").read_text()
    lines = text.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.strip().startswith("profile =")
             and "[thrusters]" in "\n".join(lines[:k]))
    lines[i] = f'profile = "{ref}"'
    p = tmp_path / "myvehicle.toml"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError) as e:
        load_vehicle_profile(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}:{i + 1}: [thrusters.profile]"), msg
