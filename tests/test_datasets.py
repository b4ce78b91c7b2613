"""torchseq.datasets: local copies in each dataset's layout, their ground truth, the CLI flags."""

import csv
import json
import math

import cv2
import numpy as np
import pytest
import torch
from conftest import shared_data

import torchseq.cli.eval as cli_eval
from torchseq import load_traverse
from torchseq.cli.errors import UsageError
from torchseq.cli.runs import run_main
from torchseq.datasets import (
    DatasetError,
    brisbane_event,
    gardens_point,
    nordland,
    open_dataset,
    read_nmea,
    vpr_bench,
)
from torchseq.events import EventStream, write_npz
from torchseq.ground_truth import alignment_ranges, load_ground_truth


def test_nordland_on_the_real_route():
    root = shared_data("nordland-b")
    ds = open_dataset("nordland", root)
    assert ds.splits == ("summer", "winter") and len(ds.reference) == len(ds.query) == 1788
    want = alignment_ranges(1788, 1788, 2.0)
    assert np.array_equal(ds.ground_truth.lo, want.lo)
    assert np.array_equal(ds.ground_truth.hi, want.hi)
    first = load_traverse(root / "winter", progress=False,
                          select=__import__("torchseq.sources").sources.FrameSelection(
                              start=5, stop=6))[0]
    assert torch.equal(ds.query[5], first)
    wide = nordland(root, "winter", "summer", tolerance=0)
    assert wide.splits == ("winter", "summer") and wide.ground_truth.dense().sum() == 1788


def test_vpr_bench_layout_on_the_corridor():
    root = shared_data("corridor")
    ds = vpr_bench(root)
    assert len(ds.reference) == len(ds.query) == 111
    assert ds.ground_truth_file.name == "ground_truth.csv"
    np.testing.assert_array_equal(ds.ground_truth,
                                  load_ground_truth(root / "ground_truth.csv", 111, 111))


def _images(folder, n, seed):
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        cv2.imwrite(str(folder / f"Image{i:03d}.jpg"), rng.integers(0, 255, (8, 12), np.uint8))


def test_gardens_point_and_vpr_bench_layouts(tmp_path):
    for split, seed in (("day_left", 0), ("day_right", 1), ("night_right", 2)):
        _images(tmp_path / "gp" / split, 12, seed)
    ds = gardens_point(tmp_path / "gp")
    assert ds.splits == ("day_right", "night_right")
    assert ds.ground_truth.dense().sum() == sum(min(11, i + 2) - max(0, i - 2) + 1
                                                for i in range(12))
    assert ds.reference[3].shape == (8, 12) and ds.reference[3].dtype == torch.float32
    assert gardens_point(tmp_path / "gp", "day_left", tolerance=0).ground_truth.dense().sum() \
        == 12
    _images(tmp_path / "vb" / "ref", 6, 3)
    _images(tmp_path / "vb" / "query", 4, 4)
    truth = np.empty((4, 2), dtype=object)  # VPR-Bench: per query (query index, references)
    for q in range(4):
        truth[q, 0], truth[q, 1] = q, [q, q + 1]
    np.save(tmp_path / "vb" / "ground_truth_new.npy", truth, allow_pickle=True)
    ds = vpr_bench(tmp_path / "vb")
    assert ds.ground_truth.shape == (6, 4)
    assert [list(np.nonzero(ds.ground_truth[:, q])[0]) for q in range(4)] == \
        [[q, q + 1] for q in range(4)]


def test_missing_pieces_say_which_layout_was_expected(tmp_path):
    with pytest.raises(DatasetError, match=r"nordland: no folder .*expected ROOT/<season>/"):
        nordland(tmp_path / "nothing")
    _images(tmp_path / "nl" / "summer", 2, 0)
    with pytest.raises(DatasetError, match=r"no split folder .*winter \(folders here: "
                                           r"summer\); expected ROOT/<season>/"):
        nordland(tmp_path / "nl")
    (tmp_path / "nl" / "winter").mkdir()
    with pytest.raises(DatasetError, match="no images in"):
        nordland(tmp_path / "nl")
    _images(tmp_path / "vb" / "ref", 3, 0)
    _images(tmp_path / "vb" / "query", 3, 1)
    with pytest.raises(DatasetError, match=r"no ground truth \(ground_truth_new.npy, "
                                           r".*expected ROOT/ref/ and ROOT/query/"):
        vpr_bench(tmp_path / "vb")
    with pytest.raises(DatasetError, match="unknown dataset 'kitti'; one of nordland"):
        open_dataset("kitti", tmp_path)
    with pytest.raises(DatasetError, match=r"no event file for traverse 'sunset1' .*"
                                           r"dvs_vpr_2020-04-21-17-03-03.parquet"):
        brisbane_event(tmp_path)


# --------------------------------------------------------------------- Brisbane-Event-VPR
def _nmea(path, start_s, lat0, lon0, dlat_per_s, n):
    """A GPS log: one $GPRMC fix per second moving north, UTC seconds of day from start_s."""
    lines = []
    for i in range(n):
        t = start_s + i
        hh, mm, ss = int(t // 3600), int(t % 3600 // 60), t % 60
        lat = lat0 + dlat_per_s * i
        la, lo = abs(lat), abs(lon0)
        lat_s = f"{int(la):02d}{(la - int(la)) * 60:07.4f}"
        lon_s = f"{int(lo):03d}{(lo - int(lo)) * 60:07.4f}"
        lines.append(f"$GPRMC,{hh:02d}{mm:02d}{ss:05.2f},A,{lat_s},{'S' if lat < 0 else 'N'},"
                     f"{lon_s},E,0.0,0.0,210420,,,A*00")
        lines.append(f"$GPGGA,{hh:02d}{mm:02d}{ss:05.2f},{lat_s},S,{lon_s},E,1,08,1.0,10,M,,,*00")
    path.write_text("\n".join(lines) + "\n")


def _events(path, first_us, seconds, rng):
    t = np.sort(rng.integers(0, int(seconds * 1e6), 4000)) + first_us
    t[0] = first_us
    ev = np.zeros(len(t), dtype=[("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")])
    ev["t"], ev["x"], ev["y"] = t, rng.integers(0, 16, len(t)), rng.integers(0, 12, len(t))
    ev["p"] = rng.integers(0, 2, len(t))
    write_npz(path, EventStream(ev, (16, 12)))


def haversine(a, b):
    r = 6_371_000.0
    la1, lo1, la2, lo2 = map(math.radians, (*a, *b))
    h = math.sin((la2 - la1) / 2) ** 2 + math.cos(la1) * math.cos(la2) * math.sin(
        (lo2 - lo1) / 2) ** 2
    return 2 * r * math.asin(math.sqrt(h))


def test_brisbane_gps_ground_truth_against_a_loop(tmp_path):
    rng = np.random.default_rng(0)
    day = 1587452400  # 2020-04-21 07:00:00 UTC
    # reference: Unix timestamps, starts 10 s into its log; query: relative timestamps
    _events(tmp_path / "sunset1.npz", (day + 70) * 10**6, 20, rng)
    _nmea(tmp_path / "sunset1.nmea", 25260, -27.47, 153.02, -2e-5, 40)  # 07:01:00 UTC on
    _events(tmp_path / "dvs_vpr_2020-04-27-18-13-29.npz", 0, 12, rng)
    night0 = 1587975221.10 % 86400  # its known start (Event-LAB's offset), seconds of day
    _nmea(tmp_path / "20200427_181204-night_concat.nmea", int(night0) - 2, -27.47 - 2e-5 * 8,
          153.02, -2e-5, 30)
    from torchseq.sources import EventFrameOptions

    ds = brisbane_event(tmp_path, "sunset1", "night", tolerance=10,
                        events=EventFrameOptions(window_ms=1000))
    assert len(ds.reference) == 20 and len(ds.query) == 12
    track = {s: read_nmea(p) for s, p in (("sunset1", tmp_path / "sunset1.nmea"), (
        "night", tmp_path / "20200427_181204-night_concat.nmea"))}
    assert len(track["sunset1"]) == 40  # RMC and GGA of one second: one fix

    def position(name, sec):
        t = track[name][:, 0]
        i = int(np.searchsorted(t, sec)) - 1
        w = (sec - t[i]) / (t[i + 1] - t[i])
        return tuple((1 - w) * track[name][i, 1:] + w * track[name][i + 1, 1:])

    want = np.zeros((20, 12), bool)
    for r in range(20):
        for q in range(12):
            a = position("sunset1", 25270 + r + 0.5)
            b = position("night", night0 + q + 0.5)
            want[r, q] = haversine(a, b) <= 10
    np.testing.assert_array_equal(ds.ground_truth, want)
    assert want.any() and not want.all()
    with pytest.raises(DatasetError, match="relative timestamps and 'other'"):
        _events(tmp_path / "other.npz", 0, 5, rng)
        _nmea(tmp_path / "other.nmea", 25260, -27.47, 153.02, -2e-5, 40)
        brisbane_event(tmp_path, "sunset1", "other")


# --------------------------------------------------------------------- the command line
def _run(tmp_path, name, *args):
    out = tmp_path / name
    assert run_main(cli_eval.main, "eval.py", [*args, "--engine", "seqslam", "--out", str(out),
                                               "--no-tensorboard", "--no-progress"]) == 0
    return (list(csv.DictReader(open(out / "matches.csv"))),
            json.loads((out / "metrics.json").read_text()))


@pytest.mark.slow
def test_dataset_flags_equal_the_explicit_run(tmp_path):
    root = shared_data("corridor")
    a_rows, a = _run(tmp_path, "a", "--dataset", "vpr-bench", "--root", str(root))
    b_rows, b = _run(tmp_path, "b", "--reference", str(root / "ref"), "--query",
                     str(root / "query"), "--ground-truth", str(root / "ground_truth.csv"))
    assert a_rows == b_rows and a["seqslam"]["recall"] == b["seqslam"]["recall"]
    assert a["inputs"]["dataset"] == "vpr-bench"
    nl = shared_data("nordland-b")
    c_rows, c = _run(tmp_path, "c", "--dataset", "nordland", "--root", str(nl),
                     "--reference-split", "winter", "--query-split", "summer", "--stop", "150")
    d_rows, d = _run(tmp_path, "d", "--reference", str(nl / "winter"), "--query",
                     str(nl / "summer"), "--tolerance", "2", "--stop", "150")
    assert c_rows == d_rows and c["seqslam"]["recall_at_1"] == d["seqslam"]["recall_at_1"]


def test_dataset_flag_refusals(tmp_path):
    root = shared_data("corridor")
    base = ["--out", str(tmp_path / "o"), "--no-progress", "--no-tensorboard"]
    with pytest.raises(UsageError, match="--dataset gives the reference, query and ground "
                                         "truth; drop --reference"):
        cli_eval.main([*base, "--dataset", "vpr-bench", "--root", str(root), "--reference",
                       str(root / "ref")])
    with pytest.raises(UsageError, match="--dataset needs --root"):
        cli_eval.main([*base, "--dataset", "nordland"])
    with pytest.raises(UsageError, match="--reference-split belongs to --dataset"):
        cli_eval.main([*base, "--reference-split", "summer"])
    with pytest.raises(UsageError, match=r"--dataset: nordland: no split folder"):
        cli_eval.main([*base, "--dataset", "nordland", "--root", str(root), "--overwrite"])
