"""Building a segmentation backbone from its config, and restoring one from weights."""

from __future__ import annotations

from pathlib import Path

import torch

from omnilidar.errors import InputError
from omnilidar.segnets.build import BACKBONES, IN_CHANNELS, build_segmentor

def model_spec(backbone: str, settings: dict, num_classes: int) -> dict:
    """The architecture record stored with a checkpoint (enough to rebuild it)."""
    if backbone not in BACKBONES:
        raise InputError(None, f"unknown backbone {backbone!r}; known: {', '.join(BACKBONES)}")
    return {"backbone": backbone, "width": settings["width"], "depth": int(settings["depth"]),
            "in_channels": IN_CHANNELS, "num_classes": int(num_classes)}


def restore(spec: dict, state_dict: dict, backend: str, device, source: str | Path) -> torch.nn.Module:
    """Build ``spec`` and load ``state_dict`` strictly; a mismatch names ``source``."""
    model = build_segmentor(spec, backend, device)
    try:
        model.load_state_dict(state_dict, strict=True)
    except RuntimeError as err:
        lines = str(err).strip().splitlines()
        raise InputError(source, f"weights do not fit {spec['backbone']} {spec['width']} depth {spec['depth']} "
                                 f"with {spec['num_classes']} classes: {' '.join(lines[:3])[:300]}") from None
    return model.to(device).eval()
