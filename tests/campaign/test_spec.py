"""Campaign files: parsing, the matrix, the scenario copies, and errors naming file, line and key."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from hilsim.campaign.matrix import expand, expand_command, scenario_data, write_scenario
from hilsim.campaign.spec import load_campaign
from hilsim.config import ConfigError
from hilsim.sim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "scenarios" / "water_tank" / "campaigns"

BASE = """name = "t"
scenario = "water_tank"
time_scale = 4.0
duration_s = 30.0

[stack]
command = "{python} -c pass {endpoints} {out}"
timeout_s = 5.0
"""


def write(tmp: Path, text: str, name: str = "c.toml") -> Path:
    p = tmp / name
    p.write_text(text)
    return p


def error_of(path: Path) -> ConfigError:
    with pytest.raises(ConfigError) as e:
        load_campaign(path)
    return e.value


def line_of(path: Path, needle: str) -> int:
    return next(i for i, ln in enumerate(path.read_text().splitlines(), 1) if needle in ln)


@pytest.mark.parametrize("name", ["nightly.toml", "faults.toml", "render.toml"])
def test_the_example_campaigns_load(name: str) -> None:
    c = load_campaign(EXAMPLES / name)
    assert c.scenario == (ROOT / "scenarios" / "water_tank" / "scenario.toml").resolve()
    assert expand(c)


def test_the_matrix_is_a_product_first_key_slowest_or_zipped(tmp_path: Path) -> None:
    p = write(tmp_path, BASE + '[matrix]\nseed = [1, 2, 3]\ncurrent_m_s = [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]\n')
    cases = expand(load_campaign(p))
    assert [(k.seed, k.params["current_m_s"][0]) for k in cases] == [
        (1, 0.0), (1, 0.1), (2, 0.0), (2, 0.1), (3, 0.0), (3, 0.1)]
    assert len({k.key for k in cases}) == 6 and len({k.id for k in cases}) == 6
    z = write(tmp_path, BASE + '[matrix]\nzip = true\nseed = [1, 2]\n"vehicle.position_m" = [[-2.0, 0.0, 1.5], '
                               '[-1.0, 0.0, 1.5]]\n', "z.toml")
    assert [(k.seed, k.params["vehicle.position_m"][0]) for k in expand(load_campaign(z))] == [(1, -2.0), (2, -1.0)]
    # the key depends on the parameters only: the same case has the same key in another file
    assert expand(load_campaign(p))[0].key == cases[0].key


def test_a_case_changes_a_copy_of_the_scenario_that_the_loader_accepts(tmp_path: Path) -> None:
    tl = write(tmp_path, '[[timeline]]\nat_s = 2.0\naction = "fault"\ntarget = "thruster:front_left"\nfault = "fail"\n',
               "fail.toml")
    p = write(tmp_path, BASE + f'''[set]
"water.sound_speed_m_s" = 1490.0
[matrix]
zip = true
"objects.cuboid.position_m" = [[1.0, 0.5, 2.85]]
"sensors.sonar.profile" = ["didson_lf"]
start = [{{ position_m = [-2.5, 0.5, 1.4], orientation_deg = [0.0, 0.0, 10.0] }}]
current_m_s = [[0.05, -0.02, 0.0]]
timeline = ["{tl.name}"]
''')
    c = load_campaign(p)
    case = expand(c)[0]
    run = tmp_path / "run"
    run.mkdir()
    path = write_scenario(c, case, run)
    assert path.parent == run / "scenario" and path.name == "scenario.toml"
    data = tomllib.loads(path.read_text())
    cuboid = next(o for o in data["objects"] if o["name"] == "cuboid")
    assert cuboid["position_m"] == [1.0, 0.5, 2.85]
    assert next(s for s in data["sensors"] if s["name"] == "sonar")["profile"] == "didson_lf"
    assert data["water"]["sound_speed_m_s"] == 1490.0
    assert data["vehicle"]["position_m"] == [-2.5, 0.5, 1.4]
    assert data["timeline"][0] == {"at_s": 0.0, "action": "current", "velocity_m_s": [0.05, -0.02, 0.0]}
    assert data["timeline"][-1]["target"] == "thruster:front_left"
    s = load_scenario(path)  # the copy is a valid scenario, its profiles and folder found
    assert s.object_placement("cuboid").position.tolist() == [1.0, 0.5, 2.85]
    assert s.vehicle is not None and s.vehicle.position == (-2.5, 0.5, 1.4)
    # the original is untouched; a case that changes nothing runs the original file
    orig = tomllib.loads(c.scenario.read_text())
    assert next(o for o in orig["objects"] if o["name"] == "cuboid")["position_m"] == [0.275, 0.0, 2.85]
    plain = load_campaign(write(tmp_path, BASE + "[matrix]\nseed = [4]\n", "plain.toml"))
    assert scenario_data(plain, expand(plain)[0]) is None
    assert write_scenario(plain, expand(plain)[0], run) == plain.scenario


def test_placeholders_are_filled_per_word_without_a_shell() -> None:
    words = expand_command("{python} 'my stack.py' {endpoints} --out={out} --seed {seed}; rm -rf /",
                           {"python": "/py", "endpoints": "/r/e p.json", "out": "/r/o", "seed": "3"})
    assert words == ["/py", "my stack.py", "/r/e p.json", "--out=/r/o", "--seed", "3;", "rm", "-rf", "/"]
    with pytest.raises(ValueError, match=r"unknown placeholder \{outdir\}"):
        expand_command("x {outdir}", {"out": "o"})


@pytest.mark.parametrize("extra, needle, key, words", [
    ('time_scal = 4.0\n', "time_scal", "time_scal", "did you mean 'time_scale'"),
    ('[matrix]\n"objects.box.position_m" = [[0.0, 0.0, 0.0]]\n', "objects.box", "matrix.objects.box.position_m",
     "no entry 'box' in 'objects'"),
    ('[matrix]\n"vehicle.nope.x" = [1]\n', "vehicle.nope", "matrix.vehicle.nope.x", "the scenario has no 'vehicle.nope'"),
    ('[matrix]\nspeed = [1]\n', "speed", "matrix.speed", "a matrix key is one of"),
    ('[matrix]\nseed = [1, -2]\n', "seed =", "matrix.seed", "integers >= 0"),
    ('[matrix]\nseed = []\n', "seed =", "matrix.seed", "non-empty list"),
    ('[matrix]\ncurrent_m_s = [[0.1, 0.0]]\n', "current_m_s", "matrix.current_m_s", "[north, east, down]"),
    ('[matrix]\nstart = [{ position = [0.0, 0.0, 1.0] }]\n', "start", "matrix.start", "position_m"),
    ('[matrix]\nzip = true\nseed = [1, 2]\ncurrent_m_s = [[0.0, 0.0, 0.0]]\n', "zip", "matrix.zip", "one length"),
    ('[matrix]\ntimeline = ["nowhere.toml"]\n', "timeline", "matrix.timeline", "not found"),
    ('[pass]\nok = "exit_code == 0"\nbad = "exit_code == 0 or true"\n', "bad =", "pass.bad", "unexpected 'or'"),
    ('[pass]\nbad = "__import__(\'os\')"\n', "bad =", "pass.bad", "unexpected"),
    ('[metrics]\ndepth_target = 1.8\n', "depth_target", "metrics.depth_target", "did you mean 'depth_target_m'"),
])
def test_mistakes_name_file_line_and_key(tmp_path: Path, extra: str, needle: str, key: str, words: str) -> None:
    if extra.startswith("time_scal"):
        p = write(tmp_path, extra + BASE)
    else:
        p = write(tmp_path, BASE + extra)
    e = error_of(p)
    assert e.path == p and e.key == key and e.line == line_of(p, needle), str(e)
    assert words in str(e), str(e)
    assert str(e).startswith(f"{p}:{e.line}: [{key}]")


def test_more_mistakes(tmp_path: Path) -> None:
    e = error_of(write(tmp_path, BASE.replace("{out}", "{outdir}")))
    assert e.key == "stack.command" and "unknown placeholder {outdir}" in str(e)
    e = error_of(write(tmp_path, 'scenario = "no_such_place"\n[stack]\ncommand = "x"\n'))
    assert e.key == "scenario" and e.line == 1 and "not found" in str(e)
    e = error_of(write(tmp_path, 'scenario = "water_tank"\n'))
    assert e.key == "stack" and "needs [stack]" in str(e)
    e = error_of(write(tmp_path, 'kind = "renders"\n'))
    assert e.key == "kind" and "one of mission, render" in str(e)
    e = error_of(write(tmp_path, 'kind = "render"\n[render]\ncount = 5\n[render.poses]\nmode = "box"\n'
                                 'min_m = [0.0, 0.0, 1.0]\nmax_m = [1.0, -1.0, 2.0]\n'))
    assert e.key == "render.poses.max_m" and e.line == 7
    # a timeline file's own mistakes name that file and its line
    bad = write(tmp_path, '[[timeline]]\nat_s = 1.0\naction = "falut"\n', "bad_timeline.toml")
    e = error_of(write(tmp_path, BASE + '[matrix]\ntimeline = ["bad_timeline.toml"]\n'))
    assert e.path == bad and e.line == 3 and "did you mean 'fault'" in str(e)
    p = write(tmp_path, BASE + "[matrix\nseed = [1]\n")
    e = error_of(p)
    assert "not valid TOML" in str(e) and e.line == line_of(p, "[matrix")


def test_the_command_line_prints_the_error_without_a_traceback(tmp_path: Path) -> None:
    p = write(tmp_path, BASE + '[matrix]\n"objects.box.position_m" = [[0.0, 0.0, 0.0]]\n')
    for cmd in (["hilsim", "campaign"], ["hilsim.campaign"]):
        r = subprocess.run([sys.executable, "-m", *cmd, str(p), "--out", str(tmp_path / "out")],
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 2, r.stderr
        assert f"{p}:{line_of(p, 'objects.box')}: [matrix.objects.box.position_m]" in r.stderr
        assert "Traceback" not in r.stderr
