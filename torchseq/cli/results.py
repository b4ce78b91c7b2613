"""What a run hands to its report: typed results, not dicts keyed by strings.

Each eval engine returns an :class:`EngineRun` (:class:`SeqSLAMRun`, :class:`NeuralRun`); the
eval command bundles them with its inputs as an :class:`EvalOutcome`, which
:func:`torchseq.cli.report.report` writes out. The train command hands a :class:`TrainRun` to
:func:`torchseq.cli.report.write_train_json`. The files keep their keys: an engine's
:meth:`EngineRun.reported` entries follow its metrics in ``metrics.json``, and
:meth:`TrainRun.reported` is ``train.json`` but for its warnings.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from torchseq.cli.eval_settings import Settings
from torchseq.cli.traverse import Traverse
from torchseq.matches import Matches
from torchseq.seqslam import SingleFrameResult
from torchseq.versions import VERSIONS_KEY


@dataclass
class EngineRun:
    """One engine's run over the query.

    Attributes:
        matches: one match (or none) per query.
        ranked: ``(Q, K)`` reference indices of the best ``K`` candidates, best first.
        ranked_score: ``(Q, K)`` their scores, or None (the candidate-mode map run).
        seconds: the engine's time on the query.
        parameters: the engine's config as JSON values.
    """

    matches: Matches
    ranked: torch.Tensor
    ranked_score: torch.Tensor | None
    seconds: float
    parameters: dict

    def reported(self) -> dict:
        """The engine's own entries of ``metrics.json``, after its metrics, in the file's order."""
        return {"seconds": self.seconds, "parameters": self.parameters}


@dataclass
class SeqSLAMRun(EngineRun):
    """Classic SeqSLAM's run, with the difference matrix its plot draws.

    Attributes:
        matrix: the engine's reduced preview or its enhanced matrix (dense or sparse), in
            full-matrix coordinates of ``matrix_shape``; None when nothing was kept.
        matrix_shape: ``(R, Q)`` of the full matrix.
        matrix_reduced: ``matrix`` is a reduced copy (a banded run kept no full matrix).
        difference: the raw ``(R, Q)`` difference matrix of the run's own descriptors, which
            the single-frame baseline ranks instead of computing it again; None for an
            ensemble or a map run, and dropped (set to None) once the baseline has it.
        kernels: which kernel ran per stage (``SeqSLAMResult.kernels``: ``"difference"``
            ``"sad"``, ``"thermometer"``, ``"cdist"`` ..., ``"threads"``, ``"matrices"``),
            reported in ``metrics.json``; None where the run does not say (ensemble).
        candidate_agreement: a candidate-mode run against the exact mode on a sample of
            queries (``cli.engines.candidate_check``), reported in ``metrics.json``.
        sharding: a ``--shards`` run's shard count and the shards whose Ray actor was
            restarted during it (``ShardedSeqSLAM.restarted``), reported in ``metrics.json``.
    """

    matrix: torch.Tensor | None
    matrix_shape: tuple[int, int]
    matrix_reduced: bool
    difference: torch.Tensor | None = None
    kernels: dict | None = None
    candidate_agreement: dict | None = None
    sharding: dict | None = None

    def reported(self) -> dict:
        """The engine's own entries of ``metrics.json``, after its metrics, in the file's order."""
        out = super().reported()
        if self.kernels:
            out["kernels"] = self.kernels
        if self.candidate_agreement:
            out["candidate_agreement"] = self.candidate_agreement
        if self.sharding:
            out["sharding"] = self.sharding
        return out


@dataclass
class NeuralRun(EngineRun):
    """Neural SeqSLAM's run, with its output activity and what the model learnt.

    Every figure comes from the stage that decided (``stage``).

    Attributes:
        activity: ``(Q, N)`` the deciding stage's score per unit over the query (the raster
            plot): the ring's activity, or the unit search's best position per unit.
        unit_spans: ``(N, 2)`` reference frames each output unit stands for.
        fit_seconds: learning the reference (or checking a checkpoint).
        preset: the ``--neural-preset`` (None with a checkpoint).
        model_bytes: the model's size.
        seqslam_template_bytes: SeqSLAM's templates for the same route (one byte a value).
        frames_per_unit: reference frames per output unit.
        self_check: the model's recall on its own reference (None: not measured).
        stage: the decision stage (``"ring"``, ``"adaptive ring"``, ``"unit search"``).
        sequence_frames: query frames a decision integrates (SeqSLAM's ``ds`` to compare
            with; :func:`torchseq.neural.search.sequence_frames`).
    """

    activity: torch.Tensor
    unit_spans: torch.Tensor
    fit_seconds: float
    preset: str | None
    model_bytes: int
    seqslam_template_bytes: int
    frames_per_unit: float
    self_check: float | None
    stage: str = "ring"
    sequence_frames: float | None = None

    def reported(self) -> dict:
        """The engine's own entries of ``metrics.json``, after its metrics, in the file's order."""
        return {"seconds": self.seconds, "fit_seconds": self.fit_seconds,
                "model_bytes": self.model_bytes,
                "seqslam_template_bytes": self.seqslam_template_bytes,
                "frames_per_unit": self.frames_per_unit, "stage": self.stage,
                "sequence_frames": self.sequence_frames,
                "self_check": self.self_check, "preset": self.preset,
                "parameters": self.parameters}


@dataclass
class EvalOutcome:
    """An eval run as its report takes it: settings, inputs, each engine's run, the folder.

    Attributes:
        settings: the run's checked settings.
        reference: the reference traverse (or the map's record of it).
        query: the query traverse.
        ground_truth: ``(R, Q)`` bool array, sparse ranges, or None.
        inputs: what the inputs were (``metrics.json``'s ``"inputs"``, before the counts).
        engines: each engine's run, by name (``"seqslam"``, ``"neural"``).
        out: the run's folder.
        single: the single-frame baseline (with ground truth), or None.
        metrics: ``metrics.json`` once the report wrote it, else None.
    """

    settings: Settings
    reference: Traverse
    query: Traverse
    ground_truth: object
    inputs: dict
    engines: dict[str, EngineRun]
    out: Path
    single: SingleFrameResult | None = None
    metrics: dict | None = None


@dataclass
class TrainRun:
    """A training run as ``train.json`` records it.

    Attributes:
        reference: what the reference was (``"source"``: ``"demo"`` with the demo's size and
            seed, or the resolved path with the event options and frame selection), then its
            ``"n_frames"`` and ``"frame_size"``.
        neural_preset: the ``--neural-preset`` by its name.
        fit_seconds: learning the reference.
        versions: :func:`torchseq.versions.versions` of the run.
        model_bytes: the model's size.
        seqslam_template_bytes: SeqSLAM's templates for the same route (one byte a value).
        n_units: output units the model recruited.
        self_check: the model's recall on its own reference (None: not measured).
        export_passed: ``--export``'s validation verdict; None before or without an export.
    """

    reference: dict
    neural_preset: str | None
    fit_seconds: float
    versions: dict
    model_bytes: int
    seqslam_template_bytes: int
    n_units: int
    self_check: float | None
    export_passed: bool | None = None

    def reported(self) -> dict:
        """``train.json`` but for its ``"warnings"``, in the file's order.

        ``"export_passed"`` only once an export ran.
        """
        out = {"reference": self.reference, "neural_preset": self.neural_preset,
               "fit_seconds": self.fit_seconds, VERSIONS_KEY: self.versions,
               "model_bytes": self.model_bytes,
               "seqslam_template_bytes": self.seqslam_template_bytes,
               "n_units": self.n_units, "self_check": self.self_check}
        if self.export_passed is not None:
            out["export_passed"] = self.export_passed
        return out
