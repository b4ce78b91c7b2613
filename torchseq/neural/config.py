"""``NeuralConfig``: every setting of a Neural SeqSLAM model (defaults = the seed's Table 1)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields


class NeuralError(ValueError):
    """Bad input or a bad checkpoint for Neural SeqSLAM."""


# fields added after the first checkpoints were written, with the behaviour those had
FORMER_DEFAULTS = {"input_steps": 0, "l1_levels": 0, "l3_levels": 0}


@dataclass
class NeuralConfig:
    """Settings of :class:`torchseq.neural.NeuralSeqSLAM`.

    The structure is the seed's Table 1: 32x24 input, 20% L1 -> L2 mask, 3072 L2 units, 20%
    L2 -> L3 mask, 555 output units. The dynamics were chosen by measurements over several
    seeds (``experiments/neural_quality.py --ablation``, ``docs/neural.md``):
    ``k_fraction=0.10`` (Table 1's example: 5%), ``patch_size=4``, ``ring_decay=0.97``,
    ``hebbian="centred"``, ``rectify=True``. :meth:`table1` gives 5% winners;
    :meth:`dense_readout` a dense L2 -> L3 layer, which measured better on the corridor.
    The L1 input, the L1 weights and the L2 -> L3 weights sit on integer grids
    (:mod:`torchseq.neural.fixed_point`): the L2 code is exact in float32 and in int8.

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
    density_out: float = 0.2
    l1_levels: int = 64
    l3_levels: int = 127
    k_fraction: float = 0.10
    n_output: int = 555
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
    eps: float = 1e-6
    chunk: int = 256
    seed: int = 0

    def __post_init__(self) -> None:
        self.input_size = (int(self.input_size[0]), int(self.input_size[1]))

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
        """Raise :class:`NeuralError` with a one-line reason for any bad setting; return self."""
        h, w = self.input_size
        if h < 1 or w < 1:
            raise NeuralError(f"input_size must be positive, got {self.input_size}")
        p = self.patch_size
        if p < 0 or (p and (h % p or w % p)):
            raise NeuralError(f"input_size {self.input_size} is not a multiple of patch_size "
                              f"{self.patch_size}")
        if self.patch_mode not in ("zscore", "seqslam"):
            raise NeuralError(f"patch_mode must be 'zscore' or 'seqslam', got {self.patch_mode!r}")
        if self.input_steps < 0:
            raise NeuralError(f"input_steps must be >= 0, got {self.input_steps}")
        if not 0 <= self.l1_levels <= 64 or not 0 <= self.l3_levels <= 127:
            raise NeuralError(f"need 0 <= l1_levels <= 64 and 0 <= l3_levels <= 127, got "
                              f"{self.l1_levels} and {self.l3_levels}")
        if self.hidden < 1 or self.n_output < 1:
            raise NeuralError("hidden and n_output must be >= 1")
        for name in ("density", "density_out", "k_fraction"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise NeuralError(f"{name} must be in (0, 1], got {getattr(self, name)}")
        if not 0.0 <= self.ring_decay < 1.0:
            raise NeuralError(f"ring_decay must be in [0, 1), got {self.ring_decay}")
        if self.gain <= 0:
            raise NeuralError(f"ring_gain must be > 0, got {self.ring_gain}")
        if self.ring_spread < 1 or self.ring_spread_decay < 0 or self.ring_stay < 0:
            raise NeuralError("need ring_spread >= 1, ring_spread_decay >= 0, ring_stay >= 0")
        if self.n_cohorts < 1:
            raise NeuralError(f"n_cohorts must be >= 1, got {self.n_cohorts}")
        if self.hebbian not in ("mean", "centred"):
            raise NeuralError(f"hebbian must be 'mean' or 'centred', got {self.hebbian!r}")
        if self.uniqueness_window < 0 or self.eps <= 0 or self.chunk < 1:
            raise NeuralError("need uniqueness_window >= 0, eps > 0 and chunk >= 1")
        return self

    @classmethod
    def table1(cls, **overrides) -> NeuralConfig:
        """The seed's Table 1 network: 20% L2 -> L3 mask and 5% k-WTA winners.

        The remaining fields keep this class's defaults; ``overrides`` replace any field.
        """
        return cls(**{"density_out": 0.2, "k_fraction": 0.05, **overrides})

    @classmethod
    def dense_readout(cls, **overrides) -> NeuralConfig:
        """A dense L2 -> L3 layer (no mask) with ring decay 0.96: the best corridor recall measured.

        ``overrides`` replace any field.
        """
        return cls(**{"density_out": 1.0, "ring_decay": 0.96, **overrides})

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
        d = {**FORMER_DEFAULTS, **d}
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise NeuralError(f"unknown NeuralConfig keys: {sorted(unknown)}")
        return cls(**d).validate()
