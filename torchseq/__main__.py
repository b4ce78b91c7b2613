"""``python -m torchseq eval|train|export``: see :mod:`torchseq.cli`."""

import sys

from torchseq.cli import main

sys.exit(main())
