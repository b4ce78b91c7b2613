"""Checkpoint integrity: a mutated checkpoint loads as the exact same model or is refused.

Hypothesis mutates a real saved checkpoint (a small model fitted on the demo route): bit
flips in the tensor data and anywhere in the file, hostile config values and tensors
written back with ``torch.save``. Every load must either raise ``NeuralError`` naming the
file, or give the very model that was saved. Where the mutant's checksum is recomputed (a
crafted file, not a corrupt one) an accepted model must still decide without NaN. No
mutant may make the loader allocate much more than the file holds (peak RSS).
"""

import math
import resource
import struct
import warnings
import zipfile

import pytest
import torch
from conftest import coarse_units_expected
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchseq.demo import make_demo
from torchseq.neural import NeuralConfig, NeuralError, NeuralSeqSLAM
from torchseq.neural.checkpoint import FORMAT, FORMAT_V1, checksum, expected_tensors

PROPERTY = settings(deadline=None, database=None, suppress_health_check=list(HealthCheck))


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    demo = make_demo(n_reference=40, size=(48, 64), seed=3)
    model = NeuralSeqSLAM(NeuralConfig(hidden=256, n_output=20))
    with coarse_units_expected():  # a small model: units of several frames
        model.fit(demo.reference, log=False)
    path = tmp_path_factory.mktemp("ckpt") / "model.pt"
    model.save(path, extra={"route": "demo", "frames": 40})
    blob = torch.load(path, weights_only=True)
    return path, path.read_bytes(), blob, demo.query[:6]


def _data_ranges(path) -> list[tuple[int, int]]:
    """Byte ranges of the tensor storages (the zip's ``data/N`` records, stored raw)."""
    out = []
    with zipfile.ZipFile(path) as z, open(path, "rb") as f:
        for info in z.infolist():
            if "/data/" in info.filename and info.file_size:
                f.seek(info.header_offset + 26)
                name_len, extra_len = struct.unpack("<HH", f.read(4))
                start = info.header_offset + 30 + name_len + extra_len
                out.append((start, start + info.file_size))
    return out


def _same_model(model, original) -> None:
    assert model.config.to_dict() == original["config"]
    sd = model.state_dict()
    assert set(sd) == set(original["state_dict"])
    for name, t in original["state_dict"].items():
        assert sd[name].dtype == t.dtype and torch.equal(sd[name], t), name
    assert model.extra == original["extra"]


def _load_or_refuse(path):
    """The model, or None after a NeuralError that names the file; anything else fails."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # a version-1 warning would be a wrong format
            return NeuralSeqSLAM.load(path)
    except NeuralError as err:
        assert str(path) in str(err), err
        return None


def test_round_trip_is_exact_and_checksummed(saved, tmp_path):
    path, _, blob, query = saved
    assert blob["format"] == FORMAT
    assert blob["checksum"] == checksum(FORMAT, blob["config"], blob["state_dict"], blob["extra"])
    model = NeuralSeqSLAM.load(path)
    _same_model(model, blob)
    assert torch.isfinite(model.run(query).activity).all()


def test_one_flipped_bit_in_a_weight_is_refused(saved, tmp_path):
    path, data, _, _ = saved
    start, _ = _data_ranges(path)[0]
    mutant = bytearray(data)
    mutant[start + 5] ^= 0x01  # a low mantissa bit: the model would still run, differently
    bad = tmp_path / "flipped.pt"
    bad.write_bytes(bytes(mutant))
    with pytest.raises(NeuralError, match="flipped.pt: checksum mismatch"):
        NeuralSeqSLAM.load(bad)


def test_a_huge_tensor_on_one_stored_element_is_refused(saved, tmp_path):
    _, _, blob, _ = saved
    sd = dict(blob["state_dict"], **{"l1.weight": torch.zeros(()).expand(2**24, 768)})
    torch.save(dict(blob, state_dict=sd), tmp_path / "huge.pt")
    with pytest.raises(NeuralError, match="huge.pt: tensor l1.weight .* not stored densely"):
        NeuralSeqSLAM.load(tmp_path / "huge.pt")


@settings(PROPERTY, max_examples=50)
@given(flips=st.lists(st.tuples(st.integers(0, 2**40), st.integers(0, 7)), min_size=1,
                      max_size=4),
       anywhere=st.booleans())
def test_flipped_bits_load_the_same_model_or_are_refused(saved, tmp_path_factory, flips,
                                                         anywhere):
    path, data, blob, _ = saved
    ranges = [(0, len(data))] if anywhere else _data_ranges(path)
    mutant = bytearray(data)
    for where, bit in flips:
        start, end = ranges[where % len(ranges)]
        mutant[start + (where >> 8) % (end - start)] ^= 1 << bit
    bad = tmp_path_factory.mktemp("flip") / "mutant.pt"
    bad.write_bytes(bytes(mutant))
    model = _load_or_refuse(bad)
    if model is not None:  # e.g. a flip in an unused zip field
        _same_model(model, blob)


HOSTILE = st.one_of(
    st.sampled_from([None, True, False, "", "zscore", "1", [], [24], [24, 32, 1], ["a", "b"],
                     [2**40, 1], [24.0, 32.0], {}, {"a": 1}, 0, -1, 1, 2, 3, 8, 10**9, 2**62,
                     -2**63, 0.0, -0.0, 1e-300, 0.5, 1.0, 1.5, 1e308, math.inf, -math.inf,
                     math.nan]),
    st.integers(), st.floats(allow_nan=True, allow_infinity=True),
)


@settings(PROPERTY, max_examples=80)
@given(field=st.sampled_from(sorted(NeuralConfig().to_dict())), value=HOSTILE,
       reseal=st.booleans())
def test_hostile_config_values_are_refused_or_harmless(saved, tmp_path_factory, field, value,
                                                       reseal):
    path, _, blob, query = saved
    mutant = dict(blob, config=dict(blob["config"], **{field: value}))
    if reseal:  # a crafted file: its checksum agrees with its contents
        mutant["checksum"] = checksum(FORMAT, mutant["config"], mutant["state_dict"],
                                      mutant["extra"])
    bad = tmp_path_factory.mktemp("cfg") / "mutant.pt"
    torch.save(mutant, bad)
    model = _load_or_refuse(bad)
    if model is None:
        return
    if not reseal:
        _same_model(model, blob)  # only a value equal to the saved one can pass the checksum
        return
    res = model.run(query)
    assert torch.isfinite(res.activity).all() and torch.isfinite(res.matches.confidence).all()


@settings(PROPERTY, max_examples=40)
@given(name=st.sampled_from(sorted(expected_tensors(NeuralConfig(), 1))),
       shape=st.lists(st.sampled_from([0, 1, 2, 19, 20, 21, 256, 768, 2**20]), max_size=3),
       dtype=st.sampled_from([torch.float32, torch.float64, torch.int64, torch.uint8,
                              torch.bool]),
       fill=st.sampled_from([0.0, 1.0, math.nan, math.inf]))
def test_foreign_tensors_are_refused(saved, tmp_path_factory, name, shape, dtype, fill):
    path, _, blob, _ = saved
    if math.prod(shape) > 2**16:  # a huge shape on one stored element (stride 0)
        t = torch.zeros((), dtype=dtype).expand(shape)
    elif dtype.is_floating_point:
        t = torch.full(shape, fill, dtype=dtype)
    else:
        t = torch.zeros(shape, dtype=dtype)
    sd = dict(blob["state_dict"], **{name: t})
    mutant = dict(blob, state_dict=sd)
    if math.prod(shape) <= 2**16:  # (hashing a stride-0 giant would allocate it, in the test)
        mutant["checksum"] = checksum(FORMAT, mutant["config"], sd, mutant["extra"])
    bad = tmp_path_factory.mktemp("sd") / "mutant.pt"
    torch.save(mutant, bad)
    model = _load_or_refuse(bad)
    if model is not None:  # a resealed file of the right shapes is a valid model: exactly it
        _same_model(model, mutant)


@pytest.mark.parametrize("field, value", [("ring_spread", 2**24), ("uniqueness_window", 10**9)])
def test_huge_reach_in_a_resealed_config_runs_like_the_ring_it_covers(saved, tmp_path, field,
                                                                    value):
    # a window or lag reaching past the ring means "every unit": it must not size a tensor
    # (found by the hostile-config property: 16 GB for ring_spread 2**24 in band_diagonals)
    path, _, blob, query = saved
    n = blob["state_dict"]["unit_to_reference"].shape[0]
    mutant = dict(blob, config=dict(blob["config"], **{field: value}))
    mutant["checksum"] = checksum(FORMAT, mutant["config"], mutant["state_dict"],
                                  mutant["extra"])
    torch.save(mutant, tmp_path / "reach.pt")
    same = dict(blob, config=dict(blob["config"], **{field: n}))
    same["checksum"] = checksum(FORMAT, same["config"], same["state_dict"], same["extra"])
    torch.save(same, tmp_path / "ring.pt")
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for kernels in ("auto", "portable"):
        a = NeuralSeqSLAM.load(tmp_path / "reach.pt")
        b = NeuralSeqSLAM.load(tmp_path / "ring.pt")
        ra, rb = a.inference(kernels).run(query), b.inference(kernels).run(query)
        assert torch.equal(ra.matches.reference, rb.matches.reference)
        assert torch.equal(ra.matches.confidence, rb.matches.confidence)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 512 * 1024  # KiB


def test_no_mutant_allocated_more_than_the_file_holds(saved):
    # runs after the properties above (file order): none pushed the peak RSS up by a model
    # the size a hostile config asks for (hidden = 2**24 alone would be 48 GiB of weights)
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    assert peak_mib < 4096, f"peak RSS {peak_mib:.0f} MiB"


def test_version_1_files_load_with_a_warning(saved, tmp_path):
    path, _, blob, _ = saved
    old = {k: v for k, v in blob.items() if k != "checksum"}
    old["format"] = FORMAT_V1
    torch.save(old, tmp_path / "v1.pt")
    with pytest.warns(UserWarning, match="no checksum"):
        model = NeuralSeqSLAM.load(tmp_path / "v1.pt")
    _same_model(model, blob)
    old["checksum"] = "sha256:00"  # a v1 file that carries a checksum must match it
    torch.save(old, tmp_path / "v1c.pt")
    with pytest.raises(NeuralError, match="checksum mismatch"):
        NeuralSeqSLAM.load(tmp_path / "v1c.pt")


@pytest.mark.parametrize("field, value, match", [
    ("hidden", "3072", "hidden must be an integer, got str"),
    ("hidden", 2**40, "hidden must be in 1..16777216"),
    ("hidden", True, "hidden must be an integer, got bool"),
    ("input_size", [24], "input_size must be two integers"),
    ("input_size", [24.0, 32.0], "input_size must be two integers"),
    ("eps", math.nan, "eps must be a finite number in \\(0, 1\\]"),
    ("ring_gain", math.inf, "ring_gain must be a finite number"),
    ("ring_stay", math.nan, "ring_stay must be a finite number"),
    ("ring_spread_decay", math.inf, "ring_spread_decay must be a finite number"),
    ("rectify", 1, "rectify must be one of False, True"),
    ("hebbian", None, "hebbian must be one of 'mean', 'centred'"),
    ("readout", "middle", "readout must be one of 'centre', 'interpolate'"),
    ("seed", 0.5, "seed must be an integer"),
    ("n_output", 2**24, "n_output x hidden = .* exceed"),
])
def test_bad_config_fields_name_the_field(saved, tmp_path, field, value, match):
    _, _, blob, _ = saved
    mutant = dict(blob, config=dict(blob["config"], **{field: value}))
    torch.save(mutant, tmp_path / "m.pt")
    with pytest.raises(NeuralError, match=f"m.pt: bad config: {match}"):
        NeuralSeqSLAM.load(tmp_path / "m.pt")
    with pytest.raises(NeuralError, match=match):
        NeuralConfig(**{field: value}).validate()


def test_a_model_with_an_inference_module_saves_and_loads_as_the_same_model(saved, tmp_path):
    # the inference module's derived buffers must not enter the checkpoint (when fold() kept
    # it inside the model they did: load then refused the file as "unexpected _inference.*")
    path, _, blob, query = saved
    model = NeuralSeqSLAM.load(path)
    inf = model.inference()
    before = inf.run(query)
    assert not [k for k in model.state_dict() if "inference" in k]
    model.save(tmp_path / "folded.pt", extra=blob["extra"])
    again = NeuralSeqSLAM.load(tmp_path / "folded.pt")
    _same_model(again, blob)
    after = again.run(query)
    assert torch.equal(before.matches.reference, after.matches.reference)
