"""Semantic segmentation metrics: confusion over all scans, IoU, mIoU, accuracy.

Conventions (REFERENCE section 7):

- Labels are train ids 0..K-1 with 0 = ignore; points whose GROUND TRUTH is 0
  are dropped before counting. Predictions are 1..K-1 (a prediction of 0 on a
  labelled point counts as a false positive of nothing and a false negative of
  the true class, as in semantic-kitti-api).
- IoU_c = tp / (tp + fp + fn + 1e-15).
- ``miou`` (semantic-kitti-api): mean over ALL K-1 classes; a class absent from
  both ground truth and predictions has IoU 0 and still counts.
- ``miou_nanmean`` (mmdet3d): mean over classes with tp + fp + fn > 0 only.
  The two differ on sets that lack some classes; results report both.
- accuracy: correct / labelled points (a prediction of 0 counts as wrong;
  semantic-kitti-api leaves such points out of its accuracy denominator, which
  :func:`accuracy_from_confusion` offers for external predictions; our models
  never predict 0, so the two agree for them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnilidar.errors import InputError

EPS = 1e-15


class ConfusionMatrix:
    """Accumulates a ``(K, K)`` int64 confusion matrix (rows: truth, cols: prediction)."""

    def __init__(self, num_classes: int = 20, ignore: int = 0):
        if num_classes < 2:
            raise ValueError("num_classes counts the ignore id too and must be >= 2")
        self.num_classes = int(num_classes)
        self.ignore = int(ignore)
        self.matrix = np.zeros((num_classes, num_classes), np.int64)

    def update(self, truth: np.ndarray, pred: np.ndarray, path=None) -> None:
        """Add one scan; ``path`` names it in error messages."""
        truth = np.asarray(truth).reshape(-1)
        pred = np.asarray(pred).reshape(-1)
        if truth.shape != pred.shape:
            raise InputError(path, f"{len(pred)} predictions for {len(truth)} labelled points")
        for name, a in (("ground truth", truth), ("prediction", pred)):
            if a.dtype.kind not in "iu":
                raise InputError(path, f"{name} ids must be integers, got {a.dtype}")
            if a.size and (a.min() < 0 or a.max() >= self.num_classes):
                raise InputError(path, f"{name} ids must lie in 0..{self.num_classes - 1}")
        keep = truth != self.ignore
        k = self.num_classes
        idx = truth[keep].astype(np.int64) * k + pred[keep].astype(np.int64)
        self.matrix += np.bincount(idx, minlength=k * k).reshape(k, k)

    def result(self) -> "SegmentationScores":
        return scores_from_confusion(self.matrix, self.ignore)


@dataclass(frozen=True)
class SegmentationScores:
    iou: np.ndarray  # (K-1,) per class, ignore id excluded, in class order
    miou: float  # semantic-kitti-api: absent classes count as 0
    miou_nanmean: float  # mmdet3d: mean over classes present in truth or predictions
    accuracy: float
    present: np.ndarray  # (K-1,) bool: tp + fp + fn > 0

    def as_dict(self, class_names=None) -> dict:
        names = class_names or [str(i) for i in range(len(self.iou))]
        return {
            "miou": self.miou,
            "miou_convention": "semantic-kitti-api (absent classes count as 0)",
            "miou_nanmean": self.miou_nanmean,
            "accuracy": self.accuracy,
            "iou": {n: float(v) for n, v in zip(names, self.iou)},
            "present": {n: bool(p) for n, p in zip(names, self.present)},
        }


def scores_from_confusion(confusion: np.ndarray, ignore: int = 0) -> SegmentationScores:
    """IoU per class, both mIoU conventions and accuracy from a confusion matrix.

    Rows and columns of ``ignore`` are excluded from tp/fp/fn (semantic-kitti-api
    zeroes them); the ignore row must already be empty or is dropped here.
    """
    conf = np.asarray(confusion, np.float64).copy()
    if conf.ndim != 2 or conf.shape[0] != conf.shape[1]:
        raise ValueError(f"confusion must be square, got {conf.shape}")
    accuracy = accuracy_from_confusion(confusion, "labelled", ignore)
    conf[ignore, :] = 0
    conf[:, ignore] = 0
    tp = np.diag(conf)
    fp = conf.sum(0) - tp
    fn = conf.sum(1) - tp
    classes = np.array([c for c in range(conf.shape[0]) if c != ignore])
    # A prediction of the ignore id on a labelled point is a miss (fn) of its
    # true class, as in semantic-kitti-api; it was zeroed with the column above.
    missed = np.asarray(confusion, np.float64)[classes, ignore]
    union = (tp + fp + fn)[classes] + missed
    iou = tp[classes] / (union + EPS)
    present = union > 0
    miou = float(iou.mean())
    miou_nan = float(iou[present].mean()) if present.any() else 0.0
    return SegmentationScores(iou, miou, miou_nan, accuracy, present)


ACCURACY_CONVENTIONS = ("labelled", "semantic-kitti-api")


def accuracy_from_confusion(confusion: np.ndarray, convention: str = "labelled", ignore: int = 0) -> float:
    """Point accuracy: ``labelled`` = correct / labelled points (a prediction of the ignore id is
    wrong); ``semantic-kitti-api`` = correct / labelled points predicted as a class, as its
    ``getacc`` (points predicted as the ignore id leave the denominator)."""
    if convention not in ACCURACY_CONVENTIONS:
        raise ValueError(f"accuracy convention {convention!r}; known: {', '.join(ACCURACY_CONVENTIONS)}")
    conf = np.asarray(confusion, np.float64)
    labelled = conf.sum() - conf[ignore].sum()
    correct = np.trace(conf) - conf[ignore, ignore]
    if convention == "semantic-kitti-api":
        labelled -= conf[:, ignore].sum() - conf[ignore, ignore]
    return float(correct / labelled) if labelled > 0 else 0.0
