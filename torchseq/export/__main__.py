"""``python -m torchseq.export``: see :mod:`torchseq.export.cli`."""

import sys

from torchseq.export.cli import main

sys.exit(main(prog="python -m torchseq.export"))
