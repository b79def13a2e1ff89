"""mIoU conventions on hand-computed confusion matrices."""

from __future__ import annotations

import numpy as np
import pytest

from omnilidar.errors import InputError
from omnilidar.io.semantickitti import CLASS_NAMES, NUM_CLASSES
from omnilidar.metrics.segmentation import ConfusionMatrix, scores_from_confusion

TRUTH = np.array([1, 1, 2, 2, 3, 0, 0])
PRED = np.array([1, 2, 2, 2, 1, 3, 1])
# Labelled pairs (truth, pred): (1,1) (1,2) (2,2) (2,2) (3,1); truth-0 points dropped.
# class 1: tp 1, fp 1, fn 1 -> 1/3; class 2: tp 2, fp 1 -> 2/3; class 3: fn 1 -> 0.


def test_hand_computed_iou_all_classes_present():
    cm = ConfusionMatrix(4)
    cm.update(TRUTH, PRED)
    s = cm.result()
    np.testing.assert_allclose(s.iou, [1 / 3, 2 / 3, 0.0])
    assert s.miou == pytest.approx(1 / 3)
    assert s.miou_nanmean == pytest.approx(1 / 3)
    assert s.accuracy == pytest.approx(3 / 5)
    assert cm.matrix[0].sum() == 0  # ignore ground truth dropped


def test_absent_class_counts_as_zero_in_kitti_convention_only():
    cm = ConfusionMatrix(5)  # class 4 never appears
    cm.update(TRUTH, PRED)
    s = cm.result()
    assert s.iou[3] == 0.0 and not s.present[3]
    assert s.miou == pytest.approx((1 / 3 + 2 / 3 + 0 + 0) / 4)
    assert s.miou_nanmean == pytest.approx((1 / 3 + 2 / 3 + 0) / 3)


def test_scores_from_a_written_out_confusion_matrix():
    # rows truth 0..3, cols prediction 0..3
    conf = np.array([
        [9, 9, 9, 9],  # ignore truth: never counted
        [0, 8, 2, 0],  # class 1: 8 right, 2 as class 2
        [1, 0, 5, 4],  # class 2: 1 predicted as ignore (a miss), 4 as class 3
        [0, 0, 0, 0],  # class 3 absent from truth, predicted 4 times
    ])
    s = scores_from_confusion(conf)
    # class1: tp 8, fp 0, fn 2 -> 0.8; class2: tp 5, fp 2, fn 1 + 4 -> 5/12; class3: tp 0, fp 4 -> 0
    np.testing.assert_allclose(s.iou, [0.8, 5 / 12, 0.0])
    assert s.present.tolist() == [True, True, True]
    assert s.miou == pytest.approx((0.8 + 5 / 12) / 3)
    assert s.miou_nanmean == pytest.approx((0.8 + 5 / 12) / 3)
    assert s.accuracy == pytest.approx(13 / 20)


def test_prediction_of_ignore_is_a_miss():
    cm = ConfusionMatrix(3)
    cm.update(np.array([1, 1]), np.array([0, 1]))
    s = cm.result()
    assert s.iou[0] == pytest.approx(0.5)
    assert s.accuracy == pytest.approx(0.5)


def test_accumulates_over_scans_like_one_concatenated_scan():
    rng = np.random.default_rng(0)
    truth = [rng.integers(0, NUM_CLASSES, n) for n in (50, 70, 30)]
    pred = [rng.integers(1, NUM_CLASSES, len(t)) for t in truth]
    a, b = ConfusionMatrix(NUM_CLASSES), ConfusionMatrix(NUM_CLASSES)
    for t, p in zip(truth, pred):
        a.update(t, p)
    b.update(np.concatenate(truth), np.concatenate(pred))
    assert np.array_equal(a.matrix, b.matrix)
    d = a.result().as_dict(list(CLASS_NAMES))
    assert set(d["iou"]) == set(CLASS_NAMES) and len(d["iou"]) == 19
    assert 0.0 <= d["miou"] <= d["miou_nanmean"] <= 1.0


def test_bad_input_names_the_file():
    cm = ConfusionMatrix(NUM_CLASSES)
    with pytest.raises(InputError, match="scan.label.*3 predictions for 2"):
        cm.update(np.array([1, 2]), np.array([1, 2, 3]), path="scan.label")
    with pytest.raises(InputError, match="must lie in"):
        cm.update(np.array([1, 25]), np.array([1, 2]), path="scan.label")
    with pytest.raises(InputError, match="integers"):
        cm.update(np.array([1.0]), np.array([1]), path="scan.label")
