#!/usr/bin/env python3
"""clrf benchmark runner (the package tools/bench/; see its docstring).

    python tools/bench.py                       # everything; JSON to bench-results/bench-<time>.json
    python tools/bench.py --only 'grid.*128*'   # fnmatch pattern(s) on the benchmark names
    python tools/bench.py --quick               # smoke mode: tiny sizes, one repeat, checks only
    python tools/bench.py --list                # names and parameters, nothing run
"""
import sys
from pathlib import Path

TOOLS = Path(__file__).resolve().parent
for _p in (str(TOOLS.parent), str(TOOLS)):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from bench.runner import main  # noqa: E402  (the package tools/bench/; sets POCL_MEMORY_LIMIT)

if __name__ == "__main__":
    sys.exit(main())
