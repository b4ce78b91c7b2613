"""What Neural SeqSLAM returns: one step, a whole query traverse, a fit."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from torchseq.matches import Matches


class NeuralStep(NamedTuple):
    """Output of one streaming step.

    Attributes:
        reference: ``(B,)`` int64 reference frame of the winning unit (centre of its stretch).
        confidence: ``(B,)`` float, higher = more confident (winner minus best rival).
        activity: ``(B, N)`` output-ring activity.
    """

    reference: torch.Tensor
    confidence: torch.Tensor
    activity: torch.Tensor


@dataclass
class NeuralResult:
    """A query traverse through the network.

    Every figure but ``activity`` comes from the stage that decided (``stage``).

    Attributes:
        matches: per-frame decisions (``lower_is_better=False``).
        activity: ``(T, N)`` output-ring activity.
        stage: the decision stage (``"ring"``, ``"adaptive ring"`` or ``"unit search"``).
        scores: ``(T, N)`` the deciding stage's score per unit, higher is better (the rings:
            ``activity``; the search: each unit's best position), the raster to draw.
        ranked: ``(T, K)`` int64 reference frames of the stage's best ``K`` units, best
            first, the first the decision (:func:`~torchseq.neural.readout.rank`).
        ranked_score: ``(T, K)`` their ``scores``.

    The engine times nothing: callers time :meth:`NeuralSeqSLAM.run` themselves.
    """

    matches: Matches
    activity: torch.Tensor
    stage: str
    scores: torch.Tensor
    ranked: torch.Tensor
    ranked_score: torch.Tensor


@dataclass
class NeuralFitLog:
    """What :meth:`NeuralSeqSLAM.fit` learnt.

    Attributes:
        winners: ``(T,)`` int64 unit recruited for each reference frame (firing order).
        evidence: ``(T, N)`` normalised feed-forward evidence of each reference frame after
            learning (a raster; its argmax should equal ``winners``).
        unit_to_reference: ``(N, 2)`` int64 first and one-past-last reference frame per unit.
        self_check: share of the reference frames, lightly disturbed, whose winning unit holds
            them (:mod:`torchseq.neural.selfcheck`); None when ``fit(check=False)``.
    """

    winners: torch.Tensor
    evidence: torch.Tensor
    unit_to_reference: torch.Tensor
    self_check: float | None = None
