"""The integer weight file (``.tsq``): versioned, little-endian, sectioned, CRC32-checked.

The layout and the arithmetic are specified in ``docs/reference/integer_format.md``; this module is
the writer and the reader. :class:`IntegerModel` is the in-memory form: the typed stages of
:mod:`torchseq.export.int_stages`, each checked against the spec when built;
:func:`encode` / :func:`decode` turn it into bytes and back; :func:`write_integer_model` /
:func:`read_integer_model` add the (atomic) file.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchseq.atomic import atomic_path
from torchseq.export.int_stages import (
    INPUT_RAW,
    INPUT_ZSCORE,
    MAX_FAN_IN,
    READOUT_CENTRE,
    READOUT_INTERPOLATE,
    X_MAX,
    CohortStage,
    InputStage,
    IntegerFormatError,
    L1Product,
    L3Product,
    ReadoutStage,
    RingStage,
    VelocityStage,
    integer,
    section,
)

__all__ = [
    "FORMAT_VERSION", "INPUT_RAW", "INPUT_ZSCORE", "MAGIC", "MAX_FAN_IN", "PARAM_NAMES",
    "PARAM_NAMES_V1", "READOUT_CENTRE", "READOUT_INTERPOLATE", "SECTIONS", "SUPPORTED_VERSIONS",
    "X_MAX", "CohortStage", "PARAM_NAMES_V3", "VelocityStage", "InputStage", "IntegerFormatError",
    "IntegerModel", "L1Product", "L3Product", "ReadoutStage", "RingStage", "decode", "encode",
    "read_integer_model", "write_integer_model",
]

MAGIC = b"TSQI\r\n\x1a\n"
FORMAT_VERSION = 3  # the newest; a model is written in the oldest version that holds it
SUPPORTED_VERSIONS = (1, 2, 3)
_HEADER = struct.Struct("<8sIIQII")  # magic, version, n_sections, file_bytes, header_crc, 0
_SECTION = struct.Struct("<16sBBH4IQI")  # name, dtype, ndim, 0, dims[4], payload bytes, crc
_TRAILER = struct.Struct("<I")

DTYPES = {1: np.dtype("<u1"), 2: np.dtype("<i1"), 3: np.dtype("<u2"), 4: np.dtype("<i2"),
          5: np.dtype("<i4"), 6: np.dtype("<i8")}
_CODES = {v: k for k, v in DTYPES.items()}

# params: the integer scalars of the header section, in file order
# (docs/reference/integer_format.md).
# Version 1 holds the first 24; version 2 appends ``readout`` (version 1: READOUT_CENTRE).
PARAM_NAMES_V1 = (
    "height", "width", "pool_h", "pool_w", "patch", "input_mode", "x_frac", "sqrt_frac",
    "norm_const", "n_input", "hidden", "k", "l1_fan_in", "n_units", "l3_fan_in", "e_shift",
    "n_cohorts", "rectify", "gain_const", "gain_shift", "state_frac", "ring_frac",
    "ring_width", "window",
)
PARAM_NAMES = (*PARAM_NAMES_V1, "readout")
# version 3 (the adaptive ring) appends the speed estimator and the ring.shift section
PARAM_NAMES_V3 = (*PARAM_NAMES, "decay_const", "velocity_window", "v_min", "v_max",
                  "v_tolerance", "v_rate")
_NAMES = {1: PARAM_NAMES_V1, 2: PARAM_NAMES, 3: PARAM_NAMES_V3}
_VELOCITY_SECTIONS = {"ring.shift"}  # version 3 only
# section name -> (dtype, shape as param names or ints; params: version 2's, version 1 has 24)
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
    "ring.shift": (np.dtype("<i4"), ("n_units", "ring_width")),
}
# the sizes among the params: each must be the matching section dimension
_SIZES = {"hidden": 2**15 - 1, "l1_fan_in": MAX_FAN_IN, "n_units": 2**15 - 1,
          "l3_fan_in": 2**15 - 1, "ring_width": 2**15 - 1, "n_input": 2**15 - 1}


@dataclass(frozen=True, eq=False)
class IntegerModel:
    """An integer Neural SeqSLAM model: the typed stages of one step.

    Each stage checks its own fields on construction (:mod:`torchseq.export.int_stages`);
    the model checks that they fit together. :attr:`params` and :attr:`arrays` give the
    file's view (the ``params`` section by name, the other sections by name).

    Attributes:
        input: :class:`InputStage`.
        l1: :class:`L1Product` (L1 -> L2).
        l3: :class:`L3Product` (k-WTA code -> evidence).
        cohort: :class:`CohortStage`.
        ring: :class:`RingStage`.
        readout: :class:`ReadoutStage`.
        velocity: :class:`VelocityStage` of the adaptive ring (format version 3), or None:
            the fixed ring.
    """

    input: InputStage
    l1: L1Product
    l3: L3Product
    cohort: CohortStage
    ring: RingStage
    readout: ReadoutStage
    velocity: VelocityStage | None = None

    def __post_init__(self) -> None:
        types = {"input": InputStage, "l1": L1Product, "l3": L3Product, "cohort": CohortStage,
                 "ring": RingStage, "readout": ReadoutStage}
        for name, kind in types.items():
            if not isinstance(getattr(self, name), kind):
                raise IntegerFormatError(f"stage {name} must be a {kind.__name__}")
        if self.l1.n_input != self.input.n_input:
            raise IntegerFormatError(f"l1 reads {self.l1.n_input} inputs, the input stage "
                                     f"gives {self.input.n_input}")
        if self.l3.hidden != self.l1.hidden:
            raise IntegerFormatError(f"l3 reads {self.l3.hidden} L2 units, l1 has "
                                     f"{self.l1.hidden}")
        n = self.l3.n_units
        for name, got in (("cohort", self.cohort.cohort.shape[0]),
                          ("ring.cols", self.ring.cols.shape[0]),
                          ("unit_centre", self.readout.unit_centre.shape[0])):
            if got != n:
                raise IntegerFormatError(f"section {name}: {got} units inconsistent with "
                                         f"l3's {n}")
        if self.velocity is not None:
            if not isinstance(self.velocity, VelocityStage):
                raise IntegerFormatError("stage velocity must be a VelocityStage or None")
            self.velocity.check_fits(int(self.readout.unit_to_ref[:, 1].max()),
                                     self.ring.cols.shape)

    @property
    def format_version(self) -> int:
        """The oldest format version that holds this model.

        3 for the adaptive ring; else 1 for the centre read-out, 2 for the interpolating
        one. A fixed centre model is written exactly as version 1 always was (readers of
        version 1 keep reading it), a fixed interpolating one exactly as version 2.
        """
        if self.velocity is not None:
            return 3
        return 1 if self.readout.readout == READOUT_CENTRE else 2

    @property
    def params(self) -> dict:
        """Every parameter name of this model -> int (a new dict).

        :data:`PARAM_NAMES`, and with the adaptive ring those of :data:`PARAM_NAMES_V3`.
        The file's ``params`` section holds the names of :attr:`format_version`.
        """
        i, l1, l3, c, r = self.input, self.l1, self.l3, self.cohort, self.ring
        v = self.velocity
        speed = {} if v is None else {
            "decay_const": v.decay_const, "velocity_window": v.window, "v_min": v.v_min,
            "v_max": v.v_max, "v_tolerance": v.tolerance, "v_rate": v.rate}
        return {**speed, "height": i.height, "width": i.width, "pool_h": i.pool_h,
                "pool_w": i.pool_w, "patch": i.patch, "input_mode": i.input_mode,
                "x_frac": i.x_frac,
                "sqrt_frac": i.sqrt_frac, "norm_const": i.norm_const, "n_input": i.n_input,
                "hidden": l1.hidden, "k": l3.k, "l1_fan_in": l1.cols.shape[1],
                "n_units": l3.n_units, "l3_fan_in": l3.cols.shape[1], "e_shift": l3.e_shift,
                "n_cohorts": c.n_cohorts, "rectify": c.rectify, "gain_const": c.gain_const,
                "gain_shift": c.gain_shift, "state_frac": c.state_frac,
                "ring_frac": r.ring_frac, "ring_width": r.cols.shape[1],
                "window": self.readout.window, "readout": self.readout.readout}

    @property
    def arrays(self) -> dict:
        """Every section of this model's version except ``params`` -> its read-only array."""
        speed = {} if self.velocity is None else {"ring.shift": self.velocity.shift}
        return {**speed, "l1.cols": self.l1.cols, "l1.values": self.l1.values,
                "l3.cols": self.l3.cols, "l3.values": self.l3.values,
                "l3.row_scale": self.l3.row_scale, "cohort": self.cohort.cohort,
                "ring.cols": self.ring.cols, "ring.values": self.ring.values,
                "unit_centre": self.readout.unit_centre,
                "unit_to_ref": self.readout.unit_to_ref}

    @classmethod
    def from_params(cls, params: dict, arrays: dict,
                    format_version: int | None = None) -> IntegerModel:
        """Build and check a model from the file's view (``params`` and section arrays).

        Args:
            params: the names of :data:`PARAM_NAMES_V3` (version 3: the adaptive ring),
                :data:`PARAM_NAMES` (version 2) or :data:`PARAM_NAMES_V1` (version 1: the
                centre read-out) -> int.
            arrays: the sections other than ``params`` (``ring.shift`` only in version 3).
            format_version: 1, 2 or 3; None: 3 when ``params`` has ``velocity_window``, 2
                when it has ``readout``, else 1.

        Raises:
            IntegerFormatError: a missing or unknown name, a non-integer parameter, a shape
                inconsistent with the parameters, or any stage's own check.
        """
        if not isinstance(params, dict) or not isinstance(arrays, dict):
            raise IntegerFormatError("params and arrays must be dicts")
        if format_version is None:
            format_version = (3 if "velocity_window" in params
                              else 2 if "readout" in params else 1)
        if format_version not in _NAMES:
            raise IntegerFormatError(f"unsupported integer format_version {format_version!r} "
                                     f"(this reader knows {SUPPORTED_VERSIONS})")
        wanted = _NAMES[format_version]
        missing = [n for n in wanted if n not in params]
        unknown = sorted(map(str, set(params) - set(wanted)))
        if missing or unknown:
            raise IntegerFormatError(f"params: missing {missing}, unknown {unknown}")
        names = set(SECTIONS) - {"params"}
        if format_version < 3:
            names -= _VELOCITY_SECTIONS
        if set(arrays) != names:
            raise IntegerFormatError(
                f"arrays: missing {sorted(names - set(arrays))}, unknown section types "
                f"{sorted(map(str, set(arrays) - names))}")
        p = {n: integer(n, params[n], -2**63, 2**63 - 1) for n in wanted}
        p.setdefault("readout", READOUT_CENTRE)
        for name, top in _SIZES.items():
            integer(name, p[name], 1, top)
        a = {}
        for name in sorted(names):
            dtype, dims = SECTIONS[name]
            want = tuple(p[x] if isinstance(x, str) else x for x in dims)
            a[name] = section(name, arrays[name], dtype.str, want, copy=False)  # stages copy
        stage = InputStage(p["height"], p["width"], p["pool_h"], p["pool_w"], p["patch"],
                           p["input_mode"], p["x_frac"], p["sqrt_frac"], p["norm_const"])
        if p["n_input"] != stage.n_input:
            raise IntegerFormatError(f"n_input {p['n_input']} is not height*width = "
                                     f"{p['height']}*{p['width']}")
        velocity = None
        if format_version >= 3:
            velocity = VelocityStage(a["ring.shift"], p["decay_const"], p["velocity_window"],
                                     p["v_min"], p["v_max"], p["v_tolerance"], p["v_rate"])
        return cls(
            stage, L1Product(a["l1.cols"], a["l1.values"], p["n_input"]),
            L3Product(a["l3.cols"], a["l3.values"], a["l3.row_scale"], p["e_shift"],
                      p["hidden"], p["k"]),
            CohortStage(a["cohort"], p["n_cohorts"], p["gain_const"], p["gain_shift"],
                        p["state_frac"], p["rectify"]),
            RingStage(a["ring.cols"], a["ring.values"], p["ring_frac"]),
            ReadoutStage(a["unit_centre"], a["unit_to_ref"], p["window"], p["readout"]),
            velocity)

    def to_dict(self) -> dict:
        """``{"format_version", "params", "arrays"}`` (arrays copied, writable).

        ``format_version`` is :attr:`format_version` and ``params`` holds its names.
        """
        version = self.format_version
        params = {n: v for n, v in self.params.items() if n in _NAMES[version]}
        return {"format_version": version, "params": params,
                "arrays": {k: np.array(v) for k, v in self.arrays.items()}}

    @classmethod
    def from_dict(cls, d: dict) -> IntegerModel:
        """Build and check a model from :meth:`to_dict` output."""
        if not isinstance(d, dict):
            raise IntegerFormatError(f"an integer model dict is a dict, got {type(d).__name__}")
        version = d.get("format_version")
        if isinstance(version, bool) or version not in SUPPORTED_VERSIONS:
            raise IntegerFormatError(f"unsupported integer format_version {version!r} "
                                     f"(this reader knows {SUPPORTED_VERSIONS})")
        return cls.from_params(d.get("params"), d.get("arrays"), version)

    def check(self) -> IntegerModel:
        """Return self: a model is checked when built and cannot change afterwards."""
        return self


def encode(model: IntegerModel) -> bytes:
    """Serialise a model to the bytes of a file of its :attr:`~IntegerModel.format_version`.

    A fixed centre read-out model gives exactly the bytes version 1 always gave, a fixed
    interpolating one those of version 2.
    """
    if not isinstance(model, IntegerModel):
        raise IntegerFormatError(f"encode takes an IntegerModel, got {type(model).__name__}")
    version = model.format_version
    parts = [_section("params", np.array([model.params[n] for n in _NAMES[version]], "<i8"))]
    arrays = model.arrays
    parts += [_section(n, arrays[n]) for n in SECTIONS if n in arrays]
    body = b"".join(parts)
    total = _HEADER.size + len(body) + _TRAILER.size
    head = _HEADER.pack(MAGIC, version, len(parts), total, 0, 0)
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
    view = memoryview(data).cast("B")  # slices of it check and read without copying
    if zlib.crc32(view[: total - _TRAILER.size]) != crc:
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
        payload = view[pos:pos + nbytes]
        if zlib.crc32(payload) != pcrc:
            raise bad(f"section {name}: corrupt payload (CRC32 mismatch)")
        # a view of the bytes: the stage that takes it stores its own read-only copy
        found[name] = np.frombuffer(payload, dtype=dtype).reshape(shape)
        pos += nbytes
    if pos != total - _TRAILER.size:
        raise bad("unexpected bytes after the last section")
    names = _NAMES[version]
    if "params" not in found or found["params"].shape != (len(names),):
        raise bad(f"missing or malformed params section (version {version} holds "
                  f"{len(names)} parameters)")
    params = {n: int(v) for n, v in zip(names, found.pop("params"))}
    try:
        return IntegerModel.from_params(params, found, version)
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
