"""``model.nir`` and its validation figures for ``python -m torchseq.export``.

The spiking model and the graph: ``docs/guide/nir.md``.

:func:`export_nir` converts the checkpoint's rate model to the spiking model (calibrated on
the reference it learnt, never on the validation query), writes ``model.nir``, reads it back
(values must be equal), runs it in every installed consumer over the validation query (cut
into streams of :data:`CONSUMER_SEGMENT` frames) and returns the JSON-ready figures
the exporter puts under ``"nir"`` in ``validation.json``, with the hardware budget.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

NIR_FILE = "model.nir"
# model.nir holds two dense float32 matrices of N x N*K values (levels and shift): 8 N^2 K
# bytes, held again by the read-back and each consumer's modules. Above this bound the NIR
# step is skipped with the estimate (a 3,576-unit model at 128 levels: 13.1 GB, >13 GB seen).
NIR_MAX_BYTES = 2 ** 31


def nir_dense_bytes(n_units: int, levels: int) -> int:
    """Bytes of ``model.nir``'s dense ``levels`` and ``shift`` matrices (float32, N x N*K each)."""
    return 8 * int(n_units) ** 2 * int(levels)
MIN_CONSUMER_AGREEMENT = 0.99
# The consumers run the query cut into streams of this many frames, stepped together
# (nir_consumers.compare): on a 500-frame route 32 streams of 16 steps instead of 500 steps.
CONSUMER_SEGMENT = 16


def calibration_frames(model, recorded: dict | None, replayed=None, load=None):
    """The reference frames to calibrate the spiking conversion on, and where they came from.

    Only the reference the model learnt: a device has no query to calibrate on. The
    checkpoint's recorded demo reference is regenerated; a recorded reference file that the
    exporter is replaying as the query (``replayed``) is those frames; otherwise the
    recorded file is read with ``load()`` (the exporter's reader of the recorded reference).

    Args:
        model: the fitted rate model.
        recorded: the checkpoint's recorded reference (``export.checkpoint.recorded_reference``).
        replayed: the reference frames when the validation query is their replay, or None.
        load: a callable returning the recorded reference's frames (raising ``ValueError``
            when they cannot be read), or None.

    Returns:
        ``(frames, source)``, or ``(None, reason)`` where the learnt reference is not at
        hand (then the NIR export is skipped with that reason).
    """
    if recorded is not None and recorded.get("source") == "demo":
        from torchseq.demo import make_demo

        demo = make_demo(n_reference=int(recorded.get("demo_frames", 200)),
                         seed=int(recorded.get("demo_seed", 0)))
        return demo.reference, "the checkpoint's demo reference"
    remedy = ("the spiking model is calibrated on the reference the model learnt, never on a "
              "validation query (a device has none); export a checkpoint written by "
              "train.py whose reference can be read")
    if recorded is None:
        return None, f"the checkpoint does not record its reference: {remedy}"
    if replayed is not None:
        return replayed, f"the checkpoint's reference {recorded['source']}"
    if load is None:
        return None, f"its reference {recorded['source']} was not loaded: {remedy}"
    try:
        return load(), f"the checkpoint's reference {recorded['source']}"
    except ValueError as err:
        return None, f"{str(err).splitlines()[0] if str(err) else type(err).__name__}: {remedy}"


def _roundtrip_equal(graph, back) -> bool:
    if set(graph.nodes) != set(back.nodes) or sorted(graph.edges) != sorted(back.edges):
        return False
    for k, node in graph.nodes.items():
        for field, value in vars(node).items():
            if isinstance(value, np.ndarray) and not np.array_equal(
                    getattr(back.nodes[k], field), value):
                return False
    return True


def export_nir(model, out_dir, frames, ground_truth, calib, calib_source: str,
               progress=None, config=None, chips: bool = False, timed: bool = False) -> dict:
    """Write ``model.nir`` and validate it; return the ``"nir"`` section of the report.

    Args:
        model: the fitted rate model.
        out_dir: output folder.
        frames: validation query ``(T, H, W)``.
        ground_truth: ``(R, T)`` bool or None.
        calib: the reference frames to calibrate the conversion on (None: skipped, with
            ``calib_source`` as the reason).
        calib_source: where they came from (reported).
        progress: an :class:`~torchseq.export.progress.ExportProgress`, or None.
        config: the :class:`~torchseq.neural.spiking.SpikingConfig` (None: defaults).
        chips: also check the budget against each chip's published limits (``"chips"``).
        timed: also run the timed spiking model on the query (``"timed"``,
            :func:`timed_report`; as long as the rest of the export on a long query).

    Returns:
        ``{"file", "bytes", "round_trip_equal", "steps_per_frame", "time_steps", "levels",
        "calibration_source", "spiking": {agreement with the rate model, recall},
        "consumers": {name: agreement, recall, time steps, streams ..., skipped (not
        installed) or failed (it raised: the check fails)}, "budget", "checks"}``, with
        ``"chips"`` and ``"timed"`` where asked for,
        or ``{"skipped": reason}`` without the ``nir`` package or the learnt reference.
    """
    from torchseq.export.nir_export import NIRExportError, read_nir, require_nir, write_nir
    from torchseq.export.progress import QUIET

    progress = progress or QUIET
    try:
        require_nir()
    except NIRExportError as err:
        return {"skipped": str(err)}
    if calib is None:
        return {"skipped": calib_source}
    from torchseq.neural.spiking import SpikingConfig

    levels = (config or SpikingConfig()).levels
    need = nir_dense_bytes(model.n_units, levels)
    if need > NIR_MAX_BYTES:
        return {"skipped": f"model.nir would hold {need / 1e9:.1f} GB of dense weights "
                           f"({model.n_units} units x {levels} levels; more again while it is "
                           f"validated), above the {NIR_MAX_BYTES / 2 ** 30:g} GiB bound: "
                           f"lower --nir-levels or give --no-nir"}
    from torchseq.export.hardware_budget import budget, check
    from torchseq.export.nir_consumers import compare
    from torchseq.metrics import recall_at_k
    from torchseq.neural.spiking import SpikingSeqSLAM

    query = torch.as_tensor(frames).to(torch.float32)
    with progress.step(f"NIR: spiking conversion and model.nir ({need / 1e6:,.0f} MB of "
                       f"dense weights)"):
        sp = SpikingSeqSLAM.convert(model, torch.as_tensor(calib).to(torch.float32), config)
        path = Path(out_dir) / NIR_FILE
        graph = write_nir(sp, path)
        back = read_nir(path)
        same = _roundtrip_equal(graph, back)
        x = sp.encode(query)
    with progress.step("NIR: rate and spiking models, whole query", int(x.shape[0])):
        rate = model.run(query).matches.reference.numpy()
        ours = sp.run(x, encoded=True)
    rep = compare(sp, path, x, ground_truth, segment=CONSUMER_SEGMENT, progress=progress,
                  graph=back)
    refs = ours["reference"].numpy()
    consumers = {k: v for k, v in rep.items() if k != "torchseq"}
    ran = {k: v for k, v in consumers.items() if "skipped" not in v}
    with progress.step("NIR: hardware budget"):
        b = budget(graph)
    extra = {}
    if chips:
        extra["chips"] = check(b)
    if timed:
        extra["timed"] = timed_report(model, calib, query, ground_truth, rate, progress,
                                      None if config is None else config.weight_bits, chips)
    return {
        "file": NIR_FILE, "bytes": path.stat().st_size, "round_trip_equal": same,
        "steps_per_frame": 1, "time_steps": int(x.shape[0]), "levels": sp.levels,
        "weight_bits": sp.calibration.get("weight_bits"),
        "dt": float(graph.metadata["dt"]), "calibration_source": calib_source,
        "calibration": sp.calibration,
        "spiking": {
            "agreement_with_rate_model": float(np.mean(refs == rate)),
            "recall_at_1": (None if ground_truth is None else
                            recall_at_k(torch.as_tensor(refs), ground_truth, 1)),
            "rate_model_recall_at_1": (None if ground_truth is None else
                                       recall_at_k(torch.as_tensor(rate), ground_truth, 1)),
            "l2_spikes_per_frame": float(ours["l2_spikes"].mean()),
            "ring_spikes_per_frame": float(ours["ring_spikes"].mean()),
            "synaptic_ops_per_frame": float(ours["synaptic_ops"].mean()),
        },
        "consumers": consumers,
        "consumer_streams": {"segment_frames": CONSUMER_SEGMENT,
                             "streams": rep["torchseq"].get("streams"),
                             "torchseq_streams_recall_at_1":
                                 rep["torchseq"].get("streams_recall_at_1")},
        "budget": {k: v for k, v in b.items() if k != "effective_synapses_by_pair"},
        **extra,
        "checks": {"nir_round_trip": same,
                   "nir_consumers_agree": all(v.get("agreement", 0.0) >= MIN_CONSUMER_AGREEMENT
                                              for v in ran.values())},
    }


def timed_report(model, calib, query, ground_truth, rate, progress,
                 weight_bits: int | None, chips: bool = True) -> dict:
    """The timed spiking model's figures on the query: it is not written to ``model.nir``.

    :class:`~torchseq.neural.spiking_timed.TimedSpikingSeqSLAM` (many steps per frame,
    calibrated on ``calib`` only, at ``weight_bits``): agreement with the rate model's
    decisions ``rate`` ``(T,)``, recall@1, steps per frame, its budget and (``chips``) the
    chips it fits. Its IF units reset by subtraction and its phases start from zero, which NIR's
    nodes do not express (``docs/results/nir.md``, "The timed model").
    """
    from torchseq.export.hardware_budget import check, memory_bytes
    from torchseq.metrics import recall_at_k
    from torchseq.neural.spiking_timed import TimedConfig, TimedSpikingSeqSLAM

    with progress.step("timed spiking model: conversion and whole query", int(len(query))):
        net = TimedSpikingSeqSLAM.convert(model, torch.as_tensor(calib).to(torch.float32),
                                          TimedConfig(weight_bits=weight_bits))
        out = net.run(query)
    refs = out["reference"].numpy()
    b = net.budget()
    ops = sum(out["synaptic_ops"].values())
    return {
        "written": False,
        "why_not_written": "IF units with reset by subtraction and per-phase resets have no "
                           "NIR node (docs/results/nir.md, 'The timed model')",
        "agreement_with_rate_model": float(np.mean(refs == rate)),
        "recall_at_1": (None if ground_truth is None else
                        recall_at_k(torch.as_tensor(refs), ground_truth, 1)),
        "steps_per_frame": out["steps_per_frame"], "weight_bits": weight_bits,
        "windows_clipped": int((out["windows"] == 0).sum()),
        "synaptic_ops_per_frame": float(ops.mean()),
        "budget": {"neurons": b["neurons"], "effective_synapses": b["effective_synapses"],
                   "memory_bytes_8bit": memory_bytes(b, 8), "max_fan_in": b["max_fan_in"],
                   "max_fan_out": b["max_fan_out"]},
        **({"chips": check(b)} if chips else {}),
    }
