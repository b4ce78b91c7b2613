"""Reference maps: round trips, refusal of damaged/foreign/newer maps, atomic writes, eval --map."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from torchseq.maps import MapError, build_map, load_map
from torchseq.maps import build as map_build
from torchseq.maps.format import manifest_checksum
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig

faiss = pytest.importorskip(
    "faiss", reason="maps hold a FAISS index (pip install 'torchseq[faiss]'); not installed")

from torchseq.seqslam.candidates import CandidateSeqSLAM  # noqa: E402

DATA = Path(__file__).parent / "data"


def descriptors(n=230, dim=24, seed=0):
    rng = np.random.default_rng(seed)
    return torch.tensor(127 + np.round(rng.normal(0, 3, (n, dim))), dtype=torch.float32)


def rewrite_manifest(folder, **changes):
    m = json.loads((folder / "map.json").read_text())
    m.update(changes)
    m["checksum"] = manifest_checksum(m)
    (folder / "map.json").write_text(json.dumps(m))


@pytest.fixture
def built(tmp_path):
    ref = descriptors()
    record = {"source": "synthetic", "n_frames": 230, "frame_size": [32, 64]}
    m = build_map(ref, tmp_path / "map", SeqSLAMConfig(metric="l2", ds=6), shard_size=50,
                  index="flat", record=record)
    return ref, m


def test_round_trip(built):
    ref, m = built
    again = load_map(m.path)
    assert [(s.start, s.stop) for s in again.shards] == [(0, 50), (50, 100), (100, 150),
                                                          (150, 200), (200, 230)]
    assert sorted(p.name for p in m.path.iterdir()) == [
        "index.npy", "map.json"] + [f"shard-{i:05d}.npy" for i in range(5)]
    assert torch.equal(again.descriptors(), ref)
    assert torch.equal(again.rows(45, 155), ref[45:155])  # across three shard files
    assert again.config == SeqSLAMConfig(metric="l2", ds=6)
    assert again.reference == {"source": "synthetic", "n_frames": 230, "frame_size": [32, 64]}
    assert again.n_places == 230 and again.dim == 24 and again.dtype == np.float32
    index = again.index()
    assert index.kind == "flat" and index.metric == "l2"
    query = ref[100:140] + 0.5
    fresh = CandidateSeqSLAM(ref, SeqSLAMConfig(metric="l2", candidates=4))
    np.testing.assert_array_equal(index.search(query, 4), fresh.search(query))
    loaded = CandidateSeqSLAM(again.descriptors(), SeqSLAMConfig(metric="l2", candidates=4),
                              index=index).match_descriptors(query)
    want = fresh.match_descriptors(query)
    np.testing.assert_array_equal(loaded.matches.reference, want.matches.reference)
    np.testing.assert_array_equal(loaded.matches.score, want.matches.score)
    again.verify()


@pytest.mark.parametrize("kind", ["ivf", "hnsw"])
def test_approximate_index_round_trip(tmp_path, kind):
    ref = descriptors(400, 16, seed=1)
    options = dict(pca_dim=8, nlist=6, nprobe=3)
    m = build_map(ref, tmp_path / kind, SeqSLAMConfig(), shard_size=128, index=kind,
                  index_options=options)
    from torchseq.seqslam.ann_index import CandidateIndex

    fresh = CandidateIndex(ref, "l1", kind, **options)
    got = load_map(m.path).index()
    assert got.kind == kind
    np.testing.assert_array_equal(got.search(ref[:50], 5), fresh.search(ref[:50], 5))


def test_uint8_descriptors_and_no_index(tmp_path):
    ref = descriptors().to(torch.uint8)
    m = build_map(ref, tmp_path / "m", shard_size=1000, index=None)
    assert torch.equal(load_map(m.path).descriptors(), ref)
    with pytest.raises(MapError, match="holds no index"):
        load_map(m.path).index()


def test_damage_is_refused(built, tmp_path):
    _, m = built
    cases = {}

    def copy(name):
        dst = tmp_path / name
        shutil.copytree(m.path, dst)
        cases[name] = dst
        return dst

    shard = copy("truncated") / "shard-00002.npy"
    shard.write_bytes(shard.read_bytes()[:-7])
    shard = copy("flipped") / "shard-00003.npy"
    data = bytearray(shard.read_bytes())
    data[-5] ^= 0x40
    shard.write_bytes(bytes(data))
    index = copy("index") / "index.npy"
    data = bytearray(index.read_bytes())
    data[200] ^= 1
    index.write_bytes(bytes(data))
    (copy("missing") / "shard-00004.npy").unlink()
    want = {"truncated": "shard-00002.npy: .* truncated", "flipped": "shard-00003.npy: checksum",
            "index": "index.npy: checksum", "missing": "shard-00004.npy: missing"}
    for name, folder in cases.items():
        opened = load_map(folder)  # the manifest is intact: files are checked when read
        with pytest.raises(MapError, match=want[name]):
            opened.verify()
    # the manifest itself: edited, foreign, newer, not JSON, not a map at all
    folder = copy("edited")
    text = (folder / "map.json").read_text().replace('"n_places": 230', '"n_places": 231')
    (folder / "map.json").write_text(text)
    with pytest.raises(MapError, match="map.json: checksum mismatch"):
        load_map(folder)
    folder = copy("newer")
    rewrite_manifest(folder, version=2)
    with pytest.raises(MapError, match="version 2 is newer than this torchseq reads"):
        load_map(folder)
    folder = copy("foreign")
    rewrite_manifest(folder, format="somebody.else")
    with pytest.raises(MapError, match="not a torchseq map"):
        load_map(folder)
    folder = copy("garbage")
    (folder / "map.json").write_bytes(b"\x00\xffnot json")
    with pytest.raises(MapError, match="not a readable map manifest"):
        load_map(folder)
    folder = copy("inconsistent")
    rewrite_manifest(folder, shard_size=40)  # checksum right, contents wrong
    with pytest.raises(MapError, match="damaged manifest"):
        load_map(folder)
    folder = copy("wrong-shape")  # a shard replaced by another array, checksums updated
    np.save(folder / "shard-00000.npy", np.zeros((50, 23), np.float32))
    m2 = json.loads((folder / "map.json").read_text())
    from torchseq.maps.format import file_sha256

    path = folder / "shard-00000.npy"
    m2["shards"][0].update(bytes=path.stat().st_size, sha256=file_sha256(path))
    rewrite_manifest(folder, shards=m2["shards"])
    with pytest.raises(MapError, match=r"shard-00000.npy: holds float32 \(50, 23\)"):
        load_map(folder).rows(0, 10)
    with pytest.raises(MapError, match="not a torchseq map"):
        load_map(tmp_path)
    with pytest.raises(MapError, match="no such map"):
        load_map(tmp_path / "nowhere")


def test_writes_are_atomic(built, tmp_path, monkeypatch):
    ref, m = built
    with pytest.raises(MapError, match="already holds a map"):
        build_map(ref, m.path)
    (tmp_path / "other").mkdir()
    with pytest.raises(MapError, match="is not a map"):
        build_map(ref, tmp_path / "other", overwrite=True)
    calls = []
    real = map_build._save_npy

    def failing(path, array):
        calls.append(path.name)
        if len(calls) % 3 == 0:
            raise OSError("disk full")
        return real(path, array)

    monkeypatch.setattr(map_build, "_save_npy", failing)
    with pytest.raises(OSError, match="disk full"):
        build_map(ref[:100], tmp_path / "new", shard_size=40)
    calls.clear()
    with pytest.raises(OSError, match="disk full"):
        build_map(ref[:100], m.path, shard_size=40, overwrite=True)
    assert not (tmp_path / "new").exists()
    assert torch.equal(load_map(m.path).descriptors(), ref)  # the old map is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map", "other"]  # no temp folders
    monkeypatch.setattr(map_build, "_save_npy", real)
    build_map(ref[:100], m.path, shard_size=40, overwrite=True)
    assert load_map(m.path).n_places == 100


def test_bad_input():
    with pytest.raises(ValueError, match="shard_size"):
        build_map(descriptors(), "unused", shard_size=0)
    with pytest.raises(ValueError, match="NaN"):
        build_map(torch.full((5, 3), float("nan")), "unused")
    with pytest.raises(ValueError, match="must be one of"):
        build_map(descriptors().to(torch.int32), "unused")


def test_released_version_1_map_still_loads():
    """tests/data/map_v1 was written by format version 1 (tests/data/make_map_v1.py)."""
    m = load_map(DATA / "map_v1")
    m.verify()
    want = np.load(DATA / "map_v1_expected.npz")
    np.testing.assert_array_equal(m.descriptors().numpy(), want["descriptors"])
    np.testing.assert_array_equal(m.index().search(m.descriptors()[:5], 3), want["top3"])


@pytest.mark.slow
def test_cli_build_and_eval_with_map_equal_eval_with_reference(tmp_path, capsys):
    """``torchseq map build`` + ``eval --map`` give the frames route's matches exactly."""
    from torchseq.cli import main
    from torchseq.demo import make_demo

    demo = make_demo(n_reference=60, speed=0.9, seed=3)
    np.save(tmp_path / "ref.npy", demo.reference.numpy())
    np.save(tmp_path / "query.npy", demo.query.numpy())
    ref, query = str(tmp_path / "ref.npy"), str(tmp_path / "query.npy")
    common = ["--query", query, "--tolerance", "2", "--no-progress", "--no-tensorboard",
              "--image-size", "16x32", "--candidates", "5"]
    assert main(["map", "build", "--reference", ref, "--out", str(tmp_path / "m"),
                 "--shard-size", "25", "--image-size", "16x32", "--no-progress"]) == 0
    assert "60 places x 512 (float32), 3 shard(s)" in capsys.readouterr().out
    assert main(["eval", "--reference", ref, "--engine", "seqslam", "--out",
                 str(tmp_path / "a")] + common) == 0
    assert main(["eval", "--map", str(tmp_path / "m"), "--out", str(tmp_path / "b")]
                + common) == 0
    a = (tmp_path / "a" / "matches.csv").read_text()
    assert a == (tmp_path / "b" / "matches.csv").read_text()
    assert a.count("\n") > 40
    metrics = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert metrics["inputs"]["reference"] == f"map {tmp_path / 'm'}"
    assert metrics["seqslam"]["recall_at_1"] > 0.5
    desc = SeqSLAM(SeqSLAMConfig(image_size=(16, 32))).descriptors(demo.reference)
    assert torch.equal(load_map(tmp_path / "m").descriptors(), desc)
    assert load_map(tmp_path / "m").reference["source"] == str(Path(ref).resolve())
    assert main(["map", "verify", str(tmp_path / "m")]) == 0


def test_cli_refusals(tmp_path, capsys):
    from torchseq.cli import main

    ref = descriptors(40, 8)
    build_map(ref, tmp_path / "m", SeqSLAMConfig(image_size=(16, 32)), index="flat")
    np.save(tmp_path / "q.npy", np.zeros((20, 16, 32), np.float32))
    q = str(tmp_path / "q.npy")
    bad = {
        ("--map", str(tmp_path / "m")): "--map needs --query",
        ("--map", str(tmp_path / "m"), "--query", q, "--reference", q): "--map replaces",
        ("--map", str(tmp_path / "m"), "--query", q, "--engine", "neural"): "neural engine",
        ("--map", str(tmp_path / "m"), "--query", q, "--image-size", "8x16"):
            "--image-size .* differs from the map's",
        ("--map", str(tmp_path / "m"), "--query", q, "--max-frames", "9"): "--max-frames",
        ("--map", str(tmp_path), "--query", q): "--map .*not a torchseq map",
        ("--shards", "2",): "give --map",
        ("--map", str(tmp_path / "m"), "--query", q, "--ray-address", "x"): "needs --shards",
    }
    for args, message in bad.items():
        assert main(["eval", *args, "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1
        import re

        assert re.search(message, err), (args, err)
    assert main(["map", "build", "--out", str(tmp_path / "x")]) == 2
    assert "give --reference" in capsys.readouterr().err
    assert main(["map", "verify", str(tmp_path)]) == 2
    assert "not a torchseq map" in capsys.readouterr().err
