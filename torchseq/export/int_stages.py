"""The stages of an integer model, typed, each checking its own fields against the spec.

``docs/reference/integer_format.md`` defines one step as: the input stage (pool, patch z-score), two
sparse products (L1 -> L2 with the k-WTA, L2 -> L3 with the per-row rescale), the cohort
normalisation with the gain, the fixed-point ring and the read-out. Each is a frozen
dataclass here that validates its fields on construction: dtypes, shapes, index ranges and
the bounds that keep every intermediate value inside the widths the spec names (``|a| <
2**61`` and ``0 < b < 2**62`` for each ``round_div(a, b)``, ``isqrt`` arguments below
``2**62``). Arrays are stored little-endian and read-only, so a built stage stays valid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from torchseq.quantise import fixed_point  # the writer's own rounding (HALF_AWAY)

INPUT_RAW, INPUT_ZSCORE = 0, 1
READOUT_CENTRE, READOUT_INTERPOLATE = 0, 1  # the read-out parameter (format version 2)
X_MAX = 2047  # L1 activity and L1 weights are 12-bit: |x|, |w| <= 2047 (int32 sums)
MAX_FAN_IN = (2**31 - 1) // (X_MAX * X_MAX)  # 512: an L1 sum cannot overflow int32
MAX_SIZE = 2**15 - 1  # n_input, hidden and n_units (uint16 indices, int32 sums)
E_MAX = 32767  # |E| after the evidence rescale
GAIN_BITS = 24  # gain_const < 2**GAIN_BITS
A_BOUND = 2**61  # |a| of every round_div(a, b)
B_BOUND = 2**62  # b of every round_div(a, b) and the argument of every isqrt
INT32_MAX = 2**31 - 1


class IntegerFormatError(ValueError):
    """A bad integer model file or dict: wrong magic, version, section, checksum or shape."""


class IntegerInputError(ValueError):
    """Bad input to an integer runtime: frames, state or speeds of the wrong shape or dtype."""


def _fail(msg: str) -> None:
    raise IntegerFormatError(msg)


def integer(name: str, value, lo: int, hi: int) -> int:
    """``value`` as a Python int in ``lo..hi``, or :class:`IntegerFormatError` (bool refused)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        _fail(f"{name} must be an integer, got {type(value).__name__} {value!r}")
    v = int(value)
    if not lo <= v <= hi:
        _fail(f"{name} {v} not in {lo}..{hi}")
    return v


def section(name: str, a, dtype: str, shape: tuple[int, ...], copy: bool = True) -> np.ndarray:
    """``a`` as a read-only little-endian copy of ``dtype`` and ``shape``, or an error.

    With ``copy=False`` the same checks, and ``a`` itself comes back (as an array): for a
    caller that hands it on to a stage, which makes the one stored copy.
    """
    a = np.asarray(a)
    want = np.dtype(dtype)
    if a.dtype.kind not in "iu" or a.dtype.newbyteorder("<") != want:
        _fail(f"section {name}: dtype {a.dtype} is not {want}")
    if a.shape != tuple(shape):
        _fail(f"section {name}: shape {a.shape} inconsistent with the header (expected "
              f"{tuple(shape)})")
    if not copy:
        return a
    out = np.array(a, dtype=want)
    out.setflags(write=False)
    return out


def _index_lists(name: str, cols: np.ndarray, bound: int, ascending: bool) -> None:
    """Every index of the unsigned ``(R, F)`` lists below ``bound`` (rows strictly ascending).

    Compared in the stored unsigned dtype (exact, no wider copy); an ascending row's largest
    index is its last, so only that column is searched for the bound.
    """
    if ascending and cols.shape[1] > 1 and not (cols[:, 1:] > cols[:, :-1]).all():
        _fail(f"section {name}: index lists must be strictly ascending")
    top = int((cols[:, -1] if ascending else cols).max()) if cols.size else -1
    if top >= bound:
        _fail(f"section {name}: index {top} out of range 0..{bound - 1}")


def _frozen(obj, **values) -> None:
    for k, v in values.items():
        object.__setattr__(obj, k, v)


@dataclass(frozen=True, eq=False)
class InputStage:
    """Pooling and the integer patch z-score: uint8 ``(B, h*ph, w*pw)`` -> ``x`` ``(B, D)``.

    Attributes:
        height, width: the L1 grid ``h, w`` (``D = h * w < 32768``).
        pool_h, pool_w: frames are summed over ``pool_h x pool_w`` blocks.
        patch: z-score block side ``s`` (``input_mode = 1``).
        input_mode: :data:`INPUT_ZSCORE` or :data:`INPUT_RAW` (``x`` = pooled pixels).
        x_frac, sqrt_frac: fractional bits of ``x`` and of the block standard deviation.
        norm_const: ``round_half_away(sqrt((n-1)/n) * 2**(x_frac + sqrt_frac))``, ``n = s*s``.
    """

    height: int
    width: int
    pool_h: int
    pool_w: int
    patch: int
    input_mode: int
    x_frac: int
    sqrt_frac: int
    norm_const: int

    def __post_init__(self) -> None:
        big = 2**16
        _frozen(self, height=integer("height", self.height, 1, MAX_SIZE),
                width=integer("width", self.width, 1, MAX_SIZE),
                pool_h=integer("pool_h", self.pool_h, 1, big),
                pool_w=integer("pool_w", self.pool_w, 1, big),
                patch=integer("patch", self.patch, 0, MAX_SIZE),
                input_mode=integer("input_mode", self.input_mode, INPUT_RAW, INPUT_ZSCORE),
                x_frac=integer("x_frac", self.x_frac, 0, 62),
                sqrt_frac=integer("sqrt_frac", self.sqrt_frac, 0, 62),
                norm_const=integer("norm_const", self.norm_const, 0, 2**63 - 1))
        h, w, ph, pw, s = self.height, self.width, self.pool_h, self.pool_w, self.patch
        if h * w > MAX_SIZE:
            _fail(f"n_input = height*width = {h}*{w} is not below 32768")
        peak = 255 * ph * pw  # largest pooled pixel
        if self.input_mode == INPUT_RAW:
            if peak > X_MAX:
                _fail(f"raw input pooled {ph}x{pw} exceeds {X_MAX}")
            return
        if s < 2 or h % s or w % s:
            _fail(f"patch {s} does not tile {h}x{w}")
        n = s * s
        if n * ph * pw >= 65536:
            _fail(f"patch {s} with pool {ph}x{pw} overflows the integer z-score")
        frac = self.x_frac + self.sqrt_frac
        if frac > 62 or self.norm_const != fixed_point(math.sqrt((n - 1) / n), frac, 64):
            _fail(f"norm_const {self.norm_const} is not round(sqrt((n-1)/n) * 2**{frac}) for "
                  f"n = {n}")
        var_max = (n * peak) ** 2 // 4  # V = n Q - S^2 of values in 0..peak
        if var_max << (2 * self.sqrt_frac) >= B_BOUND:
            _fail(f"sqrt_frac {self.sqrt_frac} takes the z-score's isqrt past 2**62")
        if (n - 1) * peak * self.norm_const >= A_BOUND:
            _fail(f"norm_const {self.norm_const} takes the z-score numerator past 2**61")

    @property
    def n_input(self) -> int:
        """``D = height * width``."""
        return self.height * self.width

    @property
    def frame_size(self) -> tuple[int, int]:
        """``(h * pool_h, w * pool_w)``: the device frames."""
        return self.height * self.pool_h, self.width * self.pool_w


@dataclass(frozen=True, eq=False)
class L1Product:
    """L1 -> L2 sparse product: ``hid[m] = sum_f values[m, f] * x[cols[m, f]]`` (int32 exact).

    Attributes:
        cols: ``(M, F)`` uint16 input columns of each L2 unit, strictly ascending.
        values: ``(M, F)`` int16, ``|values| <= 2047``; ``F <= 512``.
        n_input: ``D``, the width of ``x``.
    """

    cols: np.ndarray
    values: np.ndarray
    n_input: int

    def __post_init__(self) -> None:
        d = integer("n_input", self.n_input, 1, MAX_SIZE)
        shape = np.shape(self.cols)
        fan = min(MAX_FAN_IN, d)
        if len(shape) != 2 or not 1 <= shape[0] <= MAX_SIZE or not 1 <= shape[1] <= fan:
            _fail(f"section l1.cols: shape {shape} is not (hidden < 32768, 1..{fan})")
        cols = section("l1.cols", self.cols, "<u2", shape)
        values = section("l1.values", self.values, "<i2", shape)
        _index_lists("l1.cols", cols, d, ascending=True)
        if values.size and not -X_MAX <= int(values.min()) <= int(values.max()) <= X_MAX:
            _fail(f"section l1.values: values exceed +-{X_MAX}")
        _frozen(self, cols=cols, values=values, n_input=d)

    @property
    def hidden(self) -> int:
        """``M``, the L2 units."""
        return self.cols.shape[0]


@dataclass(frozen=True, eq=False)
class L3Product:
    """k-WTA code -> rescaled evidence ``E = round_shift(e * row_scale, e_shift)``.

    Attributes:
        cols: ``(N, F)`` uint16 L2 units feeding each output unit, strictly ascending.
        values: ``(N, F)`` int8, ``|values| <= 127``.
        row_scale: ``(N,)`` int32 in ``0..32768``.
        e_shift: ``0..61`` with ``k * 127 * 2**15 <= 32767 * 2**e_shift``.
        hidden: ``M``, the width of the code.
        k: the code's ones (the k-WTA winners), ``1..M``.
    """

    cols: np.ndarray
    values: np.ndarray
    row_scale: np.ndarray
    e_shift: int
    hidden: int
    k: int

    def __post_init__(self) -> None:
        m = integer("hidden", self.hidden, 1, MAX_SIZE)
        k = integer("k", self.k, 1, m)
        e_shift = integer("e_shift", self.e_shift, 0, 61)
        shape = np.shape(self.cols)
        if len(shape) != 2 or not 1 <= shape[0] <= MAX_SIZE or not 1 <= shape[1] <= m:
            _fail(f"section l3.cols: shape {shape} is not (n_units < 32768, 1..{m})")
        cols = section("l3.cols", self.cols, "<u2", shape)
        values = section("l3.values", self.values, "<i1", shape)
        scale = section("l3.row_scale", self.row_scale, "<i4", shape[:1])
        _index_lists("l3.cols", cols, m, ascending=True)
        if values.size and int(values.min()) < -127:
            _fail("section l3.values: -128 is outside the symmetric int8 range")
        if scale.size and not 0 <= int(scale.min()) <= int(scale.max()) <= 2**15:
            _fail("section l3.row_scale: scales must lie in 0..32768")
        if k * 127 * 2**15 > E_MAX * 2**e_shift:
            _fail(f"e_shift {e_shift} lets the rescaled evidence exceed 32767 (k = {k})")
        _frozen(self, cols=cols, values=values, row_scale=scale, e_shift=e_shift, hidden=m, k=k)

    @property
    def n_units(self) -> int:
        """``N``, the output units."""
        return self.cols.shape[0]


@dataclass(frozen=True, eq=False)
class CohortStage:
    """Cohort z-score of ``E`` times the gain, on the activity grid (rectified or not).

    Attributes:
        cohort: ``(N,)`` uint16 cohort of each unit, ``0..n_cohorts-1``.
        n_cohorts: ``C``, ``1..N``.
        gain_const: ``1 .. 2**24 - 1``: ``round(gain * 2**(state_frac + gain_shift))``.
        gain_shift: ``0..62`` with ``(largest cohort) * 32767 * 2**gain_shift < 2**62``.
        state_frac: fractional bits of the activity, ``0..62``.
        rectify: 1: negative values become 0; 0: kept.
    """

    cohort: np.ndarray
    n_cohorts: int
    gain_const: int
    gain_shift: int
    state_frac: int
    rectify: int

    def __post_init__(self) -> None:
        shape = np.shape(self.cohort)
        if len(shape) != 1 or not 1 <= shape[0] <= MAX_SIZE:
            _fail(f"section cohort: shape {shape} is not (n_units < 32768,)")
        cohort = section("cohort", self.cohort, "<u2", shape)
        c = integer("n_cohorts", self.n_cohorts, 1, shape[0])
        _frozen(self, cohort=cohort, n_cohorts=c,
                gain_const=integer("gain_const", self.gain_const, 1, 2**GAIN_BITS - 1),
                gain_shift=integer("gain_shift", self.gain_shift, 0, 62),
                state_frac=integer("state_frac", self.state_frac, 0, 62),
                rectify=integer("rectify", self.rectify, 0, 1))
        _index_lists("cohort", cohort[None, :], c, ascending=False)
        largest = int(np.bincount(cohort, minlength=c).max())
        # sqrt(V_c) <= n_c * 32767, so the divisor r_c * 2**gain_shift stays below 2**62; the
        # numerator |n_c E - T| * gain_const < 2 * 2**15 * 32767 * 2**24 < 2**61 always
        if (largest * E_MAX) << self.gain_shift >= B_BOUND:
            _fail(f"gain_shift {self.gain_shift} takes the cohort divisor past 2**62")


@dataclass(frozen=True, eq=False)
class RingStage:
    """The fixed-point ring: ``a = clamp(round_shift(sum_j values * state[cols], ring_frac) + g)``.

    Attributes:
        cols: ``(N, W)`` uint16 non-zero columns of each row (padding: own index).
        values: ``(N, W)`` int16 ``decay * shift`` on a ``2**-ring_frac`` grid (padding: 0).
        ring_frac: ``0..61``.
    """

    cols: np.ndarray
    values: np.ndarray
    ring_frac: int

    def __post_init__(self) -> None:
        shape = np.shape(self.cols)
        if len(shape) != 2 or not 1 <= shape[0] <= MAX_SIZE or not 1 <= shape[1] <= shape[0]:
            _fail(f"section ring.cols: shape {shape} is not (n_units < 32768, 1..n_units)")
        cols = section("ring.cols", self.cols, "<u2", shape)
        values = section("ring.values", self.values, "<i2", shape)
        _index_lists("ring.cols", cols, shape[0], ascending=False)
        # |m| <= W * 2**15 * (2**31 - 1) < 2**61 (W < 2**15), so only the divisor is bounded
        _frozen(self, cols=cols, values=values,
                ring_frac=integer("ring_frac", self.ring_frac, 0, 61))


@dataclass(frozen=True, eq=False)
class ReadoutStage:
    """The decision: the most active unit's reference frame and its confidence margin.

    Attributes:
        unit_centre: ``(N,)`` int32 reference frame each unit reports.
        unit_to_ref: ``(N, 2)`` int32 first and one-past-last reference frame of each unit,
            ``0 <= first <= unit_centre < last``.
        window: units around the winner the margin ignores, ``0..32767``.
        readout: ``READOUT_CENTRE`` (0): the winner's ``unit_centre``;
            ``READOUT_INTERPOLATE`` (1): the frame within the winner's span read from its
            neighbours' activity (docs/reference/integer_format.md, step 8; format version 2).
    """

    unit_centre: np.ndarray
    unit_to_ref: np.ndarray
    window: int
    readout: int = READOUT_CENTRE

    def __post_init__(self) -> None:
        shape = np.shape(self.unit_centre)
        if len(shape) != 1 or not 1 <= shape[0] <= MAX_SIZE:
            _fail(f"section unit_centre: shape {shape} is not (n_units < 32768,)")
        centre = section("unit_centre", self.unit_centre, "<i4", shape)
        spans = section("unit_to_ref", self.unit_to_ref, "<i4", (shape[0], 2))
        first, last = spans[:, 0], spans[:, 1]
        if (first < 0).any() or (last <= first).any():
            _fail("section unit_to_ref: spans must satisfy 0 <= first < last")
        if (centre < first).any() or (centre >= last).any():
            _fail("section unit_centre: each centre must lie in its unit's span")
        # interpolate: (last - first) * (a0 - am) < 2**31 * 2**32 = 2**63 (int32 activity),
        # so the one product of the read-out fits int64 with no further bound
        _frozen(self, unit_centre=centre, unit_to_ref=spans,
                window=integer("window", self.window, 0, MAX_SIZE),
                readout=integer("readout", self.readout, READOUT_CENTRE, READOUT_INTERPOLATE))


VEL_FRAC = 16  # fractional bits of the speed, the tolerance and the rate (format version 3)
VEL_ONE = 1 << VEL_FRAC  # speed 1: one reference frame per query frame
MAX_SPEED = 8  # at most 8 shift products per frame (layers.ring_velocity.MAX_VELOCITY)
MAX_WINDOW = 4096  # velocity_window (the float config's bound)
SLOPE_LIMIT = 1 << 36  # |target| clamp (2**20 frames per frame): exact, see velocity_den


def velocity_den(window: int) -> int:
    """``K (K^2 - 1) / 6``: ``sum_i (t_i - mean t)^2`` of the window, times 2 squared / 4.

    With ``c_i = 2 i - (K - 1)`` the LS slope is ``sum c_i p_i / velocity_den(K)``.
    """
    return window * (window * window - 1) // 6


@dataclass(frozen=True, eq=False)
class VelocityStage:
    """The adaptive ring of format version 3 (docs/reference/integer_format.md, step 7v and 9).

    Attributes:
        shift: ``(N, W)`` int32 the learnt shift alone (no decay) at ``ring.cols`` on the
            ``2**-ring_frac`` grid (padding: 0), ``abs <= 2**20``.
        decay_const: ``round(decay * 2**ring_frac)``, ``0..2**30``.
        window: ``K``, decisions in the speed fit, ``3..4096``.
        v_min, v_max: the speed's clamp on the ``2**-16`` grid,
            ``0 <= v_min <= 2**16 <= v_max <= 8 * 2**16``.
        tolerance: largest residual of a trusted window (reference frames, ``2**-16`` grid).
        rate: step of the estimate towards its target, ``1..2**16`` (``2**-16`` grid).
    """

    shift: np.ndarray
    decay_const: int
    window: int
    v_min: int
    v_max: int
    tolerance: int
    rate: int

    def __post_init__(self) -> None:
        shape = np.shape(self.shift)
        if len(shape) != 2:
            _fail(f"section ring.shift: shape {shape} is not (n_units, ring_width)")
        shift = section("ring.shift", self.shift, "<i4", shape)
        if shift.size and int(np.abs(shift.astype(np.int64)).max()) > 2**20:
            _fail("section ring.shift: values must satisfy abs <= 2**20")
        window = integer("velocity_window", self.window, 3, MAX_WINDOW)
        v_min = integer("v_min", self.v_min, 0, VEL_ONE)
        v_max = integer("v_max", self.v_max, VEL_ONE, MAX_SPEED * VEL_ONE)
        _frozen(self, shift=shift, decay_const=integer("decay_const", self.decay_const, 0, 2**30),
                window=window, v_min=v_min, v_max=v_max,
                tolerance=integer("v_tolerance", self.tolerance, 0, 2**40),
                rate=integer("v_rate", self.rate, 1, VEL_ONE))

    @property
    def top(self) -> int:
        """Shift products per frame: ``ceil(v_max / 2**16)`` (1..8)."""
        return -(-self.v_max // VEL_ONE)

    def check_fits(self, n_frames: int, ring_cols_shape: tuple[int, int]) -> None:
        """The bounds that need the rest of the model (``IntegerFormatError`` otherwise).

        Args:
            n_frames: ``F``, one past the largest reference frame (every decision is below).
            ring_cols_shape: ``ring.cols``' shape, which ``ring.shift`` must have.
        """
        if self.shift.shape != tuple(ring_cols_shape):
            _fail(f"section ring.shift: shape {self.shift.shape} is not ring.cols' "
                  f"{tuple(ring_cols_shape)}")
        width = self.shift.shape[1]
        if width * 2**20 * INT32_MAX >= A_BOUND:
            _fail(f"ring_width {width} too large for the velocity ring's int64 sums")
        k, den = self.window, velocity_den(self.window)
        num = k * k // 2 * n_frames  # |sum c_i p_i|: sum |c_i| <= K^2 / 2, 0 <= p < F
        resid = 2 * k * den * n_frames + k * (k - 1) * num  # |R_i|
        if num << VEL_FRAC >= A_BOUND or resid << VEL_FRAC >= B_BOUND \
                or self.tolerance * 2 * k * den >= B_BOUND:
            _fail(f"velocity_window {k} and {n_frames} reference frames (or the tolerance) "
                  "overflow the speed fit's int64 arithmetic")
