"""How ``torchseq eval|train|export --help`` is laid out: which group each flag sits in.

The flags themselves come from dataclass fields (``flags.add_config_flags``); this module is
only the table that sorts them for a reader: six groups in a fixed order, the common flags of
each shown by ``--help``, every flag by ``--help-all``. A flag the table does not name falls
into "advanced" (``--help-all`` only), so a new field is listed without an edit here; name it
below to give it a group or to show it in the short help. Choices are shown in the usage
(``--engine {seqslam,neural,both}``) through the flag's metavar.
"""

from __future__ import annotations

import argparse
import fnmatch
import sys
from dataclasses import dataclass, field

GROUPS = {  # key -> section title, in the order printed
    "inputs": "inputs",
    "SeqSLAM": "SeqSLAM (SeqSLAMConfig)",
    "neural": "Neural SeqSLAM (NeuralConfig)",
    "events": "event files (.aedat, .aedat4, .raw, event .npy/.npz/.csv/.h5/.parquet)",
    "outputs": "outputs",
    "advanced": "advanced",
}

# NeuralConfig fields as flags (``--neural-`` prefix; train also takes them without); common first
NEURAL_COMMON = ("n-output", "seed")
NEURAL_OTHER = (
    "input-size", "patch-size", "patch-mode", "input-steps", "density", "density-out",
    "l1-levels", "l3-levels", "k-fraction", "ring-decay", "ring-gain", "ring-spread",
    "ring-spread-decay", "ring-stay", "ring-wrap", "n-cohorts", "rectify", "hebbian",
    "uniqueness-window", "recruit", "ring-velocity", "velocity-window", "velocity-min",
    "velocity-max", "velocity-tolerance", "velocity-rate", "unit-search", "search-length",
    "search-contrast", "search-ring-weight", "search-phases")
EVENT_COMMON = ("--window-ms", "--event-count", "--frame-size", "--event-mode",
                "--window-anchor", "--t-start", "--duration")
EVENT_OTHER = ("--sensor-size", "--evt3-time", "--evt3-kernel", "--truncated", "--hot-pixel",
               "--refractory-us", "--time-unit")
SELECTION = ("--start", "--stop", "--frame-step", "--max-frames")

# (group, common flags, other flags) per command; a '*' in a name matches any text
EVAL = (
    ("inputs", ("--reference", "--query", "--ground-truth", "--tolerance", "--engine",
                "--checkpoint", "--config", "--dataset", "--descriptor", "--map", "--shards"),
     ("--gt-offset", "--gt-scale", *SELECTION, "--root", "--reference-split", "--query-split",
      "--descriptor-batch", "--ray-address", "--demo-frames", "--demo-speed", "--seed")),
    ("SeqSLAM", ("--preset", "--ds", "--speed-ratio", "--metric", "--candidates",
                 "--image-size"),
     ("--vmin", "--vmax", "--patch-size", "--enhance-window", "--speed-tolerance", "--rwindow",
      "--top-k", "--match-at", "--preprocessing", "--edges")),
    ("neural", ("--neural-preset", *(f"--neural-{n}" for n in NEURAL_COMMON)),
     tuple(f"--neural-{n}" for n in NEURAL_OTHER)),
    ("events", EVENT_COMMON, EVENT_OTHER),
    ("outputs", ("--out", "--overwrite", "--sweep", "--tensorboard"),
     ("--target-precision", "--progress", "--matches-top-k")),
    ("advanced", (), ("--device", "--threads", "--max-chunk-elements", "--keep-matrices",
                      "--neural-eps", "--neural-chunk")),
)
TRAIN = (
    ("inputs", ("--reference", "--config"), (*SELECTION, "--demo-frames", "--demo-seed")),
    ("neural", ("--neural-preset", *(f"--neural-{n}" for n in NEURAL_COMMON)),
     tuple(f"--neural-{n}" for n in NEURAL_OTHER)),
    ("events", EVENT_COMMON, EVENT_OTHER),
    ("outputs", ("--out", "--overwrite", "--export", "--export-query", "--tensorboard"),
     ("--export-ground-truth", "--export-frame-size", "--export-chip-report",
      "--export-timed-spiking", "--progress")),
    ("advanced", (), ("--device", "--neural-eps", "--neural-chunk")),
)
EXPORT = (
    ("inputs", ("checkpoint", "--query", "--ground-truth"), ()),
    ("outputs", ("--out", "--overwrite", "--frame-size", "--no-nir", "--nir-weight-bits",
                 "--nir-levels", "--chip-report", "--timed-spiking"), ("--no-progress",)),
)

CHOICES = {  # flag -> the values it takes, shown as its metavar
    "--engine": ("seqslam", "neural", "both"),
    "--preset": ("openseqslam", "events"),
    "--neural-preset": ("default", "table1", "dense-readout", "adaptive-velocity"),
    "--event-mode": ("count", "signed", "two-channel", "binary"),
    "--evt3-kernel": ("auto", "numpy", "numba"),
    "--evt3-time": ("spec", "carry"),
    "--truncated": ("error", "drop"),
    "--time-unit": ("s", "ms", "us", "ns"),
    "--device": ("cpu", "cuda", "auto"),
    "--metric": ("l1", "l2", "cosine"),
    "--preprocessing": ("torchseq", "openseqslam"),
    "--readout": ("centre", "interpolate"),
    "--recruit": ("uniform", "novelty"),
    "--ring-velocity": ("fixed", "adaptive"),
    "--unit-search": ("auto", "on", "off"),
}

METAVARS = {  # flag -> its placeholder; other flags: N (integers), X (numbers), VALUE
    "--reference": "PATH", "--query": "PATH", "--ground-truth": "FILE", "--checkpoint": "FILE",
    "--config": "FILE", "--out": "DIR", "--export-query": "PATH",
    "--export-ground-truth": "FILE", "--window-anchor": "first|zero|US",
    "--sensor-size": "WxH",
}

EVAL_EXAMPLES = """\
examples:
  torchseq eval                                  # the built-in demo route, both engines
  torchseq eval --reference ref/ --query query/ --ground-truth gt.csv --out runs/mine
  torchseq eval --reference a.mp4 --query b.mp4 --tolerance 2 --engine seqslam --ds 20
  torchseq eval --reference a.aedat --query b.aedat --preset events --engine seqslam
      # event files, 16x16 frames; speed ratio from the window counts (or --speed-ratio)
  torchseq eval --engine neural --checkpoint runs/train-<time>/model.pt
  torchseq eval --config runs/mine/config.json --out runs/again   # replay a run

Which engine: seqslam (exact, the most recall) while reference x query pairs fit in memory
(--candidates K beyond, with a K that holds recall; --map --shards across machines); neural
to recognise a route in fewer bytes, on a device. Guide: docs/guide/seqslam.md.
Every flag: torchseq eval --help-all. Guides: docs/guide/; flags: docs/reference/cli.md."""

TRAIN_EXAMPLES = """\
examples:
  torchseq train                                 # learn the demo route
  torchseq train --reference ref/ --out runs/model --export   # then export and validate
  torchseq train --reference ref/ --neural-preset adaptive-velocity --neural-n-output 1000

Every flag: torchseq train --help-all. Guides: docs/guide/; flags: docs/reference/cli.md."""

EXPORT_EXAMPLES = """\
examples:
  torchseq export runs/model/model.pt --out deploy/
  torchseq export model.pt --out deploy/ --query query/ --ground-truth gt.csv --frame-size 120x160

Files written and checks: docs/guide/export.md; integer format: docs/reference/integer_format.md."""


@dataclass
class HelpLayout:
    """Where each flag of one command goes in its help (see the module docstring)."""

    table: tuple
    epilog: str
    choices: dict = field(default_factory=lambda: dict(CHOICES))

    def place(self, name: str) -> tuple[str, bool]:
        """``(group, common)`` of a flag (its first option string, or a positional's dest)."""
        for group, common, other in self.table:
            for pattern in common:
                if fnmatch.fnmatchcase(name, pattern):
                    return group, True
            for pattern in other:
                if fnmatch.fnmatchcase(name, pattern):
                    return group, False
        return "advanced", False

    def format(self, parser: argparse.ArgumentParser, full: bool) -> str:
        """The help text: usage, description, the groups in order, the examples."""
        shown = {key: [] for key in GROUPS}
        rank = {}  # the table's order within a group
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, _HelpAllAction)):
                continue
            name = flag_name(action)
            group, common = self.place(name)
            if full or common:
                shown[group].append(action)
            rank[id(action)] = self._rank(name)
        helps = [a for a in parser._actions
                 if isinstance(a, (argparse._HelpAction, _HelpAllAction))]
        ordered = {key: sorted(shown[key], key=lambda a: rank[id(a)]) for key in GROUPS}
        formatter = parser._get_formatter()
        formatter.add_usage(None, helps + [a for key in GROUPS for a in ordered[key]], [])
        formatter.add_text(parser.description)
        for key, title in GROUPS.items():
            actions = (helps if key == "inputs" else []) + ordered[key]
            if not actions:
                continue
            formatter.start_section(title)
            formatter.add_arguments(actions)
            formatter.end_section()
        text = formatter.format_help()
        return text.rstrip("\n") + "\n\n" + self.epilog + "\n"

    def _rank(self, name: str) -> int:
        i = 0
        for _, common, other in self.table:
            for pattern in (*common, *other):
                if fnmatch.fnmatchcase(name, pattern):
                    return i
                i += 1
        return i


def flag_name(action: argparse.Action) -> str:
    """A flag's long name (``--engine``; ``--tensorboard`` for ``--[no-]tensorboard``)."""
    longs = [s for s in action.option_strings if s.startswith("--")]
    if not action.option_strings:
        return action.dest
    return longs[0] if longs else action.option_strings[0]


class _HelpAllAction(argparse.Action):
    """``--help-all``: every flag of every group, then exit 0."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="show every flag, in groups, and exit"):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0,
                         help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        sys.stdout.write(parser.help_layout.format(parser, full=True))
        parser.exit()


def organise_help(parser: argparse.ArgumentParser, table: tuple, epilog: str) -> None:
    """Give ``parser`` the grouped short ``--help``, ``--help-all`` and choice metavars."""
    layout = HelpLayout(table, epilog)
    for action in parser._actions:
        values = layout.choices.get(flag_name(action))
        if values is None and flag_name(action).startswith("--neural-"):  # eval's prefix
            values = layout.choices.get("--" + flag_name(action)[len("--neural-"):])
        if action.metavar is not None or action.nargs is not None or not action.option_strings:
            continue  # flags without a value, positionals, and placeholders set where made
        if values is not None:
            action.metavar = "{" + ",".join(values) + "}"
        elif flag_name(action) in METAVARS:
            action.metavar = METAVARS[flag_name(action)]
        elif flag_name(action).endswith("-size"):
            action.metavar = "HxW"
        else:
            kind = getattr(action.type, "__name__", "")
            action.metavar = {"bounded_int": "N", "finite_float": "X", "int": "N",
                              "float": "X"}.get(kind, "VALUE")
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            action.help = "show the common flags and exit"
    parser.add_argument("--help-all", action=_HelpAllAction)
    parser.help_layout = layout
