"""torchseq as an Event-LAB baseline, called the way Event-LAB calls baselines (a fake of its
calling convention, tests/eventlab_fake.py), checked against torchseq's own engines."""

import importlib
import sys

import numpy as np
import pytest
import torch
from eventlab_fake import FakeEventBaseline, FakeSequence, eventlab_run, recall_at_k

from torchseq.demo import make_world, render
from torchseq.events import load_event_frames
from torchseq.events.runs import ground_truth, simulate_run
from torchseq.integrations import eventlab
from torchseq.metrics import evaluate
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.preprocess import resize
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig

h5py = pytest.importorskip("h5py")
OFFSET_S = 1_600_000_000.0  # sequences start at a Unix time, as Brisbane-Event-VPR's


class torchseq_baseline(eventlab.TorchseqBaseline, FakeEventBaseline):  # noqa: N801
    """What baselines/torchseq.py declares, with the fake in place of EventBaseline."""


def write_formatted(path, events):
    """Event-LAB's formatted HDF5: /events/{t,x,y,p}, t in ns (timestamp_val: ns)."""
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        g["t"] = (events["t"].astype(np.int64) + int(OFFSET_S * 1e6)) * 1000
        for k in "xyp":
            g[k] = events[k]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    folder = tmp_path_factory.mktemp("eventlab")
    world = make_world(700, 32, 5)
    positions = np.arange(0.0, 601.0, 2.0)
    views = render(world, positions, 48)
    runs = {}
    for name, speed, seed in (("sunset", 1.0, 1), ("sunrise", 0.66, 2)):
        runs[name] = simulate_run(views, positions, speed, 1000.0, seed=seed,
                                  threshold_noise=0.03)
        write_formatted(folder / f"{name}.hdf5", runs[name].stream.events)
    return folder, runs


def setup(folder):
    config = {"frame_generator": "frames", "ground_truth_tolerance": 0.0}
    dataset_config = {"dataset": {"name": "fake_event", "resolution": [48, 32]},
                      "format": {"data": {"timestamp_val": "ns"}},
                      "other": {"offset": {"sunset": OFFSET_S, "sunrise": OFFSET_S}}}
    ref = FakeSequence("fake_event", "sunset", folder / "sunset.hdf5", [10])
    query = FakeSequence("fake_event", "sunrise", folder / "sunrise.hdf5", [10])
    return config, dataset_config, ref, query


def test_eventlab_runs_torchseq_and_scores_its_matches(dataset, tmp_path):
    folder, runs = dataset
    settings = {"seqslam": {"ds": 20, "speed_ratio": 0.66, "edges": True},
                "neural": {"n_output": 100}}
    frames = {n: load_event_frames(folder / f"{n}.hdf5", window_ms=10, time_unit="ns",
                                   sensor_size=(48, 32), anchor=int(OFFSET_S * 1e6))
              for n in ("sunset", "sunrise")}
    n_ref, n_q = len(frames["sunset"]), len(frames["sunrise"])
    gt = ground_truth(runs["sunset"].window_positions(n_ref, 10_000),
                      runs["sunrise"].window_positions(n_q, 10_000),
                      16.0).astype(np.uint8)  # +-2 reference windows of 8 px
    gt_file = tmp_path / "sunset_sunrise_GT.npy"
    np.save(gt_file, gt)
    config, dataset_config, ref, query = setup(folder)
    baseline = torchseq_baseline(settings=settings, outdir=str(tmp_path / "output"))
    eventlab_run(baseline, config, dataset_config, ref, query, str(gt_file))

    out = tmp_path / "output" / "fake_event" / "sunset_sunrise" / "frames_10"
    seq, neural = np.load(out / "seqslam.npy"), np.load(out / "neural.npy")
    assert seq.shape == neural.shape == (n_ref, n_q)
    # SeqSLAM: each column's best reference is torchseq's own match on the same frames
    cfg = SeqSLAMConfig(ds=20, speed_ratio=0.66, edges=True)
    result = SeqSLAM(cfg).match(frames["sunset"], frames["sunrise"])
    assert bool((result.matches.reference >= 0).all())
    np.testing.assert_array_equal(seq.argmax(0), result.matches.reference.numpy())
    # Event-LAB's recall@1 is torchseq's (every query has a true match here)
    r1 = {row["array_name"]: row["R@1"] for row in baseline.scored}
    assert r1["seqslam"] == pytest.approx(evaluate(result.matches, gt)["recall_at_1"])
    assert r1["seqslam"] > 0.9
    # Neural: S[r, q] is the activity of the unit that stands for reference frame r
    ncfg = NeuralConfig(unit_search="off", n_output=100)
    model = NeuralSeqSLAM(ncfg)
    model.fit(resize(frames["sunset"], ncfg.input_size), progress=False)
    act = model.run(resize(frames["sunrise"], ncfg.input_size), progress=False).activity
    spans = model.unit_to_reference.numpy()
    for r in range(n_ref):
        u = [i for i, (a, b) in enumerate(spans) if a <= r < b]
        assert len(u) == 1
        np.testing.assert_array_equal(neural[r], act[:, u[0]].float().numpy())
    assert baseline.saved == [("torchseq", "sunset_sunrise", 2)]


def test_rank_similarity_orders_the_ranked_places_and_carries_the_confidence():
    match = torch.tensor([2, -1, 0])
    u = torch.tensor([0.25, float("nan"), 0.0])
    ranked = torch.tensor([[2, 4, 1], [-1, -1, -1], [0, 3, -1]])
    sim = eventlab.rank_similarity(match, u, ranked, 5)
    want = np.zeros((5, 3), np.float32)
    want[2, 0], want[4, 0], want[1, 0] = 4 - 0.25, 2, 1
    want[0, 2], want[3, 2] = 4, 2
    np.testing.assert_array_equal(sim, want)
    gt = np.zeros((5, 3), bool)
    gt[4, 0] = gt[0, 1] = gt[3, 2] = True
    assert recall_at_k(sim, gt, 1) == pytest.approx(0.0)
    assert recall_at_k(sim, gt, 2) == pytest.approx(2 / 3)  # ranked 2nd places count at K=2


def test_write_baseline_gives_the_module_event_lab_imports(tmp_path, monkeypatch):
    root = tmp_path / "Event-LAB"
    (root / "baselines").mkdir(parents=True)
    (root / "baselines" / "__init__.py").write_text("")
    # Event-LAB's own module, here the fake: the written file subclasses it
    (root / "baselines" / "EventBaselineLab.py").write_text(
        "import sys\nsys.path.insert(0, %r)\n"
        "from eventlab_fake import FakeEventBaseline as EventBaseline\n"
        % str(__import__("pathlib").Path(__file__).parent))
    paths = eventlab.write_baseline(root)
    assert [p.name for p in paths] == ["torchseq.py", "torchseq.yaml"]
    with pytest.raises(FileExistsError):
        eventlab.write_baseline(root)
    monkeypatch.chdir(root)
    monkeypatch.syspath_prepend(str(root))
    for name in [m for m in sys.modules if m == "baselines" or m.startswith("baselines.")]:
        monkeypatch.delitem(sys.modules, name)
    module = importlib.import_module("baselines.torchseq")
    baseline = module.torchseq_baseline()  # as get_baseline builds it: no arguments
    assert baseline.K_list[0] == 1 and baseline.matrix_type == "similarity"
    yaml = pytest.importorskip("yaml")
    assert baseline.baseline_config == eventlab.resolve_settings(
        yaml.safe_load(paths[1].read_text()))
    with pytest.raises(ValueError, match="unknown torchseq baseline settings"):
        eventlab.resolve_settings({"dss": 10})
    with pytest.raises(ValueError, match="engines"):
        eventlab.resolve_settings({"engines": ["lens"]})


def test_the_module_command_writes_the_files_or_says_why(tmp_path, capsys):
    root = tmp_path / "Event-LAB"
    assert eventlab.main([str(root)]) == 2  # no baselines/ folder
    assert "not an Event-LAB checkout" in capsys.readouterr().err
    (root / "baselines").mkdir(parents=True)
    assert eventlab.main([str(root)]) == 0
    assert "VPR-Baselines" in capsys.readouterr().out
    assert (root / "baselines" / "torchseq.py").read_text() == eventlab.BASELINE_FILE
    assert eventlab.main([str(root)]) == 2 and "exist" in capsys.readouterr().err
    assert eventlab.main([str(root), "--overwrite"]) == 0
    assert eventlab.main([]) == 2
