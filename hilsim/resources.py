"""Locate the data folders (devices/, scenarios/, protocols/).

In a checkout they sit at the top of the repository, beside ``hilsim/``; in an
installed wheel they are shipped as ``hilsim/_data/<name>``. ``HILSIM_DATA``
overrides both (a folder holding ``devices/``, ``scenarios/``...).
"""

from __future__ import annotations

import os
from pathlib import Path

from hilsim.config import Doc, resolve_inside

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


def check_profile_ref(kind: str | None, name: object, base: Path | None = None, *,
                      doc: Doc | None = None, key: str | None = None) -> str:
    """Refuse a profile reference that is not a plain name inside the search path.

    A reference is data: ``didson_hf`` or ``sonars/didson_hf``, looked up below ``base`` (the
    scenario folder) and below the bundled ``devices/``. Absolute references, and references
    that leave either folder (``..``, a symlink pointing out), are refused: with ``doc`` and
    ``key`` as the :class:`~hilsim.config.ConfigError` of that file, line and key, else as
    a ValueError. Returns the file name to look up (``name`` with ``.toml``).
    """
    def refused(message: str) -> ValueError:
        return doc.error(key, message) if doc is not None else ValueError(message)

    what = f"{kind[:-1] if kind.endswith('s') else kind} profile" if kind else "profile"
    if not isinstance(name, str) or not name.strip():
        raise refused(f"expected a {what} name such as 'didson_hf', got {name!r}")
    rel = name if name.endswith(".toml") else name + ".toml"
    if Path(rel).is_absolute():
        raise refused(f"{what} {name!r} is absolute; a profile is a name looked up in the scenario "
                      f"folder, then in {data_path('devices')}")
    roots = ([(base, "the scenario folder")] if base is not None else []) + [(data_path("devices"), "devices/")]
    for root, label in roots:
        for sub in ([rel, f"{kind}/{rel}"] if kind else [rel]):
            if resolve_inside(root, sub) is None:
                raise refused(f"{what} {name!r} leaves {label} {root.resolve()}; give the name of a "
                              "profile in the scenario folder or in devices/")
    return rel


def find_profile(kind: str, name: str, base: Path | None = None, *,
                 doc: Doc | None = None, key: str | None = None) -> Path:
    """Resolve a device profile reference such as ``sonars/didson_hf``.

    ``name`` is looked up relative to ``base`` (a scenario folder, for profiles a
    scenario ships itself) and then in the bundled ``devices/`` folder; ``.toml``
    is optional. ``kind`` is the sub-folder used when ``name`` has none. A reference
    that is absolute or leaves those folders is refused (:func:`check_profile_ref`:
    a ConfigError naming ``doc``'s file, line and ``key`` when given, else a ValueError).
    """
    rel = check_profile_ref(kind, name, base, doc=doc, key=key)
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
