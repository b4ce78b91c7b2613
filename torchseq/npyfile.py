"""Reading ``.npy`` / ``.npz`` files that may be damaged or hostile, with bounded memory.

The one header parser, size check and ``.npz`` member reader of the library, shared by the
frame and ground-truth loaders (``TraverseError``, ``GroundTruthError``) and the event
readers (``EventFormatError``): each caller passes its own error class, and every message
reads ``"<file>: <what went wrong> (at byte <offset>)"`` where the offset is known.

NumPy's own ``np.load`` trusts the header: a corrupt header that declares a huge shape makes
it allocate that much before noticing the data is missing, and zip archives, pickles and
odd dtypes surface as foreign exceptions. Here the header is parsed without ``np.load``
(format versions 1.0, 2.0 and 3.0; C or Fortran order), its declared size is checked
against the bytes that really follow before anything is allocated, and data is read in
bounded pieces. Object arrays (VPR-Bench ground truth) are read, only where the caller
allows them, by a restricted unpickler that rebuilds NumPy arrays, lists and numbers;
nothing else can run.
"""

from __future__ import annotations

import ast
import io
import pickle
import struct
import zipfile
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np

MAGIC = b"\x93NUMPY"
MAX_HEADER = 1 << 16
_PIECE = 1 << 24  # bytes read per piece
_DTYPE_ERRORS = (TypeError, ValueError, KeyError, IndexError, AttributeError, RecursionError,
                 SyntaxError, OverflowError, MemoryError)
ZIP_ERRORS = (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, NotImplementedError,
               RuntimeError, ValueError, struct.error, zlib.error)


def fail(error: type[Exception], path, where: int | None, msg: str) -> Exception:
    """``error("<path>: <msg> (at byte <where>)")``; the offset is left out when ``None``."""
    return error(f"{path}: {msg}" + (f" (at byte {where})" if where is not None else ""))


class NpyHeader(NamedTuple):
    """A checked ``.npy`` header.

    Attributes:
        dtype: element type (never of size 0; an object dtype only where allowed).
        shape: the declared shape, non-negative ints.
        fortran_order: whether the data is stored column-major.
        size: bytes of magic plus header; the data starts this far after the header's start.
    """

    dtype: np.dtype
    shape: tuple[int, ...]
    fortran_order: bool
    size: int

    @property
    def count(self) -> int:
        """Elements the header declares (a Python int: never overflows)."""
        n = 1
        for v in self.shape:
            n *= v
        return n


def read_header(f, path, error: type[Exception], where: int | None = 0,
                allow_object: bool = False) -> NpyHeader:
    """Parse a ``.npy`` header from ``f``'s position (versions 1.0, 2.0, 3.0).

    Args:
        f: binary file object positioned at the magic string.
        path: the file, for messages.
        error: exception class every failure is raised as.
        where: byte offset of the header in the file (for messages), or None.
        allow_object: accept object dtypes (pickled data); refused otherwise.

    Returns:
        The checked :class:`NpyHeader`; ``f`` is left at the first data byte.
    """
    head = f.read(8)
    if len(head) < 8 or head[:6] != MAGIC:
        raise fail(error, path, where, "not a .npy array (bad magic)")
    major, minor = head[6], head[7]
    if major not in (1, 2, 3) or minor != 0:
        raise fail(error, path, where, f"unsupported .npy version {major}.{minor}")
    width = 2 if major == 1 else 4
    raw = f.read(width)
    n = struct.unpack("<H" if major == 1 else "<I", raw)[0] if len(raw) == width else -1
    if not 0 <= n <= MAX_HEADER:
        raise fail(error, path, where, "truncated or oversized .npy header")
    text = f.read(n)
    if len(text) < n:
        raise fail(error, path, where, "truncated .npy header")
    try:
        d = ast.literal_eval(text.decode("utf-8" if major == 3 else "latin1"))
    except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError) as err:
        raise fail(error, path, where, f"unreadable .npy header ({type(err).__name__})") from None
    if not isinstance(d, dict) or set(d) != {"descr", "fortran_order", "shape"}:
        raise fail(error, path, where, "the .npy header is not a dict of descr, fortran_order, "
                   "shape")
    shape = d["shape"]
    if (not isinstance(shape, tuple) or not all(type(v) is int and v >= 0 for v in shape)
            or not isinstance(d["fortran_order"], bool)):
        raise fail(error, path, where, f"bad .npy shape/fortran_order {shape!r} in the header")
    try:
        dtype = np.lib.format.descr_to_dtype(d["descr"])
    except _DTYPE_ERRORS as err:
        raise fail(error, path, where, f"bad .npy dtype ({type(err).__name__})") from None
    if dtype.hasobject and not allow_object:
        raise fail(error, path, where, "the .npy array holds Python objects (a pickle; refused); "
                   "expected a numeric array")
    if dtype.itemsize == 0:
        raise fail(error, path, where, f"the .npy dtype {dtype} has no size")
    return NpyHeader(dtype, shape, d["fortran_order"], 8 + width + n)


def check_size(header: NpyHeader, available: int, path, error: type[Exception],
               where: int | None = 0, what: str = "the array") -> int:
    """Bytes of data ``header`` declares, refused when more than the ``available`` bytes.

    Object arrays have no fixed size: all ``available`` bytes (the pickle) are theirs.
    """
    if header.dtype.hasobject:
        return max(available, 0)
    n = header.count
    need = n * header.dtype.itemsize
    if need > available:
        raise fail(error, path, where, f"{what} declares {n} elements of shape {header.shape} "
                   f"{header.dtype} ({need} bytes) but only {max(available, 0)} bytes follow "
                   f"the header")
    return need


def read_data(f, header: NpyHeader, nbytes: int, path, error: type[Exception],
              where: int | None = 0) -> np.ndarray:
    """Read the array after a checked header, ``nbytes`` (from :func:`check_size`) in pieces.

    Returns:
        A writable array of ``header.shape`` that owns its memory (object arrays through the
        restricted unpickler).
    """
    if header.dtype.hasobject:
        return _object_array(f.read(nbytes), header.shape, path, error)
    flat = np.empty(header.count, header.dtype)  # bounded: nbytes fit in the file
    buf = memoryview(flat.view(np.uint8).reshape(-1))
    done = 0
    while done < nbytes:
        got = f.readinto(buf[done:done + _PIECE])
        if not got:
            raise fail(error, path, where, f"truncated array data ({done} of {nbytes} bytes)")
        done += got
    try:
        if header.fortran_order:
            return flat.reshape(header.shape[::-1]).transpose()
        return flat.reshape(header.shape)
    except (ValueError, TypeError) as err:
        raise fail(error, path, where, f"cannot interpret the array data ({err})") from None


def _open_npy(path: Path, error: type[Exception], allow_object: bool):
    size = path.stat().st_size
    fp = open(path, "rb")
    try:
        if fp.read(4) == b"PK\x03\x04":
            raise fail(error, path, 0, "is a zip archive (an .npz?), not an .npy array")
        fp.seek(0)
        header = read_header(fp, path, error, 0, allow_object)
        return fp, header, size - header.size
    except BaseException:
        fp.close()
        raise


def load_npy(path: str | Path, error: type[Exception], allow_object: bool = False) -> np.ndarray:
    """Read an ``.npy`` file with every failure as ``error`` (the file named).

    Args:
        path: the file.
        error: exception class to raise (e.g. ``TraverseError``).
        allow_object: read object arrays with the restricted unpickler.

    Returns:
        The array (memory at most the file's size for numeric dtypes).
    """
    path = Path(path)
    try:
        fp, header, available = _open_npy(path, error, allow_object)
        with fp:
            nbytes = check_size(header, available, path, error)
            return read_data(fp, header, nbytes, path, error)
    except OSError as err:
        raise error(f"{path}: cannot read ({err})") from None


def npy_header(path: str | Path, error: type[Exception],
               allow_object: bool = True) -> tuple[tuple[int, ...], np.dtype]:
    """``(shape, dtype)`` of an ``.npy`` file from its header alone, checked against its size."""
    path = Path(path)
    try:
        fp, header, available = _open_npy(path, error, allow_object)
        fp.close()
    except OSError as err:
        raise error(f"{path}: cannot read ({err})") from None
    check_size(header, available, path, error)
    return header.shape, header.dtype


def npz_members(path: str | Path, error: type[Exception]) -> dict[str, zipfile.ZipInfo]:
    """The arrays of an ``.npz`` by name (without ``.npy``), checked as a zip archive."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as z:
            infos = z.infolist()
    except ZIP_ERRORS as err:  # also zip features zipfile does not implement
        raise error(f"{path}: not a readable .npz archive ({err})") from None
    return {i.filename[:-4] if i.filename.endswith(".npy") else i.filename: i for i in infos}


def read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, path, error: type[Exception]
                ) -> np.ndarray:
    """One ``.npy`` member of an open archive, bounded by what the member really stores.

    The declared size may not exceed the member's uncompressed size, nor what its compressed
    bytes can expand to (deflate: at most ~1032x). Header failures name the member's byte
    offset in the archive. Zip-level failures (bad CRC, unknown compression) propagate as
    ``zipfile``/``zlib`` exceptions for the caller to wrap.
    """
    where = info.header_offset
    name = info.filename
    if info.compress_type == zipfile.ZIP_STORED and info.file_size != info.compress_size:
        raise fail(error, path, where, f"member {name} declares {info.file_size} bytes but "
                   f"stores {info.compress_size}")
    limit = info.file_size
    if info.compress_type != zipfile.ZIP_STORED:
        limit = min(limit, info.compress_size * 1100 + MAX_HEADER)
    with zf.open(info) as f:
        header = read_header(f, path, error, where)
        nbytes = check_size(header, limit - header.size, path, error, where, f"member {name}")
        return read_data(f, header, nbytes, path, error, where)


def npz_member_header(path: str | Path, name: str, error: type[Exception]) -> NpyHeader:
    """The checked ``.npy`` header of one member of an ``.npz`` (its data is not read)."""
    path = Path(path)
    info = npz_members(path, error)[name]
    try:
        with zipfile.ZipFile(path) as z, z.open(info) as f:
            return read_header(f, f"{path}[{name}]", error, info.header_offset)
    except ZIP_ERRORS as err:
        if isinstance(err, error):
            raise
        raise fail(error, f"{path}[{name}]", info.header_offset,
                   f"damaged archive member ({err})") from None


def load_npz_member(path: str | Path, name: str, error: type[Exception]) -> np.ndarray:
    """Read one numeric array of an ``.npz``, bounded by the member's stored size."""
    path = Path(path)
    members = npz_members(path, error)
    if name not in members:
        raise error(f"{path}: has no array {name!r} (it has {', '.join(members) or 'none'})")
    info = members[name]
    try:
        with zipfile.ZipFile(path) as z:
            return read_member(z, info, f"{path}[{name}]", error)
    except ZIP_ERRORS as err:
        if isinstance(err, error):
            raise
        raise fail(error, f"{path}[{name}]", info.header_offset,
                   f"damaged archive member ({err})") from None


class _NumpyOnly(pickle.Unpickler):
    """Rebuilds NumPy arrays, dtypes and scalars, lists and numbers; refuses anything else."""

    ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
        ("numpy", "ndarray"), ("numpy", "dtype"),
    }

    def find_class(self, module: str, name: str):
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name}")
        return super().find_class(module, name)


def _object_array(data: bytes, shape, path, error) -> np.ndarray:
    try:
        array = _NumpyOnly(io.BytesIO(data)).load()
    except Exception as err:  # noqa: BLE001 - any damage or refused global is a format error
        raise error(f"{path}: unreadable object array ({str(err).splitlines()[0]})") from None
    if not isinstance(array, np.ndarray) or array.shape != tuple(shape):
        raise error(f"{path}: object array does not match its header shape {shape}")
    return array
