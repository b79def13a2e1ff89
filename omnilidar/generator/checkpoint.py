"""The generator's checkpoint: final EMA weights, resolved config, domains and prompt geometry.

Written by :func:`omnilidar.generator.training.train_generator`; read here, without the
trainer, by sampling and every evaluation stage.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from omnilidar.errors import InputError
from omnilidar.generator.unet import build_denoiser

CHECKPOINT_FORMAT = "omnilidar-generator/1"


def load_generator(path: str | Path, device: str | torch.device = "cpu", backend: str | None = None):
    """Load a checkpoint written by :func:`train_generator` (weights-only); return (denoiser, payload).

    ``backend`` overrides the Mamba backend (the state_dict is the same for both).
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "generator checkpoint not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise InputError(path, f"not a readable generator checkpoint: {err}") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise InputError(path, f"not an omnilidar generator checkpoint ({CHECKPOINT_FORMAT})")
    settings = json.loads(json.dumps(payload["config"]))
    if backend is not None:
        settings["model"]["mamba"]["backend"] = backend
    denoiser = build_denoiser(settings, payload["text"]["dim"], len(payload["domains"]))
    try:
        denoiser.load_state_dict(payload["state_dict"], strict=True)
    except RuntimeError as err:
        raise InputError(path, f"weights do not match the stored config: {err}") from None
    # A calibrated student's return decision and range map (omnilidar.generator.return_decision):
    # per domain and image row, or per domain, azimuth sector and image row.
    domains, rows = len(payload["domains"]), int(settings["range_image"]["height"])
    width = int(settings["range_image"]["width"])
    for key, tail, what in (("return_thresholds", 0, "image rows"), ("range_map", 2, "image rows, 2, knots")):
        table = payload.get(key)
        if table is None:
            continue
        shape = tuple(table.shape)
        sectored = len(shape) == 3 + tail
        sectors, rest = (shape[1], shape[2:]) if sectored else (1, shape[1:])  # rest: (rows, [2, knots])
        fits = (len(shape) in (2 + tail, 3 + tail) and shape[0] == domains and rest[0] == rows
                and (tail == 0 or rest[1] == 2) and sectors > 0 and width % sectors == 0)
        if not fits:
            raise InputError(path, f"{key} is {shape}, not (domains, {what}) or (domains, azimuth sectors "
                                   f"dividing {width} columns, {what})")
        setattr(denoiser, key, table.float())
    return denoiser.to(device).eval(), payload
