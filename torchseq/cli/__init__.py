"""``torchseq eval|train|export``: the command-line front ends as one console script.

Installed by pip as ``torchseq`` (and runnable as ``python -m torchseq``); ``eval.py`` and
``train.py`` in a source checkout are thin wrappers over the same code.
"""

from __future__ import annotations

import gc
import sys

COMMANDS = {
    "eval": "run a query traverse through SeqSLAM and Neural SeqSLAM and report metrics",
    "train": "learn a Neural SeqSLAM model from a reference traverse",
    "export": "export a Neural SeqSLAM checkpoint to ONNX and integer files and validate them",
    "map": "build a reference map (descriptors, index, record) once; verify one",
}
USAGE = "usage: torchseq [--version] {eval,train,export,map} [--help] ...\n\n" + "\n".join(
    f"  {name:<8}{text}" for name, text in COMMANDS.items()) + (
    "\n\n`torchseq COMMAND --help` lists a command's common flags, `--help-all` all of them.")


def main(argv: list[str] | None = None) -> int:
    """Dispatch ``torchseq COMMAND ...``; returns the exit status.

    ``argv`` None (the console script, ``python -m torchseq``): the process's own command
    line, and the process ends with it, so the objects of the command's imports and, at the
    end, of its run are frozen (``gc.freeze``): the cycle collector no longer walks torch's
    objects in every full pass and again at exit (0.4-0.6 s of a SeqSLAM eval). Outputs are
    closed by the commands themselves, not by the collector. A list (tests, scripts calling
    it in process) freezes nothing.
    """
    process = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        return 0 if argv else 2
    if argv[0] in ("-V", "--version"):
        from torchseq.versions import versions_line
        print(versions_line())
        return 0
    command, rest = argv[0], argv[1:]
    prog = f"torchseq {command}"
    if command == "eval":
        from torchseq.cli.eval import cli
    elif command == "train":
        from torchseq.cli.train import cli
    elif command == "map":
        from torchseq.cli.map import cli
    elif command == "export":
        from torchseq.cli.export import main as cli
    else:
        cli = None
    if cli is not None:
        if process:
            gc.freeze()
        code = cli(rest, prog)
        if process:
            gc.freeze()
        return code
    print(f"torchseq: error: unknown command {command!r} (choose from "
          f"{', '.join(COMMANDS)})", file=sys.stderr)
    return 2
