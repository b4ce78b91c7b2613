"""``eval.py``: a thin wrapper over ``torchseq eval`` (:mod:`torchseq.cli.eval`)."""

import torchseq.cli.eval as cli_eval
from torchseq.cli.eval import *  # noqa: F401,F403 - the script's names, for tests and users


def main(argv: list[str] | None = None) -> int:
    """Entry point (errors raise; the command line turns them into one line and exit 2)."""
    return cli_eval.main(argv, prog="eval.py")


if __name__ == "__main__":
    raise SystemExit(cli_eval.cli(prog="eval.py"))
