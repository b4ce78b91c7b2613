"""Hardware budget of an exported spiking graph against published neuromorphic chip limits.

:func:`budget` counts, from the NIR graph :func:`~torchseq.export.nir_export.to_nir` makes,
the spiking neurons, the weights stored in the graph (and whether each matrix already sits on
an int8 grid), the *effective* neuron-to-neuron
synapses (a chain of Linear nodes between two spiking populations multiplied out, as a chip
without analog intermediate layers would have to hold it), fan-in and fan-out, and memory
at 8-bit weights. :func:`check` compares it with :data:`LIMITS`. Sources of the limits
(figures as published; see ``docs/guide/nir.md``):

- Speck: 328K integrate-and-fire neurons, 9 layers (https://open-neuromorphic.org/
  neuromorphic-computing/hardware/speck-synsense); a layer's fan-out is 2 destination
  layers, 8-bit weights, at most 1024 features per layer (SynSense samna docs, Speck 2b:
  https://synsense-sys-int.gitlab.io/samna/models/speckSeries/speck2b.html).
- Loihi 2: 1 million neurons, 120 million synapses, 128 neuron cores
  (https://open-neuromorphic.org/neuromorphic-computing/hardware/loihi-2-intel/), 128 KB of
  SRAM per core (https://fbhtechinfo.com/intels-new-loihi-2-chip-uses-1-million-neurons;
  taken as the chip's 16 MiB for synapses and states together).
- Xylo Audio 2: 16 input channels, 1000 hidden neurons, 8 outputs, 8-bit weights, fan-in
  at most 63, 64,000 synaptic weights (https://open-neuromorphic.org/neuromorphic-computing/
  hardware/xylo-synsense/); fan-out at most 64 (https://rockpool.ai/devices/
  xylo-overview.html).
"""

from __future__ import annotations

import numpy as np

LIMITS = {
    "speck": {"neurons": 328_000, "layers": 9, "features_per_layer": 1024, "weight_bits": 8,
              "fanout_layers": 2, "analog_input": False},
    "loihi2": {"neurons": 1_000_000, "synapses": 120_000_000, "memory_bytes": 128 * 128 * 1024,
               "analog_input": True},
    "xylo_audio2": {"neurons": 1000, "inputs": 16, "outputs": 8, "fan_in": 63, "fan_out": 64,
                    "synapses": 64_000, "weight_bits": 8, "analog_input": False},
}


def _populations(graph) -> dict[str, int]:
    import nir

    return {k: int(np.prod(n.output_type["output"])) for k, n in graph.nodes.items()
            if isinstance(n, (nir.LIF, nir.IF, nir.CubaLIF, nir.LI))}


def _effective(graph) -> dict[tuple[str, str], list[tuple]]:
    """``{(source, target): [(top, rest, size), ...]}`` between spiking populations/input.

    Each path's effective weight ``(target, source)`` is ``top @ rest`` (``top`` the last
    Linear before the target, ``rest`` the product of the earlier ones or None; both None:
    a direct edge, the identity of ``size``). The product is left unmultiplied: the ring's
    ``levels @ shift`` is ``(N K)^2`` (71,040^2 floats, 18.8 GiB, for the default 555 units
    and 128 levels); :func:`_row_blocks` evaluates it a block of rows at a time.
    """
    import nir

    pops = set(_populations(graph)) | {"input"}
    out: dict[tuple[str, str], list[tuple]] = {}
    for src in pops:
        stack = [(dst, None, None) for s, dst in graph.edges if s == src]
        while stack:
            node, top, rest = stack.pop()
            n = graph.nodes[node]
            if node in pops:
                size = int(np.prod(n.output_type["output"]))
                out.setdefault((src, node), []).append((top, rest, size))
            elif isinstance(n, (nir.Linear, nir.Affine)):
                ww = n.weight.astype(np.float32)
                below = top if rest is None else (rest if top is None else top @ rest)
                stack += [(d, ww, below) for s, d in graph.edges if s == node]
    return out


def _row_blocks(paths: list[tuple], max_elements: int = 2**24):
    """Yield ``(r0, block)``: rows ``r0..`` of the summed effective weight of ``paths``."""
    top, rest, size = paths[0]
    rows = size if top is None else top.shape[0]
    cols = size if top is None else (top.shape[1] if rest is None else rest.shape[1])
    step = max(1, max_elements // max(cols, 1))
    for r0 in range(0, rows, step):
        r1 = min(rows, r0 + step)
        acc = None
        for top, rest, size in paths:
            if top is None:
                part = np.eye(r1 - r0, size, k=r0, dtype=np.float32)
            else:
                part = top[r0:r1] if rest is None else top[r0:r1] @ rest
            acc = part if acc is None else acc + part
        yield r0, acc


TINY = float(np.finfo(np.float32).smallest_subnormal)


def _selection(paths: list[tuple]):
    """The pattern of a single path whose last Linear picks one source row per target row.

    For ``levels @ rest`` (each row of ``levels`` holds one non-zero, ``s_r`` at column
    ``c_r``) row ``r`` of the product is ``s_r * rest[c_r]``: its non-zeros are those of
    ``rest[c_r]`` whenever no product can round to zero in float32 (``min |s| * min |rest|``
    at least the smallest subnormal). Returns ``(row_counts (R,), col_counts (C,))`` of the
    product's non-zeros without forming it (the ring's ``levels @ shift`` is ``(N K)^2``),
    or None where that does not hold (then :func:`_row_blocks` multiplies it out).
    """
    if len(paths) != 1 or paths[0][0] is None or paths[0][1] is None:
        return None
    top, rest, _ = paths[0]
    nz_top = top != 0
    if (nz_top.sum(1) > 1).any():
        return None
    used = nz_top.any(1)
    cols = np.argmax(nz_top, axis=1)
    rest_nz = rest != 0
    if used.any() and rest_nz.any():
        lo = float(np.abs(top[nz_top]).astype(np.float64).min()) * \
            float(np.abs(rest[rest_nz]).astype(np.float64).min())
        if not lo >= TINY:
            return None
    per_row = rest_nz.sum(1)
    row_counts = np.where(used, per_row[cols], 0)
    picks = np.bincount(cols[used], minlength=rest.shape[0])
    col_counts = np.zeros(rest.shape[1], dtype=np.int64)
    for c in np.flatnonzero(picks):  # rows of rest, each counted as often as it is picked
        col_counts += int(picks[c]) * rest_nz[c]
    return row_counts, col_counts


def _counts(paths: list[tuple], fast: bool = True):
    """``(row_counts, col_counts, kernel)`` of the non-zeros of the summed effective weight.

    ``kernel`` is ``"selection"`` (:func:`_selection`) or ``"row_blocks"``
    (:func:`_row_blocks`); ``fast=False`` forces the latter.
    """
    sel = _selection(paths) if fast else None
    if sel is not None:
        return sel[0], sel[1], "selection"
    rows, col = [], 0
    for _, block in _row_blocks(paths):
        nz = block != 0
        rows.append(nz.sum(1))
        col = col + nz.sum(0)
    return np.concatenate(rows), col, "row_blocks"


def weight_grid(w: np.ndarray, tol: float = 1e-4) -> str:
    """How few bits a weight matrix needs as it stands (no quantisation applied).

    ``"int8"``: every non-zero is a signed integer of at most 127 times one scale (the
    smallest magnitude); ``"int8_per_row"``: the same with one scale per row; else
    ``"float"``.
    """
    def on_grid(v: np.ndarray) -> bool:
        v = np.abs(v[v != 0]).astype(np.float64)
        if v.size == 0:
            return True
        q = v / v.min()
        return bool(q.max() <= 127.0 + tol and np.abs(q - np.rint(q)).max() <= tol)

    if on_grid(w):
        return "int8"
    w = np.atleast_2d(w)
    step = max(1, 2**22 // max(w.shape[1], 1))
    for r0 in range(0, w.shape[0], step):  # each row on its own grid, a block at a time
        a = np.abs(w[r0:r0 + step]).astype(np.float64)
        nz = a != 0
        low = np.where(nz, a, np.inf).min(axis=1, keepdims=True)
        q = np.where(nz, a / low, 0.0)  # rows of zeros: 0 (on every grid)
        if q.max() > 127.0 + tol or np.abs(q - np.rint(q)).max() > tol:
            return "float"
    return "int8_per_row"


def budget(graph, fast: bool = True) -> dict:
    """Neurons, weights, effective synapses, fan-in/out and memory of a spiking NIR graph.

    Args:
        graph: the ``nir.NIRGraph``.
        fast: count the non-zeros of a product through a selection matrix from its
            operands' patterns (:func:`_selection`, exact; the default); False multiplies
            every product out block by block (the oracle). ``"count_kernels"`` in the
            result says which ran for each pair.
    """
    import nir

    pops = _populations(graph)
    stored = {k: int(np.count_nonzero(n.weight)) for k, n in graph.nodes.items()
              if isinstance(n, (nir.Linear, nir.Affine))}
    eff = _effective(graph)
    fan_in: dict[str, np.ndarray] = {}
    fan_out: dict[str, np.ndarray] = {}
    syn = 0
    by_pair = {}
    kernels = {}
    for (src, dst), paths in eff.items():
        row, col, kernels[f"{src}->{dst}"] = _counts(paths, fast)
        pair = int(row.sum())
        by_pair[f"{src}->{dst}"] = pair
        syn += pair
        fan_in[dst] = row if dst not in fan_in else fan_in[dst] + row
        fan_out[src] = col if src not in fan_out else fan_out[src] + col
    neurons = sum(pops.values())
    return {
        "neurons": neurons, "populations": pops,
        "inputs": int(np.prod(graph.nodes["input"].output_type["output"])),
        "outputs": int(np.prod(graph.nodes["output"].input_type["input"])),
        "stored_weights": stored, "stored_weights_total": sum(stored.values()),
        "effective_synapses": syn,
        "effective_synapses_by_pair": by_pair,
        "count_kernels": kernels,
        "max_fan_in": max(int(v.max()) for v in fan_in.values()),
        "max_fan_in_by_population": {k: int(v.max()) for k, v in fan_in.items()},
        "max_fan_out": max(int(v.max()) for v in fan_out.values()),
        "mean_fan_out": {k: float(v.mean()) for k, v in fan_out.items()},
        "graph_weight_bits": 32,
        "weight_grids": {k: weight_grid(n.weight) for k, n in graph.nodes.items()
                         if isinstance(n, (nir.Linear, nir.Affine))},
        "memory_bytes_8bit": syn + 2 * neurons,  # 8-bit synapses, 16-bit neuron states
        "spiking_layers": len(pops),
    }


def check(b: dict) -> dict:
    """Each chip of :data:`LIMITS`: ``{"fits": bool, "exceeds": [reasons]}``."""
    out = {}
    for chip, lim in LIMITS.items():
        bad = []
        if b["neurons"] > lim["neurons"]:
            bad.append(f"{b['neurons']} neurons > {lim['neurons']}")
        if "synapses" in lim and b["effective_synapses"] > lim["synapses"]:
            bad.append(f"{b['effective_synapses']} synapses > {lim['synapses']}")
        if "memory_bytes" in lim and b["memory_bytes_8bit"] > lim["memory_bytes"]:
            bad.append(f"{b['memory_bytes_8bit']} bytes at 8-bit weights > "
                       f"{lim['memory_bytes']} bytes of core memory")
        if "fan_in" in lim and b["max_fan_in"] > lim["fan_in"]:
            bad.append(f"fan-in {b['max_fan_in']} > {lim['fan_in']}")
        if "fan_out" in lim and b["max_fan_out"] > lim["fan_out"]:
            bad.append(f"fan-out {b['max_fan_out']} > {lim['fan_out']}")
        if "inputs" in lim and b["inputs"] > lim["inputs"]:
            bad.append(f"{b['inputs']} input channels > {lim['inputs']}")
        if "outputs" in lim and b["outputs"] > lim["outputs"]:
            bad.append(f"{b['outputs']} outputs > {lim['outputs']}")
        if "features_per_layer" in lim:
            big = {k: v for k, v in b["populations"].items() if v > lim["features_per_layer"]}
            if big:
                bad.append(f"populations {big} > {lim['features_per_layer']} features per "
                           f"layer (dense layers as 1x1 convolutions)")
        if "weight_bits" in lim:
            off = sorted(k for k, g in b["weight_grids"].items() if g == "float")
            if off:
                bad.append(f"{', '.join(off)} are not on an int8 grid; {lim['weight_bits']}-bit "
                           f"weights need quantising them (not done)")
        if not lim["analog_input"]:
            bad.append("the input is an analog current (the encoded frame); the chip takes "
                       "events only")
        out[chip] = {"fits": not bad, "exceeds": bad}
    return out
