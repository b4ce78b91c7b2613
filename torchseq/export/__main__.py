"""``python -m torchseq.export``: see :mod:`torchseq.cli.export`."""

import sys

from torchseq.cli.export import main

sys.exit(main(prog="python -m torchseq.export"))
