"""Variable-length ``uint8`` elements of an HDF5 dataset, read from the file's own bytes.

A variable-length element is stored as 16 bytes: ``uint32`` length, then a global heap id
(``uint64`` address of a heap collection, ``uint32`` object index). A collection is
``"GCOL"``, version 1, 3 reserved bytes, ``uint64`` collection size, then objects: ``uint16``
index, ``uint16`` reference count, 4 reserved bytes, ``uint64`` size, the data padded to 8
bytes; index 0 is the free space that ends it (HDF5 file format specification, "Global Heap").

libhdf5 trusts these sizes: one damaged byte in a collection header made ``h5py`` hang (seen
in the libcaer fuzz run). Here every address and size is checked against the file's length
and the collection before anything is allocated, and a damaged one is an
:class:`EventFormatError` naming the row. Used for unfiltered chunked or contiguous datasets
with 16-byte elements (what h5py and DDD20's recorder write); any other storage (filters,
compact layout) is read through h5py, which then trusts the heap.
"""

from __future__ import annotations

import os
import struct

import numpy as np

from torchseq.events.stream import EventFormatError

REF_DTYPE = np.dtype([("len", "<u4"), ("addr", "<u8"), ("idx", "<u4")])
COLLECTION_HEAD = 16
OBJECT_HEAD = struct.Struct("<HHIQ")  # index, reference count, reserved, size


class VlenReader:
    """Rows of an ``(N, C)`` variable-length uint8 dataset, as lists of ``(n,)`` uint8 arrays.

    Args:
        d: the h5py dataset.
        where: ``"<file>:<dataset>"`` for messages.
    """

    def __init__(self, d, where: str) -> None:
        self.d, self.where, self.cols = d, where, d.shape[1]
        self.path = d.file.filename
        self.size = os.path.getsize(self.path)
        self.direct = self._direct_storage()
        self._cache: dict[int, tuple[bytes, dict[int, tuple[int, int]]]] = {}

    def _direct_storage(self) -> bool:
        plist = self.d.id.get_create_plist()
        if plist.get_nfilters() > 0:
            return False
        if self.d.chunks is None:
            return self.d.id.get_offset() is not None
        return True

    def rows(self, a: int, b: int, cols: tuple[int, ...]) -> list[list[np.ndarray]]:
        """Rows ``a..b`` (``b`` exclusive), columns ``cols`` of each.

        Raises:
            EventFormatError: a reference or heap object outside the file or its collection.
        """
        if not self.direct:
            block = self.d[a:b]
            return [[np.asarray(row[c], np.uint8) for c in cols] for row in block]
        refs = self._refs(a, b)
        return [[self._object(refs[i, c], a + i) for c in cols] for i in range(b - a)]

    def _read(self, offset: int, n: int, what: str) -> bytes:
        if offset < 0 or n < 0 or offset + n > self.size:
            raise EventFormatError(f"{self.where}: {what} at byte {offset} (+{n}) lies beyond "
                                   f"the end of the file ({self.size} bytes)")
        with open(self.path, "rb") as f:
            f.seek(offset)
            return f.read(n)

    def _refs(self, a: int, b: int) -> np.ndarray:
        row_bytes = self.cols * REF_DTYPE.itemsize
        if self.d.chunks is None:
            base = int(self.d.id.get_offset())
            raw = self._read(base + a * row_bytes, (b - a) * row_bytes, "the dataset's elements")
            return np.frombuffer(raw, REF_DTYPE).reshape(b - a, self.cols)
        out = np.zeros((b - a, self.cols), REF_DTYPE)  # unallocated chunks: empty rows
        step = self.d.chunks[0]
        for c0 in range(a // step * step, b, step):
            info = self.d.id.get_chunk_info_by_coord((c0, 0))
            if info.byte_offset is None or info.size == 0:
                continue
            want = step * row_bytes
            if info.size != want or self.d.chunks[1] != self.cols:
                raise EventFormatError(f"{self.where}: chunk at row {c0} stores {info.size} "
                                       f"bytes, not {want} (at byte {info.byte_offset})")
            chunk = np.frombuffer(self._read(info.byte_offset, want, f"chunk at row {c0}"),
                                  REF_DTYPE).reshape(step, self.cols)
            lo, hi = max(a, c0), min(b, c0 + step)
            out[lo - a:hi - a] = chunk[lo - c0:hi - c0]
        return out

    def _collection(self, addr: int, row: int):
        if addr in self._cache:
            return self._cache[addr]
        head = self._read(addr, COLLECTION_HEAD, f"row {row}'s heap collection")
        size = struct.unpack_from("<Q", head, 8)[0]
        if head[:4] != b"GCOL" or head[4] != 1 or size < COLLECTION_HEAD:
            raise EventFormatError(f"{self.where} row {row}: no global heap collection at "
                                   f"byte {addr} (found {head[:5]!r}, size {size})")
        data = self._read(addr + COLLECTION_HEAD, size - COLLECTION_HEAD,
                          f"row {row}'s heap collection of {size} bytes")
        objects, pos = {}, 0
        while pos + OBJECT_HEAD.size <= len(data):
            idx, _, _, n = OBJECT_HEAD.unpack_from(data, pos)
            if idx == 0:
                break  # free space: the end of the collection's objects
            if pos + OBJECT_HEAD.size + n > len(data):
                raise EventFormatError(f"{self.where} row {row}: heap object {idx} of {n} bytes "
                                       f"overruns its collection (at byte "
                                       f"{addr + COLLECTION_HEAD + pos})")
            objects[idx] = (pos + OBJECT_HEAD.size, n)
            pos += OBJECT_HEAD.size + -(-n // 8) * 8
        if len(self._cache) >= 4:
            self._cache.pop(next(iter(self._cache)))
        self._cache[addr] = (data, objects)
        return data, objects

    def _object(self, ref, row: int) -> np.ndarray:
        n = int(ref["len"])
        if n == 0:
            return np.empty(0, np.uint8)
        data, objects = self._collection(int(ref["addr"]), row)
        start, size = objects.get(int(ref["idx"]), (0, -1))
        if size != n:
            raise EventFormatError(f"{self.where} row {row}: element of {n} bytes refers to heap "
                                   f"object {int(ref['idx'])} at byte {int(ref['addr'])}, which "
                                   f"{'holds %d bytes' % size if size >= 0 else 'does not exist'}")
        return np.frombuffer(data, np.uint8, count=n, offset=start)
