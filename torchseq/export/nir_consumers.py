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
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from torchseq.export.nir_export import NIRExportError, graph_metadata, read_nir

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


def run_consumer(name: str, path: str | Path, x: torch.Tensor,
                 update: Callable[[int], None] | None = None, graph=None) -> torch.Tensor:
    """Import ``path`` into consumer ``name`` and step it over ``x``.

    Args:
        name: ``"snntorch"`` or ``"norse"``.
        path: a ``.nir`` file written by :func:`~torchseq.export.nir_export.write_nir`.
        x: ``(T, D)`` encoded frames, one time step each, or ``(T, B, D)``: ``B`` streams
            stepped together (each from rest).
        update: called with the steps done after each step (progress), or None.
        graph: ``read_nir(path)`` when the caller has read it already (None: read here).

    Returns:
        ``(T, N * K)`` (or ``(T, B, N * K)``) ring spikes the consumer computed.

    Raises:
        NIRExportError: unknown or unavailable consumer, or an output of the wrong size.
    """
    if name not in CONSUMERS:
        raise NIRExportError(f"consumer must be one of {CONSUMERS}, got {name!r}")
    reason = available()[name]
    if reason is not None:
        raise NIRExportError(reason)
    if graph is None:
        graph = read_nir(path)  # its metadata checked
    meta = graph_metadata(graph)
    n_out, dt = meta["units"] * meta["levels"], meta["dt"]
    with contextlib.redirect_stdout(io.StringIO()):  # snnTorch's importer prints progress
        if name == "snntorch":
            from snntorch.import_nir import import_from_nir

            net = import_from_nir(graph)
        else:
            import norse.torch as norse

            net = norse.from_nir(graph, dt=dt)
    steps = x if x.dim() == 3 else x[:, None]  # (T, B, D)
    out, state = [], None
    with torch.no_grad():
        for t in range(steps.shape[0]):
            y, state = net(steps[t].float(), state)
            out.append(y.reshape(steps.shape[1], -1))
            if update is not None:
                update(t + 1)
    spikes = torch.stack(out)  # (T, B, n)
    if spikes.shape[2] != n_out:
        raise NIRExportError(f"{name} returned {spikes.shape[2]} outputs per step, "
                             f"the graph's ring has {n_out}")
    return spikes if x.dim() == 3 else spikes[:, 0]


def segments(x: torch.Tensor, length: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Cut ``(T, D)`` inputs into ``B = ceil(T / length)`` streams of equal length.

    Returns:
        ``(steps (L, B, D), index (L, B))``: stream ``b`` holds frames ``b L .. b L + L - 1``
        of ``x`` (``L = ceil(T / B)``); ``index`` gives each step's frame, ``-1`` for the
        zero inputs padding the last stream.
    """
    t = x.shape[0]
    b = max(1, -(-t // max(1, length)))
    seg = -(-t // b)
    index = torch.arange(b * seg).reshape(b, seg).T  # (L, B)
    index = torch.where(index < t, index, torch.full_like(index, -1))
    steps = torch.cat([x, x.new_zeros(b * seg - t, *x.shape[1:])]).reshape(b, seg, -1)
    return steps.transpose(0, 1).contiguous(), index


def _run_streams(spiking, steps: torch.Tensor, update=None) -> torch.Tensor:
    """Run the spiking model over ``(L, B, D)`` streams from rest: ring spikes ``(L, B, n)``."""
    state, out = None, []
    with torch.no_grad():
        for t in range(steps.shape[0]):
            step, state = spiking.forward(steps[t], state)
            out.append(step.ring_spikes)
            if update is not None:
                update(t + 1)
    return torch.stack(out)


def compare(spiking, path: str | Path, x: torch.Tensor, ground_truth=None,
            consumers=CONSUMERS, segment: int | None = None, progress=None,
            graph=None) -> dict:
    """Each consumer's decisions against torchseq's spiking model on the same inputs.

    Args:
        spiking: the :class:`~torchseq.neural.spiking.SpikingSeqSLAM` that was exported.
        path: its ``.nir`` file.
        x: ``(T, D)`` encoded query frames.
        ground_truth: ``(R, T)`` bool or None (then no recall).
        consumers: names to run; an unavailable one is reported with its reason.
        segment: None: one stream over the whole traverse. An int ``L``: the traverse cut
            into streams of about ``L`` frames (:func:`segments`), each run from rest, all
            stepped together, by torchseq and by each consumer alike: every frame is still
            compared, in ``L`` steps of a batch instead of ``T`` steps of one (the
            consumers' dense ``levels`` and ``shift`` products cost nearly as much for one
            stream as for many), and the recall is that of the cut traverse.
        progress: an :class:`~torchseq.export.progress.ExportProgress`, or None.
        graph: ``read_nir(path)`` when the caller has read it already (None: read once
            here); every consumer imports that graph.

    Returns:
        ``{"torchseq": {recall_at_1, ...}, consumer: {"agreement", "recall_at_1",
        "time_steps", "steps_per_frame", "streams", "differing_frames", "spike_agreement",
        "seconds"}, {"skipped": reason} (not installed) or {"failed": error} (it raised)}``;
        with ``segment`` the recall is ``"streams_recall_at_1"`` (that of the cut query).
    """
    from torchseq.export.progress import QUIET
    from torchseq.metrics import recall_at_k

    progress = progress or QUIET
    if segment is None:
        steps, index = x[:, None], torch.arange(x.shape[0])[:, None]
    else:
        steps, index = segments(x, segment)
    keep = index >= 0
    order = index[keep]  # frame of each kept entry, in (step, stream) order

    def per_frame(v: torch.Tensor) -> torch.Tensor:  # (L, B, ...) -> (T, ...) in frame order
        out = v.new_zeros((x.shape[0], *v.shape[2:]))
        out[order] = v[keep]
        return out

    unit = f"steps of {steps.shape[1]} streams" if steps.shape[1] > 1 else "steps"
    with progress.step("NIR: torchseq spiking model", steps.shape[0], unit) as update:
        raster = per_frame(_run_streams(spiking, steps, update))
    ref = spiking.decide(spiking.counts(raster))[0].numpy()

    def recall(refs: np.ndarray):
        if ground_truth is None:
            return None
        return recall_at_k(torch.as_tensor(refs), ground_truth, 1)

    shape = {"time_steps": int(steps.shape[0]), "steps_per_frame": 1,
             "streams": int(steps.shape[1])}
    # a cut query's recall is not the traverse's (each stream starts from rest): named apart
    recall_key = "recall_at_1" if segment is None else "streams_recall_at_1"
    report = {"torchseq": {recall_key: recall(ref), **shape}}
    for name in consumers:
        reason = available().get(name, f"unknown consumer {name!r}")
        if reason is not None:
            report[name] = {"skipped": reason}
            continue
        t0 = time.perf_counter()
        try:
            with progress.step(f"NIR: {name}", steps.shape[0], unit) as update:
                graph = read_nir(path) if graph is None else graph  # the file, read once
                spikes = per_frame(run_consumer(name, path, steps, update, graph=graph))
        except Exception as err:  # noqa: BLE001 - a consumer that breaks fails its check
            report[name] = {"failed": f"{type(err).__name__}: {str(err)[:200]}"}
            continue
        theirs = spiking.decide(spiking.counts(spikes))[0].numpy()
        report[name] = {
            "agreement": float(np.mean(theirs == ref)),
            recall_key: recall(theirs),
            **shape,
            "differing_frames": [int(i) for i in np.flatnonzero(theirs != ref)],
            "spike_agreement": float((spikes == raster).float().mean()),
            "seconds": round(time.perf_counter() - t0, 3),
        }
    return report
