"""Every reader and settings object refuses garbage in one line of its own error (issue 35).

One test per hostile input found by fuzzing the newer input surfaces (reference maps,
descriptor files and hooks, dataset roots, event frames, Event-LAB settings, checkpoints,
NIR): each names the file or field and raises the module's own error, before anything is
sized from what the input declares. Allocations run under an address-space cap, so a
declared-size allocation fails the test as a ``MemoryError`` instead of swapping.
"""

import json
import shutil

import numpy as np
import pytest
import torch

from torchseq.seqslam import SeqSLAMConfig
from torchseq.seqslam.search import velocities

pytestmark = pytest.mark.usefixtures("memory_cap")  # conftest: address space capped


# ------------------------------------------------------------------ SeqSLAMConfig (item 1)

@pytest.mark.parametrize("over, field", [
    (dict(ds=10 ** 9), "ds"), (dict(vmax=1e9), "vmax"), (dict(speed_ratio=1e300), "speed_ratio"),
    (dict(image_size=(10 ** 6, 10 ** 6)), "image_size"), (dict(image_size=(4096, 4096)),
                                                            "image_size"),
    (dict(ds="10"), "ds"), (dict(top_k=1.5), "top_k"), (dict(vmin=float("nan")), "vmin"),
    (dict(threads=10 ** 9), "threads"), (dict(edges="yes"), "edges"),
    (dict(ds=10 ** 5, vmin=0.5, vmax=1.5), "trajectories per start"),
])
def test_seqslam_config_bounds_its_fields(over, field):
    with pytest.raises(ValueError, match=field):
        SeqSLAMConfig(**over).validate()


def test_velocities_are_counted_before_they_are_listed():
    assert len(velocities(10, 0.8, 1.2)) == 5
    with pytest.raises(ValueError, match="more than 4096"):
        velocities(10 ** 5, 1e-3, 1e3)


# ------------------------------------------------------------------ maps (items 1-6)

faiss = pytest.importorskip(
    "faiss", reason="maps hold a FAISS index (pip install 'torchseq[faiss]'); not installed")

from torchseq.maps import MapError, build_map, load_map  # noqa: E402
from torchseq.maps.format import file_sha256, manifest_checksum  # noqa: E402


def _map(tmp_path, index="flat", n=120, dim=8, **options):
    rng = np.random.default_rng(0)
    ref = torch.tensor(rng.normal(0, 1, (n, dim)), dtype=torch.float32)
    return build_map(ref, tmp_path / "map", SeqSLAMConfig(metric="l2", ds=6), shard_size=50,
                     index=index, index_options=options or None,
                     record={"source": "synthetic", "frame_size": [32, 64]})


def _edit(folder, text=None, **changes):
    """Rewrite map.json with ``changes`` (or raw ``text``), its checksum made valid."""
    m = json.loads((folder / "map.json").read_text())
    for key, value in changes.items():
        if "." in key:
            outer, inner = key.split(".")
            m[outer][inner] = value
        else:
            m[key] = value
    m["checksum"] = manifest_checksum(m)
    (folder / "map.json").write_text(text(m) if text else json.dumps(m))


def _replace_file(folder, name, data: bytes, entry="index"):
    (folder / name).write_bytes(data)
    m = json.loads((folder / "map.json").read_text())
    target = m["index"] if entry == "index" else m["shards"][entry]
    target.update(bytes=len(data), sha256=file_sha256(folder / name))
    _edit(folder, **{k: m[k] for k in ("index", "shards")})


@pytest.mark.parametrize("changes", [
    {"config.ds": 10 ** 9}, {"config.vmax": 1e9}, {"config.speed_ratio": 1e300},
    {"config.image_size": [10 ** 6, 10 ** 6]},
])
def test_map_config_sizes_are_bounded(tmp_path, changes):
    m = _map(tmp_path, index=None)
    _edit(m.path, **changes)
    with pytest.raises(MapError, match="map.json: bad config"):
        load_map(m.path)


@pytest.mark.parametrize("name, edit", [
    ("nan", lambda t: t.replace('"dim": 8', '"dim": NaN')),
    ("infinity", lambda t: t.replace('"vmin": 0.8', '"vmin": Infinity')),
    ("4301 digits", lambda t: t.replace('"dim": 8', '"dim": ' + "9" * 4301)),
])
def test_map_manifest_literals_are_map_errors(tmp_path, name, edit):
    m = _map(tmp_path, index=None)
    _edit(m.path, text=lambda d: edit(json.dumps(d)))
    with pytest.raises(MapError, match="map.json: not a readable map manifest"):
        load_map(m.path)


@pytest.mark.parametrize("changes, what", [
    ({"n_places": 10 ** 400}, "n_places"), ({"dim": 10 ** 13}, "dim"),
    ({"reference.frame_size": ["a", "b"]}, "reference.frame_size"),
    ({"reference.frame_size": [10 ** 12, 4]}, "reference.frame_size"),
])
def test_map_manifest_sizes_are_bounded(tmp_path, changes, what):
    m = _map(tmp_path, index=None)
    _edit(m.path, **changes)
    with pytest.raises(MapError, match=f"map.json: damaged manifest \\({what}"):
        load_map(m.path)


def test_map_rows_check_the_shards_before_allocating(tmp_path):
    m = _map(tmp_path, index=None)
    _edit(m.path, dim=1 << 24)  # within the manifest's bound; 120 x 2^24 float32 = 7.5 GiB
    with pytest.raises(MapError, match=r"shard-00000.npy: holds float32 \(50, 8\)"):
        load_map(m.path).rows(0, 120)


def test_map_index_ids_are_checked(tmp_path):
    m = _map(tmp_path)
    ref = m.descriptors().numpy()
    foreign = faiss.IndexIDMap(faiss.IndexFlatL2(8))
    foreign.add_with_ids(ref, np.arange(1000, 1000 + len(ref)))
    _replace_file(m.path, "index.npy", _npy(faiss.serialize_index(foreign)))
    with pytest.raises(MapError, match="index.npy: unusable index .*plain IndexFlat"):
        load_map(m.path).index()
    with pytest.raises(MapError, match="index.npy: unusable index"):
        load_map(m.path).verify()
    quantiser = faiss.IndexFlatL2(4)
    ivf = faiss.IndexIVFFlat(quantiser, 4, 3)
    pca = faiss.PCAMatrix(8, 4)
    offset = faiss.IndexPreTransform(pca, ivf)
    offset.train(ref)
    offset.add_with_ids(ref, np.arange(len(ref)) + 7)
    shutil.rmtree(m.path)
    m = _map(tmp_path, index="ivf", pca_dim=4, nlist=3)
    _replace_file(m.path, "index.npy", _npy(faiss.serialize_index(offset)))
    with pytest.raises(MapError, match="ids outside 0..119"):
        load_map(m.path).index()


def _npy(data) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, np.asarray(data, dtype=np.uint8))
    return buf.getvalue()


def test_map_index_options_and_names_are_bounded(tmp_path):
    m = _map(tmp_path, index="ivf", pca_dim=4, nlist=3, nprobe=2)
    _edit(m.path, **{"index": {**json.loads((m.path / "map.json").read_text())["index"],
                                "options": {"nprobe": -1}}})
    with pytest.raises(MapError, match="damaged manifest \\(index option nprobe=-1"):
        load_map(m.path)
    shutil.rmtree(m.path)
    m = _map(tmp_path, index=None)
    shards = json.loads((m.path / "map.json").read_text())["shards"]
    shards[0]["file"] = "s" * 300
    _edit(m.path, shards=shards)
    with pytest.raises(MapError, match="damaged manifest \\(shard 0 file name"):
        load_map(m.path)


def test_map_verify_checks_values(tmp_path, capsys):
    from torchseq.cli.map import cli

    m = _map(tmp_path)
    assert cli(["verify", str(m.path)]) == 0
    assert "finite descriptors, index ids checked" in capsys.readouterr().out
    bad = np.load(m.path / "shard-00001.npy")
    bad[3, 2] = np.nan
    import io

    buf = io.BytesIO()
    np.save(buf, bad)
    _replace_file(m.path, "shard-00001.npy", buf.getvalue(), entry=1)
    with pytest.raises(MapError, match="shard-00001.npy: holds NaN or infinite"):
        load_map(m.path).verify()
    assert cli(["verify", str(m.path)]) == 2
    assert "shard-00001.npy: holds NaN" in capsys.readouterr().err


# ------------------------------------------------------------------ descriptors (items 7-12)

h5py = pytest.importorskip("h5py", reason="HDF5 descriptors need h5py (torchseq[hdf5])")

from torchseq.descriptors import (  # noqa: E402
    DescriptorError,
    describe,
    descriptor_kind,
    load_descriptors,
)

X = np.random.default_rng(0).normal(0, 1, (6, 4))


@pytest.mark.parametrize("dtype", [">f4", ">f8", ">i2"])
def test_big_endian_descriptors_load(tmp_path, dtype):
    np.save(tmp_path / "d.npy", X.astype(dtype))
    got = load_descriptors(tmp_path / "d.npy")
    np.testing.assert_array_equal(got.numpy(), X.astype(dtype).astype(got.numpy().dtype))


def test_long_double_descriptors_are_refused(tmp_path):
    np.save(tmp_path / "d.npy", X.astype(np.longdouble))
    with pytest.raises(DescriptorError, match="d.npy: dtype float128 is not a number type"):
        load_descriptors(tmp_path / "d.npy")


def test_hdf5_declared_size_is_checked_before_reading(tmp_path):
    with h5py.File(tmp_path / "d.h5", "w") as f:
        f.create_dataset("descriptors", shape=(2 ** 20, 2 ** 16), dtype="f4")  # nothing stored
    assert (tmp_path / "d.h5").stat().st_size < 4096
    with pytest.raises(DescriptorError, match="d.h5: dataset /descriptors declares 274877906944 "
                                              "bytes but the file stores 0"):
        load_descriptors(tmp_path / "d.h5")


@pytest.mark.parametrize("link", ["dangling", "external", "loop"])
def test_hdf5_links_are_descriptor_errors(tmp_path, link):
    with h5py.File(tmp_path / "d.h5", "w") as f:
        if link == "dangling":
            f["descriptors"] = h5py.SoftLink("/nowhere")
        elif link == "external":
            f["descriptors"] = h5py.ExternalLink("other.h5", "/x")
        else:
            f["a"], f["b"] = h5py.SoftLink("/b"), h5py.SoftLink("/a")
            f["descriptors"] = h5py.SoftLink("/a")
    with pytest.raises(DescriptorError, match="d.h5: 'descriptors' is a (Soft|External)Link"):
        load_descriptors(tmp_path / "d.h5")


def test_damaged_hdf5_heap_is_a_descriptor_error(tmp_path):
    with h5py.File(tmp_path / "d.h5", "w") as f:
        f["descriptors"] = X.astype("f4")
    data = bytearray((tmp_path / "d.h5").read_bytes())
    heap = data.find(b"HEAP")
    assert heap > 0
    data[heap + 4:heap + 40] = b"\xff" * 36
    (tmp_path / "d.h5").write_bytes(bytes(data))
    with pytest.raises(DescriptorError, match="d.h5"):
        load_descriptors(tmp_path / "d.h5")


def test_gfeat_symlink_loop_is_a_descriptor_error(tmp_path):
    (tmp_path / "global_features.txt").write_text("x, float32, 4, L2\n")
    X[0].astype("f4").tofile(tmp_path / "a.gfeat")
    (tmp_path / "b.gfeat").symlink_to(tmp_path / "b.gfeat")
    with pytest.raises(DescriptorError, match="b.gfeat: cannot read"):
        load_descriptors(tmp_path)


@pytest.mark.parametrize("metric", ["l1", "l2", "cosine"])
def test_huge_descriptors_are_refused_not_matched(metric):
    from torchseq.seqslam import SeqSLAM
    from torchseq.seqslam.candidates import CandidateSeqSLAM
    from torchseq.seqslam.streaming import StreamingSeqSLAM

    ref = torch.tensor(X, dtype=torch.float32).repeat(4, 1)
    config = SeqSLAMConfig(metric=metric, ds=4)
    with pytest.raises(ValueError, match="reference descriptors hold values up to .*rescale"):
        SeqSLAM(config).match_descriptors(ref * 1e19, ref)
    with pytest.raises(ValueError, match="query descriptors hold values up to .*rescale"):
        SeqSLAM(config).match_descriptors(ref, ref * 1e19)
    with pytest.raises(ValueError, match="reference descriptors hold values up to"):
        CandidateSeqSLAM(ref * 1e19, config, 4)
    with pytest.raises(ValueError, match="query descriptors hold values up to"):
        CandidateSeqSLAM(ref, config, 4).match_descriptors(ref * 1e19)
    with pytest.raises(ValueError, match="reference descriptors hold values up to"):
        StreamingSeqSLAM(ref * 1e19, config, descriptors=True)


def test_only_member_layouts_are_descriptors_for_eval_too(tmp_path):
    np.savez(tmp_path / "only.npz", feats=X.astype("f4"))
    with h5py.File(tmp_path / "only.h5", "w") as f:
        f["feats"] = X.astype("f4")
    for name in ("only.npz", "only.h5"):
        assert descriptor_kind(tmp_path / name) in ("npz", "hdf5")
        assert load_descriptors(tmp_path / name).shape == (6, 4)
    np.savez(tmp_path / "events.npz", events=X.astype("f4"))  # an event file's name: not taken
    assert descriptor_kind(tmp_path / "events.npz") is None


def test_eval_reads_an_only_member_npz_as_descriptors(tmp_path):
    import torchseq.cli.eval as cli_eval

    rng = np.random.default_rng(1)
    ref = rng.normal(0, 1, (40, 16)).astype("f4")
    np.savez(tmp_path / "ref.npz", feats=ref)
    np.savez(tmp_path / "qry.npz", feats=ref + rng.normal(0, 0.01, ref.shape).astype("f4"))
    assert cli_eval.main(["--reference", str(tmp_path / "ref.npz"), "--query",
                          str(tmp_path / "qry.npz"), "--engine", "seqslam", "--ds", "4",
                          "--out", str(tmp_path / "run"), "--no-progress",
                          "--no-tensorboard"]) == 0
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["seqslam"]["parameters"]["metric"] == "l1"  # ran on the (40, 16) arrays
    assert (tmp_path / "run" / "matches.csv").read_text().count("\n") == 41


@pytest.mark.parametrize("out", [None, "abc", {"a": 1}, np.zeros((1, 3), np.longdouble)])
def test_hook_output_of_the_wrong_kind_is_a_descriptor_error(out):
    with pytest.raises(DescriptorError, match="descriptor hook"):
        describe([np.zeros((4, 4))], lambda x: out)


def test_hook_big_endian_output_is_read():
    got = describe([np.zeros((4, 4))], lambda x: np.ones((1, 3), ">f4"))
    assert got.tolist() == [[1.0, 1.0, 1.0]]


# ------------------------------------------------------------------ arrays (items 19, 20)

from torchseq.sources import TraverseError, load_traverse  # noqa: E402


@pytest.mark.parametrize("dtype", [">f4", ">u2", np.longdouble])
def test_frame_arrays_of_any_byte_order_or_refused_dtype(tmp_path, dtype):
    frames = np.random.default_rng(0).integers(0, 255, (3, 8, 8)).astype(dtype)
    np.save(tmp_path / "f.npy", frames)
    if dtype == np.longdouble:
        with pytest.raises(TraverseError, match="f.npy: dtype float128 is not a number type"):
            load_traverse(tmp_path / "f.npy")
    else:
        got = load_traverse(tmp_path / "f.npy")
        np.testing.assert_array_equal(got.numpy(), frames.astype(np.float32))


def test_npz_zip_features_zipfile_lacks_are_refused(tmp_path):
    np.savez(tmp_path / "d.npz", descriptors=X.astype("f4"))
    data = bytearray((tmp_path / "d.npz").read_bytes())
    central = data.find(b"PK\x01\x02")
    data[central + 6] = 100  # "needs zip 10.0 to extract": NotImplementedError in zipfile
    (tmp_path / "d.npz").write_bytes(bytes(data))
    with pytest.raises(DescriptorError, match="d.npz: not a readable .npz archive .*version"):
        load_descriptors(tmp_path / "d.npz")


# ------------------------------------------------------------------ datasets (item 13)

@pytest.mark.parametrize("opener", ["nordland", "vpr_bench", "brisbane_event"])
def test_split_names_longer_than_a_file_name_are_dataset_errors(tmp_path, opener):
    import torchseq.datasets as datasets

    with pytest.raises(datasets.DatasetError, match="split 's{40}\\.\\.\\.' is not a folder"):
        getattr(datasets, opener)(tmp_path, "s" * 300)
    with pytest.raises(datasets.DatasetError, match="is not a folder or file name"):
        getattr(datasets, opener)(tmp_path, None, "../up")


# ------------------------------------------------------------------ event frames (14, 15, 22)

from torchseq.events import EventFormatError, load_event_frames  # noqa: E402
from torchseq.sources import EventFrameOptions  # noqa: E402

AEDAT = "alex_walking_again.aedat"


@pytest.fixture(scope="module")
def aedat():
    from conftest import shared_data

    return shared_data("events", AEDAT)


def test_a_filter_that_drops_every_event_is_said(aedat):
    with pytest.raises(EventFormatError, match="no events left: the hot_pixel \\(0.01\\)"):
        load_event_frames(aedat, hot_pixel=0.01)
    with pytest.raises(TraverseError, match=f"{AEDAT}: no events left"):
        load_traverse(aedat, EventFrameOptions(hot_pixel=0.01), progress=False)


@pytest.mark.parametrize("option, value, field", [
    ("window_ms", float("inf"), "window_ms"), ("window_ms", 1e300, "window_ms"),
    ("anchor", -10 ** 36, "anchor"), ("frame_size", (8,), "frame_size"),
    ("start_ms", 1e300, "start_ms"), ("duration_ms", float("nan"), "duration_ms"),
])
def test_event_frame_options_are_bounded(aedat, option, value, field):
    with pytest.raises(ValueError, match=f"{field} must be"):
        load_event_frames(aedat, **{option: value})
    with pytest.raises(TraverseError, match=f"{AEDAT}: {field} must be"):
        load_traverse(aedat, EventFrameOptions(**{option: value}), progress=False)


def _flipped_aedat(path, bits):
    """A 4,000-event AEDAT 2.0 cut of the DVS128 recording with two time bits flipped."""
    from conftest import shared_data

    src = shared_data("events", AEDAT).read_bytes()
    i = 0
    while src[i:i + 1] == b"#":
        i = src.index(b"\n", i) + 1
    body = bytearray(src[i:i + 8 * 4000])
    for ev, bit in zip((1333, 2666), bits):
        at = 8 * ev + 4  # big-endian int32 address, then the int32 time stamp
        body[at:at + 4] = (int.from_bytes(body[at:at + 4], "big") ^ (1 << bit)).to_bytes(4, "big")
    path.write_bytes(src[:i] + bytes(body))
    return path


@pytest.mark.filterwarnings("ignore:.*backward time steps")
def test_mostly_empty_event_frames_are_bounded_by_the_events(tmp_path):
    path = _flipped_aedat(tmp_path / "cut.aedat", (27, 26))  # 13,475 windows, 82 with events
    with pytest.raises(TraverseError, match="cut.aedat: 13,475 frames of which 13,393 are "
                                            "empty windows"):
        load_traverse(path, progress=False)  # at sensor size: 0.8 GiB, 1.1 GB peak before
    small = load_traverse(path, progress=False, size=(32, 64))  # 110 MB: kept
    assert small.shape == (13475, 32, 64) and float(small[100:1000].abs().sum()) == 0


# ------------------------------------------------------------------ Event-LAB (item 16)

from torchseq.integrations.eventlab import (  # noqa: E402
    EventLabError,
    TorchseqBaseline,
    resolve_settings,  # noqa: E402
)


@pytest.mark.parametrize("settings, field", [
    (dict(engines=5), "engines"), (dict(seqslam=[1]), "seqslam"),
    (dict(frame_size=["a", "b"]), "frame_size"), (dict(seqslam={"ds": 10 ** 9}), "ds"),
    (dict(seqslam={"image_size": [10 ** 6, 10 ** 6]}), "image_size"),
    (dict(neural={"hidden": "x"}), "neural settings"), (dict(hot_pixel=float("inf")),
                                                        "hot_pixel"),
    (dict(event_mode=["count"]), "event_mode"), ("x", "mapping"),
])
def test_eventlab_settings_of_the_wrong_type_are_the_adapters_error(settings, field):
    with pytest.raises(EventLabError, match=field):
        resolve_settings(settings)


class _Sequence:
    def __init__(self, path):
        self.path = path

    def get_dataset_info(self):
        return {"dataset_name": "d", "sequence_name": "s", "hdf5_path": str(self.path)}


@pytest.mark.parametrize("dataset_config, field", [
    ({"dataset": {"resolution": ["a", "b"]}}, "dataset.resolution"),
    ({"other": {"offset": {"s": float("inf")}}}, "other.offset.s"),
    ({"other": {"offset": {"s": "soon"}}}, "other.offset.s"),
    ({"format": {"data": {"timestamp_val": 5}}}, "timestamp_val"),
])
def test_eventlab_dataset_config_fields_are_checked(tmp_path, aedat, dataset_config, field):
    class Baseline(TorchseqBaseline):
        pass

    b = Baseline(settings={}, outdir=str(tmp_path / "out"))
    with pytest.raises(EventLabError, match=field):
        b.format_data({}, dataset_config, _Sequence(aedat), _Sequence(aedat), 10.0)


# ------------------------------------------------------------------ checkpoints (17, 21)

from torchseq.neural import NeuralConfig, NeuralError, NeuralSeqSLAM  # noqa: E402
from torchseq.neural.checkpoint import FORMAT, checksum  # noqa: E402


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    from conftest import coarse_units_expected

    from torchseq.demo import make_demo

    demo = make_demo(n_reference=40, size=(48, 64), seed=3)
    model = NeuralSeqSLAM(NeuralConfig(hidden=256, n_output=20))  # units of 2 frames: search
    with coarse_units_expected():
        model.fit(demo.reference, log=False)
    assert model.search is not None
    path = tmp_path_factory.mktemp("ckpt") / "model.pt"
    model.save(path)
    return torch.load(path, weights_only=True), demo.query[:8]


def _resealed(blob, tmp_path, **tensors):
    sd = dict(blob["state_dict"], **tensors)
    mutant = dict(blob, state_dict=sd)
    mutant["checksum"] = checksum(FORMAT, mutant["config"], sd, mutant["extra"])
    torch.save(mutant, tmp_path / "mutant.pt")
    return tmp_path / "mutant.pt"


def test_resealed_checkpoint_with_huge_ring_shift_is_refused(checkpoint, tmp_path):
    blob, query = checkpoint
    path = _resealed(blob, tmp_path, **{"ring.shift": blob["state_dict"]["ring.shift"] * 1e30})
    with pytest.raises(NeuralError, match="mutant.pt: ring.shift has negative entries or rows "
                                          "summing to more than 1"):
        NeuralSeqSLAM.load(path)


@pytest.mark.parametrize("name, change", [
    ("unit_to_reference", lambda t: t.flip(0)),  # the unit search's spans, reversed
    ("unit_to_reference", lambda t: t + 1),
    ("unit_centre", lambda t: t + 5),
    ("l3.mask", lambda t: t * 2), ("cohorts", lambda t: t * 0),
    ("l3.weight", lambda t: t * 1e9),
])
def test_resealed_checkpoint_with_values_fit_cannot_make_is_refused(checkpoint, tmp_path, name,
                                                                   change):
    blob, _ = checkpoint
    path = _resealed(blob, tmp_path, **{name: change(blob["state_dict"][name])})
    with pytest.raises(NeuralError, match=f"mutant.pt: {name} .*not a fitted model's values"):
        NeuralSeqSLAM.load(path)


def test_resealed_checkpoint_of_fit_values_still_loads(checkpoint, tmp_path):
    blob, query = checkpoint
    path = _resealed(blob, tmp_path)
    res = NeuralSeqSLAM.load(path).run(query)
    assert torch.isfinite(res.activity).all()


# ------------------------------------------------------------------ NIR read bound (item 18)

def test_read_nir_is_bounded_in_time_and_memory(tmp_path, monkeypatch):
    pytest.importorskip("nir", reason="the 'nir' package is absent: pip install 'torchseq[nir]'")
    import time

    import torchseq.export.nir_export as nir_export

    class Slow:  # a read that libhdf5 would hold for minutes on a damaged file
        @staticmethod
        def read(path):
            time.sleep(30)

    class Greedy:
        @staticmethod
        def read(path):
            return bytearray(8 << 30)

    (tmp_path / "model.nir").write_bytes(b"\x89HDF\r\n\x1a\n")
    monkeypatch.setattr(nir_export, "READ_SECONDS", 1.0, raising=False)
    monkeypatch.setattr(nir_export, "require_nir", lambda: Slow)
    start = time.monotonic()
    with pytest.raises(nir_export.NIRExportError, match="model.nir: .*took more than 1 s"):
        nir_export.read_nir(tmp_path / "model.nir")
    assert time.monotonic() - start < 10
    monkeypatch.setattr(nir_export, "require_nir", lambda: Greedy)
    with pytest.raises(nir_export.NIRExportError, match="model.nir: .*needs more than 2048 MiB"):
        nir_export.read_nir(tmp_path / "model.nir")
