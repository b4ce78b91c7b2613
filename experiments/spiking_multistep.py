"""Several time steps per frame: a design study of a multi-step spiking Neural SeqSLAM.

One command (from the repository root, one thread, a few minutes on a quiet host):

    PYTHONPATH=. .venv/bin/python experiments/spiking_multistep.py [--seeds 0-7]
        [--data corridor,lens] [--variants default|stages|std|all|v1,v2,...]
        [--out experiments/results]

An experiment, not a library feature: nothing here is exported to NIR. It extends
``experiments/spiking_split.py`` (whose loading, seeding, L2 rules and one-step variants it
imports) with stage forms that need ``T`` time steps per frame, all built from NIR-expressible
parts (IF units, Linear/Affine weights, recurrent edges), simulated in float64. A variant is
``l2:norm:rect:ring`` as in the split, with these new forms:

- ``l2``: ``inh<T>`` / ``inhc<T>``: exact k-WTA by inhibition (:func:`inhibition_kwta`).
  The ``M`` L2 units are non-leaky IF units (threshold 1, reset to 0) that each inhibit
  themselves once they fire (a recurrent ``-big`` diagonal: each fires at most once per
  frame; the L3 stage integrates the winners' one spike each over the frame); one inhibitory
  counter IF unit receives every L2 spike with weight 1, threshold ``k - 1/2``, and once it
  fires inhibits the whole layer (recurrent edge, so from the next step on). Everything that
  fired up to and including the step where the count reaches ``k`` wins: ties at the ``k``-th
  place (several units crossing in that step) make more than ``k`` winners; a frame whose
  ``k``-th sum lies below the schedule's floor keeps fewer. Schedules: ``inh`` = *ramp*:
  the frame enters once, at step 1 (``(h - hi) / (hi - lo) + 1``, an Affine with a one-off
  offset from a start channel), and a bias ``1 / T`` per step ramps every membrane, so unit
  ``i`` fires at the first ``t`` with ``h_i > hi - t (hi - lo) / T``: ``T`` equal steps
  between ``hi`` and ``lo``, the range of the reference's ``k``-th L1 sums widened by 25%
  each side. ``inhc`` = *constant current*: the frame's current ``(h - lo) / (hi - lo)`` is
  held every step, unit ``i`` fires at the first ``t`` with ``t (h_i - lo) / (hi - lo) > 1``
  (higher current first; thresholds ``lo + (hi - lo) / t``, dense near ``lo`` only).
- ``ring``: ``rate<T>``: ring unit ``j`` is one IF unit (reset by subtraction) fed its
  input ``u_j / a_max`` every step for ``T`` steps: its count ``clamp(floor(T u_j / a_max),
  0, T)`` is the value (``count * a_max / T``) carried through the shift to the next frame
  (a uniform ladder of ``T`` rungs in time instead of ``K`` neurons); the decision is the
  unit with the most spikes. ``li<T>`` (with ``rect=evidence``): the rectified evidence is
  rate-coded the same way by one IF unit per output unit (``e_max``: the largest rectified
  evidence on the reference), and the ring is a non-spiking integrator per unit (NIR ``I``/
  ``LI`` with the shift as its recurrent Linear) holding ``a = decay S a + count e_max / T``
  as graded membrane; the decision reads the membranes (argmax, as the rate model's).
- ``norm``: ``frame`` (the rate model's division by each frame's cohort std, which no NIR
  node computes), ``fixed`` (calibrated ``sigma_c``), ``mad`` (each frame's cohort mean
  absolute deviation times ``ratio_c``, the reference's median std/MAD: float, to see
  whether a linear spread can stand in for the std) and ``div<T>``: the division by timing.
  Two IF units per output unit (reset by subtraction) carry ``+c_j`` and ``-c_j`` (the
  cohort-centred evidence, ``rate * c`` per step, ``rate`` keeping them at <= 1 spike per
  step on the reference), so together they spike at a rate ``rate * |c_j|``; one window IF
  unit per cohort integrates their spikes (weight ``1 / n_c``) and, once past ``theta_w``
  (set so the reference's median window is ``T`` steps), inhibits them: the window is
  ``W = ceil(theta_w / (rate * MAD))`` steps and the ``+`` unit's count
  ``floor(rate * max(c_j, 0) * W)`` is ``max(c_j, 0) / MAD`` up to the factor
  ``theta_w``: rectified, divided by the frame's spread, rate-coded. Simulated in closed
  form (the window from the analog MAD, not from the integer spike counts). The ring then
  integrates ``count * gain / theta_w`` (``ring=exact``: the input is already >= 0, so the
  unquantised ring is a linear integrator; ``rate<T>``: the ring's IF count, as above).
  ``divsd<T>``: the same window from the frame's cohort std itself (as if a circuit
  squaring and taking the root by timing were exact; not built, not simulated).
  ``sq<T>`` / ``sqstep<T>``: the division by the std by timing, built
  (:func:`square_window`, stepped: :func:`square_window_steps`). Squares by parts: per
  output unit ``2 R`` rate IF units (reset by subtraction) fed ``rate * (+-c_j - k_r)``
  (rung 0 is the evidence pair; thresholds ``k_r``: 0, then from a quarter of the
  reference's median cohort std doubling up to its largest ``|c|``: ``R`` = 6 on the
  corridor, 7 on LENS; :func:`square_rungs`), whose spikes, weighted ``w_r / n_c``, are the
  chord interpolant of ``c_j ** 2`` per step. A non-spiking integrator per cohort (NIR
  ``I``) sums them, so its membrane grows as ``rate * var * t``; the window IF unit is fed
  that membrane (a double integrator) and crosses ``theta`` at ``t ~ sqrt(2 theta / (rate
  var))``, one over the std, then inhibits the ``+`` units, whose count is ``max(c_j, 0) /
  std`` up to a constant. Every rate unit gets a one-off ``+1/2`` at the phase's first step
  (from a start channel) so its count rounds rather than floors (the integer counts would
  otherwise bias the window by a MAD-like term). ``theta`` makes the reference's median
  window ``T`` steps; ``ratio`` (the reference's median std over the rung estimate) sets the
  output scale. ``sq`` is the closed form (the integrator's membrane analog), ``sqstep`` the
  network stepped with 0/1 spikes (closes the window at most one step later: tested).
  ``sq<T>k<a>r<rho>``: first rung ``a`` median stds, ratio ``rho`` (default ``k0.25r2``).

Prints a markdown table per route (agreement per seed, min and mean; the L2 winners per frame
and the frames with ties at the k-th place for the inhibition forms) and writes
``spiking_multistep.json`` (group ``stages``; ``spiking_multistep_<group>.json`` for another
group, ``spiking_multistep_list.json`` for a list) under ``--out``. The all-exact variant
run through this script's own pipeline must equal ``NeuralSeqSLAM.run`` frame for frame (it
stops otherwise; it runs whatever the list).
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

from neural_quality import datasets  # noqa: E402
from spiking_split import RATE, SPIKING, l2_rule, seeds_arg  # noqa: E402
from spiking_split import simulate as split_simulate  # noqa: E402

from torchseq.atomic import write_json  # noqa: E402
from torchseq.export.hardware_budget import memory_bytes  # noqa: E402
from torchseq.neural import NeuralConfig, NeuralSeqSLAM  # noqa: E402
from torchseq.neural.readout import decide  # noqa: E402
from torchseq.neural.spiking import SpikingSeqSLAM  # noqa: E402
from torchseq.neural.spiking_timed import (  # noqa: E402
    divide_by_timing,
    kwta_by_inhibition,
    rung_squares,
    square_rungs,
)

SQ_FIRST, SQ_RATIO = 0.25, 2.0  # sq<T>: first rung at 1/4 of the reference's median std
VARIANTS = [
    SPIKING,  # the one-step spiking model (split's pipeline)
    RATE,  # the rate model through this script's own pipeline
    # L2 alone approximate: the inhibition k-WTA at T steps
    "inh64:frame:evidence:exact", "inh256:frame:evidence:exact",
    "inh1024:frame:evidence:exact", "inhc1024:frame:evidence:exact",
    # ring alone approximate: values coded over T steps
    "kwta:frame:evidence:rate256", "kwta:frame:evidence:rate1024",
    "kwta:frame:evidence:rate4096",
    "kwta:frame:evidence:li16", "kwta:frame:evidence:li64", "kwta:frame:evidence:li256",
    # normalisation alone approximate (calibrated), for its cost beside the others
    "kwta:fixed:evidence:exact",
    "kwta:mad:evidence:exact", "kwta:div64:evidence:exact", "kwta:div256:evidence:exact",
    "kwta:div1024:evidence:exact",
    # combinations
    "inh256:frame:evidence:li64", "inh1024:frame:evidence:li256",
    "inh256:fixed:evidence:li64", "inh1024:fixed:evidence:li256",
    "inh256:div256:evidence:exact", "inh1024:div1024:evidence:exact",
    "inh256:div256:evidence:rate1024", "inh256:div256:evidence:rate4096",
    "inh1024:div1024:evidence:rate4096",
    # the division by the std itself by timing (a square-and-root circuit assumed exact)
    "kwta:divsd256:evidence:exact", "inh256:divsd256:evidence:rate4096",
    "inh1024:divsd1024:evidence:rate4096",
]
# the division by the std by timing, built (rung squares, a double integrator): closed form
# (sq) and the stepped network (sqstep), alone and with the inhibition k-WTA and count ring
STD_VARIANTS = [
    RATE,
    "kwta:sq32:evidence:exact", "kwta:sq64:evidence:exact", "kwta:sq128:evidence:exact",
    "kwta:sq256:evidence:exact", "kwta:sqstep32:evidence:exact",
    "kwta:sqstep64:evidence:exact", "kwta:sqstep128:evidence:exact",
    "kwta:sqstep256:evidence:exact",
    "kwta:frame:evidence:rate1536", "kwta:frame:evidence:rate2048",
    "inh256:sqstep64:evidence:rate4096", "inh256:sqstep128:evidence:rate4096",
    "inh256:sqstep256:evidence:rate4096", "inh64:sqstep128:evidence:rate4096",
    "inh256:sqstep128:evidence:rate2048", "inh64:sqstep128:evidence:rate2048",
    "inh128:sqstep128:evidence:rate2048", "inh256:sqstep96:evidence:rate4096",
    "inh128:sqstep96:evidence:rate2048", "inh256:sqstep128:evidence:rate1536",
    "inh128:sqstep96:evidence:rate1536", "inh64:sqstep96:evidence:rate1536",
    "inh64:sqstep64:evidence:rate1536",
]
VARIANT_GROUPS = {
    "stages": VARIANTS,  # the stage-by-stage table (docs/results/nir.md)
    "std": STD_VARIANTS,
    "all": VARIANTS + STD_VARIANTS[1:],
    "default": [SPIKING, RATE, "inh256:frame:evidence:exact", "kwta:frame:evidence:rate4096",
                "kwta:div256:evidence:exact", "kwta:divsd256:evidence:exact",
                "kwta:sqstep128:evidence:exact", "inh256:div256:evidence:rate4096",
                "inh256:sqstep128:evidence:rate4096", "inh128:sqstep96:evidence:rate1536"],
}


def inhibition_kwta(h: torch.Tensor, k: int, steps: int, lo: float, hi: float,
                    schedule: str = "ramp") -> torch.Tensor:
    """Winners ``(F, M)`` 0/1 of the inhibition k-WTA, stepped unit by unit for ``steps`` steps.

    ``h`` ``(F, M)``: the frames' L1 sums. Non-leaky IF L2 units (threshold 1, reset to 0,
    a self-inhibition once fired), one counter IF unit (weight 1 from every L2 unit,
    threshold ``k - 1/2``) whose spike inhibits the layer from the next step on. The ramp
    schedule is the timed model's phase A (:func:`kwta_by_inhibition`).
    """
    if schedule == "ramp":  # the frame at step 1, a ramp 1/T every step
        return kwta_by_inhibition((h - hi) / (hi - lo) + 1.0, k, steps)[0]
    if schedule != "const":
        raise ValueError(f"unknown schedule {schedule!r}")
    f, m = h.shape
    v = torch.zeros_like(h)
    fired = torch.zeros_like(h)
    counter = torch.zeros(f, 1, dtype=h.dtype)
    stop = torch.zeros(f, 1, dtype=h.dtype)  # the counter's spike, delivered next step
    big = 1e9
    span = hi - lo
    cur = (h - lo) / span  # the frame's current every step
    for _ in range(steps):
        v = v + cur - big * stop - big * fired  # layer inhibition, self-inhibition
        z = (v > 1.0).to(h.dtype)
        v = v * (1.0 - z)
        fired = fired + z
        counter = counter + z.sum(1, keepdim=True)
        stop = torch.maximum(stop, (counter > k - 0.5).to(h.dtype))
    return fired


def ring_bounds(h: torch.Tensor, k: int, widen: float = 0.25) -> tuple[float, float]:
    """The schedule's range: the reference frames' ``k``-th L1 sums, widened each side."""
    kth = h.topk(k, dim=1).values[:, -1]
    lo, hi = float(kth.min()), float(kth.max())
    return lo - widen * (hi - lo), hi + widen * (hi - lo)


def square_window(c: torch.Tensor, g: torch.Tensor, rate: float, knots: torch.Tensor,
                  weights: torch.Tensor, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed form of the division by the std by timing: ``(+ counts (F, N), windows (F, C))``.

    ``c`` ``(F, N)``: the cohort-centred evidence; ``g`` ``(N, C)``: the cohorts; ``rate``:
    spikes per step per unit of ``c``; ``theta`` ``(C,)``: the window's threshold. Rate units
    (IF, threshold 1, reset by subtraction, a one-off ``+1/2`` at the phase's first step)
    fed ``rate * (+-c_j - k_r)`` spike ``floor(t x + 1/2)`` times in ``t`` steps; a
    non-spiking integrator per cohort sums their spikes with weights ``w_r / n_c``, so its
    membrane is ``rate * Q * t`` with ``Q`` the cohort's mean rung square (about its
    variance), and the window IF unit fed that membrane crosses ``theta`` at the first ``t``
    with ``rate * Q * t (t + 1) / 2 > theta``: ``W ~ sqrt(2 theta / (rate Q))``, one over
    the std. The ``+`` units (``r = 0``) are inhibited from step ``W + 1``.
    """
    n_c = g.sum(0).clamp_min(1.0)
    q = (rung_squares(c, knots, weights) @ g) / n_c  # (F, C)
    y = theta / (rate * q).clamp_min(1e-300)
    t = torch.floor((torch.sqrt(1.0 + 8.0 * y) - 1.0) / 2.0) + 1.0
    t = torch.where((t - 1.0) * t / 2.0 > y, t - 1.0, t)  # float rounding at the root
    t = torch.where(t * (t + 1.0) / 2.0 <= y, t + 1.0, t).clamp(1.0, 2.0 ** 31)
    w = t @ g.T  # each unit's cohort window (F, N)
    return torch.minimum(torch.floor(rate * c.clamp_min(0.0) * w + 0.5), w), t


def square_window_steps(c: torch.Tensor, g: torch.Tensor, rate: float, knots: torch.Tensor,
                        weights: torch.Tensor, theta: torch.Tensor,
                        max_steps: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`square_window` stepped one time step at a time, with 0/1 spikes.

    ``2 N R`` IF units (``+c_j`` and ``-c_j`` for each rung ``r``; rung 0 is the evidence
    pair), one integrator (its membrane is the weighted spike count so far) and one window
    IF unit per cohort fed that membrane, which fires once and inhibits its cohort's ``+``
    units from the next step on. Windows still closed after ``max_steps`` are 0. The timed
    model's phase B (:func:`divide_by_timing`, its compiled kernel).
    """
    plus, windows, _ = divide_by_timing(c, g, rate, knots, weights, theta, max_steps, "numba")
    return plus, windows


def square_spec(norm: str) -> dict | None:
    """``sq<T>[k<first>r<ratio>]`` / ``sqstep<T>...`` as a dict, or None for another norm."""
    m = re.fullmatch(r"sq(step)?(\d+)(?:k([0-9.]+)r([0-9.]+))?", norm)
    if m is None:
        return None
    return {"stepped": m.group(1) is not None, "steps": int(m.group(2)),
            "first": float(m.group(3) or SQ_FIRST), "ratio": float(m.group(4) or SQ_RATIO)}


def simulate(model, xr, xq, theta2: float, variant: str, cache: dict | None = None) -> dict:
    """Decisions ``(Q,)``, L2 winners, ties, division windows and evidence ``(Q, N)`` of a variant.

    ``cache`` (one per model): the L2 codes of reference and query by ``l2`` form, reused
    by the variants that share it.
    """
    l2, norm, rect, ring = variant.split(":")
    if not (l2.startswith("inh") or ring.startswith(("rate", "li"))) and ring != "exact":
        refs, fired = split_simulate(model, xr, xq, theta2, variant)
        return {"reference": refs, "fired": fired, "ties": None, "window": None,
                "evidence": None, "rungs": None, "spread_vs_std": None}
    if ring.startswith("li") and rect != "evidence":
        raise ValueError("li<T> integrates rectified evidence: use rect=evidence")
    w1 = model.l1.folded_weight().detach().double()
    w3 = model.l3.folded_weight().detach().double()
    g = model.cohorts.detach().double()
    decay, gain = (float(v) for v in model.ring.params)
    s = model.ring.shift.detach().double()
    eps, k = model.config.eps, model.config.k
    n_c = g.sum(0).clamp_min(1.0)
    if l2.startswith("inh"):
        schedule = "const" if l2.startswith("inhc") else "ramp"
        steps = int(l2[4:] if schedule == "const" else l2[3:])
        lo, hi = ring_bounds(xr @ w1.T, k)

        def code(x):
            return inhibition_kwta(x @ w1.T, k, steps, lo, hi, schedule)
    else:
        code = l2_rule(l2, xr, w1, k, theta2)

    def centred_sd(z2):
        e = z2 @ w3.T
        mu = ((e @ g) / n_c) @ g.T
        return e - mu, ((((e - mu) ** 2) @ g) / n_c).sqrt()

    windows = []  # the division's window lengths (steps), reference then query

    spreads = []  # the spread estimate over the cohort std, reference then query

    def mad(c):  # each cohort's mean absolute deviation (T, C)
        return (c.abs() @ g) / n_c

    def evidence(z2, sigma):
        c, sd = centred_sd(z2)
        if sq is not None:  # the spread estimate's ratio to the std, frame by frame
            spreads.append((((rung_squares(c, knots, weights) @ g) / n_c).sqrt() / sd))
        elif norm == "mad" or (norm.startswith("div") and not norm.startswith("divsd")):
            spreads.append(mad(c) / sd)
        if sq is not None:  # division by the std by timing: rung squares, double integrator
            if sq["stepped"]:
                count, w = square_window_steps(c, g, rate, knots, weights, theta_sq,
                                               64 * sq["steps"])
                if bool((w == 0).any()):
                    raise SystemExit(f"{variant}: a window did not close in {64 * sq['steps']}"
                                     " steps")
            else:
                count, w = square_window(c, g, rate, knots, weights, theta_sq)
            windows.append(w)
            return count * gain / ((ratio_sq * (2.0 * theta_sq * rate).sqrt()) @ g.T)
        if norm.startswith("div"):  # division by timing (rectified, counts over a window)
            spread = ratio * mad(c) if not norm.startswith("divsd") else sd
            w = torch.ceil(theta_w / (rate * spread).clamp_min(1e-300)).clamp(max=2**31)
            windows.append(w)
            count = torch.floor(rate * c.clamp_min(0.0) * (w @ g.T))
            return count * gain / (theta_w @ g.T)
        if norm == "frame":
            e = gain * c / (sd @ g.T + eps)
        elif norm == "mad":
            e = gain * c / ((ratio * mad(c)) @ g.T + eps)
        else:
            e = gain * c / (sigma @ g.T)
        return e.clamp_min(0.0) if rect == "evidence" else e

    cache = {} if cache is None else cache
    if l2 not in cache:
        cache[l2] = code(xr), code(xq)
    zr, zq = cache[l2]
    cr, sdr = centred_sd(zr)
    sigma = torch.quantile(sdr, 0.5, dim=0).clamp_min(eps)
    # mad/div calibration on the reference: sd ~ ratio * mad; the rate scale keeps every
    # evidence unit at <= 1 spike per step; theta_w makes the median window T steps
    ratio = torch.quantile(sdr / mad(cr).clamp_min(1e-300), 0.5, dim=0)
    rate = 1.0 / float(cr.abs().max())
    steps_div = int(norm.lstrip("divsd") or 1) if norm.startswith("div") else 1
    sq = square_spec(norm)
    if sq is not None:  # rungs from the reference's median std up to its largest |c|
        knots, weights = square_rungs(float(cr.abs().max()), sq["first"] * float(sdr.median()),
                                      sq["ratio"])
        qr = (rung_squares(cr, knots, weights) @ g) / n_c
        ratio_sq = torch.quantile(sdr / qr.sqrt().clamp_min(1e-300), 0.5, dim=0)
        theta_sq = sq["steps"] ** 2 * rate * torch.quantile(qr, 0.5, dim=0) / 2.0
    theta_w = steps_div * rate * torch.quantile(ratio * mad(cr), 0.5, dim=0)
    er = evidence(zr, sigma)
    steps_ring = int(ring[4:] if ring.startswith("rate") else ring[2:]) if ring != "exact" else 0
    if ring.startswith("rate"):  # the top of the rate code: the unquantised ring's largest
        a, top = torch.zeros(er.shape[1], dtype=torch.float64), 0.0
        for t in range(er.shape[0]):
            a = (er[t] + decay * (s @ a)).clamp_min(0.0)
            top = max(top, float(a.max()))
    elif ring.startswith("li"):
        top = float(er.max())
    eq = evidence(zq, sigma)
    q, out = torch.zeros(eq.shape[1], dtype=torch.float64), []
    for t in range(eq.shape[0]):
        if ring == "exact":
            q = (eq[t] + decay * (s @ q)).clamp_min(0.0)
            out.append(q)
        elif ring.startswith("rate"):
            u = eq[t] + decay * (s @ q)
            count = torch.floor(steps_ring * u / top).clamp(0, steps_ring)
            q = count * (top / steps_ring)
            out.append(count)
        else:  # li: rate-coded rectified evidence into a graded integrator
            count = torch.floor(steps_ring * eq[t] / top).clamp(0, steps_ring)
            q = count * (top / steps_ring) + decay * (s @ q)
            out.append(q)
    ref = decide(torch.stack(out), model.unit_centre, model.config.uniqueness_window)[0]
    fired = zq.sum(1)
    h = xq @ w1.T
    ties = None
    if l2.startswith("inh"):  # winners beyond k (ties at the k-th place) / short of k
        ties = {"frames_over_k": int((fired > k).sum()), "frames_under_k": int((fired < k).sum()),
                "max_over": int((fired - k).clamp_min(0).max())}
        # the winners are the top of the L1 sums (no non-winner above a winner)
        lowest_win = torch.where(zq > 0, h, torch.full_like(h, np.inf)).min(1).values
        highest_loss = torch.where(zq > 0, torch.full_like(h, -np.inf), h).max(1).values
        if not bool((lowest_win >= highest_loss).all()):
            raise SystemExit(f"{variant}: the inhibition k-WTA kept a unit below a loser")
    window = None
    if norm.startswith("div") or sq is not None:  # the query's windows: the division's steps
        wq = windows[-1]
        window = [int(wq.min()), float(wq.median()), int(wq.max())]
    return {"reference": ref.numpy(), "fired": fired.numpy(), "ties": ties, "window": window,
            "evidence": eq.numpy(), "rungs": None if sq is None else len(knots),
            "spread_vs_std": None if not spreads else
            [float(spreads[-1].min() / spreads[-1].median()),
             float(spreads[-1].max() / spreads[-1].median())]}


def design_budget(model, rungs: int | None = None) -> dict:
    """Arithmetic budget of the ``inh:div:evidence:rate`` (or ``inh:sq:evidence:rate``) design.

    Not an exported graph: counts by hand, with :func:`memory_bytes` of
    ``torchseq.export.hardware_budget`` (8-bit synapses, 16-bit states). ``rungs=None``: the
    MAD division. Populations: ``M`` L2 IF units, 1 inhibitory counter, ``2 N`` evidence IF
    units (``+c``, ``-c``), one window unit per cohort, ``N`` ring IF units. Synapses: input
    -> L2 (``nnz(w1)``), L2 <-> counter (``2 M``), L2 -> evidence (``2 N M``, the dense
    centred ``l3`` and its negative), evidence -> window (``2 N``), window -> evidence
    (``2 N``), evidence+ -> ring (``N``), ring -> ring (``nnz(S)``, through a Delay of one
    frame). ``rungs=R``: the division by the std (``sq<T>``): the L2 spikes integrate into
    ``N`` non-spiking L3 units holding ``c`` (``N M`` synapses, the dense centred ``l3``),
    which feed ``2 N R`` rate IF units (``+-c_j`` at each rung; rung 0 is the evidence pair;
    one synapse each, the rung's threshold a constant bias); one non-spiking integrator per
    cohort sums their spikes (``2 N R`` synapses) and feeds the window unit (one per cohort);
    the window inhibits the ``N`` ``+`` units.
    """
    w1 = model.l1.folded_weight().detach()
    m, d = w1.shape
    n = model.unit_centre.shape[0]
    c = model.cohorts.shape[1]
    nnz_s = int((model.ring.shift.detach() != 0).sum())
    if rungs is None:
        pops = {"l2": m, "counter": 1, "evidence": 2 * n, "window": c, "ring": n}
        pairs = {"input->l2": int((w1 != 0).sum()), "l2->counter": m, "counter->l2": m,
                 "l2->evidence": 2 * n * m, "evidence->window": 2 * n,
                 "window->evidence": 2 * n, "evidence->ring": n,
                 "ring->ring (delay: one frame)": nnz_s}
        fan_in, fan_out = m + 1, max(m, 2 * n + 1)
    else:
        pops = {"l2": m, "counter": 1, "l3 (integrator)": n, "evidence and rungs": 2 * n * rungs,
                "accumulator (integrator)": c, "window": c, "ring": n}
        pairs = {"input->l2": int((w1 != 0).sum()), "l2->counter": m, "counter->l2": m,
                 "l2->l3": n * m, "l3->evidence and rungs": 2 * n * rungs,
                 "evidence and rungs->accumulator": 2 * n * rungs, "accumulator->window": c,
                 "window->evidence+": n, "evidence->ring": n,
                 "ring->ring (delay: one frame)": nnz_s}
        fan_in, fan_out = max(m + 1, 2 * n * rungs), max(m, n + 1, 2 * rungs)
    b = {"neurons": sum(pops.values()), "effective_synapses": sum(pairs.values())}
    return {"input": d, "populations": pops, "synapses_by_pair": pairs, **b,
            "memory_bytes_8bit": memory_bytes(b, 8), "max_fan_in": fan_in,
            "max_fan_out": fan_out}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-7")
    ap.add_argument("--data", default="corridor,lens")
    ap.add_argument("--variants", default="default",
                    help=f"a group ({', '.join(VARIANT_GROUPS)}) or comma-separated "
                         "l2:norm:rect:ring")
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results"))
    ap.add_argument("--budget", action="store_true",
                    help="only print design_budget of each route's first seed")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    seeds = seeds_arg(args.seeds)
    if args.budget:
        out = {}
        for name, (ref, _qry, _gt) in datasets(tuple(args.data.split(","))).items():
            if not name.endswith("+-2"):
                model = NeuralSeqSLAM(NeuralConfig(seed=seeds[0]))
                model.fit(ref, log=False)
                xr = model.encode(ref).double()
                rungs = simulate(model, xr, xr, 0.0, "kwta:sq64:evidence:exact")["rungs"]
                out[name] = {"div": design_budget(model), "sq": design_budget(model, rungs)}
                print(name, out[name])
        return out
    variants = VARIANT_GROUPS.get(args.variants) or args.variants.split(",")
    variants = variants if RATE in variants else [RATE, *variants]  # the check below runs
    json_name = ("spiking_multistep.json" if args.variants == "stages" else
                 f"spiking_multistep_{args.variants}.json" if args.variants in VARIANT_GROUPS
                 else "spiking_multistep_list.json")
    results = {}
    for name, (ref, qry, _gt) in datasets(tuple(args.data.split(","))).items():
        if name.endswith("+-2"):
            continue
        rows = {v: {"agreement": [], "fired": [], "ties": [], "window": [], "spread": []}
                for v in variants}
        for seed in seeds:
            t0 = time.perf_counter()
            model = NeuralSeqSLAM(NeuralConfig(seed=seed))
            model.fit(ref, log=False)
            rate = model.run(qry).matches.reference.numpy()
            sp = SpikingSeqSLAM.convert(model, ref)
            xr, xq = model.encode(ref).double(), model.encode(qry).double()
            cache = {}
            for v in variants:
                r = simulate(model, xr, xq, sp.calibration["theta2"], v, cache)
                if v == RATE and not np.array_equal(r["reference"], rate):
                    raise SystemExit(f"{name} seed {seed}: the all-exact variant is not the "
                                     f"rate model on {int(np.sum(r['reference'] != rate))} "
                                     "frames")
                rows[v]["agreement"].append(float(np.mean(r["reference"] == rate)))
                f = r["fired"]
                rows[v]["fired"].append([int(f.min()), int(f.max())])
                rows[v]["ties"].append(r["ties"])
                rows[v]["window"].append(r["window"])
                rows[v]["spread"].append(r["spread_vs_std"])
            print(f"{name} seed {seed} done ({time.perf_counter() - t0:.1f} s)", flush=True)
        results[name] = rows
        write_json(Path(args.out) / json_name, {"seeds": seeds, "results": results})
    print("| data | variant | " + " | ".join(f"seed {s}" for s in seeds)
          + " | worst | mean | L2 winners per frame (min..max) | frames with > k / < k winners "
          "(sum over seeds) | division window, steps (min / median / max over seeds) |")
    print("|" + "---|" * (len(seeds) + 7))
    for name, rows in results.items():
        for v, r in rows.items():
            a, f = r["agreement"], np.array(r["fired"])
            t = r["ties"]
            ties = "" if t[0] is None else (f"{sum(x['frames_over_k'] for x in t)} / "
                                            f"{sum(x['frames_under_k'] for x in t)}")
            w = r["window"]
            win = "" if w[0] is None else (f"{min(x[0] for x in w)} / "
                                           f"{np.median([x[1] for x in w]):.0f} / "
                                           f"{max(x[2] for x in w)}")
            print(f"| {name} | `{v}` | " + " | ".join(f"{x:.3f}" for x in a)
                  + f" | {min(a):.3f} | {np.mean(a):.3f} | {f[:, 0].min()}..{f[:, 1].max()} | "
                  + f"{ties} | {win} |")
    print("\n| data | variant | spread estimate / cohort std over the query frames, "
          "divided by its median: min..max (over seeds) |\n|---|---|---|")
    for name, rows in results.items():
        for v, r in rows.items():
            if r["spread"][0] is not None:
                lo, hi = min(x[0] for x in r["spread"]), max(x[1] for x in r["spread"])
                print(f"| {name} | `{v}` | {lo:.3f}..{hi:.3f} |")
    return results


if __name__ == "__main__":
    main()
