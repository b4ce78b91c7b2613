"""NIR export of the spiking Neural SeqSLAM (``docs/guide/nir.md``).

:func:`to_nir` turns a :class:`~torchseq.neural.spiking.SpikingSeqSLAM` into a
``nir.NIRGraph`` (the Neuromorphic Intermediate Representation, package ``nir``);
:func:`write_nir` writes it atomically with ``nir.write`` (HDF5). Nodes:

================ ================ =================================================
``input``        Input ``(D,)``   the encoded frame (analog current, one step a frame)
``l1``           Linear ``(M, D)`` L1 weights with the mask folded, over ``theta2``
``l2``           LIF ``(M,)``     threshold units (``tau = dt``): the k-WTA stand-in
``l3``           Linear ``(N, M)`` masked L2 -> L3 weights, cohort-centred, ``* gain/sigma_c``
``levels``       Linear ``(N*K, N)`` ``1 / theta_k`` to the ``K`` neurons of each unit
``ring``         LIF ``(N*K,)``   the thermometer-coded ring (``tau = dt``)
``shift``        Linear ``(N, N*K)`` the learnt shift times ``decay * (g_l - g_{l-1})``
``output``       Output ``(N*K,)`` ring spikes; the unit's count is the sum of its ``K``
================ ================ =================================================

Edges: ``input -> l1 -> l2 -> l3 -> levels -> ring -> {shift, output}`` and
``shift -> levels`` (the cycle; inputs to a node add). The graph has no other branch that
joins again: Norse's importer (nirtorch's ``GraphExecutor``) runs nodes in depth-first
order, so a second feed-forward path into ``levels`` would reach it one step late; that is
why the cohort centring is folded into ``l3`` (dense) and not kept as a mean unit.
A model with event input (:class:`~torchseq.neural.spiking_events.EventSpikingSeqSLAM`)
has ``input`` ``(2 H W,)`` (one window's event counts) and a ``pool`` Linear ``(D, 2 H W)``
before ``l1``: ``input -> pool -> l1`` (:func:`event_input_nodes`; ``sensor`` in metadata).
The graph's ``metadata`` carries ``dt`` (the time step the time constants are written
for), the unit layout, each unit's reference frame, the calibration and the k-WTA
approximation with its reason. ``nir`` is an optional dependency (``torchseq[nir]``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from torchseq.atomic import atomic_path
from torchseq.neural.spiking import DT

FORMAT = "torchseq.spiking-nir/1"
KWTA_NOTE = ("k-WTA has no NIR primitive: L2 is a layer of threshold units (LIF, tau = dt) with "
             "the threshold calibrated on the reference traverse so that about k units fire; "
             "the number of winners varies from frame to frame (see docs/guide/nir.md)")


class NIRExportError(ValueError):
    """The NIR export cannot be made or read back (missing package, bad graph or file)."""


def require_nir():
    """Import ``nir``, or raise :class:`NIRExportError` saying how to install it."""
    try:
        import nir
    except ImportError:
        raise NIRExportError("the NIR export needs the 'nir' package: "
                             "pip install 'torchseq[nir]'") from None
    return nir


def _f32(t) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy().astype(np.float32))


def _lif(nir, n: int, dt: float):
    """NIR LIF of ``n`` memoryless units: ``tau = dt``, ``r = 1``, threshold 1, reset 0."""
    one = np.ones(n, dtype=np.float32)
    return nir.LIF(tau=np.full(n, dt, dtype=np.float32), r=one,
                   v_leak=np.zeros(n, dtype=np.float32), v_threshold=one,
                   v_reset=np.zeros(n, dtype=np.float32))


def to_nir(spiking, dt: float = DT):
    """The NIR graph of a spiking model (node table in the module docstring).

    Args:
        spiking: a :class:`~torchseq.neural.spiking.SpikingSeqSLAM`.
        dt: the simulation time step the time constants are written for (s).

    Returns:
        ``nir.NIRGraph``.
    """
    nir = require_nir()
    s = spiking.sizes
    n, k = s["units"], s["levels"]
    inv_theta = _f32(spiking.inv_theta)  # (K,)
    levels = np.zeros((n * k, n), dtype=np.float32)
    rows = np.arange(n * k)
    levels[rows, rows // k] = np.tile(inv_theta, n)
    # (N, N*K): column j*K+l = shift[:, j] * step[l] (level l's share of unit j's value);
    # a quantised model holds that matrix itself, quantised row by row
    shift = (_f32(spiking.shift_dense) if spiking.shift_dense is not None else
             np.kron(_f32(spiking.shift), _f32(spiking.rung_step)[None, :]).astype(np.float32))
    nodes = {
        "input": nir.Input(input_type={"input": np.array([s["input"]])}),
        "l1": nir.Linear(weight=_f32(spiking.w1)),
        "l2": _lif(nir, s["l2"], dt),
        "l3": nir.Linear(weight=_f32(spiking.w3)),
        "levels": nir.Linear(weight=levels),
        "ring": _lif(nir, n * k, dt),
        "shift": nir.Linear(weight=shift),
        "output": nir.Output(output_type={"output": np.array([n * k])}),
    }
    edges = [("input", "l1"), ("l1", "l2"), ("l2", "l3"), ("l3", "levels"),
             ("shift", "levels"), ("levels", "ring"), ("ring", "shift"), ("ring", "output")]
    meta = {
        "format": FORMAT, "dt": float(dt), "units": n, "levels": k,
        "layout": "ring neuron j*levels + l is level l of output unit j; a unit's spike count "
                  "is the sum of its levels; the decision is the unit with the most spikes "
                  "(first on ties)",
        "unit_centre": spiking.unit_centre.cpu().numpy().astype(np.int64),
        "uniqueness_window": int(spiking.window),
        "steps_per_frame": 1,
        "nir_compatibility": "readable by nir 1.0.4 and 1.0.8: the LIF nodes' v_reset (0) is "
                             "not written (nir >= 1.0.5 reads it as 0; nir 1.0.4 resets by "
                             "subtracting the threshold, the same spikes for tau = dt)",
        "kwta": KWTA_NOTE,
        "calibration": json.dumps(spiking.calibration),
        **quantisation_metadata(spiking),
        "input": ("analog current: the encoded frame (D values), one step per frame"
                  if spiking.input_threshold is None else
                  f"spikes: ON/OFF events, ON where the encoded pixel > {spiking.input_threshold}"
                  f", OFF where < -{spiking.input_threshold} (2 D channels: ON then OFF)"),
    }
    if getattr(spiking, "sensor", None) is not None:  # event input: input -> pool -> l1
        nodes, edges, meta = event_input_nodes(nir, spiking, nodes, edges, meta)
    return nir.NIRGraph(nodes=nodes, edges=edges, metadata=meta)


def event_input_nodes(nir, spiking, nodes: dict, edges: list, meta: dict):
    """The graph's input stage for event input (:mod:`torchseq.neural.spiking_events`).

    ``input`` becomes the ``2 H W`` event counts of one window (``(2, H, W)`` channel-major,
    channel 0 OFF, 1 ON, flattened), ``pool`` a Linear ``(D, 2 H W)`` of 0/1 sum-pooling
    weights onto the model's input grid, and ``l1`` (already the folded
    ``W1 S C diag(1 / n) / theta2``) reads ``pool``. Linear nodes only: snnTorch, Norse and
    nir 1.0.4 read them. The metadata gains ``sensor`` ``[H, W]`` and the stage's words.

    Returns:
        ``(nodes, edges, meta)``, new objects.
    """
    h, w = spiking.sensor
    n_in = int(spiking.pool.shape[1])
    nodes = {"input": nir.Input(input_type={"input": np.array([n_in])}),
             "pool": nir.Linear(weight=_f32(spiking.pool)),
             **{k: v for k, v in nodes.items() if k != "input"}}
    edges = [("input", "pool"), ("pool", "l1")] + [e for e in edges if e != ("input", "l1")]
    size = spiking.calibration.get("event_input", {}).get("input_size")
    meta = {**meta, "sensor": np.array([h, w], dtype=np.int64),
            "input": (f"spikes: event counts of one time window from a {h}x{w} sensor, "
                      f"{n_in} values (2, H, W) channel-major, channel 0 OFF, 1 ON; one step "
                      f"per window; pool sums both polarities onto the {size} input grid, "
                      f"l1 holds the patch centring and a per-block scale calibrated on the "
                      f"reference windows (the linear stand-in of the patch z-score)")}
    return nodes, edges, meta


def quantisation_metadata(spiking) -> dict:
    """The graph's ``weight_bits`` (0: float32) and ``quantisation`` (what was done, words)."""
    bits = spiking.calibration.get("weight_bits")
    if bits is None:
        return {"weight_bits": 0, "quantisation": "none: float32 weights"}
    pool = (" pool (event input) holds 0/1 sum-pooling weights, exact at any precision."
            if getattr(spiking, "sensor", None) is not None else "")
    return {"weight_bits": int(bits),
            "quantisation": f"l1, l3, levels and shift: signed {bits}-bit integers (symmetric, "
                            f"|q| <= {2 ** (bits - 1) - 1}) times one power-of-two scale per "
                            f"row (output neuron), rounded half away from zero; l3, levels and "
                            f"shift store q * 2^e exactly; l1 stores q * 2^e / theta2 (the L2 "
                            f"threshold theta2, in the calibration, folded in: on a chip, q "
                            f"with threshold theta2 / 2^e per row); LIF thresholds 1.{pool}"}


def write_nir(spiking, path: str | Path, dt: float = DT):
    """Write :func:`to_nir`'s graph to ``path`` atomically (``nir.write``, HDF5); return it."""
    nir = require_nir()
    graph = to_nir(spiking, dt)
    path = Path(path)
    with atomic_path(path) as tmp:  # gzip level 1: half the CPU of nir's default 4, +18%
        nir.write(tmp, graph, compression="gzip", compression_opts=1)
        drop_zero_resets(tmp, graph)
    return graph


def drop_zero_resets(path, graph) -> list[str]:
    """Remove the LIF nodes' ``v_reset`` datasets from a written file, so nir 1.0.4 reads it.

    nir 1.0.4's ``LIF`` has no ``v_reset`` (its reset subtracts the threshold) and refuses a
    file that has one; nir >= 1.0.5 fills an absent ``v_reset`` with zeros. Every LIF of this
    graph resets to 0 and has ``tau = dt`` (memoryless: ``v <- I`` every step), so both
    readings give the same spikes. Only such nodes are touched.

    Returns:
        The nodes whose ``v_reset`` was removed.
    """
    import h5py
    import nir

    done = []
    with h5py.File(path, "r+") as f:
        nodes = f["node"]["nodes"]
        for name, node in graph.nodes.items():
            if isinstance(node, nir.LIF) and np.all(node.v_reset == 0) \
                    and np.allclose(node.tau, float(graph.metadata["dt"]), rtol=1e-6) \
                    and "v_reset" in nodes[name]:
                del nodes[name]["v_reset"]
                done.append(name)
    return done


def _whole(value, key: str, lo: int, hi: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
            or not lo <= int(value) <= hi:
        raise NIRExportError(f"metadata {key!r} must be a whole number in {lo}..{hi}, "
                             f"got {_show(value)}")
    return int(value)


def _show(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def graph_metadata(graph) -> dict:
    """The parsed metadata a reader of the graph needs: ``{"units", "levels", "dt"}``.

    Checks that the graph holds the ring its metadata describes: ``units`` (1..2**24) and
    ``levels`` (1..1024) whole numbers, ``dt`` a finite positive number, ``steps_per_frame``
    1, and an ``output`` node of ``units * levels`` values.

    Raises:
        NIRExportError: a field that is missing or cannot be parsed, or a graph of another
            size.
    """
    meta = graph.metadata if isinstance(graph.metadata, dict) else {}
    missing = [k for k in ("units", "levels", "dt", "steps_per_frame") if k not in meta]
    if missing:
        raise NIRExportError(f"metadata lacks {', '.join(map(repr, missing))}")
    units = _whole(meta["units"], "units", 1, 2**24)
    levels = _whole(meta["levels"], "levels", 1, 1024)
    _whole(meta["steps_per_frame"], "steps_per_frame", 1, 1)
    dt = meta["dt"]
    if isinstance(dt, (bool, np.bool_)) or not isinstance(dt, (int, float, np.integer,
                                                               np.floating)) \
            or not math.isfinite(float(dt)) or not float(dt) > 0:
        raise NIRExportError(f"metadata 'dt' must be a finite positive number, got {_show(dt)}")
    try:
        n_out = int(np.prod(graph.nodes["output"].output_type["output"]))
    except Exception:  # noqa: BLE001 - any malformed output node: not our graph
        raise NIRExportError("the graph has no readable 'output' node") from None
    if n_out != units * levels:
        raise NIRExportError(f"the graph's output has {n_out} values, its metadata says "
                             f"{units} units x {levels} levels")
    return {"units": units, "levels": levels, "dt": float(dt)}


READ_SECONDS = 10.0  # a trial read's time; the largest ring's file reads in well under 1 s
READ_BYTES = 2 << 30  # and the memory it may add


def _trial_child(path: str, conn, limit: int) -> None:
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))
    try:
        require_nir().read(path)
        conn.send(None)
    except MemoryError:
        conn.send(f"reading it needs more than {READ_BYTES >> 20} MiB")
    except Exception as err:  # noqa: BLE001 - reported by the parent's own read
        conn.send(type(err).__name__)


def _trial_read(path) -> str | None:
    """Read ``path`` once in a child process bounded in time and memory; why it failed or None.

    libhdf5 runs damaged files in C code no Python signal interrupts (one changed byte in a
    variable-length string's heap address: 3 s and gigabytes inside ``nir.read``; the fuzz
    found reads past 60 s), so the bound is a process: forked (nothing to import; spawned
    where fork is missing), capped at ``READ_BYTES`` more address space, killed after
    ``READ_SECONDS``. Only a file the child read is read here.
    """
    import multiprocessing as mp
    import resource

    method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
    ctx = mp.get_context(method)
    used = int(open("/proc/self/statm").read().split()[0]) * resource.getpagesize() \
        if Path("/proc/self/statm").is_file() else 0
    hard = resource.getrlimit(resource.RLIMIT_AS)[1]
    limit = used + READ_BYTES if hard == resource.RLIM_INFINITY else min(used + READ_BYTES, hard)
    receive, send = ctx.Pipe(duplex=False)
    child = ctx.Process(target=_trial_child, args=(str(path), send, limit), daemon=True)
    child.start()
    send.close()
    try:
        if receive.poll(READ_SECONDS):
            return receive.recv()
        return f"reading it took more than {READ_SECONDS:g} s"
    except EOFError:  # the child died without a word (killed for memory)
        return f"reading it needs more than {READ_BYTES >> 20} MiB"
    finally:
        if child.is_alive():
            child.kill()
        child.join()
        receive.close()


def read_nir(path: str | Path):
    """``nir.read`` a file written by :func:`write_nir`, checking its format and metadata.

    The format tag must be this module's :data:`FORMAT`, and :func:`graph_metadata` must
    parse (units, levels, ``dt``, the ring's size).

    The file is first read in a child process bounded in time and memory
    (:func:`_trial_read`): a damaged HDF5 file can hold libhdf5 for minutes.

    Raises:
        NIRExportError: not a readable NIR file (or one whose read exceeds the bounds), not
            one of ours, or metadata that cannot be parsed.
    """
    nir = require_nir()
    failed = _trial_read(path)
    if failed is not None:
        raise NIRExportError(f"{path}: not a readable NIR file ({failed})")
    try:
        graph = nir.read(path)
    except Exception as err:  # noqa: BLE001 - h5py/nir raise many types on a bad file
        raise NIRExportError(f"{path}: not a readable NIR file ({type(err).__name__})") from None
    fmt = graph.metadata.get("format") if isinstance(graph.metadata, dict) else None
    if isinstance(fmt, bytes):
        fmt = fmt.decode("utf-8", "replace")
    if not isinstance(fmt, str) or fmt != FORMAT:  # an array or a number is no format tag
        raise NIRExportError(f"{path}: format {_show(fmt)} is not {FORMAT!r}")
    try:
        graph_metadata(graph)
    except NIRExportError as err:
        raise NIRExportError(f"{path}: {err}") from None
    return graph
