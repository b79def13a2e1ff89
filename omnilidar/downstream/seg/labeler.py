"""The fixed off-the-shelf labeler that pseudo-labels every generated scan.

Either a user's checkpoint (``downstream.labeler.checkpoint``: a pretrained
MinkUNet / SPVCNN in the SemanticKITTI label space) or, when none is given, one
segmentor trained once by the workflow on 100 % of the real SemanticKITTI
training split and cached. The same labeler labels the samples of every GDA run.

A user checkpoint is loaded with ``torch.load(weights_only=True)``: our own
payload format, or a plain state dict whose architecture is described by the
labeler section (``backbone``, ``model.width``, ``model.depth``). The labeler
stage turns either into a payload, so downstream stages see one format.
"""

from __future__ import annotations

from pathlib import Path

from omnilidar.downstream.seg.checkpoints import FORMAT, load_payload, load_state_dict, save_payload
from omnilidar.downstream.seg.label_spaces import get_label_space
from omnilidar.downstream.seg.models import model_spec, restore
from omnilidar.errors import InputError

LABEL_SPACE = "semantickitti"  # pseudo-labels are raw SemanticKITTI ids


def import_labeler(settings: dict, checkpoint: str | Path, out: str | Path) -> dict:
    """Check a user's checkpoint (it must load into the configured architecture)
    and write it as a segmentor payload to ``out``."""
    checkpoint = Path(checkpoint)
    space = get_label_space(LABEL_SPACE)
    try:
        payload = load_payload(checkpoint)
        spec, state = payload["model"], payload["state_dict"]
        voxel_size = float(payload["voxel_size"])
        if payload.get("label_space") != LABEL_SPACE:
            raise InputError(checkpoint, f"labeler predicts {payload.get('label_space')} classes, "
                                         f"pseudo-labels need {LABEL_SPACE}")
    except InputError as err:
        if f"({FORMAT})" not in str(err):
            raise
        spec = model_spec(settings["backbone"], settings["model"], space.num_classes)
        state = load_state_dict(checkpoint)
        voxel_size = float(settings["voxel_size"])
    restore(spec, state, "torch", "cpu", checkpoint)  # fails clearly if the weights do not fit
    save_payload({"state_dict": state, "model": spec, "label_space": LABEL_SPACE, "voxel_size": voxel_size,
                  "config": settings, "seed": None, "iterations": None,
                  "train": {"imported_from": str(checkpoint)}}, out)
    return {"model": spec, "voxel_size": voxel_size, "source": str(checkpoint)}


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
    from omnilidar.data.index import read_index
    from omnilidar.downstream.seg.dataset import records_from_entries

    index = read_index(index_path)
    if index.get("dataset") != LABEL_SPACE:
        raise InputError(index_path, f"the labeler trains on a {LABEL_SPACE} index, got {index.get('dataset')}")
    real = records_from_entries(index["splits"].get("train", []), LABEL_SPACE)
    if not real:
        raise InputError(index_path, "train split holds no scans")
    return real
