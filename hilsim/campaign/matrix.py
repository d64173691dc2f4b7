"""The matrix of a campaign: its cases, and each case's copy of the scenario.

A case is one combination of the ``[matrix]`` lists (full product, or position
by position with ``zip = true``). Keys that change the scenario (a start pose,
a current, a timeline file, any dotted scenario key) are applied to a copy of
the scenario's folder written into the case's run folder, so mesh paths and
local profiles keep working and no two runs share a file.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import shutil
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from hilsim.campaign.spec import PLACEHOLDERS, Campaign, expand_command, find_in_scenario  # noqa: F401 (re-exported)



@dataclass(frozen=True)
class Case:
    """One run of a campaign.

    index: position in the matrix order; params: the matrix values of this case
    (key -> value as written); key: a stable hash of ``params`` (``--resume`` matches it);
    seed: the seed of the run (``seed`` in the matrix, else the campaign's or None).
    """

    index: int
    params: Mapping[str, Any]
    key: str
    seed: int | None
    overrides: Mapping[str, Any] = field(default_factory=dict)

    @property
    def id(self) -> str:
        return f"{self.index:04d}-{self.key}"

    def label(self) -> str:
        return " ".join(f"{k}={json.dumps(v, separators=(',', ':'))}" for k, v in self.params.items()) or "(base)"


def case_key(params: Mapping[str, Any]) -> str:
    return hashlib.sha1(json.dumps(params, sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:10]


def expand(c: Campaign) -> list[Case]:
    """The cases in order: the full product of the matrix lists (the first key slowest), or zipped."""
    keys = list(c.matrix)
    if not keys:
        combos: list[tuple[Any, ...]] = [()]
    elif c.zip:
        combos = list(zip(*(c.matrix[k] for k in keys)))
    else:
        combos = list(itertools.product(*(c.matrix[k] for k in keys)))
    out = []
    for i, combo in enumerate(combos):
        params = dict(zip(keys, combo))
        seed = params.get("seed", c.seed)
        over = {k: v for k, v in params.items() if k != "seed"}
        out.append(Case(i, params, case_key(params), seed, over))
    return out


def scenario_data(c: Campaign, case: Case) -> dict[str, Any] | None:
    """The scenario's data with the case's changes, or None when the case changes nothing."""
    if not case.overrides and not c.fixed:
        return None
    data = copy.deepcopy(dict(c.scenario_data))
    for k, v in list(c.fixed.items()) + [(k, v) for k, v in case.overrides.items()
                                         if k not in ("start", "current_m_s", "timeline")]:
        found = find_in_scenario(data, k)
        if isinstance(found, str):  # checked at load time; a [set] key can create what a matrix key names
            raise ValueError(found)
        table, last = found
        table[last] = copy.deepcopy(v)
    start = case.overrides.get("start")
    if start:
        veh = data.setdefault("vehicle", {})
        for k, v in start.items():
            veh[k] = list(v)
    timeline = list(data.get("timeline", []))
    cur = case.overrides.get("current_m_s")
    if cur is not None:
        timeline.insert(0, {"at_s": 0.0, "action": "current", "velocity_m_s": [float(x) for x in cur]})
    tfile = case.overrides.get("timeline")
    if tfile:
        with open(c.timelines[tfile], "rb") as f:
            timeline.extend(tomllib.load(f).get("timeline", []))
    if timeline:
        data["timeline"] = timeline
    return data


def write_scenario(c: Campaign, case: Case, run_dir: Path, force: bool = False) -> Path:
    """The scenario file this case runs: the original, or a changed copy in ``run_dir/scenario/``
    (``force``: a copy even when unchanged, to ship to a machine without the original)."""
    data = scenario_data(c, case)
    if data is None and not force:
        return c.scenario
    dest = run_dir / "scenario"
    src = c.scenario.parent
    skip = {run_dir.resolve()}

    def ignore(folder: str, names: list[str]) -> list[str]:
        return [n for n in names if n in ("out", "__pycache__", ".git") or (Path(folder) / n).resolve() in skip]

    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(src, dest, ignore=ignore, symlinks=False)
    target = dest / c.scenario.name
    if data is not None:
        target.write_bytes(dump_toml(data))
    return target


def dump_toml(data: Mapping[str, Any]) -> bytes:
    try:
        import tomli_w
    except ImportError:  # pragma: no cover - a dependency of hilsim
        sys.exit("hilsim campaign needs tomli-w (pip install tomli-w)")
    return tomli_w.dumps(dict(data)).encode()
