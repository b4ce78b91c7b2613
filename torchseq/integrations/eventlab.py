"""torchseq as an Event-LAB baseline: SeqSLAM and Neural SeqSLAM in Event-LAB's one command.

Event-LAB (github.com/EventLAB-Team/Event-LAB) runs ``python eventlab_run.py <baseline>
<dataset> <reference> <query>``: it loads ``baselines/<baseline>.py``, builds the baseline
with no arguments (``baselines/get_baseline.py``), and for every time window of its
``config.yaml`` calls ``format_data(config, dataset_config, reference, query, timewindow)``,
``build_execute(config, dataset_config, GT_file)``, ``run()``, ``parse_results(GT_file)`` and
``cleanup()``. ``run`` saves ``(n_references, n_queries)`` matrices as ``.npy`` in the
output folder; ``parse_results`` scores each with Event-LAB's own ``run_metrics`` and
``save_results`` (inherited from its ``EventBaseline``).

:class:`TorchseqBaseline` implements those five methods; Event-LAB's ``EventBaseline``
supplies the scoring, so torchseq never imports Event-LAB. :func:`write_baseline` writes the
two files Event-LAB needs (``baselines/torchseq.py``, ``baselines/torchseq.yaml``); register
the name in ``baselines/get_baseline.py`` and ``config.yaml`` (docs/guide/event-lab.md).

The matrices (both **similarities**, higher is better):

- ``seqslam.npy``: rank-coded SeqSLAM decisions. For query ``q`` with a match, its matched
  reference gets ``top_k + 1 - u`` (``u`` the uniqueness ratio in 0..1, lower = surer, so
  Event-LAB's PR curve thresholds torchseq's confidence), the engine's next ranked places
  ``top_k - 1, top_k - 2, ...``, every other reference 0; an unmatched query is all 0. The
  best reference of each column is torchseq's match, and Event-LAB's recall@K counts
  torchseq's ranked places.
- ``neural.npy``: the network's output activity, ``S[r, q]`` the activity after query frame
  ``q`` of the output unit that stands for reference frame ``r``.

Event files are read with torchseq's own readers from Event-LAB's formatted HDF5 (the
``hdf5_path`` of ``get_dataset_info()``), time unit from the dataset's
``format.data.timestamp_val``, windows starting at the sequence's ``other.offset`` (seconds,
as Event-LAB's frame builder reads it) when the dataset gives one, else at the first event.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from torchseq.atomic import atomic_path, write_text

ENGINES = ("seqslam", "neural")
DEFAULTS = {
    "engines": ["seqslam", "neural"],
    "seqslam": {"ds": 10},          # SeqSLAMConfig fields (after the preset)
    "preset": None,                 # None, "openseqslam" or "events" (SeqSLAMConfig presets)
    "neural": {},                   # NeuralConfig fields
    "event_mode": "count",          # torchseq's event modes: count, signed, binary
    "frame_size": None,             # [H, W] area pooling of the event frames (None: sensor)
    "hot_pixel": None,              # torchseq's statistical hot-pixel filter factor
    "device": "cpu",
}
UNITS = {"ns": "ns", "nanosecond": "ns", "nanoseconds": "ns", "us": "us", "microsecond": "us",
         "microseconds": "us", "ms": "ms", "millisecond": "ms", "milliseconds": "ms",
         "s": "s", "sec": "s", "second": "s", "seconds": "s"}
EVENT_MODES = ("count", "signed", "binary")
MAX_SIDE = 1 << 16  # resolution and frame_size sides
MAX_OFFSET_S = 2.0**52 / 1e6  # other.offset: seconds that stay exact as int64 us


class EventLabError(ValueError):
    """Baseline settings or an Event-LAB dataset configuration this adapter cannot use."""


BASELINE_FILE = '''"""torchseq (SeqSLAM, Neural SeqSLAM) as an Event-LAB baseline; written by
torchseq.integrations.eventlab.write_baseline. Settings: baselines/torchseq.yaml."""
from baselines.EventBaselineLab import EventBaseline
from torchseq.integrations.eventlab import TorchseqBaseline


class torchseq_baseline(TorchseqBaseline, EventBaseline):
    """Event-LAB's scoring (EventBaseline) around torchseq's engines (TorchseqBaseline)."""
'''
CONFIG_FILE = """---
# torchseq baseline settings (torchseq.integrations.eventlab.DEFAULTS gives every key)
engines: ["seqslam", "neural"]   # which matrices to write: seqslam.npy, neural.npy
preset: null                     # SeqSLAM preset: null, openseqslam or events
seqslam:                         # SeqSLAMConfig fields, on top of the preset
  ds: 10                         # sequence length in frames (Event-LAB's windows are long)
neural: {}                       # NeuralConfig fields, e.g. {n_output: 1000}
event_mode: count                # count, signed or binary
frame_size: null                 # [H, W]: area-pool event frames first (saves memory)
hot_pixel: null                  # torchseq's hot-pixel filter factor (null: off)
device: cpu                      # cpu, cuda
"""


class TorchseqBaseline:
    """Event-LAB baseline protocol over torchseq's engines (mix in Event-LAB's EventBaseline).

    Args:
        settings: overrides of :data:`DEFAULTS`; None reads ``config_path`` when it exists.
        config_path: the baseline's YAML settings (Event-LAB keeps them beside the module).
        outdir: Event-LAB's output root for this baseline.
    """

    name = "torchseq"
    matrix_type = "similarity"

    def __init__(self, settings: dict | None = None,
                 config_path: str = "./baselines/torchseq.yaml",
                 outdir: str = "./output/torchseq") -> None:
        super().__init__()  # EventBaseline: its K list
        if settings is None and os.path.exists(config_path):
            import yaml  # Event-LAB's environment has it

            with open(config_path) as f:
                settings = yaml.safe_load(f) or {}
        self.baseline_config = resolve_settings(settings or {})
        self.outdir = outdir
        os.makedirs(self.outdir, exist_ok=True)

    def format_data(self, config: dict, dataset_config: dict, reference, query,
                    timewindow: float) -> None:
        """Read both recordings into event frames of ``timewindow`` ms; make the output folder."""
        self.config = config
        self.timewindow = timewindow
        ref_info, query_info = reference.get_dataset_info(), query.get_dataset_info()
        self.ref_name, self.query_name = ref_info["sequence_name"], query_info["sequence_name"]
        self.ref_frames = self._frames(ref_info, dataset_config, timewindow)
        self.query_frames = self._frames(query_info, dataset_config, timewindow)
        self.output_dir = os.path.join(self.outdir, f"{ref_info['dataset_name']}",
                                       f"{self.ref_name}_{self.query_name}",
                                       f"{config.get('frame_generator', 'frames')}_{timewindow}")
        os.makedirs(self.output_dir, exist_ok=True)

    def _frames(self, info: dict, dataset_config: dict, timewindow: float) -> torch.Tensor:
        from torchseq.events import load_event_frames

        path = info.get("hdf5_path")
        if not path:
            raise ValueError(f"Event-LAB sequence {info.get('sequence_name')!r}: "
                             f"get_dataset_info() has no 'hdf5_path' (the formatted recording "
                             f"torchseq reads); this baseline follows Event-LAB >= 1.1")
        s = self.baseline_config
        fmt = (dataset_config.get("format") or {}).get("data") or {}
        unit = fmt.get("timestamp_val")
        if unit is not None and (not isinstance(unit, str)
                                 or unit.strip().lower() not in UNITS):
            raise EventLabError(f"format.data.timestamp_val {unit!r}: torchseq reads ns, us, "
                                f"ms or s")
        resolution = (dataset_config.get("dataset") or {}).get("resolution")
        offset = ((dataset_config.get("other") or {}).get("offset") or {}).get(
            info["sequence_name"])
        kwargs = {}
        if unit is not None:
            kwargs["time_unit"] = UNITS[unit.strip().lower()]
        if resolution is not None:
            kwargs["sensor_size"] = _sides(resolution, "dataset.resolution")
        if s["frame_size"] is not None:
            kwargs["frame_size"] = tuple(s["frame_size"])
        if s["hot_pixel"] is not None:
            kwargs["hot_pixel"] = float(s["hot_pixel"])
        if offset is not None and not (_real(offset) and abs(offset) <= MAX_OFFSET_S):
            raise EventLabError(f"other.offset.{info['sequence_name']} must be a time in "
                                f"seconds within +-{MAX_OFFSET_S:g}, got {offset!r}")
        anchor = "first" if offset is None else int(round(float(offset) * 1e6))  # s -> us
        return load_event_frames(path, window_ms=float(timewindow), mode=s["event_mode"],
                                 anchor=anchor, **kwargs)

    def build_execute(self, config: dict, data_config: dict, ground_truth: str) -> None:
        """Nothing to build: the engines run in process. Keeps the ground-truth path."""
        self.ground_truth = ground_truth

    def run(self) -> None:
        """Run each engine and save its ``(n_references, n_queries)`` similarity matrix."""
        matrices = torchseq_matrices(self.ref_frames, self.query_frames, self.baseline_config)
        for name, matrix in matrices.items():
            save_npy(Path(self.output_dir) / f"{name}.npy", matrix)

    def parse_results(self, GT: str) -> None:  # noqa: N803 (Event-LAB's name)
        """Score every saved matrix with Event-LAB's ``run_metrics`` and ``save_results``."""
        files = sorted(Path(self.output_dir).glob("*.npy"))
        names = [f.stem for f in files]
        arrays = [np.load(f) for f in files]
        if not arrays:
            print(f"torchseq: no .npy result in {self.output_dir}", file=sys.stderr)
            return
        timestamp = datetime.now(timezone.utc).replace(tzinfo=None).isoformat()
        rows, pr_curves = self.run_metrics(
            names, arrays, np.load(GT), timestamp, self.name,
            f"{self.ref_name}_{self.query_name}", matrix_type=self.matrix_type,
            outdir=self.output_dir, tolerance=self.config.get("ground_truth_tolerance", 0.0))
        self.save_results(rows, pr_curves, self.name, f"{self.ref_name}_{self.query_name}")

    def cleanup(self) -> None:
        """Nothing temporary is written outside the output folder."""


def _real(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)


def _sides(value, what: str) -> tuple[int, int]:
    """Two sizes of 1..``MAX_SIDE`` (``[W, H]`` or ``[H, W]`` as the field says)."""
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(isinstance(v, numbers.Integral) and not isinstance(v, bool)
                       and 1 <= v <= MAX_SIDE for v in value)):
        raise EventLabError(f"{what} must be two sizes of 1..{MAX_SIDE}, got {value!r}")
    return int(value[0]), int(value[1])


def resolve_settings(settings: dict) -> dict:
    """:data:`DEFAULTS` with ``settings`` on top, every field checked (types and bounds).

    The engines' configs are built here too, so a bad ``seqslam`` or ``neural`` field is
    refused before any recording is read.

    Raises:
        EventLabError: an unknown key or engine, or a field of the wrong type or range,
            naming it.
    """
    if not isinstance(settings, dict):
        raise EventLabError(f"torchseq baseline settings must be a mapping, got "
                            f"{type(settings).__name__}")
    unknown = set(settings) - set(DEFAULTS)
    if unknown:
        raise EventLabError(f"unknown torchseq baseline settings {sorted(unknown)}; known: "
                            f"{sorted(DEFAULTS)}")
    out = {**DEFAULTS, **settings}
    engines = out["engines"]
    if (not isinstance(engines, list) or not engines
            or not all(isinstance(e, str) and e in ENGINES for e in engines)):
        raise EventLabError(f"engines must be a non-empty list of {ENGINES}, got {engines!r}")
    for key in ("seqslam", "neural"):
        if out[key] is not None and not isinstance(out[key], dict):
            raise EventLabError(f"{key} must be a mapping of config fields, got {out[key]!r}")
    if out["event_mode"] not in EVENT_MODES:
        raise EventLabError(f"event_mode must be one of {EVENT_MODES}, got "
                            f"{out['event_mode']!r}")
    if out["frame_size"] is not None:
        out["frame_size"] = list(_sides(out["frame_size"], "frame_size"))
    if out["hot_pixel"] is not None and not (_real(out["hot_pixel"]) and out["hot_pixel"] > 0):
        raise EventLabError(f"hot_pixel must be a number > 0, got {out['hot_pixel']!r}")
    if not isinstance(out["device"], str):
        raise EventLabError(f"device must be a string such as 'cpu', got {out['device']!r}")
    seqslam_config(out)
    neural_config(out)
    return out


def seqslam_config(settings: dict):
    """The run's :class:`~torchseq.seqslam.SeqSLAMConfig`: the preset, then ``seqslam`` fields."""
    from torchseq.seqslam import SeqSLAMConfig

    fields = {k: tuple(v) if isinstance(v, list) else v
              for k, v in (settings["seqslam"] or {}).items()}
    preset = settings["preset"] or "default"
    try:
        return SeqSLAMConfig.preset(preset, **fields)
    except (TypeError, ValueError) as err:
        raise EventLabError(f"seqslam settings (preset {preset!r}): {err}") from None


def neural_config(settings: dict):
    """The run's :class:`~torchseq.neural.NeuralConfig`: the defaults, then ``neural`` fields."""
    from torchseq.neural import NeuralConfig

    fields = {k: tuple(v) if isinstance(v, list) else v
              for k, v in (settings["neural"] or {}).items()}
    try:
        return dataclasses.replace(NeuralConfig(), **fields).validate()
    except (TypeError, ValueError) as err:
        raise EventLabError(f"neural settings: {err}") from None


def torchseq_matrices(reference: torch.Tensor, query: torch.Tensor,
                      settings: dict) -> dict[str, np.ndarray]:
    """Every engine's ``(R, Q)`` float32 similarity matrix (see the module docstring).

    Args:
        reference: ``(R, H, W)`` frames.
        query: ``(Q, H, W)`` frames.
        settings: resolved baseline settings (:func:`resolve_settings`).
    """
    out = {}
    if "seqslam" in settings["engines"]:
        from torchseq.seqslam import SeqSLAM

        result = SeqSLAM(seqslam_config(settings), device=settings["device"]).match(
            reference, query)
        out["seqslam"] = rank_similarity(result.matches.reference, result.matches.score,
                                         result.ranked, len(reference))
    if "neural" in settings["engines"]:
        from torchseq.neural import NeuralSeqSLAM
        from torchseq.preprocess import resize

        cfg = neural_config(settings)
        model = NeuralSeqSLAM(cfg, device=settings["device"])
        model.fit(resize(reference.float(), cfg.input_size), progress=False)
        result = model.run(resize(query.float(), cfg.input_size), progress=False)
        out["neural"] = unit_similarity(result.activity, model.unit_to_reference,
                                        len(reference))
    return out


def rank_similarity(match: torch.Tensor, uniqueness: torch.Tensor, ranked: torch.Tensor,
                    n_ref: int) -> np.ndarray:
    """SeqSLAM's decisions as an ``(R, Q)`` similarity (module docstring, ``seqslam.npy``).

    Args:
        match: ``(Q,)`` matched reference, -1 for none.
        uniqueness: ``(Q,)`` uniqueness ratio (lower is surer), NaN where unmatched.
        ranked: ``(Q, K)`` ranked places, -1 padded (the match first).
        n_ref: ``R``.
    """
    match, ranked = match.cpu().numpy(), ranked.cpu().numpy()
    u = np.nan_to_num(uniqueness.cpu().double().numpy(), nan=1.0, posinf=1.0).clip(0.0, 1.0)
    k = ranked.shape[1]
    sim = np.zeros((n_ref, len(match)), dtype=np.float32)
    for q, m in enumerate(match):
        if m < 0:
            continue
        level = k - 1
        for r in ranked[q]:
            if r >= 0 and r != m and level > 0 and sim[r, q] == 0:
                sim[r, q] = level
                level -= 1
        sim[m, q] = k + 1 - u[q]
    return sim


def unit_similarity(activity: torch.Tensor, unit_to_reference: torch.Tensor,
                    n_ref: int) -> np.ndarray:
    """``(R, Q)``: the activity of the unit standing for each reference frame.

    Args:
        activity: ``(Q, U)`` output activity after each query frame.
        unit_to_reference: ``(U, 2)`` reference frames ``[start, stop)`` of each unit.
        n_ref: ``R``.
    """
    spans = unit_to_reference.cpu()
    frames = torch.arange(n_ref)
    unit = torch.searchsorted(spans[:, 0].contiguous(), frames, right=True) - 1
    unit = unit.clamp(0, len(spans) - 1)
    return activity.cpu().float()[:, unit].T.contiguous().numpy()


def save_npy(path: Path, array: np.ndarray) -> None:
    """Write ``array`` to ``path`` atomically (a finished file or none)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array)


def write_baseline(root: str | Path, overwrite: bool = False) -> list[Path]:
    """Write ``baselines/torchseq.py`` and ``baselines/torchseq.yaml`` into an Event-LAB tree.

    Args:
        root: the Event-LAB checkout (it holds ``eventlab_run.py`` and ``baselines/``).
        overwrite: replace existing files instead of refusing.

    Returns:
        The two paths written.
    """
    root = Path(root)
    if not (root / "baselines").is_dir():
        raise FileNotFoundError(f"{root} is not an Event-LAB checkout (no baselines/ folder)")
    paths = [root / "baselines" / "torchseq.py", root / "baselines" / "torchseq.yaml"]
    existing = [str(p) for p in paths if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{', '.join(existing)} exist; pass overwrite=True to replace")
    for path, text in zip(paths, (BASELINE_FILE, CONFIG_FILE)):
        write_text(path, text)
    return paths


def main(argv: list[str] | None = None) -> int:
    """``python -m torchseq.integrations.eventlab EVENTLAB_ROOT [--overwrite]``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    overwrite = "--overwrite" in argv
    roots = [a for a in argv if a != "--overwrite"]
    if len(roots) != 1:
        print("usage: python -m torchseq.integrations.eventlab EVENTLAB_ROOT [--overwrite]",
              file=sys.stderr)
        return 2
    try:
        paths = write_baseline(roots[0], overwrite)
    except (FileNotFoundError, FileExistsError) as err:
        print(f"torchseq eventlab: error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {paths[0]} and {paths[1]}; now add '\"torchseq\": lambda: "
          f"torchseq_baseline()' (importing it from baselines.torchseq) to "
          f"baselines/get_baseline.py and '- \"torchseq\"' to VPR-Baselines in config.yaml")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
