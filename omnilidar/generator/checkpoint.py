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
    thresholds = payload.get("return_thresholds")  # a calibrated student's (omnilidar.generator.return_decision)
    if thresholds is not None:
        if tuple(thresholds.shape) != (len(payload["domains"]), int(settings["range_image"]["height"])):
            raise InputError(path, f"return_thresholds are {tuple(thresholds.shape)}, not (domains, image rows)")
        denoiser.return_thresholds = thresholds.float()
    range_map = payload.get("range_map")  # a range-calibrated student's
    if range_map is not None:
        rows = int(settings["range_image"]["height"])
        if range_map.dim() != 4 or tuple(range_map.shape[:3]) != (len(payload["domains"]), rows, 2):
            raise InputError(path, f"range_map is {tuple(range_map.shape)}, not (domains, image rows, 2, knots)")
        denoiser.range_map = range_map.float()
    return denoiser.to(device).eval(), payload
