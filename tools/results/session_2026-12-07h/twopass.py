"""clrf train with grid.exposure's two-pass step on every step (the step before the transform
moved into the backward's one march): for an A/B of whole runs on the same machine."""
import sys

import clrf.grid.model as gm
from clrf.cli.main import main

_init = gm.GridModel.__init__


def init(self, *a, **k):
    _init(self, *a, **k)
    self.colour_in_backward = False


gm.GridModel.__init__ = init
sys.exit(main(sys.argv[1:]))
