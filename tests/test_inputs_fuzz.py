"""Property-based tests of the newer input surfaces: maps, descriptor files, hooks, dataset
roots and Event-LAB settings (issue 35).

Each family gives a reader or a settings object hostile input built from a valid one (a map,
descriptor files written by torchseq's own writers, a dataset root, the default settings):
the result is well-formed data or the module's own error naming the file or field, never a
foreign exception, a non-finite result or a huge allocation (every example runs under an
address-space cap of 2 GiB more than the process holds).
"""

import io
import json
import shutil
import zipfile

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from torchseq.seqslam import SeqSLAMConfig

FUZZ = settings(max_examples=25, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])
HOSTILE = st.one_of(
    st.sampled_from([None, True, 0, -1, 1, 2, 7, 2**31, 2**63, 10**13, 10**400, -10**36, 0.5,
                     1e9, 1e300, -1e300, "", "a", "1", "x" * 300, "../x", [], [1], [10**6, 10**6],
                     ["a", "b"], [1, 2, 3], {}, {"a": 1}]),
    st.integers(), st.floats(allow_nan=False, allow_infinity=False), st.text(max_size=20),
)


pytestmark = pytest.mark.usefixtures("memory_cap")  # conftest: address space capped


def mutate(data: bytes, edits, cut) -> bytes:
    b = bytearray(data)
    for where, value in edits:
        b[int(where * len(b))] = value
    return bytes(b[:int(cut * len(b))] if cut is not None else b)


EDITS = st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255)),
                 min_size=1, max_size=8)
CUTS = st.one_of(st.none(), st.floats(0, 1))


# ------------------------------------------------------------------ maps

faiss = pytest.importorskip(
    "faiss", reason="maps hold a FAISS index (pip install 'torchseq[faiss]'); not installed")

from torchseq.maps import MapError, build_map, load_map  # noqa: E402
from torchseq.maps.format import file_sha256, manifest_checksum  # noqa: E402


@pytest.fixture(scope="module")
def map_folder(tmp_path_factory):
    rng = np.random.default_rng(0)
    ref = torch.tensor(rng.normal(0, 1, (60, 8)), dtype=torch.float32)
    m = build_map(ref, tmp_path_factory.mktemp("map") / "map", SeqSLAMConfig(ds=4),
                  shard_size=25, index="flat", record={"source": "x", "frame_size": [8, 8]})
    return m.path


def _use(folder):
    """Open and verify a map; once verify passes, every use must work (no MapError after)."""
    try:
        m = load_map(folder)
        m.verify()
    except MapError as err:
        assert str(folder) in str(err)
        return
    rows = m.descriptors()
    assert rows.shape == (m.n_places, m.dim) and bool(torch.isfinite(rows).all())
    assert m.index().size == m.n_places


MANIFEST_FIELDS = ["n_places", "dim", "shard_size", "dtype", "version", "reference.frame_size",
                   "index.options", "index.kind", "shards.0.file", "shards.0.bytes",
                   "shards.1.start", *[f"config.{k}" for k in SeqSLAMConfig().__dict__]]


@FUZZ
@given(field=st.sampled_from(MANIFEST_FIELDS), value=HOSTILE)
@example(field="config.ds", value=10**9)  # the reproducers (items 1, 2, 5)
@example(field="n_places", value=10**400)
@example(field="reference.frame_size", value=["a", "b"])
@example(field="index.options", value={"nprobe": -1})
def test_resealed_manifest_values_are_used_or_map_errors(map_folder, tmp_path_factory, field,
                                                         value):
    folder = tmp_path_factory.mktemp("m") / "map"
    shutil.copytree(map_folder, folder)
    m = json.loads((folder / "map.json").read_text())
    *outer, last = field.split(".")
    target = m
    for key in outer:
        target = target[int(key)] if isinstance(target, list) else target[key]
    target[int(last) if isinstance(target, list) else last] = value
    m["checksum"] = manifest_checksum(m)
    try:
        (folder / "map.json").write_text(json.dumps(m))
    except (ValueError, OverflowError):  # JSON cannot hold it
        return
    _use(folder)


NAN_AT = [(900 + i + 0.5) / 928 for i in range(4)]  # a float of shard 0 (128 + 25 x 8 x 4 B)


@FUZZ
@given(name=st.sampled_from(["map.json", "shard-00000.npy", "shard-00002.npy", "index.npy"]),
       edits=EDITS, cut=CUTS, reseal=st.booleans())
@example(name="shard-00000.npy", edits=[(w, 255) for w in NAN_AT], cut=None, reseal=True)
def test_damaged_map_files_are_used_or_map_errors(map_folder, tmp_path_factory, name, edits,
                                                  cut, reseal):
    folder = tmp_path_factory.mktemp("m") / "map"
    shutil.copytree(map_folder, folder)
    path = folder / name
    path.write_bytes(mutate(path.read_bytes(), edits, cut))
    if reseal and name != "map.json":  # a crafted map: the manifest agrees with the file
        m = json.loads((folder / "map.json").read_text())
        entry = m["index"] if name == "index.npy" else m["shards"][int(name[6:11])]
        entry.update(bytes=max(1, path.stat().st_size), sha256=file_sha256(path))
        m["checksum"] = manifest_checksum(m)
        (folder / "map.json").write_text(json.dumps(m))
    _use(folder)


# ------------------------------------------------------------------ descriptor files

h5py = pytest.importorskip("h5py", reason="HDF5 descriptors need h5py (torchseq[hdf5])")

from torchseq.descriptors import DescriptorError, describe, load_descriptors  # noqa: E402


@pytest.fixture(scope="module")
def descriptor_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("desc")
    np.savez_compressed(d / "only.npz", feats=X)
    with h5py.File(d / "d.h5", "w") as f:
        f.create_dataset("descriptors", data=X, chunks=(4, 6), compression="gzip")
    files = {p.name: p.read_bytes() for p in d.iterdir()}
    assert zipfile.is_zipfile(io.BytesIO(_npz_bytes()))
    return {**files, "d.npy": _npy_bytes(), "d.npz": _npz_bytes()}


X = np.random.default_rng(0).normal(0, 1, (12, 6)).astype(np.float32)


def _offset(data: bytes, find: bytes, shift: int = 0) -> float:
    """Where (as a fraction of the file, for ``mutate``) ``find`` starts, plus ``shift``."""
    return (data.index(find) + shift + 0.5) / len(data)


def _npy_bytes() -> bytes:
    buf = io.BytesIO()
    np.save(buf, X)
    return buf.getvalue()


def _npz_bytes() -> bytes:
    buf = io.BytesIO()
    np.savez(buf, descriptors=X)
    return buf.getvalue()


@FUZZ
@given(name=st.sampled_from(["d.npy", "d.npz", "only.npz", "d.h5"]), edits=EDITS, cut=CUTS)
@example(name="d.npy", edits=[(_offset(_npy_bytes(), b"<f4"), ord(">"))], cut=None)  # item 7
@example(name="d.npz", edits=[(_offset(_npz_bytes(), b"PK\x01\x02", 6), 100)], cut=None)
def test_damaged_descriptor_files_load_or_are_descriptor_errors(descriptor_files,
                                                                tmp_path_factory, name, edits,
                                                                cut):
    path = tmp_path_factory.mktemp("d") / name
    path.write_bytes(mutate(descriptor_files[name], edits, cut))
    try:
        x = load_descriptors(path)
    except DescriptorError as err:
        assert str(path) in str(err)
        return
    assert x.dim() == 2 and min(x.shape) > 0 and bool(torch.isfinite(x).all())


# ------------------------------------------------------------------ descriptor hooks

HOOK_OUTPUTS = st.one_of(
    HOSTILE,
    st.builds(lambda shape, dtype: np.ones(shape, dtype),
              st.lists(st.integers(0, 4), max_size=3).map(tuple),
              st.sampled_from(["<f4", ">f4", ">f8", "<i2", ">u2", "u8", "f2", "c8", "?",
                               "U3", "M8[s]", np.longdouble])),
    st.builds(lambda shape: torch.ones(shape), st.lists(st.integers(0, 4), max_size=3)),
)


@FUZZ
@given(out=HOOK_OUTPUTS, frames=st.integers(1, 3))
def test_hook_outputs_are_descriptors_or_descriptor_errors(out, frames):
    try:
        x = describe([np.zeros((4, 4))] * frames, lambda batch: out)
    except DescriptorError as err:
        assert "descriptor" in str(err) or "hook" in str(err)
        return
    assert x.shape[0] == frames and bool(torch.isfinite(x).all())


# ------------------------------------------------------------------ dataset roots

from torchseq.datasets import DatasetError, open_dataset  # noqa: E402


@FUZZ
@given(dataset=st.sampled_from(["nordland", "gardens-point", "vpr-bench", "brisbane-event"]),
       splits=st.tuples(st.one_of(st.none(), HOSTILE), st.one_of(st.none(), HOSTILE)),
       tolerance=st.one_of(st.none(), st.floats(0, 10)))
def test_dataset_roots_open_or_are_dataset_errors(tmp_path_factory, dataset, splits, tolerance):
    import cv2

    root = tmp_path_factory.mktemp("root")
    for split in ("summer", "winter", "ref", "query", "day_right", "night_right"):
        (root / split).mkdir()
        cv2.imwrite(str(root / split / "0.png"), np.zeros((4, 6), np.uint8))
    try:
        ds = open_dataset(dataset, root, *splits, tolerance=tolerance)
    except DatasetError as err:
        assert dataset in str(err) or str(root) in str(err)
        return
    assert len(ds.reference) == len(ds.query) == 1


# ------------------------------------------------------------------ Event-LAB settings

from torchseq.integrations.eventlab import DEFAULTS, EventLabError, resolve_settings  # noqa: E402

SETTINGS_FIELDS = [*DEFAULTS, "seqslam.ds", "seqslam.vmax", "seqslam.image_size",
                   "seqslam.speed_ratio", "seqslam.metric", "neural.hidden",
                   "neural.input_size", "neural.n_output"]


@FUZZ
@given(changes=st.dictionaries(st.sampled_from(SETTINGS_FIELDS), HOSTILE, max_size=3))
def test_eventlab_settings_resolve_or_are_eventlab_errors(changes):
    settings_ = {}
    for field, value in changes.items():
        outer, _, inner = field.partition(".")
        if inner:
            settings_.setdefault(outer, {})
            if isinstance(settings_[outer], dict):
                settings_[outer][inner] = value
        else:
            settings_[outer] = value
    try:
        out = resolve_settings(settings_)
    except EventLabError as err:
        assert str(err)
        return
    from torchseq.integrations.eventlab import neural_config, seqslam_config

    seqslam_config(out)
    neural_config(out)
