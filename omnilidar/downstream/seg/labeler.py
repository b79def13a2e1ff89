"""The fixed off-the-shelf labeler that pseudo-labels every generated scan.

Either a user's checkpoint (``downstream.labeler.checkpoint``: a pretrained
MinkUNet / SPVCNN in the SemanticKITTI label space) or, when none is given, one
segmentor trained once by the workflow on 100 % of the real SemanticKITTI
training split and cached. The same labeler labels the samples of every GDA run.

A user checkpoint is loaded with ``torch.load(weights_only=True)`` (classes
such a load refuses, like mmengine's message hub, become inert data) and may be

* our own payload format (architecture and voxel size inside);
* an mmdetection3d MinkUNet / SPVCNN segmentor (``backbone.`` and
  ``decode_head.`` keys; torchsparse or spconv backend): converted on load,
  architecture read from the shapes (:mod:`~.mmdet3d_weights`);
* a plain state dict in our key layout (alone, or under ``state_dict`` /
  ``model``, ``module.`` prefix allowed) whose architecture the labeler
  section describes (``backbone``, ``model.width``, ``model.depth``).

The labeler stage turns each into a payload, so downstream stages see one format.
"""

from __future__ import annotations

from pathlib import Path

import torch

from omnilidar.data.index import read_index
from omnilidar.downstream.seg.checkpoints import FORMAT, load_payload, save_payload
from omnilidar.downstream.seg.dataset import records_from_entries
from omnilidar.downstream.seg.label_spaces import get_label_space
from omnilidar.downstream.seg.models import model_spec, restore
from omnilidar.errors import InputError
from omnilidar.interop.lidm import load_checkpoint, unwrap_state
from omnilidar.interop.mmdet3d import convert_mmdet3d_state, looks_like_mmdet3d

LABEL_SPACE = "semantickitti"  # pseudo-labels are raw SemanticKITTI ids


def import_labeler(settings: dict, checkpoint: str | Path, out: str | Path) -> dict:
    """Check a user's checkpoint (it must load into its architecture) and write
    it as a segmentor payload to ``out``."""
    checkpoint = Path(checkpoint)
    if not checkpoint.is_file():
        raise InputError(checkpoint, "labeler checkpoint not found")
    space = get_label_space(LABEL_SPACE)
    loaded = load_checkpoint(checkpoint)
    if isinstance(loaded, dict) and loaded.get("format") == FORMAT:
        payload = load_payload(checkpoint)  # our own payload
        spec, state, layout = payload["model"], payload["state_dict"], "omnilidar-payload"
        voxel_size = float(payload["voxel_size"])
        if payload.get("label_space") != LABEL_SPACE:
            raise InputError(checkpoint, f"labeler predicts {payload.get('label_space')} classes, "
                                         f"pseudo-labels need {LABEL_SPACE}")
    else:
        spec, state, layout = user_state(settings, loaded, checkpoint, space.num_classes)
        voxel_size = float(settings["voxel_size"])
    if spec["num_classes"] != space.num_classes:
        raise InputError(checkpoint, f"labeler predicts {spec['num_classes']} classes, pseudo-labels need the "
                                     f"{space.num_classes} SemanticKITTI classes")
    restore(spec, state, "torch", "cpu", checkpoint)  # fails clearly if the weights do not fit
    save_payload({"state_dict": state, "model": spec, "label_space": LABEL_SPACE, "voxel_size": voxel_size,
                  "config": settings, "seed": None, "iterations": None,
                  "train": {"imported_from": str(checkpoint), "layout": layout}}, out)
    return {"model": spec, "voxel_size": voxel_size, "source": str(checkpoint), "layout": layout}


def user_state(settings: dict, loaded, checkpoint: Path, num_classes: int) -> tuple[dict, dict, str]:
    """``(spec, our_state_dict, layout)`` of a loaded user checkpoint that is not our payload."""
    state = unwrap_state(loaded, checkpoint)
    if looks_like_mmdet3d(state):
        state, spec = convert_mmdet3d_state(state, checkpoint)
        return spec, state, "mmdet3d"
    bad = next((k for k, v in state.items() if v.is_floating_point() and not torch.isfinite(v).all()), None)
    if bad is not None:
        raise InputError(checkpoint, f"checkpoint holds NaN or infinite weights (first: {bad})")
    return model_spec(settings["backbone"], settings["model"], num_classes), state, "omnilidar"


def training_settings(section: dict) -> dict:
    """The labeler section in the shape :func:`~.training.train_segmentor` takes."""
    return {
        "backend": section["backend"], "device": section["device"],
        "models": {section["backbone"]: section["model"]}, "voxel_size": section["voxel_size"],
        "max_voxels": section["max_voxels"], "max_points": section["max_points"], "schedule": section["schedule"],
        "augmentation": section["augmentation"], "mixing": {"mode": "concat", "generated_share": 0.5},
    }


def labeler_records(index_path: str | Path) -> list[dict]:
    """The labeler's training scans: 100 % of the real SemanticKITTI training split."""
    index = read_index(index_path)
    if index.get("dataset") != LABEL_SPACE:
        raise InputError(index_path, f"the labeler trains on a {LABEL_SPACE} index, got {index.get('dataset')}")
    real = records_from_entries(index["splits"].get("train", []), LABEL_SPACE)
    if not real:
        raise InputError(index_path, "train split holds no scans")
    return real
