"""Scoring predictions as Pi3DET does: KITTI annos, OpenPCDet's eval.py, R11 and R40.

Ground truth is every box of the platform's classes in each val frame (Pi3DET
does not range-filter boxes, and every box is "easy"); predictions are the
detector's boxes in the frame's own coordinates. Both go through
:func:`omnilidar.metrics.kitti_ap.pi3det_annos` and
:func:`omnilidar.metrics.kitti_ap.kitti_eval`. The numbers reported per class
are 3D AP with 11 and 40 recall positions at the class's IoU 0.5 overlap set
(Car: the second set, Pedestrian: the first), BEV AP at the same overlap, and
the 41-point precision curves behind them for the figure.
"""

from __future__ import annotations

import numpy as np

from omnilidar.errors import InputError

# Which of OpenPCDet's two overlap sets holds IoU 0.5 for a class (Car 0.7/0.5, Pedestrian 0.5/0.25).
OVERLAP_SET_AT_05 = {"Car": 1, "Pedestrian": 0}


def annos(records: list[dict], predictions: list[dict], class_names) -> tuple[list[dict], list[dict]]:
    """KITTI-format (gt, dt) annos of the frames, in the same order."""
    from omnilidar.metrics.kitti_ap import pi3det_annos

    if len(records) != len(predictions):
        raise InputError(None, f"{len(records)} frames but {len(predictions)} predictions")
    gt, dt = [], []
    for rec, pred in zip(records, predictions):
        if rec["frame_id"] != pred["frame_id"]:
            raise InputError(None, f"prediction for frame {pred['frame_id']} paired with frame {rec['frame_id']}")
        keep = [i for i, n in enumerate(rec["names"]) if n in class_names]
        boxes = np.asarray(rec["boxes"], np.float32).reshape(-1, 7)[keep]
        gt.append(pi3det_annos(boxes, [rec["names"][i] for i in keep]))
        dt.append(pi3det_annos(pred["boxes"], pred["names"], scores=pred["scores"]))
    return gt, dt


def score(records: list[dict], predictions: list[dict], class_names) -> dict:
    """Per-class AP (R11 and R40, 3D and BEV at IoU 0.5) and precision curves."""
    from omnilidar.metrics.kitti_ap import kitti_eval

    gt, dt = annos(records, predictions, class_names)
    result = kitti_eval(gt, dt, list(class_names))
    per_class = {}
    for name in class_names:
        s = OVERLAP_SET_AT_05[name]
        per_class[name] = {
            "3d_R11@0.5": ap_value(result, name, "3d", "R11", s),
            "3d_R40@0.5": ap_value(result, name, "3d", "R40", s),
            "bev_R11@0.5": ap_value(result, name, "bev", "R11", s),
            "bev_R40@0.5": ap_value(result, name, "bev", "R40", s),
            "precision_3d@0.5": precision_curve(result, name, "3d", s),
            "gt_boxes": int(sum(int(np.sum(np.asarray(g["name"]) == name)) for g in gt)),
            "detections": int(sum(int(np.sum(np.asarray(d["name"]) == name)) for d in dt)),
        }
    return per_class


def ap_value(result: dict, name: str, metric: str, recall_positions: str, overlap_set: int) -> float:
    """One AP number (percent, easy difficulty: Pi3DET marks every box easy) from kitti_eval's result."""
    return float(result[recall_positions][name][metric][overlap_set]["easy"])


def precision_curve(result: dict, name: str, metric: str, overlap_set: int) -> list[float]:
    """The 41 precision values (monotone, per score threshold index) behind the AP."""
    curve = result.get("precision", {}).get(name, {}).get(metric)
    if curve is None:
        return []
    return [float(v) for v in np.asarray(curve[overlap_set]["easy"]).reshape(-1)]
