"""The suite's two tiers (tests/conftest.py): the default run keeps every test; the quick
selection (`pytest -m quick -n auto`, the inner loop) touches every test module with fewer
tests. And the suite's cost is measured by tools/suite_times.py from what --clrf-times records.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tools"))

import suite_times  # noqa: E402


def _collect(*args) -> list:
    env = dict(os.environ, CLRF_TEST_IMPLS="default")
    r = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:xdist",
                        "-p", "no:cacheprovider", *args, "tests"], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return [ln for ln in r.stdout.splitlines() if "::" in ln]


def test_the_quick_selection_touches_every_module_with_fewer_tests():
    quick, every = _collect("-m", "quick"), _collect()
    modules = {p.relative_to(ROOT).as_posix() for p in (ROOT / "tests").glob("test_*.py")}
    touched = {n.split("::", 1)[0] for n in quick}
    assert touched == modules, f"not touched by -m quick: {sorted(modules - touched)}"
    assert set(quick) < set(every)
    assert len(quick) < len(every) / 3, (len(quick), len(every))


def test_the_table_adds_up_by_file():
    rows = [
        {"nodeid": "tests/test_a.py::t1", "when": "setup", "outcome": "passed", "wall": 2.0,
         "cpu": 3.0, "fixtures": [["built", "module", 1.5, 2.5]]},
        {"nodeid": "tests/test_a.py::t1", "when": "call", "outcome": "passed", "wall": 1.0,
         "cpu": 1.0, "fixtures": []},
        {"nodeid": "tests/test_a.py::t1", "when": "teardown", "outcome": "passed", "wall": 0.5,
         "cpu": 0.0, "fixtures": []},
        {"nodeid": "tests/test_b.py::t2", "when": "setup", "outcome": "skipped", "wall": 0.1,
         "cpu": 0.1, "fixtures": []},
        {"nodeid": "tests/test_b.py::t2", "when": "teardown", "outcome": "passed", "wall": 0.0,
         "cpu": 0.0, "fixtures": []},
    ]
    s = suite_times.summarise({"rows": rows})
    a, b = s["files"]["tests/test_a.py"], s["files"]["tests/test_b.py"]
    assert (a["wall"], a["cpu"], a["count"], a["setup"]) == (3.5, 4.0, 1, 2.0)
    assert (b["count"], b["skipped"]) == (1, 1)
    md = suite_times.table({"rows": rows, "elapsed": 60.0, "workers": 2, "cpus": 2}, top=3)
    lines = md.splitlines()
    assert lines[0].startswith("Suite: 2 tests in 2 files, 1.0 min elapsed with 2 worker(s)")
    first = next(ln for ln in lines if ln.startswith("| tests/"))
    assert first.startswith("| tests/test_a.py | 3.5 |")             # the largest file first
    assert any("fixture | tests/test_a.py: built (module; first asked by t1)" in ln
               for ln in lines)


def test_the_times_are_recorded_for_a_real_run(tmp_path):
    """--clrf-times in a child pytest of two small tests: a row per phase, CPU seconds, the
    module fixture's set-up."""
    test = tmp_path / "test_tiny.py"
    test.write_text("import pytest, time\n"
                    "@pytest.fixture(scope='module')\n"
                    "def slow_thing():\n    time.sleep(0.2)\n    return 1\n"
                    "def test_one(slow_thing):\n    assert slow_thing == 1\n"
                    "def test_two():\n    sum(range(10**6))\n")
    (tmp_path / "conftest.py").write_text((ROOT / "tests" / "conftest.py").read_text())
    out = tmp_path / "times.json"
    env = dict(os.environ, CLRF_TEST_IMPLS="default")
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:xdist", "-p",
                        "no:cacheprovider", "--rootdir", str(tmp_path), "--clrf-times", str(out),
                        str(test)], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    data = json.loads(out.read_text())
    phases = {(row["nodeid"].split("::")[-1], row["when"]) for row in data["rows"]}
    assert {("test_one", "setup"), ("test_one", "call"), ("test_two", "call")} <= phases
    setup = next(row for row in data["rows"] if row["nodeid"].endswith("test_one")
                 and row["when"] == "setup")
    assert setup["wall"] >= 0.2 and any(f[0] == "slow_thing" and f[2] >= 0.2
                                        for f in setup["fixtures"])
    assert all(row["cpu"] is not None and row["cpu"] >= 0 for row in data["rows"])
