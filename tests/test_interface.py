"""The model interface (clrf/interface.py) and the registry (clrf/registry.py): outside each
representation's package only the registry names the representations, and every registered
kind keeps the protocol.

"Names" is checked two ways over the product layers (runtime, interface, data, outputs,
training, viewer, cli): no import of a representation's package (every import counts, lazy
ones too: tests/test_layout.py's graph), and no string constant that is a kind's name or
holds a key "<kind>.field" (``model.kind == "grid"``, ``cfg.train.model in ("nerf", "hash")``,
``"lower grid.batch_size"`` in a message). Comments and docstrings may mention them. Two places are
outside the rule by design: clrf/__init__.py re-exports the grid's public functions
(``clrf.SparseGrid``, ``clrf.render_rays``), and clrf/references/ and clrf/testing/ hold
per-representation float64 references, test helpers and benchmarks.
"""
import ast
import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from clrf import registry
from clrf.interface import Budget, Kind, Model, Unsupported
from test_layout import PKG, import_graph, layer

PRODUCT = ("runtime", "interface", "corrections", "data", "outputs", "training", "viewer",
           "cli")
KEY = re.compile(r"\b([a-z]+)\.[a-z_]+\b")   # a configuration key: SECTION.field


def representation_mentions(pkg: Path, names) -> list:
    """'module:line: what' for imports of, and string constants naming, the representations
    ``names`` in the PRODUCT layers of the package at ``pkg``."""
    graph = import_graph(pkg)
    out = [f"{m}:{line}: imports {n}" for m, edges in sorted(graph.items())
           if layer(m) in PRODUCT for n, line in sorted(edges) if layer(n) in names]
    for p in sorted(pkg.rglob("*.py")):
        mod = ".".join(p.relative_to(pkg.parent).with_suffix("").parts).replace(".__init__", "")
        if layer(mod) not in PRODUCT:
            continue
        tree = ast.parse(p.read_text())
        docs = {id(n.body[0].value) for n in ast.walk(tree)
                if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef))
                and n.body and isinstance(n.body[0], ast.Expr)
                and isinstance(n.body[0].value, ast.Constant)}
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) \
                    and id(node) not in docs:
                v = node.value
                if v in names or any(k in names for k in KEY.findall(v)):
                    out.append(f"{mod}:{node.lineno}: the string {v!r}")
    return out


def test_only_the_registry_names_the_representations():
    names = tuple(registry.PACKAGES) + ("splat",)
    bad = representation_mentions(PKG, names)
    assert not bad, "outside the representations, only clrf/registry.py may name them:\n" + \
        "\n".join(bad)


def test_the_check_can_fail(tmp_path):
    pkg = tmp_path / "clrf"
    for d in ("training", "grid", "outputs"):
        (pkg / d).mkdir(parents=True)
        (pkg / d / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "grid" / "model.py").write_text("X = 1\n")
    (pkg / "training" / "loop.py").write_text(
        '"""Mentions grid in a docstring: allowed."""\n'
        "def f(model):\n    from ..grid.model import X\n    return model.kind == 'grid'\n")
    (pkg / "outputs" / "export.py").write_text("MSG = 'lower grid.reso'\n")
    bad = representation_mentions(pkg, ("grid",))
    assert bad == ["clrf.training.loop:3: imports clrf.grid.model",
                   "clrf.outputs.export:1: the string 'lower grid.reso'",
                   "clrf.training.loop:4: the string 'grid'"], bad


def test_every_kind_is_declared_completely():
    kinds = registry.kinds()
    assert [k.name for k in kinds] == list(registry.PACKAGES) and registry.DEFAULT == "grid"
    assert {k.batches for k in kinds} <= {"rays", "views"}
    from clrf.training.config import PRESETS, Config
    cfg = Config()
    for k in kinds:
        assert isinstance(k, Kind) and k.title and callable(k.create) and callable(k.memory)
        assert dataclasses.is_dataclass(k.config) and isinstance(cfg.section(k.name), k.config)
        assert set(k.scene_presets) <= set(PRESETS), k.name   # only known scene presets
        for name in k.presets:
            assert isinstance(k.config.from_preset(name), k.config)
        for ok, field, msg in cfg.section(k.name).checks():
            assert ok and field.startswith(f"{k.name}.") and msg, (k.name, field)
    with pytest.raises(KeyError, match="known: grid, nerf, hash, splat"):
        registry.get("voxels")


def test_cli_model_choices_come_from_the_registry():
    from clrf.cli.main import build_parser
    p = build_parser()
    sub = next(a for a in p._actions if a.dest == "cmd" or getattr(a, "choices", None)
               and "train" in (a.choices or {}))
    train = sub.choices["train"]
    model = next(a for a in train._actions if a.dest == "model")
    assert list(model.choices) == registry.names()
    for k in registry.kinds():
        assert k.title in model.help


@pytest.mark.parametrize("name", registry.PACKAGES)
def test_each_kind_keeps_the_protocol(device, name, tmp_path):
    """A tiny model of each kind through the whole interface: create, the budget hook, a step,
    render, export fields, state_dict and back; the memory estimate names its stages."""
    from clrf.data import load_dataset
    from clrf.training.config import build_config
    kind = registry.get(name)
    ds = load_dataset(None)
    small = {"grid": {"grid": {"reso": [[16, 16, 16]], "upsample_at": [], "batch_size": 256}},
             "nerf": {"nerf": {"preset": "tiny", "batch_rays": 64, "n_coarse": 8,
                               "n_fine": 0}},
             "hash": {"hash": {"preset": "tiny", "batch_rays": 64, "batch_samples": 0,
                               "samples": 16}},
             "splat": {"splat": {"preset": "tiny", "init_points": 200}}}[name]
    cfg = build_config("procedural", overrides={"train": {"model": name}, **small})
    model = kind.create(device, cfg, ds, (1.0, 1.0, 1.0))
    assert isinstance(model, Model) and model.kind == name
    # the budget hook: nothing scheduled at step 0 of these settings (no upsample); the hash
    # model takes the fraction as its learning-rate clock
    assert model.on_iteration(0, Budget(0, 3.0, 0.25, None)) is None
    if name == "hash":
        assert model.progress == 0.25
    from clrf.runtime.programs import upload
    q = device.queue
    if kind.batches == "views":
        # an image-space model: it draws its own training view and renders whole cameras
        assert model.batch_size == ds.hw[0] * ds.hw[1]
        loss = float(model.train_step(1, None, None, None))
        assert np.isfinite(loss) and loss >= 0
        c2w, hw = np.asarray(ds.poses[ds.split["test"][0]], np.float64), (16, 24)
        intr = np.float64([20.0, 20.0, 12.0, 8.0])
        out = model.render_image(c2w, intr, hw)
        assert out["rgb"].shape == (16, 24, 3) and out["depth"].shape == (16, 24) \
            and out["acc"].shape == (16, 24)
        with pytest.raises(Unsupported):   # the CLI reports it as bad input
            model.render(np.zeros((8, 3), np.float32), np.ones((8, 3), np.float32))
        with pytest.raises(Unsupported):   # no density field: the kind exports its own files
            model.export_fields(upload(q, np.zeros((5, 3), np.float32)), None)
        state = model.state_dict()
        assert state["kind"] == name
        back = kind.from_state(device, state, cfg)
        np.testing.assert_array_equal(back.render_image(c2w, intr, hw)["rgb"], out["rgb"])
    else:
        _rays_protocol(device, model, kind, cfg, name)
    stages, fix = kind.memory(cfg, 1000, device.caps, device.tuning, device.is_cpu)
    assert stages and all(s.total >= 0 for s in stages) and f"{name}." in fix
    assert isinstance(model.describe(), str) and model.describe()


def _rays_protocol(device, model, kind, cfg, name):
    """A ray-batch model's step, ray render, export fields and checkpoint round trip."""
    o = np.tile(np.float32([[0, 0, 4]]), (64, 1))
    d = np.tile(np.float32([[0, 0, -1]]), (64, 1))
    from clrf.runtime.programs import upload
    q = device.queue
    loss = float(model.train_step(1, upload(q, o), upload(q, d),
                                  upload(q, np.full((64, 3), 0.5, np.float32))))
    assert np.isfinite(loss) and loss >= 0
    out = model.render(o[:8], d[:8])
    assert out["rgb"].shape == (8, 3) and out["depth"].shape == (8,) and out["acc"].shape == (8,)
    pts = upload(q, np.zeros((5, 3), np.float32))
    dirs = upload(q, np.tile(np.float32([[0, 0, -1]]), (5, 1))) if model.view_dependent \
        else None
    sigma, rgb = model.export_fields(pts, dirs)
    assert sigma.shape == (5,) and rgb.shape == (5, 3) and np.isfinite(rgb.get()).all()
    assert 1 <= model.export_block(1 << 20) <= 1 << 20 and model.sample_length > 0
    state = model.state_dict()
    assert state["kind"] == name
    back = kind.from_state(device, state, cfg)
    np.testing.assert_array_equal(back.render(o[:8], d[:8])["rgb"], out["rgb"])
