"""An eval run's engines: SeqSLAM and Neural SeqSLAM on its traverses, with their checks.

Each engine returns its matches, ranked candidates, what the report draws and its timing
(:func:`run_engines`); :func:`single_frame_baseline` is the single-frame matcher beside them.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from pathlib import Path

import torch

from torchseq import metrics
from torchseq.cli.errors import UsageError
from torchseq.cli.eval_settings import EvalConfig, Settings
from torchseq.cli.event_options import event_frame_options
from torchseq.cli.flags import frame_selection
from torchseq.cli.map import run_seqslam_map
from torchseq.cli.presets import preset_name
from torchseq.cli.results import EngineRun, NeuralRun, SeqSLAMRun
from torchseq.cli.runs import Notes, to_jsonable, warn
from torchseq.cli.traverse import Traverse
from torchseq.descriptors import neural_config, neural_input
from torchseq.matches import Matches
from torchseq.neural.memory import seqslam_template_bytes
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig

PROG = "torchseq eval"  # names warnings given a plain list (a run's WarningLog names itself)


RANKED = max(metrics.RECALL_KS) + 1  # candidates ranked: recall@20 and the tie past it


def ranked_config(config: SeqSLAMConfig) -> SeqSLAMConfig:
    """The run's SeqSLAM config with at least :data:`RANKED` ranked candidates.

    ``top_k`` only sizes the ranked list (it changes no match); metrics.json's recall@20
    needs 20 candidates and one more to see a tie at the 20th.
    """
    return dataclasses.replace(config, top_k=max(config.top_k, RANKED))


def transposed_size(size, frame_size) -> str | None:
    """A warning when ``size`` ``(h, w)`` has the transposed aspect of ``frame_size`` ``(H, W)``.

    OpenSeqSLAM and much of the literature write image sizes as width x height (64x32);
    ``--image-size`` is height x width, so the transposed spelling squeezes landscape frames
    into portrait images (corridor recall@1 0.441 -> 0.216).
    """
    (h, w), (fh, fw) = (int(v) for v in size), (int(v) for v in frame_size)
    if h == w or fh == fw or (h > w) == (fh > fw):
        return None
    # closer to the frames' aspect when swapped?
    if abs(math.log((w / h) / (fw / fh))) <= abs(math.log((h / w) / (fw / fh))):
        return None
    return (f"--image-size {h}x{w} is height x width ({h} high, {w} wide), the transposed "
            f"shape of these {fh}x{fw} frames ({'landscape' if fw > fh else 'portrait'}); "
            f"give --image-size {w}x{h} if you meant width x height (OpenSeqSLAM's 64x32 is "
            f"32x64 here)")


def run_seqslam(s: Settings, ref, query, device, notes: Notes) -> SeqSLAMRun:
    """Classic SeqSLAM: matches, ranked candidates, the matrix to plot, seconds, parameters."""
    ds = s.seqslam.sequence_length
    if ds > len(query):
        hint = ""
        if query.info.get("events") and s.run.event_count is None:
            n, w = query.info["n_total"], event_frame_options(s.run).window_ms
            if n > 1:  # the events span more than (n - 1) windows
                hint = (f": the query recording fills {n} windows of {w:g} ms (more than "
                        f"{(n - 1) * w:g} ms of events); --window-ms {(n - 1) * w / ds:.3g} "
                        f"or less gives at least {ds} frames")
            else:
                hint = (f": the query recording is shorter than one {w:g} ms window; give "
                        f"shorter windows (--window-ms) or a fixed number of events per frame "
                        f"(--event-count N makes frames of N events each)")
        raise UsageError(f"--ds {s.seqslam.ds} is longer than the query ({len(query)} frames)"
                         + hint)
    if s.run.map is not None:
        return run_seqslam_map(s, query, device, s.run.progress)
    size = s.seqslam.image_size
    if ref.descriptors is None:
        transposed = transposed_size(size, ref.info["frame_size"])
        if transposed:
            warn(PROG, transposed, notes)
    config = ranked_config(s.seqslam)
    if ref.descriptors is not None:
        result = SeqSLAM(config, device=device).match_descriptors(
            ref.descriptors, query.descriptors, progress=s.run.progress)
    elif ref.members is not None:  # temporal-window ensemble (--window-ms 5,10,20)
        from torchseq.events.ensemble import match_ensemble

        result = match_ensemble(ref.members_at(size), query.members_at(size), config, device)
    else:
        result = SeqSLAM(config, device=device).match(ref.at(size), query.at(size),
                                                      progress=s.run.progress)
    # plots draw the engine's reduced copy (area averages, at most 1024 a side; the whole
    # matrix below that) in full-matrix coordinates; long routes keep nothing else. Without
    # one, the enhanced matrix (a sparse one is reduced as it is, never made dense)
    matrix = result.preview if result.preview is not None else result.enhanced
    # the raw difference matrix of the run's own descriptors: the single-frame baseline ranks
    # it instead of computing it again (not an ensemble's: that is not one descriptor set's)
    # (dense only: candidate mode keeps the candidates' entries, a sparse matrix)
    difference = result.difference if ref.members is None else None
    if difference is not None and difference.layout != torch.strided:
        difference = None
    return SeqSLAMRun(matches=result.matches, ranked=result.ranked,
                      ranked_score=result.ranked_score, matrix=matrix,
                      matrix_shape=(len(ref), len(query)), matrix_reduced=result.enhanced is None,
                      seconds=result.seconds["total"], parameters=to_jsonable(config),
                      difference=difference,
                      kernels=to_jsonable(result.kernels) or None)


SAMPLE_QUERIES = 256  # queries of a candidate-mode run matched in the exact mode as well
MAX_RECALL_LOSS = 0.02  # with ground truth: sample recall@1 below the exact mode's by more
MIN_AGREEMENT = 0.75  # without: the share of the exact mode's matches found (nordland-b:
#                       K = 20 28%, recall 0.380 against 0.653; K = 100 82%, recall held)


def candidate_check(s: Settings, run: SeqSLAMRun, ref: Traverse, query: Traverse, gt, device,
                    notes: Notes) -> None:
    """Candidate mode against the exact mode on a sample of queries; warn where K loses.

    A block of :data:`SAMPLE_QUERIES` queries in the middle of the route (with ``ds/2`` more
    each side, so every sampled query has its whole sequence) is matched in the exact mode
    against the whole reference. With ground truth the two recall@1 on the sample are
    compared, else the share of sampled queries whose candidate-mode match lies within one
    frame of the exact mode's; both go to ``run.candidate_agreement`` (metrics.json).
    """
    from torchseq.maps import ReferenceMap
    from torchseq.seqslam.candidates import resolve_candidates

    cfg = s.seqslam
    with warnings.catch_warnings():  # said once already, by the run
        warnings.simplefilter("ignore")
        k = resolve_candidates(cfg, run.matrix_shape[0], len(query))
    if not k or ref.members is not None:  # exact mode; an ensemble is not one descriptor set
        return
    engine = SeqSLAM(dataclasses.replace(ranked_config(cfg), candidates=0), device=device)
    half = cfg.sequence_length // 2
    n = min(len(query), SAMPLE_QUERIES + 2 * half)
    a = (len(query) - n) // 2
    if query.descriptors is not None:
        sample = query.descriptors[a:a + n]
    else:
        sample = engine.descriptors(query.at(cfg.image_size)[a:a + n])
    if s.run.map is not None:
        reference = ReferenceMap(s.run.map).descriptors()
    elif ref.descriptors is not None:
        reference = ref.descriptors
    else:
        reference = engine.descriptors(ref.at(cfg.image_size))
    cols = torch.arange(a + half, a + n - half)
    exact = torch.full_like(run.matches.reference, -1)
    exact[cols] = engine.match_descriptors(reference, sample).matches.reference[half:n - half]
    mine = run.matches.reference
    found = (exact[cols] >= 0) & ((mine[cols] - exact[cols]).abs() <= 1)
    check = {"candidates": k, "queries": [int(cols[0]), int(cols[-1])],
             "exact_match_found": float(found.float().mean())}
    if gt is not None:
        score = torch.full(exact.shape, 0.0, dtype=torch.float64)
        keep = torch.from_numpy(metrics.positives(gt)).bool()[cols]
        rows = {name: torch.from_numpy(metrics.correct(Matches(m, score, True), gt))[cols][keep]
                for name, m in (("exact", exact), ("candidates", mine))}
        check.update({f"{name}_recall_at_1": float(v.double().mean()) if len(v) else None
                      for name, v in rows.items()})
    run.candidate_agreement = check
    if gt is not None and check["exact_recall_at_1"] is not None:
        short = check["exact_recall_at_1"] - check["candidates_recall_at_1"] > MAX_RECALL_LOSS
        text = (f"recall@1 {check['candidates_recall_at_1']:.3f} against the exact mode's "
                f"{check['exact_recall_at_1']:.3f}")
    else:
        short = check["exact_match_found"] < MIN_AGREEMENT
        text = f"finds the exact mode's match for {100 * check['exact_match_found']:.1f}%"
    if short:
        warn(PROG, f"--candidates {k}: {text} on {len(cols)} sampled queries; raise K or give "
             f"--candidates 0 (the exact mode)", notes)


def describe_reference(cfg: EvalConfig, ref: Traverse) -> dict:
    """What identifies a reference traverse: source, frames, frame size, selection, events."""
    if cfg.reference is None:
        source = {"source": "demo", "demo_frames": cfg.demo_frames, "demo_seed": cfg.seed}
    else:
        source = {"source": str(Path(cfg.reference).resolve()), "select": to_jsonable(
            frame_selection(cfg.start, cfg.stop, cfg.frame_step, cfg.max_frames))}
        if ref.info.get("events"):
            source["events"] = to_jsonable(event_frame_options(cfg))
    size = ref.info["frame_size"]
    return {**source, "n_frames": len(ref), "frame_size": None if size is None else list(size)}


# event settings that change no frame (the same events either way, or a complete file read)
SAME_FRAMES = {"evt3_kernel", "truncated"}


def _setting_changes(learnt: dict, now: dict) -> str:
    """``"mode 'count' -> 'signed', ..."`` for the settings both dicts hold that differ."""
    return ", ".join(f"{k} {learnt[k]!r} -> {now[k]!r}" for k in now
                     if k in learnt and k not in SAME_FRAMES and learnt[k] != now[k])


def checkpoint_mismatch(model, this: dict) -> str | None:
    """Say how a checkpoint's learnt reference differs from this run's reference, if it does."""
    learnt = model.extra.get("reference") if isinstance(model.extra, dict) else None
    n_learnt = int(model.unit_to_reference[-1, 1])
    problems = []
    if n_learnt != this["n_frames"]:
        problems.append(f"it learnt {n_learnt} reference frames, this reference has "
                        f"{this['n_frames']}")
    if isinstance(learnt, dict):
        keys = ("source", "demo_frames", "demo_seed")
        was = {k: learnt.get(k) for k in keys if k in learnt or k in this}
        now = {k: this.get(k) for k in keys if k in learnt or k in this}
        if was != now:
            problems.append(f"it learnt {learnt.get('source')}, this reference is "
                            f"{this['source']}")
        if learnt.get("frame_size") not in (None, this["frame_size"]) and this["frame_size"]:
            fs = learnt["frame_size"]
            problems.append(f"its frames were {fs[0]}x{fs[1]}, these are "
                            f"{this['frame_size'][0]}x{this['frame_size'][1]}")
        for key, what in (("events", "event frame settings differ"),
                          ("select", "frame selection differs")):
            if isinstance(learnt.get(key), dict) and isinstance(this.get(key), dict):
                changed = _setting_changes(learnt[key], this[key])
                if changed:
                    problems.append(f"its {what} ({changed})")
    elif not problems:
        return None  # an API-saved model: the frame count is all there is to check
    if not problems:
        return None
    return ("the checkpoint does not match this reference (" + "; ".join(problems) +
            "): its matches index the reference it learnt, so the metrics are meaningless "
            "unless that is the same route")


def run_neural(s: Settings, ref, query, device, notes: Notes, model=None) -> NeuralRun:
    """Neural SeqSLAM, from a checkpoint (``model``, loaded) or trained on the reference now."""
    from torchseq.neural import NeuralSeqSLAM
    from torchseq.neural.advice import coarse_units

    cfg = s.run
    start = time.perf_counter()
    if model is not None:
        problem = checkpoint_mismatch(model, describe_reference(cfg, ref))
        if problem:
            warn(PROG, problem, notes)
    elif ref.descriptors is not None:
        model = NeuralSeqSLAM(neural_config(s.neural, ref.descriptors.shape[1]), device=device)
        model.fit(neural_input(ref.descriptors), progress=cfg.progress)
    else:
        model = NeuralSeqSLAM(s.neural, device=device)
        with warnings.catch_warnings():  # one warning per cause: the run's own, below, names
            warnings.filterwarnings(      # the flag (--neural-n-output)
                "ignore", message=r"a route of \d+ frames on \d+ output units")
            model.fit(ref.at(s.neural.input_size), progress=cfg.progress)
    size = model.config.input_size
    if ref.descriptors is not None and tuple(size) != (1, ref.descriptors.shape[1]):
        raise UsageError(f"the checkpoint's L1 takes {size[0]}x{size[1]} inputs, not "
                         f"{ref.descriptors.shape[1]}-value descriptors (train it on these "
                         f"descriptors)")
    fit_seconds = time.perf_counter() - start
    n_ref = int(model.unit_to_reference[-1, 1])
    coarse = coarse_units(n_ref, model.n_units, model.config.readout, model.search is not None,
                          "--neural-n-output")  # the message of the stage that decides
    if coarse:
        warn(PROG, f"neural: {coarse}", notes)
    self_check = model.self_check  # fit's figure, or the one a trained checkpoint carries
    if self_check is None:
        self_check = (getattr(model, "extra", None) or {}).get("self_check")
    t0 = time.perf_counter()
    result = model.inference().run(query.at(size) if query.descriptors is None else
                                   neural_input(query.descriptors), cfg.progress, RANKED)
    run_seconds = time.perf_counter() - t0
    preset = None if cfg.checkpoint else preset_name(cfg.neural_preset)
    # every figure of the run from the stage that decided (result.stage)
    return NeuralRun(matches=result.matches, ranked=result.ranked,
                     ranked_score=result.ranked_score, activity=result.scores,
                     unit_spans=model.unit_to_reference.cpu(),
                     seconds=run_seconds, fit_seconds=fit_seconds, preset=preset,
                     parameters=to_jsonable(model.config), model_bytes=int(model.model_bytes()),
                     seqslam_template_bytes=seqslam_template_bytes(n_ref),
                     frames_per_unit=n_ref / model.n_units, self_check=self_check,
                     stage=result.stage, sequence_frames=model.sequence_frames)


def run_engines(s: Settings, ref, query, device, notes: Notes,
                model=None) -> dict[str, EngineRun]:
    """Every engine the run asks for, by name (``model``: a loaded checkpoint)."""
    names = ["seqslam", "neural"] if s.run.engine == "both" else [s.run.engine]
    return {name: run_seqslam(s, ref, query, device, notes) if name == "seqslam" else
            run_neural(s, ref, query, device, notes, model) for name in names}


def single_frame_baseline(s: Settings, ref: Traverse, query: Traverse, device,
                          difference: torch.Tensor | None = None):
    """Single-frame matches on the run's descriptors (:func:`torchseq.seqslam.single_frame`).

    ``difference``: the SeqSLAM engine's raw ``(R, Q)`` difference matrix of the same
    descriptors (:attr:`SeqSLAMRun.difference`), ranked as it is instead of computed again;
    used for ``l1`` (whose kernels are exact, so the numbers are the same) on frames or
    float32/float64 descriptors (which the engine takes as they are).
    """
    from torchseq.seqslam.single import single_frame, single_frame_from_difference

    if difference is not None and s.seqslam.metric == "l1" and (
            ref.descriptors is None or ref.descriptors.dtype in (torch.float32, torch.float64)):
        return single_frame_from_difference(difference, RANKED, s.seqslam.max_chunk_elements)
    if ref.descriptors is not None:
        r, q = ref.descriptors, query.descriptors
    else:
        engine = SeqSLAM(s.seqslam, device=device)
        size = s.seqslam.image_size
        r, q = engine.descriptors(ref.at(size)), engine.descriptors(query.at(size))
    return single_frame(r.to(device), q.to(device), s.seqslam.metric, RANKED,
                        s.seqslam.max_chunk_elements)
