"""Event-driven input of the spiking model: pooling, the linear z-score stand-in, the NIR graph's
input stage, snnTorch / Norse on event windows, nir 1.0.4, and bad input."""

import math
from functools import lru_cache

import numpy as np
import pytest
import torch
from conftest import coarse_units_expected, shared_data

from torchseq.demo import make_demo
from torchseq.events import simulate_run
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.neural.spiking import SpikingConfig, SpikingError
from torchseq.neural.spiking_events import (
    EventSpikingSeqSLAM,
    count_frames,
    pool_matrix,
)
from torchseq.preprocess import resize


def windows_between_frames(frames, fps=10.0):
    """Simulated events (one camera over the whole sequence), one window per frame interval."""
    run = simulate_run(frames, np.arange(len(frames)), 1.0, fps)
    return run.windows(len(frames) - 1, int(1e6 / fps))


def test_run_windows_bin_every_event_by_its_time():
    demo = make_demo(n_reference=12, size=(24, 32), seed=1)
    run = simulate_run(demo.reference, np.arange(12), 1.0, 10.0)
    got = run.windows(11, 100_000)
    ev = run.stream.events
    want = np.zeros((11, 2, 24, 32))
    k = np.minimum(ev["t"] // 100_000, 10)  # a crossing on the last frame's time: last window
    np.add.at(want, (k, ev["p"].astype(np.int64), ev["y"], ev["x"]), 1)
    assert len(ev) > 1000 and got.sum() == len(ev)
    np.testing.assert_array_equal(got.numpy(), want)
    # hand-made: an event on the last frame's time (t = 200 ms of 2 windows) joins window 1
    from torchseq.events import EventRun, EventStream, make_events

    made = EventRun(EventStream(make_events(np.array([0, 150_000, 200_000]), np.array([0, 1, 2]),
                                            np.array([0, 0, 1]), np.array([1, 0, 1])), (3, 2)),
                    1.0, 10.0)
    w = made.windows(2, 100_000)
    assert w.shape == (2, 2, 2, 3) and w.sum() == 3
    assert w[0, 1, 0, 0] == 1 and w[1, 0, 0, 1] == 1 and w[1, 1, 1, 2] == 1


@lru_cache(maxsize=None)
def tiny_events(scale="global"):
    """A tiny model fitted on the count frames of simulated event windows of a demo route."""
    demo = make_demo(n_reference=40, size=(48, 64), seed=3)
    ref = windows_between_frames(demo.reference)  # (39, 2, 48, 64)
    qry = windows_between_frames(demo.query)
    model = NeuralSeqSLAM(NeuralConfig(
        unit_search="off", input_size=(8, 12), hidden=96, n_output=20))
    with coarse_units_expected(), pytest.warns(UserWarning):  # a tiny model: coarse units
        model.fit(count_frames(ref), log=False)
    sp = EventSpikingSeqSLAM.convert_events(model, ref, SpikingConfig(levels=6), scale=scale)
    return model, ref, qry, sp


# ------------------------------------------------------------------ the input stage's maths
@pytest.mark.parametrize("sensor,size", [((48, 64), (8, 12)), ((80, 80), (24, 32)),
                                         ((32, 64), (16, 32)), ((7, 9), (7, 9))])
def test_pool_over_cells_is_the_rate_models_resize(sensor, size):
    """Sum pooling / cell pixels == torch's adaptive average pooling (the rate model's resize)."""
    pool, cells = pool_matrix(sensor, size)
    g = torch.Generator().manual_seed(0)
    counts = torch.randint(0, 5, (3, 2, *sensor), generator=g).float()
    ours = (counts.reshape(3, -1).double() @ pool.double().T) / cells
    theirs = resize(count_frames(counts).double(), size).reshape(3, -1)
    torch.testing.assert_close(ours, theirs, rtol=1e-12, atol=1e-12)
    assert set(pool.unique().tolist()) <= {0.0, 1.0}


def standin_loop(counts: np.ndarray, size, patch, scales):
    """The stand-in written as loops: pool both polarities over adaptive windows, average,
    subtract each block's mean, multiply by the block's scale (row-major ``(h, w)``)."""
    _, big_h, big_w = counts.shape
    h, w = size
    img = np.zeros((h, w))
    for i in range(h):
        r0, r1 = math.floor(i * big_h / h), math.ceil((i + 1) * big_h / h)
        for j in range(w):
            c0, c1 = math.floor(j * big_w / w), math.ceil((j + 1) * big_w / w)
            img[i, j] = counts[:, r0:r1, c0:c1].sum() / ((r1 - r0) * (c1 - c0))
    out = np.zeros((h, w))
    b = 0
    for bi in range(0, h, patch):
        for bj in range(0, w, patch):
            block = img[bi:bi + patch, bj:bj + patch]
            out[bi:bi + patch, bj:bj + patch] = (block - block.mean()) * scales[b]
            b += 1
    return out.reshape(-1)


def block_std_median_loop(counts: np.ndarray, size, patch, scale):
    """1 / median of the blocks' sample std: per block over windows ("patch") or over all
    blocks of all windows, flat ones left out ("global"); loops, NumPy's std."""
    h, w = size
    frames = []
    for c in counts:
        img = np.zeros((h, w))
        big_h, big_w = c.shape[1:]
        for i in range(h):
            r0, r1 = math.floor(i * big_h / h), math.ceil((i + 1) * big_h / h)
            for j in range(w):
                c0, c1 = math.floor(j * big_w / w), math.ceil((j + 1) * big_w / w)
                img[i, j] = c[:, r0:r1, c0:c1].sum() / ((r1 - r0) * (c1 - c0))
        frames.append(img)
    stds = []  # per block: its std in every window
    for bi in range(0, h, patch):
        for bj in range(0, w, patch):
            stds.append([np.std(f[bi:bi + patch, bj:bj + patch], ddof=1) for f in frames])

    def lower_median(v):  # torch's median of an even count is the lower middle value
        return np.sort(v)[(len(v) - 1) // 2]

    if scale == "global":
        live = [v for block in stds for v in block if v > 0]
        return np.full(len(stds), 1.0 / lower_median(live))
    return np.array([1.0 / lower_median(block) for block in stds])


class TestStandIn:
    @pytest.mark.parametrize("scale", ["global", "patch"])
    def test_block_scales_are_the_reference_median_std(self, scale):
        model, ref, qry, sp = tiny_events(scale)
        want = block_std_median_loop(ref.double().numpy(), (8, 12), 4, scale)
        got = np.array(sp.calibration["event_input"]["block_scales"])
        assert sp.calibration["event_input"]["scale"] == scale
        np.testing.assert_allclose(got, want, rtol=1e-9)
        assert (scale == "global") == (len(set(got.tolist())) == 1)

    @pytest.mark.parametrize("scale", ["global", "patch"])
    def test_folded_l1_is_w1_over_theta2_times_the_loop_standin(self, scale):
        model, ref, qry, sp = tiny_events(scale)
        scales = np.array(sp.calibration["event_input"]["block_scales"])
        w1 = model.l1.folded_weight().double().numpy() / sp.calibration["theta2"]
        for t in (0, 7, 20):
            x = qry[t].double().numpy()
            want = w1 @ standin_loop(x, (8, 12), 4, scales)
            pooled = qry[t].reshape(1, -1) @ sp.pool.T
            got = (pooled.double() @ sp.w1.double().T)[0].numpy()
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)

    def test_centring_is_the_z_score_times_each_blocks_std(self):
        """The stand-in differs from the patch z-score only by the per-block scale."""
        from torchseq.preprocess import patch_normalise

        model, ref, qry, sp = tiny_events()
        x = qry[10].double().numpy()
        ones = np.ones(6)
        centred = standin_loop(x, (8, 12), 4, ones).reshape(8, 12)
        img = resize(count_frames(qry[10:11]).double(), (8, 12))
        z = patch_normalise(img, 4, "zscore")[0].numpy()
        for bi in range(0, 8, 4):
            for bj in range(0, 12, 4):
                std = np.std(img[0, bi:bi + 4, bj:bj + 4].numpy(), ddof=1)
                np.testing.assert_allclose(centred[bi:bi + 4, bj:bj + 4],
                                           z[bi:bi + 4, bj:bj + 4] * std, atol=1e-9)

    def test_about_k_l2_units_fire_on_the_reference_windows(self):
        model, ref, qry, sp = tiny_events()
        run = sp.run(ref)
        med = float(run["l2_spikes"].median())
        assert abs(med - model.config.k) <= 1, (med, model.config.k)

    def test_run_reports_the_windows_events_and_their_synapses(self):
        model, ref, qry, sp = tiny_events()
        run = sp.run(qry[:5])
        torch.testing.assert_close(run["input_events"], qry[:5].sum((1, 2, 3)))
        # each event reaches the pool cells of its pixel; every l1 synapse carries the pool
        fan = (sp.pool != 0).sum(0).float()
        want = qry[:5].reshape(5, -1) @ fan + float((sp.w1 != 0).sum())
        torch.testing.assert_close(run["chip_ops"]["input"], want)

    def test_batched_windows_equal_single_streams(self):
        model, ref, qry, sp = tiny_events()
        both = torch.stack([qry[:12], qry[12:24]], 1)  # (T, 2 streams, 2, H, W)
        state, rings = None, []
        for t in range(12):
            step, state = sp(both[t], state)
            rings.append(step.ring_spikes)
        got = torch.stack(rings)
        for b, part in enumerate((qry[:12], qry[12:24])):
            alone = sp.run(part, raster=True)["raster"]
            torch.testing.assert_close(got[:, b], alone, rtol=0, atol=0)


# ------------------------------------------------------------------ bad input
class TestBadInput:
    def test_bad_counts_raise_spiking_error(self):
        model, ref, qry, sp = tiny_events()
        x = qry[:2].clone()
        with pytest.raises(SpikingError, match=r"\(B, 2, 48, 64\) for the 48x64 sensor"):
            sp(torch.zeros(1, 2, 40, 64))
        with pytest.raises(SpikingError, match=r"\(B, 2, 48, 64\)"):
            sp(torch.zeros(1, 3, 48, 64))
        for bad, msg in ((float("nan"), "NaN"), (float("inf"), "NaN or infinite"),
                         (-1.0, ">= 0"), (0.5, "whole numbers")):
            y = x.clone()
            y[0, 1, 3, 4] = bad
            with pytest.raises(SpikingError, match=msg):
                sp(y)
            with pytest.raises(SpikingError, match=msg):
                sp.run(y)
        with pytest.raises(SpikingError, match="empty"):
            sp(torch.zeros(0, 2, 48, 64))
        with pytest.raises(SpikingError, match="must be a tensor"):
            sp.encode(np.zeros((1, 2, 48, 64)))

    def test_bad_conversions_raise_spiking_error(self):
        model, ref, qry, sp = tiny_events()
        with pytest.raises(SpikingError, match=r"a 720x1280 sensor .* downsample"):
            pool_matrix((720, 1280), (24, 32))  # a Prophesee HD sensor: 1.4 G weights
        with pytest.raises(SpikingError, match="smaller than the model's input"):
            EventSpikingSeqSLAM.convert_events(model, ref[:, :, :6, :6])
        with pytest.raises(SpikingError, match=r"\(R, 2, H, W\)"):
            EventSpikingSeqSLAM.convert_events(model, count_frames(ref))
        with pytest.raises(SpikingError, match=r"\(R, 2, H, W\)"):
            EventSpikingSeqSLAM.convert_events(model, ref[:1])
        with pytest.raises(SpikingError, match="no events"):
            EventSpikingSeqSLAM.convert_events(model, torch.zeros_like(ref))
        bad = ref.clone()
        bad[3, 0, 0, 0] = -2
        with pytest.raises(SpikingError, match=">= 0"):
            EventSpikingSeqSLAM.convert_events(model, bad)
        with pytest.raises(SpikingError, match="scale must be one of"):
            EventSpikingSeqSLAM.convert_events(model, ref, scale="std")
        with pytest.raises(SpikingError, match="event input is spikes already"):
            EventSpikingSeqSLAM.convert_events(model, ref, SpikingConfig(input_threshold=0.5))
        with pytest.raises(SpikingError, match="weight_bits must be None or an int"):
            EventSpikingSeqSLAM.convert_events(model, ref, SpikingConfig(weight_bits=1))
        unfitted = NeuralSeqSLAM(NeuralConfig(unit_search="off", input_size=(8, 12),
                                              hidden=96, n_output=20))
        with pytest.raises(SpikingError, match="has not learnt a route"):
            EventSpikingSeqSLAM.convert_events(unfitted, ref)

    def test_seqslam_patch_mode_is_refused(self):
        model, ref, qry, sp = tiny_events()
        other = NeuralSeqSLAM(NeuralConfig(unit_search="off", input_size=(8, 12), hidden=96,
                                           n_output=20, patch_mode="seqslam"))
        with coarse_units_expected(), pytest.warns(UserWarning):
            other.fit(count_frames(ref), log=False)
        with pytest.raises(SpikingError, match="patch_mode='zscore'"):
            EventSpikingSeqSLAM.convert_events(other, ref)


# ------------------------------------------------------------------ NIR
nir = pytest.importorskip("nir", reason="the 'nir' package is absent: pip install 'torchseq[nir]'")

from spiking_helpers import nir_reference_run  # noqa: E402

from torchseq.export.nir_export import read_nir, write_nir  # noqa: E402
from torchseq.neural.spiking import DT  # noqa: E402


@pytest.fixture(scope="module")
def event_file(tmp_path_factory):
    model, ref, qry, sp = tiny_events()
    path = tmp_path_factory.mktemp("nirev") / "events.nir"
    graph = write_nir(sp, path)
    return sp, qry, graph, path


class TestGraph:
    def test_input_stage_nodes_edges_and_sensor(self, event_file):
        sp, qry, graph, path = event_file
        back = read_nir(path)
        n = back.nodes
        assert int(np.prod(n["input"].output_type["output"])) == 2 * 48 * 64
        assert isinstance(n["pool"], nir.Linear) and n["pool"].weight.shape == (96, 2 * 48 * 64)
        np.testing.assert_array_equal(n["pool"].weight, sp.pool.numpy())
        np.testing.assert_array_equal(n["l1"].weight, sp.w1.numpy())
        assert ("input", "pool") in back.edges and ("pool", "l1") in back.edges
        assert ("input", "l1") not in back.edges
        np.testing.assert_array_equal(back.metadata["sensor"], [48, 64])
        assert str(back.metadata["input"]).startswith("spikes: event counts")

    def test_nir_semantics_reproduce_the_event_model(self, event_file):
        sp, qry, graph, path = event_file
        x = sp.encode(qry)
        ours = sp.run(qry, raster=True)["raster"].numpy()
        ref = nir_reference_run(read_nir(path), x.numpy(), DT)
        assert ours.sum() > 0
        np.testing.assert_array_equal(ref, ours)

    def test_budget_reads_the_event_graph_as_spike_input(self, event_file):
        from torchseq.export.hardware_budget import budget

        sp, qry, graph, path = event_file
        b = budget(graph)
        assert b["input_kind"] == "spikes" and b["inputs"] == 2 * 48 * 64
        assert b["neurons"] == 96 + sp.n_units * sp.levels


@lru_cache(maxsize=None)
def tiny_events_at(bits: int):
    """:func:`tiny_events`' model converted with ``bits``-bit weights."""
    model, ref, qry, _ = tiny_events()
    return EventSpikingSeqSLAM.convert_events(model, ref, SpikingConfig(levels=6,
                                                                        weight_bits=bits))


@pytest.fixture(scope="module")
def quantised_files(tmp_path_factory):
    out = {}
    for bits in (8, 4):
        sp = tiny_events_at(bits)
        path = tmp_path_factory.mktemp(f"nirev{bits}") / "events.nir"
        write_nir(sp, path)
        out[bits] = sp, path
    return out


class TestChipPrecision:
    """Event input with weights at a chip's precision (``SpikingConfig(weight_bits=b)``)."""

    @pytest.mark.parametrize("bits", [8, 4])
    def test_every_graph_weight_sits_on_its_bit_grid(self, quantised_files, bits):
        from torchseq.export.hardware_budget import budget, pow2_rows

        sp, path = quantised_files[bits]
        back = read_nir(path)
        n, qmax = back.nodes, 2 ** (bits - 1) - 1
        for node in ("l3", "levels", "shift"):
            assert pow2_rows(n[node].weight, qmax), node
        # the pool is 0/1; l1 holds the quantised fold over theta2: integers |q| <= qmax
        # times one power of two per row, once multiplied back by theta2 (a plain loop)
        assert set(np.unique(n["pool"].weight).tolist()) == {0.0, 1.0}
        w = n["l1"].weight.astype(np.float64) * sp.calibration["theta2"]
        for row in w:
            e = np.ceil(np.log2(np.abs(row).max() / qmax) - 1e-6)  # float32 / theta2 slack
            q = row / 2.0 ** e
            assert np.abs(q).max() <= qmax + 1e-4 and np.abs(q - np.rint(q)).max() < 1e-4
        assert int(back.metadata["weight_bits"]) == bits and budget(back)["weight_bits"] == bits
        assert "pool (event input) holds 0/1" in str(back.metadata["quantisation"])

    @pytest.mark.parametrize("bits", [8, 4])
    def test_l2_threshold_sits_between_attainable_sums(self, bits):
        """theta2 is mid-cell of the sums' grid: no window's L1 sum comes near it."""
        model, ref, qry, _ = tiny_events()
        sp = tiny_events_at(bits)
        grid = sp.calibration["l1_grid"]
        assert grid is not None
        theta2 = sp.calibration["theta2"]
        for x in (ref, qry):
            pooled = sp.encode(x).double() @ sp.pool.double().T
            h = pooled @ (sp.w1.double() * theta2).T  # the quantised fold's sums
            assert np.abs(h - theta2).min().item() > 0.45 * grid

    def test_eight_bits_keep_most_decisions_of_the_float_model(self):
        model, ref, qry, sp = tiny_events()
        ours = tiny_events_at(8).run(qry)["reference"]
        assert float((ours == sp.run(qry)["reference"]).float().mean()) >= 0.8

    @pytest.mark.parametrize("bits", [8, 4])
    def test_nir_semantics_reproduce_the_quantised_event_model(self, quantised_files, bits):
        sp, path = quantised_files[bits]
        qry = tiny_events()[2]
        ours = sp.run(qry, raster=True)["raster"].numpy()
        assert ours.sum() > 0
        np.testing.assert_array_equal(nir_reference_run(read_nir(path), sp.encode(qry).numpy(),
                                                        DT), ours)

    @pytest.mark.parametrize("name", ["snntorch", "norse"])
    @pytest.mark.parametrize("bits", [8, pytest.param(4, marks=pytest.mark.slow)])
    def test_consumer_runs_quantised_event_windows_spike_for_spike(self, quantised_files,
                                                                   name, bits):
        from torchseq.export.nir_consumers import available, compare

        if available()[name] is not None:
            pytest.skip(available()[name])
        sp, path = quantised_files[bits]
        qry = tiny_events()[2]
        rep = compare(sp, path, sp.encode(qry), consumers=(name,), segment=8)[name]
        assert rep["spike_agreement"] == 1.0 and rep["agreement"] == 1.0, rep


@pytest.mark.parametrize("name", ["snntorch", "norse"])
def test_consumer_runs_event_windows_spike_for_spike(name, event_file):
    from torchseq.export.nir_consumers import available, compare

    if available()[name] is not None:
        pytest.skip(available()[name])
    sp, qry, graph, path = event_file
    for segment in (None, 8):
        rep = compare(sp, path, sp.encode(qry), consumers=(name,), segment=segment)[name]
        assert rep["spike_agreement"] == 1.0 and rep["agreement"] == 1.0, rep


@pytest.mark.slow
def test_nir_104_reads_the_event_graph(event_file, tmp_path_factory):
    import subprocess

    from spiking_helpers import NIR104_SCRIPT, nir104_python

    sp, qry, graph, path = event_file
    py = nir104_python(tmp_path_factory)
    out = tmp_path_factory.mktemp("nir104ev") / "read.npz"
    run = subprocess.run([py, "-c", NIR104_SCRIPT, str(out), str(path)], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    theirs = np.load(out)
    ours = read_nir(path)
    for node_name, node in ours.nodes.items():
        assert str(theirs[f"0/{node_name}/type"]) == type(node).__name__
        for field, value in vars(node).items():
            if isinstance(value, np.ndarray) and field != "v_reset":
                np.testing.assert_array_equal(theirs[f"0/{node_name}/{field}"], value)
    assert theirs["0/edges"].tolist() == sorted(map(list, ours.edges))


@pytest.mark.slow
@pytest.mark.parametrize("bits", [None, 8])
@pytest.mark.parametrize("name", ["snntorch", "norse"])
def test_consumer_agrees_on_lens_event_windows(name, bits, tmp_path):
    """LENS frames as event windows (each pixel the window's count, polarity unknown: ON)."""
    from torchseq.export.nir_consumers import available, compare
    from torchseq.sources import load_traverse

    if available()[name] is not None:
        pytest.skip(available()[name])
    root = shared_data("lens-davis128")
    ref = load_traverse(root / "example-reference", progress=False).float()
    qry = load_traverse(root / "example-query", progress=False).float()
    as_events = lambda f: torch.stack([torch.zeros_like(f), f], 1)  # noqa: E731
    model = NeuralSeqSLAM(NeuralConfig(unit_search="off"))
    model.fit(ref, log=False)
    sp = EventSpikingSeqSLAM.convert_events(model, as_events(ref),
                                            SpikingConfig(weight_bits=bits))
    path = tmp_path / "lens.nir"
    write_nir(sp, path)
    rep = compare(sp, path, sp.encode(as_events(qry)), consumers=(name,), segment=16)[name]
    assert rep["agreement"] == 1.0 and rep["spike_agreement"] == 1.0, rep["differing_frames"]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["snntorch", "norse"])
def test_consumer_agrees_on_a_dvs128_recording(name, tmp_path):
    """Real camera events: the DVS128 recording in 100 ms windows (no second traverse, so no
    recall: the first 34 windows are the reference, the other 35 the query)."""
    from torchseq.events import accumulate, read_events
    from torchseq.export.nir_consumers import available, compare

    if available()[name] is not None:
        pytest.skip(available()[name])
    stream = read_events(shared_data("events", "alex_walking_again.aedat"))
    windows = accumulate(stream, window_us=100_000, mode="two_channel")  # (69, 2, 128, 128)
    ref, qry = windows[:34], windows[34:]
    model = NeuralSeqSLAM(NeuralConfig())
    model.fit(count_frames(ref), log=False)
    sp = EventSpikingSeqSLAM.convert_events(model, ref)
    path = tmp_path / "dvs128.nir"
    graph = write_nir(sp, path)
    np.testing.assert_array_equal(graph.metadata["sensor"], [128, 128])
    rep = compare(sp, path, sp.encode(qry), consumers=(name,), segment=16)[name]
    assert rep["agreement"] == 1.0 and rep["spike_agreement"] == 1.0, rep["differing_frames"]
