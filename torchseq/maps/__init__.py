"""Reference maps: descriptors, a FAISS index and a record, built once and loaded anywhere."""

from torchseq.maps.build import build_map
from torchseq.maps.format import FORMAT, VERSION, MapError, ReferenceMap, load_map

__all__ = ["FORMAT", "VERSION", "MapError", "ReferenceMap", "build_map", "load_map"]
