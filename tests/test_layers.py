"""The layers hold (DESIGN.md): the imports of every module of hilsim/, walked with ``ast``.

* ``hilsim.protocols`` and ``hilsim.sim`` import nothing above them (links, devices, runtime, cli ...);
* ``hilsim.devices`` imports nothing from ``hilsim.runtime`` (it talks to the bridge through the
  device context, ``hilsim/devices/context.py``);
* no protocol name appears in ``hilsim.runtime`` (devices declare what they need);
* no import cycle between modules anywhere, counting imports made inside functions and under
  ``TYPE_CHECKING`` too (a cycle hidden there is still one).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "hilsim"


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in ROOT.rglob("*.py") if "_pb2" not in p.name}


def imports_of(path: Path, name: str) -> set[str]:
    """Every hilsim module ``path`` imports (absolute and relative, at any depth of the file)."""
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("hilsim"))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if not mod.startswith("hilsim"):
                continue
            out.add(mod)
            for a in node.names:  # `from hilsim.protocols import aris` imports a module
                out.add(f"{mod}.{a.name}")
    return out


def graph() -> dict[str, set[str]]:
    mods = modules()
    g: dict[str, set[str]] = {}
    for name, path in mods.items():
        deps = set()
        for imp in imports_of(path, name):
            # the module itself, or the package whose attribute was imported
            while imp and imp not in mods:
                imp = imp.rpartition(".")[0]
            if imp and imp != name and not name.startswith(imp + "."):
                deps.add(imp)
        g[name] = deps
    return g


def test_the_walk_sees_the_package():
    g = graph()
    assert "hilsim.runtime.bridge" in g and "hilsim.devices.base" in g["hilsim.devices.ddf_stream"]


@pytest.mark.parametrize("low", ["hilsim.protocols", "hilsim.sim"])
def test_bottom_layers_import_nothing_above_them(low):
    allowed = ("hilsim.protocols", "hilsim.sim", "hilsim.config", "hilsim.resources")
    bad = {m: sorted(d for d in deps if not d.startswith(allowed) and d != "hilsim")
           for m, deps in graph().items() if m.startswith(low)}
    assert {m: d for m, d in bad.items() if d} == {}


def test_devices_import_nothing_from_the_runtime():
    bad = {m: sorted(d for d in deps if d.startswith(("hilsim.runtime", "hilsim.cli")))
           for m, deps in graph().items() if m.startswith("hilsim.devices")}
    assert {m: d for m, d in bad.items() if d} == {}


def test_no_protocol_name_in_the_runtime():
    from hilsim.devices import REGISTRY

    names = sorted(REGISTRY, key=len, reverse=True)
    pattern = re.compile(r"""["'](%s)["']""" % "|".join(re.escape(n) for n in names))
    found = {}
    for path in (ROOT / "runtime").rglob("*.py"):
        hits = pattern.findall(path.read_text())
        if hits:
            found[path.name] = sorted(set(hits))
    assert found == {}


def test_no_import_cycle():
    g = graph()
    cycles: list[list[str]] = []
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(g.get(m, ())):
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d):] + [d])
            elif d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(g):
        if m not in state:
            visit(m)
    assert cycles == []
