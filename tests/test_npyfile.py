"""The one bounded ``.npy``/``.npz`` parser against NumPy's own format module (the reference)."""

import io
import struct
import zipfile

import numpy as np
import pytest

from torchseq.events.stream import EventFormatError
from torchseq.npyfile import (
    check_size,
    load_npy,
    load_npz_member,
    read_data,
    read_header,
    read_member,
)


class Bad(ValueError):
    pass


DTYPES = ["<f4", ">f4", "<i8", ">i8", ">u2", "<c8", ">c16", "|u1", "|b1",
          [("t", "<i8"), ("x", ">i2"), ("y", "<i2"), ("p", "|u1")]]


def arrays():
    rng = np.random.default_rng(0)
    for descr in DTYPES:
        dt = np.dtype(descr)
        for shape in [(0,), (7,), (3, 5), (2, 3, 4), (), (4, 0, 2)]:
            raw = rng.integers(0, 256, int(np.prod(shape, dtype=np.int64)) * dt.itemsize, np.uint8)
            a = np.frombuffer(raw.tobytes(), dt).reshape(shape)
            if dt.kind == "b":
                a = a.astype(np.uint8).astype(bool)  # bytes other than 0/1 are not bools
            yield a
            if a.ndim >= 2:
                yield np.asfortranarray(a)


def reference_header(data: bytes):
    """``(version, shape, fortran_order, dtype, data offset)`` as NumPy's format module reads it."""
    fp = io.BytesIO(data)
    version = np.lib.format.read_magic(fp)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fp)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fp)
    else:  # 3.0 only differs from 2.0 by utf-8; NumPy's own reader is np.load
        arr = np.load(io.BytesIO(data), allow_pickle=False)
        shape, fortran, dtype = arr.shape, arr.flags.f_contiguous and not arr.flags.c_contiguous, \
            arr.dtype
        return version, shape, fortran, dtype, None
    return version, shape, fortran, dtype, fp.tell()


@pytest.mark.parametrize("version", [(1, 0), (2, 0), (3, 0)])
def test_headers_and_data_match_numpy(version):
    n = 0
    for a in arrays():
        buf = io.BytesIO()
        np.lib.format.write_array(buf, a, version=version)
        data = buf.getvalue()
        assert data[6:8] == bytes(version)
        ref_version, shape, fortran, dtype, offset = reference_header(data)
        fp = io.BytesIO(data)
        h = read_header(fp, "mem.npy", Bad)
        assert ref_version == version
        assert (h.shape, h.fortran_order, h.dtype) == (shape, fortran, dtype), (a.dtype, a.shape)
        assert h.dtype.byteorder == a.dtype.byteorder or h.dtype.itemsize == 1
        if offset is not None:
            assert h.size == offset
        nbytes = check_size(h, len(data) - h.size, "mem.npy", Bad)
        assert nbytes == a.nbytes
        got = read_data(fp, h, nbytes, "mem.npy", Bad)
        ref = np.load(io.BytesIO(data), allow_pickle=False)
        assert got.dtype == ref.dtype and got.shape == ref.shape
        assert got.tobytes(order="A") == ref.tobytes(order="A")
        assert got.tobytes(order="C") == ref.tobytes(order="C")  # the same values, bit for bit
        assert got.flags.f_contiguous == ref.flags.f_contiguous
        assert got.flags.writeable
        n += 1
    assert n > 80


def test_version_3_utf8_field_names(tmp_path):
    a = np.zeros(3, [("τ", "<i8"), ("x", ">i2")])
    a["τ"] = [1, -2, 3]
    np.lib.format.write_array(open(tmp_path / "u.npy", "wb"), a, version=(3, 0))
    got = load_npy(tmp_path / "u.npy", Bad)
    ref = np.load(tmp_path / "u.npy")
    assert got.dtype == ref.dtype and got["τ"].tolist() == [1, -2, 3]


def test_npz_members_match_numpy(tmp_path):
    a = np.asfortranarray(np.arange(24, dtype=">i4").reshape(2, 3, 4))
    b = np.linspace(0, 1, 11, dtype="<f8")
    for save in (np.savez, np.savez_compressed):
        save(tmp_path / "z.npz", a=a, b=b)
        ref = np.load(tmp_path / "z.npz")
        for name in "ab":
            got = load_npz_member(tmp_path / "z.npz", name, Bad)
            assert got.dtype == ref[name].dtype and np.array_equal(got, ref[name])
            assert got.flags.f_contiguous == ref[name].flags.f_contiguous
        with zipfile.ZipFile(tmp_path / "z.npz") as zf:
            assert np.array_equal(read_member(zf, zf.getinfo("a.npy"), "z", Bad), a)


def npy(header: str, body: bytes = b"", major=1, minor=0) -> bytes:
    text = header.encode("latin1") + b"\n"
    size = struct.pack("<H", len(text)) if major == 1 else struct.pack("<I", len(text))
    return b"\x93NUMPY" + bytes([major, minor]) + size + text + body


@pytest.mark.parametrize("data,match", [
    (npy("{'descr': '<i4', 'fortran_order': False, 'shape': (2,)}", bytes(8), 4), "version 4.0"),
    (npy("{'descr': '<i4', 'fortran_order': False, 'shape': (2,)}", bytes(8), 1, 1),
     "version 1.1"),
    (b"\x93NUMPX\x01\x00", "bad magic"),
    (b"\x93NUMPY\x01\x00\xff", "truncated or oversized"),
    (b"\x93NUMPY\x02\x00\xff\xff\xff\x7f", "truncated or oversized"),
    (npy("{'descr': '<i4', 'fortran_order': False, 'shape': (2,)}")[:-5], "truncated .npy header"),
    (npy("{'descr': '<i4', 'fortran_order': 0, 'shape': (2,)}", bytes(8)), "fortran_order"),
    (npy("{'descr': '<i4', 'fortran_order': False, 'shape': (-2,)}", bytes(8)), "shape"),
    (npy("{'descr': '<i4', 'fortran_order': False, 'shape': (2.0,)}", bytes(8)), "shape"),
    (npy("{'descr': '<i4', 'fortran_order': False}", bytes(8)), "not a dict of"),
    (npy("{'descr': '<q7', 'fortran_order': False, 'shape': (2,)}", bytes(8)), "bad .npy dtype"),
    (npy("{'descr': '|V0', 'fortran_order': False, 'shape': (2,)}", bytes(8)), "no size"),
    (npy("{'descr': '|O', 'fortran_order': False, 'shape': (2,)}", bytes(8)), "Python objects"),
    (npy("__import__('os')", bytes(8)), "unreadable .npy header"),
])
def test_bad_headers_are_the_callers_error_with_the_offset(data, match):
    for error in (Bad, EventFormatError):
        with pytest.raises(error, match=match) as err:
            read_header(io.BytesIO(data), "f.npy", error, where=123)
        assert str(err.value).startswith("f.npy: ") and "(at byte 123)" in str(err.value)


def test_size_check_before_allocation():
    h = read_header(io.BytesIO(npy("{'descr': '<f8', 'fortran_order': True, "
                                   "'shape': (1000000, 10000000)}")), "f.npy", Bad)
    with pytest.raises(Bad, match=r"declares 10000000000000 elements .* only 80 bytes"):
        check_size(h, 80, "f.npy", Bad)
    # data shorter than its (honest-looking) size: a clean error, not a short array
    fp = io.BytesIO(npy("{'descr': '<i4', 'fortran_order': False, 'shape': (4,)}", bytes(10)))
    h = read_header(fp, "f.npy", Bad)
    with pytest.raises(Bad, match="truncated array data"):
        read_data(fp, h, 16, "f.npy", Bad)


def test_event_npy_streams_in_bounded_memory(tmp_path):
    """A large event ``.npy`` goes through the shared header check and is then streamed from a
    memory map chunk by chunk, never read whole (13 MB on disk, well under 3 MB traced)."""
    import tracemalloc

    from torchseq.events import iter_events
    from torchseq.events.stream import make_events
    n = 1_000_000
    rng = np.random.default_rng(1)
    ev = make_events(np.arange(n), rng.integers(0, 64, n), rng.integers(0, 48, n),
                     rng.integers(0, 2, n))
    np.save(tmp_path / "big.npy", ev)
    with open(tmp_path / "big.npy", "rb") as f:
        data = read_header(f, "big.npy", Bad).size
    tracemalloc.start()
    total, last_t, offsets = 0, -1, []
    for chunk in iter_events(tmp_path / "big.npy", 1 << 14, sensor_size=(64, 48)):
        t = chunk.events["t"]
        assert t[0] == last_t + 1
        assert np.array_equal(chunk.events["x"], ev["x"][total:total + len(t)])
        total, last_t = total + len(t), int(t[-1])
        offsets.append(chunk.offset)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert total == n
    assert offsets == [data + i * ev.dtype.itemsize for i in range(0, n, 1 << 14)]
    assert peak < 3_000_000, peak
