"""The device contract in docs/guide/export.md: its NumPy/OpenCV host agrees with the library."""

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from torchseq.demo import make_demo
from torchseq.export import export_checkpoint
from torchseq.neural import NeuralConfig, NeuralSeqSLAM
from torchseq.sources import load_traverse

ROOT = Path(__file__).resolve().parents[1]


def doc_snippet() -> dict:
    text = (ROOT / "docs" / "guide" / "export.md").read_text()
    block = re.search(r"<!-- contract-snippet -->\s*```python\n(.*?)```", text, re.S).group(1)
    namespace: dict = {}
    exec(compile(block, "docs/guide/export.md", "exec"), namespace)  # the documented code, as is
    return namespace


@pytest.mark.parametrize("config", [
    NeuralConfig(unit_search="off", hidden=512, n_output=40),
    # the adaptive ring's graph has three more state inputs the host must feed back
    pytest.param(NeuralConfig.adaptive_velocity(hidden=512, n_output=40), marks=pytest.mark.slow),
], ids=["fixed", "adaptive-velocity"])
def test_documented_host_code_gives_the_librarys_decisions(tmp_path, config):
    # colour camera frames at a size that is no multiple of the input (area windows overlap)
    route = make_demo(n_reference=40, size=(90, 125), seed=3)
    rng = np.random.default_rng(0)
    folder = tmp_path / "cam"
    folder.mkdir()
    for i, f in enumerate(route.reference.numpy()):
        g = np.clip(f, 0, 255)
        bgr = np.stack([g * 0.9, g, np.clip(g * 1.1 + rng.normal(0, 3, g.shape), 0, 255)], -1)
        cv2.imwrite(str(folder / f"{i:03d}.png"), bgr.round().astype(np.uint8))
    frames = load_traverse(folder, progress=False)  # the library's own reading
    model = NeuralSeqSLAM(config)
    model.fit(frames)
    model.save(tmp_path / "m.pt", extra={"reference": {
        "source": str(folder), "n_frames": 40, "frame_size": [90, 125]}})
    assert export_checkpoint(tmp_path / "m.pt", tmp_path / "deploy")
    library = model.run(frames).matches
    bgr = [cv2.imread(str(p)) for p in sorted(folder.iterdir())]
    host = list(doc_snippet()["run_float_graph"](str(tmp_path / "deploy" / "model_float.onnx"),
                                                  bgr))
    ref = np.array([r for r, _ in host])
    conf = np.array([c for _, c in host])
    assert np.array_equal(ref, library.reference.numpy())  # every decision
    assert np.allclose(conf, library.confidence.numpy(), atol=1e-4)
