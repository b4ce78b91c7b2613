"""Damaged and crafted ``.nir`` files: ``read_nir`` returns a graph it can run, or refuses.

The NIR family of the fuzz tests. Hypothesis mutates a real ``model.nir`` (the tiny spiking
model of ``tests/test_spiking.py``): hostile values written into each metadata field with
h5py (integer and float arrays, strings, bytes, booleans, out-of-range and non-finite
numbers), metadata fields deleted, and bytes overwritten anywhere in the file. Every read
must either raise ``NIRExportError`` naming the file, or return a graph whose metadata parses
(``graph_metadata``: whole ``units`` and ``levels``, finite positive ``dt``, a ring of
``units * levels`` outputs), so that a consumer can be sized from it; no other exception
(numpy's "truth value of an array is ambiguous" escaped for an integer-array ``format``).
"""

import math

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from spiking_helpers import tiny

from torchseq.export.nir_export import FORMAT, NIRExportError, graph_metadata, read_nir, write_nir

pytest.importorskip("nir", reason="the 'nir' package is absent: pip install 'torchseq[nir]'")

FUZZ = settings(deadline=None, database=None, derandomize=True,
                suppress_health_check=list(HealthCheck))
FIELDS = ["format", "units", "levels", "dt", "steps_per_frame", "unit_centre",
          "uniqueness_window", "calibration"]


@pytest.fixture(scope="module")
def original(tmp_path_factory):
    model, demo, sp = tiny()
    path = tmp_path_factory.mktemp("nirfuzz") / "tiny.nir"
    write_nir(sp, path)
    return path.read_bytes(), sp


def _mutant(tmp_path_factory, data: bytes) -> str:
    path = tmp_path_factory.mktemp("mut") / "mutant.nir"
    path.write_bytes(data)
    return str(path)


def _set_field(path: str, field: str, value) -> None:
    with h5py.File(path, "r+") as f:
        meta = f["node/metadata"]
        if field in meta:
            del meta[field]
        if value is not None:
            meta[field] = value


def _accepted_is_sound(graph, sp) -> None:
    meta = graph_metadata(graph)  # must not raise on an accepted graph
    assert meta["units"] * meta["levels"] == sp.n_units * sp.levels
    assert math.isfinite(meta["dt"]) and meta["dt"] > 0
    assert graph.metadata["format"] == FORMAT


HOSTILE = st.one_of(
    st.sampled_from([0, -1, 1, 2, 20, 6, 10**9, 2**62, -2**63, 0.0, -0.0, 1e-300, 1e-4, 0.5,
                     1.0, 20.0, 1e308, math.inf, -math.inf, math.nan, True, False, "", "20",
                     "1e-4", FORMAT, b"\xff\xfe", FORMAT.encode(), "torchseq.spiking-nir/2"]),
    st.integers(-2**63, 2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=30),
    hnp.arrays(st.sampled_from([np.int64, np.int8, np.float64, np.float32, np.bool_]),
               hnp.array_shapes(min_dims=1, max_dims=2, max_side=4)),
    st.just(np.array([FORMAT.encode()])), st.just(np.array([20])), st.just(np.array(20.0)),
)


def test_an_integer_array_format_is_an_export_error(original, tmp_path_factory):
    # the fuzzer's finding: `fmt != FORMAT` on an array raised numpy's bare ValueError
    path = _mutant(tmp_path_factory, original[0])
    _set_field(path, "format", np.arange(3))
    with pytest.raises(NIRExportError, match="format"):
        read_nir(path)


@pytest.mark.parametrize("field, value, match", [
    ("units", "twenty", "units"), ("units", np.arange(2), "units"), ("units", 21, "120 values"),
    ("levels", 0, "levels"), ("levels", 6.0, "levels"), ("dt", math.nan, "dt"),
    ("dt", -1e-4, "dt"), ("dt", "1e-4", "dt"), ("dt", np.ones(2), "dt"),
    ("steps_per_frame", 4, "steps_per_frame"), ("units", None, "lacks 'units'"),
    ("dt", None, "lacks 'dt'"),
])
def test_metadata_that_cannot_be_parsed_is_refused(original, tmp_path_factory, field, value,
                                                   match):
    path = _mutant(tmp_path_factory, original[0])
    _set_field(path, field, value)
    with pytest.raises(NIRExportError, match=match) as err:
        read_nir(path)
    assert path in str(err.value)


@settings(FUZZ, max_examples=30)
@given(field=st.sampled_from(FIELDS), value=st.one_of(HOSTILE, st.none()))
@example(field="format", value=np.arange(3))  # the finding: numpy's bare ValueError
@example(field="format", value=np.array([1.5, 2.0]))
@example(field="units", value=np.array([20, 20]))
@example(field="levels", value=6.5)
@example(field="dt", value=math.nan)
def test_hostile_metadata_is_refused_or_sound(original, tmp_path_factory, field, value):
    data, sp = original
    path = _mutant(tmp_path_factory, data)
    try:
        _set_field(path, field, value)
    except (TypeError, ValueError):  # h5py cannot store it: nothing to read
        return
    try:
        graph = read_nir(path)
    except NIRExportError as err:
        assert path in str(err)
        return
    _accepted_is_sound(graph, sp)


@settings(FUZZ, max_examples=30)
@given(edits=st.lists(st.tuples(st.integers(0, 2**40), st.binary(min_size=1, max_size=8)),
                      min_size=1, max_size=4))
def test_overwritten_bytes_are_refused_or_sound(original, tmp_path_factory, edits):
    data, sp = original
    mutant = bytearray(data)
    for where, new in edits:
        at = where % len(mutant)
        mutant[at:at + len(new)] = new[:len(mutant) - at]
    path = _mutant(tmp_path_factory, bytes(mutant))
    try:
        graph = read_nir(path)
    except NIRExportError as err:
        assert path in str(err)
        return
    _accepted_is_sound(graph, sp)
