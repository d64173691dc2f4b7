"""The wheel carries the data folders: an installed hilsim renders the default scenario."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_wheel_installs_into_a_fresh_venv_and_renders(tmp_path):
    dist = tmp_path / "dist"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", str(dist), str(ROOT)],
                   check=True, timeout=300)
    wheels = list(dist.glob("hilsim-*.whl"))
    assert len(wheels) == 1
    names = zipfile.ZipFile(wheels[0]).namelist()
    assert "hilsim/_data/scenarios/water_tank/scenario.toml" in names
    assert "hilsim/_data/devices/sonars/didson_hf.toml" in names

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    subprocess.run([str(py), "-m", "pip", "install", "--quiet", "--no-deps", "--no-index", str(wheels[0])],
                   check=True, timeout=120)
    # The dependencies (numpy, embreex...) come from the test environment's site-packages,
    # added as a plain path: .pth files there (our own editable install) are not processed.
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          check=True, capture_output=True, text=True).stdout.strip()
    Path(site, "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")

    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "HILSIM_DATA")}
    where = subprocess.run([str(py), "-c", "import hilsim.resources as r; print(r.data_root())"],
                           cwd=work, env=env, check=True, capture_output=True, text=True).stdout.strip()
    assert where.startswith(str(venv)), f"hilsim data found outside the installed wheel: {where}"
    out = work / "out"
    proc = subprocess.run([str(venv / "bin" / "hilsim"), "render", "--at", "A", "--out", str(out)],
                          cwd=work, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    report = json.loads((out / "A" / "render.json").read_text())
    assert report["scenario"]["name"] == "water_tank"
    assert (out / "A" / "sonar.png").stat().st_size > 1000
    assert (out / "A" / "camera.png").stat().st_size > 1000
