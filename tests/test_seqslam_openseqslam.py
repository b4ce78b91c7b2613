"""The OpenSeqSLAM preset, kernel dispatch, worker threads and edge matching, against the
loop oracle (tests/seqslam_oracle.py) extended with OpenSeqSLAM's uint8 rules."""

import platform

import cv2
import numpy as np
import pytest
import torch
from conftest import shared_data
from seqslam_oracle import (
    oracle_difference,
    oracle_enhance,
    oracle_openseqslam_descriptors,
    oracle_seqslam,
)

from torchseq.demo import make_demo
from torchseq.metrics import evaluate
from torchseq.preprocess import grey_openseqslam, preprocess_openseqslam
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig, search, velocities
from torchseq.seqslam import difference as difference_module
from torchseq.seqslam.difference import (
    _int_matmul,
    difference_with_kernel,
    int_mm_supported,
    thermometer_levels,
    thermometer_product,
)


def flat_block_route(rng, n_ref, n_query, colour=False):
    """uint8 frames (T, 32, 64[, 3]) along a route with a saturated sky (rows 0-7 at 255,
    flat 8x8 blocks) and flat grey boards; the query revisits it brighter and noisier."""
    world_w = n_ref * 2 + 64
    shape = (32, world_w, 3) if colour else (32, world_w)
    world = rng.integers(0, 200, shape).astype(np.float64)
    world[:8] = 255  # sky: flat in both traverses (saturated)
    for x0 in range(16, world_w - 16, 40):  # flat boards, 8x8-aligned in the reference
        world[16:24, x0:x0 + 16] = 90
    ref = np.stack([world[:, 2 * i:2 * i + 64] for i in range(n_ref)])
    pos = np.minimum(np.arange(n_query), n_ref - 1)
    query = np.clip(ref[pos] * 1.3 + rng.normal(0, 6, ref[pos].shape), 0, 255)
    query[:, :8] = 255
    return np.round(ref).astype(np.uint8), np.round(query).astype(np.uint8)


def test_preset_fields():
    c = SeqSLAMConfig.openseqslam()
    assert (c.image_size, c.patch_size, c.ds, c.vmin, c.vmax, c.enhance_window, c.rwindow) == \
        ((32, 64), 8, 10, 0.8, 1.2, 10, 10)
    assert c.preprocessing == "openseqslam" and c.match_rule == "start" and not c.edges
    assert SeqSLAMConfig.openseqslam(ds=20).ds == 20
    e = SeqSLAMConfig.events(0.66)  # ds: 100 reference windows = 100 / 0.66 query frames
    assert e.ds == 152 and e.image_size == (16, 16) and e.match_rule == "trajectory"
    assert e.velocity_range == pytest.approx((0.66 * 0.8, 0.66 * 1.2))
    assert SeqSLAMConfig.preset("default") == SeqSLAMConfig()
    with pytest.raises(ValueError, match="preset"):
        SeqSLAMConfig.preset("matlab")
    with pytest.raises(ValueError, match="preprocessing"):
        SeqSLAMConfig(preprocessing="octave").validate()
    with pytest.raises(ValueError, match="threads"):
        SeqSLAMConfig(threads=0).validate()


@pytest.mark.parametrize("colour", [False, True])
def test_openseqslam_descriptors_match_oracle_with_flat_blocks(colour):
    rng = np.random.default_rng(3)
    ref, _ = flat_block_route(rng, 6, 1, colour)
    got = preprocess_openseqslam(torch.from_numpy(ref), (32, 64), 8).double().numpy()
    want = oracle_openseqslam_descriptors(ref)
    np.testing.assert_array_equal(got, want)
    assert (got[:, :64] == 0).all()  # the flat sky blocks: OpenSeqSLAM stores NaN as 0
    default = SeqSLAM().descriptors(torch.from_numpy(ref)).numpy()
    assert (default[:, :64] == 127).all()  # torchseq's own rule (the default) keeps 127


def test_openseqslam_grey_is_matlab_rgb2gray_rounded():
    rgb = torch.tensor([[[[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 20, 30]]]],
                       dtype=torch.uint8)
    # 0.298936021293775 * 255 = 76.229 -> 76; 149.696 -> 150; 29.075 -> 29;
    # 2.989 + 11.741 + 3.421 = 18.151 -> 18
    assert grey_openseqslam(rgb).tolist() == [[[76.0, 150.0, 29.0, 18.0]]]
    assert grey_openseqslam(torch.tensor([[[0.5, 1.5, -3.0, 300.0]]])).tolist() == \
        [[[1.0, 2.0, 0.0, 255.0]]]


def test_openseqslam_descriptors_on_real_colour_frames():
    root = shared_data("corridor", "ref")
    files = sorted(root.glob("*.jpg"))[::20]
    rgb = np.stack([cv2.imread(str(f))[:, :, ::-1] for f in files])  # (T, 120, 160, 3)
    got = preprocess_openseqslam(torch.from_numpy(rgb.copy()), rgb.shape[1:3], 8)
    np.testing.assert_array_equal(got.double().numpy(), oracle_openseqslam_descriptors(rgb))


@pytest.mark.parametrize("colour", [False, True])
def test_openseqslam_preset_matches_oracle_end_to_end(colour):
    rng = np.random.default_rng(4)
    ref, query = flat_block_route(rng, 40, 30, colour)
    engine = SeqSLAM(SeqSLAMConfig.openseqslam())
    result = engine.match(torch.from_numpy(ref), torch.from_numpy(query))
    rd, qd = oracle_openseqslam_descriptors(ref), oracle_openseqslam_descriptors(query)
    assert (rd == 0).any() and (qd == 0).any()
    d = oracle_difference(rd, qd)
    np.testing.assert_array_equal(result.difference.double().numpy(), d)
    assert result.kernels["difference"] == "thermometer"  # 0 and 119..135: still int8
    e = oracle_enhance(d)
    match, best, uniq, ranked = oracle_seqslam(e)
    np.testing.assert_array_equal(result.matches.reference.numpy(), match)
    np.testing.assert_array_equal(result.ranked.numpy(), ranked)
    np.testing.assert_allclose(result.matches.score.double().numpy(), uniq, rtol=1e-4)


def test_difference_kernel_dispatch():
    rng = np.random.default_rng(5)
    x = torch.tensor(127 + np.round(rng.normal(0, 2.5, (20, 64))).clip(-8, 8))
    assert difference_with_kernel(x, x[:7])[1] == "thermometer"
    x0 = x.clone()
    x0[:3, :8] = 0  # flat blocks under OpenSeqSLAM's rule: gap 0 -> 119 (<= 127)
    thr, w = thermometer_levels(x0, x0)
    assert thr[0] == 0 and int(w[0]) == int(x0[x0 > 0].min())
    d, kernel = difference_with_kernel(x0, x0[5:])
    assert kernel == "thermometer"
    np.testing.assert_array_equal(d.numpy(), oracle_difference(x0.numpy(), x0[5:].numpy()))
    assert difference_with_kernel(x + 0.5, x)[1] == "cdist"  # not integer-valued
    far = x.clone()
    far[0, 0] = 127 + 200  # a gap above 127 does not fit the int8 weights
    assert difference_with_kernel(far, x)[1] == "cdist"
    assert difference_with_kernel(torch.full((4, 64), 127.0), x[:1] * 0 + 127)[1] == "constant"
    assert SeqSLAM().match_descriptors(x, x[:12]).kernels["difference"] == "thermometer"


@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"),
                    reason="the int8 kernel is checked on x86 CPUs, where it must be exact")
def test_int_mm_is_exact_on_x86_cpu():
    # torch._int_mm is private API: on x86 this must FAIL (not skip) if it stops giving
    # exact int32 results, so the thermometer kernel never silently goes wrong
    g = torch.Generator().manual_seed(0)
    a = torch.randint(-128, 128, (67, 4096), dtype=torch.int8, generator=g)
    b = torch.randint(-128, 128, (45, 4096), dtype=torch.int8, generator=g)
    a[0], b[0] = -128, -128  # the extreme: 4096 * 16384 = 2**26
    assert int_mm_supported(a, b)
    want = (a.to(torch.int64) @ b.to(torch.int64).T).to(torch.int32)
    got = torch._int_mm(a, b.T)
    assert got.dtype == torch.int32 and torch.equal(got, want)
    if thermometer_product("cpu") == "int8":  # the float32 form holds sums below 2**24 only
        assert torch.equal(_int_matmul(a, b), want)


@pytest.mark.parametrize("capability, product", [
    ("AVX512", "int8"), ("AVX512_BF16", "int8"), ("AVX2", "float32"), ("DEFAULT", "float32")])
def test_thermometer_product_dispatch(monkeypatch, capability, product):
    """The int8 GEMM runs only where it is fast (AVX-512); the float32 product elsewhere, and
    the engine reports which ran. Both give the same exact distances."""
    calls = []
    real_int_mm = torch._int_mm
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: capability)
    monkeypatch.setattr(torch, "_int_mm", lambda a, b: calls.append(1) or real_int_mm(a, b))
    assert thermometer_product("cpu") == product
    g = torch.Generator().manual_seed(3)
    x = 127 + torch.randint(-8, 9, (40, 64), generator=g).double()
    d, kernel = difference_with_kernel(x, x[:25])
    assert kernel == "thermometer" and bool(calls) == (product == "int8")
    want = (x[:, None, :] - x[None, :25, :]).abs().sum(-1)
    assert torch.equal(d.double(), want)
    result = SeqSLAM(SeqSLAMConfig.openseqslam(), device="cpu").match(
        torch.rand(30, 32, 64) * 255, torch.rand(24, 32, 64) * 255)
    assert result.kernels["difference"] == "thermometer"
    assert result.kernels["product"] == product


def test_int_matmul_float_fallback_is_exact(monkeypatch):
    g = torch.Generator().manual_seed(1)
    a = torch.randint(0, 2, (30, 2048), dtype=torch.int8, generator=g) * 119
    b = torch.randint(0, 2, (20, 2048), dtype=torch.int8, generator=g)
    want = (a.to(torch.int64) @ b.to(torch.int64).T).to(torch.int32)
    monkeypatch.setattr(difference_module, "int_mm_supported", lambda a, b: False)
    assert torch.equal(_int_matmul(a, b), want)


def test_worker_threads_give_identical_results():
    rng = np.random.default_rng(6)
    ref = torch.tensor(127 + np.round(rng.normal(0, 2.5, (300, 64))).clip(-8, 8))
    query = ref[np.minimum(np.arange(200), 299)] + torch.tensor(
        np.round(rng.normal(0, 1, (200, 64))))
    out = {}
    for threads in (1, 2, 3):
        cfg = SeqSLAMConfig(threads=threads, max_chunk_elements=2**13, edges=True)
        out[threads] = SeqSLAM(cfg).match_descriptors(ref, query)
        assert set(out[threads].kernels["threads"].values()) == {threads}
    for t in (2, 3):
        assert torch.equal(out[t].difference, out[1].difference)
        assert torch.equal(out[t].enhanced, out[1].enhanced)
        assert torch.equal(out[t].matches.reference, out[1].matches.reference)
        assert torch.equal(out[t].ranked, out[1].ranked)
    assert torch.get_num_threads() >= 1  # the intra-op count is restored after the stages


CASES = [  # (R, Q, speed, config overrides)
    (40, 30, 1.0, {}),
    (25, 60, 0.4, dict(ds=8, vmin=0.3, vmax=0.6)),
    (60, 24, 2.0, dict(ds=6, speed_ratio=2.0)),  # trajectory rule
    (12, 40, 0.3, dict(ds=12, vmin=0.5, vmax=1.5)),  # trajectories running off the end
    (20, 13, 1.0, {}),  # Q = ds + 3: queries 3 .. 9 have no whole edge window
]


@pytest.mark.parametrize("case", range(len(CASES)))
def test_edge_matching_matches_oracle(case):
    n_ref, n_query, speed, over = CASES[case]
    rng = np.random.default_rng(20 + case)
    ref = 127 + np.clip(np.round(rng.normal(0, 2.5, (n_ref, 48))), -8, 8)
    pos = np.minimum(np.round(np.arange(n_query) * speed).astype(int), n_ref - 1)
    query = np.clip(ref[pos] + np.round(rng.normal(0, 1.5, (n_query, 48))), 119, 135)
    cfg = SeqSLAMConfig(edges=True, top_k=5, **over)
    result = SeqSLAM(cfg).match_descriptors(torch.tensor(ref), torch.tensor(query))
    e = oracle_enhance(oracle_difference(ref, query))
    vmin, vmax = cfg.velocity_range
    match, best, uniq, ranked = oracle_seqslam(e, cfg.ds, vmin, vmax, cfg.rwindow, cfg.top_k,
                                               cfg.match_rule, edges=True)
    np.testing.assert_array_equal(result.matches.reference.numpy(), match)
    np.testing.assert_array_equal(result.ranked.numpy(), ranked)
    np.testing.assert_allclose(result.best_score.numpy(), best, rtol=1e-10)
    np.testing.assert_allclose(result.matches.score.numpy(), uniq, rtol=1e-10)
    half = cfg.sequence_length // 2
    edge = np.r_[0:half, n_query - half:n_query]
    assert np.isfinite(best[edge]).any()  # the edges are scored


def test_edge_matching_on_the_demo():
    demo = make_demo()
    base = SeqSLAM().match(demo.reference, demo.query)
    edged = SeqSLAM(SeqSLAMConfig(edges=True)).match(demo.reference, demo.query)
    inner = slice(5, len(demo.query) - 5)
    assert torch.equal(base.matches.reference[inner], edged.matches.reference[inner])
    assert (base.matches.reference[:5] == -1).all() and (edged.matches.reference >= 0).all()
    m_base = evaluate(base.matches, demo.ground_truth)
    m_edge = evaluate(edged.matches, demo.ground_truth)
    # measured: recall@1 0.952 -> 0.992 (the 10 edge queries all correct)
    assert m_edge["recall_at_1"] >= m_base["recall_at_1"] + 0.03


def test_search_edges_off_leaves_edges_unmatched():
    e = torch.rand(30, 25, dtype=torch.float64)
    match, best, _, _ = search(e, 10, velocities(10), edges=False)
    assert (match[:5] == -1).all() and torch.isnan(best[-5:]).all()


def test_default_threads_leave_busy_cores_alone(monkeypatch, tmp_path):
    from torchseq.seqslam import _parallel

    monkeypatch.setattr(_parallel, "cpu_count", lambda: 2)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    fake = tmp_path / "loadavg"
    for running, want in ((1, 2), (2, 1), (5, 1)):  # this process alone, +1 busy, +4 busy
        fake.write_text(f"0.50 0.40 0.30 {running}/300 12345\n")
        monkeypatch.setattr(_parallel, "LOADAVG", str(fake))
        assert _parallel.resolve_threads(None) == want
    assert _parallel.resolve_threads(3) == 3  # explicit: as given
    monkeypatch.setattr(_parallel, "LOADAVG", str(tmp_path / "absent"))
    assert _parallel.resolve_threads(None) == 2


def test_eval_preset_flag(tmp_path, capsys):
    import importlib.util
    import json
    import sys
    from pathlib import Path

    from torchseq.cli.runs import run_main

    path = Path(__file__).resolve().parents[1] / "eval.py"
    spec = importlib.util.spec_from_file_location("eval_preset_script", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    out = tmp_path / "out"
    args = ["--engine", "seqslam", "--demo-frames", "60", "--preset", "openseqslam", "--ds",
            "12", "--no-tensorboard", "--no-progress", "--out", str(out)]
    assert run_main(module.main, "eval.py", args) == 0
    params = json.loads((out / "metrics.json").read_text())["seqslam"]["parameters"]
    assert params["preprocessing"] == "openseqslam" and params["ds"] == 12  # flag overrides
    assert params["match_at"] == "start" and params["edges"] is False
    code = run_main(module.main, "eval.py", ["--preset", "matlab", "--engine", "seqslam",
                                             "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "preset must be one of" in err[0]


@pytest.mark.parametrize("over", [
    {},
    dict(edges=True, ds=6, speed_ratio=1.0),
    dict(metric="l2", edges=True),
    dict(preprocessing="openseqslam", top_k=3),
])
def test_banded_path_matches_oracle_and_full_path(over):
    # bands of a few query columns (tiny budget): no full matrix is ever built
    rng = np.random.default_rng(30)
    ref = 127 + np.clip(np.round(rng.normal(0, 2.5, (45, 48))), -8, 8)
    pos = np.minimum(np.arange(38), 44)
    query = np.clip(ref[pos] + np.round(rng.normal(0, 1.5, (38, 48))), 119, 135)
    ref[:3, :8] = query[:2, :8] = 0  # flat blocks under OpenSeqSLAM's rule
    cfg = SeqSLAMConfig(**{"keep_matrices": False, "max_chunk_elements": 2**11, **over})
    banded = SeqSLAM(cfg).match_descriptors(torch.tensor(ref), torch.tensor(query))
    assert banded.kernels["matrices"] == "banded" and banded.difference is None
    assert banded.kernels["difference"] == ("thermometer" if cfg.metric == "l1" else "l2")
    full = SeqSLAM(SeqSLAMConfig(**{**over, "keep_matrices": True})).match_descriptors(
        torch.tensor(ref), torch.tensor(query))
    assert full.kernels["matrices"] == "full"
    e = oracle_enhance(oracle_difference(ref, query, cfg.metric))
    vmin, vmax = cfg.velocity_range
    want = oracle_seqslam(e, cfg.ds, vmin, vmax, cfg.rwindow, cfg.top_k, cfg.match_rule,
                          edges=cfg.edges)
    for got in (banded, full):
        np.testing.assert_array_equal(got.matches.reference.numpy(), want[0])
        np.testing.assert_array_equal(got.ranked.numpy(), want[3])
        np.testing.assert_allclose(got.best_score.numpy(), want[1], rtol=1e-9)
        np.testing.assert_allclose(got.matches.score.numpy(), want[2], rtol=1e-9)
    torch.testing.assert_close(banded.preview, full.preview)
    assert full.preview.shape == (45, 38)  # below 1024 a side: the matrix itself
    torch.testing.assert_close(full.preview, full.enhanced.float())
