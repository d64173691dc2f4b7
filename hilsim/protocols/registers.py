"""Modbus register maps as data: load a map TOML, turn readings into register words.

Sans-I/O (no sockets, no asyncio). A map file (``protocols/*.toml``, format in
``protocols/modbus-registers.md``) lists registers with their address, type,
word order, unit, scale and the simulated signal they show; :func:`load_map`
reads it into a :class:`RegisterMap` (errors are :class:`~hilsim.config.ConfigError`
naming file, line and key). A :class:`RegisterImage` is the one live copy of a
device's registers: the device calls :meth:`RegisterImage.update` with signals
in SI units at the sensor's rate, and every server (Modbus TCP, Modbus RTU)
answers reads from it with :meth:`RegisterImage.read`. Writes are validated by
:meth:`RegisterImage.check_write`, which decodes them to values in the
register's unit; what a write *does* is the device's business.

Encoding of one register value ``v`` (SI) to words:

* ``negate``: ``v = -v`` (a frame change: body FRD -> a sensor's own axes);
* SI -> ``unit`` (``Pa`` -> ``bar``, ``K`` -> ``degC``, ``rad`` -> ``deg``...);
* ``float32``: IEEE-754 single of ``v / scale``; NaN stays NaN (a channel
  error), out-of-range values become +-inf (over/underflow, as Keller reports);
* integer types: ``round(v / scale)``, so ``scale`` is the value of one count
  in ``unit``; outside the type's range the count saturates (``overflow =
  "saturate"``) or wraps modulo 2^bits (``"wrap"``: angles); NaN gives the
  type's most negative value (unsigned: its largest), +-inf saturates;
* words: 16-bit, big-endian bytes; ``word_order = "big"`` puts the high word
  at the lower address (ABCD), ``"little"`` the low word (CDAB).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

from hilsim.config import ConfigError, Doc, check_keys, convert, load_toml, unit_si

# Modbus exception codes (Modbus application protocol v1.1b3, section 7)
ILLEGAL_FUNCTION = 0x01
ILLEGAL_ADDRESS = 0x02
ILLEGAL_VALUE = 0x03
DEVICE_FAILURE = 0x04
GATEWAY_NO_RESPONSE = 0x0B

TYPES: dict[str, tuple[int, bool, bool]] = {  # name -> (words, is_float, signed)
    "float32": (2, True, True),
    "int32": (2, False, True),
    "uint32": (2, False, False),
    "int16": (1, False, True),
    "uint16": (1, False, False),
}
ACCESS = ("r", "w", "rw")
FLOAT32_MAX = 3.4028234663852886e38

_MAP_KEYS = ("name", "description", "source", "device_id", "transparent_id", "read_functions",
             "write_functions", "read_only_exception", "word_order", "max_count")
_REG_KEYS = ("name", "address", "type", "word_order", "unit", "scale", "source", "value", "access",
             "negate", "overflow", "min", "max", "on_write", "description")


class ModbusError(Exception):
    """A request the device refuses: answered with exception ``code`` (01, 02, 03, ...)."""

    def __init__(self, code: int, message: str = ""):
        self.code = int(code)
        super().__init__(message or f"Modbus exception {code:#04x}")


@dataclass(frozen=True)
class Register:
    """One value in the map (1 or 2 words).

    address: first word's address (0-based PDU address); type: a key of
    :data:`TYPES`; word_order: ``"big"`` (high word first) or ``"little"``;
    unit: the wire unit (a unit of :mod:`hilsim.config`, ``"1"`` for none);
    scale: the value of one count in ``unit`` (floats: the value is divided by it);
    source: the signal shown (SI units) or None; value: a constant in ``unit``
    (used when there is no source, and as the initial value); access: ``r``,
    ``w`` or ``rw``; negate: flip the sign of the signal; overflow: ``saturate``
    or ``wrap``; minimum/maximum: accepted written values in ``unit`` (None: any);
    on_write: what a write does (``store`` or a device action such as ``device_id``).
    """

    name: str
    address: int
    type: str = "uint16"
    word_order: str = "big"
    unit: str = "1"
    scale: float = 1.0
    source: str | None = None
    value: float | None = None
    access: str = "r"
    negate: bool = False
    overflow: str = "saturate"
    minimum: float | None = None
    maximum: float | None = None
    on_write: str = "store"
    description: str = ""
    _to_unit: tuple[float, float] = field(default=(1.0, 0.0), init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.type not in TYPES:
            raise ValueError(f"{self.name}: unknown type {self.type!r}; types: {', '.join(TYPES)}")
        si = unit_si(self.unit)
        off = convert(0.0, self.unit, si)
        object.__setattr__(self, "_to_unit", (convert(1.0, self.unit, si) - off, off))

    @property
    def words(self) -> int:
        """Number of 16-bit registers the value takes."""
        return TYPES[self.type][0]

    @property
    def end(self) -> int:
        """One past the last word's address."""
        return self.address + self.words

    @property
    def readable(self) -> bool:
        return "r" in self.access

    @property
    def writable(self) -> bool:
        return "w" in self.access

    def from_si(self, value: float) -> float:
        """A signal value (SI) in this register's unit, sign applied."""
        factor, offset = self._to_unit
        v = (value - offset) / factor
        return -v if self.negate else v

    def to_si(self, value: float) -> float:
        """A value in this register's unit back to SI (sign applied)."""
        factor, offset = self._to_unit
        v = -value if self.negate else value
        return v * factor + offset

    def encode(self, value: float) -> tuple[int, ...]:
        """Words (each 0..65535, in address order) for ``value`` in ``unit``."""
        nwords, is_float, signed = TYPES[self.type]
        x = value / self.scale if self.scale != 1.0 else value
        if is_float:
            if math.isfinite(x) and abs(x) > FLOAT32_MAX:
                x = math.copysign(math.inf, x)
            raw = int.from_bytes(struct.pack(">f", x), "big")
        else:
            raw = _to_int(x, 16 * nwords, signed, self.overflow == "wrap")
        if nwords == 1:
            return (raw,)
        hi, lo = raw >> 16, raw & 0xFFFF
        return (hi, lo) if self.word_order == "big" else (lo, hi)

    def decode(self, words: Sequence[int]) -> float:
        """The value in ``unit`` that ``words`` (address order) encode."""
        nwords, is_float, signed = TYPES[self.type]
        if len(words) != nwords:
            raise ValueError(f"{self.name}: expected {nwords} words, got {len(words)}")
        if nwords == 1:
            raw = int(words[0]) & 0xFFFF
        elif self.word_order == "big":
            raw = ((int(words[0]) & 0xFFFF) << 16) | (int(words[1]) & 0xFFFF)
        else:
            raw = ((int(words[1]) & 0xFFFF) << 16) | (int(words[0]) & 0xFFFF)
        if is_float:
            x = float(struct.unpack(">f", raw.to_bytes(4, "big"))[0])
        else:
            bits = 16 * nwords
            x = float(raw - (1 << bits) if signed and raw >= 1 << (bits - 1) else raw)
        return x * self.scale if self.scale != 1.0 else x

    def encode_si(self, value: float) -> tuple[int, ...]:
        """Words for a signal value in SI units."""
        return self.encode(self.from_si(value))


def _to_int(x: float, bits: int, signed: bool, wrap: bool) -> int:
    """Two's-complement raw value of ``round(x)`` on ``bits`` bits."""
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    if math.isnan(x):
        n = lo if signed else hi
    elif math.isinf(x):
        n = hi if x > 0 else lo
    else:
        n = int(round(x))
        if wrap:
            n = (n - lo) % (1 << bits) + lo
        else:
            n = min(max(n, lo), hi)
    return n & ((1 << bits) - 1)


@dataclass(frozen=True)
class RegisterMap:
    """A device's register map.

    device_id: default Modbus address; transparent_id: an address every such
    device answers besides its own (Keller: 250) or None; read_functions /
    write_functions: supported function codes (others answer 01);
    read_only_exception: the code a write to a read-only register gets;
    max_count: most registers one read may ask for.
    """

    name: str
    registers: tuple[Register, ...]
    device_id: int = 1
    transparent_id: int | None = None
    read_functions: tuple[int, ...] = (3,)
    write_functions: tuple[int, ...] = (6, 16)
    read_only_exception: int = ILLEGAL_ADDRESS
    max_count: int = 125
    description: str = ""
    path: Path | None = None

    def __post_init__(self) -> None:
        seen: dict[int, str] = {}
        for r in self.registers:
            for a in range(r.address, r.end):
                if a in seen:
                    raise ValueError(f"map {self.name}: register {r.name!r} overlaps {seen[a]!r} at {a:#06x}")
                seen[a] = r.name

    @property
    def by_name(self) -> dict[str, Register]:
        return {r.name: r for r in self.registers}

    def __getitem__(self, name: str) -> Register:
        for r in self.registers:
            if r.name == name:
                return r
        raise KeyError(f"map {self.name!r} has no register {name!r}; registers: "
                       f"{', '.join(r.name for r in self.registers)}")

    @property
    def sources(self) -> set[str]:
        """Signal names the map shows."""
        return {r.source for r in self.registers if r.source is not None}

    @property
    def actions(self) -> set[str]:
        """Write actions the map asks the device for (besides ``store``)."""
        return {r.on_write for r in self.registers if r.writable and r.on_write != "store"}

    def at(self, address: int) -> Register | None:
        """The register holding word ``address``, or None."""
        for r in self.registers:
            if r.address <= address < r.end:
                return r
        return None


class RegisterImage:
    """The live register words of one device: one copy, read by every server.

    ``version`` counts :meth:`update` calls; ``time`` [s] is the time of the last
    one. Reads and writes happen on the asyncio loop that also runs updates, so
    a read never sees half an update.
    """

    def __init__(self, regmap: RegisterMap):
        self.map = regmap
        self._words: list[int] = [0] * 65536
        self._readable = bytearray(65536)
        self._writable = bytearray(65536)
        self._exists = bytearray(65536)
        self._by_source: dict[str, list[Register]] = {}
        self.values: dict[str, float] = {}  # last value per register name, in its unit
        for r in regmap.registers:
            for a in range(r.address, r.end):
                self._exists[a] = 1
                self._readable[a] = r.readable
                self._writable[a] = r.writable
            if r.source is not None:
                self._by_source.setdefault(r.source, []).append(r)
            self.store(r, r.value if r.value is not None else math.nan if TYPES[r.type][1] else 0.0)
        self.version = 0
        self.time = math.nan

    def update(self, signals: Mapping[str, float], time: float = math.nan) -> None:
        """Encode signals (name -> SI value) into every register showing them."""
        for name, value in signals.items():
            for r in self._by_source.get(name, ()):
                self.store(r, r.from_si(float(value)))
        self.version += 1
        self.time = time

    def store(self, register: Register, value: float) -> None:
        """Set one register to ``value`` in its unit."""
        words = register.encode(value)
        self._words[register.address:register.end] = words
        self.values[register.name] = value

    def words(self, address: int, count: int) -> list[int]:
        """Raw words (no checks) for tests and tools."""
        return self._words[address:address + count]

    def read(self, address: int, count: int) -> list[int]:
        """Words ``address .. address + count - 1``; raises :class:`ModbusError`:
        03 if ``count`` is outside 1..max_count, 02 if any word is not readable."""
        if not 1 <= count <= self.map.max_count:
            raise ModbusError(ILLEGAL_VALUE, f"count {count} outside 1..{self.map.max_count}")
        end = address + count
        if address < 0 or end > 65536 or self._readable.find(0, address, end) != -1:
            raise ModbusError(ILLEGAL_ADDRESS, f"read {address:#06x}+{count} outside the map")
        return self._words[address:end]

    def check_write(self, address: int, words: Sequence[int]) -> list[tuple[Register, float]]:
        """Validate a write of ``words`` at ``address``; returns (register, value in
        its unit) for each register written, or raises :class:`ModbusError`: 02 for a
        word outside the map or a partial multi-word register, the map's
        ``read_only_exception`` for a read-only one, 03 for a value out of range."""
        end = address + len(words)
        if not words or address < 0 or end > 65536 or self._exists.find(0, address, end) != -1:
            raise ModbusError(ILLEGAL_ADDRESS, f"write {address:#06x}+{len(words)} outside the map")
        if self._writable.find(0, address, end) != -1:
            raise ModbusError(self.map.read_only_exception, f"write {address:#06x}+{len(words)}: read-only")
        out: list[tuple[Register, float]] = []
        a = address
        while a < end:
            r = self.map.at(a)
            if r is None or r.address != a or r.end > end:
                raise ModbusError(ILLEGAL_ADDRESS, f"write {address:#06x}+{len(words)}: splits a register")
            value = r.decode(words[a - address:r.end - address])
            if (r.minimum is not None and not value >= r.minimum) or (r.maximum is not None and not value <= r.maximum):
                raise ModbusError(ILLEGAL_VALUE, f"{r.name}: {value} outside [{r.minimum}, {r.maximum}]")
            out.append((r, value))
            a = r.end
        return out


# -- loading ------------------------------------------------------------------


def _int(doc: Doc, t: Mapping[str, Any], key: str, where: str, default: int | None, lo: int, hi: int) -> int:
    dotted = f"{where}.{key}"
    if key not in t:
        if default is None:
            raise doc.error(where, f"missing required key {key!r}")
        return default
    v = t[key]
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise doc.error(dotted, f"expected an integer in [{lo}, {hi}], got {v!r}")
    return v


def _float(doc: Doc, t: Mapping[str, Any], key: str, where: str) -> float | None:
    if key not in t:
        return None
    v = t[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise doc.error(f"{where}.{key}", f"expected a number, got {v!r}")
    return float(v)


def _choice(doc: Doc, t: Mapping[str, Any], key: str, where: str, options: Sequence[str], default: str) -> str:
    v = t.get(key, default)
    if v not in options:
        raise doc.error(f"{where}.{key}", f"expected one of {', '.join(map(repr, options))}, got {v!r}")
    return str(v)


def _functions(doc: Doc, t: Mapping[str, Any], key: str, default: tuple[int, ...]) -> tuple[int, ...]:
    v = t.get(key, list(default))
    if not isinstance(v, list) or not all(isinstance(x, int) and not isinstance(x, bool) and 1 <= x <= 127 for x in v):
        raise doc.error(f"map.{key}", f"expected a list of function codes (1..127), got {v!r}")
    return tuple(v)


def _register(doc: Doc, t: Any, i: int, word_order: str) -> Register:
    where = f"registers.{i}"
    if not isinstance(t, Mapping):
        raise doc.error("registers", f"[[registers]] entry {i} is not a table")
    check_keys(doc, t, _REG_KEYS, "registers")
    name = t.get("name")
    if not isinstance(name, str) or not name:
        raise doc.error(where, "every register needs a name")
    where = f"registers.{name}"
    address = _int(doc, t, "address", where, None, 0, 0xFFFF)
    rtype = _choice(doc, t, "type", where, tuple(TYPES), "uint16")
    if address + TYPES[rtype][0] > 0x10000:
        raise doc.error(f"{where}.address", f"{rtype} at {address:#06x} runs past 0xFFFF")
    unit = t.get("unit", "1")
    try:
        unit_si(unit)
    except (KeyError, TypeError):
        raise doc.error(f"{where}.unit", f"unknown unit {unit!r}") from None
    scale = _float(doc, t, "scale", where)
    if scale is not None and not (math.isfinite(scale) and scale > 0):
        raise doc.error(f"{where}.scale", f"scale must be a positive number, got {scale}")
    source = t.get("source")
    if source is not None and (not isinstance(source, str) or not source):
        raise doc.error(f"{where}.source", f"expected a signal name, got {source!r}")
    value = _float(doc, t, "value", where)
    access = _choice(doc, t, "access", where, ACCESS, "r")
    if source is None and value is None and access == "r":
        raise doc.error(where, "a read-only register needs a source signal or a constant value")
    negate = t.get("negate", False)
    if not isinstance(negate, bool):
        raise doc.error(f"{where}.negate", f"expected true or false, got {negate!r}")
    on_write = t.get("on_write", "store")
    if not isinstance(on_write, str) or not on_write:
        raise doc.error(f"{where}.on_write", f"expected an action name, got {on_write!r}")
    desc = t.get("description", "")
    return Register(
        name=name, address=address, type=rtype,
        word_order=_choice(doc, t, "word_order", where, ("big", "little"), word_order),
        unit=str(unit), scale=1.0 if scale is None else scale, source=source, value=value, access=access,
        negate=negate, overflow=_choice(doc, t, "overflow", where, ("saturate", "wrap"), "saturate"),
        minimum=_float(doc, t, "min", where), maximum=_float(doc, t, "max", where),
        on_write=on_write, description=str(desc))


def load_map(path: Path | str) -> RegisterMap:
    """Read a register map TOML (``protocols/modbus-registers.md``); raises ConfigError."""
    doc = load_toml(path)
    check_keys(doc, doc.data, ("map", "registers"), "")
    m = doc.data.get("map")
    if not isinstance(m, Mapping):
        raise doc.error(None, "missing the [map] table")
    check_keys(doc, m, _MAP_KEYS, "map")
    regs_raw = doc.data.get("registers")
    if not isinstance(regs_raw, list) or not regs_raw:
        raise doc.error(None, "missing [[registers]] entries")
    word_order = _choice(doc, m, "word_order", "map", ("big", "little"), "big")
    regs = [_register(doc, t, i, word_order) for i, t in enumerate(regs_raw)]
    names = [r.name for r in regs]
    for n in names:
        if names.count(n) > 1:
            raise doc.error(f"registers.{n}", f"register name {n!r} used twice")
    transparent = m.get("transparent_id")
    try:
        return RegisterMap(
            name=str(m.get("name", Path(path).stem)), registers=tuple(sorted(regs, key=lambda r: r.address)),
            device_id=_int(doc, m, "device_id", "map", 1, 1, 247),
            transparent_id=None if transparent is None else _int(doc, m, "transparent_id", "map", None, 1, 255),
            read_functions=_functions(doc, m, "read_functions", (3,)),
            write_functions=_functions(doc, m, "write_functions", (6, 16)),
            read_only_exception=_int(doc, m, "read_only_exception", "map", ILLEGAL_ADDRESS, 1, 4),
            max_count=_int(doc, m, "max_count", "map", 125, 1, 125),
            description=str(m.get("description", "")), path=doc.path)
    except ValueError as exc:  # overlapping registers
        raise ConfigError(doc.path, "registers", str(exc)) from None


__all__ = ["DEVICE_FAILURE", "GATEWAY_NO_RESPONSE", "ILLEGAL_ADDRESS", "ILLEGAL_FUNCTION", "ILLEGAL_VALUE",
           "ModbusError", "Register", "RegisterImage", "RegisterMap", "TYPES", "load_map"]
