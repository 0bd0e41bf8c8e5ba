"""The package's layers (``docs/architecture.md``), checked on the source itself.

Every import of every module is read from its syntax tree (those inside functions included,
since a deferred import is still a dependency), then:

- imports run downward only: core < engine < process < data < cli, and ``calendaring/__init__``
  (the public surface) may name any of them;
- no module imports itself back through others (no cycles);
- only the engine imports Taichi;
- the other packages, the notebooks, the benchmarks and the scripts import from the public
  surface ``calendaring`` only, and every name they take is in ``calendaring.__all__``;
- ``import calendaring`` imports neither Taichi nor h5py, and every public name resolves.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

import calendaring

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "calendaring"
#: layer of each top-level part of the package, lowest first
RANK = {"_version": 0, "core": 0, "engine": 1, "process": 2, "data": 3, "cli": 4, "__init__": 5}
CONSUMERS = ("surrogate", "inverse", "analysis", "notebooks", "benchmarks", "scripts")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__" and len(parts) > 1 and parts != ["calendaring", "__init__"]:
        parts = parts[:-1]
    return ".".join(parts)


MODULES = {_module_name(p): p for p in sorted(PKG.rglob("*.py"))}


def _resolve(name: str) -> str:
    """The project module an imported dotted name refers to (a package's submodule if the
    name is one, else the longest module prefix)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name


def _imports(source: str) -> list[tuple[str, int]]:
    """(imported dotted name, line) for every import in ``source``, ``from a import b`` giving
    ``a.b`` (a submodule, or an attribute that :func:`_resolve` trims)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out += [(f"{node.module}.{a.name}", node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level:
            raise AssertionError(f"relative import at line {node.lineno}: use absolute ones")
    return out


def _layer(module: str) -> str:
    parts = module.split(".")
    return "__init__" if len(parts) == 1 else parts[1]


def _graph() -> dict[str, set[str]]:
    graph = {}
    for mod, path in MODULES.items():
        deps = set()
        for name, _ in _imports(path.read_text()):
            if name.split(".")[0] == "calendaring":
                target = _resolve(name)
                if target and target != mod:
                    deps.add(target)
        graph[mod] = deps
    return graph


def test_the_layers_are_what_the_docs_say():
    assert {_layer(m) for m in MODULES} == set(RANK)
    assert len(MODULES) > 30


def test_imports_run_downward_only():
    bad = []
    for mod, path in MODULES.items():
        for name, line in _imports(path.read_text()):
            if name.split(".")[0] != "calendaring":
                continue
            target = _resolve(name)
            if RANK[_layer(target)] > RANK[_layer(mod)]:
                bad.append(f"{path.relative_to(ROOT)}:{line} ({_layer(mod)}) imports {target} "
                           f"({_layer(target)})")
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of two or more modules (Tarjan): the cycles."""
    index, low, stack, on, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return cycles


def test_no_import_cycles():
    graph = _graph()
    assert sum(len(d) for d in graph.values()) > 80
    assert not _cycles(graph), f"import cycles: {_cycles(graph)}"
    # the finder itself finds one
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_the_layer_check_can_fail(monkeypatch):
    """A fake upward import (the engine importing the run) is reported."""
    fake = "from calendaring.process.run import run\n"
    path = MODULES["calendaring.engine.timestep"]
    original = Path.read_text

    def read_text(self, *args, **kwargs):
        text = original(self, *args, **kwargs)
        return text + fake if self == path else text

    monkeypatch.setattr(Path, "read_text", read_text)
    with pytest.raises(AssertionError, match=r"engine/timestep\.py"):
        test_imports_run_downward_only()


def test_only_the_engine_imports_taichi():
    bad = [f"{path.relative_to(ROOT)}:{line}" for mod, path in MODULES.items()
           for name, line in _imports(path.read_text())
           if name.split(".")[0] == "taichi" and _layer(mod) != "engine"]
    assert not bad, f"taichi imported outside calendaring.engine: {bad}"


def _consumer_sources():
    for top in CONSUMERS:
        for path in sorted((ROOT / top).rglob("*.py")):
            yield path, path.read_text()
        for path in sorted((ROOT / top).rglob("*.ipynb")):
            cells = json.loads(path.read_text())["cells"]
            code = "\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "code")
            yield path, "\n".join(x for x in code.splitlines() if not x.startswith(("%", "!")))


def test_other_packages_use_the_public_surface_only():
    bad, seen = [], 0
    for path, source in _consumer_sources():
        for name, line in _imports(source):
            head, _, rest = name.partition(".")
            if head != "calendaring":
                continue
            seen += 1
            if rest and (rest not in calendaring.__all__ or "." in rest):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    assert seen > 50
    assert not bad, "imports past the public surface ``calendaring``:\n" + "\n".join(bad)


def test_the_surface_resolves_without_heavy_imports():
    code = ("import sys, calendaring\n"
            "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('taichi', 'h5py'))\n"
            "assert not heavy, heavy\n"
            "missing = [n for n in calendaring.__all__ if getattr(calendaring, n, None) is None]\n"
            "assert not missing, missing\n"
            "print('ok', len(calendaring.__all__))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[-1] == f"ok {len(calendaring.__all__)}"
    with pytest.raises(AttributeError, match="no attribute 'nonexistent'"):
        calendaring.nonexistent  # noqa: B018
