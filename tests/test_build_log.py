"""Every kernel file builds with an empty compiler log (no warnings) on this device, with the
defines the library and tools use: users never see compiler output, and a warning introduced
in cl/ fails here instead of being hidden by the filter in clrf/programs.py."""
import itertools

import pytest

from clrf.nerf.mlp import MLPSpec
from clrf.programs import build, build_log


def _grid_render():
    base = {"SH_DEGREE": 2, "GRAD_MODE": 0, "GRAD_SLOTS": 0, "SAMPLE_RECORD": 0,
            "TRACK_TOUCHED": 0, "COMPENSATED_SUMS": 0, "CLRF_PREFETCH": 1, "T_STOP": 1e-4,
            "BLOCK": 8}
    for deg in (0, 1, 3):
        yield {**base, "SH_DEGREE": deg}
    for mode, (slots, rec, locks), touched in itertools.product(
            (0, 1), ((0, 0, 0), (2, 0, 0), (2, 1, 0), (2, 0, 4), (2, 1, 4)), (0, 1)):
        yield {**base, "GRAD_MODE": mode, "GRAD_SLOTS": slots, "SAMPLE_RECORD": rec,
               "GRAD_LOCKS": locks, "TRACK_TOUCHED": touched}
    yield {**base, "COMPENSATED_SUMS": 1, "CLRF_PREFETCH": 0, "BLOCK": 0}
    for mode, (slots, rec, locks) in itertools.product(
            (0, 1), ((0, 0, 0), (2, 1, 0), (2, 1, 4))):   # GridModel + MSI
        yield {**base, "BG_PER_RAY": 1, "GRAD_MODE": mode, "GRAD_SLOTS": slots,
               "SAMPLE_RECORD": rec, "GRAD_LOCKS": locks, "TRACK_TOUCHED": 1}
    # the distributed bricks (clrf/grid/bricks.py): no early termination
    for (slots, rec, locks), touched, pf in itertools.product(
            ((0, 0, 0), (2, 1, 0), (2, 1, 4)), (0, 1), (0, 1)):
        yield {**base, "BRICK": 1, "CLRF_PREFETCH": pf, "T_STOP": 0.0, "GRAD_SLOTS": slots,
               "SAMPLE_RECORD": rec, "GRAD_LOCKS": locks, "TRACK_TOUCHED": touched}


# (file, defines) for every program the library and tools build, grid_render.cl over the
# combinations of its switches that change which code is compiled.
CASES = ([("grid_render.cl", d) for d in _grid_render()]
         + [("grid_ops.cl", {"SH_DEGREE": d, "TV_EPS": 1e-9}) for d in (0, 1, 2, 3)]
         + [("composite.cl", {"GRAD_MODE": m}) for m in (0, 1)]
         + [("encode.cl", {"ENC_FREQS": f, "ENC_INCLUDE_INPUT": 1}) for f in (4, 10)]
         + [("sample.cl", {}), ("batch.cl", {}), ("probe.cl", {}), ("bench.cl", {}),
            ("bench.cl", {"FMA_CHAINS": 8, "FMA_ITERS": 20000})]
         + [("optim.cl", {"OPT_MODE": m}) for m in (0, 1, 2)]
         + [("background.cl", {"BG_LAYERS": 32, "BG_H": 128})]
         + [("mlp.cl", MLPSpec().defines()),
            ("mlp.cl", MLPSpec(width=64, depth=1, color_width=64, in_dim=32, dir_dim=16,
                               sigma_act="trunc_exp", color_depth=2, features=16).defines())]
         + [("hash.cl", {"HASH_LEVELS": 16, "HASH_FEATURES": f, "HASH_LOG2_T": 19,
                         "HASH_GRAD_OWNED": o}) for f in (1, 2, 4) for o in (0, 1)]
         + [("hash_occ.cl", {}), ("hash_march.cl", {})])


@pytest.mark.parametrize("source,defines", CASES,
                         ids=[f"{s}-{i}" for i, (s, _) in enumerate(CASES)])
def test_build_log_empty(device, source, defines):
    prg = build(device, source, defines)
    assert build_log(prg.cl_program, device) == "", f"{source} {defines}"


def test_verbose_build_prints_only_non_empty_logs(device, capsys, monkeypatch):
    build(device, "probe.cl", {}, verbose=True)
    assert capsys.readouterr().err == ""     # clean build: nothing shown even when verbose
    monkeypatch.setattr("clrf.programs.build_log", lambda prg, dev: "warning: stand-in log")
    build(device, "probe.cl", {}, verbose=True)
    assert "probe.cl" in capsys.readouterr().err
