"""``python -m torchseq.export``: see :mod:`torchseq.export.checkpoint`."""

import sys

from torchseq.export.checkpoint import main

sys.exit(main(prog="python -m torchseq.export"))
