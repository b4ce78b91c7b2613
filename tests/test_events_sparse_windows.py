"""Event frames follow the events a file holds, not its time span (issue 23, item 1).

A 300-byte AEDAT 2.0 file with two events 2**31 us apart asked for 14 GB of frames; two
events 100 s apart built 10,001 dense sensor-size frames (about 2 GB at peak). Empty windows
are now zero frames made when used (:class:`WindowFrames`), and frames that are mostly empty
and too many to hold are refused before anything is allocated, with a message naming the
span, the window and the remedies.
"""

import resource

import numpy as np
import pytest
import torch
from events_oracle import loop_frames, loop_pool

import torchseq.cli.eval as cli_eval
from torchseq.cli.runs import run_main
from torchseq.events import EventStream, accumulate, load_event_frames, make_events, write_aedat2
from torchseq.events.frames import MAX_SPARSE_ELEMENTS
from torchseq.events.traverse import WindowFrames, load_event_windows
from torchseq.sources import EventFrameOptions, TraverseError, load_traverse


def two_events(path, gap_us):
    ev = make_events(np.array([5, 5 + gap_us]), np.array([3, 100]), np.array([4, 90]),
                     np.array([1, 0]))
    write_aedat2(path, EventStream(ev, (128, 128)))
    return path


class memory_cap:
    """Address-space cap of ``extra`` bytes over what the process holds now."""

    def __init__(self, extra):
        self.extra = extra

    def __enter__(self):
        self.soft, self.hard = resource.getrlimit(resource.RLIMIT_AS)
        used = int(open("/proc/self/statm").read().split()[0]) * resource.getpagesize()
        resource.setrlimit(resource.RLIMIT_AS, (used + self.extra, self.hard))

    def __exit__(self, *exc):
        resource.setrlimit(resource.RLIMIT_AS, (self.soft, self.hard))


def test_two_events_2_31_us_apart_are_refused_before_allocating(tmp_path):
    path = two_events(tmp_path / "far.aedat", 2**31)
    with memory_cap(1 << 30), pytest.raises(TraverseError) as err:
        load_traverse(path, progress=False)
    text = str(err.value)
    assert err.value.__cause__ is not None and not isinstance(err.value.__cause__, MemoryError)
    assert "214,749 windows of 10 ms span 2,147.5 s" in text, text
    assert "only 2 of them hold events" in text and "--window-ms" in text
    assert "--t-start/--duration" in text and "--event-count" in text


def test_two_events_100_s_apart_give_10001_frames_in_bounded_memory(tmp_path):
    path = two_events(tmp_path / "s100.aedat", 100_000_000)
    with memory_cap(600 << 20):  # the dense sensor-size frames alone are 655 MB
        x = load_traverse(path, progress=False, size=(32, 64))
    assert x.shape == (10_001, 32, 64)
    # independent reference: the plain loop at sensor size, then the resize
    ev = make_events(np.array([5, 100_000_005]), np.array([3, 100]), np.array([4, 90]),
                     np.array([1, 0]))
    ref = loop_frames(ev[[0]], 128, 128, window_us=10_000, mode="count")[0]
    first = load_traverse(torch.from_numpy(ref[None]).float(), progress=False, size=(32, 64))
    assert torch.equal(x[0], first[0]) and float(x[0].sum()) > 0
    assert float(x[1:-1].abs().sum()) == 0 and float(x[-1].sum()) > 0


@pytest.mark.parametrize("mode", ["count", "signed", "binary", "two_channel"])
@pytest.mark.parametrize("frame_size", [None, (4, 6)])
def test_sparse_windows_equal_the_dense_loop(tmp_path, mode, frame_size):
    rng = np.random.default_rng(1)
    t = np.sort(np.concatenate([rng.integers(0, 30_000, 200),  # a burst, a pause, a burst
                                rng.integers(900_000, 950_000, 200)]))
    ev = make_events(t, rng.integers(0, 12, 400), rng.integers(0, 8, 400),
                     rng.integers(0, 2, 400))
    path = tmp_path / "gap.npz"
    np.savez(path, events=ev, sensor_size=np.array([12, 8]))
    sparse = load_event_windows(path, window_ms=10.0, mode=mode, frame_size=frame_size)
    assert isinstance(sparse, WindowFrames) and len(sparse) == 95
    assert len(sparse.windows) < 20  # only the windows holding events are built
    ref = loop_frames(ev, 12, 8, window_us=10_000, mode=mode)
    ref = np.abs(ref) * (255 if mode == "binary" else 1)
    if frame_size is not None:
        ref = loop_pool(ref, *frame_size)
    if mode == "two_channel":
        ref = np.concatenate([ref[:, 0], ref[:, 1]], axis=-1)
    dense = load_event_frames(path, window_ms=10.0, mode=mode, frame_size=frame_size)
    np.testing.assert_allclose(dense.numpy(), ref, atol=1e-5)
    for i in range(len(sparse)):
        assert torch.equal(sparse[i], dense[i])


def test_dense_accumulate_refuses_mostly_empty_frames_naming_the_span():
    ev = make_events(np.array([0, 10**9]), np.array([1, 2]), np.array([1, 2]), np.array([1, 0]))
    with memory_cap(1 << 30), pytest.raises(
            ValueError, match=r"100,001 windows of 10 ms span 1,000.0 s"):
        accumulate(ev, (128, 128), window_us=10_000)
    assert 100_001 * 128 * 128 > MAX_SPARSE_ELEMENTS
    # full windows of the same size are not refused by this rule (they hold events)
    frames = accumulate(ev, (128, 128), window_us=10**9 // 4)
    assert frames.shape == (5, 128, 128)


def test_eval_on_a_far_apart_recording_says_why_in_one_line(tmp_path, capsys):
    path = two_events(tmp_path / "far.aedat", 2**31)
    with memory_cap(1 << 30):
        code = run_main(cli_eval.main, "eval.py", [
            "--engine", "seqslam", "--reference", str(path), "--query", str(path),
            "--no-progress", "--no-tensorboard", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "far.aedat" in err[0] and "only 2 of them hold events" in err[0]


def test_event_frame_options_reach_the_sparse_path(tmp_path):
    path = two_events(tmp_path / "s.aedat", 50_000)
    x = load_traverse(path, events=EventFrameOptions(window_ms=20.0), progress=False)
    assert x.shape == (3, 128, 128) and float(x[1].sum()) == 0
