"""Property test: any damaged event file gives valid events or an EventFormatError, nothing else.

Seeds are the real recordings in ../shared/data/events (cut to a few tens of kB so that a
case reads in milliseconds) and the writers' output (AEDAT 2.0 both layouts, AEDAT 4.0 with
LZ4 / Zstd / no compression, ``.npz`` stored and deflated, ``.npy``, CSV). Hypothesis
mutates them (truncation, bit flips, inserted and deleted bytes, bytes overwritten with
hostile integers, damage aimed at the header) and every case must either

- read as data that satisfies the documented invariants (``t`` int64 non-decreasing,
  ``0 <= x < W``, ``0 <= y < H``, ``p`` in {0, 1}, ``1 <= W, H <= 32768``), identical
  through ``read_events`` and chunked ``iter_events``; or
- raise :class:`EventFormatError` naming the file (and, for the binary formats, a byte
  offset), from both entry points alike.

Any other exception, a hang or an invariant violation fails the test. Derandomised, so CI
runs the same cases every time.
"""

import io
import os
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchseq.events import (
    EVENT_DTYPE,
    EventFormatError,
    EventStream,
    detect_format,
    iter_events,
    make_events,
    read_events,
    write_aedat2,
    write_aedat4,
    write_npz,
)
from torchseq.events.aedat4 import parse_io_header

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "events"
CASES = int(os.environ.get("TORCHSEQ_FUZZ_CASES", 500))  # per seed family; 7 families


def _random(n, w, h, seed, t0=0):
    rng = np.random.default_rng(seed)
    return EventStream(make_events(t0 + np.sort(rng.integers(0, 3_000_000, n)),
                                   rng.integers(0, w, n), rng.integers(0, h, n),
                                   rng.integers(0, 2, n)), (w, h))


def _real_prefix(name: str, keep: int, header: int = 0, unit: int = 1) -> bytes | None:
    """The header and about ``keep`` bytes of whole records of ``unit`` bytes after it."""
    path = DATA / name
    if not path.exists():
        return None
    return path.read_bytes()[:header + keep // unit * unit]


def _header_len(name: str, marker: bytes) -> int:
    path = DATA / name
    if not path.exists():
        return 0
    data, pos = path.read_bytes(), 0
    while data[pos:pos + 1] == marker:
        pos = data.index(b"\n", pos) + 1
    return pos


def _real_npy(n: int) -> bytes | None:
    """The first ``n`` events of the decoded real EVT 3 recording, as a .npy file."""
    path = DATA / "evt3_sample.npy"
    if not path.exists():
        return None
    out = io.BytesIO()
    np.save(out, np.load(path, mmap_mode="r")[:n])
    return out.getvalue()


def _aedat4_real_prefix() -> bytes | None:
    """The real DVXplorer file's header and first packets, data table position set to -1."""
    path = DATA / "sample.aedat4"
    if not path.exists():
        return None
    data = bytearray(path.read_bytes())
    start = 18 + struct.unpack_from("<i", data, 14)[0]
    pos = start
    for _ in range(4):
        pos += 8 + struct.unpack_from("<i", data, pos + 4)[0]
    table_pos = parse_io_header(bytes(data[18:start]))[1]
    table = data.find(struct.pack("<q", table_pos), 18, start)
    out = data[:pos]
    if table >= 0:
        out[table : table + 8] = struct.pack("<q", -1)
    return bytes(out)


def _seeds(tmp: Path) -> dict[str, list[tuple[str, bytes]]]:
    """Seed files by family: (suffix, bytes)."""
    def written(writer, name, *args, **kw):
        writer(tmp / name, *args, **kw)
        return (Path(name).suffix, (tmp / name).read_bytes())

    s128, s240 = _random(600, 128, 128, 1), _random(600, 240, 180, 2)
    s320 = _random(800, 320, 240, 3, t0=1_600_000_000_000_000)
    npy = io.BytesIO()
    np.save(npy, _random(300, 64, 48, 4).events)
    deflated = io.BytesIO()
    ev = _random(300, 64, 48, 5)
    np.savez_compressed(deflated, events=ev.events, sensor_size=np.array(ev.sensor_size))
    csv = "t,x,y,p\n" + "".join(f"{t},{x},{y},{p}\n" for t, x, y, p in
                                _random(200, 20, 10, 6).events.tolist())
    fams = {
        "aedat2": [written(write_aedat2, "a.aedat", s128),
                   written(write_aedat2, "b.aedat", s240, layout="davis"),
                   (".aedat", _real_prefix("alex_walking_again.aedat", 24_000,
                                            _header_len("alex_walking_again.aedat", b"#"), 8)),
                   (".aedat", _real_prefix("IMU_translBoxes.aedat", 30_000,
                                           _header_len("IMU_translBoxes.aedat", b"#"), 8))],
        "aedat4": [written(write_aedat4, "a.aedat4", s320, packet_events=150),
                   written(write_aedat4, "b.aedat4", s320, compression="zstd",
                           packet_events=200),
                   written(write_aedat4, "c.aedat4", s320, compression="none",
                           packet_events=250)],
        "aedat4_real": [(".aedat4", _aedat4_real_prefix())],
        "raw": [(".raw", _real_prefix("evt3_sample.raw", 30_000,
                                       _header_len("evt3_sample.raw", b"%"), 2)),
                (".raw", b"% evt 2.0\n% geometry 16x8\n% end\n" + np.array(
                    [w for k in range(40) for w in ((8 << 28) | (15 + k),
                                                    (1 << 28) | (5 << 22) | (3 << 11) | 2,
                                                    (0 << 28) | (9 << 22) | (15 << 11) | 7)],
                    "<u4").tobytes())],
        "npy": [(".npy", npy.getvalue()),
                (".npy", _real_npy(800))],
        "npz": [written(write_npz, "a.npz", _random(300, 64, 48, 7)),
                (".npz", deflated.getvalue())],
        "csv": [(".csv", csv.encode())],
    }
    return {k: [(sfx, b) for sfx, b in v if b is not None] for k, v in fams.items()}


TALLY: dict = {}  # (family, outcome) -> cases, printed with -s by the last family
HOSTILE = [0, 1, 0x7F, 0x80, 0xFF, 0x7FFF, 0x8000, 0xFFFF, 0x7FFFFFFF, 0x80000000,
           0xFFFFFFFF, 2**63 - 1, 2**63, 2**64 - 1]


@st.composite
def mutations(draw):
    """A list of 1-4 edits; positions are fractions, mapped onto the file when applied."""
    edits = []
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["truncate", "flip", "insert", "delete", "hostile",
                                     "header"]))
        at = draw(st.floats(0, 1))
        if kind == "flip":
            edits.append((kind, at, draw(st.integers(0, 7))))
        elif kind == "insert":
            edits.append((kind, at, draw(st.binary(min_size=1, max_size=16))))
        elif kind == "delete":
            edits.append((kind, at, draw(st.integers(1, 64))))
        elif kind == "hostile":
            edits.append((kind, at, (draw(st.sampled_from(HOSTILE)),
                                     draw(st.sampled_from([2, 4, 8])),
                                     draw(st.sampled_from(["<", ">"])))))
        elif kind == "header":  # damage in the first 300 bytes, where the headers live
            edits.append((kind, draw(st.integers(0, 299)), draw(st.integers(1, 255))))
        else:
            edits.append((kind, at, None))
    return edits


def apply(data: bytes, edits) -> bytes:
    b = bytearray(data)
    for kind, at, arg in edits:
        pos = min(int(at * len(b)), max(len(b) - 1, 0)) if kind != "header" else at
        if kind == "truncate":
            del b[pos:]
        elif kind == "flip" and b:
            b[pos] ^= 1 << arg
        elif kind == "insert":
            b[pos:pos] = arg
        elif kind == "delete":
            del b[pos : pos + arg]
        elif kind == "hostile" and b:
            value, size, order = arg
            raw = (value % (1 << (8 * size))).to_bytes(size, "little" if order == "<" else "big")
            b[pos : pos + size] = raw
        elif kind == "header" and pos < len(b):
            b[pos] ^= arg
    return bytes(b)


def check_invariants(stream: EventStream) -> None:
    ev, (w, h) = stream.events, stream.sensor_size
    assert ev.dtype == EVENT_DTYPE and ev.ndim == 1
    assert isinstance(w, int) and isinstance(h, int) and 1 <= w <= 32768 and 1 <= h <= 32768
    if len(ev):
        t = ev["t"]
        assert not (t[1:] < t[:-1]).any()
        assert ev["x"].min() >= 0 and ev["x"].max() < w
        assert ev["y"].min() >= 0 and ev["y"].max() < h
        assert set(np.unique(ev["p"]).tolist()) <= {0, 1}


BYTE_OFFSET_FORMATS = {"aedat2", "aedat4", "raw", "npy", "npz"}


def outcome(fn, path: Path, binary: bool):
    """``("data", events, size)`` or ``("error",)``; anything else propagates (a failure).

    Errors name the file, and a byte offset when the file (as detected, perhaps not the
    seed's format any more) is one of the binary formats of this issue.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return ("data", *fn())
    except EventFormatError as err:
        msg = str(err)
        assert str(path) in msg, msg
        try:
            fmt = detect_format(path)
        except EventFormatError:
            fmt = None
        if binary and fmt in BYTE_OFFSET_FORMATS | {None}:
            assert "byte" in msg or "no sensor size" in msg or "sensor size implied" in msg, msg
        return ("error",)


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    return _seeds(tmp_path_factory.mktemp("seeds"))


@pytest.mark.slow
@pytest.mark.parametrize("family", ["aedat2", "aedat4", "aedat4_real", "raw", "npy", "npz",
                                    "csv"])
def test_damaged_files_give_valid_events_or_a_clear_error(seeds, tmp_path, family):
    fam = seeds[family]
    if not fam:
        pytest.skip(f"no seed for {family}: real data at {DATA} absent")
    for sfx, data in fam:  # every unmutated seed reads cleanly
        path = tmp_path / f"seed{sfx}"
        path.write_bytes(data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # .npy: no sensor size stored
            check_invariants(read_events(path))

    @settings(max_examples=CASES, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(which=st.integers(0, len(fam) - 1), edits=mutations(),
           drop=st.booleans(), chunk=st.sampled_from([61, 4099, 1 << 20]))
    def run(which, edits, drop, chunk):
        sfx, data = fam[which]
        path = tmp_path / f"case{sfx}"
        path.write_bytes(apply(data, edits))
        kw = {"truncated": "drop"} if drop and family in ("aedat2", "aedat4", "aedat4_real",
                                                          "raw") else {}
        binary = family != "csv"

        def whole():
            s = read_events(path, **kw)
            check_invariants(s)
            return s.events, s.sensor_size

        def chunked():
            chunks = list(iter_events(path, chunk, **kw))
            for c in chunks:
                check_invariants(c)
            assert len({c.sensor_size for c in chunks}) == 1
            ev = np.concatenate([c.events for c in chunks])
            check_invariants(EventStream(ev, chunks[0].sensor_size))
            return ev, chunks[0].sensor_size

        a, b = outcome(whole, path, binary), outcome(chunked, path, binary)
        TALLY[family, a[0]] = TALLY.get((family, a[0]), 0) + 1
        assert a[0] == b[0], (a[0], b[0])
        if a[0] == "data":
            assert a[2] == b[2] and np.array_equal(a[1], b[1])

    run()
    print(family, {k[1]: v for k, v in TALLY.items() if k[0] == family})
