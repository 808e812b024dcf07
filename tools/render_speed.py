"""Forward and forward+backward throughput of the grid renderer (see clrf/benchmark.py)."""
import sys
from pathlib import Path

sys.path.append(str(Path(__file__).resolve().parent.parent))   # the checkout's clrf only where none is installed
from clrf.testing.benchmark import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
