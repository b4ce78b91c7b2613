"""The reference map: a folder of checksummed ``.npy`` shards, a FAISS index and a manifest.

A map is built once (:func:`torchseq.maps.build_map`) and loaded anywhere
(:class:`ReferenceMap`) without the reference's images. Layout (format version 1)::

    MAP/map.json             manifest (JSON): format, version, sizes, the SeqSLAMConfig the
                             descriptors were made with, the reference's record, files
    MAP/shard-00000.npy      (S, D) descriptors of places 0 .. S - 1
    MAP/shard-00001.npy      places S .. 2S - 1, ... (the last shard may be shorter)
    MAP/index.npy            uint8: the FAISS index over all places, faiss.serialize_index

Every file's size and SHA-256 are in the manifest, and the manifest's own SHA-256 (over its
canonical JSON without the ``checksum`` key) is its ``checksum``. Nothing is pickled: ``.npy``
files are read with ``allow_pickle=False`` after their header is checked
(:mod:`torchseq.npyfile`) and their checksum matched. A missing, damaged, truncated or
foreign map, or a newer format version, raises :class:`MapError` naming the file.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchseq.npyfile import npy_header
from torchseq.seqslam.config import SeqSLAMConfig

FORMAT = "torchseq.map"
VERSION = 1
SUPPORTED_VERSIONS = (1,)
MANIFEST = "map.json"
INDEX_FILE = "index.npy"
DTYPES = ("float32", "float64", "uint8")
# SeqSLAMConfig fields that shape the descriptors (the map's; an eval may not change them)
DESCRIPTOR_FIELDS = ("image_size", "patch_size", "preprocessing", "metric")
MAX_MANIFEST_BYTES = 1 << 26  # 64 MiB: 10^8 places in shards of 10^4 is ~2 MB of JSON
# bounds on what a manifest may declare, checked before anything is sized from it
MAX_PLACES = 1 << 40
MAX_DIM = 1 << 24
MAX_NAME = 200  # file name characters
MAX_FRAME_SIDE = 1 << 16  # reference.frame_size
INDEX_OPTIONS = {"nprobe": (1, 1 << 20), "ef_search": (1, 1 << 20)}
_HASH_PIECE = 1 << 22
_VERIFY_ROWS = 1 << 14


class MapError(ValueError):
    """A reference map that cannot be used: missing, damaged, foreign or of a newer version."""


def shard_name(i: int) -> str:
    """File name of shard ``i``."""
    return f"shard-{i:05d}.npy"


def file_sha256(path: Path) -> str:
    """``"sha256:<hex>"`` of a file's bytes, read in pieces."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for piece in iter(lambda: f.read(_HASH_PIECE), b""):
            h.update(piece)
    return "sha256:" + h.hexdigest()


def manifest_checksum(manifest: dict) -> str:
    """``"sha256:<hex>"`` of the manifest's canonical JSON, without its ``checksum`` key."""
    body = {k: v for k, v in manifest.items() if k != "checksum"}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class ShardInfo:
    """One shard file: places ``start .. stop - 1``."""

    file: str
    start: int
    stop: int
    bytes: int
    sha256: str


def _need(cond: bool, path: Path, what: str) -> None:
    if not cond:
        raise MapError(f"{path}: damaged manifest ({what})")


def _int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _file_entry(entry, path: Path, what: str) -> None:
    _need(isinstance(entry, dict), path, f"{what} is not an object")
    _need(isinstance(entry.get("file"), str) and "/" not in entry["file"]
          and "\\" not in entry["file"] and entry["file"] not in ("", ".", "..")
          and len(entry["file"]) <= MAX_NAME and "\0" not in entry["file"], path,
          f"{what} file name")
    _need(_int(entry.get("bytes")) and 0 < entry["bytes"] < 1 << 62, path, f"{what} bytes")
    sha = entry.get("sha256")
    _need(isinstance(sha, str) and sha.startswith("sha256:") and len(sha) == 71, path,
          f"{what} sha256")


def read_manifest(folder: str | Path) -> dict:
    """Read and check ``folder/map.json``: format, version, checksum, then every field.

    Raises:
        MapError: anything wrong, naming the file.
    """
    folder = Path(folder)
    path = folder / MANIFEST
    if not folder.is_dir():
        raise MapError(f"{folder}: no such map (a map is a folder holding {MANIFEST})")
    if not path.is_file():
        raise MapError(f"{folder}: not a torchseq map (no {MANIFEST})")
    if path.stat().st_size > MAX_MANIFEST_BYTES:
        raise MapError(f"{path}: manifest larger than {MAX_MANIFEST_BYTES} bytes: not a map")
    try:
        m = json.loads(path.read_bytes().decode("utf-8"), parse_constant=_no_constant)
    except (ValueError, RecursionError) as err:  # bad UTF-8/JSON, NaN, a 4,301-digit int
        raise MapError(f"{path}: not a readable map manifest ({err})") from None
    if not isinstance(m, dict) or m.get("format") != FORMAT:
        got = m.get("format") if isinstance(m, dict) else type(m).__name__
        raise MapError(f"{path}: format {got!r} is not {FORMAT!r}: not a torchseq map")
    version = m.get("version")
    if not _int(version) or version < 1:
        raise MapError(f"{path}: damaged manifest (version {version!r})")
    if version not in SUPPORTED_VERSIONS:
        raise MapError(f"{path}: map format version {version} is newer than this torchseq "
                       f"reads ({', '.join(map(str, SUPPORTED_VERSIONS))}); upgrade torchseq")
    if m.get("checksum") != manifest_checksum(m):
        raise MapError(f"{path}: checksum mismatch: the manifest is corrupt")
    for key, most in (("n_places", MAX_PLACES), ("dim", MAX_DIM), ("shard_size", MAX_PLACES)):
        _need(_int(m.get(key)) and 1 <= m[key] <= most, path, f"{key} not in 1..{most}")
    _need(m["n_places"] >= 2, path, "n_places < 2")
    _need(m.get("dtype") in DTYPES, path, f"dtype {m.get('dtype')!r}")
    _need(isinstance(m.get("config"), dict), path, "config")
    _need(isinstance(m.get("reference"), dict), path, "reference")
    size = m["reference"].get("frame_size")
    _need(size is None or (isinstance(size, list) and len(size) == 2 and all(
        _int(v) and 1 <= v <= MAX_FRAME_SIDE for v in size)), path, "reference.frame_size")
    shards = m.get("shards")
    _need(isinstance(shards, list) and len(shards) == -(-m["n_places"] // m["shard_size"]),
          path, "shard count")
    for i, s in enumerate(shards):
        _file_entry(s, path, f"shard {i}")
        want = (i * m["shard_size"], min(m["n_places"], (i + 1) * m["shard_size"]))
        _need((s.get("start"), s.get("stop")) == want, path, f"shard {i} range")
    if m.get("index") is not None:
        _file_entry(m["index"], path, "index")
        options = m["index"].get("options", {})
        _need(isinstance(m["index"].get("kind"), str) and isinstance(options, dict), path,
              "index kind")
        for key, value in options.items():
            lo, hi = INDEX_OPTIONS.get(key, (1, 0))
            _need(_int(value) and lo <= value <= hi, path, f"index option {key}={value!r}")
    return m


def _no_constant(name: str):
    raise ValueError(f"{name} is not a number a manifest may hold")


def config_from_manifest(m: dict, path: Path) -> SeqSLAMConfig:
    """The :class:`SeqSLAMConfig` a map was built with (its descriptor settings matter)."""
    fields = dict(m["config"])
    if isinstance(fields.get("image_size"), list):
        fields["image_size"] = tuple(fields["image_size"])
    try:
        return SeqSLAMConfig(**fields).validate()
    except (TypeError, ValueError) as err:
        raise MapError(f"{path}: bad config in the manifest ({err})") from None


class ReferenceMap:
    """A reference map opened for reading (see the module docstring for the layout).

    Opening reads and checks the manifest only; each data file is checked (size, ``.npy``
    header, SHA-256) the first time it is read.

    Args:
        path: the map folder.

    Attributes:
        path: the folder.
        manifest: the checked manifest.
        config: the :class:`SeqSLAMConfig` the descriptors were built with.
        reference: the reference's record (source, frames, frame size, selection).
        shards: one :class:`ShardInfo` per shard file, in place order.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.manifest = read_manifest(self.path)
        m = self.manifest
        self.config = config_from_manifest(m, self.path / MANIFEST)
        self.reference = dict(m["reference"])
        self.shards = [ShardInfo(s["file"], s["start"], s["stop"], s["bytes"], s["sha256"])
                       for s in m["shards"]]
        self._checked: set[str] = set()

    @property
    def n_places(self) -> int:
        """Reference places ``R``."""
        return int(self.manifest["n_places"])

    @property
    def dim(self) -> int:
        """Descriptor length ``D``."""
        return int(self.manifest["dim"])

    @property
    def dtype(self) -> np.dtype:
        """Stored descriptor dtype."""
        return np.dtype(self.manifest["dtype"])

    @property
    def shard_size(self) -> int:
        """Places per shard file (the last may hold fewer)."""
        return int(self.manifest["shard_size"])

    def _check_file(self, name: str, size: int, sha: str) -> Path:
        path = self.path / name
        if name in self._checked:
            return path
        try:
            if not path.is_file():
                raise MapError(f"{path}: missing map file")
            got = path.stat().st_size
            if got != size:
                raise MapError(f"{path}: {got} bytes, the manifest says {size}: truncated or "
                               f"damaged")
            if file_sha256(path) != sha:
                raise MapError(f"{path}: checksum mismatch: the file is corrupt")
        except OSError as err:
            raise MapError(f"{path}: cannot read ({err.strerror or err})") from None
        self._checked.add(name)
        return path

    def shard_array(self, i: int) -> np.ndarray:
        """Shard ``i``'s ``(stop - start, D)`` descriptors, memory-mapped read-only (checked)."""
        s = self.shards[i]
        path = self._check_file(s.file, s.bytes, s.sha256)
        shape, dtype = npy_header(path, MapError, allow_object=False)
        if tuple(shape) != (s.stop - s.start, self.dim) or dtype != self.dtype:
            raise MapError(f"{path}: holds {dtype} {tuple(shape)}, the manifest says "
                           f"{self.dtype} ({s.stop - s.start}, {self.dim})")
        try:
            return np.load(path, mmap_mode="r", allow_pickle=False)
        except (ValueError, OSError) as err:
            raise MapError(f"{path}: unreadable shard ({err})") from None

    def rows(self, start: int, stop: int) -> torch.Tensor:
        """Descriptors of places ``start .. stop - 1`` as one ``(stop - start, D)`` tensor.

        Reads (and checks) only the shard files those places are in.
        """
        if not 0 <= start < stop <= self.n_places:
            raise ValueError(f"rows {start}..{stop} outside the map's 0..{self.n_places}")
        size = self.shard_size
        parts = [(self.shards[i], self.shard_array(i))  # checked against the files first:
                 for i in range(start // size, (stop - 1) // size + 1)]  # out is their size
        out = np.empty((stop - start, self.dim), dtype=self.dtype)
        for s, array in parts:
            a, b = max(start, s.start), min(stop, s.stop)
            out[a - start:b - start] = array[a - s.start:b - s.start]
        if out.dtype.kind == "f" and not np.isfinite(out).all():
            raise MapError(f"{self.path}: places {start}..{stop - 1} hold NaN or infinite "
                           f"descriptors")
        return torch.from_numpy(out)

    def descriptors(self) -> torch.Tensor:
        """All ``(R, D)`` descriptors."""
        return self.rows(0, self.n_places)

    def index(self):
        """The map's :class:`~torchseq.seqslam.ann_index.CandidateIndex` (checked, no rebuild).

        Raises:
            MapError: the map holds no index, or it is damaged or does not fit the map.
        """
        from torchseq.seqslam.ann_index import CandidateIndex

        info = self.manifest.get("index")
        if info is None:
            raise MapError(f"{self.path}: the map holds no index (build it with one for "
                           f"candidate mode)")
        path = self._check_file(info["file"], info["bytes"], info["sha256"])
        shape, dtype = npy_header(path, MapError, allow_object=False)
        if len(shape) != 1 or dtype != np.uint8:
            raise MapError(f"{path}: holds {dtype} {tuple(shape)}, not the index's uint8 bytes")
        data = np.load(path, allow_pickle=False)
        try:
            return CandidateIndex.deserialize(data, self.config.metric, info["kind"],
                                              size=self.n_places, dim=self.dim,
                                              **info.get("options", {}))
        except (RuntimeError, ValueError, TypeError) as err:
            raise MapError(f"{path}: unusable index ({str(err).splitlines()[0][:200]})") \
                from None

    def verify(self) -> str:
        """Check now what any use would refuse: every file and every value the map holds.

        Sizes, ``.npy`` headers and SHA-256 of every file; finite descriptors in every shard;
        the index's kind, size, dimension and ids (each place once).

        Returns:
            What was checked, one line.
        """
        for i, s in enumerate(self.shards):
            array = self.shard_array(i)
            if array.dtype.kind == "f":
                for r0 in range(0, len(array), _VERIFY_ROWS):
                    if not np.isfinite(array[r0:r0 + _VERIFY_ROWS]).all():
                        raise MapError(f"{self.path / s.file}: holds NaN or infinite "
                                       f"descriptors")
        done = "sizes, headers, checksums, finite descriptors"
        if self.manifest.get("index") is not None:
            self.index()
            done += ", index ids"
        return done


def load_map(path: str | Path) -> ReferenceMap:
    """Open a reference map (:class:`ReferenceMap`); the manifest is checked now."""
    return ReferenceMap(path)
