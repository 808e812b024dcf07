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
if str(TOOLS) not in sys.path:
    sys.path.insert(0, str(TOOLS))
if str(TOOLS.parent) not in sys.path:   # the checkout's clrf only where none is installed
    sys.path.append(str(TOOLS.parent))

from bench.runner import main  # noqa: E402  (the package tools/bench/; sets POCL_MEMORY_LIMIT)

if __name__ == "__main__":
    sys.exit(main())
