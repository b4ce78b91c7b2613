"""Run an exported NIR graph in other frameworks (snnTorch, Norse) and compare decisions.

Each consumer imports the ``.nir`` file with its own NIR importer and steps it once per
frame over encoded frames ``(T, D)``; the ring spikes it returns are read out exactly as
torchseq reads its own (:meth:`SpikingSeqSLAM.counts`, then the decision). The consumers are
optional (``pip install 'torchseq[nir]'``); :func:`available` says which are installed.

- **snnTorch** (``snntorch.import_nir.import_from_nir``, nirtorch's ``nir_to_torch``): NIR
  ``LIF`` becomes ``snn.Leaky(beta = 1 - dt / tau, reset "zero")`` with snnTorch's fixed
  ``dt = 1e-4`` (the graph's ``dt``); the cycle is carried by nirtorch's state.
- **Norse** (``norse.torch.from_nir(graph, dt=...)``, nirtorch's ``GraphExecutor``): NIR
  ``LIF`` becomes ``LIFBoxCell`` (Euler, reset to ``v_reset = 0``); ``dt`` is passed from the
  graph's metadata.
"""

from __future__ import annotations

import contextlib
import io
import time
from pathlib import Path

import numpy as np
import torch

from torchseq.export.nir_export import NIRExportError, read_nir

CONSUMERS = ("snntorch", "norse")


def available() -> dict[str, str | None]:
    """``{consumer: None if importable else the reason}``."""
    out = {}
    for name, mod in (("snntorch", "snntorch.import_nir"), ("norse", "norse.torch")):
        try:
            __import__(mod)
            out[name] = None
        except Exception as err:  # noqa: BLE001 - any import failure means "not usable here"
            out[name] = f"{name} is not importable ({type(err).__name__}: {err}); " \
                        f"pip install 'torchseq[nir]'"
    return out


def _meta(graph, key: str):
    value = graph.metadata[key]
    return value.decode() if isinstance(value, bytes) else value


def run_consumer(name: str, path: str | Path, x: torch.Tensor) -> torch.Tensor:
    """Import ``path`` into consumer ``name`` and step it over ``x``.

    Args:
        name: ``"snntorch"`` or ``"norse"``.
        path: a ``.nir`` file written by :func:`~torchseq.export.nir_export.write_nir`.
        x: ``(T, D)`` encoded frames, one time step each.

    Returns:
        ``(T, N * K)`` ring spikes the consumer computed.

    Raises:
        NIRExportError: unknown or unavailable consumer, or an output of the wrong size.
    """
    if name not in CONSUMERS:
        raise NIRExportError(f"consumer must be one of {CONSUMERS}, got {name!r}")
    reason = available()[name]
    if reason is not None:
        raise NIRExportError(reason)
    graph = read_nir(path)
    n_out = int(_meta(graph, "units")) * int(_meta(graph, "levels"))
    dt = float(_meta(graph, "dt"))
    with contextlib.redirect_stdout(io.StringIO()):  # snnTorch's importer prints progress
        if name == "snntorch":
            from snntorch.import_nir import import_from_nir

            net = import_from_nir(graph)
        else:
            import norse.torch as norse

            net = norse.from_nir(graph, dt=dt)
    out, state = [], None
    with torch.no_grad():
        for t in range(x.shape[0]):
            y, state = net(x[t:t + 1].float(), state)
            out.append(y.reshape(1, -1))
    spikes = torch.cat(out)
    if spikes.shape[1] != n_out:
        raise NIRExportError(f"{name} returned {spikes.shape[1]} outputs per step, "
                             f"the graph's ring has {n_out}")
    return spikes


def compare(spiking, path: str | Path, x: torch.Tensor, ground_truth=None,
            consumers=CONSUMERS) -> dict:
    """Each consumer's decisions against torchseq's spiking model on the same inputs.

    Args:
        spiking: the :class:`~torchseq.neural.spiking.SpikingSeqSLAM` that was exported.
        path: its ``.nir`` file.
        x: ``(T, D)`` encoded query frames.
        ground_truth: ``(R, T)`` bool or None (then no recall).
        consumers: names to run; an unavailable one is reported with its reason.

    Returns:
        ``{"torchseq": {recall_at_1, ...}, consumer: {"agreement", "recall_at_1",
        "time_steps", "steps_per_frame", "differing_frames", "spike_agreement",
        "seconds"}, {"skipped": reason} (not installed) or {"failed": error} (it raised)}``.
    """
    from torchseq.metrics import recall_at_k

    ours = spiking.run(x, encoded=True, raster=True)
    ref = ours["reference"].numpy()

    def recall(refs: np.ndarray):
        if ground_truth is None:
            return None
        return recall_at_k(torch.as_tensor(refs), ground_truth, 1)

    report = {"torchseq": {"recall_at_1": recall(ref), "time_steps": int(x.shape[0]),
                           "steps_per_frame": 1}}
    for name in consumers:
        reason = available().get(name, f"unknown consumer {name!r}")
        if reason is not None:
            report[name] = {"skipped": reason}
            continue
        t0 = time.perf_counter()
        try:
            spikes = run_consumer(name, path, x)
        except Exception as err:  # noqa: BLE001 - a consumer that breaks fails its check
            report[name] = {"failed": f"{type(err).__name__}: {str(err)[:200]}"}
            continue
        theirs = spiking.decide(spiking.counts(spikes))[0].numpy()
        report[name] = {
            "agreement": float(np.mean(theirs == ref)),
            "recall_at_1": recall(theirs),
            "time_steps": int(x.shape[0]), "steps_per_frame": 1,
            "differing_frames": [int(i) for i in np.flatnonzero(theirs != ref)],
            "spike_agreement": float((spikes == ours["raster"]).float().mean()),
            "seconds": round(time.perf_counter() - t0, 3),
        }
    return report
