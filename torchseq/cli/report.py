"""A run's report: metrics.json, matches.csv, PNG plots and TensorBoard logs.

:func:`report` writes an eval run's files, :func:`write_train_json` and :func:`log_training` a
training run's ``train.json``, figures and logs. Figures come from :mod:`torchseq.cli.plots`.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import torch

import torchseq.cli.plots as plots
import torchseq.cli.report_images as report_images
from torchseq import metrics
from torchseq.atomic import write_json, write_text
from torchseq.cli.eval_settings import Settings, config_dict
from torchseq.cli.results import EngineRun, EvalOutcome, TrainRun
from torchseq.cli.run_warnings import warning_list
from torchseq.cli.runs import Notes, config_text, mark_incomplete, to_jsonable, warn
from torchseq.neural import NeuralConfig, NeuralFitLog, NeuralSeqSLAM
from torchseq.versions import VERSIONS_KEY, versions

SINGLE_FRAME_RULE = ("each query's nearest reference by the run's --metric on the same "
                     "descriptors (SeqSLAM's own for frames), no contrast enhancement, no "
                     "sequence (ds = 1)")


def report(outcome: EvalOutcome, notes: Notes) -> dict:
    """Write metrics.json, matches.csv, plots and TensorBoard logs; return the metrics.

    ``outcome.single``: the single-frame baseline (:func:`single_frame_baseline`), reported
    beside each engine with the share of queries the sequence makes worse (needs ground truth).
    The metrics are also kept as ``outcome.metrics``.
    """
    s, ref, query, gt = outcome.settings, outcome.reference, outcome.query, outcome.ground_truth
    source, results, out, single = outcome.inputs, outcome.engines, outcome.out, outcome.single
    if gt is not None:
        for name, r in results.items():
            misaligned_truth_warning(name, r, gt, s, notes)
    summary = {"inputs": {**source, "n_reference": len(ref), "n_query": len(query),
                          "reference_frame_size": ref.info["frame_size"],
                          "query_frame_size": query.info["frame_size"]},
               "warnings": warning_list(notes), VERSIONS_KEY: versions()}
    if single is not None and gt is not None:
        summary["single_frame"] = {
            "rule": SINGLE_FRAME_RULE, "metric": s.seqslam.metric,
            **metrics.evaluate(single.matches, gt, single.ranked, single.ranked_score)}
    curves = {}
    for name, r in results.items():
        summary[name] = engine_metrics(r, gt, s.run.target_precision)
        if gt is not None:
            curves[name] = metrics.precision_recall_curve(r.matches, gt)
            if single is not None:
                summary[name]["versus_single_frame"] = metrics.sequence_vs_single(
                    r.matches, single.matches, gt)
    mark_incomplete(out)  # before the first file: an interrupted run never looks finished
    summary["status"] = "incomplete"  # until the plots and logs are written too
    write_json(out / "metrics.json", summary)
    write_text(out / "matches.csv", matches_csv(results, gt, s.run.matches_top_k))
    write_text(out / "config.json",
               config_text({**config_dict(s), VERSIONS_KEY: versions()}) + "\n")
    images = report_figures(ref, query, gt, results, curves)
    for k, img in images.items():
        plots.save_image(img, out / f"{k}.png")
    if s.run.tensorboard:
        log_tensorboard(s, out, summary, results, gt, images)
    summary["status"] = "complete"
    write_json(out / "metrics.json", summary)
    outcome.metrics = summary
    return summary


def misaligned_truth_warning(name: str, r: EngineRun, gt, s: Settings, notes: Notes) -> None:
    """Warn where an engine's matches follow a line the ground truth does not admit."""
    line = metrics.match_line(r.matches, gt)
    if line is None or not line.disagrees():
        return
    cfg = s.run
    alignment = cfg.tolerance is not None and cfg.ground_truth is None and cfg.dataset is None
    remedy = (f"try --gt-scale {line.scale:.3f} --gt-offset {max(0.0, line.offset):.0f}"
              if alignment else "check the ground truth")
    warn("torchseq eval", f"{name}: {100 * line.correct:.1f}% of matches are correct, yet "
         f"{100 * line.share:.1f}% lie within {line.band:g} frames of reference "
         f"{line.offset:.1f} + {line.scale:.3f} x query: the ground truth looks misaligned "
         f"({remedy})", notes)


def report_figures(ref, query, gt, results: dict[str, EngineRun], curves: dict) -> dict:
    """The report's figures as ``(H, W, 3)`` uint8 RGB images, by file name (no ``.png``).

    The difference matrix, matched pairs and PR curves are drawn straight into images
    (:mod:`torchseq.cli.report_images`: NumPy and OpenCV, milliseconds); the neural activity
    raster with matplotlib (:mod:`torchseq.cli.plots`, which imports it by the first figure).
    """
    images = {}
    if "seqslam" in results and results["seqslam"].matrix is not None:
        r = results["seqslam"]
        images["seqslam_difference_matrix"] = report_images.draw_difference_matrix(
            r.matrix, r.matches, gt, "SeqSLAM contrast-enhanced difference matrix"
            + (" (banded run: reduced copy)" if r.matrix_reduced else ""),
            shape=r.matrix_shape)
    if "neural" in results:
        r = results["neural"]
        truth = (None if gt is None else
                 plots.true_units(gt, r.unit_spans, r.activity.shape[0]))
        what = "output activity" if "ring" in r.stage else f"{r.stage} score per unit"
        fig = plots.plot_activity_raster(
            r.activity, title=f"neural {what} over the query", truth=truth)
        images["neural_activity"] = plots.figure_to_array(fig)  # drawn once
        fig.clear()
    for name, r in results.items():
        if ref.thumbnail is None or query.thumbnail is None:
            continue  # descriptor files and maps: no frames to show
        images[f"{name}_matched_pairs"] = report_images.draw_matched_pairs(
            ref.thumbnail, query.thumbnail, r.matches, gt,
            title=f"{name}: query (top) and matched reference")
    if curves:
        images["pr_curve"] = report_images.draw_pr_curves(curves)
    return images


def log_tensorboard(s: Settings, out: Path, summary: dict,
                    results: dict[str, EngineRun], gt,
                    images: dict) -> None:
    """Scalars, images, PR curves and the config in ``OUT/tensorboard``.

    torch's ``SummaryWriter``, its records checksummed in C where google-crc32c is installed
    (:mod:`torchseq.cli.tensorboard_log`).
    """
    from torchseq.cli.tensorboard_log import summary_writer

    with summary_writer(out / "tensorboard") as tb:
        tb.add_text("config", "```\n" + config_text(config_dict(s)) + "\n```")
        for name in results:
            for key, value in summary[name].items():
                if isinstance(value, (int, float)) and value is not None and np.isfinite(value):
                    tb.add_scalar(f"{name}/{key}", value)
        for key, img in images.items():
            tb_png_image(tb, key, img, out / f"{key}.png")
        for name in results:  # the HParams tab: this run's settings beside its results
            tb.add_hparams(hparams(s, name), {
                f"hparam/{name}/{k}": float(v) for k, v in summary[name].items()
                if k in ("recall_at_1", "recall_at_5", "auc", "seconds")
                and isinstance(v, (int, float)) and np.isfinite(v)}, run_name=name)
        if gt is None:
            return
        for name, r in results.items():
            m = r.matches
            has = m.reference >= 0
            if not bool(has.any()):
                continue
            labels = torch.from_numpy(metrics.correct(m, gt))[has]
            conf = m.confidence[has]
            lo, hi = conf.min(), conf.max()
            pred = (conf - lo) / (hi - lo) if hi > lo else torch.ones_like(conf)
            tb.add_pr_curve(f"{name}/pr_curve", labels, pred.float())


def tb_png_image(tb, key: str, image: np.ndarray, png: Path) -> None:
    """``tb.add_image(key, image, dataformats="HWC")`` with the PNG already written for it.

    The same ``Summary.Image`` (height, width, RGB, PNG bytes of the same pixels) as
    ``add_image``, which would encode the image a second time (with PIL).
    """
    from tensorboard.compat.proto.summary_pb2 import Summary

    height, width = image.shape[:2]
    picture = Summary.Image(height=height, width=width, colorspace=3,
                            encoded_image_string=png.read_bytes())
    tb._get_file_writer().add_summary(Summary(value=[Summary.Value(tag=key, image=picture)]))


def hparams(s: Settings, engine: str) -> dict:
    """TensorBoard hparams of one engine: the run's and that engine's scalar settings."""
    section = to_jsonable(s.seqslam if engine == "seqslam" else s.neural)
    flat = {**{k: v for k, v in to_jsonable(s.run).items()}, **{
        f"{engine}.{k}": v for k, v in section.items()}}
    out = {"engine": engine}
    for k, v in flat.items():
        if isinstance(v, (bool, int, float, str)):
            out[k] = v
        elif isinstance(v, (list, tuple)) and v and all(isinstance(x, (int, float)) for x in v):
            out[k] = "x".join(str(x) for x in v)
    return out


def matches_csv(results: dict[str, EngineRun], gt=None, top_k: int = 5) -> str:
    """``engine,query,reference,score[,correct],candidates`` rows.

    Empty reference and score where no match; ``correct`` (1/0, only with ground truth):
    the ground truth admits the match; ``candidates``: the best ``top_k`` reference indices
    the engine ranked, best first, space-separated.
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["engine", "query", "reference", "score", *(["correct"] if gt is not None
                                                            else []), "candidates"])
    for name, r in results.items():
        ref = r.matches.reference.cpu().numpy()
        score = r.matches.score.cpu().numpy()
        good = metrics.correct(r.matches, gt) if gt is not None else None
        ranked = np.asarray(r.ranked.cpu() if torch.is_tensor(r.ranked) else r.ranked)
        ranked = ranked.reshape(len(ref), -1)[:, :top_k].astype(np.int64).tolist()
        good = None if good is None else good.astype(int).tolist()
        # Python ints and floats (the same values, formatted alike): a row costs microseconds
        for q, (i, s) in enumerate(zip(ref.astype(np.int64).tolist(), score.tolist())):
            row = [name, q, i if i >= 0 else "", f"{s:.6g}" if i >= 0 else ""]
            if good is not None:
                row.append(good[q])
            row.append(" ".join(str(c) for c in ranked[q] if c >= 0))
            w.writerow(row)
    return buf.getvalue()


def engine_metrics(r: EngineRun, gt, target_precision: float) -> dict:
    """metrics.json entry of one engine."""
    if gt is None:
        m = {"recall_at_1": None, "auc": None, "recall_at_100_precision": None,
             "n_queries": len(r.matches), "coverage": metrics.coverage(r.matches)}
    else:
        m = metrics.evaluate(r.matches, gt, r.ranked, r.ranked_score)
        m["operating_point"] = metrics.operating_point(r.matches, gt, target_precision)
    m.update(r.reported())
    return m


def summary_line(name: str, m: dict) -> str:
    """One engine's line: recall@1 (ties both ways), single frame, share made worse, AUC."""
    if m.get("recall_at_1") is None:
        return (f"{name}: recall@1 n/a (no ground truth) over {m['n_queries']} queries "
                f"({m['seconds']:.2f} s)")
    text = f"{name}: recall@1 {m['recall_at_1']:.3f}"
    rec = m.get("recall", {}).get("queries_with_a_true_match")
    if rec and rec["ties_for"]["1"] != rec["ties_against"]["1"]:
        text += f" (ties {rec['ties_against']['1']:.3f}..{rec['ties_for']['1']:.3f})"
    vs = m.get("versus_single_frame")
    if vs:
        text += (f", single frame {vs['single_frame_recall_at_1']:.3f}, made worse "
                 f"{100 * vs['made_worse']:.1f}% / better {100 * vs['made_better']:.1f}% "
                 f"of queries")
        if vs["n_without_sequence_match"] and vs["n_queries"]:  # SeqSLAM's ends (ds/2 each)
            text += (f" ({100 * vs['n_without_sequence_match'] / vs['n_queries']:.1f}% "
                     f"unmatched at the route's ends; --edges matches them)")
    return (f"{text}, AUC {m['auc']:.3f} over {m['n_queries']} queries "
            f"({m['seconds']:.2f} s)")


def write_train_json(run: TrainRun, notes: Notes, out: Path) -> dict:
    """Write ``OUT/train.json``: the run's :meth:`TrainRun.reported` entries, then its warnings.

    Returns:
        What was written.
    """
    summary = {**run.reported(), "warnings": warning_list(notes)}
    write_json(out / "train.json", summary)
    return summary


def log_training(cfg, ncfg: NeuralConfig, model: NeuralSeqSLAM,
                 log: NeuralFitLog, out: Path) -> None:
    """Figures as PNG and, with TensorBoard on, scalars, images, histograms and the config."""
    activity = log.evidence
    figures = {
        "reference_activity": plots.plot_activity_raster(
            activity, log.winners, "output activity over the reference (winners marked)"),
        "ring_shift_matrix": plots.plot_matrix(
            model.ring.shift, "learnt ring shift matrix",
            xlabel="from output unit (the current winner)",
            ylabel="to output unit (the next winner)"),
    }
    images = {k: plots.figure_to_array(f) for k, f in figures.items()}
    for k, f in figures.items():
        plots.save_figure(f, out / f"{k}.png")
    if not cfg.tensorboard:
        return
    from torchseq.cli.tensorboard_log import summary_writer

    with summary_writer(out / "tensorboard") as tb:
        text = config_text({"train": cfg, "model": ncfg})
        tb.add_text("config", "```\n" + text + "\n```")
        for k, img in images.items():
            tb.add_image(k, img, dataformats="HWC")
        for name, p in list(model.named_parameters()) + list(model.named_buffers()):
            if p.is_floating_point() and p.numel() > 1:
                tb.add_histogram(f"weights/{name}", p.detach().float().cpu())
        tb.add_histogram("activity/reference", torch.as_tensor(activity).float())
        tb.add_scalar("train/reference_frames", len(activity))
        tb.add_scalar("train/model_bytes", model.model_bytes())
