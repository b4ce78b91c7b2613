"""``model.nir`` and its validation figures for ``python -m torchseq.export``.

The spiking model and the graph: ``docs/guide/nir.md``.

:func:`export_nir` converts the checkpoint's rate model to the spiking model (calibrated on
the reference it learnt), writes ``model.nir``, reads it back (values must be equal), runs
it in every installed consumer over the validation query and returns the JSON-ready figures
the exporter puts under ``"nir"`` in ``validation.json``, with the hardware budget.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

NIR_FILE = "model.nir"
MIN_CONSUMER_AGREEMENT = 0.99


def calibration_frames(model, recorded: dict | None, query_given: bool, frames):
    """Frames to calibrate the spiking conversion on, and where they came from.

    The checkpoint's recorded demo reference is regenerated; a recorded reference file that
    the exporter is already replaying as the query is those frames; otherwise (a query given
    for a checkpoint whose reference is not at hand) the validation query, said so.
    """
    if recorded is not None and recorded.get("source") == "demo":
        from torchseq.demo import make_demo

        demo = make_demo(n_reference=int(recorded.get("demo_frames", 200)),
                         seed=int(recorded.get("demo_seed", 0)))
        return demo.reference, "the checkpoint's demo reference"
    if recorded is not None and not query_given:
        return frames, f"the checkpoint's reference {recorded['source']}"
    return frames, "the validation query (the learnt reference is not at hand)"


def _roundtrip_equal(graph, back) -> bool:
    if set(graph.nodes) != set(back.nodes) or sorted(graph.edges) != sorted(back.edges):
        return False
    for k, node in graph.nodes.items():
        for field, value in vars(node).items():
            if isinstance(value, np.ndarray) and not np.array_equal(
                    getattr(back.nodes[k], field), value):
                return False
    return True


def export_nir(model, out_dir, frames, ground_truth, calib, calib_source: str) -> dict:
    """Write ``model.nir`` and validate it; return the ``"nir"`` section of the report.

    Args:
        model: the fitted rate model.
        out_dir: output folder.
        frames: validation query ``(T, H, W)``.
        ground_truth: ``(R, T)`` bool or None.
        calib: frames to calibrate the conversion on.
        calib_source: where they came from (reported).

    Returns:
        ``{"file", "bytes", "round_trip_equal", "steps_per_frame", "time_steps", "levels",
        "calibration_source", "spiking": {agreement with the rate model, recall},
        "consumers": {name: agreement, recall, time steps ..., skipped (not installed) or
        failed (it raised: the check fails)}, "budget", "chips", "checks"}``, or
        ``{"skipped": reason}`` without the ``nir`` package.
    """
    from torchseq.export.nir_export import NIRExportError, read_nir, require_nir, write_nir

    try:
        require_nir()
    except NIRExportError as err:
        return {"skipped": str(err)}
    from torchseq.export.hardware_budget import budget, check
    from torchseq.export.nir_consumers import compare
    from torchseq.metrics import recall_at_k
    from torchseq.neural.spiking import SpikingSeqSLAM

    query = torch.as_tensor(frames).to(torch.float32)
    sp = SpikingSeqSLAM.convert(model, torch.as_tensor(calib).to(torch.float32))
    path = Path(out_dir) / NIR_FILE
    graph = write_nir(sp, path)
    same = _roundtrip_equal(graph, read_nir(path))
    x = sp.encode(query)
    rep = compare(sp, path, x, ground_truth)
    rate = model.run(query).matches.reference.numpy()
    ours = sp.run(x, encoded=True)
    refs = ours["reference"].numpy()
    consumers = {k: v for k, v in rep.items() if k != "torchseq"}
    ran = {k: v for k, v in consumers.items() if "skipped" not in v}
    b = budget(graph)
    return {
        "file": NIR_FILE, "bytes": path.stat().st_size, "round_trip_equal": same,
        "steps_per_frame": 1, "time_steps": int(x.shape[0]), "levels": sp.levels,
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
        "budget": {k: v for k, v in b.items() if k != "effective_synapses_by_pair"},
        "chips": check(b),
        "checks": {"nir_round_trip": same,
                   "nir_consumers_agree": all(v.get("agreement", 0.0) >= MIN_CONSUMER_AGREEMENT
                                              for v in ran.values())},
    }
