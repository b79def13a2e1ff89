"""Building a MinkUNet or SPVCNN from an architecture record (``backbone``, ``width``, ``depth``,
``in_channels``, ``num_classes``): the one builder of the students, the labelers, the FSVD/FPVD
extractors and the checkpoint converters."""

from __future__ import annotations

import torch

from omnilidar.errors import InputError
from omnilidar.segnets.minkunet import MinkUNet
from omnilidar.segnets.spvcnn import SPVCNN

BACKBONES = ("minkunet", "spvcnn")
IN_CHANNELS = 4  # x, y, z, intensity (0..1)


def build_segmentor(spec: dict, backend: str = "auto", device: str | torch.device = "cpu",
                    generator: torch.Generator | None = None) -> torch.nn.Module:
    """A freshly initialised MinkUNet or SPVCNN (weights drawn from ``generator``)."""
    cls = {"minkunet": MinkUNet, "spvcnn": SPVCNN}.get(spec["backbone"])
    if cls is None:
        raise InputError(None, f"unknown backbone {spec['backbone']!r}; known: {', '.join(BACKBONES)}")
    try:
        return cls(in_channels=spec["in_channels"], num_classes=spec["num_classes"], width=spec["width"],
                   depth=spec["depth"], backend=backend, device=device, generator=generator)
    except ValueError as err:  # unknown width or depth
        raise InputError(None, f"{spec['backbone']}: {err}") from None
