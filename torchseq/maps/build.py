"""Writing a reference map (format in :mod:`torchseq.maps.format`), atomically.

The files are written into a temporary folder beside the target, the manifest last, and the
folder is renamed into place: a crash leaves no half-written map under the target's name.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch

import torchseq
from torchseq._checks import check_finite, check_not_empty, check_shape
from torchseq.atomic import atomic_path, write_text
from torchseq.maps.format import (
    DTYPES,
    FORMAT,
    INDEX_FILE,
    MANIFEST,
    VERSION,
    MapError,
    ReferenceMap,
    file_sha256,
    manifest_checksum,
    shard_name,
)
from torchseq.seqslam.config import SeqSLAMConfig

DEFAULT_SHARD_SIZE = 100_000


def _save_npy(path: Path, array: np.ndarray) -> dict:
    """Write ``array`` as ``.npy`` atomically; return its manifest entry."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, np.ascontiguousarray(array), allow_pickle=False)
    return {"file": path.name, "bytes": path.stat().st_size, "sha256": file_sha256(path)}


def _replace_folder(tmp: Path, out: Path, overwrite: bool) -> None:
    """Rename the finished ``tmp`` folder to ``out`` (replacing an old map if allowed)."""
    if not out.exists():
        os.rename(tmp, out)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    os.rename(out, old / out.name)
    try:
        os.rename(tmp, out)
    except BaseException:
        os.rename(old / out.name, out)
        raise
    shutil.rmtree(old, ignore_errors=True)


def build_map(reference: torch.Tensor, out: str | Path, config: SeqSLAMConfig | None = None,
              shard_size: int = DEFAULT_SHARD_SIZE, index: str | None = "auto",
              index_options: dict | None = None, record: dict | None = None,
              overwrite: bool = False) -> ReferenceMap:
    """Write a reference map of ``(R, D)`` descriptors, its FAISS index and its record.

    Args:
        reference: ``(R, D)`` descriptors (float32, float64 or uint8; kept as they are).
        out: the map folder to create.
        config: the :class:`SeqSLAMConfig` the descriptors were made with (its metric also
            chooses the index's); recorded in the manifest.
        shard_size: places per shard file.
        index: index kind (:data:`~torchseq.seqslam.ann_index.INDEX_KINDS`) or None for no
            index (the map then serves the exact mode only).
        index_options: keyword arguments of
            :class:`~torchseq.seqslam.ann_index.CandidateIndex`.
        record: what the reference is (source, frame count, frame size, selection); plain
            JSON data.
        overwrite: replace an existing map at ``out`` (never any other folder).

    Returns:
        The written map, opened.

    Raises:
        MapError: ``out`` exists (and is no map, or ``overwrite`` is False).
        ValueError: bad descriptors or settings.
    """
    config = (config or SeqSLAMConfig()).validate()
    reference = torch.as_tensor(reference)
    check_not_empty(reference, "reference descriptors")
    check_shape(reference, ("R", "D"), "reference descriptors")
    check_finite(reference, "reference descriptors")
    dtype = str(reference.dtype).replace("torch.", "")
    if dtype not in DTYPES:
        raise ValueError(f"reference descriptors must be one of {DTYPES}, got {dtype}")
    n_ref, dim = reference.shape
    if n_ref < 2:
        raise ValueError(f"a map needs at least 2 places, got {n_ref}")
    if isinstance(shard_size, bool) or int(shard_size) < 1:
        raise ValueError(f"shard_size must be an integer >= 1, got {shard_size!r}")
    shard_size = int(shard_size)
    out = Path(out)
    if out.exists():
        if not (out / MANIFEST).is_file():
            raise MapError(f"{out} exists and is not a map; choose a new folder")
        if not overwrite:
            raise MapError(f"{out} already holds a map; pass overwrite (--overwrite) to "
                           f"replace it")
    index_entry = None
    built = None
    if index is not None:
        from torchseq.seqslam.ann_index import CandidateIndex

        options = dict(index_options or {})
        built = CandidateIndex(reference, config.metric, index, **options)
        keep = {k: options[k] for k in ("nprobe", "ef_search") if k in options}
        index_entry = {"kind": built.kind, "options": keep}
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        data = reference.detach().cpu().numpy()
        shards = []
        for i, r0 in enumerate(range(0, n_ref, shard_size)):
            r1 = min(n_ref, r0 + shard_size)
            entry = _save_npy(tmp / shard_name(i), data[r0:r1])
            shards.append({**entry, "start": r0, "stop": r1})
        if built is not None:
            index_entry = {**_save_npy(tmp / INDEX_FILE, built.serialize()), **index_entry}
        cfg = dataclasses.asdict(config)
        cfg["image_size"] = list(cfg["image_size"])
        manifest = {"format": FORMAT, "version": VERSION, "n_places": int(n_ref),
                    "dim": int(dim), "dtype": dtype, "shard_size": shard_size, "config": cfg,
                    "reference": dict(record or {}), "index": index_entry, "shards": shards,
                    "torchseq_version": torchseq.__version__}
        manifest["checksum"] = manifest_checksum(manifest)
        write_text(tmp / MANIFEST, json.dumps(manifest, indent=1, allow_nan=False) + "\n")
        os.chmod(tmp, 0o777 & ~_umask())
        _replace_folder(tmp, out, overwrite)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return ReferenceMap(out)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
