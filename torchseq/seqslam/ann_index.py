"""Nearest-neighbour index over reference descriptors (FAISS), for SeqSLAM's candidate mode.

The index only proposes candidates: every score candidate mode reports is computed afterwards
from the stored descriptors, exactly. Kinds (chosen explicitly, or by ``"auto"``):

- ``"flat"``: exact top-K under the engine's own metric (``l1``: FAISS ``METRIC_L1``, ``l2``:
  squared L2, ``cosine``: inner product of L2-normalised vectors). Memory: a float32 copy of
  the references; time: ``R x D`` per query.
- ``"ivf"``: PCA to ``pca_dim`` dimensions, then an inverted file (``nlist`` k-means cells,
  ``nprobe`` cells scanned per query) with exact L2 inside the cells. For ``l1`` the L2 order
  in the PCA space is a proxy (measured in docs/guide/seqslam.md).
- ``"hnsw"``: PCA as above, then an HNSW graph (``hnsw_m`` links per node).

``"auto"`` is ``"flat"`` up to :data:`FLAT_MAX_REFERENCES` references, ``"ivf"`` above.
FAISS (``pip install 'torchseq[faiss]'``) is imported only when an index is built.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchseq._checks import check_finite, check_not_empty, check_shape

INDEX_KINDS = ("auto", "flat", "ivf", "hnsw")
# "auto" builds an exact flat index up to this many references (a float32 copy of R x D and
# R x D work per query), an IVF index above it (see docs/guide/seqslam.md for the measurements)
FLAT_MAX_REFERENCES = 5_000
# rows converted to float32 at a time while adding references (bounds the temporary copy)
ADD_CHUNK_ROWS = 16_384


def import_faiss():
    """The ``faiss`` module, or an ``ImportError`` that says how to install it."""
    try:
        import faiss
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError(
            "SeqSLAM candidate mode needs FAISS: pip install 'torchseq[faiss]' "
            "(or pip install faiss-cpu)") from err
    return faiss


def _as_float32(x: torch.Tensor, unit: bool) -> np.ndarray:
    """``(N, D)`` tensor -> contiguous float32 NumPy (L2-normalised rows when ``unit``)."""
    a = np.ascontiguousarray(x.detach().cpu().numpy(), dtype=np.float32)
    if unit:
        norm = np.linalg.norm(a, axis=1, keepdims=True)
        a = a / np.maximum(norm, np.finfo(np.float32).tiny)
    return a


def _check_ivf_ids(inner, size: int) -> None:
    """Refuse an IVF index whose stored ids are not each of ``0 .. size - 1`` once."""
    faiss = import_faiss()
    lists = inner.invlists
    seen = np.zeros(size, dtype=bool)
    for c in range(inner.nlist):
        n = lists.list_size(c)
        if n == 0:
            continue
        ids = faiss.rev_swig_ptr(lists.get_ids(c), n).astype(np.int64)
        if ids.min() < 0 or ids.max() >= size or seen[ids].any() or len(np.unique(ids)) != n:
            raise ValueError(f"the IVF index holds ids outside 0..{size - 1} or repeated")
        seen[ids] = True


class CandidateIndex:
    """Top-K reference candidates per query descriptor.

    Args:
        reference: ``(R, D)`` reference descriptors (any real dtype; uint8 is converted in
            chunks of :data:`ADD_CHUNK_ROWS` rows, so no float copy of all of it is made
            except by the ``"flat"`` index itself).
        metric: the engine's metric, ``"l1"``, ``"l2"`` or ``"cosine"``.
        kind: ``"auto"``, ``"flat"``, ``"ivf"`` or ``"hnsw"`` (see the module docstring).
        pca_dim: PCA output dimensions of ``"ivf"`` and ``"hnsw"`` (capped at ``D`` and at
            the training rows).
        nlist: IVF cells (None: ``round(sqrt(R))``, at least 1).
        nprobe: IVF cells scanned per query.
        hnsw_m: HNSW links per node.
        ef_search: HNSW search breadth (raised to ``k`` when smaller).
        train_size: most reference rows (a seeded random sample) used to train PCA and IVF.
        seed: seed of the training sample and of k-means.

    Attributes:
        kind: the kind actually built (``"auto"`` resolved).
    """

    def __init__(self, reference: torch.Tensor, metric: str = "l1", kind: str = "auto",
                 pca_dim: int = 128, nlist: int | None = None, nprobe: int = 16,
                 hnsw_m: int = 32, ef_search: int = 64, train_size: int = 50_000,
                 seed: int = 0) -> None:
        reference = torch.as_tensor(reference)
        check_not_empty(reference, "reference descriptors")
        check_shape(reference, ("R", "D"), "reference descriptors")
        check_finite(reference, "reference descriptors")
        if metric not in ("l1", "l2", "cosine"):
            raise ValueError(f"metric must be l1, l2 or cosine, got {metric!r}")
        if kind not in INDEX_KINDS:
            raise ValueError(f"index kind must be one of {INDEX_KINDS}, got {kind!r}")
        for name, value in (("pca_dim", pca_dim), ("nprobe", nprobe), ("hnsw_m", hnsw_m),
                            ("ef_search", ef_search), ("train_size", train_size)):
            if int(value) < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")
        if nlist is not None and int(nlist) < 1:
            raise ValueError(f"nlist must be >= 1, got {nlist}")
        faiss = import_faiss()
        n_ref, dim = reference.shape
        if kind == "auto":
            kind = "flat" if n_ref <= FLAT_MAX_REFERENCES else "ivf"
        self.kind, self.metric, self.dim, self.size = kind, metric, dim, n_ref
        self._unit = metric == "cosine"
        self.ef_search = int(ef_search)
        if kind == "flat":
            if metric == "l1":
                index = faiss.IndexFlat(dim, faiss.METRIC_L1)
            elif metric == "l2":
                index = faiss.IndexFlatL2(dim)
            else:
                index = faiss.IndexFlatIP(dim)
        else:
            rng = np.random.default_rng(seed)
            take = np.sort(rng.choice(n_ref, min(int(train_size), n_ref), replace=False))
            out = min(int(pca_dim), dim, len(take))  # PCA keeps at most n_train directions
            pca = faiss.PCAMatrix(dim, out)
            if kind == "ivf":
                cells = int(nlist) if nlist is not None else max(1, round(math.sqrt(n_ref)))
                cells = min(cells, n_ref)
                inner = faiss.IndexIVFFlat(faiss.IndexFlatL2(out), out, cells)
                inner.nprobe = min(int(nprobe), cells)
                inner.cp.seed = int(seed)
            else:
                inner = faiss.IndexHNSWFlat(out, int(hnsw_m))
            index = faiss.IndexPreTransform(pca, inner)
            self._inner = inner
            index.train(_as_float32(reference[torch.from_numpy(take)], self._unit))
        for r0 in range(0, n_ref, ADD_CHUNK_ROWS):
            index.add(_as_float32(reference[r0:r0 + ADD_CHUNK_ROWS], self._unit))
        self.index = index

    def search(self, query: torch.Tensor, k: int) -> torch.Tensor:
        """The ``k`` nearest references of each query, nearest first.

        Args:
            query: ``(Q, D)`` descriptors.
            k: candidates per query (capped at ``R``).

        Returns:
            ``(Q, min(k, R))`` int64 reference indices; ``-1`` where the index found fewer.
        """
        query = torch.as_tensor(query)
        check_shape(query, ("Q", self.dim), "query descriptors")
        check_finite(query, "query descriptors")
        if int(k) < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        k = min(int(k), self.size)
        if self.kind == "hnsw":
            self._inner.hnsw.efSearch = max(self.ef_search, k)
        if query.shape[0] == 0:
            return torch.empty(0, k, dtype=torch.int64)
        _, idx = self.index.search(_as_float32(query, self._unit), k)
        return torch.from_numpy(idx.astype(np.int64))

    def serialize(self) -> np.ndarray:
        """The FAISS index as a ``uint8`` array (``faiss.serialize_index``; no pickle).

        :meth:`deserialize` reads it back; reference maps store it as ``.npy``.
        """
        return np.asarray(import_faiss().serialize_index(self.index), dtype=np.uint8)

    @classmethod
    def deserialize(cls, data: np.ndarray, metric: str, kind: str, size: int, dim: int,
                    nprobe: int | None = None, ef_search: int = 64) -> CandidateIndex:
        """Rebuild an index from :meth:`serialize`'s bytes, checked against what it must hold.

        Args:
            data: ``uint8`` bytes.
            metric: the engine's metric the index was built for.
            kind: ``"flat"``, ``"ivf"`` or ``"hnsw"`` (as built).
            size: references it must hold.
            dim: descriptor length it must take.
            nprobe: IVF cells scanned per query (None: as stored).
            ef_search: HNSW search breadth.

        Raises:
            ValueError: the bytes are not an index of that kind, size and dimension.
        """
        if metric not in ("l1", "l2", "cosine"):
            raise ValueError(f"metric must be l1, l2 or cosine, got {metric!r}")
        if kind not in INDEX_KINDS[1:]:
            raise ValueError(f"index kind must be one of {INDEX_KINDS[1:]}, got {kind!r}")
        faiss = import_faiss()
        index = faiss.deserialize_index(np.ascontiguousarray(data, dtype=np.uint8))
        if index.ntotal != size or index.d != dim:
            raise ValueError(f"index holds {index.ntotal} vectors of {index.d} dimensions, "
                             f"expected {size} of {dim}")
        self = cls.__new__(cls)
        self.kind, self.metric, self.dim, self.size = kind, metric, dim, size
        self._unit = metric == "cosine"
        self.ef_search = int(ef_search)
        if kind != "flat":
            if not isinstance(index, faiss.IndexPreTransform):
                raise ValueError(f"a {kind} index is a PCA transform and an inner index")
            inner = faiss.downcast_index(index.index)
            want = faiss.IndexIVFFlat if kind == "ivf" else faiss.IndexHNSWFlat
            if not isinstance(inner, want):
                raise ValueError(f"inner index is {type(inner).__name__}, not {want.__name__}")
            if kind == "ivf":
                _check_ivf_ids(inner, size)
                if nprobe is not None:
                    if int(nprobe) < 1:
                        raise ValueError(f"nprobe must be >= 1, got {nprobe}")
                    inner.nprobe = min(int(nprobe), inner.nlist)
            self._inner = inner
        else:
            want = {"l1": faiss.METRIC_L1, "l2": faiss.METRIC_L2,
                    "cosine": faiss.METRIC_INNER_PRODUCT}[metric]
            if type(index).__name__ not in ("IndexFlat", "IndexFlatL2", "IndexFlatIP"):
                raise ValueError(f"a flat index is a plain IndexFlat (ids 0..R-1), got "
                                 f"{type(index).__name__}")
            if index.metric_type != want:
                raise ValueError(f"flat index metric {index.metric_type} does not fit {metric}")
        self.index = index
        return self
