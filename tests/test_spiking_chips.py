"""The spiking model at a chip's precision and input: quantised weights, ON/OFF event input,
and the hardware budget against the chips' published limits (CHIPS)."""

from functools import lru_cache

import numpy as np
import pytest
import torch
from spiking_helpers import NIR104_SCRIPT, nir104_python, nir_reference_run, tiny

from torchseq.neural.spiking import (
    SpikingConfig,
    SpikingError,
    SpikingSeqSLAM,
    input_events,
    quantise_rows,
)

nir = pytest.importorskip("nir", reason="the 'nir' package is absent: pip install 'torchseq[nir]'")

from torchseq.export.hardware_budget import (  # noqa: E402
    CHIPS,
    LIMITS,
    budget,
    check,
    layer_kernel_entries,
    pow2_rows,
    speck_layers,
)
from torchseq.export.nir_export import read_nir, write_nir  # noqa: E402
from torchseq.neural.spiking import DT  # noqa: E402

VARIANTS = {"float": SpikingConfig(levels=6),
            "8-bit": SpikingConfig(levels=6, weight_bits=8),
            "4-bit": SpikingConfig(levels=6, weight_bits=4),
            "8-bit events": SpikingConfig(levels=6, weight_bits=8, input_threshold=0.5)}


@lru_cache(maxsize=None)
def variant(name):
    model, demo, _ = tiny()
    return model, demo, SpikingSeqSLAM.convert(model, demo.reference, VARIANTS[name])


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    out = {}
    for name in VARIANTS:
        sp = variant(name)[2]
        path = tmp_path_factory.mktemp("chips") / f"{name.replace(' ', '_')}.nir"
        out[name] = (sp, write_nir(sp, path), path)
    return out


def test_input_events_are_on_then_off():
    x = torch.tensor([[0.6, -0.6, 0.5, -0.5, 0.0]])
    np.testing.assert_array_equal(input_events(x, 0.5).numpy(),
                                  [[1, 0, 0, 0, 0, 0, 1, 0, 0, 0]])


def test_quantise_rows_keeps_the_rate_models_l1_integers():
    # the rate model's L1 weights are n * 2**e with |n| <= 64: 8 bits hold them exactly
    model = tiny()[0]
    w1 = model.l1.folded_weight()
    assert torch.equal(quantise_rows(w1, 8), w1)
    assert not torch.equal(quantise_rows(w1, 4), w1)
    assert quantise_rows(w1, None) is w1


@pytest.mark.parametrize("name,bits", [("8-bit", 8), ("4-bit", 4), ("8-bit events", 8)])
def test_every_graph_weight_sits_on_its_bit_grid(files, name, bits):
    sp, graph, path = files[name]
    back = read_nir(path)
    qmax = 2 ** (bits - 1) - 1
    n = back.nodes
    for node in ("l3", "levels", "shift"):
        assert pow2_rows(n[node].weight, qmax), node
    # l1: the quantised folded weights over the L2 threshold (folded into the weights):
    # integers |q| <= qmax times 2**e / theta2 per row, up to float32 rounding of the division
    a = np.abs(n["l1"].weight.astype(np.float64)) * sp.calibration["theta2"]
    scale = np.exp2(np.ceil(np.log2(a.max(axis=1, keepdims=True) / qmax)))
    q = a / scale
    assert q.max() <= qmax + 1e-4 and np.abs(q - np.rint(q)).max() < 1e-4
    assert int(back.metadata["weight_bits"]) == bits
    assert f"{bits}-bit" in str(back.metadata["quantisation"])
    assert budget(back)["weight_bits"] == bits


def test_float_graph_says_float(files):
    sp, graph, path = files["float"]
    back = read_nir(path)
    assert int(back.metadata["weight_bits"]) == 0 and budget(back)["weight_bits"] is None
    assert not pow2_rows(back.nodes["l3"].weight, 127)  # the centred L3 is not on a grid


def test_shift_kernel_is_chosen_by_the_config(files):
    assert files["float"][0].shift_kernel == "factored"
    assert files["8-bit"][0].shift_kernel == "dense"
    assert files["8-bit"][0].shift_dense.shape == (files["8-bit"][0].n_units,
                                                   files["8-bit"][0].sizes["ring"])


@pytest.mark.parametrize("name", list(VARIANTS))
def test_nir_semantics_reproduce_each_variant(files, name):
    sp, graph, path = files[name]
    demo = variant(name)[1]
    x = sp.encode(demo.query)
    ours = sp.run(x, encoded=True, raster=True)["raster"].numpy()
    ref = nir_reference_run(read_nir(path), x.numpy(), DT)
    assert ours.sum() > 0
    np.testing.assert_array_equal(ref, ours)


def test_event_input_is_two_channels_per_pixel(files):
    sp, graph, path = files["8-bit events"]
    demo = variant("8-bit events")[1]
    model = variant("8-bit events")[0]
    x = sp.encode(demo.query[:3])
    d = model.encode(demo.query[:3]).shape[1]
    assert x.shape == (3, 2 * d) and set(np.unique(x.numpy())) <= {0.0, 1.0}
    assert graph.nodes["l1"].weight.shape[1] == 2 * d
    assert str(read_nir(path).metadata["input"]).startswith("spikes")
    assert budget(graph)["input_kind"] == "spikes"
    # events drive only their own synapses
    out = sp.run(x, encoded=True)
    fan = (sp.w1 != 0).sum(0).float()
    np.testing.assert_allclose(out["chip_ops"]["input"].numpy(), (x @ fan).numpy())


@pytest.mark.parametrize("consumer", ["snntorch", "norse"])
@pytest.mark.parametrize("name", ["8-bit", "4-bit", "8-bit events"])
def test_consumers_agree_at_the_chips_precision(files, consumer, name):
    from torchseq.export.nir_consumers import available, compare

    if available()[consumer] is not None:
        pytest.skip(available()[consumer])
    sp, graph, path = files[name]
    demo = variant(name)[1]
    rep = compare(sp, path, sp.encode(demo.query), demo.ground_truth, consumers=(consumer,))
    assert rep[consumer]["agreement"] == 1.0 and rep[consumer]["spike_agreement"] == 1.0


def test_bad_settings_raise():
    for bad in (dict(weight_bits=1), dict(weight_bits=True), dict(weight_bits=8.0),
                dict(input_threshold=-1.0), dict(input_threshold=float("inf")),
                dict(input_threshold="0.5")):
        with pytest.raises(SpikingError):
            SpikingConfig(**bad).validate()


class TestChips:
    def test_every_figure_has_a_source(self):
        for name, chip in CHIPS.items():
            given = {k for k, v in vars(chip).items()
                     if k not in ("title", "sources", "estimates", "state_bits")
                     and v is not None and v != ()}
            assert given <= set(chip.sources), (name, given - set(chip.sources))
            assert set(chip.estimates) <= given
        assert set(LIMITS) == set(CHIPS)

    def test_float_weights_exceed_every_chips_precision(self, files):
        res = check(budget(files["float"][1]))
        for chip in CHIPS:
            assert not res[chip]["fits"]
            assert any("weight precision float32" in r for r in res[chip]["exceeds"]), chip

    def test_tiny_8bit_fits_loihi2_and_with_events_speck(self, files):
        analog = check(budget(files["8-bit"][1]))
        assert analog["loihi2"]["fits"] and analog["loihi2"]["exceeds"] == []
        assert not analog["speck"]["fits"]
        assert any("analog" in r for r in analog["speck"]["exceeds"])
        events = check(budget(files["8-bit events"][1]))
        assert events["speck"]["fits"], events["speck"]["exceeds"]
        xylo = " ".join(events["xylo_audio2"]["exceeds"])
        assert "input channels 192 > 16" in xylo and "fan-in" in xylo

    def test_reasons_name_value_and_limit(self, files):
        b = budget(files["8-bit"][1])
        big = dict(b, neurons=2_000_000, effective_synapses=130_000_000)
        loihi = check(big)["loihi2"]["exceeds"]
        assert "neurons 2000000 > 1000000" in loihi
        assert "synapses 130000000 > 120000000" in loihi
        mem = [r for r in loihi if r.startswith("memory")]
        assert mem and mem[0].endswith(f"> {128 * 128 * 1024}")
        assert any(r == "weight bits 16 > 8" for r in check(dict(b, weight_bits=16))["loihi2"][
            "exceeds"])

    def test_speck_kernel_memory_follows_sinabs_worked_example(self):
        # Sinabs' Speck overview: Conv2d(16, 32, 3x3) takes 16 * 2^(2 + 5)... = 8Ki entries
        assert layer_kernel_entries(16, 32, kernel=9) == 8 * 1024
        assert layer_kernel_entries(384, 128) == 384 * 128
        assert layer_kernel_entries(384, 129) == 384 * 256  # outputs round up to 2^8

    def test_speck_places_populations_on_layers(self, files):
        b = budget(files["8-bit events"][1])
        placed, bad = speck_layers(b, CHIPS["speck"])
        assert bad == [] and set(placed) == {"l2", "ring"}
        assert placed["l2"]["layer"] != placed["ring"]["layer"]
        c = b["population_input_channels"]
        assert c["l2"] == b["inputs"] and c["ring"] == b["populations"]["l2"] + \
            b["populations"]["ring"]
        big = dict(b, population_input_channels=dict(c, ring=5000))
        placed, bad = speck_layers(big, CHIPS["speck"])
        assert "ring" not in placed and bad and bad[0].startswith("ring:")
        assert not check(big)["speck"]["fits"]


# ------------------------------------------------------------------ nir 1.0.4


def test_lif_nodes_are_written_without_v_reset(files):
    import h5py

    for name, (sp, graph, path) in files.items():
        with h5py.File(path, "r") as f:
            for node in ("l2", "ring"):
                assert "v_reset" not in f["node"]["nodes"][node], (name, node)
        back = read_nir(path)  # nir >= 1.0.5 fills the default: 0
        assert not back.nodes["ring"].v_reset.any()


@pytest.mark.slow
def test_nir_104_reads_our_files(files, tmp_path_factory):
    import subprocess

    py = nir104_python(tmp_path_factory)
    version = subprocess.run([py, "-c", "import nir, importlib.metadata as m; "
                              "print(m.version('nir'))"], capture_output=True, text=True)
    if version.returncode != 0:
        pytest.skip(f"{py} cannot import nir: {version.stderr.strip()[-200:]}")
    assert version.stdout.strip() == "1.0.4"
    out = tmp_path_factory.mktemp("nir104out") / "read.npz"
    paths = [str(files[name][2]) for name in VARIANTS]
    run = subprocess.run([py, "-c", NIR104_SCRIPT, str(out), *paths], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    theirs = np.load(out)
    for i, name in enumerate(VARIANTS):
        ours = read_nir(files[name][2])
        assert str(theirs[f"{i}/meta/format"]) == str(ours.metadata["format"])
        for node_name, node in ours.nodes.items():
            assert str(theirs[f"{i}/{node_name}/type"]) == type(node).__name__
            for field, value in vars(node).items():
                if isinstance(value, np.ndarray) and field != "v_reset":  # not in nir 1.0.4
                    np.testing.assert_array_equal(theirs[f"{i}/{node_name}/{field}"], value)
        assert theirs[f"{i}/edges"].tolist() == sorted(map(list, ours.edges))


# ------------------------------------------------------------------ the export command
def test_export_flags_reject_bad_bits(tmp_path, capsys):
    from torchseq.cli.export import main

    assert main(["missing.pt", "--out", str(tmp_path / "o"), "--nir-weight-bits", "1"]) == 2
    assert "weight_bits must be None or an int in 2..16" in capsys.readouterr().err


@pytest.mark.slow
def test_export_command_reports_each_chip_at_8_bits(tmp_path, capsys):
    import json

    from export_helpers import small_setup

    from torchseq.cli.export import main

    model, demo, *_ = small_setup()
    np.save(tmp_path / "ref.npy", demo.reference.numpy())
    model.save(tmp_path / "small.pt", extra={"reference": {"source": str(tmp_path / "ref.npy")}})
    np.save(tmp_path / "query.npy", demo.query.numpy()[:20])
    out = tmp_path / "export"
    code = main([str(tmp_path / "small.pt"), "--out", str(out), "--query",
                 str(tmp_path / "query.npy"), "--nir-weight-bits", "8", "--nir-levels", "8",
                 "--no-progress", "--chip-report", "--timed-spiking"])
    printed = capsys.readouterr().out
    report = json.loads((out / "validation.json").read_text())["nir"]
    assert code == 0 and report["weight_bits"] == 8 and report["levels"] == 8
    assert int(read_nir(out / "model.nir").metadata["weight_bits"]) == 8
    assert report["chips"]["loihi2"]["fits"], report["chips"]["loihi2"]
    assert "nir_chip_loihi2: fits" in printed
    assert "nir_chip_speck: does not fit: input is an analog current" in printed
    # the timed model at the same 8 bits: its own per-chip lines (no file)
    assert report["timed"]["weight_bits"] == 8 and report["timed"]["chips"]["loihi2"]["fits"]
    assert "timed spiking model (not in model.nir" in printed
    assert "timed_chip_loihi2: fits" in printed
    assert "timed_chip_xylo_audio2: does not fit" in printed
    for name in ("snntorch", "norse"):
        c = report["consumers"][name]
        assert "skipped" in c or c["agreement"] == 1.0
