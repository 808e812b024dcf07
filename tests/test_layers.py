"""The representations and the per-view corrections (clrf/corrections/, docs/architecture.md):
no representation package imports another, no model file refers to a correction by name, and
every correction class has the hooks of the protocol its kind of change asks for.

"Imports" counts every import, relative ones and those inside functions (tests/test_layout.py's
graph). "Refers to a correction by name" is, in a model file (``clrf/<package>/model.py``), an
attribute whose name has a correction's name as one of its ``_``-separated words (``.exposure``,
``.pose``, ``.lr_exposure``, ``.attach_exposure``, ``.pose_opt``), or a string constant,
docstrings aside, that is such a name (``"exposure"``, ``"pose_steps"``: a checkpoint key) or
holds a configuration key with one (``f"hash.exposure needs ..."``; prose such as "pose the
photos" is not a name): a branch on one correction, its settings or its checkpoint keys. A
model holds ``corrections`` and calls the list's hooks instead.
"""
from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
import re
from pathlib import Path

import numpy as np
import pytest

from clrf import corrections
from clrf.corrections import PROTOCOLS, RAYS, VIEWS, Views, build
from test_layout import PKG, REPRESENTATIONS, import_graph, layer


# ---- no representation imports another ---------------------------------------------------------
def cross_imports(pkg: Path, names=REPRESENTATIONS) -> list:
    """'module:line -> imported' for modules of a representation package ``names`` of the
    package at ``pkg`` importing another of them."""
    graph = import_graph(pkg)
    return [f"{m}:{line} -> {n}" for m, edges in sorted(graph.items()) if layer(m) in names
            for n, line in sorted(edges) if layer(n) in names and layer(n) != layer(m)]


def test_no_representation_imports_another():
    bad = cross_imports(PKG)
    assert not bad, ("a representation imports another (shared code belongs below them: "
                     "clrf/mlp, clrf/corrections, clrf/runtime):\n" + "\n".join(bad))


def test_the_import_check_can_fail(tmp_path):
    pkg = tmp_path / "clrf"
    for d in ("hash", "splat", "nerf", "mlp"):
        (pkg / d).mkdir(parents=True)
        (pkg / d / "__init__.py").write_text("")
        (pkg / d / "config.py").write_text("X = 1\n")
    (pkg / "__init__.py").write_text("")
    (pkg / "hash" / "model.py").write_text(
        "from ..mlp.config import X\n"                      # below: allowed
        "from .config import X as Y\n"                      # its own: allowed
        "def f():\n    from ..splat.config import X\n    return X\n"
        "import clrf.nerf.config\n")
    assert sorted(cross_imports(pkg)) == ["clrf.hash.model:4 -> clrf.splat.config",
                                          "clrf.hash.model:6 -> clrf.nerf.config"]


# ---- no model file names a correction ----------------------------------------------------------
def correction_classes() -> list:
    """Every correction class of clrf/corrections: a class with string ``name``, ``changes`` and
    ``batches`` (the protocols declare them without values; private bases have no
    ``batches``)."""
    found = {}
    for info in pkgutil.iter_modules(corrections.__path__):
        mod = importlib.import_module(f"clrf.corrections.{info.name}")
        for _, cls in inspect.getmembers(mod, inspect.isclass):
            if cls.__module__ == mod.__name__ and all(
                    isinstance(getattr(cls, k, None), str) for k in ("name", "changes", "batches")):
                found[cls.__qualname__] = cls
    return [found[k] for k in sorted(found)]


def correction_names() -> set:
    return {cls.name for cls in correction_classes()}


IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
KEY = re.compile(r"\b[a-z]+\.([a-z_]+)\b")   # a configuration key: SECTION.field


def _names_in(s: str, names) -> bool:
    """Whether string ``s`` is an identifier or holds a configuration key with one of ``names``
    as a ``_``-separated word."""
    fields = [s] if IDENTIFIER.fullmatch(s) else KEY.findall(s)
    return any(set(f.lower().split("_")) & names for f in fields)


def named_corrections(paths, names) -> list:
    """'file:line: what' for each reference to a correction ``names`` in the files ``paths``
    (module doc)."""
    out = []
    for p in paths:
        tree = ast.parse(Path(p).read_text(), str(p))
        docs = {id(n.body[0].value) for n in ast.walk(tree)
                if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef,
                                  ast.AsyncFunctionDef))
                and n.body and isinstance(n.body[0], ast.Expr)
                and isinstance(n.body[0].value, ast.Constant)}
        where = f"{Path(p).parent.name}/{Path(p).name}"
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and set(node.attr.lower().split("_")) & names:
                out.append(f"{where}:{node.lineno}: the attribute .{node.attr}")
            elif isinstance(node, ast.Constant) and isinstance(node.value, str) \
                    and id(node) not in docs and _names_in(node.value, names):
                out.append(f"{where}:{node.lineno}: the string {node.value!r}")
    return sorted(out, key=lambda s: (s.split(":")[0], int(s.split(":")[1])))


def model_files(pkg: Path = PKG) -> list:
    return sorted(pkg.glob("*/model.py"))


def test_no_model_file_names_a_correction():
    names = correction_names()
    assert names >= {"exposure", "bilateral", "pose"}, names
    files = model_files()
    assert {p.parent.name for p in files} >= set(REPRESENTATIONS), files
    bad = named_corrections(files, names)
    assert not bad, ("a model file refers to a correction by name (hold `corrections` and call "
                     "the list's hooks: clrf/corrections/base.py):\n" + "\n".join(bad))


def test_the_name_check_can_fail(tmp_path):
    p = tmp_path / "splat" / "model.py"
    p.parent.mkdir()
    p.write_text(
        '"""A docstring may say exposure and pose."""\n'
        "class M:\n"
        "    def step(self, c, state):\n"
        "        if self.exposure is not None:\n"
        "            lr = c.lr_exposure\n"
        "        poses = state.poses\n"                     # another word: allowed
        "        self.corrections.camera_step(0)\n"         # the list's hook: allowed
        "        why = 'or pose the photos'\n"               # prose: allowed
        "        return state['pose_steps'], f'hash.exposure {lr}'\n")
    assert named_corrections([p], {"exposure", "pose"}) == [
        "splat/model.py:4: the attribute .exposure",
        "splat/model.py:5: the attribute .lr_exposure",
        "splat/model.py:9: the string 'pose_steps'",
        "splat/model.py:9: the string 'hash.exposure '"]


# ---- every correction keeps its protocol -------------------------------------------------------
def _members(proto) -> tuple:
    """(data members, {method: signature}) of a protocol and the protocols it extends."""
    data, methods = set(), {}
    for base in reversed(proto.__mro__):
        if base in (object,) or not getattr(base, "_is_protocol", False):
            continue
        data |= set(getattr(base, "__annotations__", {}))
        for k, v in vars(base).items():
            if inspect.isfunction(v) and not k.startswith("_"):
                methods[k] = inspect.signature(v)
    return data, methods


def protocol_gaps(cls) -> list:
    """What class ``cls`` lacks of the protocol of its (changes, batches): missing members,
    and methods whose parameters do not start with the protocol's (extra ones need
    defaults)."""
    proto = PROTOCOLS.get((getattr(cls, "changes", None), getattr(cls, "batches", None)))
    if proto is None:
        return [f"{cls.__name__}: no protocol for changes {getattr(cls, 'changes', None)!r} "
                f"of {getattr(cls, 'batches', None)!r}"]
    data, methods = _members(proto)
    out = []
    for name, want in sorted(methods.items()):
        got = getattr(cls, name, None)
        if not callable(got):
            out.append(f"{cls.__name__}.{name}: missing")
            continue
        have = list(inspect.signature(got).parameters.values())
        need = [p.name for p in want.parameters.values()]
        if [p.name for p in have[:len(need)]] != need or any(
                p.default is inspect.Parameter.empty and p.kind not in (p.VAR_POSITIONAL,
                                                                       p.VAR_KEYWORD)
                for p in have[len(need):]):
            out.append(f"{cls.__name__}.{name}{inspect.signature(got)}: the protocol's is "
                       f"{name}{want}")
    for name in sorted(data - {"n_images"}):   # n_images: an instance's (test below)
        if not isinstance(getattr(cls, name, None), str):
            out.append(f"{cls.__name__}.{name}: missing")
    return out


def test_every_correction_class_has_its_protocols_hooks():
    classes = correction_classes()
    assert {c.__name__ for c in classes} >= {"Exposure", "RayExposure", "PoseCorrection",
                                             "BilateralGrid"}
    bad = [g for cls in classes for g in protocol_gaps(cls)]
    assert not bad, "\n".join(bad)


def test_the_protocol_check_can_fail():
    class Half:
        name, changes, batches = "half", "camera", "views"

        def camera(self, cam, v):
            return cam

        def step(self, v, viewmat):          # dR, dt missing
            pass

    gaps = protocol_gaps(Half)
    assert any(g.startswith("Half.step(") for g in gaps), gaps
    assert "Half.schedule: missing" in gaps and "Half.camera: missing" not in gaps
    Half.changes = "mood"
    assert protocol_gaps(Half) == ["Half: no protocol for changes 'mood' of 'views'"]


def test_the_corrections_each_section_turns_on_are_their_protocols_instances(device):
    """What the settings make of the splat and hash sections are instances of their protocols
    (members included), one of each correction class (the colour corrections of the splat
    section one at a time)."""
    from clrf.hash.config import HashConfig
    from clrf.splat.config import SplatConfig
    made = list(build(device, SplatConfig(exposure=True, pose_opt=True),
                      Views(3, pivots=lambda: [1.0, 2.0, 0.0]), VIEWS))
    made += list(build(device, SplatConfig(bilateral_grid=True, bilateral_grid_shape=[3, 2, 2]),
                       Views(3), VIEWS))
    made += list(build(device, HashConfig(exposure=True, pose_opt=True),
                       Views(3, pixels=16, viewmats=lambda: np.tile(np.eye(4), (3, 1, 1))),
                       RAYS))
    assert sorted(type(c).__name__ for c in made) == sorted(
        c.__name__ for c in correction_classes())
    for c in made:
        proto = PROTOCOLS[(c.changes, c.batches)]
        assert isinstance(c, proto) and c.n_images == 3, type(c).__name__
