"""Integer file format v1 and v2: dict/file round trips and every rejection with a clear error."""

import struct
import zlib

import numpy as np
import pytest
from export_helpers import small_setup

from torchseq.export.int_format import (
    FORMAT_VERSION,
    MAGIC,
    IntegerFormatError,
    IntegerModel,
    decode,
    encode,
    read_integer_model,
    write_integer_model,
)


@pytest.fixture(scope="module")
def model() -> IntegerModel:
    return small_setup()[4]


def _same(a: IntegerModel, b: IntegerModel) -> None:
    assert a.params == b.params
    assert set(a.arrays) == set(b.arrays)
    for name in a.arrays:
        assert a.arrays[name].dtype == b.arrays[name].dtype, name
        assert np.array_equal(a.arrays[name], b.arrays[name]), name


def test_dict_round_trip(model):
    d = model.to_dict()
    assert d["format_version"] == 1 < FORMAT_VERSION  # the centre read-out: still version 1
    assert "readout" not in d["params"]
    _same(IntegerModel.from_dict(d), model)


def test_file_round_trip(model, tmp_path):
    path = tmp_path / "m.tsq"
    size = write_integer_model(path, model)
    assert size == path.stat().st_size
    assert path.read_bytes()[:8] == MAGIC
    _same(read_integer_model(path), model)
    assert encode(read_integer_model(path)) == path.read_bytes()  # byte-stable
    assert [p.name for p in tmp_path.iterdir()] == ["m.tsq"]  # no temp file left behind


def _reseal(data: bytearray) -> bytes:
    """Recompute the header and file CRCs after an edit (to reach the deeper checks)."""
    data[24:28] = struct.pack("<I", zlib.crc32(bytes(data[:24])))
    data[-4:] = struct.pack("<I", zlib.crc32(bytes(data[:-4])))
    return bytes(data)


def test_bad_magic(model):
    data = bytearray(encode(model))
    data[0:4] = b"NOPE"
    with pytest.raises(IntegerFormatError, match="magic"):
        decode(bytes(data))


def test_unknown_version(model):
    data = bytearray(encode(model))
    data[8:12] = struct.pack("<I", 99)
    with pytest.raises(IntegerFormatError, match="unsupported format_version 99"):
        decode(_reseal(data))
    d = model.to_dict()
    d["format_version"] = 4
    with pytest.raises(IntegerFormatError, match="format_version"):
        IntegerModel.from_dict(d)
    d["format_version"] = 3  # a version-3 dict must hold the adaptive ring
    with pytest.raises(IntegerFormatError, match=r"missing \['readout', 'decay_const'"):
        IntegerModel.from_dict(d)
    d["format_version"] = 2  # a version-2 dict must name the read-out
    with pytest.raises(IntegerFormatError, match=r"missing \['readout'\]"):
        IntegerModel.from_dict(d)


@pytest.mark.parametrize("cut", [0, 7, 31, 32, 100, 0.5, -5, -1])
def test_truncated(model, cut, tmp_path):
    data = encode(model)
    n = int(len(data) * cut) if isinstance(cut, float) else (cut if cut >= 0 else len(data) + cut)
    path = tmp_path / "cut.tsq"
    path.write_bytes(data[:n])
    with pytest.raises(IntegerFormatError, match="truncated|magic"):
        read_integer_model(path)


@pytest.mark.parametrize("where", [12, 40, 0.3, 0.7, -6])
def test_flipped_byte_is_caught(model, where):
    data = bytearray(encode(model))
    i = int(len(data) * where) if isinstance(where, float) else where % len(data)
    data[i] ^= 0x5A
    with pytest.raises(IntegerFormatError, match="CRC32|corrupt|truncated"):
        decode(bytes(data))


def test_flipped_payload_byte_names_the_section(model):
    data = bytearray(encode(model))
    data[32 + 48 + 8] ^= 1  # inside the first section's payload (params)
    data[-4:] = struct.pack("<I", zlib.crc32(bytes(data[:-4])))  # file CRC fixed, section not
    with pytest.raises(IntegerFormatError, match="section params: corrupt payload"):
        decode(bytes(data))


def test_unknown_section_type(model):
    data = bytearray(encode(model))
    data[32:48] = b"mystery.layer".ljust(16, b"\0")
    with pytest.raises(IntegerFormatError, match="unknown section type 'mystery.layer'"):
        decode(_reseal(data))
    d = model.to_dict()
    d["arrays"]["conv.weights"] = np.zeros(3, np.int8)
    with pytest.raises(IntegerFormatError, match="unknown section types"):
        IntegerModel.from_dict(d)


def test_inconsistent_shapes(model):
    d = model.to_dict()
    d["arrays"]["unit_centre"] = d["arrays"]["unit_centre"][:-1]
    with pytest.raises(IntegerFormatError, match="unit_centre.*inconsistent"):
        IntegerModel.from_dict(d)
    d = model.to_dict()
    d["params"]["hidden"] += 1  # header disagrees with every hidden-sized section
    with pytest.raises(IntegerFormatError, match="inconsistent"):
        IntegerModel.from_params(d["params"], d["arrays"])
    d = model.to_dict()
    d["arrays"]["l1.values"] = d["arrays"]["l1.values"].astype(np.int32)
    with pytest.raises(IntegerFormatError, match="dtype"):
        IntegerModel.from_dict(d)


def test_out_of_range_values(model):
    d = model.to_dict()
    d["arrays"]["ring.cols"][0, 0] = model.params["n_units"]
    with pytest.raises(IntegerFormatError, match="ring.cols: index"):
        IntegerModel.from_dict(d)
    d = model.to_dict()
    d["params"]["rectify"] = 7
    with pytest.raises(IntegerFormatError, match="rectify"):
        IntegerModel.from_dict(d)
    d = model.to_dict()
    del d["params"]["k"]
    with pytest.raises(IntegerFormatError, match="missing"):
        IntegerModel.from_dict(d)


def test_trailing_bytes_and_missing_file(model, tmp_path):
    with pytest.raises(IntegerFormatError, match="unexpected bytes"):
        decode(encode(model) + b"\0")
    with pytest.raises(IntegerFormatError, match="no such"):
        read_integer_model(tmp_path / "absent.tsq")
    assert issubclass(IntegerFormatError, ValueError)
