"""AEDAT 2.0 header lines, read in blocks by one regular expression, against a line loop."""

import io

import numpy as np
import pytest

import torchseq.events.aedat2 as aedat2
from torchseq.events.aedat2 import detect_chip, read_header

TEXT = set(range(0x20, 0x7F)) | {0x09, 0x0D}


def loop_header(data: bytes):
    """Reference: line by line, a line is '#', printable ASCII/tab/CR, newline, <= 65536 B."""
    pos, lines = 0, []
    while True:
        nl = data.find(b"\n", pos, pos + 65536)
        line = data[pos:nl + 1] if nl >= 0 else b""
        if not line.startswith(b"#") or not set(line[:-1]) <= TEXT:
            return pos, lines
        lines.append(line.decode("ascii").rstrip("\r\n"))
        pos = nl + 1


def header_cases():
    rng = np.random.default_rng(7)
    yield b"#!AER-DAT2.0\r\n# AEChip: DVS128\r\n" + bytes([0x23, 0x00, 0x01, 0x02])
    yield b"#" * 10 + b"\n#\n##\r\n\x00\x01#\n"  # a binary record right after
    yield b"#ok\n#bad \x80 byte\n#never read\n"
    yield b"#" + b"a" * 65534 + b"\n#next\n"  # the longest line (65536 bytes) is a line
    yield b"#" + b"a" * 65535 + b"\n#next\n"  # one byte more is not
    yield b"# only header, no newline at the end"
    yield b""
    # 1.3 MB of header lines of varied lengths: lines straddle the 1 MiB (and 4 KiB) blocks
    yield b"".join(b"#" + b"x" * (i % 97) + b"\r\n" for i in range(25_000)) + b"\x00#\n"
    for _ in range(8):  # random printable lines, then binary records
        n = int(rng.integers(1, 2000))
        lens = rng.integers(0, 120, n)
        body = b"".join(b"#" + bytes(rng.integers(0x20, 0x7F, k).astype(np.uint8)) + b"\r\n"
                        for k in lens)
        yield body + bytes(rng.integers(0, 256, int(rng.integers(0, 50))).astype(np.uint8))


@pytest.mark.parametrize("block", [1 << 20, 4096])
def test_read_header_equals_a_line_loop(monkeypatch, block):
    monkeypatch.setattr(aedat2, "_BLOCK", block)
    for data in header_cases():
        f = io.BytesIO(b"PRE" + data)
        f.seek(3)
        size, lines = read_header(f)
        ref_size, ref_lines = loop_header(data)
        assert (size, lines) == (ref_size, ref_lines)
        assert f.tell() == 3 + size


def test_detect_chip_from_lines():
    assert detect_chip(["#!AER-DAT2.0", "# AEChip: eu.seebetter.ini.chips.davis.DAVIS240C"]) \
        == ("davis", (240, 180))
    assert detect_chip(["# HardwareInterface: unknown", "# HardwareInterface: DVS128 USB"]) \
        == ("dvs128", (128, 128))
    assert detect_chip(["# AEChip: DAVIS346B", "# torchseq layout: davis sensor_size: 20x10"]) \
        == ("davis", (20, 10))
    assert detect_chip(["# something else", "#  AEChip  : no known fragment"]) is None


def test_corrupt_records_are_counted_and_located(tmp_path):
    """4,000 random bytes in the middle of a DVS128 file: the skipped records are said."""
    import warnings

    from conftest import shared_data

    from torchseq.events.io import read_events

    path = shared_data("events", "alex_walking_again.aedat")
    src = path.read_bytes()
    header, _ = read_header(io.BytesIO(src))
    mid = header + (len(src) - header) // 16 * 8
    noise = np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8)
    noise[::8] |= 1  # every record's top address byte non-zero: none a DVS128 word
    (tmp_path / "bad.aedat").write_bytes(src[:mid] + noise.tobytes() + src[mid:])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        clean = read_events(path)  # the intact file reads without a word
    with pytest.warns(UserWarning) as said:
        bad = read_events(tmp_path / "bad.aedat")
    assert len(bad) == len(clean)
    assert [str(w.message) for w in said] == [
        f"{tmp_path / 'bad.aedat'}: skipped 500 of {len(clean) + 500} records that are not "
        f"DVS128 events (address bits 16-31 set), the first at byte {mid}: the file may be "
        f"corrupt there"]
