"""The unit search of a fitted Neural SeqSLAM: built after ``fit``, run beside the ring.

:class:`UnitSearch` holds the derived line table of :mod:`torchseq.layers.unit_search` (not
state: rebuilt from the config and the units' spans after ``fit`` and
``load_state_dict``) and calls its functions; :func:`search_step` is the model's streaming
step with the search, :class:`SearchState` its state (the ring's and the search's).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from torchseq.layers import RingState
from torchseq.layers.unit_search import (
    SearchHistory,
    search_decide,
    search_lines,
    search_units,
    unit_search_scan,
    unit_search_step,
)
from torchseq.neural.config import NeuralConfig, NeuralError
from torchseq.neural.results import NeuralStep


class SearchState(NamedTuple):
    """State of a model with the unit search.

    Attributes:
        ring: the ring's :class:`~torchseq.layers.RingState`, ``(B, N)``.
        search: the search's :class:`~torchseq.layers.unit_search.SearchHistory`.
    """

    ring: RingState
    search: SearchHistory


SEARCH_ROUTE_LINES = 10  # "auto": the search decides on routes of more lines than this


def resolve_search(config: NeuralConfig, n_frames: int, n_units: int) -> str:
    """``fit``'s reading of ``unit_search``: ``"on"`` or ``"off"``, kept in the model's config.

    ``"auto"``: the search decides where units stand for several frames (``n_frames >
    n_units``) or the route holds more than :data:`SEARCH_ROUTE_LINES` search lines
    (``n_frames > 10 * search_length``: 400 frames at the default 40), with the fixed ring;
    else the ring. Measured from the reference's length alone
    (``experiments/neural_long_route.py stage``, docs/results/neural-long-routes.md): at one
    unit per frame the ring wins on the corridor (111 frames, 0.866 against 0.611) and LENS
    (100, +-2 frames: 0.827 against 0.760), ties on the demo (200: 0.999, 1.000) and loses on
    nordland-b (500: 0.901 against 0.969; 1,788: 0.587 against 0.913).
    """
    if config.unit_search != "auto":
        return config.unit_search
    long = n_frames > n_units or n_frames > SEARCH_ROUTE_LINES * config.search_length
    return "on" if long and config.ring_velocity == "fixed" else "off"


def search_active(config: NeuralConfig, n_frames: int, n_units: int) -> bool:
    """Whether a fitted model of ``n_units`` units on ``n_frames`` frames searches.

    ``"on"`` / ``"off"``: as :func:`resolve_search` left them at fit. ``"auto"`` is a
    checkpoint fitted before fit resolved it, which keeps the rule it was made with: units
    of several frames (``n_frames > n_units``) and the fixed ring.
    """
    if config.unit_search != "auto":
        return config.unit_search == "on"
    return n_frames > n_units and config.ring_velocity == "fixed"


STAGES = ("ring", "adaptive ring", "unit search")  # what decides a fitted model's places


def decision_stage(config: NeuralConfig, search: bool) -> str:
    """The stage that decides: ``"unit search"`` where it runs, else the fixed or adaptive ring.

    ``search``: whether the model searches (:func:`search_active`, resolved at fit).
    """
    if search:
        return "unit search"
    return "adaptive ring" if config.ring_velocity == "adaptive" else "ring"


def sequence_frames(config: NeuralConfig, stage: str) -> float:
    """Query frames a decision of ``stage`` integrates (what SeqSLAM's ``ds`` compares with).

    The unit search: its lines' ``search_length`` frames. The rings: ``1 / (1 -
    ring_decay)``, the sum of the weights ``decay ** j`` of frame ``j`` back against the
    newest's 1 (33.3 at the default 0.97; 90% of the weight lies in the last
    ``ln 0.1 / ln decay`` frames, 75.6 there).
    """
    if stage == "unit search":
        return float(config.search_length)
    return 1.0 / (1.0 - config.ring_decay)


class UnitSearch(nn.Module):
    """The sequence search over unit evidence (:mod:`torchseq.layers.unit_search`).

    Args:
        config: the model's settings (``search_*``, ``uniqueness_window``, ``eps``).
        spans: ``(N, 2)`` int64 first and one-past-last reference frame of each unit.
    """

    def __init__(self, config: NeuralConfig, spans: torch.Tensor) -> None:
        super().__init__()
        self.config = config
        n_units, n_frames = spans.shape[0], int(spans[-1, 1])
        self.register_buffer("spans", spans.clone(), persistent=False)
        self.register_buffer("lines", search_lines(n_units, n_frames, config.search_length,
                                                   config.search_phases,
                                                   device=spans.device), persistent=False)

    def initial(self, evidence: torch.Tensor) -> SearchHistory:
        """An empty history for ``evidence.shape[0]`` streams."""
        b, n = evidence.shape
        return SearchHistory(evidence.new_zeros(b, self.config.search_length, n),
                             torch.zeros(b, dtype=torch.int64, device=evidence.device))

    def step(self, evidence: torch.Tensor, activity: torch.Tensor,
             state: SearchHistory | None) -> tuple[torch.Tensor, torch.Tensor, SearchHistory]:
        """``(reference (B,), confidence (B,), new state)`` after one frame per stream."""
        cfg = self.config
        state = self.initial(evidence) if state is None else state
        scores, state = unit_search_step(evidence, activity, state, self.lines,
                                         cfg.search_contrast, cfg.search_ring_weight, cfg.eps)
        reference, confidence = search_decide(scores, self.spans, cfg.search_phases,
                                              cfg.uniqueness_window)
        return reference, confidence, state

    def scan(self, evidence: torch.Tensor, activity: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """One stream from its start: its decisions and each unit's best position.

        Returns:
            ``(reference (T,), confidence (T,), unit scores (T, N), unit frames (T, N))``:
            :func:`~torchseq.layers.unit_search.search_decide` and
            :func:`~torchseq.layers.unit_search.search_units` of the same scores.
        """
        cfg = self.config
        scores = unit_search_scan(evidence, activity, self.lines, cfg.search_contrast,
                                  cfg.search_ring_weight, cfg.eps)
        return (*search_decide(scores, self.spans, cfg.search_phases, cfg.uniqueness_window),
                *search_units(scores, self.spans, cfg.search_phases))


def checked_search_state(state, batch: int, n_units: int) -> SearchState | None:
    """``state`` after its checks: None or a :class:`SearchState` of ``(batch, n_units)``."""
    if state is None:
        return None
    if not isinstance(state, SearchState):
        raise NeuralError(f"a model with the unit search steps with a SearchState (None at "
                          f"the start), got {type(state).__name__}")
    if tuple(state.ring.activity.shape) != (batch, n_units):
        raise NeuralError(f"state must be ({batch}, {n_units}), got "
                          f"{tuple(state.ring.activity.shape)}")
    return state


def search_step(model, frames: torch.Tensor, state) -> tuple[NeuralStep, SearchState]:
    """:meth:`NeuralSeqSLAM.step` of a model whose :attr:`search` is set (the layers).

    The evidence and the ring run as without the search; the search decides.
    :meth:`NeuralInference.step <torchseq.neural.NeuralInference.step>` is the same step
    through the fast kernels.
    """
    state = checked_search_state(state, frames.shape[0], model.n_units)
    with torch.no_grad():
        e = model.evidence(model.code(model.encode(frames)))
        activity, ring = model.ring(e, None if state is None else state.ring)
        reference, confidence, history = model.search.step(
            e, activity, None if state is None else state.search)
    return NeuralStep(reference, confidence, activity), SearchState(ring, history)


def refuse_export(model, form: str, error: type[Exception] = NeuralError,
                  hint: str = "") -> None:
    """Raise ``error`` naming the unit search when ``model`` uses it: ``form`` has no such stage.

    The search (:mod:`torchseq.layers.unit_search`) has a float definition and a float ONNX
    form (:mod:`torchseq.export.onnx_search`) only; an export that dropped it would deploy
    a different model (the ring's decisions) without a word.
    """
    if getattr(model, "search", None) is None:
        return
    n_frames, n_units = int(model.unit_to_reference[-1, 1]), model.n_units
    raise error(f"{form} refuses this model: it decides with the unit search (unit_search="
                f"{model.config.unit_search!r}, a route of {n_frames} frames on {n_units} "
                f"units), which has no form there yet; to export, fit with unit_search='off' "
                f"(the ring alone){hint}")
