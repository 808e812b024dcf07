#!/usr/bin/env python3
"""Numerical-stability matrix of clrf (the package tools/stability/; see its docstring).

    python tools/stability.py [--quick] --out DIR         # DIR/stability.md, DIR/stability.json
    python tools/stability.py --convergence --out DIR     # also DIR/convergence.csv
"""
import sys
from pathlib import Path

TOOLS = Path(__file__).resolve().parent
for _p in (str(TOOLS.parent), str(TOOLS)):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from stability.runner import main  # noqa: E402  (the package tools/stability/)

if __name__ == "__main__":
    sys.exit(main())
