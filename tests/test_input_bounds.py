"""Every reader and settings object refuses garbage in one line of its own error (issue 35).

One test per hostile input found by fuzzing the newer input surfaces (reference maps,
descriptor files and hooks, dataset roots, event frames, Event-LAB settings, checkpoints,
NIR): each names the file or field and raises the module's own error, before anything is
sized from what the input declares. Allocations run under an address-space cap, so a
declared-size allocation fails the test as a ``MemoryError`` instead of swapping.
"""

import json
import resource
import shutil

import numpy as np
import pytest
import torch

from torchseq.seqslam import SeqSLAMConfig
from torchseq.seqslam.search import velocities


@pytest.fixture(scope="module", autouse=True)
def memory_cap():
    """Cap the address space at what the process uses now plus 2 GiB (every test here)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    used = int(open("/proc/self/statm").read().split()[0]) * resource.getpagesize()
    cap = used + (2 << 30)
    if hard != resource.RLIM_INFINITY:
        cap = min(cap, hard)
    resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    yield
    resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


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
