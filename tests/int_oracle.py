"""An independent plain-Python reference of one integer step (docs/reference/integer_format.md).

Written from the spec with Python integers, ``math.isqrt``, exact ``Fraction`` rounding,
explicit loops and a sort-based top-k, sharing no code with ``torchseq.export.int_runtime``.
Slow: only for tiny models.
"""

import math
from fractions import Fraction


def round_half_away(q: Fraction) -> int:
    n = math.floor(abs(q) + Fraction(1, 2))
    return n if q >= 0 else -n


def oracle_step(model, frame, state):
    """frame: nested lists (h*ph, w*pw) of 0..255; state: list of N ints -> (act, ref, conf)."""
    p, a = model.params, model.arrays
    h, w, ph, pw = p["height"], p["width"], p["pool_h"], p["pool_w"]
    g = [[sum(int(frame[i * ph + u][j * pw + v]) for u in range(ph) for v in range(pw))
          for j in range(w)] for i in range(h)]
    x = [[0] * w for _ in range(h)]
    if p["input_mode"] == 1:
        s = p["patch"]
        n = s * s
        for bi in range(0, h, s):
            for bj in range(0, w, s):
                pix = [(i, j) for i in range(bi, bi + s) for j in range(bj, bj + s)]
                total = sum(g[i][j] for i, j in pix)
                var = n * sum(g[i][j] ** 2 for i, j in pix) - total * total
                root = math.isqrt(var * 4 ** p["sqrt_frac"])
                for i, j in pix:
                    if var > 0:
                        z = round_half_away(Fraction((n * g[i][j] - total) * p["norm_const"],
                                                     root))
                        x[i][j] = max(-2047, min(2047, z))
    else:
        x = g
    flat = [x[i][j] for i in range(h) for j in range(w)]
    # the weights as Python ints once per step (iterating NumPy scalars made the sums 5x slower)
    l1_cols, l1_values = a["l1.cols"].tolist(), a["l1.values"].tolist()
    hidden = [sum(v * flat[c] for c, v in zip(l1_cols[m], l1_values[m]))
              for m in range(p["hidden"])]
    winners = sorted(range(p["hidden"]), key=lambda m: (-hidden[m], m))[:p["k"]]
    n_units = p["n_units"]
    e = [0] * n_units
    for u in range(n_units):
        row = dict(zip(a["l3.cols"][u].tolist(), a["l3.values"][u].tolist()))
        raw = sum(row.get(m, 0) for m in winners)
        e[u] = round_half_away(Fraction(raw * int(a["l3.row_scale"][u]), 2 ** p["e_shift"]))
    cohort = [int(c) for c in a["cohort"]]
    gz = [0] * n_units
    for c in range(p["n_cohorts"]):
        units = [u for u in range(n_units) if cohort[u] == c]
        n, total = len(units), sum(e[u] for u in units)
        var = n * sum(e[u] ** 2 for u in units) - total * total
        for u in units:
            if var > 0:
                gz[u] = round_half_away(Fraction((n * e[u] - total) * p["gain_const"],
                                                 math.isqrt(var) * 2 ** p["gain_shift"]))
            if p["rectify"]:
                gz[u] = max(gz[u], 0)
    act = []
    ring_cols, ring_values = a["ring.cols"].tolist(), a["ring.values"].tolist()
    for u in range(n_units):
        moved = sum(v * state[c] for c, v in zip(ring_cols[u], ring_values[u]))
        val = round_half_away(Fraction(moved, 2 ** p["ring_frac"])) + gz[u]
        act.append(max(-(2**31 - 1), min(2**31 - 1, val)))
    best = max(range(n_units), key=lambda u: (act[u], -u))
    rivals = [act[v] for v in range(n_units) if abs(v - best) > p["window"]]
    second = max(rivals) if rivals else min(act)
    if p.get("readout", 0) == 1:
        first, last = (int(v) for v in a["unit_to_ref"][best])
        return act, oracle_within_unit(act, best, first, last), act[best] - second
    return act, int(a["unit_centre"][best]), act[best] - second


def oracle_within_unit(act, best, first, last):
    """The interpolating read-out as the float definition writes it, in exact fractions.

    The vertex of the parabola through ``(-1, am), (0, a0), (1, ap)``,
    ``x = (am - ap) / (2 (am - 2 a0 + ap))`` (0 at the ring's ends and when the curvature is
    not negative), then ``clamp(floor((first + last - 1) / 2 + x (last - first) + 1/2),
    first, last - 1)``.
    """
    x = Fraction(0)
    if 0 < best < len(act) - 1:
        am, a0, ap = act[best - 1], act[best], act[best + 1]
        if am - 2 * a0 + ap < 0:
            x = Fraction(am - ap, 2 * (am - 2 * a0 + ap))
    pos = math.floor(Fraction(first + last - 1, 2) + x * (last - first) + Fraction(1, 2))
    return min(max(pos, first), last - 1)
