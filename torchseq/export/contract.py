"""The device contract, written into the exported ONNX files as ``metadata_props``.

A host that feeds an exported graph must make its input exactly as the library does, or
decisions drift (a few percent of frames with another grey conversion or resize). The rules
travel with the files under ``torchseq.*`` keys; ``docs/guide/export.md`` ("Device contract") has
a NumPy/OpenCV reference that follows them and that a test runs against the library.
"""

from __future__ import annotations

from pathlib import Path

import onnx

from torchseq.atomic import atomic_path

CONTRACT_VERSION = "1"
GREY_RULE = ("camera BGR uint8 -> grey uint8 by cv2.cvtColor(COLOR_BGR2GRAY) "
             "(BT.601: 0.299 R + 0.587 G + 0.114 B, rounded), before any resize")
RESIZE_RULE = ("grey uint8 -> float32, then area mean to the target size: output row i "
               "averages source rows floor(i*H/h) .. ceil((i+1)*H/h)-1, columns alike "
               "(torch adaptive_avg_pool2d); no resize when the size already matches")
INT_INPUT_RULE = ("resize (as torchseq.resize) to device_frame_size, then round half away "
                  "from zero and clamp to uint8; a camera already at device_frame_size "
                  "gives its uint8 grey frames as they are")


def contract(kind: str, model, report: dict, threshold: float | None) -> dict[str, str]:
    """The ``torchseq.*`` metadata of one exported graph.

    Args:
        kind: ``"float"`` (float and quantised graphs) or ``"integer"``.
        model: the exported :class:`~torchseq.neural.NeuralSeqSLAM`.
        report: ``export_and_validate``'s report (input size, device frame size, pool).
        threshold: suggested minimum confidence (float units), or None when unknown.
    """
    h, w = report["input_size"]
    n = int(model.n_units)
    props = {
        "torchseq.contract_version": CONTRACT_VERSION,
        "torchseq.graph": kind,
        "torchseq.input_size": f"{h}x{w}",
        "torchseq.n_units": str(n),
        "torchseq.grey": GREY_RULE,
        "torchseq.reference_frames": str(int(model.unit_to_reference[-1, 1])),
    }
    if kind == "float":
        props.update({
            "torchseq.input": f"frames float32 (B, {h}, {w}): grey levels 0..255",
            "torchseq.resize": RESIZE_RULE,
            "torchseq.initial_state": f"zeros float32 (B, {n})",
            "torchseq.confidence_unit": "1.0",
        })
    else:
        dh, dw = report["device_frame_size"]
        ph, pw = report["integer_pool"]
        props.update({
            "torchseq.input": f"frames uint8 (B, {dh}, {dw})",
            "torchseq.device_frame_size": f"{dh}x{dw}",
            "torchseq.integer_pool": f"{ph}x{pw}",
            "torchseq.resize": INT_INPUT_RULE + "; " + RESIZE_RULE,
            "torchseq.initial_state": f"zeros int32 (B, {n})",
            "torchseq.confidence_unit": str(2.0 ** -16),
        })
    props["torchseq.confidence_threshold"] = "none" if threshold is None else f"{threshold:.6g}"
    return props


def write_contract(path: str | Path, props: dict[str, str]) -> None:
    """Add (or replace) ``props`` in an ONNX file's ``metadata_props``, atomically."""
    m = onnx.load(str(path))
    keep = [p for p in m.metadata_props if p.key not in props]
    del m.metadata_props[:]
    m.metadata_props.extend(keep)
    for key, value in props.items():
        m.metadata_props.add(key=key, value=value)
    with atomic_path(path) as tmp:
        onnx.save(m, str(tmp))


def read_contract(path: str | Path) -> dict[str, str]:
    """The ``torchseq.*`` metadata of an exported ONNX file."""
    m = onnx.load(str(path), load_external_data=False)
    return {p.key: p.value for p in m.metadata_props if p.key.startswith("torchseq.")}
