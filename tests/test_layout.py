"""The package layout (docs/architecture.md): the import graph of clrf/ has no cycle and its
layers import downwards only.

Every ``clrf/**/*.py`` is parsed with ``ast``; every import counts, also one inside a function
(a lazy import is still a dependency), and relative imports are resolved. ``from pkg import
name`` is an edge to ``pkg.name`` when that is a module, else to ``pkg``. Importing a module
runs its package's ``__init__`` as well, but that is not counted: it would make every
submodule depend on ``clrf/__init__.py``, which re-exports the public API from the layers.

Layers, bottom to top (a module may import its own layer and the ones below):

    runtime                 OpenCL devices, programs, memory planning, measuring, caches
    references              clrf/references/reference*.py: the float64 references (numpy only;
                            the grid's gradient self-check compares with one)
    interface               clrf/interface.py: the Model protocol and the Kind record
    mlp                     the fused MLP that nerf and hash share (its tiles, its tuner)
    corrections             per-view corrections (colour, camera) that models hold and the
                            trainer reports; no representation owns one
    grid, nerf, hash, splat the representations
    data                    datasets, cameras, protocols
    registry                clrf/registry.py: the representations by name (imported by name)
    outputs                 checkpoints, run directories, renders, exports, logs
    training                the trainer, run configuration, model kinds, metrics
    viewer, testing         the web viewer; test helpers, tolerances, benchmarks
    cli                     the command line (``clrf bench`` runs clrf/testing/benchmark.py)
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "clrf"

REPRESENTATIONS = ("grid", "nerf", "hash", "splat")
RANK = {"runtime": 0, "references": 0.5, "interface": 0.75, "mlp": 0.9, "corrections": 0.95,
        "grid": 1, "nerf": 1, "hash": 1,
        "splat": 1, "data": 1, "registry": 1.5, "outputs": 2, "training": 3, "viewer": 4,
        "testing": 4, "cli": 5}


def modules(pkg: Path = PKG) -> dict:
    """{dotted module name: (path, is_package)} for every .py file under ``pkg``."""
    out = {}
    for p in sorted(pkg.rglob("*.py")):
        parts = list(p.relative_to(pkg.parent).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        if is_pkg:
            parts = parts[:-1]
        out[".".join(parts)] = (p, is_pkg)
    return out


def _absolute(node: ast.ImportFrom, mod: str, is_pkg: bool) -> str:
    if node.level == 0:
        return node.module or ""
    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
    if node.level > 1:
        base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def import_graph(pkg: Path = PKG) -> dict:
    """{module: {(imported module, line)}} over the clrf modules, every import counted."""
    mods = modules(pkg)

    def known(name):
        while name not in mods and "." in name:
            name = name.rsplit(".", 1)[0]
        return name if name in mods else None

    graph = {}
    for mod, (path, is_pkg) in mods.items():
        edges = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _absolute(node, mod, is_pkg)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base
                           for a in node.names]
            for t in targets:
                if t == "clrf" or t.startswith("clrf."):
                    k = known(t)
                    if k is not None and k != mod:
                        edges.add((k, node.lineno))
        graph[mod] = edges
    return graph


def find_cycle(graph: dict):
    """One import cycle as a list of modules (first == last), or None."""
    state, stack = {}, []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for n, _ in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state:
                c = visit(n)
                if c:
                    return c
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state:
            c = visit(m)
            if c:
                return c
    return None


def layer(mod: str):
    """The layer of a module (its first package under clrf, or "references" for the float64
    references of clrf/testing/), None for clrf/__init__.py."""
    if mod.startswith("clrf.references.reference"):
        return "references"
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else None


def upward_imports(graph: dict, below: tuple, forbidden: tuple) -> list:
    """'importer:line -> imported' for modules of the layers ``below`` importing from the
    layers ``forbidden``."""
    return [f"{m}:{line} -> {n}" for m, edges in sorted(graph.items()) if layer(m) in below
            for n, line in sorted(edges) if layer(n) in forbidden]


@pytest.fixture(scope="module")
def graph():
    return import_graph()


def test_every_module_is_in_a_layer(graph):
    loose = [m for m in graph if m != "clrf" and layer(m) not in RANK]
    assert not loose, f"modules outside the layers of docs/architecture.md: {loose}"


def test_no_import_cycle(graph):
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_runtime_imports_no_higher_layer(graph):
    bad = upward_imports(graph, ("runtime",),
                         REPRESENTATIONS + ("data", "outputs", "training", "viewer", "cli",
                                            "testing", "references"))
    assert not bad, "the runtime imports from higher layers:\n" + "\n".join(bad)


def test_representations_import_no_training_outputs_or_ui(graph):
    bad = upward_imports(graph, REPRESENTATIONS,
                         ("data", "outputs", "training", "viewer", "cli"))
    assert not bad, "a representation imports from higher layers:\n" + "\n".join(bad)


def test_layers_point_down(graph):
    bad = [f"{m}:{line} -> {n}" for m, edges in sorted(graph.items())
           for n, line in sorted(edges)
           if layer(m) in RANK and layer(n) in RANK and RANK[layer(n)] > RANK[layer(m)]]
    assert not bad, "imports from a higher layer:\n" + "\n".join(bad)


TEST_ENV = re.compile(r"""(environ\b[^\n]*|getenv\([^\n]*)["']CLRF_TEST""")


def test_no_test_hook_in_package_code():
    """Test-only switches are set by the tests (a parameter, a module attribute), never read
    from CLRF_TEST* variables by package code. clrf/testing/ (the tests' helpers) may."""
    bad = [f"{p.relative_to(ROOT)}:{i}" for p in sorted(PKG.rglob("*.py"))
           if "testing" not in p.relative_to(PKG).parts
           for i, line in enumerate(p.read_text().splitlines(), 1) if TEST_ENV.search(line)]
    assert not bad, "package code reads a CLRF_TEST* variable: " + ", ".join(bad)


def test_the_checks_can_fail(tmp_path):
    """The graph sees a cycle through a function-level relative import, and an upward one."""
    pkg = tmp_path / "clrf"
    (pkg / "runtime").mkdir(parents=True)
    (pkg / "grid").mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "runtime" / "__init__.py").write_text("")
    (pkg / "grid" / "__init__.py").write_text("")
    (pkg / "runtime" / "device.py").write_text("from . import check\n")
    (pkg / "runtime" / "check.py").write_text("def f():\n    from ..grid.render import g\n")
    (pkg / "grid" / "render.py").write_text("from clrf.runtime import device\n")
    g = import_graph(pkg)
    assert find_cycle(g) == ["clrf.grid.render", "clrf.runtime.device", "clrf.runtime.check",
                             "clrf.grid.render"]
    assert upward_imports(g, ("runtime",), REPRESENTATIONS) == [
        "clrf.runtime.check:2 -> clrf.grid.render"]
