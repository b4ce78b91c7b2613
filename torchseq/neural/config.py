"""``NeuralConfig``: every setting of a Neural SeqSLAM model (defaults = the seed's Table 1)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from numbers import Integral, Real

from torchseq.layers.ring_velocity import MAX_VELOCITY


class NeuralError(ValueError):
    """Bad input or a bad checkpoint for Neural SeqSLAM."""


# fields added after the first checkpoints were written, with the behaviour those had
FORMER_DEFAULTS = {"input_steps": 0, "l1_levels": 0, "l3_levels": 0, "readout": "centre",
                   "recruit": "uniform",
                   "ring_velocity": "fixed", "unit_search": "off"}
MAX_COUNT = 2**24  # hidden, n_output, chunk, ... (a size past this is a corrupt setting)
MAX_ELEMENTS = 2**31  # the largest weight matrix a config may ask for (8 GiB of float32)
MAX_FACTOR = 1e6  # ring gain and weights: larger ones overflow float32 activity into inf/NaN
SEED_RANGE = (-(2**63), 2**64 - 2)  # torch.Generator.manual_seed's range (seed + 1 is used)


def _is_int(v) -> bool:
    return isinstance(v, Integral) and not isinstance(v, bool)


def _check_int(name: str, v, lo: int, hi: int) -> None:
    if not _is_int(v):
        raise NeuralError(f"{name} must be an integer, got {type(v).__name__} {v!r}")
    if not lo <= v <= hi:
        raise NeuralError(f"{name} must be in {lo}..{hi}, got {v}")


def _check_real(name: str, v, lo: float, hi: float, lo_open: bool = False,
                hi_open: bool = False) -> None:
    if isinstance(v, bool) or not isinstance(v, Real):
        raise NeuralError(f"{name} must be a number, got {type(v).__name__} {v!r}")
    v = float(v)
    ok = math.isfinite(v) and (lo < v if lo_open else lo <= v) and (v < hi if hi_open else v <= hi)
    if not ok:
        interval = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
        raise NeuralError(f"{name} must be a finite number in {interval}, got {v}")


def _check_choice(name: str, v, choices: tuple) -> None:
    if not isinstance(v, (str, bool)) or v not in choices:
        raise NeuralError(f"{name} must be one of {', '.join(map(repr, choices))}, got {v!r}")


@dataclass
class NeuralConfig:
    """Settings of :class:`torchseq.neural.NeuralSeqSLAM`.

    The structure is the seed's Table 1: 32x24 input, 20% L1 -> L2 mask, 3072 L2 units,
    except the L2 -> L3 layer, which is dense (``density_out=1.0``; Table 1: a 20% mask),
    and the output units: one per reference frame up to 4,096 (Table 1: 555; measured on
    nordland-b, 1,788 places: one unit per frame 0.913 recall@1, one per two 0.845, 555
    units 0.754, 3 seeds, docs/results/neural-long-routes.md). The dynamics were chosen by
    measurements over several seeds
    (``experiments/neural_quality.py --ablation``, ``docs/results/neural.md``):
    ``k_fraction=0.10`` (Table 1's example: 5%), ``patch_size=4``, ``ring_decay=0.97``,
    ``hebbian="centred"``, ``rectify=True``, ``density_out=1.0`` (over 8 seeds it lifts the
    worst corridor seed from 0.676 to 0.811 and helps every other data set measured).
    :meth:`table1` gives the 20% L2 -> L3 mask and 5% winners; :meth:`dense_readout` adds
    ring decay 0.96 to the dense layer.
    The L1 input, the L1 weights and the L2 -> L3 weights sit on integer grids
    (:mod:`torchseq.quantise`, :func:`torchseq.preprocess.quantise_input`): the L2 code is
    exact in float32 and in int8.

    Attributes:
        input_size: ``(H, W)`` the frames are resized to (L1 has ``H * W`` units).
        patch_size: patch-normalisation block side (0 disables it).
        patch_mode: ``"zscore"`` (float z-scores) or ``"seqslam"`` (OpenSeqSLAM rounding,
            ``round(z)`` clamped to -127..128 once centred).
        input_steps: L1 input (z-scores) rounded to multiples of ``1 / input_steps``
            (32: signed 8-bit for 4x4 patches); 0 keeps float input.
        hidden: L2 units.
        density: connection density of L1 -> L2.
        density_out: connection density of L2 -> L3.
        l1_levels: L1 weights are integers ``-l1_levels..l1_levels`` times a power of two
            (at most 64: the int8 products stay exact); 0 keeps float weights.
        l3_levels: each unit's Hebbian weights are rounded to integers
            ``-l3_levels..l3_levels`` times a per-unit scale (127: int8); 0 keeps floats.
        k_fraction: fraction of L2 units that win the k-WTA.
        n_output: most L3 units; a route of ``R`` frames uses ``min(R, n_output)``.
        ring_decay: weight of the shifted old activity in the ring.
        ring_gain: weight of the new evidence (None: ``1 - ring_decay``).
        ring_spread: largest lag that learns in the shift matrix.
        ring_spread_decay: weight ratio between successive lags.
        ring_stay: weight of lag 0 (a unit onto itself: slower repeats).
        ring_wrap: the route is a closed loop (last place leads to the first).
        n_cohorts: evidence is z-scored within this many contiguous blocks of units.
        rectify: clamp the z-scored evidence at 0 before it enters the ring.
        hebbian: ``"mean"`` (a unit's weights = mean code of its frames) or ``"centred"``
            (minus the mean code of the whole route).
        uniqueness_window: units around the winner ignored by the confidence margin.
        readout: ``"centre"`` (the winner's centre frame) or ``"interpolate"`` (the position
            within the winner's stretch of frames from its neighbours' activity, see
            :func:`torchseq.neural.readout.decide`; the same decisions while every unit
            holds one frame, finer when a long route gives units several frames; measured
            worse for queries much faster than the reference, so opt-in; integer format
            v2 holds it).
        recruit: how ``fit`` gives the route's frames to units, each unit a contiguous
            stretch: ``"uniform"`` (frame ``t`` -> unit ``floor(t N / R)``) or ``"novelty"``
            (a new unit where the frames' L2 codes stop matching the current unit's mean
            code, :func:`torchseq.neural.learning.recruit_by_novelty`; exactly ``N`` units,
            of unequal lengths). The same units while ``R <= n_output``.
        ring_velocity: ``"fixed"`` (the learnt shift moves the activity as fast as the
            reference, the seed's ring) or ``"adaptive"`` (each stream estimates its speed
            from its own decisions and moves the activity by that fraction of the shift,
            :mod:`torchseq.neural.velocity`; opt-in; float ONNX and integer format v3, no NIR).
        velocity_window: decisions in the adaptive speed fit (``K``).
        velocity_min: smallest adaptive speed (reference frames per query frame, <= 1).
        velocity_max: largest adaptive speed (>= 1, at most 8).
        velocity_tolerance: largest residual (reference frames, per frame of a unit) of a
            window that is trusted; other windows pull the speed back to 1.
        velocity_rate: step of the speed estimate towards its target per frame (0, 1].
        unit_search: ``"auto"`` (the default: a short sequence search over unit evidence
            beside the ring, :mod:`torchseq.layers.unit_search`, decides on routes of more
            than 10 search lines, ``10 * search_length`` frames, or where units stand for
            several frames; shorter routes keep the ring alone, bit for bit; ``fit``
            resolves it to ``"on"`` or ``"off"`` from the reference's length and keeps that
            in the model's config, :func:`torchseq.neural.search.resolve_search`), ``"on"``
            (always) or ``"off"`` (the ring alone; older checkpoints). Where it runs it
            decides instead of ``readout``. Measured on
            nordland-b, ``docs/results/neural-long-routes.md``. Float ONNX form:
            ``torchseq.export.onnx_search``; no integer or NIR form yet, so ``torchseq
            export`` refuses a model that uses it.
        search_length: frames of a search line (``L``).
        search_contrast: units on each side of the search's contrast window.
        search_ring_weight: weight of the standardised ring activity in the search score.
        search_phases: positions per unit at which lines end (``P``).
        eps: numerical floor of normalisations.
        chunk: frames per batch in ``fit`` and ``run`` (memory bound, not a result change).
        seed: seed of the random masks and L1 weights.
    """

    input_size: tuple[int, int] = (24, 32)
    patch_size: int = 4
    patch_mode: str = "zscore"
    input_steps: int = 32
    hidden: int = 3072
    density: float = 0.2
    density_out: float = 1.0
    l1_levels: int = 64
    l3_levels: int = 127
    k_fraction: float = 0.10
    n_output: int = 4096
    ring_decay: float = 0.97
    ring_gain: float | None = None
    ring_spread: int = 2
    ring_spread_decay: float = 0.5
    ring_stay: float = 0.5
    ring_wrap: bool = False
    n_cohorts: int = 1
    rectify: bool = True
    hebbian: str = "centred"
    uniqueness_window: int = 5
    readout: str = "centre"
    recruit: str = "uniform"
    ring_velocity: str = "fixed"
    velocity_window: int = 16
    velocity_min: float = 0.5
    velocity_max: float = 2.0
    velocity_tolerance: float = 3.0
    velocity_rate: float = 0.2
    unit_search: str = "auto"
    search_length: int = 40
    search_contrast: int = 5
    search_ring_weight: float = 0.1
    search_phases: int = 4
    eps: float = 1e-6
    chunk: int = 256
    seed: int = 0

    def __post_init__(self) -> None:
        size = self.input_size
        if isinstance(size, (tuple, list)) and len(size) == 2 and all(map(_is_int, size)):
            self.input_size = (int(size[0]), int(size[1]))  # else left for validate to refuse

    @property
    def n_input(self) -> int:
        """L1 units: ``H * W``."""
        return self.input_size[0] * self.input_size[1]

    @property
    def k(self) -> int:
        """L2 winners: ``max(1, round(k_fraction * hidden))``."""
        return max(1, int(round(self.k_fraction * self.hidden)))

    @property
    def gain(self) -> float:
        """Evidence weight in the ring."""
        return 1.0 - self.ring_decay if self.ring_gain is None else float(self.ring_gain)

    def validate(self) -> NeuralConfig:
        """Raise :class:`NeuralError` with a one-line reason for any bad setting; return self.

        Every field is checked by type (integers are not bools, numbers are finite) and by
        range, before anything is allocated: sizes up to ``2**24`` and weight matrices up to
        ``2**31`` elements; ring weights small enough that float32 activity stays finite.
        """
        size = self.input_size
        if not (isinstance(size, (tuple, list)) and len(size) == 2 and all(map(_is_int, size))):
            raise NeuralError(f"input_size must be two integers (H, W), got {size!r}")
        h, w = size
        _check_int("input_size[0]", h, 1, 2**15)
        _check_int("input_size[1]", w, 1, 2**15)
        _check_int("patch_size", self.patch_size, 0, min(h, w))
        p = self.patch_size
        if p and (h % p or w % p):
            raise NeuralError(f"input_size {tuple(size)} is not a multiple of patch_size {p}")
        _check_choice("patch_mode", self.patch_mode, ("zscore", "seqslam"))
        _check_int("input_steps", self.input_steps, 0, MAX_COUNT)
        _check_int("l1_levels", self.l1_levels, 0, 64)
        _check_int("l3_levels", self.l3_levels, 0, 127)
        for name in ("hidden", "n_output", "ring_spread", "n_cohorts", "chunk"):
            _check_int(name, getattr(self, name), 1, MAX_COUNT)
        for name in ("density", "density_out", "k_fraction"):
            _check_real(name, getattr(self, name), 0.0, 1.0, lo_open=True)
        _check_real("ring_decay", self.ring_decay, 0.0, 1.0, hi_open=True)
        if self.ring_gain is not None:
            _check_real("ring_gain", self.ring_gain, 0.0, MAX_FACTOR, lo_open=True)
        _check_real("ring_stay", self.ring_stay, 0.0, MAX_FACTOR)
        _check_real("ring_spread_decay", self.ring_spread_decay, 0.0, MAX_FACTOR)
        top_lag = self.ring_spread_decay ** min(self.ring_spread - 1, 64) if \
            self.ring_spread_decay > 1 else 1.0
        if top_lag > MAX_FACTOR:
            raise NeuralError(f"ring_spread_decay {self.ring_spread_decay} ** (ring_spread - 1) "
                              f"exceeds {MAX_FACTOR:g}: the shift weights would overflow")
        _check_choice("ring_wrap", self.ring_wrap, (False, True))
        _check_choice("rectify", self.rectify, (False, True))
        _check_choice("hebbian", self.hebbian, ("mean", "centred"))
        _check_choice("readout", self.readout, ("centre", "interpolate"))
        _check_choice("recruit", self.recruit, ("uniform", "novelty"))
        _check_int("uniqueness_window", self.uniqueness_window, 0, 2**31 - 1)
        _check_choice("ring_velocity", self.ring_velocity, ("fixed", "adaptive"))
        _check_int("velocity_window", self.velocity_window, 3, 4096)
        _check_real("velocity_min", self.velocity_min, 0.0, 1.0)
        _check_real("velocity_max", self.velocity_max, 1.0, MAX_VELOCITY)
        _check_real("velocity_tolerance", self.velocity_tolerance, 0.0, MAX_COUNT)
        _check_real("velocity_rate", self.velocity_rate, 0.0, 1.0, lo_open=True)
        _check_choice("unit_search", self.unit_search, ("auto", "on", "off"))
        _check_int("search_length", self.search_length, 1, 4096)
        _check_int("search_contrast", self.search_contrast, 0, 4096)
        _check_real("search_ring_weight", self.search_ring_weight, 0.0, MAX_FACTOR)
        _check_int("search_phases", self.search_phases, 1, 64)
        if self.unit_search == "on" and self.ring_velocity == "adaptive":
            raise NeuralError("unit_search='on' needs ring_velocity='fixed' (the search has "
                              "its own speeds); use unit_search='auto' or 'off'")
        _check_real("eps", self.eps, 0.0, 1.0, lo_open=True)
        _check_int("seed", self.seed, *SEED_RANGE)
        for name, n in (("hidden x n_input", self.hidden * h * w),
                        ("n_output x hidden", self.n_output * self.hidden),
                        ("n_output x n_output", self.n_output ** 2),
                        ("search lines", 5 * self.search_length * self.n_output
                         * self.search_phases)):
            if n > MAX_ELEMENTS:
                raise NeuralError(f"{name} = {n} weights exceed {MAX_ELEMENTS} (2**31)")
        return self

    @classmethod
    def table1(cls, **overrides) -> NeuralConfig:
        """The seed's Table 1 network: 20% L2 -> L3 mask, 5% k-WTA winners, 555 output units.

        The remaining fields keep this class's defaults; ``overrides`` replace any field.
        """
        return cls(**{"density_out": 0.2, "k_fraction": 0.05, "n_output": 555, **overrides})

    @classmethod
    def dense_readout(cls, **overrides) -> NeuralConfig:
        """A dense L2 -> L3 layer (no mask, the default now) with ring decay 0.96.

        Measured (8 seeds): better than the default under speed and strong appearance change
        on the demo, lower on the corridor (0.832 against 0.866 recall@1).

        ``overrides`` replace any field.
        """
        return cls(**{"density_out": 1.0, "ring_decay": 0.96, **overrides})

    @classmethod
    def adaptive_velocity(cls, **overrides) -> NeuralConfig:
        """The adaptive ring (``ring_velocity="adaptive"``) with a narrow shift (lag 1 only).

        With the speed estimated online the ring no longer needs the default's wide kernel
        (lags 0/1/2) to cover other speeds: measured (``experiments/neural_quality.py``,
        ``docs/results/neural.md``) better than the default on the corridor, LENS and every demo
        variant there (strong appearance change, 0.6x-1.6x speed, repeats), equal on the
        one where both are perfect, while each unit holds one frame (routes of at most
        ``n_output`` frames). With units of several frames it costs recall (3,000 frames on
        555 units, interpolate: 0.994 -> 0.953; corridor at 55 units 0.798 -> 0.741).
        Opt-in: exported as float ONNX and integer format v3; the spiking form refuses it.

        ``overrides`` replace any field.
        """
        return cls(**{"ring_velocity": "adaptive", "ring_spread": 1, "ring_stay": 0.0,
                      **overrides})

    def to_dict(self) -> dict:
        """Plain dict (JSON- and ``weights_only``-safe)."""
        d = asdict(self)
        d["input_size"] = list(self.input_size)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> NeuralConfig:
        """Build from :meth:`to_dict` output; unknown keys raise :class:`NeuralError`.

        Keys missing from older checkpoints take the value those models were made with.
        """
        if not isinstance(d, dict):
            raise NeuralError(f"a NeuralConfig dict is a dict, got {type(d).__name__}")
        d = {**FORMER_DEFAULTS, **d}
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise NeuralError(f"unknown NeuralConfig keys: {sorted(map(str, unknown))}")
        return cls(**d).validate()
