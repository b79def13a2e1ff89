"""Detector checkpoints: our final payload and users' OpenPCDet checkpoints, weights-only.

Final payload (written atomically by training and by the labeler import)::

    {"format": "omnilidar-detector/1", "model_state": {OpenPCDet key names},
     "detector": "voxel_rcnn" | "pv_rcnn", "model_cfg": {MODEL section},
     "data": PlatformConfig.as_dict(), "config": {...}, "seed": int,
     "iterations": int, "provenance": {...}, "train": {...}}

``model_state`` is the key OpenPCDet's own checkpoints use, so OpenPCDet's
``load_params_from_file`` reads our weights as they are. A user's OpenPCDet
checkpoint (``{"model_state": ..., "optimizer_state": ..., "epoch": ...}``) is
loaded with ``torch.load(weights_only=True)`` and only ``model_state`` is used.
"""

from __future__ import annotations

from pathlib import Path

import torch

from omnilidar.checkpoints import load_tagged_payload, load_weights_only, save_tagged_payload
from omnilidar.errors import InputError

FORMAT = "omnilidar-detector/1"


def save_payload(payload: dict, out: str | Path) -> None:
    save_tagged_payload(payload, out, FORMAT)


def load_payload(path: str | Path) -> dict:
    """Load a payload written by :func:`save_payload` (weights-only)."""
    return load_tagged_payload(path, FORMAT, "detector checkpoint")


def load_openpcdet_state(path: str | Path) -> dict[str, torch.Tensor]:
    """The ``model_state`` of a user's OpenPCDet checkpoint (or a bare state dict), weights-only."""
    path = Path(path)
    obj = load_weights_only(path, "OpenPCDet checkpoint")
    if isinstance(obj, dict) and isinstance(obj.get("model_state"), dict):
        obj = obj["model_state"]
    if not isinstance(obj, dict) or not obj or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise InputError(path, "checkpoint has no model_state of tensors (OpenPCDet layout)")
    bad = [k for k, v in obj.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise InputError(path, f"checkpoint holds NaN or infinite weights (first: {bad[0]})")
    return obj
