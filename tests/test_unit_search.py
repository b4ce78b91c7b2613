"""The sequence search over unit evidence (issue 20): oracle, model paths, export refusal.

The stage's maths is pinned against a plain loop written from the module docstring of
``torchseq/layers/unit_search.py``; its effect on a real long route is measured by
``experiments/neural_long_route.py search`` (docs/results/neural-long-routes.md).
"""

import csv
import dataclasses
import json
import math
import warnings

import numpy as np
import pytest
import torch
from conftest import shared_data

import torchseq.cli.eval as cli_eval
import torchseq.cli.plots as plots
from torchseq.cli.runs import run_main
from torchseq.demo import make_demo
from torchseq.layers.unit_search import (
    VELOCITIES,
    SearchHistory,
    contrast_units,
    search_decide,
    search_lines,
    search_units,
    unit_search_scan,
    unit_search_step,
)
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.neural.config import NeuralError
from torchseq.neural.search import SearchState


def loop_search(e, a, n_frames, length, phases, window, weight, spans, uwin, eps=1e-6):
    """Independent oracle: every step of the docstring written as plain Python loops."""
    t_len, n = len(e), len(e[0])
    c = [] if window else [list(row) for row in e]  # window 0: the evidence unchanged
    for t in range(t_len if window else 0):  # 1. contrast across units, shrunk at the ends
        row = []
        for u in range(n):
            w = [e[t][i] for i in range(max(0, u - window), min(n, u + window + 1))]
            mu = sum(w) / len(w)
            var = sum(x * x for x in w) / len(w) - mu * mu
            row.append((e[t][u] - mu) / math.sqrt(max(var, eps * eps)))
        c.append(row)
    refs, confs, units = [], [], []
    for t in range(t_len):
        filled = min(t + 1, length)
        q = []
        amean = sum(a[t]) / n
        asd = math.sqrt(max(sum((x - amean) ** 2 for x in a[t]) / n, eps * eps))
        for m in range(n * phases):
            x = (m + 0.5) / phases
            best = -math.inf
            for v in VELOCITIES:  # 2. lines at each speed, mean over the frames seen
                s = 0.0
                for j in range(filled):
                    u = max(0, math.floor(x - v * n / n_frames * j))
                    s += c[t - j][u]
                best = max(best, s / filled)
            q.append(best + weight * (a[t][m // phases] - amean) / asd)  # 3. the ring
        mstar = max(range(len(q)), key=lambda i: (q[i], -i))  # 4. first best position
        u, p = mstar // phases, mstar % phases
        f, last = spans[u]
        refs.append(f + math.floor((p + 0.5) * (last - f) / phases))
        rivals = [q[i] for i in range(len(q)) if abs(i // phases - u) > uwin]
        confs.append(q[mstar] - (max(rivals) if rivals else min(q)))
        row = []  # each unit's best phase (first on ties): its score and its frame
        for v in range(n):
            p = max(range(phases), key=lambda i: (q[v * phases + i], -i))
            f, last = spans[v]
            row.append((q[v * phases + p], f + math.floor((p + 0.5) * (last - f) / phases)))
        units.append(row)
    return refs, confs, units


def _case(seed=0, t_len=23, n=9, n_frames=30):
    g = torch.Generator().manual_seed(seed)
    e = torch.rand(t_len, n, generator=g, dtype=torch.float64) * 2
    a = torch.rand(t_len, n, generator=g, dtype=torch.float64)
    starts = torch.arange(n) * n_frames // n
    spans = torch.stack([starts, torch.cat([starts[1:], torch.tensor([n_frames])])], 1)
    return e, a, spans


@pytest.mark.parametrize("length,phases,window,weight", [(7, 3, 2, 0.1), (4, 1, 0, 0.0),
                                                          (30, 2, 20, 0.5)])
def test_scan_and_step_match_a_plain_loop(length, phases, window, weight):
    e, a, spans = _case()
    n_frames = int(spans[-1, 1])
    ref, conf, units = loop_search(e.tolist(), a.tolist(), n_frames, length, phases, window,
                                   weight, spans.tolist(), 2)
    lines = search_lines(e.shape[1], n_frames, length, phases)
    scores = unit_search_scan(e, a, lines, window, weight)
    got_ref, got_conf = search_decide(scores, spans, phases, 2)
    assert got_ref.tolist() == ref
    np.testing.assert_allclose(got_conf.numpy(), conf, rtol=1e-9, atol=1e-9)
    unit_score, unit_frame = search_units(scores, spans, phases)  # the ranked candidates
    np.testing.assert_allclose(unit_score.numpy(), [[s for s, _ in r] for r in units],
                               rtol=1e-9, atol=1e-9)
    assert unit_frame.tolist() == [[f for _, f in r] for r in units]
    state = SearchHistory(torch.zeros(1, length, e.shape[1], dtype=e.dtype),
                          torch.zeros(1, dtype=torch.int64))
    for t in range(e.shape[0]):  # the streaming step is the definition: the same numbers
        s, state = unit_search_step(e[t:t + 1], a[t:t + 1], state, lines, window, weight)
        np.testing.assert_allclose(s[0].numpy(), scores[t].numpy(), rtol=1e-9, atol=1e-9)


def test_contrast_matches_its_definition_and_batches():
    e, _, _ = _case(1, t_len=4, n=12)
    c = contrast_units(e, 3)
    for u in (0, 5, 11):
        w = e[:, max(0, u - 3):u + 4]
        want = (e[:, u] - w.mean(1)) / w.std(1, unbiased=False)
        np.testing.assert_allclose(c[:, u].numpy(), want.numpy(), rtol=1e-9)
    assert torch.equal(contrast_units(e, 0), e)


def test_lines_move_at_the_reference_speed_in_units():
    lines = search_lines(10, 40, 9, 1, velocities=(1.0,))  # 4 frames per unit
    assert lines.shape == (1, 9, 10)
    assert lines[0, :, 9].tolist() == [9, 9, 9, 8, 8, 8, 8, 7, 7]  # from x = 9.5, 1/4 a frame
    assert lines[0, 8, 0] == 0  # clamped at the route's start


def _coarse_demo():
    d = make_demo(n_reference=120, seed=3)
    return d, NeuralConfig(n_output=40, hidden=512, seed=0)  # 3 frames per unit


def _fit(ref, cfg):
    m = NeuralSeqSLAM(cfg)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m.fit(ref, log=False, check=False)
    return m


def test_search_runs_only_where_units_hold_several_frames():
    d, cfg = _coarse_demo()
    assert _fit(d.reference, cfg).search is not None
    small = NeuralConfig(n_output=555, hidden=512)
    assert _fit(d.reference, small).search is None  # one frame per unit: the ring alone
    off = NeuralConfig(n_output=40, hidden=512, unit_search="off")
    assert _fit(d.reference, off).search is None
    on = NeuralConfig(n_output=555, hidden=512, unit_search="on")
    assert _fit(d.reference, on).search is not None


def test_run_equals_step_by_step_layers_or_fast_path_and_survives_state_dict():
    d, cfg = _coarse_demo()
    m = _fit(d.reference, cfg)
    res = m.run(d.query)
    inf = m.inference()
    assert inf.search is not None
    assert torch.equal(inf.run(d.query).matches.reference, res.matches.reference)
    for stepper in (m, inf):  # the layers, then the fast path
        state, refs = None, []
        for t in range(len(d.query)):
            out, state = stepper.step(torch.as_tensor(d.query[t:t + 1]), state)
            refs.append(int(out.reference))
        assert isinstance(state, SearchState)
        assert refs == res.matches.reference.tolist()
    m2 = NeuralSeqSLAM(cfg)
    m2.load_state_dict(m.state_dict())
    assert m2.search is not None
    assert torch.equal(m2.run(d.query).matches.reference, res.matches.reference)
    off = _fit(d.reference, NeuralConfig(n_output=40, hidden=512, unit_search="off"))
    assert not torch.equal(off.run(d.query).matches.reference, res.matches.reference)


def test_step_refuses_a_ring_state():
    d, cfg = _coarse_demo()
    m = _fit(d.reference, cfg)
    _, state = m.step(torch.as_tensor(d.query[:1]))
    with pytest.raises(NeuralError, match="SearchState"):
        m.step(torch.as_tensor(d.query[1:2]), state.ring)
    with pytest.raises(NeuralError, match="SearchState"):
        m.inference().step(torch.as_tensor(d.query[1:2]), state.ring)


def test_config_checks_and_older_checkpoints():
    for bad in ({"unit_search": "yes"}, {"search_length": 0}, {"search_phases": 65},
                {"search_ring_weight": -1.0}, {"search_contrast": -1},
                {"unit_search": "on", "ring_velocity": "adaptive"}):
        with pytest.raises(NeuralError):
            NeuralConfig(**bad).validate()
    old = NeuralConfig().to_dict()
    del old["unit_search"]
    assert NeuralConfig.from_dict(old).unit_search == "off"  # the ring alone, as made


def test_every_export_refuses_a_searching_model_by_name(tmp_path):
    from torchseq.export import ExportError, build_float_onnx, export_checkpoint, integer_model
    from torchseq.export.int_format import IntegerFormatError
    from torchseq.neural.spiking import SpikingError, SpikingSeqSLAM

    d, cfg = _coarse_demo()
    m = _fit(d.reference, cfg)
    with pytest.raises(IntegerFormatError, match="unit search"):
        integer_model(m)
    with pytest.raises(NeuralError, match="unit search"):
        build_float_onnx(m)
    with pytest.raises(SpikingError, match="unit search"):
        SpikingSeqSLAM.convert(m, torch.as_tensor(d.reference))
    m.save(tmp_path / "m.pt")  # the command writes every form, so it refuses the model
    with pytest.raises(ExportError, match="unit search") as err:
        export_checkpoint(tmp_path / "m.pt", tmp_path / "out", query=d.query)
    import torchseq.cli.train as cli_train  # its remedies are train flags that exist

    said = str(err.value)
    assert "(torchseq train --neural-unit-search off)" in said
    assert cli_train.parse_args(["--neural-unit-search", "off"])[1].unit_search == "off"


@pytest.mark.parametrize("n_reference, n_output", [(120, 40), (420, None)])
def test_the_export_remedy_gives_a_model_that_exports(tmp_path, n_reference, n_output):
    # units of several frames, and a route long enough for "auto" to pick the search with
    # one unit per frame: each remedy the refusal names must make the model exportable
    import torchseq.cli.train as cli_train
    from torchseq.cli.flags import changed_fields
    from torchseq.export import ExportError, export_checkpoint
    from torchseq.neural.search import refuse_export

    d = make_demo(n_reference=n_reference, seed=3)
    cfg = NeuralConfig(hidden=256, seed=0, **({} if n_output is None else {"n_output": n_output}))
    m = _fit(d.reference, cfg)
    m.save(tmp_path / "m.pt")
    with pytest.raises(ExportError, match="unit search") as err:
        export_checkpoint(tmp_path / "m.pt", tmp_path / "out", query=d.query)
    flags = str(err.value).split("(torchseq train ")[1].rstrip(")").split(", or ")
    assert flags
    default = cli_train.parse_args([])[1]
    for flag in flags:
        changed = changed_fields(cli_train.parse_args(flag.split())[1], default)
        assert changed, flag
        refuse_export(_fit(d.reference, dataclasses.replace(cfg, **changed)), "export")


@pytest.mark.slow
def test_search_lifts_a_real_route_at_three_frames_per_unit():
    from torchseq.metrics import evaluate
    from torchseq.sources import load_traverse

    root = shared_data("nordland-b")
    ref = load_traverse(root / "summer", progress=False)[:600]
    query = load_traverse(root / "winter", progress=False)[:600]
    i = np.arange(600)
    gt = np.abs(i[:, None] - i[None, :]) <= 2
    got = {}
    for mode in ("auto", "off"):
        m = _fit(ref, NeuralConfig(n_output=200, unit_search=mode))
        got[mode] = evaluate(m.run(query).matches, gt)["recall_at_1"]
    assert got["auto"] > got["off"] + 0.1, got


def test_float_onnx_of_the_search_decides_as_the_model():
    ort = pytest.importorskip("onnxruntime")
    from torchseq.export.onnx_search import build_search_onnx, run_search_onnx

    d, cfg = _coarse_demo()
    m = _fit(d.reference, cfg)
    res = m.run(d.query)
    sess = ort.InferenceSession(build_search_onnx(m).SerializeToString())
    frames = torch.cat([m._grey(torch.as_tensor(d.query[t:t + 1]))
                        for t in range(len(d.query))]).numpy()
    ref, conf = run_search_onnx(sess, frames)
    assert ref.tolist() == res.matches.reference.tolist()
    np.testing.assert_allclose(conf, res.matches.score.numpy(), atol=1e-4)
    with pytest.raises(ValueError, match="does not use the unit search"):
        build_search_onnx(_fit(d.reference, NeuralConfig(n_output=40, hidden=512,
                                                         unit_search="off")))


@pytest.mark.parametrize("n_output,stage", [(40, "unit search"), (200, "ring")])
def test_every_figure_of_an_eval_run_comes_from_the_stage_that_decided(
        tmp_path, capsys, monkeypatch, n_output, stage):
    """Issue 33: recall@K, the recall table, the raster, matches.csv and the warnings of one
    run all come from the stage that decided (the demo's 200 frames on 40 units: the search;
    on 200: the ring). Before, recall@5 and the table came from the ring under the search
    (recall@1 0.984 against recall@5 0.843)."""
    drawn = {}
    draw = plots.plot_activity_raster

    def spy(activity, *args, **kwargs):
        drawn["raster"], drawn["title"] = np.asarray(activity), kwargs.get("title", "")
        return draw(activity, *args, **kwargs)

    monkeypatch.setattr(plots, "plot_activity_raster", spy)
    out = tmp_path / "o"
    assert run_main(cli_eval.main, "eval.py", [
        "--engine", "neural", "--neural-n-output", str(n_output), "--no-progress",
        "--no-tensorboard", "--out", str(out)]) == 0
    capsys.readouterr()
    summary = json.loads((out / "metrics.json").read_text())
    m = summary["neural"]
    assert m["stage"] == stage
    assert drawn["title"] == ("neural unit search score per unit over the query" if stage ==
                              "unit search" else "neural output activity over the query")
    assert m["sequence_frames"] == pytest.approx(40 if stage == "unit search" else 1 / 0.03)
    rows = [r for r in csv.DictReader((out / "matches.csv").open()) if r["engine"] == "neural"]
    first = [int(r["candidates"].split()[0]) for r in rows]
    assert first == [int(r["reference"]) for r in rows]  # the first candidate is the decision
    unit = np.asarray(first) * n_output // 200  # uniform recruitment: frame t -> t N / R
    assert (drawn["raster"].argmax(1) == unit).all()  # the raster's best unit holds it
    assert m["recall_at_1"] <= m["recall_at_5"] <= m["recall_at_10"]
    table = m["recall"]["queries_with_a_true_match"]
    assert table["ties_against"]["1"] <= m["recall_at_1"] <= table["ties_for"]["1"]
    assert m["versus_single_frame"]["sequence_recall_at_1"] == m["recall_at_1"]
    said = " ".join(summary["warnings"] if isinstance(summary["warnings"], list) else
                    map(str, summary["warnings"]))
    assert ("unit search decides" in said) == (stage == "unit search")
    assert "matches are unit centres" not in said


def test_auto_is_resolved_at_fit_from_the_route_and_kept_in_the_checkpoint(tmp_path):
    """Issue 33: "auto" searches on routes of more than 10 lines (or units of several frames),
    resolved once at fit into the config a checkpoint carries; an older checkpoint's "auto"
    keeps the rule it was made with (units of several frames only)."""
    d = make_demo(n_reference=120, seed=3)
    long = _fit(d.reference, NeuralConfig(hidden=512, search_length=10))  # 120 > 10 x 10
    short = _fit(d.reference, NeuralConfig(hidden=512, search_length=12))  # 120 = 10 x 12
    assert (long.config.unit_search, long.stage, long.n_units) == ("on", "unit search", 120)
    assert (short.config.unit_search, short.stage) == ("off", "ring")
    long.save(tmp_path / "m.pt")
    loaded = NeuralSeqSLAM.load(tmp_path / "m.pt")
    assert loaded.config.unit_search == "on" and loaded.search is not None
    former = NeuralSeqSLAM(dataclasses.replace(long.config, unit_search="auto"))
    former.load_state_dict(long.state_dict())  # fitted before issue 33: one unit per frame
    assert former.search is None and former.stage == "ring"
