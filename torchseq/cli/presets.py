"""``--neural-preset``: a :class:`~torchseq.neural.NeuralConfig` classmethod as the base of a run.

The preset gives the base config; the NeuralConfig flags the user typed go on top (they win),
and so do the values a replayed ``config.json`` holds that differ from the preset it recorded
(the flags typed in the run that wrote it). Nothing here is needed from Python: call the
classmethods themselves.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection
from typing import Callable

from torchseq.cli.errors import UsageError
from torchseq.cli.flags import changed_fields
from torchseq.neural import NeuralConfig

NEURAL_PRESETS: dict[str, Callable[[], NeuralConfig]] = {
    "default": NeuralConfig,
    "table1": NeuralConfig.table1,
    "dense-readout": NeuralConfig.dense_readout,
    "adaptive-velocity": NeuralConfig.adaptive_velocity,
}


def preset_help(flags: str) -> str:
    """The ``--neural-preset`` help text; ``flags`` names the flags that override it."""
    return ("Neural SeqSLAM preset, the NeuralConfig classmethod the model starts from: "
            "default (NeuralConfig()), table1 (the seed paper's Table 1: 20%% L2 -> L3 mask, "
            "5%% winners), dense-readout (dense L2 -> L3, ring decay 0.96) or "
            "adaptive-velocity (the ring estimates each stream's speed; for routes of at most "
            "--neural-n-output frames; ONNX and integer export, "
            f"no NIR form); {flags} you type are applied on top of it and win "
            "(default: default)")


def preset_name(name: str | None) -> str:
    """``name`` checked (``dense_readout`` is taken for ``dense-readout``); None -> default."""
    key = "default" if name is None else str(name).replace("_", "-")
    if key not in NEURAL_PRESETS:
        raise UsageError(f"--neural-preset must be one of {', '.join(NEURAL_PRESETS)}, "
                         f"got {name!r}")
    return key


def preset_config(name: str | None) -> NeuralConfig:
    """The NeuralConfig of preset ``name`` (None: the default)."""
    return NEURAL_PRESETS[preset_name(name)]()


def apply_preset(flags: NeuralConfig, name: str | None, typed: Collection[str],
                 replayed: Collection[str] = (), recorded: str | None = None) -> NeuralConfig:
    """The run's NeuralConfig: preset ``name``, with the user's own settings on top.

    Only the fields a preset sets (this one's or the recorded one's) are taken from it; every
    other field keeps its flag value (the seed, for instance, which no preset sets).

    Args:
        flags: the config the parsed flags give (dataclass defaults, replayed values, typed
            flags).
        name: the preset (None: the default).
        typed: NeuralConfig field names typed on the command line (they win).
        replayed: field names a ``--config`` file gave.
        recorded: the preset that file recorded (None: the default); a replayed value that
            differs from that preset's was typed in the recorded run, so it wins too.

    Returns:
        The config (not yet validated).
    """
    base, was, plain = preset_config(name), preset_config(recorded), NeuralConfig()
    preset_fields = set(changed_fields(base, plain)) | set(changed_fields(was, plain))
    taken = {}
    for field in preset_fields:
        value = getattr(flags, field)
        own = field in typed or (field in replayed and value != getattr(was, field))
        taken[field] = value if own else getattr(base, field)
    return dataclasses.replace(flags, **taken)
