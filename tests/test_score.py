"""omnilidar score: SemanticKITTI predictions made elsewhere, semantic-kitti-api convention."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from real_samples import REAL

from omnilidar.cli import main
from omnilidar.io import semantickitti

ROOT = Path(__file__).resolve().parents[1]


def real_data_root() -> Path:
    """Where the real samples are (tests/real_samples.py: OMNILIDAR_REAL_DATA)."""
    return REAL


@pytest.fixture
def tiny_kitti() -> Path:
    root = real_data_root() / "semantickitti_tiny"
    if not (root / "sequences" / "00" / "labels" / "000000.label").is_file():
        pytest.skip(f"real SemanticKITTI sample not found under {root} (set OMNILIDAR_REAL_DATA)")
    return root


def _write(path: Path, raw: np.ndarray, instance: np.ndarray | None = None) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    semantickitti.write_label(path, raw.astype(np.uint16), None if instance is None else instance.astype(np.uint16))


def _score(capsys, labels, predictions, *extra) -> dict:
    out = Path(predictions).parent / "scores.json"
    assert main(["score", "--labels", str(labels), "--predictions", str(predictions), "--out", str(out), *extra]) == 0
    capsys.readouterr()
    return json.loads(out.read_text())


def test_real_labels_scored_against_themselves_and_a_known_confusion(tiny_kitti, tmp_path, capsys):
    truth, instance = semantickitti.read_label(tiny_kitti / "sequences/00/labels/000000.label")
    pred_dir = tmp_path / "run" / "sequences" / "00" / "predictions"
    _write(pred_dir / "000000.label", truth)
    same = _score(capsys, tiny_kitti, tmp_path / "run")
    train = semantickitti.to_train_ids(truth)
    present = sorted(set(train[train > 0].tolist()))
    assert [n for n, p in same["present"].items() if p] == [semantickitti.CLASS_NAMES[c - 1] for c in present]
    assert all(same["iou"][semantickitti.CLASS_NAMES[c - 1]] == pytest.approx(1.0) for c in present)
    assert same["miou"] == pytest.approx(len(present) / 19) and same["points"] == len(truth)

    # The most frequent labelled class predicted as the second: IoU 0 and n2 / (n1 + n2).
    counts = {c: int((train == c).sum()) for c in present}
    first, second = sorted(present, key=lambda c: (-counts[c], c))[:2]
    moved = truth.copy()
    moved[train == first] = semantickitti.LEARNING_MAP_INV[second]
    _write(pred_dir / "000000.label", moved)
    wrong = _score(capsys, tiny_kitti, tmp_path / "run", "--sequences", "0")
    names = semantickitti.CLASS_NAMES
    assert wrong["iou"][names[first - 1]] == 0.0
    assert wrong["iou"][names[second - 1]] == pytest.approx(counts[second] / (counts[first] + counts[second]))


def test_synthetic_cases_follow_the_api_convention(tmp_path, capsys):
    # truth: 4 car (raw 10 and moving-car 252), 4 road, 2 unlabelled; instance bits set
    truth = np.array([10, 10, 252, 252, 40, 40, 40, 40, 0, 0])
    pred = np.array([252, 10, 10, 40, 40, 60, 40, 0, 10, 40])  # lane-marking 60 counts as road
    _write(tmp_path / "gt" / "000007.label", truth, instance=np.arange(10) + 3)
    _write(tmp_path / "pred" / "000007.label", pred, instance=np.full(10, 9))
    s = _score(capsys, tmp_path / "gt", tmp_path / "pred")
    # car: tp 3, fn 1 (predicted road); road: tp 3, fp 1, fn 1 (predicted 0 = unlabelled, a miss)
    assert s["iou"]["car"] == pytest.approx(3 / 4)
    assert s["iou"]["road"] == pytest.approx(3 / 5)
    assert s["miou"] == pytest.approx((3 / 4 + 3 / 5) / 19)
    assert s["points"] == 10 and s["files"] == 1 and s["unknown_prediction_ids"] == 0


def test_missing_or_short_predictions_are_one_clear_error(tmp_path, capsys):
    _write(tmp_path / "gt" / "000000.label", np.array([10, 40]))
    _write(tmp_path / "gt" / "000001.label", np.array([10, 40]))
    _write(tmp_path / "pred" / "000000.label", np.array([10, 40, 40]))
    assert main(["score", "--labels", str(tmp_path / "gt"), "--predictions", str(tmp_path / "pred")]) == 2
    assert "000001.label: has no prediction" in capsys.readouterr().err
    _write(tmp_path / "pred" / "000001.label", np.array([10, 40]))
    out = tmp_path / "s.json"
    assert main(["score", "--labels", str(tmp_path / "gt"), "--predictions", str(tmp_path / "pred"),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "pred/000000.label: has 3 labels but its scan has 2 points" in err and not out.exists()


def test_accuracy_convention_of_semantic_kitti_api_leaves_predictions_of_0_out(tmp_path, capsys):
    truth = np.array([10, 10, 252, 252, 40, 40, 40, 40, 0, 0])
    pred = np.array([252, 10, 10, 40, 40, 60, 40, 0, 10, 40])  # one labelled point predicted 0
    _write(tmp_path / "gt" / "000007.label", truth)
    _write(tmp_path / "pred" / "000007.label", pred)
    ours = _score(capsys, tmp_path / "gt", tmp_path / "pred")
    api = _score(capsys, tmp_path / "gt", tmp_path / "pred", "--accuracy-convention", "semantic-kitti-api")
    # 8 labelled points, 6 correct; the API's denominator drops the one predicted 0.
    assert ours["accuracy"] == pytest.approx(6 / 8) and ours["accuracy_convention"] == "labelled"
    assert api["accuracy"] == pytest.approx(6 / 7) and api["accuracy_convention"] == "semantic-kitti-api"
    assert api["iou"] == ours["iou"]
    # Without predictions of 0 the conventions agree.
    _write(tmp_path / "pred" / "000007.label", np.where(pred == 0, 40, pred))
    a = _score(capsys, tmp_path / "gt", tmp_path / "pred")
    b = _score(capsys, tmp_path / "gt", tmp_path / "pred", "--accuracy-convention", "semantic-kitti-api")
    assert a["accuracy"] == b["accuracy"] == pytest.approx(7 / 8)
