"""Hardware budget of an exported spiking graph against published neuromorphic chip limits.

:func:`budget` counts, from the NIR graph :func:`~torchseq.export.nir_export.to_nir` makes,
the spiking neurons, the weights stored in the graph (and whether each matrix already sits on
an int8 grid), the *effective* neuron-to-neuron
synapses (a chain of Linear nodes between two spiking populations multiplied out, as a chip
without analog intermediate layers would have to hold it), fan-in and fan-out, recurrent
synapses, memory at a chip's weight precision and, for a layered chip (Speck), each
population's kernel and neuron memory as a layer. :func:`check` compares it with
:data:`CHIPS`: per chip, whether the model fits and every limit it exceeds. Each figure of
:data:`CHIPS` carries its source (``ChipLimits.sources``); the figures that are our estimates
or readings rather than a published number are listed in ``ChipLimits.estimates``. The
table with its sources: ``docs/guide/nir.md`` ("Chip limits").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

SRC_LOIHI2_ON = ("Open Neuromorphic, 'Loihi 2 - Intel' (https://open-neuromorphic.org/"
                 "neuromorphic-computing/hardware/loihi-2-intel/)")
SRC_LOIHI2_MEM = ("fbhtechinfo, 'Intel's new Loihi 2 chip uses 1 million neurons' "
                  "(https://fbhtechinfo.com/intels-new-loihi-2-chip-uses-1-million-neurons)")
SRC_LOIHI1 = ("M. Davies et al., 'Loihi: a neuromorphic manycore processor with on-chip "
              "learning', IEEE Micro 38(1), 2018")
SRC_SPECK_ON = ("Open Neuromorphic, 'Speck - SynSense' (https://open-neuromorphic.org/"
                "neuromorphic-computing/hardware/speck-synsense)")
SRC_SPECK_SINABS = ("Sinabs documentation, 'Speck overview', Chip resources "
                    "(https://sinabs.readthedocs.io/, the Speck section)")
SRC_SPECK_MEM = ("Sinabs dynapcnn backend, per-layer kernel and neuron memory "
                 "(16Ki,16Ki,16Ki,32Ki,32Ki,64Ki,64Ki,16Ki,16Ki / 64Ki,64Ki,64Ki,32Ki,32Ki,"
                 "16Ki,16Ki,16Ki,16Ki entries; the memory-constraints table of its Speck overview)")
SRC_SPECK_ARCH = ("Sinabs documentation, 'Available network architecture' FAQ (skip and "
                  "recurrent connections between layers by manual configuration)")
SRC_SAMNA = ("SynSense samna documentation, 'Speck 2b' (https://synsense-sys-int.gitlab.io/"
             "samna/models/speckSeries/speck2b.html)")
SRC_XYLO_ON = ("Open Neuromorphic, 'Xylo - SynSense' (https://open-neuromorphic.org/"
               "neuromorphic-computing/hardware/xylo-synsense/)")
SRC_XYLO_RP = "Rockpool documentation, 'Xylo overview' (https://rockpool.ai/devices/xylo-overview.html)"


@dataclass(frozen=True)
class ChipLimits:
    """Published limits of one neuromorphic chip (None: no published figure, not checked).

    Attributes:
        title: the chip's name.
        neurons: spiking neurons on the chip.
        synapses: synapses (effective neuron-to-neuron connections).
        memory_bytes: memory for synapses and neuron states together.
        weight_bits: synaptic weight precision.
        state_bits: neuron state precision (memory estimate).
        fan_in: most synapses into one neuron.
        fan_out: most synapses out of one neuron.
        recurrent: whether a population may connect back to itself or an earlier one.
        analog_input: whether the chip takes analog (graded) input, not only events.
        inputs: input channels.
        outputs: output channels.
        layers: layered chips: the number of layers (one population per layer).
        features_per_layer: layered chips: most channels (neurons) in and out of a layer.
        layer_kernel_entries: layered chips: kernel memory of each layer (weights).
        layer_neuron_entries: layered chips: neuron memory of each layer.
        layer_destinations: layered chips: most destination layers of one layer.
        sources: ``{field: source}`` of every figure given.
        estimates: fields that are our estimate or reading, not a published number.
    """

    title: str
    neurons: int | None = None
    synapses: int | None = None
    memory_bytes: int | None = None
    weight_bits: int | None = None
    state_bits: int = 16
    fan_in: int | None = None
    fan_out: int | None = None
    recurrent: bool = True
    analog_input: bool = False
    inputs: int | None = None
    outputs: int | None = None
    layers: int | None = None
    features_per_layer: int | None = None
    layer_kernel_entries: tuple[int, ...] = ()
    layer_neuron_entries: tuple[int, ...] = ()
    layer_destinations: int | None = None
    sources: dict = field(default_factory=dict)
    estimates: tuple[str, ...] = ()


KI = 1024
CHIPS: dict[str, ChipLimits] = {
    "loihi2": ChipLimits(
        title="Intel Loihi 2 (one chip)", neurons=1_000_000, synapses=120_000_000,
        memory_bytes=128 * 128 * KI, weight_bits=8, recurrent=True, analog_input=True,
        sources={"neurons": SRC_LOIHI2_ON, "synapses": SRC_LOIHI2_ON,
                 "memory_bytes": SRC_LOIHI2_MEM + ": 128 cores x 128 KB SRAM, flexibly "
                 "partitioned", "weight_bits": SRC_LOIHI1 + " (1 to 9-bit weights on Loihi 1; "
                 "Open Neuromorphic lists '<= 32-bit' for Loihi 2)",
                 "recurrent": SRC_LOIHI2_ON + " (any core to any core over the mesh)",
                 "analog_input": SRC_LOIHI2_ON + " (graded spikes)"},
        estimates=("memory_bytes", "weight_bits")),
    "speck": ChipLimits(
        title="SynSense Speck (DYNAP-CNN)", neurons=328_000, weight_bits=8, recurrent=True,
        analog_input=False, layers=9, features_per_layer=1024,
        layer_kernel_entries=tuple(v * KI for v in (16, 16, 16, 32, 32, 64, 64, 16, 16)),
        layer_neuron_entries=tuple(v * KI for v in (64, 64, 64, 32, 32, 16, 16, 16, 16)),
        layer_destinations=2,
        sources={"neurons": SRC_SPECK_ON + "; " + SRC_SPECK_SINABS + " (0.32M)",
                 "weight_bits": SRC_SPECK_SINABS + "; " + SRC_SAMNA,
                 "state_bits": SRC_SPECK_SINABS,
                 "layers": SRC_SPECK_SINABS, "features_per_layer": SRC_SAMNA,
                 "layer_kernel_entries": SRC_SPECK_MEM, "layer_neuron_entries": SRC_SPECK_MEM,
                 "layer_destinations": SRC_SPECK_SINABS + "; " + SRC_SAMNA + " (fan-out of 2)",
                 "recurrent": SRC_SPECK_ARCH,
                 "analog_input": SRC_SPECK_SINABS + " (DVS or external events)"}),
    "xylo_audio2": ChipLimits(
        title="SynSense Xylo Audio 2", neurons=1000, synapses=64_000, weight_bits=8,
        fan_in=63, fan_out=64, recurrent=True, analog_input=False, inputs=16, outputs=8,
        sources={"neurons": SRC_XYLO_ON, "synapses": SRC_XYLO_ON, "weight_bits": SRC_XYLO_ON,
                 "fan_in": SRC_XYLO_ON, "fan_out": SRC_XYLO_RP, "inputs": SRC_XYLO_ON,
                 "outputs": SRC_XYLO_ON, "recurrent": SRC_XYLO_RP + " (recurrent hidden layer)",
                 "analog_input": SRC_XYLO_ON + " (spike input channels)"}),
}

# the former flat view (kept for callers): {chip: {limit: value}} of the figures given
LIMITS = {name: {k: v for k, v in vars(c).items()
                 if k not in ("title", "sources", "estimates") and v not in (None, ())}
          for name, c in CHIPS.items()}


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


def pow2_rows(w: np.ndarray, qmax: int = 127) -> bool:
    """Whether each row is integers of at most ``qmax`` times a power-of-two scale of its own.

    The scale tried is the one :func:`torchseq.quantise.quantise` picks (``per_row``,
    ``power_of_two``): the row's peak over ``qmax``, rounded up to a power of two.
    """
    a = np.abs(np.atleast_2d(w)).astype(np.float64)
    peak = a.max(axis=1, keepdims=True)
    scale = np.where(peak > 0, np.exp2(np.ceil(np.log2(np.where(peak > 0, peak, 1.0) / qmax))),
                     1.0)
    q = a / scale
    return bool(q.max() <= qmax and np.array_equal(q, np.rint(q)))


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
    if pow2_rows(w):
        return "int8_per_row"
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


def _meta_int(meta, key):
    try:
        v = meta.get(key) if isinstance(meta, dict) else None
        return None if v is None or isinstance(v, (bool, np.bool_)) else int(v)
    except (TypeError, ValueError):
        return None


def budget(graph, fast: bool = True) -> dict:
    """Neurons, weights, effective synapses, fan-in/out and memory of a spiking NIR graph.

    Args:
        graph: the ``nir.NIRGraph``.
        fast: count the non-zeros of a product through a selection matrix from its
            operands' patterns (:func:`_selection`, exact; the default); False multiplies
            every product out block by block (the oracle). ``"count_kernels"`` in the
            result says which ran for each pair.

    Returns:
        A dict: ``neurons``, ``populations`` ``{name: size}``, ``inputs``, ``outputs``,
        ``stored_weights``, ``effective_synapses`` (and ``_by_pair``), ``recurrent_synapses``
        (pairs from a population to itself), ``max_fan_in`` / ``max_fan_out`` (and per
        population), ``population_sources`` / ``population_destinations`` /
        ``population_input_channels``, ``weight_grids``, ``weight_bits`` (the graph's
        quantisation from its metadata, None: float32 weights), ``input_kind``
        (``"analog"`` or ``"spikes"``, from the metadata), ``memory_bytes_8bit``.
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
    sources: dict[str, list[str]] = {}
    for (src, dst), paths in eff.items():
        row, col, kernels[f"{src}->{dst}"] = _counts(paths, fast)
        pair = int(row.sum())
        by_pair[f"{src}->{dst}"] = pair
        syn += pair
        fan_in[dst] = row if dst not in fan_in else fan_in[dst] + row
        fan_out[src] = col if src not in fan_out else fan_out[src] + col
        sources.setdefault(dst, []).append(src)
    n_in = int(np.prod(graph.nodes["input"].output_type["output"]))
    sizes = dict(pops, input=n_in)
    neurons = sum(pops.values())
    meta = graph.metadata if isinstance(graph.metadata, dict) else {}
    quant = meta.get("quantisation")
    bits = _meta_int(meta, "weight_bits") or None  # 0 or absent: float32 weights
    kind = meta.get("input", "analog")
    kind = kind.decode() if isinstance(kind, bytes) else str(kind)
    return {
        "neurons": neurons, "populations": pops,
        "inputs": n_in,
        "outputs": int(np.prod(graph.nodes["output"].input_type["input"])),
        "stored_weights": stored, "stored_weights_total": sum(stored.values()),
        "effective_synapses": syn,
        "effective_synapses_by_pair": by_pair,
        "recurrent_synapses": sum(v for k, v in by_pair.items()
                                  if k.split("->")[0] == k.split("->")[1]),
        "count_kernels": kernels,
        "max_fan_in": max(int(v.max()) for v in fan_in.values()),
        "max_fan_in_by_population": {k: int(v.max()) for k, v in fan_in.items()},
        "max_fan_out": max(int(v.max()) for v in fan_out.values()),
        "max_fan_out_by_population": {k: int(v.max()) for k, v in fan_out.items()},
        "mean_fan_out": {k: float(v.mean()) for k, v in fan_out.items()},
        "population_sources": {k: sorted(v) for k, v in sources.items()},
        "population_destinations": {s: sorted(d for d, v in sources.items() if s in v)
                                    for s in sizes},
        "population_input_channels": {d: int(sum(sizes[s] for s in v))
                                      for d, v in sources.items()},
        "graph_weight_bits": 32,
        "weight_bits": bits,
        "quantisation": quant.decode() if isinstance(quant, bytes) else quant,
        "input_kind": "spikes" if kind.startswith("spikes") else "analog",
        "weight_grids": {k: weight_grid(n.weight) for k, n in graph.nodes.items()
                         if isinstance(n, (nir.Linear, nir.Affine))},
        "memory_bytes_8bit": syn + 2 * neurons,  # 8-bit synapses, 16-bit neuron states
        "spiking_layers": len(pops),
    }


def memory_bytes(b: dict, weight_bits: int, state_bits: int = 16) -> int:
    """Synaptic and neuron-state memory of budget ``b`` at these precisions (bytes, rounded up)."""
    return math.ceil(b["effective_synapses"] * weight_bits / 8) + \
        math.ceil(b["neurons"] * state_bits / 8)


def layer_kernel_entries(channels_in: int, features_out: int, kernel: int = 1) -> int:
    """Kernel memory entries of a Speck layer: ``c * 2^(ceil log2(k_x k_y) + ceil log2 f)``.

    A dense population is a ``1 x 1`` convolution over ``c`` input channels (Sinabs' Speck
    overview, "Memory constraints and network sizing": the address encoding rounds the kernel
    and output sizes up to powers of two).
    """
    def bits(n: int) -> int:
        return 0 if n <= 1 else math.ceil(math.log2(n))

    return channels_in * 2 ** (bits(kernel) + bits(features_out))


def speck_layers(b: dict, chip: ChipLimits) -> tuple[dict, list[str]]:
    """Place each spiking population on a layer of a layered chip; ``(placement, problems)``.

    Each population is one layer whose input channels are all its sources (the input
    included) and whose outputs are its neurons: kernel entries by
    :func:`layer_kernel_entries`, neuron entries = its size. Populations are placed largest
    kernel first on the free layer with the least kernel memory that holds both.
    """
    need = {p: (layer_kernel_entries(b["population_input_channels"].get(p, 0), n), n)
            for p, n in b["populations"].items()}
    free = list(range(len(chip.layer_kernel_entries)))
    placed, bad = {}, []
    for p in sorted(need, key=lambda q: -need[q][0]):
        kern, neur = need[p]
        fits = [i for i in free if chip.layer_kernel_entries[i] >= kern
                and chip.layer_neuron_entries[i] >= neur]
        if not fits:
            bad.append(f"{p}: {kern} kernel entries ({b['population_input_channels'].get(p, 0)} "
                       f"channels in, {neur} out) and {neur} neuron entries > any free layer "
                       f"(largest kernel memory {max(chip.layer_kernel_entries)} entries)")
            continue
        i = min(fits, key=lambda j: (chip.layer_kernel_entries[j], j))
        free.remove(i)
        placed[p] = {"layer": i, "kernel_entries": kern, "neuron_entries": neur}
    return placed, bad


def check(b: dict) -> dict:
    """Each chip of :data:`CHIPS`: ``{"fits", "exceeds": [reasons], "notes": [...]}``.

    A reason names the figure, the model's value and the limit (``"neurons 28672 > 1000"``).
    Memory is counted at the chip's weight precision; weights stored as float32 (no
    quantisation in the graph's metadata) or quantised to more bits than the chip holds
    exceed its weight precision.
    """
    out = {}
    for chip, lim in CHIPS.items():
        bad, notes = [], []

        def over(what, value, limit):
            if limit is not None and value > limit:
                bad.append(f"{what} {value} > {limit}")

        over("neurons", b["neurons"], lim.neurons)
        over("synapses", b["effective_synapses"], lim.synapses)
        if lim.memory_bytes is not None:
            mem = memory_bytes(b, lim.weight_bits or 8, lim.state_bits)
            over(f"memory at {lim.weight_bits}-bit weights and {lim.state_bits}-bit states "
                 f"(bytes)", mem, lim.memory_bytes)
        over("fan-in", b["max_fan_in"], lim.fan_in)
        over("fan-out", b["max_fan_out"], lim.fan_out)
        over("input channels", b["inputs"], lim.inputs)
        over("outputs", b["outputs"], lim.outputs)
        if lim.weight_bits is not None:
            bits = b.get("weight_bits")
            if bits is None:
                bad.append(f"weight precision float32 > {lim.weight_bits} bits ("
                           f"{b.get('config', 'export with SpikingConfig')}"
                           f"(weight_bits={lim.weight_bits}))")
            else:
                over("weight bits", bits, lim.weight_bits)
        if not lim.recurrent and b.get("recurrent_synapses", 0):
            bad.append(f"recurrent synapses {b['recurrent_synapses']} > 0 (no recurrence)")
        if not lim.analog_input and b.get("input_kind", "analog") != "spikes":
            bad.append("input is an analog current (the encoded frame); the chip takes events "
                       "only " + b.get("event_input", "(convert with "
                                       "SpikingConfig(input_threshold=...))"))
        if lim.layers is not None:
            over("spiking layers", b["spiking_layers"], lim.layers)
            for p, n in b["populations"].items():
                over(f"{p} features", n, lim.features_per_layer)
            for p, c in b.get("population_input_channels", {}).items():
                over(f"{p} input channels", c, lim.features_per_layer)
            for p, d in b.get("population_destinations", {}).items():
                over(f"{p} destination layers", len(d), lim.layer_destinations)
            placed, problems = speck_layers(b, lim)
            bad += problems
            notes.append(f"layers: {placed}")
        missing = [k for k in ("fan_in", "fan_out") if getattr(lim, k) is None]
        if missing:
            notes.append(f"no published {', '.join(missing)} limit: not checked")
        if lim.estimates:
            notes.append(f"estimated limits: {', '.join(lim.estimates)}")
        out[chip] = {"fits": not bad, "exceeds": bad, "notes": notes}
    return out
