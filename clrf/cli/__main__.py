"""``python -m clrf.cli``: the ``clrf`` command."""
import sys

from .main import main

sys.exit(main())
