"""EVT 3.0 decoder kernels (numba, numpy): against a plain loop, each other, the real file."""

from pathlib import Path

import numpy as np
import pytest

import torchseq.events.prophesee as prophesee
from torchseq.events import EVENT_DTYPE, read_events
from torchseq.events.prophesee import EVT3_KERNEL, decode_evt3

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "events"
STATE_DEFAULTS = {"y": -1, "low": 0, "high_full": -1, "carry": 0, "pol": 0, "base": 0,
                  "high": 0, "loops": 0}


def evt3_loop(words, carry_mode):
    """Independent decoder: the EVT 3.0 word types read one by one, as the format describes."""
    y = high = low = None
    loops = carry = base = pol = 0
    last_high, last_low = 0, 0
    out = []
    for w in (int(v) for v in words):
        kind, v = w >> 12, w & 0xFFF
        if kind == 0x0:
            y = v & 0x7FF
        elif kind == 0x6:
            if carry_mode and v < last_low:
                carry += 1
            low = last_low = v
        elif kind == 0x8:
            if v < last_high:
                loops += 1
            last_high = v
            high = v + 4096 * loops
        elif kind == 0x3:
            base, pol = v & 0x7FF, v >> 11
        elif kind in (0x2, 0x4, 0x5):
            if kind == 0x2:
                cols, p = [v & 0x7FF], v >> 11
            else:
                nbits = 12 if kind == 0x4 else 8
                cols = [base + i for i in range(nbits) if v >> i & 1]
                p = pol
                base += nbits
            if high is not None and y is not None:
                t = (low or 0) + 4096 * (high + carry)
                out += [(t, (c + 0x8000) % 0x10000 - 0x8000, y, p) for c in cols]
    ev = np.zeros(len(out), EVENT_DTYPE)
    for i, f in enumerate("txyp"):
        ev[f] = [e[i] for e in out]
    return ev


def random_words(n, seed):
    """Words of every type; TIME_HIGH and TIME_LOW both go back sometimes (wraps, carries)."""
    rng = np.random.default_rng(seed)
    kinds = rng.choice([0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x8, 0xA, 0xE, 0xF, 0x1, 0x7], n,
                       p=[.12, .18, .1, .15, .1, .15, .1, .02, .02, .02, .02, .02])
    payload = rng.integers(0, 4096, n)
    return ((kinds << 12) | payload).astype(np.uint16)


def decode_in_chunks(words, bounds, mode, kernels):
    state, parts = {}, []
    for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
        parts.append(decode_evt3(words[a:b], state, mode, kernels[i % len(kernels)]))
    return np.concatenate(parts), {**STATE_DEFAULTS, **state}


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("mode", ["spec", "carry"])
def test_kernels_equal_a_plain_loop_in_any_chunking(seed, mode):
    words = random_words(3000, seed)
    ref = evt3_loop(words, mode == "carry")
    rng = np.random.default_rng(100 + seed)
    bounds = [0, *sorted(rng.integers(0, len(words), 7).tolist()), len(words)]
    states = []
    for kernels in (["numba"], ["numpy"], ["numba", "numpy"], ["numpy", "numba"]):
        got, state = decode_in_chunks(words, bounds, mode, kernels)
        assert got.dtype == EVENT_DTYPE
        assert np.array_equal(got, ref), kernels
        states.append(state)
    assert all(s == states[0] for s in states)  # same carried state: kernels hand over freely


def test_kernels_equal_the_loop_when_vectors_run_past_int16():
    # one base then 6000 full VECT_12 words: x runs past 32767 and 65535 and wraps (16-bit;
    # the readers' contents check reports such columns as outside the sensor)
    words = np.array([0x8001, 0x6002, 0x0005, 0x3000 | 0x800 | 7] + [0x4FFF] * 6000, np.uint16)
    ref = evt3_loop(words, False)
    assert ref["x"].min() < 0
    for kernel in ("numba", "numpy"):
        state = {}
        a = decode_evt3(words[:5500], state, "spec", kernel)
        b = decode_evt3(words[5500:], state, "spec", kernel)
        assert np.array_equal(np.concatenate([a, b]), ref), kernel
        assert 0 <= state["base"] < 1 << 16


def test_empty_and_eventless_words():
    for kernel in ("numba", "numpy"):
        state = {}
        assert len(decode_evt3(np.zeros(0, np.uint16), state, "spec", kernel)) == 0
        # events before any TIME_HIGH / ADDR_Y are dropped; the state still moves
        got = decode_evt3(np.array([0x2001, 0x3005, 0x4FFF, 0x8003], np.uint16), state, "spec",
                          kernel)
        assert len(got) == 0 and state["base"] == 17 and state["high_full"] == 3


@pytest.mark.parametrize("kernel", ["numba", "numpy"])
def test_real_file_equals_the_decoded_reference_with_each_kernel(kernel):
    raw, npy = DATA / "evt3_sample.raw", DATA / "evt3_sample.npy"
    if not raw.exists() or not npy.exists():
        pytest.skip(f"real event data {raw} is absent")
    got = read_events(raw, evt3_time="carry", evt3_kernel=kernel, chunk_events=50_000)
    assert np.array_equal(got.events, np.load(npy))


def test_default_kernel_is_numba_for_large_files_numpy_for_small(monkeypatch, tmp_path):
    # numba is in the test extra: a fast kernel that silently disappears is a failure
    assert EVT3_KERNEL == "numba"
    from torchseq.events import _evt3_numba

    calls = []
    real_numba, real_numpy = _evt3_numba.decode, prophesee._decode_evt3_numpy
    monkeypatch.setattr(_evt3_numba, "decode",
                        lambda *a: calls.append("numba") or real_numba(*a))
    monkeypatch.setattr(prophesee, "_decode_evt3_numpy",
                        lambda *a: calls.append("numpy") or real_numpy(*a))
    path = tmp_path / "e.raw"
    words = np.array([0x8001, 0x6002, 0x0005, 0x2007], "<u2")
    path.write_bytes(b"% evt 3.0\n% geometry 16x16\n% end\n" + words.tobytes())
    # a small file: numba's start-up would cost more than it saves
    assert len(read_events(path)) == 1 and calls == ["numpy"]
    assert len(read_events(path, evt3_kernel="numba")) == 1 and calls == ["numpy", "numba"]
    assert len(read_events(path, evt3_kernel="numpy")) == 1 and calls[-1] == "numpy"
    # a file of EVT3_NUMBA_MIN_BYTES words or more: numba, decided once for every chunk
    monkeypatch.setattr(prophesee, "EVT3_NUMBA_MIN_BYTES", words.nbytes)
    calls.clear()
    assert len(read_events(path, chunk_events=1)) == 1 and calls == ["numba"] * 4
    monkeypatch.setattr(prophesee, "EVT3_NUMBA_MIN_BYTES", words.nbytes + 1)
    calls.clear()
    assert len(read_events(path)) == 1 and calls == ["numpy"]
    assert prophesee.default_evt3_kernel(words.nbytes + 1) == "numba"


def test_kernel_choice_errors(monkeypatch, tmp_path):
    path = tmp_path / "e.raw"
    path.write_bytes(b"% evt 3.0\n% geometry 16x16\n% end\n" + bytes(4))
    with pytest.raises(ValueError, match="unknown EVT 3.0 kernel"):
        read_events(path, evt3_kernel="c")
    monkeypatch.setattr(prophesee.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ValueError, match="needs numba: pip install numba"):
        read_events(path, evt3_kernel="numba")
    assert len(read_events(path, evt3_kernel="numpy")) == 0
