"""Campaign files (``CAMPAIGN.toml``, format in scenarios/CAMPAIGNS.md): parsing and validation.

Errors are :class:`~hilsim.config.ConfigError` naming the campaign file, the
line and the key, as the scenario loader's do; a timeline file named in the
matrix is checked with the scenario's own timeline parser (its errors name
that file).
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from hilsim.campaign import criteria
from hilsim.config import ConfigError, Doc, check_keys, load_toml, number, vector
from hilsim.resources import find_scenario

KINDS = ("mission", "render")
_TOP = ("name", "description", "kind", "scenario", "time_scale", "fast", "duration_s", "seed", "stack",
        "matrix", "pass", "metrics", "set", "render")
_STACK = ("command", "summary", "timeout_s", "startup_timeout_s", "cpus", "env")
_METRICS = ("depth_target_m", "depth_from_s", "depth_last_s")
_RENDER = ("sonar", "camera", "count", "elevation_rays", "realism", "png", "poses", "chunk")
_POSES = ("mode", "min_m", "max_m", "yaw_deg", "waypoints_m", "list", "pitch_deg", "roll_deg")
_START = ("position_m", "orientation_deg")
SPECIAL_MATRIX = ("seed", "start", "current_m_s", "timeline")
PLACEHOLDERS = ("endpoints", "out", "seed", "run", "python", "campaign_dir", "scenario", "case")
_PLACEHOLDER = re.compile(r"\{([A-Za-z_]*)\}")
MAX_CASES = 100_000


@dataclass(frozen=True)
class Stack:
    command: str
    summary: str = "{out}/summary.json"
    timeout_s: float = 600.0
    startup_timeout_s: float = 60.0
    cpus: float = 2.0
    env: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class Poses:
    """How a render campaign samples vehicle poses (NED [m], angles [deg])."""

    mode: str                                        # box | path | list
    min_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    max_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_deg: tuple[float, float] = (0.0, 0.0)        # box: uniform in [lo, hi]; path: None -> along the path
    pitch_deg: tuple[float, float] = (0.0, 0.0)
    roll_deg: tuple[float, float] = (0.0, 0.0)
    waypoints_m: tuple[tuple[float, float, float], ...] = ()
    path_yaw: bool = True                            # path: heading follows the path (no yaw_deg given)
    listed: tuple[tuple[float, ...], ...] = ()       # list: (x, y, z, roll, pitch, yaw)


@dataclass(frozen=True)
class RenderSpec:
    sonar: str = "sonar"
    camera: str | None = None
    count: int = 10
    elevation_rays: int | None = None
    realism: bool = True          # keep the profile's speckle/noise/beam pattern in the images
    png: bool = True
    chunk: int = 10               # poses per task
    poses: Poses = Poses("list")


@dataclass(frozen=True)
class Campaign:
    path: Path
    doc: Doc
    name: str
    kind: str
    scenario: Path                                   # the scenario's TOML file
    scenario_data: Mapping[str, Any]
    time_scale: float
    fast: bool
    duration_s: float | None
    seed: int | None
    stack: Stack | None
    matrix: dict[str, list[Any]]
    zip: bool
    criteria: list[criteria.Criterion]
    metrics: Mapping[str, float]
    fixed: dict[str, Any]                            # [set]: dotted scenario keys for every case
    timelines: dict[str, Path]                       # timeline file as written -> resolved path
    render: RenderSpec | None

    @property
    def folder(self) -> Path:
        return self.path.parent


def key_line(doc: Doc, section: str, key: str) -> int | None:
    """Line of ``key`` inside ``[section]`` (the key may be quoted and hold dots)."""
    lines = doc.text.splitlines()
    inside = False
    pat = re.compile(r"^\s*(?:\"" + re.escape(key) + r"\"|'" + re.escape(key) + r"'|" + re.escape(key) + r")\s*=")
    for i, ln in enumerate(lines, 1):
        s = ln.strip()
        if s.startswith("["):
            inside = s.strip("[]").strip() == section
            continue
        if inside and pat.match(ln):
            return i
    return doc.line_of(section)


def _err(doc: Doc, section: str, key: str, msg: str) -> ConfigError:
    return ConfigError(doc.path, f"{section}.{key}", msg, key_line(doc, section, key))


def _table(doc: Doc, key: str) -> Mapping[str, Any]:
    v = doc.data.get(key, {})
    if not isinstance(v, Mapping):
        raise doc.error(key, f"expected a table [{key}]")
    return v


def _str(doc: Doc, t: Mapping[str, Any], key: str, where: str, default: str | None = None) -> str:
    if key not in t:
        if default is None:
            raise doc.error(where or key, f"missing required key {key!r}")
        return default
    v = t[key]
    if not isinstance(v, str) or not v.strip():
        raise doc.error(f"{where}.{key}" if where else key, f"expected a non-empty string, got {v!r}")
    return v


def find_in_scenario(data: Mapping[str, Any], dotted: str) -> tuple[Any, str | int] | str:
    """(container, last key) of a dotted scenario key, or a message saying which part is missing.

    An entry of an array of tables (``objects``, ``sensors``, ``devices``) is named by its
    ``name`` or its index: ``objects.cuboid.position_m``, ``sensors.sonar.profile``."""
    parts = dotted.split(".")
    cur: Any = data
    for i, part in enumerate(parts[:-1]):
        where = ".".join(parts[:i + 1])
        if isinstance(cur, Mapping):
            if part not in cur:
                return f"the scenario has no {where!r} (keys there: {', '.join(map(str, cur)) or 'none'})"
            cur = cur[part]
        elif isinstance(cur, list):
            hit = [e for e in cur if isinstance(e, Mapping) and e.get("name") == part]
            if not hit and part.isdigit() and int(part) < len(cur):
                hit = [cur[int(part)]]
            if not hit:
                names = [str(e.get("name")) for e in cur if isinstance(e, Mapping)]
                return f"no entry {part!r} in {'.'.join(parts[:i])!r} (entries: {', '.join(names)})"
            cur = hit[0]
        else:
            return f"{'.'.join(parts[:i])!r} is a value, not a table"
    last = parts[-1]
    if isinstance(cur, list):
        return f"{dotted!r} names a list of tables; name one entry"
    if not isinstance(cur, Mapping):
        return f"{'.'.join(parts[:-1])!r} is a value, not a table"
    return cur, last


def _check_dotted(doc: Doc, scen: Mapping[str, Any], section: str, key: str) -> None:
    if not re.fullmatch(r"[A-Za-z_][\w\-]*(\.[\w\-]+)+", key):
        raise _err(doc, section, key, f"unknown key {key!r}: a matrix key is one of {', '.join(SPECIAL_MATRIX)} "
                                      "or a dotted scenario key such as \"objects.cuboid.position_m\"")
    found = find_in_scenario(scen, key)
    if isinstance(found, str):
        raise _err(doc, section, key, found)


def _poses(doc: Doc, t: Mapping[str, Any], count: int) -> Poses:
    w = "render.poses"
    check_keys(doc, t, _POSES, w)
    mode = t.get("mode", "list" if "list" in t else "path" if "waypoints_m" in t else "box")
    if mode not in ("box", "path", "list"):
        raise doc.error(f"{w}.mode", f"unknown mode {mode!r}; one of box, path, list")

    def span(key: str) -> tuple[float, float]:
        if key not in t:
            return (0.0, 0.0)
        v = t[key]
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return (float(v), float(v))
        lo, hi = vector(doc, t, key, 2, w)
        if lo > hi:
            raise doc.error(f"{w}.{key}", f"[lo, hi] with lo <= hi, got {[lo, hi]}")
        return lo, hi

    if mode == "box":
        lo, hi = vector(doc, t, "min_m", 3, w), vector(doc, t, "max_m", 3, w)
        if any(a > b for a, b in zip(lo, hi)):
            raise doc.error(f"{w}.max_m", f"max_m {list(hi)} is below min_m {list(lo)} somewhere")
        return Poses("box", lo, hi, span("yaw_deg"), span("pitch_deg"), span("roll_deg"))  # type: ignore[arg-type]
    if mode == "path":
        raw = t.get("waypoints_m")
        if not isinstance(raw, list) or len(raw) < 2:
            raise doc.error(f"{w}.waypoints_m", "a path needs at least 2 waypoints [[x, y, z], ...]")
        wps = tuple(vector(doc, {"p": p}, "p", 3, f"{w}.waypoints_m") for p in raw)
        return Poses("path", waypoints_m=wps, yaw_deg=span("yaw_deg"), path_yaw="yaw_deg" not in t,  # type: ignore[arg-type]
                     pitch_deg=span("pitch_deg"), roll_deg=span("roll_deg"))
    raw = t.get("list")
    if not isinstance(raw, list) or not raw:
        raise doc.error(f"{w}.list", "a list of poses: [{ position_m = [x, y, z], yaw_deg = 0.0 }, ...]")
    out = []
    for i, e in enumerate(raw):
        ww = f"{w}.list.{i}"
        if not isinstance(e, Mapping):
            raise doc.error(f"{w}.list", f"entry {i}: expected a table {{ position_m = [...], yaw_deg = ... }}")
        check_keys(doc, e, ("position_m", "yaw_deg", "pitch_deg", "roll_deg"), ww)
        p = vector(doc, e, "position_m", 3, ww)
        out.append((*p, number(doc, e, "roll_deg", ww, 0.0), number(doc, e, "pitch_deg", ww, 0.0),
                    number(doc, e, "yaw_deg", ww, 0.0)))
    return Poses("list", listed=tuple(out))


def _render(doc: Doc) -> RenderSpec:
    t = _table(doc, "render")
    check_keys(doc, t, _RENDER, "render")
    cam = t.get("camera", None)
    if cam is not None and not isinstance(cam, (bool, str)):
        raise doc.error("render.camera", f"expected true/false or a camera sensor name, got {cam!r}")
    count = int(number(doc, t, "count", "render", 10.0, lo=1, hi=1_000_000))
    rays = t.get("elevation_rays")
    for k in ("realism", "png"):
        if k in t and not isinstance(t[k], bool):
            raise doc.error(f"render.{k}", f"expected true or false, got {t[k]!r}")
    poses_t = t.get("poses", {})
    if not isinstance(poses_t, Mapping) or not poses_t:
        raise doc.error("render.poses", "a render campaign needs [render.poses] (mode = box | path | list)")
    poses = _poses(doc, poses_t, count)
    if poses.mode == "list":
        count = len(poses.listed)
    return RenderSpec(
        sonar=_str(doc, t, "sonar", "render", "sonar"),
        camera=("camera" if cam is True else None if cam in (None, False) else str(cam)),
        count=count,
        elevation_rays=None if rays is None else int(number(doc, t, "elevation_rays", "render", lo=1, hi=100_000)),
        realism=bool(t.get("realism", True)), png=bool(t.get("png", True)),
        chunk=int(number(doc, t, "chunk", "render", 10.0, lo=1, hi=100_000)), poses=poses)


def _matrix(doc: Doc, scen: Mapping[str, Any], folder: Path) -> tuple[dict[str, list[Any]], bool, dict[str, Path]]:
    t = _table(doc, "matrix")
    zipped = t.get("zip", False)
    if not isinstance(zipped, bool):
        raise _err(doc, "matrix", "zip", f"expected true or false, got {zipped!r}")
    out: dict[str, list[Any]] = {}
    timelines: dict[str, Path] = {}
    for key, vals in t.items():
        if key == "zip":
            continue
        if not isinstance(vals, list) or not vals:
            raise _err(doc, "matrix", key, f"expected a non-empty list of values, got {vals!r}")
        if key == "seed":
            if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in vals):
                raise _err(doc, "matrix", key, f"seeds are integers >= 0, got {vals!r}")
        elif key == "current_m_s":
            for v in vals:
                if not (isinstance(v, list) and len(v) == 3 and all(_finite(x) for x in v)):
                    raise _err(doc, "matrix", key, f"each current is [north, east, down] in m/s, got {v!r}")
        elif key == "start":
            for v in vals:
                if not isinstance(v, Mapping) or "position_m" not in v or set(v) - set(_START):
                    raise _err(doc, "matrix", key, "each start is { position_m = [x, y, z], "
                                                   f"orientation_deg = [roll, pitch, yaw] }}, got {v!r}")
                for k in v:
                    if not (isinstance(v[k], list) and len(v[k]) == 3 and all(_finite(x) for x in v[k])):
                        raise _err(doc, "matrix", key, f"{k} needs 3 numbers, got {v[k]!r}")
        elif key == "timeline":
            for v in vals:
                if not isinstance(v, str):
                    raise _err(doc, "matrix", key, f"a timeline file path (or \"\" for none), got {v!r}")
                if v:
                    timelines[v] = _timeline_file(doc, folder, v)
        else:
            _check_dotted(doc, scen, "matrix", key)
        out[key] = vals
    if zipped and len({len(v) for v in out.values()}) > 1:
        lens = ", ".join(f"{k}: {len(v)}" for k, v in out.items())
        raise _err(doc, "matrix", "zip", f"zip = true needs lists of one length ({lens})")
    n = len(next(iter(out.values()))) if zipped and out else math.prod(len(v) for v in out.values())
    if n > MAX_CASES:
        raise doc.error("matrix", f"{n} cases is more than {MAX_CASES}")
    return out, zipped, timelines


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _timeline_file(doc: Doc, folder: Path, rel: str) -> Path:
    from hilsim.runtime.timeline import parse_timeline

    p = (folder / rel).resolve()
    if not p.is_file():
        raise _err(doc, "matrix", "timeline", f"timeline file {rel!r} not found (relative to {folder})")
    tdoc = load_toml(p)
    check_keys(tdoc, tdoc.data, ("timeline",), "")
    parse_timeline(tdoc)
    return p


def expand_command(command: str, values: Mapping[str, str]) -> list[str]:
    """Split ``command`` like a shell would (no shell runs it) and fill the placeholders."""
    import shlex

    try:
        words = shlex.split(command)
    except ValueError as exc:
        raise ValueError(f"cannot split the command: {exc}") from None
    if not words:
        raise ValueError("the command is empty")

    def fill(m: re.Match[str]) -> str:
        name = m.group(1)
        if name not in values:
            raise ValueError(f"unknown placeholder {{{name}}}; known: "
                             + ", ".join("{" + k + "}" for k in PLACEHOLDERS))
        return values[name]

    return [_PLACEHOLDER.sub(fill, w) for w in words]


def load_campaign(path: Path | str) -> Campaign:
    """Read and check a campaign file; :class:`ConfigError` (file, line, key) on any mistake."""
    doc = load_toml(path)
    p = doc.path.resolve()
    d = doc.data
    check_keys(doc, d, _TOP, "")
    kind = d.get("kind", "mission")
    if kind not in KINDS:
        raise doc.error("kind", f"unknown kind {kind!r}; one of {', '.join(KINDS)}")
    scen_ref = _str(doc, d, "scenario", "", "water_tank")
    local = (p.parent / scen_ref)
    try:
        scen = find_scenario(local if local.exists() else scen_ref)
    except FileNotFoundError as exc:
        raise doc.error("scenario", str(exc)) from None
    with open(scen, "rb") as f:
        try:
            scen_data = tomllib.load(f)
        except tomllib.TOMLDecodeError as exc:
            raise doc.error("scenario", f"the scenario {scen} is not valid TOML: {exc}") from None
    fast = d.get("fast", False)
    if not isinstance(fast, bool):
        raise doc.error("fast", f"expected true or false, got {fast!r}")
    time_scale = number(doc, d, "time_scale", "", 1.0, lo=0.01, hi=1000.0)
    duration = number(doc, d, "duration_s", "", lo=0.1, hi=1e7) if "duration_s" in d else None
    seed = int(number(doc, d, "seed", "", lo=0, hi=2**63)) if "seed" in d else None
    stack = None
    render = None
    if kind == "mission":
        st = _table(doc, "stack")
        if not st:
            raise doc.error("stack", "a mission campaign needs [stack] command = \"...\" (the program under test)")
        check_keys(doc, st, _STACK, "stack")
        env = st.get("env", {})
        if not isinstance(env, Mapping) or not all(isinstance(v, str) for v in env.values()):
            raise doc.error("stack.env", "expected a table of strings { NAME = \"value\" }")
        stack = Stack(command=_str(doc, st, "command", "stack"),
                      summary=_str(doc, st, "summary", "stack", "{out}/summary.json"),
                      timeout_s=number(doc, st, "timeout_s", "stack", 600.0, lo=0.1, hi=1e6),
                      startup_timeout_s=number(doc, st, "startup_timeout_s", "stack", 60.0, lo=0.1, hi=1e4),
                      cpus=number(doc, st, "cpus", "stack", 2.0, lo=0.1, hi=1024), env=dict(env))
        try:  # check the placeholders once
            expand_command(stack.command, {k: "x" for k in PLACEHOLDERS})
        except ValueError as exc:
            raise doc.error("stack.command", str(exc)) from None
    else:
        if "stack" in d:
            raise doc.error("stack", "a render campaign has no [stack]")
        render = _render(doc)
    crit: list[criteria.Criterion] = []
    for name, text in _table(doc, "pass").items():
        try:
            crit.append(criteria.parse(text, name))
        except criteria.CriterionError as exc:
            raise _err(doc, "pass", name, str(exc)) from None
    if crit and kind == "render":
        raise doc.error("pass", "a render campaign has no pass criteria")
    met = _table(doc, "metrics")
    check_keys(doc, met, _METRICS, "metrics")
    metrics = {k: number(doc, met, k, "metrics") for k in met}
    fixed = dict(_table(doc, "set"))
    for key in fixed:
        _check_dotted(doc, scen_data, "set", key)
    matrix, zipped, timelines = _matrix(doc, scen_data, p.parent)
    name = _str(doc, d, "name", "", p.stem)
    return Campaign(path=p, doc=doc, name=name, kind=kind, scenario=scen, scenario_data=scen_data,
                    time_scale=time_scale, fast=fast, duration_s=duration, seed=seed, stack=stack,
                    matrix=matrix, zip=zipped, criteria=crit, metrics=metrics, fixed=fixed,
                    timelines=timelines, render=render)
