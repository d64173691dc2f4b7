"""``hilsim render``: files written, their contents, and clear errors."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from hilsim.cli import main


def test_render_a_b_c_writes_frames_figure_and_report(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["render", "--at", "A,B,C", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "[1/3] A" in err and "[3/3] C" in err  # progress output
    fig = Image.open(out / "figure.png")
    assert fig.format == "PNG" and fig.width > fig.height
    faces = {}
    xs = {}
    for label in "ABC":
        rep = json.loads((out / label / "render.json").read_text())
        nb, ns = rep["sonar"]["n_beams"], rep["sonar"]["n_samples"]
        assert (nb, ns) == (96, 512)
        raw = np.fromfile(out / label / "sonar.raw", dtype=np.uint8)
        assert raw.size == nb * ns and raw.max() > 0
        assert Image.open(out / label / "sonar.png").format == "PNG"
        cam = Image.open(out / label / "camera.png")
        assert cam.size == tuple(rep["camera"]["size_px"]) == (640, 480)
        faces[label] = {k for k, v in rep["sonar"]["hit_counts"]["cuboid"].items() if k != "total" and v}
        # the camera sees the cuboid at every position (the paper puts it at the sonar's pose)
        assert rep["camera"]["pixel_counts"].get("cuboid", 0) > 0
        # the vehicle x written is the named position's (A, B, C approach the cuboid)
        xs[label] = rep["vehicle"]["position_m"][0]
    assert faces == {"A": {"south"}, "B": {"south", "up"}, "C": {"up"}}
    assert xs["A"] < xs["B"] < xs["C"]


def test_render_at_an_explicit_pose_and_paper_sampling(tmp_path):
    out = tmp_path / "o"
    assert main(["render", "--at=-1.33,0,1.5,0", "--paper-sampling", "--gain", "paper", "--out", str(out)]) == 0
    (folder,) = [p for p in out.iterdir() if p.is_dir()]
    rep = json.loads((folder / "render.json").read_text())
    assert rep["sonar"]["spread"] is False and rep["sonar"]["gain_mode"] == "paper"
    raw = np.fromfile(folder / "sonar.raw", dtype=np.uint8)
    assert raw.max() == 255  # paper gain: the brightest cell is white


@pytest.mark.parametrize("args,needle", [
    (["render", "--at", "Q"], "not a named position"),
    (["render", "no_such_scenario"], "not found"),
])
def test_render_errors_are_clear(tmp_path, capsys, args, needle):
    assert main(args + ["--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err


def test_python_dash_m_runs():
    proc = subprocess.run([sys.executable, "-m", "hilsim", "--version"], capture_output=True, text=True)
    assert proc.returncode == 0 and "hilsim" in proc.stdout
