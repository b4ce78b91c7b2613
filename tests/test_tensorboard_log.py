"""TensorBoard logs written through torchseq.cli.tensorboard_log: the C CRC-32C gives the same
checksums as TensorBoard's own, the files read back with TensorBoard's reader (which checks
every record with its own pure-Python function), and an eval run's logs hold the same tags,
scalars, images, PR curves, hparams and text with either kernel."""

import random
import struct
import sys

import numpy as np
import pytest
from tensorboard.compat.tensorflow_stub.pywrap_tensorflow import masked_crc32c as tb_masked

import torchseq.cli.eval as cli_eval
from torchseq.cli import tensorboard_log
from torchseq.cli.runs import run_main


@pytest.fixture
def restore_kernel():
    """Put back the record writer's checksum function after a test that changes it."""
    from tensorboard.summary.writer import record_writer

    before = record_writer.masked_crc32c
    yield
    record_writer.masked_crc32c = before


def test_masked_crc32c_equals_tensorboards():
    # the CRC-32C check value (RFC 3720 B.4 / the Castagnoli catalogue): "123456789" -> e3069283
    import google_crc32c

    assert google_crc32c.value(b"123456789") == 0xE3069283
    rng = random.Random(0)
    samples = [b"", b"\x00", struct.pack("<Q", 578155), bytes(range(256)) * 3]
    samples += [rng.randbytes(rng.randrange(1, 3000)) for _ in range(40)]
    for data in samples:
        assert tensorboard_log.masked_crc32c(data) == tb_masked(data), len(data)
    assert tensorboard_log.masked_crc32c(bytearray(b"abc")) == tb_masked(b"abc")


def test_the_c_kernel_is_chosen_and_runs(tmp_path, restore_kernel):
    from tensorboard.summary.writer import record_writer

    assert tensorboard_log.crc_kernel() == "c"  # google-crc32c is a dependency
    calls = []
    real = tensorboard_log.masked_crc32c

    with tensorboard_log.summary_writer(tmp_path) as tb:
        assert tensorboard_log.kernel_in_use() == "c"
        assert record_writer.masked_crc32c is real
        record_writer.masked_crc32c = lambda data: calls.append(len(data)) or real(data)
        tb.add_scalar("x", 1.0)
    assert 8 in calls  # the record writer called it, for a length field at least
    assert tensorboard_log.use_kernel("python") == "python"
    assert tensorboard_log.kernel_in_use() == "python"
    assert record_writer.masked_crc32c is tb_masked


def test_without_google_crc32c_the_python_kernel_runs(tmp_path, monkeypatch, restore_kernel):
    monkeypatch.setitem(sys.modules, "google_crc32c", None)  # import fails
    assert tensorboard_log.crc_kernel() == "python"
    with pytest.raises(ValueError, match="google-crc32c"):
        tensorboard_log.use_kernel("c")
    with pytest.raises(ValueError, match="unknown CRC-32C kernel"):
        tensorboard_log.use_kernel("fast")
    with tensorboard_log.summary_writer(tmp_path) as tb:
        tb.add_scalar("x", 2.0)
    assert tensorboard_log.kernel_in_use() == "python"
    assert _records(tmp_path) == [("x", 2.0)]


def _records(folder):
    """The scalars of the folder's one event file, unframed by a plain loop: (tag, value).

    Checks both checksums of every record with TensorBoard's pure-Python function.
    """
    from tensorboard.compat.proto.event_pb2 import Event

    (path,) = folder.glob("events.out.tfevents.*")
    data, at, out = path.read_bytes(), 0, []
    while at < len(data):
        header = data[at:at + 8]
        (length,) = struct.unpack("<Q", header)
        (crc_header,) = struct.unpack("<I", data[at + 8:at + 12])
        body = data[at + 12:at + 12 + length]
        (crc_body,) = struct.unpack("<I", data[at + 12 + length:at + 16 + length])
        assert crc_header == tb_masked(header) and crc_body == tb_masked(body)
        event = Event.FromString(body)
        out += [(v.tag, v.simple_value) for v in event.summary.value
                if v.HasField("simple_value")]
        at += 16 + length
    assert at == len(data)
    return out


def test_records_are_framed_as_tensorflow_frames_them(tmp_path, restore_kernel):
    picture = np.random.default_rng(0).integers(0, 256, (64, 80, 3), dtype=np.uint8)
    with tensorboard_log.summary_writer(tmp_path, kernel="c") as tb:
        for step in range(3):
            tb.add_scalar("loss", 0.5 * step, step)
        tb.add_image("picture", picture, dataformats="HWC")
    assert _records(tmp_path) == [("loss", 0.0), ("loss", 0.5), ("loss", 1.0)]
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tmp_path))
    acc.Reload()
    assert [s.value for s in acc.Scalars("loss")] == [0.0, 0.5, 1.0]
    assert acc.Images("picture")[0].width == 80


def _plugin(acc, name):
    """``{tag: content}`` of a plugin's summaries in the run, {} where it has none.

    The hparams plugin's content parsed (its maps serialise in an order that varies from one
    process to the next).
    """
    from tensorboard.plugins.hparams.plugin_data_pb2 import HParamsPluginData

    try:
        found = acc.PluginTagToContent(name)
    except KeyError:
        return {}
    if name == "hparams":
        return {tag: HParamsPluginData.FromString(c) for tag, c in found.items()}
    return found


def tensorboard_content(folder):
    """What TensorBoard shows of a run's logs, by run folder: everything but wall times.

    Read with TensorBoard's ``EventAccumulator`` (every record's checksums checked). Values
    that are timings (``seconds`` in the tag) are kept by tag only: they differ run to run.
    """
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    content = {}
    for run in sorted([folder, *(p for p in folder.rglob("*") if p.is_dir())]):
        acc = EventAccumulator(str(run), size_guidance={
            k: 0 for k in ("scalars", "images", "tensors", "histograms", "distributions",
                           "audio")})
        acc.Reload()
        tags = acc.Tags()
        timing = lambda tag: "seconds" in tag  # noqa: E731
        content[run.relative_to(folder).as_posix()] = {
            "tags": {k: sorted(v) if isinstance(v, list) else v for k, v in tags.items()},
            "scalars": {t: [(s.step, None if timing(t) else s.value) for s in acc.Scalars(t)]
                        for t in tags["scalars"]},
            "images": {t: [(i.step, i.width, i.height, i.encoded_image_string)
                           for i in acc.Images(t)] for t in tags["images"]},
            "tensors": {t: [(e.step, e.tensor_proto.SerializeToString())
                            for e in acc.Tensors(t)] for t in tags["tensors"]},
            "plugins": {p: _plugin(acc, p) for p in ("hparams", "text", "pr_curves")
                        if _plugin(acc, p)},
            "metadata": {t: acc.SummaryMetadata(t).SerializeToString()
                         for t in tags["tensors"]},
        }
    return content


def test_an_eval_runs_logs_are_the_same_with_either_kernel(tmp_path, monkeypatch,
                                                           restore_kernel):
    out = tmp_path / "o"
    seen = {}
    for kernel in ("python", "c"):  # TensorBoard's own checksums (as before), then the C ones
        monkeypatch.setattr(tensorboard_log, "crc_kernel", lambda k=kernel: k)
        code = run_main(cli_eval.main, "eval.py", [
            "--demo-frames", "40", "--neural-hidden", "256", "--neural-n-output", "40",
            "--no-progress", "--overwrite", "--out", str(out)])
        assert code == 0
        assert tensorboard_log.kernel_in_use() == kernel
        seen[kernel] = tensorboard_content(out / "tensorboard")
    python, c = seen["python"], seen["c"]
    assert python == c
    root = c["."]
    assert {"seqslam/recall_at_1", "neural/recall_at_1", "seqslam/seconds"} <= \
        set(root["scalars"])
    assert set(root["images"]) == {"seqslam_difference_matrix", "neural_activity",
                                   "seqslam_matched_pairs", "neural_matched_pairs",
                                   "pr_curve"}
    assert set(root["plugins"]["pr_curves"]) == {"seqslam/pr_curve", "neural/pr_curve"}
    assert set(root["plugins"]["text"]) == {"config/text_summary"}
    for engine in ("seqslam", "neural"):  # the HParams tab: one sub-run per engine
        assert "_hparams_/session_start_info" in c[engine]["plugins"]["hparams"]
