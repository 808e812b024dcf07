#!/usr/bin/env python3
"""Numerical-stability matrix of clrf (the package tools/stability/; see its docstring).

    python tools/stability.py [--quick] --out DIR         # DIR/stability.md, DIR/stability.json
    python tools/stability.py --convergence --out DIR     # also DIR/convergence.csv
"""
import sys
from pathlib import Path

TOOLS = Path(__file__).resolve().parent
if str(TOOLS) not in sys.path:
    sys.path.insert(0, str(TOOLS))
if str(TOOLS.parent) not in sys.path:   # the checkout's clrf only where none is installed
    sys.path.append(str(TOOLS.parent))

from stability.runner import main  # noqa: E402  (the package tools/stability/)

if __name__ == "__main__":
    sys.exit(main())
