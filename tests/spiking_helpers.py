"""Spiking helpers shared by the spiking and NIR test modules: the small fitted models (cached
once a session), a NIR reference run written from the specification, and a Python with nir
1.0.4 for the version-compatibility tests."""

from functools import lru_cache

import numpy as np
import pytest
from conftest import coarse_units_expected

from torchseq.demo import make_demo
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.neural.spiking import SpikingConfig, SpikingSeqSLAM


@lru_cache(maxsize=None)
def tiny():
    """A tiny model (small enough for a pure-Python loop) on a 40-frame demo route."""
    demo = make_demo(n_reference=40, size=(48, 64), seed=3)
    model = NeuralSeqSLAM(NeuralConfig(
        unit_search="off", input_size=(8, 12), hidden=96, n_output=20))
    with coarse_units_expected():  # a small model: units of several frames
        model.fit(demo.reference, log=False)
    spiking = SpikingSeqSLAM.convert(model, demo.reference, SpikingConfig(levels=6))
    return model, demo, spiking


@lru_cache(maxsize=None)
def demo_setup():
    demo = make_demo()
    model = NeuralSeqSLAM(NeuralConfig(unit_search="off"))
    model.fit(demo.reference, log=False)
    return model, demo, SpikingSeqSLAM.convert(model, demo.reference)



def nir_reference_run(graph, x: np.ndarray, dt: float) -> np.ndarray:
    """Run a NIR graph of Input / Linear / LIF / Output nodes by NIR's own equations.

    Written from the NIR specification, not from torchseq or a consumer: a depth-first walk
    from the input along the edges marks the edges that close a cycle (they point back to a
    node on the walk's stack); those carry the source's output of the previous step (zeros at
    the start), every other edge the output of the same step. Every step, a node adds the
    outputs of its sources; Linear is ``W @ in``; LIF is one Euler step of
    ``tau dv/dt = (v_leak - v) + r I``, spike ``v > v_threshold``, then ``v = v_reset`` where
    it spiked. Returns the output node's values ``(T, n)``.
    """
    import nir

    nodes = graph.nodes
    start = next(k for k, n in nodes.items() if isinstance(n, nir.Input))
    back, done = set(), set()

    def walk(k, stack):
        for s, d in graph.edges:
            if s != k:
                continue
            if d in stack:
                back.add((s, d))
            elif d not in done:
                walk(d, stack | {d})
        done.add(k)

    walk(start, frozenset({start}))
    forward = [e for e in graph.edges if e not in back]
    order, ready = [], [start]
    while ready:  # Kahn's topological sort on the forward edges
        k = ready.pop()
        order.append(k)
        for s, d in forward:
            if s == k and all(a in order for a, b in forward if b == d):
                ready.append(d)
    assert set(order) == set(nodes)
    sources = {k: [s for s, d in graph.edges if d == k] for k in nodes}
    prev = {k: 0.0 for k in nodes}
    v = {k: np.zeros(n.tau.shape) for k, n in nodes.items() if isinstance(n, nir.LIF)}
    out = []
    for frame in x.astype(np.float64):
        cur = {}
        for k in order:
            n = nodes[k]
            if isinstance(n, nir.Input):
                cur[k] = frame
                continue
            i = sum(prev[s] if (s, k) in back else cur[s] for s in sources[k])
            if isinstance(n, nir.Linear):
                cur[k] = n.weight.astype(np.float64) @ i
            elif isinstance(n, nir.LIF):
                vk = v[k] + dt / n.tau * ((n.v_leak - v[k]) + n.r * i)
                z = (vk > n.v_threshold).astype(np.float64)
                v[k] = np.where(z > 0, n.v_reset, vk)
                cur[k] = z
            elif isinstance(n, nir.Output):
                cur[k] = i
            else:
                raise AssertionError(f"unexpected node {type(n).__name__}")
        prev = cur
        out.append(cur["output"])
    return np.array(out)



NIR104_SCRIPT = """
import sys, numpy as np, nir
out = {}
for i, path in enumerate(sys.argv[2:]):
    g = nir.read(path)
    out[f"{i}/meta/format"] = np.array(str(g.metadata["format"]))
    for name, node in g.nodes.items():
        out[f"{i}/{name}/type"] = np.array(type(node).__name__)
        for field, value in vars(node).items():
            if isinstance(value, np.ndarray):
                out[f"{i}/{name}/{field}"] = value
    out[f"{i}/edges"] = np.array(sorted(map(list, g.edges)))
np.savez(sys.argv[1], **out)
"""


def nir104_python(tmp_path_factory) -> str:
    """A Python with nir 1.0.4: ``$TORCHSEQ_NIR104_PYTHON``, else a venv made here (pip)."""
    import os
    import subprocess
    import sys

    given = os.environ.get("TORCHSEQ_NIR104_PYTHON")
    if given:
        return given
    venv = tmp_path_factory.mktemp("nir104") / "venv"
    try:
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True,
                       capture_output=True, timeout=120)
        subprocess.run([str(venv / "bin" / "pip"), "install", "-q", "nir==1.0.4"], check=True,
                       capture_output=True, timeout=600)
    except (subprocess.SubprocessError, OSError) as err:
        pytest.skip(f"no venv with nir 1.0.4 could be made here ({type(err).__name__})")
    return str(venv / "bin" / "python")

