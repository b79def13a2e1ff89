"""Segmentor checkpoints: the final payload, user state dicts, and resumable
mmengine checkpoints that stay loadable with ``torch.load(weights_only=True)``.

Final payload (written atomically by the training stage)::

    {"format": "omnilidar-segmentor/1", "state_dict": {...}, "model": {backbone,
     width, depth, in_channels, num_classes}, "label_space": str, "voxel_size": float,
     "config": {...}, "seed": int, "iterations": int, "train": {...}}

Everything in it is a tensor, dict, list, str or number, so it loads with the
safe loader. A user's own checkpoint (the labeler) may be such a payload or a
plain state dict (optionally under a ``state_dict`` key); both are loaded with
``weights_only=True`` and anything else is rejected.

mmengine pickles its message hub into resumable checkpoints (``HistoryBuffer``
objects and numpy values), which the safe loader refuses; the hook from
:func:`omnilidar.checkpoints.weights_only_hook` turns them into tagged plain values on save and back
on load, so resuming needs no exception either.
"""

from __future__ import annotations

from pathlib import Path

import torch

from omnilidar.checkpoints import load_tagged_payload, load_weights_only, save_tagged_payload
from omnilidar.errors import InputError

FORMAT = "omnilidar-segmentor/1"


def save_payload(payload: dict, out: str | Path) -> None:
    """Write a final segmentor payload atomically."""
    save_tagged_payload(payload, out, FORMAT)


def load_payload(path: str | Path) -> dict:
    """Load a payload written by :func:`save_payload` (weights-only)."""
    return load_tagged_payload(path, FORMAT, "segmentor checkpoint")


def load_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """A user's checkpoint as a plain state dict (weights-only).

    Accepts our payload, ``{"state_dict": {...}}`` or a bare ``{name: tensor}`` dict.
    """
    path = Path(path)
    obj = load_weights_only(path, "checkpoint")
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict) or not obj or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise InputError(path, "checkpoint is not a state dict of tensors")
    bad = [k for k, v in obj.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise InputError(path, f"checkpoint holds NaN or infinite weights (first: {bad[0]})")
    return obj
