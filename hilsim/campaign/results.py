"""Campaign results: a journal written as runs finish, and the table made from it.

``results.jsonl`` gets one JSON line per finished run, flushed at once, so an
interrupted campaign loses nothing and ``--resume`` knows what is done (a
case is matched by the hash of its parameters). At the end (and on
interruption) the journal becomes ``results.parquet`` (pyarrow; ``results.csv``
when pyarrow is missing), one row per run with flat columns: ``case``,
``status``, ``failed``, ``failure``, ``param.<key>``, ``exit_code``,
``timed_out``, ``wall_s``, ``summary.<path>``, ``bridge.<path>``, ``truth.<metric>``.
"""

from __future__ import annotations

import csv
import json
import math
import threading
from pathlib import Path
from typing import Any, Iterable, Mapping

FIRST = ("case", "index", "status", "failed", "failure", "seed", "exit_code", "timed_out", "wall_s",
         "bridge_exit", "run_dir")
NESTED = ("params", "summary", "bridge", "truth", "hits", "cells", "files")
_PREFIX = {"params": "param"}


class Journal:
    """Append-only JSON lines; thread-safe."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()

    def load(self) -> list[dict[str, Any]]:
        rows = []
        if self.path.is_file():
            for ln in self.path.read_text().splitlines():
                try:
                    r = json.loads(ln)
                except ValueError:
                    continue  # a line cut by a crash
                if isinstance(r, dict) and "key" in r:
                    rows.append(r)
        return rows

    def append(self, row: Mapping[str, Any]) -> None:
        line = json.dumps(row, default=str, allow_nan=False, separators=(",", ":"))
        with self._lock, open(self.path, "a") as f:
            f.write(line + "\n")
            f.flush()


def _clean(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    return v


def flatten(row: Mapping[str, Any]) -> dict[str, Any]:
    """One flat dict per run: nested tables become dotted columns; lists become JSON text."""
    out: dict[str, Any] = {}

    def put(prefix: str, v: Any) -> None:
        if isinstance(v, Mapping):
            for k, x in v.items():
                put(f"{prefix}.{k}", x)
        elif isinstance(v, (list, tuple)):
            out[prefix] = json.dumps(_clean(v), separators=(",", ":"))
        else:
            out[prefix] = _clean(v)

    for k, v in row.items():
        if k in NESTED:
            if k == "params":
                for pk, pv in v.items():  # a parameter is one column even when its value is a list
                    out[f"param.{pk}"] = json.dumps(pv, separators=(",", ":")) if isinstance(pv, (list, dict)) else pv
            else:
                put(_PREFIX.get(k, k), v)
        else:
            out[k] = _clean(v) if not isinstance(v, (list, dict)) else json.dumps(_clean(v))
    return out


def columns(rows: Iterable[Mapping[str, Any]]) -> list[str]:
    seen: dict[str, None] = {}
    for r in rows:
        for k in r:
            seen.setdefault(k, None)
    first = [k for k in FIRST if k in seen]
    params = sorted(k for k in seen if k.startswith("param."))
    rest = sorted(k for k in seen if k not in first and k not in params)
    return first + params + rest


def _column_type(values: list[Any]) -> str:
    vals = [v for v in values if v is not None]
    if vals and all(isinstance(v, bool) for v in vals):
        return "bool"
    if vals and all(isinstance(v, int) and not isinstance(v, bool) for v in vals):
        return "int"
    if vals and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
        return "float"
    return "str"


def write_table(rows: list[dict[str, Any]], out: Path) -> Path:
    """``out/results.parquet`` (or ``results.csv`` without pyarrow) from flat rows, in case order."""
    flat = sorted((flatten(r) for r in rows), key=lambda r: (r.get("index", 0), str(r.get("frame", ""))))
    cols = columns(flat)
    typed: dict[str, list[Any]] = {}
    for c in cols:
        vals = [r.get(c) for r in flat]
        kind = _column_type(vals)
        if kind == "str":
            vals = [None if v is None else (v if isinstance(v, str) else json.dumps(v)) for v in vals]
        elif kind == "float":
            vals = [None if v is None else float(v) for v in vals]
        typed[c] = vals
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        path = out / "results.csv"
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(cols)
            for i in range(len(flat)):
                w.writerow(["" if typed[c][i] is None else typed[c][i] for c in cols])
        return path
    path = out / "results.parquet"
    pq.write_table(pa.table(typed), path)
    return path


def read_table(path: Path) -> list[dict[str, Any]]:
    """Rows of a results table written by :func:`write_table` (parquet or CSV)."""
    if path.suffix == ".parquet":
        import pyarrow.parquet as pq

        return pq.read_table(path).to_pylist()
    with open(path, newline="") as f:
        return list(csv.DictReader(f))
