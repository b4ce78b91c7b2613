"""Phase B of the timed spiking model, compiled (numba): the ``"numba"`` division kernel.

Private kernel behind :func:`torchseq.neural.spiking_timed.divide_by_timing` (the definition
and the ``"torch"`` kernel are there). The same float64 operations in the same order as the
torch kernel, so the two agree spike for spike: each rate unit's ``v <- v + x`` (and
``+ 1/2`` at step 1), ``z = v > 1``, ``v <- v - z``; per cohort and rung an integer spike
count, the increment ``sum_r count_r * w_r / n_c`` added rung by rung from 0, then
``acc += increment``, ``window_v += acc``. Two shortcuts that change no spike: a rate unit
whose input ``x <= 0`` never fires (``v <= 1/2``) and is skipped, and a frame stops at the
step its last window closes. Frames run one after another; each frame's work is its
firing units times its steps, not ``2 N R`` times the longest frame's steps.

``tests/test_spiking_timed.py`` checks it against the torch kernel and a plain loop.
Imported only when the kernel runs; compiled on first use and cached beside this file.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def divide(c, cohort_of, rate, knots, wn, theta, steps, plus, windows,
           spikes):  # pragma: no cover - compiled
    """Phase B for every frame; writes ``plus``, ``windows`` and ``spikes`` in place.

    Args:
        c: ``(F, N)`` float64 cohort-centred evidence.
        cohort_of: ``(N,)`` int64 each unit's cohort.
        rate: spikes per step per unit of ``c``.
        knots: ``(R,)`` float64 rung thresholds.
        wn: ``(C, R)`` float64 ``w_r / n_c``.
        theta: ``(C,)`` float64 window thresholds.
        steps: the phase's length.
        plus: ``(F, N)`` float64 zeros: the ``+`` counts.
        windows: ``(F, C)`` float64 zeros: each window's step (0: clipped).
        spikes: ``(F,)`` float64 zeros: the phase's spikes.
    """
    n_frames, n = c.shape
    n_rungs = knots.shape[0]
    n_coh = theta.shape[0]
    idx = np.empty(2 * n * n_rungs, np.int64)  # the firing units: j * 2 R + s * R + r
    xs = np.empty(2 * n * n_rungs, np.float64)
    v = np.empty(2 * n * n_rungs, np.float64)
    counts = np.zeros((n_coh, n_rungs), np.float64)
    acc = np.zeros(n_coh, np.float64)
    wv = np.zeros(n_coh, np.float64)
    is_open = np.ones(n_coh, np.bool_)
    for f in range(n_frames):
        m = 0
        for j in range(n):
            for s in range(2):
                sign = 1.0 if s == 0 else -1.0
                for r in range(n_rungs):
                    x = rate * (sign * c[f, j] - knots[r])
                    if x > 0.0:
                        idx[m] = (j * 2 + s) * n_rungs + r
                        xs[m] = x
                        v[m] = 0.0
                        m += 1
        for cc in range(n_coh):
            acc[cc] = 0.0
            wv[cc] = 0.0
            is_open[cc] = True
        closed = 0
        for t in range(1, steps + 1):
            for cc in range(n_coh):
                for r in range(n_rungs):
                    counts[cc, r] = 0.0
            for i in range(m):
                vv = v[i] + xs[i]
                if t == 1:
                    vv = vv + 0.5
                if vv > 1.0:
                    vv = vv - 1.0
                    k = idx[i]
                    j = k // (2 * n_rungs)
                    r = k % n_rungs
                    cc = cohort_of[j]
                    counts[cc, r] += 1.0
                    if k % (2 * n_rungs) == 0:  # s = 0, r = 0: the + unit
                        if is_open[cc]:
                            plus[f, j] += 1.0
                            spikes[f] += 1.0
                    else:
                        spikes[f] += 1.0
                v[i] = vv
            for cc in range(n_coh):
                inc = 0.0
                for r in range(n_rungs):
                    inc = inc + counts[cc, r] * wn[cc, r]
                acc[cc] = acc[cc] + inc
                wv[cc] = wv[cc] + acc[cc]
            for cc in range(n_coh):
                if windows[f, cc] == 0.0 and wv[cc] > theta[cc]:
                    windows[f, cc] = t
                    spikes[f] += 1.0
                    closed += 1
            for cc in range(n_coh):
                is_open[cc] = windows[f, cc] == 0.0
            if closed == n_coh:
                break
