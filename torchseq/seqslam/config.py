"""Parameters of the classic SeqSLAM engine, with OpenSeqSLAM's meanings and defaults."""

from __future__ import annotations

import math
from dataclasses import dataclass
from numbers import Integral, Real

METRICS = ("l1", "l2", "cosine")
MATCH_AT = ("start", "trajectory")
PREPROCESSING = ("torchseq", "openseqslam")
PRESETS = ("default", "openseqslam", "events")
EVENT_DS_REFERENCE = 100  # the event preset's sequence: this many reference windows long
KEEP_MATRICES_MAX = 2**27  # R * Q above which the full matrices are not kept by default
# Every path (flags, maps, Event-LAB settings, the API) is held to these by validate():
# each field's closed range, before anything is sized or enumerated from it.
LIMITS = {
    "patch_size": (0, 4096), "enhance_window": (0, 10 ** 6), "ds": (2, 10 ** 5),
    "vmin": (1e-3, 1e3), "vmax": (1e-3, 1e3), "speed_ratio": (1e-3, 1e3),
    "speed_tolerance": (0.0, 1.0), "rwindow": (0, 10 ** 6), "top_k": (1, 1000),
    "max_chunk_elements": (1, 2 ** 40), "candidates": (0, 10 ** 6), "threads": (1, 4096),
}
MAX_IMAGE_SIDE = 4096  # image_size: each side in 1 .. 4096 pixels
MAX_IMAGE_PIXELS = 2 ** 22  # and at most 4 Mpixel per frame


@dataclass
class SeqSLAMConfig:
    """Everything the classic engine needs; ``dataclasses.asdict`` gives a JSON-ready dict.

    Attributes:
        image_size: ``(height, width)`` frames are resized to (OpenSeqSLAM: 32 x 64).
        patch_size: patch-normalisation block side in pixels; 0 disables it.
        metric: ``"l1"`` (sum of absolute differences, OpenSeqSLAM), ``"l2"`` (Euclidean) or
            ``"cosine"`` (1 - cosine similarity).
        enhance_window: local contrast enhancement window R in reference rows (0 = off).
        ds: sequence length in query frames; odd values are rounded up to even.
        vmin: slowest trajectory velocity, reference frames per query frame.
        vmax: fastest trajectory velocity.
        speed_ratio: if set, a known speed ratio (reference frames per query frame) that
            replaces ``vmin``/``vmax`` by ``ratio * (1 -+ speed_tolerance)``.
        speed_tolerance: fractional tolerance around ``speed_ratio``.
        rwindow: uniqueness exclusion window Rwindow, in starts around the best one.
        top_k: ranked candidates kept per query (for recall@K).
        max_chunk_elements: memory budget, in elements of the working dtype, of every chunked
            temporary (difference blocks, enhancement blocks, trajectory scores).
        match_at: which reference a winning trajectory reports for the query at its centre:
            ``"trajectory"`` = start + floor(v_best ds/2), the row the best trajectory
            actually crosses at the centre column (its step ``k = ds/2`` of ``0..ds``), or
            ``"start"`` = start + ds/2 (OpenSeqSLAM; exact only at velocity 1, so a query
            at 0.8x speed is reported 1.4 frames ahead and one at 1.3x 0.6 behind, demo
            medians).
            None (default): ``"trajectory"``; the :meth:`openseqslam` preset sets
            ``"start"``. The rule moves only the reported place (and the ranked
            candidates' places), never the best start or its uniqueness; measured in
            docs/guide/seqslam.md, "Where the reported place sits".
        preprocessing: ``"torchseq"`` (default): float grey, a flat 8x8 block becomes 127;
            ``"openseqslam"``: OpenSeqSLAM's uint8 rules (MATLAB ``rgb2gray`` rounded to
            integer grey, integer resize output, ``127 + round(z)`` stored in uint8 so a flat
            block, z = 0/0 = NaN, becomes 0). See ``preprocess.preprocess_openseqslam``.
        edges: also match the first and last ``ds/2`` queries, which no centred window covers:
            from the leading window (the query and the ``ds`` after it; reported place: the
            trajectory's start) and the trailing window (the ``ds`` before it; its end).
            OpenSeqSLAM leaves them unmatched (False).
        threads: CPU worker threads per stage, each taking whole blocks; every op runs on one
            intra-op thread (see ``seqslam/_parallel.py``). None: ``torch.get_num_threads()``
            capped by the cores no other process keeps busy.
        keep_matrices: return the full ``(R, Q)`` difference and enhanced matrices. False:
            work in bands of query columns in O(R (B + ds)) memory (``seqslam/banded.py``)
            and return only a reduced copy (``SeqSLAMResult.preview``). None (default): keep
            them while ``R * Q <= KEEP_MATRICES_MAX`` (2**27, two 512 MiB float32 matrices).
        candidates: candidate mode (docs/guide/seqslam.md): K >= 1 nearest references per query
            from a FAISS index, only trajectories through them scored; 0 = always the exact
            all-pairs mode; None (default) = exact up to 2**31 reference x query pairs,
            candidate mode with K = 20 (and a warning) above.
    """

    image_size: tuple[int, int] = (32, 64)
    patch_size: int = 8
    metric: str = "l1"
    enhance_window: int = 10
    ds: int = 10
    vmin: float = 0.8
    vmax: float = 1.2
    speed_ratio: float | None = None
    speed_tolerance: float = 0.2
    rwindow: int = 10
    top_k: int = 10
    max_chunk_elements: int = 2**26
    match_at: str | None = None
    preprocessing: str = "torchseq"
    edges: bool = False
    threads: int | None = None
    keep_matrices: bool | None = None

    @classmethod
    def openseqslam(cls, **overrides) -> SeqSLAMConfig:
        """OpenSeqSLAM 2013 exactly: its defaults and its uint8 preprocessing rules.

        Parameters as ``defaultParameters.m`` (64x32, side 8, ds 10, v 0.8..1.2, R 10,
        Rwindow 10), integer grey and flat blocks -> 0 (``preprocessing="openseqslam"``),
        ``start + ds/2``, the centred window, no edge matches. ``overrides`` replace fields.
        """
        base = dict(image_size=(32, 64), patch_size=8, metric="l1", enhance_window=10, ds=10,
                    vmin=0.8, vmax=1.2, speed_ratio=None, rwindow=10, match_at="start",
                    preprocessing="openseqslam", edges=False)
        return cls(**{**base, **overrides}).validate()

    @classmethod
    def events(cls, speed_ratio: float = 1.0, **overrides) -> SeqSLAMConfig:
        """The event preset: the seed's setting with edges and a sequence of fixed route length.

        Frames 16x16 (the DVS128's 128x128 area-pooled), patch side 8, a velocity range of
        ``speed_ratio`` +- 20% (reference windows per query window), reporting where the best
        trajectory crosses the query centre, ``edges=True`` (the first and last ``ds/2``
        queries are matched from their leading or trailing window instead of left
        unmatched), and ``ds = round(100 / speed_ratio)`` query frames: every sequence spans
        100 reference windows of route (the seed's ds = 100 at equal speeds; 152 at ratio
        0.66, 400 at 0.25). A ``ds`` in ``overrides`` wins. Chosen on simulated nordland-b
        event runs, same season and across seasons at 1.5x and 4x speed difference, against
        ds = 100, temporal-window ensembles and 16x32 frames (docs/results/event-preset.md,
        ``experiments/event_preset.py``).
        """
        ok = (isinstance(speed_ratio, (int, float)) and math.isfinite(speed_ratio)
              and speed_ratio > 0)  # else validate() names the bad ratio
        ds = max(2, round(EVENT_DS_REFERENCE / speed_ratio)) if ok else EVENT_DS_REFERENCE
        base = dict(image_size=(16, 16), patch_size=8, ds=ds, speed_ratio=speed_ratio,
                    speed_tolerance=0.2, match_at="trajectory", edges=True)
        return cls(**{**base, **overrides}).validate()

    @classmethod
    def preset(cls, name: str, **overrides) -> SeqSLAMConfig:
        """A named preset: ``"default"``, ``"openseqslam"`` or ``"events"``."""
        if name not in PRESETS:
            raise ValueError(f"preset must be one of {PRESETS}, got {name!r}")
        if name == "default":
            return cls(**overrides).validate()
        return getattr(cls, name)(**overrides)
    candidates: int | None = None

    def validate(self) -> SeqSLAMConfig:
        """Raise ``ValueError`` on nonsense values; return ``self`` for chaining."""
        size = self.image_size
        if (not isinstance(size, (tuple, list)) or len(size) != 2
                or not all(isinstance(v, Integral) and not isinstance(v, bool) for v in size)
                or not all(1 <= v <= MAX_IMAGE_SIDE for v in size)
                or size[0] * size[1] > MAX_IMAGE_PIXELS):
            raise ValueError(f"image_size must be (height, width), each 1..{MAX_IMAGE_SIDE} and "
                             f"at most {MAX_IMAGE_PIXELS} pixels, got {size!r}")
        for name, (lo, hi) in LIMITS.items():
            value = getattr(self, name)
            if value is None and name in ("speed_ratio", "candidates", "threads"):
                continue
            whole = isinstance(lo, int)
            if (isinstance(value, bool) or not isinstance(value, Integral if whole else Real)
                    or not lo <= value <= hi):
                kind = "an integer" if whole else "a number"
                raise ValueError(f"{name} must be {kind} in [{lo}, {hi}], got {value!r}")
        h, w = size
        p = self.patch_size
        if p and (h % p or w % p):
            raise ValueError(
                f"patch_size {self.patch_size} must be 0 or divide image_size {self.image_size}")
        if self.metric not in METRICS:
            raise ValueError(f"metric must be one of {METRICS}, got {self.metric!r}")
        if self.enhance_window == 1:
            raise ValueError(f"enhance_window must be 0 (off) or >= 2, got {self.enhance_window}")
        if self.speed_ratio is not None and not self.speed_tolerance < 1:
            raise ValueError(f"speed_tolerance must be in [0, 1), got {self.speed_tolerance}")
        vmin, vmax = self.velocity_range
        if not (math.isfinite(vmin) and math.isfinite(vmax)) or vmin <= 0:
            raise ValueError(f"vmin must be > 0, got {vmin}")
        if vmin > vmax:
            raise ValueError(f"vmin {vmin} must not exceed vmax {vmax}")
        if self.match_at not in (None, *MATCH_AT):
            raise ValueError(f"match_at must be one of {MATCH_AT} or None, got {self.match_at!r}")
        if self.preprocessing not in PREPROCESSING:
            raise ValueError(
                f"preprocessing must be one of {PREPROCESSING}, got {self.preprocessing!r}")
        if not isinstance(self.edges, bool) or self.keep_matrices not in (None, True, False):
            raise ValueError(f"edges and keep_matrices must be True or False, got "
                             f"{self.edges!r}, {self.keep_matrices!r}")
        from torchseq.seqslam.search import velocities

        velocities(self.sequence_length, vmin, vmax)  # raises on no step or too many
        return self

    @property
    def sequence_length(self) -> int:
        """``ds`` rounded up to even, as OpenSeqSLAM uses it."""
        return int(self.ds) + int(self.ds) % 2

    def keeps_matrices(self, n_ref: int, n_query: int) -> bool:
        """Whether a run of ``n_ref`` x ``n_query`` keeps the full matrices."""
        if self.keep_matrices is not None:
            return bool(self.keep_matrices)
        return n_ref * n_query <= KEEP_MATRICES_MAX

    @property
    def match_rule(self) -> str:
        """``match_at`` with its default resolved: None -> ``"trajectory"``."""
        return "trajectory" if self.match_at is None else self.match_at

    @property
    def velocity_range(self) -> tuple[float, float]:
        """``(vmin, vmax)`` after applying ``speed_ratio`` when it is set."""
        if self.speed_ratio is None:
            return float(self.vmin), float(self.vmax)
        r, tol = float(self.speed_ratio), float(self.speed_tolerance)
        return r * (1.0 - tol), r * (1.0 + tol)
