"""Reading TOML data files (scenarios, device profiles) with clear errors.

Every error names the file, the line (where it can be found) and the dotted key.
Physical values in profiles are written as quantity tables that carry their
unit and where the number comes from::

    m_u = { value = 391.5, unit = "kg", source = "paper Table 1" }

and are converted to SI by :func:`quantity`. Scenario files use bare numbers
with the unit in the key's name (``position_m``, ``orientation_deg``).
"""

from __future__ import annotations

import difflib
import math
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

# unit -> (SI unit, factor, offset): SI = value * factor + offset
_UNITS: dict[str, tuple[str, float, float]] = {
    "1": ("1", 1.0, 0.0),
    "m": ("m", 1.0, 0.0), "cm": ("m", 0.01, 0.0), "mm": ("m", 1e-3, 0.0), "km": ("m", 1e3, 0.0),
    "rad": ("rad", 1.0, 0.0), "deg": ("rad", math.pi / 180.0, 0.0),
    "s": ("s", 1.0, 0.0), "ms": ("s", 1e-3, 0.0), "us": ("s", 1e-6, 0.0),
    "Hz": ("Hz", 1.0, 0.0), "kHz": ("Hz", 1e3, 0.0), "MHz": ("Hz", 1e6, 0.0),
    "kg": ("kg", 1.0, 0.0), "kg*m^2": ("kg*m^2", 1.0, 0.0),
    "N": ("N", 1.0, 0.0), "kgf": ("N", 9.80665, 0.0), "N*m": ("N*m", 1.0, 0.0),
    "N*s/m": ("N*s/m", 1.0, 0.0), "N*s^2/m^2": ("N*s^2/m^2", 1.0, 0.0),
    "N*m*s/rad": ("N*m*s/rad", 1.0, 0.0), "N*m*s^2/rad^2": ("N*m*s^2/rad^2", 1.0, 0.0),
    "m/s": ("m/s", 1.0, 0.0), "m/s^2": ("m/s^2", 1.0, 0.0),
    "rad/s": ("rad/s", 1.0, 0.0), "deg/s": ("rad/s", math.pi / 180.0, 0.0),
    "rpm": ("rad/s", 2.0 * math.pi / 60.0, 0.0),
    "Pa": ("Pa", 1.0, 0.0), "kPa": ("Pa", 1e3, 0.0), "bar": ("Pa", 1e5, 0.0),
    "mbar": ("Pa", 100.0, 0.0),
    "Pa*s/m": ("Pa*s/m", 1.0, 0.0), "rayl": ("Pa*s/m", 1.0, 0.0), "MRayl": ("Pa*s/m", 1e6, 0.0),
    "kg/m^3": ("kg/m^3", 1.0, 0.0), "1/m": ("1/m", 1.0, 0.0), "dB/m": ("dB/m", 1.0, 0.0),
    "dB": ("dB", 1.0, 0.0), "K": ("K", 1.0, 0.0), "degC": ("K", 1.0, 273.15),
    "A": ("A", 1.0, 0.0), "V": ("V", 1.0, 0.0), "W": ("W", 1.0, 0.0), "uT": ("T", 1e-6, 0.0),
    "T": ("T", 1.0, 0.0), "g": ("m/s^2", 9.80665, 0.0),
    "px": ("px", 1.0, 0.0), "ohm": ("ohm", 1.0, 0.0), "K/W": ("K/W", 1.0, 0.0), "nT": ("T", 1e-9, 0.0),
    "mg": ("m/s^2", 9.80665e-3, 0.0),
}


class ConfigError(ValueError):
    """A data file (scenario or profile) is malformed. The message names file, line and key."""

    def __init__(self, path: Path | str | None, key: str | None, message: str, line: int | None = None):
        self.path = Path(path) if path is not None else None
        self.key = key
        self.line = line
        where = str(self.path) if self.path is not None else "<data>"
        if line is not None:
            where += f":{line}"
        if key:
            where += f": [{key}]"
        super().__init__(f"{where}: {message}")


_HEADER = re.compile(r"^\s*(\[\[?)\s*([^\[\]#]+?)\s*\]\]?\s*(?:#.*)?$")
_NAME_LINE = re.compile(r"""^\s*name\s*=\s*(?:"([^"]*)"|'([^']*)')""")


@dataclass(frozen=True)
class _Block:
    """Lines ``start..end`` (0-based, end excluded) of one table; ``header`` is the 1-based line
    of its ``[...]`` (0 for the top of the file); ``path[i]`` holds the names part i may take."""

    path: tuple[frozenset[str], ...]
    header: int
    start: int
    end: int


def _header_keys(name: str) -> list[str]:
    return [k.strip("\"'") for k in re.findall(r'"[^"]*"|\'[^\']*\'|[^.\s]+', name)]


def _blocks(lines: list[str]) -> list[_Block]:
    """The tables of a TOML text, each with the dotted names that reach it."""
    heads: list[tuple[int, bool, list[str]]] = []  # (0-based line, array?, keys)
    for i, ln in enumerate(lines):
        m = _HEADER.match(ln)
        if m:
            heads.append((i, m.group(1) == "[[", _header_keys(m.group(2))))
    spans = [(0, heads[0][0] if heads else len(lines))]
    spans += [(h[0] + 1, heads[k + 1][0] if k + 1 < len(heads) else len(lines)) for k, h in enumerate(heads)]
    out = [_Block((), 0, *spans[0])]
    arrays: dict[tuple[str, ...], frozenset[str]] = {}  # array of tables -> labels of its current entry
    counts: dict[tuple[str, ...], int] = {}
    for (i, is_array, keys), (start, end) in zip(heads, spans[1:]):
        path: list[frozenset[str]] = []
        for j, k in enumerate(keys):
            path.append(frozenset((k,)))
            prefix = tuple(keys[:j + 1])
            if prefix in arrays and not (is_array and j == len(keys) - 1):
                path.append(arrays[prefix])  # a sub-table of the array's current entry
        if is_array:
            key = tuple(keys)
            index = counts.get(key, 0)
            counts[key] = index + 1
            labels = {str(index)}
            for ln in lines[start:end]:
                m = _NAME_LINE.match(ln)
                if m:
                    labels.add(m.group(1) if m.group(1) is not None else m.group(2))
                    break
            arrays[key] = frozenset(labels)
            path.append(arrays[key])
        out.append(_Block(tuple(path), i + 1, start, end))
    return out


@dataclass(frozen=True)
class Doc:
    """A parsed TOML file with what is needed to point at its lines."""

    path: Path
    text: str
    data: dict[str, Any]

    def line_of(self, dotted: str) -> int | None:
        """Best-effort line number of a dotted key (``objects.3.material``, ``devices.depth.path``).

        An entry of an array of tables (``[[devices]]``) is named by its index or by its
        ``name``; the key is looked for inside the table the earlier parts name, and a key
        that table does not write (a default) points at the table's header."""
        lines = self.text.splitlines()
        parts = [p for p in dotted.split(".") if p]
        if not parts:
            return None
        best: _Block | None = None
        for block in _blocks(lines):
            n = len(block.path)
            if n <= len(parts) and all(parts[i] in block.path[i] for i in range(n)):
                if best is None or n > len(best.path):
                    best = block
        if best is not None:
            rest = parts[len(best.path):]
            if not rest:
                return best.header
            pat = re.compile(r"^\s*(?:" + re.escape(rest[0]) + r"|\"" + re.escape(rest[0]) + r"\"|'"
                             + re.escape(rest[0]) + r"')\s*[=.]")
            for i in range(best.start, best.end):
                if pat.match(lines[i]):
                    return i + 1
            if best.path:  # a key the table does not write: the table itself
                return best.header
        return self._line_of_loosely(dotted)

    def _line_of_loosely(self, dotted: str) -> int | None:
        """The key's last part, preferably inside the section the earlier parts name."""
        parts = [p for p in dotted.split(".") if not p.isdigit()]
        if not parts:
            return None
        lines = self.text.splitlines()
        last = parts[-1]
        pat = re.compile(r"^\s*(\[\[?)?\s*[\w.\"-]*\b" + re.escape(last) + r"\b")
        # prefer a line inside the section named by the earlier parts
        section = ".".join(parts[:-1])
        in_section = not section
        for i, ln in enumerate(lines, 1):
            s = ln.strip()
            if s.startswith("["):
                name = s.strip("[]").strip()
                in_section = (not section) or name == section or name.startswith(section + ".") or name.endswith(section)
                if name.split(".")[-1] == last:
                    return i
                continue
            if in_section and pat.match(ln):
                return i
        for i, ln in enumerate(lines, 1):
            if pat.match(ln):
                return i
        return None

    def error(self, key: str | None, message: str) -> ConfigError:
        return ConfigError(self.path, key, message, self.line_of(key) if key else None)


def load_toml(path: Path | str) -> Doc:
    """Parse a TOML file; syntax errors become :class:`ConfigError` with the line."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(p, None, "file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(p, None, f"cannot read: {exc}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        m = re.search(r"line (\d+)", str(exc))
        raise ConfigError(p, None, f"not valid TOML: {exc}", int(m.group(1)) if m else None) from None
    return Doc(p, text, data)


def check_keys(doc: Doc, table: Mapping[str, Any], allowed: Iterable[str], where: str) -> None:
    """Refuse keys not in ``allowed``, suggesting the closest valid one."""
    allowed = list(allowed)
    for key in table:
        if key not in allowed:
            close = difflib.get_close_matches(key, allowed, n=1, cutoff=0.5)
            hint = f"; did you mean {close[0]!r}?" if close else f"; valid keys: {', '.join(sorted(allowed))}"
            dotted = f"{where}.{key}" if where else key
            raise doc.error(dotted, f"unknown key {key!r}{hint}")


def require(doc: Doc, table: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in table:
        raise doc.error(where or key, f"missing required key {key!r}")
    return table[key]


def unit_si(unit: str) -> str:
    if unit not in _UNITS:
        raise KeyError(unit)
    return _UNITS[unit][0]


def convert(value: float, unit: str, si_unit: str) -> float:
    """Convert ``value`` in ``unit`` to ``si_unit``; raises ValueError if incompatible."""
    if unit not in _UNITS:
        raise ValueError(f"unknown unit {unit!r}")
    target, factor, offset = _UNITS[unit]
    if target != si_unit:
        raise ValueError(f"unit {unit!r} is not a unit of {si_unit!r}")
    return value * factor + offset


@dataclass(frozen=True)
class Quantity:
    """A profile value converted to SI, with where it came from."""

    value: Any  # float or tuple of floats, in SI
    unit: str   # the unit as written in the file
    source: str


def quantity(doc: Doc, table: Mapping[str, Any], key: str, si_unit: str, where: str = "",
             default: Any = None, length: int | None = None) -> Any:
    """Read ``key`` as a quantity table and return its value in ``si_unit``.

    ``value`` may be a number or a list of numbers (``length`` enforced when
    given). A missing key returns ``default`` unless that is ``None``.
    """
    dotted = f"{where}.{key}" if where else key
    if key not in table:
        if default is None:
            raise doc.error(where or key, f"missing required key {key!r} (unit {si_unit})")
        return default
    q = table[key]
    if not isinstance(q, Mapping):
        raise doc.error(dotted, f"expected {{ value = ..., unit = \"{si_unit}\", source = \"...\" }}, got {q!r}")
    check_keys(doc, q, ("value", "unit", "source", "note"), dotted)
    for k in ("value", "unit", "source"):
        if k not in q:
            raise doc.error(dotted, f"quantity needs {k!r}")
    unit = q["unit"]
    raw = q["value"]
    try:
        if isinstance(raw, list):
            if length is not None and len(raw) != length:
                raise ValueError(f"expected {length} values, got {len(raw)}")
            val: Any = tuple(convert(_num(x), unit, si_unit) for x in raw)
        else:
            if length is not None:
                raise ValueError(f"expected a list of {length} values")
            val = convert(_num(raw), unit, si_unit)
    except ValueError as exc:
        raise doc.error(dotted, str(exc)) from None
    return val


def _num(x: Any) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise ValueError(f"expected a number, got {x!r}")
    if not math.isfinite(float(x)):
        raise ValueError(f"expected a finite number, got {x!r}")
    return float(x)


def number(doc: Doc, table: Mapping[str, Any], key: str, where: str = "", default: float | None = None,
           lo: float | None = None, hi: float | None = None) -> float:
    """A bare finite number, range-checked."""
    dotted = f"{where}.{key}" if where else key
    if key not in table:
        if default is None:
            raise doc.error(where or key, f"missing required key {key!r}")
        return default
    try:
        v = _num(table[key])
    except ValueError as exc:
        raise doc.error(dotted, str(exc)) from None
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise doc.error(dotted, f"{v} is outside [{lo}, {hi}]")
    return v


def vector(doc: Doc, table: Mapping[str, Any], key: str, n: int, where: str = "",
           default: tuple[float, ...] | None = None) -> tuple[float, ...]:
    """A list of ``n`` finite numbers."""
    dotted = f"{where}.{key}" if where else key
    if key not in table:
        if default is None:
            raise doc.error(where or key, f"missing required key {key!r}")
        return default
    raw = table[key]
    if not isinstance(raw, list) or len(raw) != n:
        raise doc.error(dotted, f"expected a list of {n} numbers, got {raw!r}")
    try:
        return tuple(_num(x) for x in raw)
    except ValueError as exc:
        raise doc.error(dotted, str(exc)) from None


def resolve_inside(base: Path, rel: str | Path) -> Path | None:
    """``base / rel`` with ``..`` and symlinks resolved, or None when ``rel`` is absolute or the
    result is not inside ``base`` (the file need not exist)."""
    p = Path(rel)
    if p.is_absolute():
        return None
    full = (base / p).resolve()
    root = base.resolve()
    if full != root and root not in full.parents:
        return None
    return full


def safe_join(base: Path, rel: str, doc: Doc, key: str) -> Path:
    """Resolve ``rel`` inside ``base``; refuse absolute paths and escapes (``..``, symlinks)."""
    if not isinstance(rel, str) or not rel:
        raise doc.error(key, f"expected a relative file path, got {rel!r}")
    if Path(rel).is_absolute():
        raise doc.error(key, f"path {rel!r} is absolute; paths must stay inside {base}")
    full = resolve_inside(base, rel)
    root = base.resolve()
    if full is None:
        raise doc.error(key, f"path {rel!r} leaves the scenario folder {root}")
    if not full.is_file():
        raise doc.error(key, f"file {rel!r} not found in {root}")
    return full
