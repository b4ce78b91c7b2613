"""Memory accounting of Neural SeqSLAM beside classic SeqSLAM's (bytes stored for a route)."""

from __future__ import annotations

import torch


def model_bytes(state_dict: dict[str, torch.Tensor], masked_only: bool = False) -> int:
    """Bytes of everything a model stores.

    Args:
        state_dict: the model's ``state_dict()``.
        masked_only: count only the weights inside the masks (as a sparse store would,
            value only) plus every other buffer, instead of the dense tensors.
    """
    total = 0
    for name, t in state_dict.items():
        if masked_only and name.endswith(".weight"):
            mask = state_dict[name[: -len("weight")] + "mask"]
            total += int(mask.sum()) * t.element_size()
        elif masked_only and name.endswith(".mask"):
            continue
        else:
            total += t.numel() * t.element_size()
    return total


def seqslam_bytes(n_reference: int, descriptor: int = 2048, itemsize: int = 4) -> int:
    """Bytes classic SeqSLAM keeps for a route: ``R x descriptor`` float32 descriptors."""
    return int(n_reference) * int(descriptor) * int(itemsize)


def seqslam_template_bytes(n_reference: int, image_size: tuple[int, int] = (32, 64)) -> int:
    """Bytes of classic SeqSLAM's templates: one patch-normalised frame per place, 1 byte a value.

    OpenSeqSLAM stores ``127 + round(z)`` in uint8 (``SeqSLAMConfig``'s default
    ``image_size`` 32 x 64: 2,048 bytes a place). The figure recorded beside
    ``model_bytes`` in metrics.json and train.json.
    """
    return int(n_reference) * int(image_size[0]) * int(image_size[1])


def memory_comparison(model, descriptor: int = 2048) -> dict:
    """Bytes a fitted model stores beside the bytes classic SeqSLAM keeps for the same route.

    Returns:
        ``{"n_reference", "n_units", "neural_bytes", "neural_masked_bytes",
        "seqslam_bytes"}``.
    """
    sd = model.state_dict()
    n_ref = int(model.unit_to_reference[-1, 1])
    return {"n_reference": n_ref, "n_units": model.n_units,
            "neural_bytes": model_bytes(sd),
            "neural_masked_bytes": model_bytes(sd, masked_only=True),
            "seqslam_bytes": seqslam_bytes(n_ref, descriptor)}
