import cv2
import numpy as np
import pytest
import torch
from conftest import shared_data

from torchseq.ground_truth import (
    GroundTruthError,
    alignment_ground_truth,
    load_ground_truth,
)
from torchseq.sources import TraverseError, load_traverse, natural_key


def write_images(folder, frames, names=None):
    folder.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / (names[i] if names else f"{i}.png")), f)


def test_image_folder_natural_order_and_grey(tmp_path):
    frames = [np.full((8, 12, 3), v, np.uint8) for v in (10, 20, 30)]
    frames[1][..., 2] = 200  # OpenCV is BGR: channel 2 is red
    write_images(tmp_path / "t", frames, ["img2.png", "img10.png", "img1.png"])
    x = load_traverse(tmp_path / "t", progress=False)
    assert x.shape == (3, 8, 12) and x.dtype == torch.float32
    # natural order: img1 (30), img2 (10), img10 (red 200, green/blue 20)
    assert x[0, 0, 0] == 30 and x[1, 0, 0] == 10
    assert abs(float(x[2, 0, 0]) - (0.299 * 200 + 0.587 * 20 + 0.114 * 20)) < 1.0
    assert sorted(["a10", "a2", "a1"], key=natural_key) == ["a1", "a2", "a10"]


def test_image_folder_errors(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(TraverseError, match="no images"):
        load_traverse(tmp_path / "empty", progress=False)
    write_images(tmp_path / "mixed", [np.zeros((8, 8), np.uint8), np.zeros((9, 8), np.uint8)])
    with pytest.raises(TraverseError, match="mixed image sizes"):
        load_traverse(tmp_path / "mixed", progress=False)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "0.png").write_bytes(b"not a png")
    with pytest.raises(TraverseError, match="cannot read image"):
        load_traverse(tmp_path / "bad", progress=False)
    with pytest.raises(TraverseError, match="no such file"):
        load_traverse(tmp_path / "missing", progress=False)


def test_arrays_and_array_files(tmp_path):
    a = np.random.default_rng(0).integers(0, 255, (4, 6, 7)).astype(np.uint8)
    assert torch.equal(load_traverse(a), torch.from_numpy(a).float())
    np.save(tmp_path / "f.npy", a)
    assert torch.equal(load_traverse(tmp_path / "f.npy"), torch.from_numpy(a).float())
    np.savez(tmp_path / "f.npz", frames=a)
    assert torch.equal(load_traverse(tmp_path / "f.npz"), torch.from_numpy(a).float())
    with pytest.raises(TraverseError, match="NaN"):
        load_traverse(np.full((2, 3, 3), np.nan))
    with pytest.raises(TraverseError, match="must be"):
        load_traverse(np.zeros((3, 3)))
    with pytest.raises(TraverseError, match="no frames"):
        load_traverse(np.zeros((0, 3, 3)))


def test_video_round_trip(tmp_path):
    path = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (32, 24))
    if not writer.isOpened():
        pytest.skip("OpenCV build cannot write MJPG video here")
    for v in (30, 120, 220):
        writer.write(np.full((24, 32, 3), v, np.uint8))
    writer.release()
    x = load_traverse(path, progress=False)
    assert x.shape == (3, 24, 32)
    assert [round(float(f.mean()) / 10) for f in x] == [3, 12, 22]


def test_corridor_loads():
    x = load_traverse(shared_data("corridor", "ref"), progress=False)
    assert x.shape == (111, 120, 160)


def test_alignment_ground_truth():
    gt = alignment_ground_truth(11, 21, 1.0)
    assert gt.shape == (11, 21)
    assert gt[:, 0].nonzero()[0].tolist() == [0, 1]
    assert gt[:, 10].nonzero()[0].tolist() == [4, 5, 6]
    assert gt[:, 20].nonzero()[0].tolist() == [9, 10]


def test_ground_truth_files(tmp_path):
    csv = tmp_path / "gt.csv"
    csv.write_text("query,references\n0,0 1\n1,1\n2,\n")
    gt = load_ground_truth(csv, 3, 3)
    assert gt.tolist() == [[True, False, False], [True, True, False], [False, False, False]]
    with pytest.raises(GroundTruthError, match="covers 3 queries"):
        load_ground_truth(csv, 3, 4)
    with pytest.raises(GroundTruthError, match="outside"):
        load_ground_truth(csv, 1, 3)
    np.save(tmp_path / "gt.npy", np.eye(3, dtype=np.int64))
    assert load_ground_truth(tmp_path / "gt.npy", 3, 3).sum() == 3
    with pytest.raises(GroundTruthError, match=r"\(3, 3\)"):
        load_ground_truth(tmp_path / "gt.npy", 3, 4)
    (tmp_path / "bad.csv").write_text("a,b\n")
    with pytest.raises(GroundTruthError, match="header"):
        load_ground_truth(tmp_path / "bad.csv", 3, 3)


def test_real_ground_truth_files():
    gt = load_ground_truth(shared_data("corridor", "ground_truth.csv"), 111, 111)
    assert gt[:, 0].nonzero()[0].tolist() == [0, 1, 2]  # the file's first row
    assert gt[:, 50].nonzero()[0].tolist() == [48, 49, 50, 51, 52]
    lens = shared_data("lens-davis128", "example-reference_example-query_GT.npy")
    assert np.array_equal(load_ground_truth(lens, 100, 100), np.eye(100, dtype=bool))
