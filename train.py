"""``train.py``: a thin wrapper over ``torchseq train`` (:mod:`torchseq.cli.train`)."""

import torchseq.cli.train as cli_train
from torchseq.cli.train import *  # noqa: F401,F403 - the script's names, for tests and users


def main(argv: list[str] | None = None) -> int:
    """Entry point (errors raise; the command line turns them into one line and exit 2)."""
    return cli_train.main(argv, prog="train.py")


if __name__ == "__main__":
    raise SystemExit(cli_train.cli(prog="train.py"))
