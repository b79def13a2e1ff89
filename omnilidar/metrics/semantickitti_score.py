"""Scoring SemanticKITTI prediction ``.label`` files made elsewhere.

The semantic-kitti-api convention (``evaluate_semantics.py``): predictions live
in ``<predictions>/sequences/NN/predictions/XXXXXX.label`` next to the
dataset's ``<dataset>/sequences/NN/labels/XXXXXX.label``; both are uint32 with
the raw SemanticKITTI id in the lower 16 bits (``label & 0xFFFF``, instance
bits ignored), both are mapped through the official learning map to the 19
classes (ids the map does not know become 0), ground-truth 0 is ignored and a
prediction of 0 on a labelled point is a miss of its true class; IoU per class
and mIoU over all 19 classes (:mod:`omnilidar.metrics.segmentation`).

Also accepted: two flat folders of ``XXXXXX.label`` files, paired by name.
Every ground-truth file needs its prediction and vice versa, with equal counts.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnilidar.errors import InputError


def _labels_in(folder: Path) -> dict[str, Path]:
    return {p.name: p for p in sorted(folder.glob("*.label"))}


def pair_files(labels: str | Path, predictions: str | Path, sequences: list[str] | None = None
               ) -> list[tuple[Path, Path]]:
    """``(ground truth, prediction)`` pairs, api layout or two flat folders."""
    labels, predictions = Path(labels), Path(predictions)
    for root, what in ((labels, "ground-truth"), (predictions, "predictions")):
        if not root.is_dir():
            raise InputError(root, f"{what} folder not found")
    if (predictions / "sequences").is_dir():
        found = sorted(p.name for p in (predictions / "sequences").iterdir() if (p / "predictions").is_dir())
        seqs = [f"{int(s):02d}" for s in sequences] if sequences else found
        folders = [(labels / "sequences" / s / "labels", predictions / "sequences" / s / "predictions") for s in seqs]
    else:
        if sequences:
            raise InputError(predictions, "--sequences needs the layout sequences/NN/predictions/*.label")
        folders = [(labels, predictions)]
    pairs = []
    for gt_dir, pred_dir in folders:
        if not pred_dir.is_dir():
            raise InputError(pred_dir, "prediction folder not found")
        if not gt_dir.is_dir():
            raise InputError(gt_dir, "ground-truth label folder not found")
        gt, pred = _labels_in(gt_dir), _labels_in(pred_dir)
        for name in sorted(set(gt) - set(pred)):
            raise InputError(gt[name], f"has no prediction {pred_dir / name}")
        for name in sorted(set(pred) - set(gt)):
            raise InputError(pred[name], f"has no ground truth {gt_dir / name}")
        pairs += [(gt[n], pred[n]) for n in sorted(gt)]
    if not pairs:
        raise InputError(predictions, "no .label files to score")
    return pairs


def score_files(pairs: list[tuple[Path, Path]], accuracy_convention: str = "labelled") -> dict:
    """Scores of all pairs together, with the class names and counts; ``accuracy`` in the given
    convention (:func:`omnilidar.metrics.segmentation.accuracy_from_confusion`)."""
    from omnilidar.io import semantickitti
    from omnilidar.metrics.segmentation import ConfusionMatrix, accuracy_from_confusion

    confusion = ConfusionMatrix(semantickitti.NUM_CLASSES)
    unknown = 0
    points = 0
    known = np.zeros(1 << 16, bool)
    known[list(semantickitti.LEARNING_MAP)] = True
    for gt_path, pred_path in pairs:
        truth, _ = semantickitti.read_label(gt_path)
        pred, _ = semantickitti.read_label(pred_path, num_points=len(truth))
        unknown += int((~known[pred]).sum())
        confusion.update(semantickitti.to_train_ids(truth), semantickitti.to_train_ids(pred), pred_path)
        points += len(truth)
    result = confusion.result().as_dict(list(semantickitti.CLASS_NAMES))
    result["accuracy"] = accuracy_from_confusion(confusion.matrix, accuracy_convention)
    return {**result, "accuracy_convention": accuracy_convention, "files": len(pairs), "points": points, "unknown_prediction_ids": unknown,
            "convention": "semantic-kitti-api evaluate_semantics: label & 0xFFFF, learning map, 0 ignored"}
