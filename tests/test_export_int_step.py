"""IntegerStepModule (the one definition of the integer step) against the independent
plain-Python oracle, the released v1 file, the NumPy kernels and the integer ONNX graph;
the runtimes' kernel dispatch and their memory budget."""

import io
import math
import warnings
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from conftest import coarse_units_expected
from export_helpers import small_setup
from int_oracle import oracle_step

from torchseq.demo import make_demo
from torchseq.export.int_format import IntegerFormatError, IntegerModel, read_integer_model
from torchseq.export.int_functional import isqrt, kwta_code, round_div
from torchseq.export.int_model import choose_pool, device_frames, integer_model
from torchseq.export.int_onnx import build_integer_onnx
from torchseq.export.int_runtime import IntegerRuntime
from torchseq.export.int_step import IntegerStepModule
from torchseq.export.int_stream import StreamRuntime
from torchseq.export.sessions import session
from torchseq.neural import NeuralConfig, NeuralSeqSLAM

DATA = Path(__file__).resolve().parent / "data"
CONFIGS = {
    "one_cohort_rectified": {},
    "three_cohorts_rectified": {"n_cohorts": 3},
    "three_cohorts_unrectified": {"n_cohorts": 3, "rectify": False},
    "raw_input": {"patch_size": 0},
}


def tiny(**cfg):
    demo = make_demo(n_reference=12, size=(16, 16), seed=5)
    model = NeuralSeqSLAM(NeuralConfig(
        unit_search="off", input_size=(8, 8), hidden=64, n_output=9, **cfg))
    with coarse_units_expected():  # a small model: units of several frames
        model.fit(demo.reference, log=False)
    pool = choose_pool((16, 16), (8, 8))
    frames = device_frames(demo.query, (8, 8), pool)
    frames[2] = 90  # flat: zero variance everywhere and an all-tied k-WTA
    # the first row of blocks: pooled columns alternately 0 and 4 * 255, the largest
    # variance the bounds allow (the top bit of the z-score's isqrt)
    frames[4, :8] = np.where(np.arange(16) // 2 % 2 == 0, 255, 0)[None, :]
    return integer_model(model, pool), frames


def module_run(model: IntegerModel, frames: np.ndarray, batch_streams: int = 1):
    """Stream ``(T, B, H, W)`` (or ``(T, H, W)``) frames through the module, state fed back."""
    mod = IntegerStepModule(model)
    x = torch.from_numpy(frames if frames.ndim == 4 else frames[:, None])
    state = torch.zeros(x.shape[1], model.params["n_units"], dtype=torch.int32)
    acts, refs, confs = [], [], []
    for t in range(x.shape[0]):
        state, ref, conf = mod(x[t], state)
        acts.append(state.numpy())
        refs.append(ref.numpy())
        confs.append(conf.numpy())
    return np.stack(acts), np.stack(refs), np.stack(confs)


@pytest.mark.parametrize("kind", list(CONFIGS))
def test_module_equals_the_plain_python_oracle(kind):
    model, frames = tiny(**CONFIGS[kind])
    act, ref, conf = module_run(model, frames)
    assert act.dtype == np.int32 and ref.dtype == conf.dtype == np.int64
    state = [0] * model.params["n_units"]
    for t in range(frames.shape[0]):
        state, r, c = oracle_step(model, frames[t].tolist(), state)
        assert act[t, 0].tolist() == state, f"step {t}"
        assert (int(ref[t, 0]), int(conf[t, 0])) == (r, c), f"step {t}"


def test_module_reproduces_the_released_v1_file():
    model = read_integer_model(DATA / "int_format_v1.tsq")
    exp = np.load(DATA / "int_format_v1_expected.npz")
    act, ref, conf = module_run(model, exp["frames"])
    assert np.array_equal(act[:, 0], exp["activity"])
    assert np.array_equal(ref[:, 0], exp["reference"])
    assert np.array_equal(conf[:, 0], exp["confidence"])


@pytest.mark.parametrize("kind", ["three_cohorts_unrectified", "raw_input"])
def test_module_numpy_kernels_and_onnx_graph_agree_on_three_streams(kind):
    model, frames = tiny(**CONFIGS[kind])
    streams = np.stack([frames[:6], frames[6:12], frames[::2][:6]], 1)  # (T, 3, H, W)
    act, ref, conf = module_run(model, streams)
    rt, sess = IntegerRuntime(model), session(build_integer_onnx(model))
    state_n = rt.initial_state(3)
    state_o = state_n.copy()
    for t in range(streams.shape[0]):
        out, state_n = rt.step(streams[t], state_n)
        act_o, state_o, ref_o, conf_o = sess.run(None, {"frames": streams[t], "state": state_o})
        for got in ((out.activity, out.reference, out.confidence), (act_o, ref_o, conf_o)):
            assert np.array_equal(got[0], act[t]) and np.array_equal(got[1], ref[t])
            assert np.array_equal(got[2], conf[t])


def test_integer_graph_keeps_the_hand_built_operators():
    """The exported graph's operators where they matter for speed (measured with
    benchmarks/bench_export_compare.py): five int8 MatMulInteger products, lower bounds as
    Max (a one-sided Clip runs slower in onnxruntime), the confidence's column dropped by
    Squeeze (not a Gather), no float, scalar constants 0-d."""
    model, _ = tiny()  # z-score input, rectified: three lower bounds
    graph = build_integer_onnx(model).graph
    ops = [node.op_type for node in graph.node]
    assert ops.count("MatMulInteger") == 5 and ops.count("TopK") == 1
    assert ops.count("Max") == 3 and "Squeeze" in ops and "Sqrt" not in ops
    for node in graph.node:
        if node.op_type == "Clip":
            assert len(node.input) == 3 and all(node.input), "a one-sided Clip"
    consts = {node.output[0]: onnx.numpy_helper.to_array(node.attribute[0].t)
              for node in graph.node if node.op_type == "Constant"}
    mod = next(node for node in graph.node if node.op_type == "Mod")
    assert consts[mod.input[1]].shape == ()


@pytest.fixture(scope="module")
def larger():
    """small_setup's 1024-unit integer model, its device frames and the module's run of them."""
    _, _, _, frames, im = small_setup()
    return im, frames, module_run(im, frames)


@pytest.mark.parametrize("runtime", [
    "numpy", "stream",
    # the runtime's torch kernel runs this same module (numpy == torch on the tiny models
    # in the quick run, test_runtime_kernel_is_chosen_at_construction); here in the slow pass
    pytest.param("torch", marks=pytest.mark.slow)])
def test_module_equals_numpy_stream_and_torch_runtimes_on_a_larger_model(larger, runtime):
    im, frames, (act, ref, conf) = larger
    got = {"numpy": lambda: IntegerRuntime(im).run(frames),
           "stream": lambda: StreamRuntime(im, chunk=16).run(frames),
           "torch": lambda: IntegerRuntime(im, kernel="torch").run(frames)}[runtime]()
    assert np.array_equal(got[0], ref[:, 0]) and np.array_equal(got[1], conf[:, 0])
    assert np.array_equal(got[2], act[:, 0])


def test_round_div_isqrt_and_kwta_against_python_ints():
    g = np.random.default_rng(0)
    a = np.concatenate([g.integers(-2**60, 2**60, 3000), np.arange(-30, 31)])
    b = np.concatenate([g.integers(1, 2**61, 3000), np.full(61, 4)])
    b[:40] = 2 * np.abs(a[:40]) + 1  # quotients just below one half
    b[40:80] = 2 * g.integers(1, 2**56, 40)  # even: exact halves below
    a[40:80] = b[40:80] * g.integers(-9, 9, 40) + b[40:80] // 2
    got = round_div(torch.from_numpy(a), torch.from_numpy(b)).tolist()
    for x, y, q in zip(a.tolist(), b.tolist(), got):
        want = (2 * abs(x) + y) // (2 * y)
        assert q == (want if x >= 0 else -want)
    r = g.integers(1, 2**31 - 1, 1000)
    v = np.concatenate([g.integers(0, 2**62 - 1, 3000), np.arange(300), r * r, r * r - 1,
                        np.array([2**62 - 1, (2**31 - 1) ** 2 - 1])])
    assert isqrt(torch.from_numpy(v)).tolist() == [math.isqrt(x) for x in v.tolist()]
    h = torch.from_numpy(g.integers(-3, 4, (40, 50)))
    h[0] = 2**31 - 1  # all tied at the largest |hid|
    h[1, ::2] = -(2**31 - 1)
    for k in (1, 9, 50):
        code = kwta_code(h, k)
        for row, c in zip(h.tolist(), code.tolist()):  # sort by value, then the lower index
            order = sorted(range(50), key=lambda j: (-row[j], j))[:k]
            assert [j for j in range(50) if c[j]] == sorted(order)


@pytest.mark.parametrize("bits", [31, 21, 3])
def test_isqrt_graph_form_in_onnxruntime(bits):
    class Root(torch.nn.Module):
        def forward(self, v):
            return isqrt(v, bits)

    top = 4**bits - 1
    g = np.random.default_rng(bits)
    r = g.integers(0, 2**bits, 500)
    v = np.concatenate([g.integers(0, top, 500), r * r, np.maximum(r * r - 1, 0),
                        np.array([0, 1, top, (2**bits - 1) ** 2])])
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(Root(), (torch.from_numpy(v),), buf, dynamo=False, opset_version=17,
                          input_names=["v"], dynamic_axes={"v": {0: "n"}})
    types = {node.op_type for node in onnx.load_from_string(buf.getvalue()).graph.node}
    assert "Sqrt" not in types and "Cast" not in types  # integer-only in the graph
    (got,) = session(onnx.load_from_string(buf.getvalue())).run(None, {"v": v})
    assert got.tolist() == [math.isqrt(x) for x in v.tolist()]


def test_runtime_kernel_is_chosen_at_construction(monkeypatch):
    model, frames = tiny()
    ran = []
    forward, drive = IntegerStepModule.forward, IntegerRuntime.drive
    monkeypatch.setattr(IntegerStepModule, "forward",
                        lambda self, *a: ran.append("torch") or forward(self, *a))
    monkeypatch.setattr(IntegerRuntime, "drive",
                        lambda self, *a: ran.append("numpy") or drive(self, *a))
    outs = {}
    for kernel in ("numpy", "torch"):
        ran.clear()
        rt = IntegerRuntime(model, kernel=kernel)
        outs[kernel] = rt.run(frames)
        assert rt.kernel == kernel and set(ran) == {kernel}, ran
    for a, b in zip(outs["numpy"], outs["torch"]):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    with pytest.raises(ValueError, match="kernel"):
        IntegerRuntime(model, kernel="fast")


def huge_sparse_model() -> IntegerModel:
    """A legal model of 32767 inputs, L2 and output units, every fan-in 1 (a small file)."""
    m = 32767
    idx = np.arange(m)
    params = {"height": 7, "width": 4681, "pool_h": 1, "pool_w": 1, "patch": 0,
              "input_mode": 0, "x_frac": 0, "sqrt_frac": 0, "norm_const": 0, "n_input": m,
              "hidden": m, "k": 3, "l1_fan_in": 1, "n_units": m, "l3_fan_in": 1,
              "e_shift": 15, "n_cohorts": 1, "rectify": 1, "gain_const": 1 << 20,
              "gain_shift": 0, "state_frac": 16, "ring_frac": 15, "ring_width": 1, "window": 5}
    arrays = {"l1.cols": idx[:, None].astype("<u2"),
              "l1.values": (idx % 2047 - 1023)[:, None].astype("<i2"),
              "l3.cols": idx[::-1, None].astype("<u2"),
              "l3.values": (idx % 255 - 127)[:, None].astype("<i1"),
              "l3.row_scale": np.full(m, 32768, "<i4"), "cohort": np.zeros(m, "<u2"),
              "ring.cols": ((idx + m - 1) % m)[:, None].astype("<u2"),
              "ring.values": np.full((m, 1), 29491, "<i2"),
              "unit_centre": idx.astype("<i4"), "unit_to_ref": np.stack([idx, idx + 1], 1)
              .astype("<i4")}
    return IntegerModel.from_params(params, arrays)


def test_dense_kernels_refuse_a_small_file_that_asks_for_gigabytes():
    model = huge_sparse_model()
    for build, what in ((IntegerRuntime, "NumPy L3 kernel"), (StreamRuntime, "StreamRuntime"),
                        (build_integer_onnx, "integer ONNX graph")):
        with pytest.raises(IntegerFormatError, match=f"{what}.*memory budget"):
            build(model)
    # the definition's memory follows the file: it runs, and agrees with the oracle
    rt = IntegerRuntime(model, kernel="torch")
    frames = np.random.default_rng(3).integers(0, 256, (2, 7, 4681)).astype(np.uint8)
    out, state = rt.step(frames)
    out, state = rt.step(frames[::-1].copy(), state)
    want_state = [0] * model.params["n_units"]
    for f in (frames[1], frames[0]):  # stream 1 saw frames[1] then frames[0]
        want_state, ref, conf = oracle_step(model, f.tolist(), want_state)
    assert state[1].tolist() == want_state
    assert (int(out.reference[1]), int(out.confidence[1])) == (ref, conf)

