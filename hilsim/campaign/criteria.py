"""Pass criteria: one comparison each, parsed by a small tokenizer (never ``eval``).

Grammar (whitespace between tokens is free)::

    criterion := operand OP operand
    OP        := "==" | "!=" | "<" | "<=" | ">" | ">="
    operand   := NUMBER | "true" | "false" | "null" | STRING | NAME
    NAME      := segment ("." segment)*     segment: [A-Za-z_][A-Za-z0-9_-]* or digits (a list index)
    STRING    := '...' or "..." (no escapes)

A NAME is looked up in the run's facts (:func:`evaluate`): ``exit_code``,
``timed_out``, ``wall_s``, ``summary.<path>`` (the stack's summary JSON),
``bridge.<path>`` (the bridge's summary.json) and ``truth.<metric>`` (metrics of
the bridge's truth.csv, :mod:`hilsim.campaign.metrics`). Anything else (a call,
an arithmetic operator, two comparisons, a bare name) is refused with the
position of the offending text.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any, Mapping

OPS = ("==", "!=", "<=", ">=", "<", ">")
ROOTS = ("exit_code", "timed_out", "wall_s", "summary", "bridge", "truth")

_TOKEN = re.compile(r"""
    (?P<ws>\s+)
  | (?P<op>==|!=|<=|>=|<|>)
  | (?P<num>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?(?![A-Za-z_.]))
  | (?P<str>"[^"]*"|'[^']*')
  | (?P<name>[A-Za-z_][A-Za-z0-9_\-]*(?:\.(?:[A-Za-z_][A-Za-z0-9_\-]*|\d+))*)
""", re.VERBOSE)

_MISSING = object()


class CriterionError(ValueError):
    """A criterion that is not a simple comparison; the message says where it goes wrong."""


@dataclass(frozen=True)
class Operand:
    kind: str      # "const" | "name"
    value: Any     # the constant, or the dotted name

    def text(self) -> str:
        if self.kind == "name":
            return str(self.value)
        if isinstance(self.value, bool):
            return "true" if self.value else "false"
        if self.value is None:
            return "null"
        return repr(self.value) if isinstance(self.value, str) else f"{self.value:g}"


@dataclass(frozen=True)
class Criterion:
    """``left op right``, as parsed from ``text``; ``name`` is its key in ``[pass]``."""

    name: str
    text: str
    left: Operand
    op: str
    right: Operand

    def names(self) -> list[str]:
        return [o.value for o in (self.left, self.right) if o.kind == "name"]


@dataclass(frozen=True)
class Verdict:
    criterion: Criterion
    ok: bool
    detail: str    # e.g. "truth.contacts = 2 (needs == 0)" or "summary.success missing"


def _operand(kind: str, text: str, pos: int) -> Operand:
    if kind == "num":
        v = float(text)
        return Operand("const", int(v) if re.fullmatch(r"[-+]?\d+", text) else v)
    if kind == "str":
        return Operand("const", text[1:-1])
    low = text.lower()
    if low in ("true", "false"):
        return Operand("const", low == "true")
    if low in ("null", "none"):
        return Operand("const", None)
    root = text.split(".")[0]
    if root not in ROOTS:
        raise CriterionError(f"unknown name {text!r} at column {pos + 1}: a name starts with one of "
                             f"{', '.join(ROOTS)}")
    if root in ("summary", "bridge", "truth") and "." not in text:
        raise CriterionError(f"{text!r} at column {pos + 1} needs a field: {root}.<field>")
    return Operand("name", text)


def parse(text: str, name: str = "") -> Criterion:
    """Parse one comparison; :class:`CriterionError` for anything else."""
    if not isinstance(text, str) or not text.strip():
        raise CriterionError(f"expected a comparison such as \"exit_code == 0\", got {text!r}")
    toks: list[tuple[str, str, int]] = []
    pos = 0
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None:
            raise CriterionError(f"unexpected {text[pos:pos + 12]!r} at column {pos + 1}: only a comparison "
                                 f"of two values or names ({' '.join(OPS)}) is allowed")
        kind = m.lastgroup or ""
        if kind != "ws":
            toks.append((kind, m.group(), pos))
        pos = m.end()
    shape = [k for k, _, _ in toks]
    if "op" not in shape:
        raise CriterionError(f"no comparison operator in {text!r}: write one of {' '.join(OPS)} between two operands")
    if shape.count("op") > 1 and len(toks) > 3 and shape[1] == "op" and shape[3] == "op":
        raise CriterionError(f"more than one comparison in {text!r}: a criterion is one comparison "
                             "(write another criterion for the next)")
    bad = next((t for i, t in enumerate(toks) if (i == 1) != (t[0] == "op") or i > 2), None)
    if bad is None and len(toks) < 3:
        raise CriterionError(f"incomplete comparison {text!r}: a criterion is one operand, an operator, one operand")
    if bad is not None:
        _, word, col = bad
        raise CriterionError(f"unexpected {word!r} at column {col + 1} in {text!r}: "
                             "a criterion is one operand, an operator, one operand")
    left = _operand(toks[0][0], toks[0][1], toks[0][2])
    right = _operand(toks[2][0], toks[2][1], toks[2][2])
    if left.kind == "const" and right.kind == "const":
        raise CriterionError(f"{text!r} compares two constants: one side must name a result")
    return Criterion(name or text, text.strip(), left, toks[1][1], right)


def lookup(facts: Mapping[str, Any], dotted: str) -> Any:
    """The value at a dotted path (dict keys, list indices); ``_MISSING`` when absent."""
    cur: Any = facts
    for part in dotted.split("."):
        if isinstance(cur, Mapping) and part in cur:
            cur = cur[part]
        elif isinstance(cur, (list, tuple)) and part.isdigit() and int(part) < len(cur):
            cur = cur[int(part)]
        else:
            return _MISSING
    return cur


def _eq(a: Any, b: Any) -> bool:
    if isinstance(a, bool) or isinstance(b, bool):  # true is not 1
        return type(a) is type(b) and a == b
    return bool(a == b)


def _compare(a: Any, op: str, b: Any) -> bool | None:
    """None when the two cannot be ordered (a string against a number, null, ...)."""
    if op in ("==", "!="):
        if isinstance(a, float) and isinstance(b, float) and (math.isnan(a) or math.isnan(b)):
            return op == "!="
        return _eq(a, b) if op == "==" else not _eq(a, b)
    num = (int, float)
    ordered = (isinstance(a, num) and isinstance(b, num) and not isinstance(a, bool) and not isinstance(b, bool)) \
        or (isinstance(a, str) and isinstance(b, str))
    if not ordered:
        return None
    return {"<": a < b, "<=": a <= b, ">": a > b, ">=": a >= b}[op]


def evaluate(c: Criterion, facts: Mapping[str, Any]) -> Verdict:
    """Judge one criterion against a run's facts; a missing name fails the criterion."""
    vals = []
    for o in (c.left, c.right):
        if o.kind == "const":
            vals.append(o.value)
            continue
        v = lookup(facts, o.value)
        if v is _MISSING:
            return Verdict(c, False, f"{o.value} missing")
        vals.append(v)
    res = _compare(vals[0], c.op, vals[1])
    if res is None:
        return Verdict(c, False, f"cannot compare {vals[0]!r} {c.op} {vals[1]!r}")
    shown = [f"{o.value} = {_fmt(v)}" for o, v in zip((c.left, c.right), vals) if o.kind == "name"]
    return Verdict(c, bool(res), f"{', '.join(shown)} (needs {c.text})")


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, bool):
        return "true" if v else "false"
    return repr(v) if isinstance(v, str) else str(v)


def judge(criteria: list[Criterion], facts: Mapping[str, Any]) -> tuple[bool, Verdict | None]:
    """All criteria in order: (passed, the first failing verdict or None)."""
    for c in criteria:
        v = evaluate(c, facts)
        if not v.ok:
            return False, v
    return True, None
