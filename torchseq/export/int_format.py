"""The integer weight file (``.tsq``): versioned, little-endian, sectioned, CRC32-checked.

The layout and the arithmetic are specified in ``docs/integer_format.md``; this module is
the writer and the reader. :class:`IntegerModel` is the in-memory form (a dict of integer
parameters and a dict of integer arrays); :func:`encode` / :func:`decode` turn it into bytes
and back; :func:`write_integer_model` / :func:`read_integer_model` add the (atomic) file.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchseq.atomic import atomic_path

MAGIC = b"TSQI\r\n\x1a\n"
FORMAT_VERSION = 1
SUPPORTED_VERSIONS = (1,)
_HEADER = struct.Struct("<8sIIQII")  # magic, version, n_sections, file_bytes, header_crc, 0
_SECTION = struct.Struct("<16sBBH4IQI")  # name, dtype, ndim, 0, dims[4], payload bytes, crc
_TRAILER = struct.Struct("<I")

DTYPES = {1: np.dtype("<u1"), 2: np.dtype("<i1"), 3: np.dtype("<u2"), 4: np.dtype("<i2"),
          5: np.dtype("<i4"), 6: np.dtype("<i8")}
_CODES = {v: k for k, v in DTYPES.items()}

# params: the integer scalars of the header section, in file order (docs/integer_format.md).
PARAM_NAMES = (
    "height", "width", "pool_h", "pool_w", "patch", "input_mode", "x_frac", "sqrt_frac",
    "norm_const", "n_input", "hidden", "k", "l1_fan_in", "n_units", "l3_fan_in", "e_shift",
    "n_cohorts", "rectify", "gain_const", "gain_shift", "state_frac", "ring_frac",
    "ring_width", "window",
)
INPUT_RAW, INPUT_ZSCORE = 0, 1
X_MAX = 2047  # L1 activity and L1 weights are 12-bit: |x|, |w| <= 2047 (int32 sums)
MAX_FAN_IN = (2**31 - 1) // (X_MAX * X_MAX)  # 512: an L1 sum cannot overflow int32

# section name -> (dtype, shape as param names or ints)
SECTIONS = {
    "params": (np.dtype("<i8"), (len(PARAM_NAMES),)),
    "l1.cols": (np.dtype("<u2"), ("hidden", "l1_fan_in")),
    "l1.values": (np.dtype("<i2"), ("hidden", "l1_fan_in")),
    "l3.cols": (np.dtype("<u2"), ("n_units", "l3_fan_in")),
    "l3.values": (np.dtype("<i1"), ("n_units", "l3_fan_in")),
    "l3.row_scale": (np.dtype("<i4"), ("n_units",)),
    "cohort": (np.dtype("<u2"), ("n_units",)),
    "ring.cols": (np.dtype("<u2"), ("n_units", "ring_width")),
    "ring.values": (np.dtype("<i2"), ("n_units", "ring_width")),
    "unit_centre": (np.dtype("<i4"), ("n_units",)),
    "unit_to_ref": (np.dtype("<i4"), ("n_units", 2)),
}


class IntegerFormatError(ValueError):
    """A bad integer model file or dict: wrong magic, version, section, checksum or shape."""


@dataclass
class IntegerModel:
    """An integer Neural SeqSLAM model: scalar parameters and integer arrays.

    Attributes:
        params: every name of :data:`PARAM_NAMES` -> int.
        arrays: every section of :data:`SECTIONS` except ``params`` -> NumPy integer array.
    """

    params: dict = field(default_factory=dict)
    arrays: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """``{"format_version", "params", "arrays"}`` (arrays copied)."""
        return {"format_version": FORMAT_VERSION, "params": dict(self.params),
                "arrays": {k: np.array(v) for k, v in self.arrays.items()}}

    @classmethod
    def from_dict(cls, d: dict) -> IntegerModel:
        """Build and check a model from :meth:`to_dict` output."""
        version = d.get("format_version")
        if version not in SUPPORTED_VERSIONS:
            raise IntegerFormatError(f"unsupported integer format_version {version!r} "
                                     f"(this reader knows {SUPPORTED_VERSIONS})")
        return cls(dict(d["params"]), {k: np.asarray(v) for k, v in d["arrays"].items()}).check()

    def check(self) -> IntegerModel:
        """Raise :class:`IntegerFormatError` for missing/unknown entries or bad shapes."""
        p = self.params
        missing = [n for n in PARAM_NAMES if n not in p]
        unknown = sorted(set(p) - set(PARAM_NAMES))
        if missing or unknown:
            raise IntegerFormatError(f"params: missing {missing}, unknown {unknown}")
        names = set(SECTIONS) - {"params"}
        if set(self.arrays) != names:
            raise IntegerFormatError(
                f"arrays: missing {sorted(names - set(self.arrays))}, unknown section types "
                f"{sorted(set(self.arrays) - names)}")
        for name in sorted(names):
            dtype, dims = SECTIONS[name]
            a = self.arrays[name]
            want = tuple(int(p[x]) if isinstance(x, str) else x for x in dims)
            if a.shape != want:
                raise IntegerFormatError(f"section {name}: shape {a.shape} is inconsistent with "
                                         f"the header (expected {want})")
            if a.dtype.newbyteorder("<") != dtype:
                raise IntegerFormatError(f"section {name}: dtype {a.dtype} is not {dtype}")
        _check_values(p, self.arrays)
        return self


def _check_values(p: dict, a: dict) -> None:
    def bad(msg: str) -> None:
        raise IntegerFormatError(msg)

    if p["rectify"] not in (0, 1):
        bad(f"rectify must be 0 or 1, got {p['rectify']}")
    if p["input_mode"] not in (INPUT_RAW, INPUT_ZSCORE):
        bad(f"unknown input_mode {p['input_mode']}")
    h, w, patch = p["height"], p["width"], p["patch"]
    if h < 1 or w < 1 or p["n_input"] != h * w:
        bad(f"n_input {p['n_input']} is not height*width = {h}*{w}")
    ph, pw = p["pool_h"], p["pool_w"]
    if ph < 1 or pw < 1:
        bad(f"pool {ph}x{pw} must be positive")
    if p["input_mode"] == INPUT_ZSCORE and (patch < 2 or h % patch or w % patch):
        bad(f"patch {patch} does not tile {h}x{w}")
    if p["input_mode"] == INPUT_ZSCORE and patch * patch * ph * pw >= 65536:
        bad(f"patch {patch} with pool {ph}x{pw} overflows the integer z-score")
    if p["input_mode"] == INPUT_RAW and 255 * ph * pw > X_MAX:
        bad(f"raw input pooled {ph}x{pw} exceeds {X_MAX}")
    if p["k"] * 127 * 2**15 > 32767 * 2 ** min(p["e_shift"], 62):
        bad(f"e_shift {p['e_shift']} lets the rescaled evidence exceed 32767 (k = {p['k']})")
    if not 1 <= p["l1_fan_in"] <= MAX_FAN_IN:
        bad(f"l1_fan_in {p['l1_fan_in']} not in 1..{MAX_FAN_IN} (int32 sums)")
    if not 1 <= p["k"] <= p["hidden"]:
        bad(f"k {p['k']} not in 1..hidden {p['hidden']}")
    if p["n_units"] < 1 or not 1 <= p["n_cohorts"] <= p["n_units"]:
        bad("need n_units >= 1 and 1 <= n_cohorts <= n_units")
    for name in ("x_frac", "sqrt_frac", "e_shift", "gain_shift", "state_frac", "ring_frac",
                 "window"):
        if not 0 <= p[name] <= 62:
            bad(f"{name} {p[name]} not in 0..62")
    for name, bound in (("l1.cols", p["n_input"]), ("l3.cols", p["hidden"]),
                        ("ring.cols", p["n_units"]), ("cohort", p["n_cohorts"])):
        if a[name].size and int(a[name].max()) >= bound:
            bad(f"section {name}: index {int(a[name].max())} out of range 0..{bound - 1}")
    if a["l3.row_scale"].size and not 0 <= int(a["l3.row_scale"].min()) <= int(
            a["l3.row_scale"].max()) <= 2 ** 15:
        bad("section l3.row_scale: scales must lie in 0..32768")
    if a["l1.values"].size and int(np.abs(a["l1.values"].astype(np.int64)).max()) > X_MAX:
        bad(f"section l1.values: values exceed +-{X_MAX}")


def encode(model: IntegerModel) -> bytes:
    """Serialise a model to the bytes of a format-version-1 file."""
    model.check()
    parts = [_section("params", np.array([model.params[n] for n in PARAM_NAMES], "<i8"))]
    parts += [_section(n, model.arrays[n]) for n in SECTIONS if n != "params"]
    body = b"".join(parts)
    total = _HEADER.size + len(body) + _TRAILER.size
    head = _HEADER.pack(MAGIC, FORMAT_VERSION, len(parts), total, 0, 0)
    head = head[:24] + struct.pack("<I", zlib.crc32(head[:24])) + head[28:]
    data = head + body
    return data + _TRAILER.pack(zlib.crc32(data))


def _section(name: str, array: np.ndarray) -> bytes:
    dtype = SECTIONS[name][0]
    a = np.ascontiguousarray(array, dtype=dtype)
    if a.ndim > 4:
        raise IntegerFormatError(f"section {name}: more than 4 dimensions")
    dims = list(a.shape) + [0] * (4 - a.ndim)
    payload = a.tobytes()
    return _SECTION.pack(name.encode("ascii"), _CODES[dtype], a.ndim, 0, *dims, len(payload),
                         zlib.crc32(payload)) + payload


def decode(data: bytes, source: str = "<bytes>") -> IntegerModel:
    """Parse and check the bytes of an integer model file.

    Raises:
        IntegerFormatError: bad magic, unknown version, truncated or corrupt data (CRC32),
            unknown section or dtype, or shapes inconsistent with the header.
    """
    def bad(msg: str) -> IntegerFormatError:
        return IntegerFormatError(f"{source}: {msg}")

    if len(data) < _HEADER.size:
        raise bad(f"truncated: {len(data)} bytes is shorter than the {_HEADER.size}-byte header")
    magic, version, n_sections, total, head_crc, reserved = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise bad(f"not a torchseq integer model (magic {magic!r})")
    if zlib.crc32(data[:24]) != head_crc or reserved != 0:
        raise bad("corrupt header (CRC32 mismatch)")
    if version not in SUPPORTED_VERSIONS:
        raise bad(f"unsupported format_version {version} (this reader knows "
                  f"{SUPPORTED_VERSIONS})")
    if len(data) < total:
        raise bad(f"truncated: {len(data)} bytes, the header says {total}")
    if len(data) > total:
        raise bad(f"{len(data) - total} unexpected bytes after the end of the model")
    (crc,) = _TRAILER.unpack_from(data, total - _TRAILER.size)
    if zlib.crc32(data[: total - _TRAILER.size]) != crc:
        raise bad("corrupt file (CRC32 mismatch)")
    pos, found = _HEADER.size, {}
    for _ in range(n_sections):
        if pos + _SECTION.size > total - _TRAILER.size:
            raise bad("truncated section table")
        raw, code, ndim, res, *rest = _SECTION.unpack_from(data, pos)
        dims, nbytes, pcrc = rest[:4], rest[4], rest[5]
        name = raw.rstrip(b"\0").decode("ascii", "replace")
        pos += _SECTION.size
        if name not in SECTIONS:
            raise bad(f"unknown section type {name!r}")
        if name in found:
            raise bad(f"section {name!r} appears twice")
        if code not in DTYPES or ndim > 4 or res:
            raise bad(f"section {name}: unknown dtype code {code} or bad header")
        dtype, shape = DTYPES[code], tuple(dims[:ndim])
        if dtype != SECTIONS[name][0]:
            raise bad(f"section {name}: dtype {dtype} is not {SECTIONS[name][0]}")
        if nbytes != int(np.prod(shape, dtype=np.int64)) * dtype.itemsize:
            raise bad(f"section {name}: {nbytes} bytes inconsistent with shape {shape}")
        if pos + nbytes > total - _TRAILER.size:
            raise bad(f"section {name}: payload runs past the end of the file")
        payload = data[pos:pos + nbytes]
        if zlib.crc32(payload) != pcrc:
            raise bad(f"section {name}: corrupt payload (CRC32 mismatch)")
        found[name] = np.frombuffer(payload, dtype=dtype).reshape(shape).copy()
        pos += nbytes
    if pos != total - _TRAILER.size:
        raise bad("unexpected bytes after the last section")
    if "params" not in found or found["params"].shape != (len(PARAM_NAMES),):
        raise bad("missing or malformed params section")
    params = {n: int(v) for n, v in zip(PARAM_NAMES, found.pop("params"))}
    try:
        return IntegerModel(params, found).check()
    except IntegerFormatError as err:
        raise bad(str(err)) from None


def write_integer_model(path: str | Path, model: IntegerModel) -> int:
    """Write ``model`` to ``path`` atomically; returns the file size in bytes."""
    data = encode(model)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return len(data)


def read_integer_model(path: str | Path) -> IntegerModel:
    """Read and check an integer model file (see :func:`decode` for the errors)."""
    path = Path(path)
    if not path.is_file():
        raise IntegerFormatError(f"no such integer model file: {path}")
    return decode(path.read_bytes(), str(path))
