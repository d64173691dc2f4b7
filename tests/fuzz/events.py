"""Event checks for the fuzz targets: equality with NaN equal to NaN, and fields that fit their annotations."""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from dataclasses import dataclass
from typing import Any

import numpy as np


def same(a: Any, b: Any) -> bool:
    """Equality for events, with NaN equal to NaN (decoded floats often are NaN)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"))
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if dataclasses.is_dataclass(a):
        return all(same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    return bool(a == b)


@dataclass(frozen=True, eq=False)
class Canon:
    """An event compared with :func:`same`."""

    event: Any

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Canon) and same(self.event, other.event)

    __hash__ = None  # type: ignore[assignment]


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except Exception:  # noqa: BLE001 - a hint we cannot resolve is not checked
        return {}


def well_typed(value: Any, hint: Any) -> bool:
    """Whether ``value`` fits its annotation (str, bytes, int, float, bool, None, unions, tuples and
    dataclasses are checked; anything else, numpy arrays included, passes)."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return any(well_typed(value, a) for a in typing.get_args(hint))
    if hint is type(None):
        return value is None
    if hint is float:
        return isinstance(value, (float, int)) and not isinstance(value, bool)
    if hint in (int, str, bytes, bool):
        return isinstance(value, hint)
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(well_typed(v, args[0]) for v in value)
        return len(args) == len(value) and all(well_typed(v, a) for v, a in zip(value, args))
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return isinstance(value, hint) and not badly_typed(value)
    return True


def badly_typed(event: Any) -> str:
    """The first field of a dataclass event (or of one in a tuple) whose value does not fit its
    annotation, as ``Class.field=value``; "" if none."""
    if isinstance(event, tuple):
        return next((bad for e in event if (bad := badly_typed(e))), "")
    if not dataclasses.is_dataclass(event) or isinstance(event, type):
        return ""
    hints = _hints(type(event))
    for f in dataclasses.fields(event):
        value = getattr(event, f.name)
        if f.name in hints and not well_typed(value, hints[f.name]):
            return f"{type(event).__name__}.{f.name}={value!r}"
    return ""
