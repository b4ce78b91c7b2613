"""Reading ``.npy`` / ``.npz`` files that may be damaged or hostile, with bounded memory.

NumPy's own ``np.load`` trusts the header: a corrupt header that declares a huge shape makes
it allocate that much before noticing the data is missing, and zip archives, pickles and
odd dtypes surface as foreign exceptions. These readers check the header against the bytes
the file really holds before allocating, and end every failure in the caller's error class
with the file named. Object arrays (VPR-Bench ground truth) are read by a restricted
unpickler that only rebuilds NumPy arrays, lists and numbers; nothing else can run.
"""

from __future__ import annotations

import io
import pickle
import zipfile
from pathlib import Path

import numpy as np

MAX_HEADER = 1 << 16


def _header(fp, size: int, path, error: type[Exception]):
    """``(shape, fortran_order, dtype, data_bytes)`` of an ``.npy`` stream, checked."""
    try:
        major, _ = np.lib.format.read_magic(fp)
        if major == 1:
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(
                fp, max_header_size=MAX_HEADER)
        elif major in (2, 3):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(
                fp, max_header_size=MAX_HEADER)
        else:
            raise ValueError(f"unsupported .npy version {major}")
    except Exception as err:  # noqa: BLE001 - any header damage is a format error
        raise error(f"{path}: not a readable .npy array ({str(err).splitlines()[0]})") from None
    if any(not isinstance(n, int) or n < 0 for n in shape):
        raise error(f"{path}: bad shape {shape} in the .npy header")
    available = size - fp.tell()
    if dtype.hasobject:
        return shape, fortran, dtype, available
    count = 1
    for n in shape:
        count *= n
    need = count * dtype.itemsize
    if need > available:
        raise error(f"{path}: the header declares {shape} {dtype} ({need} bytes) but the file "
                    f"holds {max(available, 0)} bytes of data")
    return shape, fortran, dtype, need


def _read(fp, size: int, path, error, allow_object: bool) -> np.ndarray:
    shape, fortran, dtype, nbytes = _header(fp, size, path, error)
    if dtype.hasobject:
        if not allow_object:
            raise error(f"{path}: holds Python objects (a pickle); expected a numeric array")
        return _object_array(fp.read(nbytes), shape, path, error)
    data = fp.read(nbytes)
    if len(data) != nbytes:
        raise error(f"{path}: truncated array data")
    try:
        array = np.frombuffer(data, dtype=dtype)
        array = array.reshape(shape[::-1]).transpose() if fortran else array.reshape(shape)
    except (ValueError, TypeError) as err:
        raise error(f"{path}: cannot interpret the array data ({err})") from None
    return array.copy()  # writable, owns its memory


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
        size = path.stat().st_size
        with open(path, "rb") as fp:
            if fp.read(4) == b"PK\x03\x04":
                raise error(f"{path}: is a zip archive (an .npz?), not an .npy array")
            fp.seek(0)
            return _read(fp, size, path, error, allow_object)
    except OSError as err:
        raise error(f"{path}: cannot read ({err})") from None


def npy_header(path: str | Path, error: type[Exception]):
    """``(shape, dtype)`` of an ``.npy`` file from its header alone, checked against its size."""
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as fp:
            if fp.read(4) == b"PK\x03\x04":
                raise error(f"{path}: is a zip archive (an .npz?), not an .npy array")
            fp.seek(0)
            shape, _, dtype, _ = _header(fp, size, path, error)
    except OSError as err:
        raise error(f"{path}: cannot read ({err})") from None
    return shape, dtype


def npz_members(path: str | Path, error: type[Exception]) -> dict[str, zipfile.ZipInfo]:
    """The arrays of an ``.npz`` by name (without ``.npy``), checked as a zip archive."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as z:
            infos = z.infolist()
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError) as err:
        raise error(f"{path}: not a readable .npz archive ({err})") from None
    return {i.filename[:-4] if i.filename.endswith(".npy") else i.filename: i for i in infos}


def load_npz_member(path: str | Path, name: str, error: type[Exception]) -> np.ndarray:
    """Read one array of an ``.npz``, bounded by the member's stored size."""
    path = Path(path)
    members = npz_members(path, error)
    if name not in members:
        raise error(f"{path}: has no array {name!r} (it has {', '.join(members) or 'none'})")
    info = members[name]
    # a deflated member cannot expand more than ~1032x; a larger declared size is a lie
    limit = min(info.file_size, info.compress_size * 1100 + MAX_HEADER)
    try:
        with zipfile.ZipFile(path) as z, z.open(info) as fp:
            return _read(fp, limit, f"{path}[{name}]", error, allow_object=False)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError) as err:
        if isinstance(err, error):
            raise
        raise error(f"{path}[{name}]: damaged archive member ({err})") from None


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
