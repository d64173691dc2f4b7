"""Locate the data folders (devices/, scenarios/, protocols/).

In a checkout they sit at the top of the repository, beside ``hilsim/``; in an
installed wheel they are shipped as ``hilsim/_data/<name>``. ``HILSIM_DATA``
overrides both (a folder holding ``devices/``, ``scenarios/``...).
"""

from __future__ import annotations

import os
from pathlib import Path

_PKG = Path(__file__).resolve().parent
DATA_FOLDERS = ("devices", "scenarios", "protocols")


def data_root() -> Path:
    """The folder that holds ``devices/``, ``scenarios/`` and ``protocols/``."""
    env = os.environ.get("HILSIM_DATA")
    if env:
        return Path(env).resolve()
    installed = _PKG / "_data"
    if (installed / "devices").is_dir():
        return installed
    checkout = _PKG.parent
    if (checkout / "devices").is_dir():
        return checkout
    raise FileNotFoundError(
        f"hilsim data folders not found: looked in {installed} and {checkout}; "
        "set HILSIM_DATA to the folder holding devices/ and scenarios/"
    )


def data_path(kind: str, *parts: str) -> Path:
    """Path of ``<kind>/<parts...>`` inside the data root (not checked to exist)."""
    if kind not in DATA_FOLDERS:
        raise ValueError(f"unknown data folder {kind!r}; expected one of {DATA_FOLDERS}")
    return data_root().joinpath(kind, *parts)


DEFAULT_SCENARIO = "water_tank"


def find_scenario(name_or_path: str | os.PathLike[str] | None) -> Path:
    """Resolve a scenario argument to its TOML file.

    Accepts a path to a ``.toml`` file, a folder holding ``scenario.toml``, or
    the name of a bundled scenario (``water_tank``). ``None`` is the default.
    """
    if name_or_path is None:
        name_or_path = DEFAULT_SCENARIO
    p = Path(name_or_path)
    if p.is_file():
        return p.resolve()
    if p.is_dir() and (p / "scenario.toml").is_file():
        return (p / "scenario.toml").resolve()
    bundled = data_path("scenarios", str(name_or_path))
    if (bundled / "scenario.toml").is_file():
        return (bundled / "scenario.toml").resolve()
    if bundled.with_suffix(".toml").is_file():
        return bundled.with_suffix(".toml").resolve()
    known = sorted(d.name for d in data_path("scenarios").iterdir() if d.is_dir())
    raise FileNotFoundError(
        f"scenario {str(name_or_path)!r} not found: not a file, not a folder with "
        f"scenario.toml, and not a bundled scenario (bundled: {', '.join(known)})"
    )


def find_profile(kind: str, name: str, base: Path | None = None) -> Path:
    """Resolve a device profile reference such as ``sonars/didson_hf``.

    ``name`` is looked up relative to ``base`` (a scenario folder, for profiles a
    scenario ships itself) and then in the bundled ``devices/`` folder; ``.toml``
    is optional. ``kind`` is the sub-folder used when ``name`` has none.
    """
    rel = name if name.endswith(".toml") else name + ".toml"
    candidates = []
    if base is not None:
        candidates += [base / rel, base / kind / rel]
    candidates += [data_path("devices", rel), data_path("devices", kind, rel)]
    for c in candidates:
        if c.is_file():
            return c.resolve()
    folder = data_path("devices", kind)
    known = sorted(p.stem for p in folder.glob("*.toml")) if folder.is_dir() else []
    raise FileNotFoundError(
        f"{kind} profile {name!r} not found (bundled {kind}: {', '.join(known) or 'none'})"
    )
