"""The fixed box labeler: a user's OpenPCDet checkpoint, imported weights-only.

The checkpoint's ``model_state`` must load strictly into the labeler detector
built from its config for the platform (same OpenPCDet key names and shapes);
it is then written as our detector payload, so pseudo-boxing and evaluation
see one format whatever the labeler's origin. Without a checkpoint the
workflow trains the labeler (``train-box-labeler --index``).
"""

from __future__ import annotations

from pathlib import Path

from omnilidar.errors import InputError


def import_labeler(det: dict, detector: str, platform: str, model_yaml: str, checkpoint: str | Path,
                   out: str | Path) -> dict:
    from omnilidar.downstream.det.checkpoints import load_openpcdet_state, save_payload
    from omnilidar.downstream.det.data_config import platform_config
    from omnilidar.downstream.det.model_config import build, model_config
    from omnilidar.downstream.det.models.detector import adapt_spconv_weights

    cfg = platform_config(det, platform)
    model = model_config(det, detector, cfg, model_yaml)
    net = build(model, cfg)
    # spconv 1.x sparse weights (k, k, k, in, out) are permuted as OpenPCDet does.
    state = adapt_spconv_weights(load_openpcdet_state(checkpoint), net.state_dict())
    missing, unexpected = [], []
    own = net.state_dict()
    for key, value in own.items():
        if key not in state:
            missing.append(key)
        elif tuple(state[key].shape) != tuple(value.shape):
            raise InputError(checkpoint, f"{key} has shape {tuple(state[key].shape)}, the {detector} labeler for "
                                         f"{cfg.name} expects {tuple(value.shape)} (classes {', '.join(cfg.class_names)})")
    unexpected = [k for k in state if k not in own]
    if missing or unexpected:
        what = (f"lacks {len(missing)} weights (first: {missing[0]})" if missing
                else f"has {len(unexpected)} weights the {detector} model does not (first: {unexpected[0]})")
        raise InputError(checkpoint, f"does not load strictly into {detector}: it {what}")
    net.load_state_dict(state, strict=True)
    save_payload({"model_state": {k: v.clone() for k, v in state.items()}, "detector": detector,
                  "model_cfg": model, "data": cfg.as_dict(), "config": det, "seed": None, "iterations": None,
                  "train": {"imported_from": str(checkpoint), "info": {"role": "labeler", "platform": platform}}},
                 out)
    return {"imported_from": str(checkpoint)}
