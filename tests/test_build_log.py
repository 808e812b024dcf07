"""Build logs: every kernel file builds without compiler diagnostics on this device, with the
defines the library and tools use (a warning introduced in cl/ fails here), and the split of a
log into diagnostics and implementation chatter (clrf/runtime/buildlog.py) holds on real logs of each
OpenCL implementation, stored in tests/fixtures/build_logs/ by tools/capture_build_logs.py."""
import itertools
import os
from collections import Counter
import json
from pathlib import Path

import pytest

from clrf.runtime.buildlog import CHATTER, diagnostics, is_chatter, split_log
from clrf.mlp.mlp import MLPSpec
from clrf.runtime.programs import build, build_log
from clrf.testing import impls

FIXTURES = Path(__file__).parent / "fixtures" / "build_logs"
KERNELS = FIXTURES / "kernels"


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
    # the GPU shape (per-corner colours), with and without compensated sums and slots
    for deg, comp, slots in itertools.product((0, 2, 3), (0, 1), (0, 2)):
        yield {**base, "SH_PER_CORNER": 1, "SH_DEGREE": deg, "COMPENSATED_SUMS": comp,
               "GRAD_SLOTS": slots, "GRAD_MODE": 1, "TRACK_TOUCHED": 1}
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
def test_build_without_diagnostics(device, source, defines):
    # compiled here, not loaded from the run's binary cache (whose log is not the compiler's)
    prg = build(device, source, defines, binary_cache=False)
    found = diagnostics(build_log(prg.cl_program, device))
    assert found == [], f"{source} {defines}:\n" + "\n".join(d.text for d in found)


def _kernels_dir(monkeypatch):
    """Point programs.build at the fixture kernels (tests/fixtures/build_logs/kernels)."""
    monkeypatch.setattr("clrf.runtime.programs.cl_dir", lambda: KERNELS)


def test_clean_build_prints_nothing(device, capsys):
    """Chatter (Intel writes it into every log) is not shown; the log is there, verbose."""
    prg = build(device, "probe.cl", {}, binary_cache=False)
    assert capsys.readouterr().err == ""
    log = build_log(prg.cl_program, device)
    build(device, "probe.cl", {}, verbose=True, binary_cache=False)
    err = capsys.readouterr().err
    assert (log in err and "probe.cl" in err) if log else err == ""


def test_warnings_are_printed_with_location(device, capsys, monkeypatch):
    """A kernel with three warnings: on stderr with file:line:col, no chatter. Mesa rusticl
    22.3 drops warnings from the log of a successful build: then nothing is shown."""
    _kernels_dir(monkeypatch)
    prg = build(device, "warning.cl", {}, binary_cache=False)
    log = build_log(prg.cl_program, device)
    err = capsys.readouterr().err
    if "warning" not in log.lower():
        assert err == ""
        return
    assert "warning.cl" in err.splitlines()[0]
    for loc in WARNING_SITES:
        assert f":{loc[0]}:{loc[1]}:" in err, (loc, err)
    assert not any(is_chatter(line) for line in err.splitlines()), err


def test_verbose_shows_raw_log(device, capsys, monkeypatch):
    monkeypatch.setattr("clrf.runtime.programs.build_log", lambda prg, dev: "Compilation started\nDone.")
    build(device, "probe.cl", {}, binary_cache=False)
    assert capsys.readouterr().err == ""
    build(device, "probe.cl", {}, verbose=True, binary_cache=False)
    err = capsys.readouterr().err
    assert "probe.cl" in err and "Compilation started\nDone." in err


# ---- the split, on stored logs of each implementation ------------------------------------

# Where the fixture kernels' diagnostics are, (line, column) in the file (see their comments).
WARNING_SITES = {(7, 1), (12, 13), (13, 11)}   # kernels/warning.cl; (13, 11) has two notes
HEADER_SITE = (4, 12)                           # kernels/header_warning.h
ERROR_SITE = (4, 33)                            # kernels/error.cl

FIXTURE_CASES = sorted(p.stem for p in FIXTURES.glob("*.txt"))


def _fixture(stem):
    meta = json.loads((FIXTURES / f"{stem}.json").read_text())
    return (FIXTURES / f"{stem}.txt").read_text(), meta


def test_fixtures_cover_each_implementation():
    impls = {json.loads(p.read_text())["implementation"] for p in FIXTURES.glob("*.json")}
    assert len(impls) >= 4, impls
    for impl in impls:
        cases = {p.stem.split("_", 1)[1] for p in FIXTURES.glob(f"{impl}_*.json")}
        assert {"clean", "warning", "werror", "header_warning", "error"} <= cases, (impl, cases)


@pytest.mark.parametrize("stem", FIXTURE_CASES)
def test_split_partitions_the_log(stem):
    """Every non-blank line is either chatter or part of exactly one diagnostic."""
    log, _ = _fixture(stem)
    s = split_log(log)
    n_diag = sum(len(d.lines) for d in s.diagnostics)
    assert n_diag + len(s.chatter) == sum(1 for line in log.splitlines() if line.strip())


@pytest.mark.parametrize("stem", FIXTURE_CASES)
def test_fixture_diagnostics(stem):
    log, meta = _fixture(stem)
    case = meta["case"]
    found = diagnostics(log)
    if case.startswith("clean"):
        assert found == [], [d.text for d in found]
        return
    if case == "error":
        assert not meta["built"]
        assert len(found) == 1, [d.text for d in found]
        d = found[0]
        assert (d.severity, (d.line, d.col)) == ("error", ERROR_SITE)
        assert d.message.startswith("expected ';'"), d.message
        return
    if "warning" not in log.lower() and meta["built"]:
        # rusticl 22.3: no warnings in the log of a successful build
        assert found == [], [d.text for d in found]
        return
    if case == "header_warning":
        assert len(found) == 1, [d.text for d in found]
        d = found[0]
        # NVIDIA's compiler (CUDA 13.0) makes this conversion an error and fails the build
        severity = "warning" if meta["built"] else "error"
        assert (d.severity, (d.line, d.col)) == (severity, HEADER_SITE)
        assert d.file.endswith("header_warning.h"), d.file
        if "In file included from" in log:
            assert d.lines[0].startswith("In file included from"), d.lines
        return
    # warning, werror (an error unless the implementation ignores -Werror: Oclgrind 21.10)
    severity = "warning" if meta["built"] else "error"
    assert Counter((d.line, d.col) for d in found) == Counter(WARNING_SITES), \
        [d.text for d in found]
    assert {d.severity for d in found} == {severity}
    assert len({d.file for d in found}) == 1
    n_notes = log.count("note:")
    for d in found:
        assert len(d.notes) == (n_notes if (d.line, d.col) == (13, 11) else 0), d.text
        assert all((n.line, n.col) == (13, 11) for n in d.notes)


# ---- the split, on hand-written lines ----------------------------------------------------

def test_split_shapes():
    log = "\n".join([
        "Compilation started",
        "<stdin>:3:9: warning: unused variable 'x'",
        "    int x;",
        "        ^",
        "<source>:5:1: note: declared here",
        "warning: /tmp/k.cl:8:2: implicit conversion",
        "error: unknown option '-cl-foo'",
        "2 warnings and 1 error generated.",
        "Done."])
    s = split_log(log)
    assert [(d.severity, d.location) for d in s.diagnostics] == [
        ("warning", "<stdin>:3:9"), ("warning", "/tmp/k.cl:8:2"), ("error", "")]
    first = s.diagnostics[0]
    assert first.lines[1:3] == ["    int x;", "        ^"]
    assert [(n.file, n.line, n.message) for n in first.notes] == [("<source>", 5, "declared here")]
    assert s.chatter == ["Compilation started", "2 warnings and 1 error generated.", "Done."]


def test_unrecognised_lines_are_diagnostics():
    """A line no pattern knows is shown (never hidden as chatter), as is an orphan note."""
    s = split_log("Compilation started\nSomething new went wrong\nnote: k.cl:1:1: see here\nDone.")
    assert [(d.severity, d.message) for d in s.diagnostics] == [
        ("unknown", "Something new went wrong"), ("note", "see here")]
    assert diagnostics("") == []


def test_chatter_patterns_name_their_implementation():
    assert all(isinstance(p, str) and who for p, who in CHATTER)
    # a warning never reads as chatter, whatever its wording
    assert not is_chatter("input.cl:1:1: warning: Compilation started")
    assert not is_chatter("remark: input.cl:3:1: loop not vectorized")


LIBRARY_BUILD = """
import sys, uuid
import numpy as np
import pyopencl.array as cla
from pyopencl.elementwise import ElementwiseKernel
import clrf
dev = clrf.Device(sys.argv[1])
# a kernel no cache has seen, built by pyopencl itself (as its array operations do)
k = ElementwiseKernel(dev.context, "float *x", f"x[i] = x[i] * 2.0f + {uuid.uuid4().int % 997}.0f",
                      "clrf_quiet_check")
x = cla.zeros(dev.queue, 16, np.float32)
k(x)
print(float(x.get()[0]))
"""


@pytest.mark.parametrize("impl", sorted(impls.present()))
def test_library_builds_print_no_chatter(impl):
    """pyopencl's own kernels (fills, reductions, scans) print no "Non-empty compiler output"
    warning in a clrf process: Intel's runtime writes progress text into every build log."""
    import subprocess
    import sys
    r = subprocess.run([sys.executable, "-c", LIBRARY_BUILD, impl], capture_output=True,
                       text=True, timeout=300, env={**os.environ, "PYTHONWARNINGS": "default"})
    assert r.returncode == 0, r.stderr
    assert "CompilerWarning" not in r.stderr and "compiler output" not in r.stderr, r.stderr
