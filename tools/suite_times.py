"""The test suite's cost, by file: run the tests with every test's and fixture's wall and CPU
seconds recorded (tests/conftest.py, ``--clrf-times``), and tabulate them.

    python tools/suite_times.py run OUT.json [-- PYTEST ARGS]    # default args: -q -n auto
    python tools/suite_times.py table OUT.json[.gz] [--top 10]   # Markdown, to stdout

``run`` uses the venv's pytest (.venv/bin/pytest, else the one on PATH) with CLRF_DATA as set,
and writes OUT.json (the raw rows) and OUT.md (the table) beside it.

How to read the table (docs/guide.md, "What the suite costs"):
- **wall** is the sum of a file's test phases (set-up, call, tear-down) as each worker saw
  them. With two workers the suite's elapsed time is about half the sum over all files, so a
  file's share of the sum is its share of the elapsed time.
- **CPU** counts the worker process (the OpenCL runtime's threads included) and the child
  processes it waited for (compilers, ``clrf`` commands, ``mpirun``). CPU well above wall means
  the file keeps both cores busy (it delays the other worker); well below, it waits (a sleep,
  a server, a subprocess not yet reaped).
- **count** is the number of tests that ran (passed, failed or skipped).
- The largest items list single tests and the fixtures whose set-up costs the most (a
  module- or session-scoped fixture is paid by the first test that asks for it).
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _pytest() -> list:
    venv = ROOT / ".venv" / "bin" / "pytest"
    if venv.is_file():
        return [str(venv)]
    found = shutil.which("pytest")
    if not found:
        raise SystemExit("suite_times: no pytest (bash tools/setup.sh test)")
    return [found]


def read(path: Path) -> dict:
    """A recorded run (``.json``, or ``.json.gz`` as kept in tools/results)."""
    if path.suffix == ".gz":
        import gzip
        with gzip.open(path, "rt") as f:
            return json.load(f)
    return json.loads(path.read_text())


def summarise(data: dict) -> dict:
    """{'files': {file: {wall, cpu, count, setup, teardown}}, 'tests': [...], 'fixtures': [...]}."""
    files = defaultdict(lambda: {"wall": 0.0, "cpu": 0.0, "count": 0, "setup": 0.0,
                                 "failed": 0, "skipped": 0})
    tests = defaultdict(lambda: {"wall": 0.0, "cpu": 0.0})
    fixtures = []
    for r in data["rows"]:
        f = r["nodeid"].split("::", 1)[0]
        row = files[f]
        row["wall"] += r["wall"] or 0.0
        row["cpu"] += r["cpu"] or 0.0
        if r["when"] == "setup":
            row["setup"] += r["wall"] or 0.0
        if r["when"] == "call" or (r["when"] == "setup" and r["outcome"] == "skipped"):
            row["count"] += 1
            row["skipped"] += r["outcome"] == "skipped"
        row["failed"] += r["outcome"] == "failed"
        t = tests[r["nodeid"]]
        t["wall"] += r["wall"] or 0.0
        t["cpu"] += r["cpu"] or 0.0
        for name, scope, wall, cpu in r.get("fixtures") or []:
            fixtures.append({"file": f, "fixture": name, "scope": scope, "wall": wall,
                             "cpu": cpu, "first_user": r["nodeid"]})
    return {"files": dict(files), "tests": [dict(v, nodeid=k) for k, v in tests.items()],
            "fixtures": fixtures}


def table(data: dict, top: int = 10) -> str:
    s = summarise(data)
    files = sorted(s["files"].items(), key=lambda kv: -kv[1]["wall"])
    total = sum(v["wall"] for _, v in files) or 1.0
    out = [f"Suite: {sum(v['count'] for _, v in files)} tests in {len(files)} files, "
           f"{data['elapsed'] / 60:.1f} min elapsed with {data.get('workers') or 1} "
           f"worker(s) on {data.get('cpus')} CPUs; the files' wall times add up to "
           f"{total / 60:.1f} min.", "",
           "| file | wall s | share | CPU s | CPU/wall | tests | skipped | set-up s |",
           "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for f, v in files:
        out.append(f"| {f} | {v['wall']:.1f} | {100 * v['wall'] / total:.1f} % | "
                   f"{v['cpu']:.1f} | {v['cpu'] / v['wall'] if v['wall'] else 0:.2f} | "
                   f"{v['count']} | {v['skipped']} | {v['setup']:.1f} |")
    items = [("test", t["nodeid"], t["wall"], t["cpu"]) for t in s["tests"]]
    items += [("fixture", f"{f['file']}: {f['fixture']} ({f['scope']}; first asked by "
                          f"{f['first_user'].split('::', 1)[-1]})", f["wall"], f["cpu"])
              for f in s["fixtures"] if f["scope"] != "function"]
    items.sort(key=lambda x: -x[2])
    out += ["", f"The {top} largest items (a fixture's set-up is also inside its first "
                f"test's wall time):", "", "| | item | wall s | CPU s |", "| --- | --- | ---: | ---: |"]
    for kind, name, wall, cpu in items[:top]:
        out.append(f"| {kind} | {name} | {wall:.1f} | {cpu:.1f} |")
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    rest = []
    if "--" in argv:
        i = argv.index("--")
        argv, rest = argv[:i], argv[i + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="run the suite with the times recorded")
    r.add_argument("out", type=Path)
    t = sub.add_parser("table", help="the table of a recorded run")
    t.add_argument("out", type=Path)
    for p in (r, t):
        p.add_argument("--top", type=int, default=10, help="largest items listed")
    a = ap.parse_args(argv)
    out = a.out.resolve()
    if a.cmd == "run":
        args = rest or ["-q", "-n", "auto"]
        t0 = time.time()
        rc = subprocess.run([*_pytest(), *args, "--clrf-times", str(out)], cwd=ROOT).returncode
        print(f"suite_times: pytest exited {rc} after {(time.time() - t0) / 60:.1f} min",
              file=sys.stderr)
        if not out.is_file():
            print(f"suite_times: pytest wrote no {out}", file=sys.stderr)
            return rc or 1
    data = read(out)
    md = table(data, a.top)
    if a.cmd == "run":
        out.with_suffix(".md").write_text(md)
    print(md)
    return 0 if a.cmd == "table" else rc


if __name__ == "__main__":
    sys.exit(main())
