"""KITTI 3D object detection AP with the semantics of OpenPCDet's
``pcdet/datasets/kitti/kitti_object_eval_python/eval.py`` (``get_official_eval_result``).

Inputs are KITTI-format annos, one dict per frame: ``name``, ``truncated``,
``occluded``, ``alpha``, ``bbox`` (N, 4 image box), ``dimensions`` (N, 3 as
l, h, w), ``location`` (N, 3 camera frame, bottom centre), ``rotation_y`` and,
for detections, ``score``. What is reproduced, per class, difficulty (easy /
moderate / hard), metric (bbox: image IoU; bev: rotated IoU of [x, z, l, w, ry];
3d: that overlap times the camera-y overlap of [y - h, y]) and overlap set:

* difficulty filters: a ground-truth box is ignored when occluded > 0/1/2,
  truncated > 0.15/0.3/0.5 or its image height <= 40/25/25 px; Van counts as an
  ignored Car and Person_sitting as an ignored Pedestrian; DontCare image boxes
  absorb unmatched detections (bbox metric only, overlap over the detection's
  area); a detection lower than the minimum height is ignored;
* matching: per ground-truth box in order, the unassigned detection with overlap
  strictly above the threshold and the highest score (when collecting the score
  thresholds) or the highest overlap, detections of ignored boxes last (when
  counting at a threshold);
* the 41 score thresholds taken from the matched scores as ``get_thresholds``
  picks them (so the curve is indexed by thresholds, not recall: with fewer than
  40 boxes it is truncated: 4 boxes, 2 perfect detections -> R11 9.09);
* precision, recall and AOS per threshold, made monotone (maximum over later
  thresholds); R11 = mean of precision at indices 0, 4, ..., 40 (x 100 / 11),
  R40 = mean over indices 1..40; these sums and the AOS similarity run term after term in
  OpenPCDet's order, so the numbers agree to the last bit (given the same overlaps);
* both overlap sets of OpenPCDet (Car 0.7/0.7/0.7 and 0.7/0.5/0.5, Pedestrian
  and Cyclist 0.5/0.5/0.5 and 0.5/0.25/0.25, ...), AOS only when detections carry
  an alpha other than -10.

Deliberate difference: rotated overlaps are exact polygon clipping
(:func:`omnilidar.geometry.rotated_iou.rotated_overlap_2d`, OpenPCDet's
clockwise angle convention); OpenPCDet's numba kernel returns 0 for identical
rotated boxes and wrong values for nearly parallel boxes far from the origin.
Loops over frames and boxes are plain Python with numpy inside (OpenPCDet uses
numba): fast enough for validation sets of thousands of frames.

:func:`pi3det_annos` converts lidar boxes the way Pi3DET's evaluation does
(OpenPCDet's ``transform_annotations_to_kitti_format``: every box "easy", no
range filter, Vehicle -> Car).
"""

from __future__ import annotations

import math

import numpy as np

from omnilidar.errors import InputError
from omnilidar.geometry.rotated_iou import rotated_overlap_2d
from omnilidar.io.kitti_object import read_objects

CLASS_NAMES = ("Car", "Pedestrian", "Cyclist", "Van", "Person_sitting", "Truck")
DIFFICULTIES = ("easy", "moderate", "hard")
METRICS = ("bbox", "bev", "3d")
MIN_HEIGHT = (40, 25, 25)
MAX_OCCLUSION = (0, 1, 2)
MAX_TRUNCATION = (0.15, 0.3, 0.5)
NUM_SAMPLE_POINTS = 41
# OpenPCDet's min_overlaps[overlap set, metric (bbox, bev, 3d), class (CLASS_NAMES order)].
MIN_OVERLAPS = np.array([
    [[0.7, 0.5, 0.5, 0.7, 0.5, 0.7]] * 3,
    [[0.7, 0.5, 0.5, 0.7, 0.5, 0.5], [0.5, 0.25, 0.25, 0.5, 0.25, 0.5], [0.5, 0.25, 0.25, 0.5, 0.25, 0.5]],
])
# Ignored neighbours of a class: their boxes neither count nor penalise.
SIMILAR_CLASS = {"car": "van", "pedestrian": "person_sitting"}
# Pi3DET's map_name_to_kitti.
PI3DET_TO_KITTI = {"Vehicle": "Car", "Pedestrian": "Pedestrian", "Cyclist": "Cyclist", "Sign": "Sign", "Car": "Car"}
NO_DETECTION = -10000000.0


# --------------------------------------------------------------------------- overlaps


def image_box_overlap(boxes: np.ndarray, query: np.ndarray, criterion: int = -1) -> np.ndarray:
    """(N, K) overlap of image boxes [x1, y1, x2, y2]: IoU (-1), over the first box's area (0)
    or over the query's area (1)."""
    boxes, query = np.asarray(boxes, np.float64).reshape(-1, 4), np.asarray(query, np.float64).reshape(-1, 4)
    iw = np.minimum(boxes[:, None, 2], query[None, :, 2]) - np.maximum(boxes[:, None, 0], query[None, :, 0])
    ih = np.minimum(boxes[:, None, 3], query[None, :, 3]) - np.maximum(boxes[:, None, 1], query[None, :, 1])
    inter = np.where((iw > 0) & (ih > 0), iw * ih, 0.0)
    area_b = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    area_q = (query[:, 2] - query[:, 0]) * (query[:, 3] - query[:, 1])
    if criterion == -1:
        union = area_b[:, None] + area_q[None, :] - inter
    elif criterion == 0:
        union = np.broadcast_to(area_b[:, None], inter.shape)
    else:
        union = np.broadcast_to(area_q[None, :], inter.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(inter > 0, inter / union, 0.0)


def _rotated_intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) intersection areas of [cx, cy, w, l, angle] rectangles (OpenPCDet's rotate_iou, criterion 2)."""
    import torch


    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)))
    return rotated_overlap_2d(torch.from_numpy(np.asarray(a, np.float64)),
                              torch.from_numpy(np.asarray(b, np.float64))).numpy()


def bev_box_overlap(boxes: np.ndarray, query: np.ndarray) -> np.ndarray:
    """(N, M) rotated IoU of camera-frame BEV boxes [x, z, l, w, ry]."""
    inter = _rotated_intersection(boxes, query)
    area_b = boxes[:, 2] * boxes[:, 3]
    area_q = query[:, 2] * query[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(inter > 0, inter / (area_b[:, None] + area_q[None, :] - inter), 0.0)


def d3_box_overlap(boxes: np.ndarray, query: np.ndarray) -> np.ndarray:
    """(N, M) 3D IoU of camera-frame boxes [x, y, z, l, h, w, ry] (y: bottom, pointing down)."""
    inter_bev = _rotated_intersection(boxes[:, [0, 2, 3, 5, 6]], query[:, [0, 2, 3, 5, 6]])
    iw = np.minimum(boxes[:, None, 1], query[None, :, 1]) - np.maximum(boxes[:, None, 1] - boxes[:, None, 4],
                                                                      query[None, :, 1] - query[None, :, 4])
    inter = np.where((inter_bev > 0) & (iw > 0), iw * inter_bev, 0.0)
    vol_b = boxes[:, 3] * boxes[:, 4] * boxes[:, 5]
    vol_q = query[:, 3] * query[:, 4] * query[:, 5]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(inter > 0, inter / (vol_b[:, None] + vol_q[None, :] - inter), 0.0)


def _boxes(anno: dict, metric: int) -> np.ndarray:
    if metric == 0:
        return np.asarray(anno["bbox"], np.float64).reshape(-1, 4)
    loc = np.asarray(anno["location"], np.float64).reshape(-1, 3)
    dims = np.asarray(anno["dimensions"], np.float64).reshape(-1, 3)
    rot = np.asarray(anno["rotation_y"], np.float64).reshape(-1, 1)
    if metric == 1:
        return np.concatenate([loc[:, [0, 2]], dims[:, [0, 2]], rot], axis=1)
    return np.concatenate([loc, dims, rot], axis=1)


def frame_overlaps(dt: dict, gt: dict, metric: int) -> np.ndarray:
    """(detections, ground truth) overlaps of one frame for metric 0 (bbox), 1 (bev) or 2 (3d)."""
    a, b = _boxes(dt, metric), _boxes(gt, metric)
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)))
    return (image_box_overlap, bev_box_overlap, d3_box_overlap)[metric](a, b)


# --------------------------------------------------------------------------- matching


def clean_data(gt: dict, dt: dict, current_class: str, difficulty: int):
    """(valid ground-truth count, ignored_gt (0 counts, 1 ignored, -1 other), ignored_dt, DontCare boxes)."""
    cls = current_class.lower()
    gt_names = [str(n).lower() for n in gt["name"]]
    gt_bbox = np.asarray(gt["bbox"], np.float64).reshape(-1, 4)
    ignored_gt, dc_boxes, num_valid = [], [], 0
    for i, name in enumerate(gt_names):
        height = gt_bbox[i, 3] - gt_bbox[i, 1]
        valid = 1 if name == cls else 0 if SIMILAR_CLASS.get(cls) == name else -1
        hard = (gt["occluded"][i] > MAX_OCCLUSION[difficulty] or gt["truncated"][i] > MAX_TRUNCATION[difficulty]
                or height <= MIN_HEIGHT[difficulty])
        if valid == 1 and not hard:
            ignored_gt.append(0)
            num_valid += 1
        elif valid == 0 or (hard and valid == 1):
            ignored_gt.append(1)
        else:
            ignored_gt.append(-1)
        if gt["name"][i] == "DontCare":
            dc_boxes.append(gt_bbox[i])
    dt_bbox = np.asarray(dt["bbox"], np.float64).reshape(-1, 4)
    ignored_dt = []
    for i, name in enumerate(dt["name"]):
        if abs(dt_bbox[i, 3] - dt_bbox[i, 1]) < MIN_HEIGHT[difficulty]:
            ignored_dt.append(1)
        elif str(name).lower() == cls:
            ignored_dt.append(0)
        else:
            ignored_dt.append(-1)
    dc = np.stack(dc_boxes).astype(np.float64) if dc_boxes else np.zeros((0, 4))
    return num_valid, np.array(ignored_gt, np.int64), np.array(ignored_dt, np.int64), dc


def compute_statistics(overlaps: np.ndarray, gt_alpha, dt_score, dt_alpha, dt_bbox, ignored_gt, ignored_dt,
                       dc_boxes, metric: int, min_overlap: float, thresh: float = 0.0, compute_fp: bool = False,
                       compute_aos: bool = False):
    """(tp, fp, fn, similarity, matched scores) of one frame, as OpenPCDet's compute_statistics_jit."""
    n_dt = len(dt_score)
    assigned = np.zeros(n_dt, bool)
    below = (dt_score < thresh) if compute_fp else np.zeros(n_dt, bool)
    tp = fp = fn = 0
    similarity = 0.0
    matched, deltas = [], []
    for i in range(len(ignored_gt)):
        if ignored_gt[i] == -1:
            continue
        ok = (ignored_dt != -1) & ~assigned & ~below & (overlaps[:, i] > min_overlap)
        det = -1
        if not compute_fp:
            cand = np.flatnonzero(ok & (dt_score > NO_DETECTION))
            if len(cand):
                det = int(cand[np.argmax(dt_score[cand])])  # the first of equal scores, as the loop
        else:
            counted = np.flatnonzero(ok & (ignored_dt == 0))
            if len(counted):
                det = int(counted[np.argmax(overlaps[counted, i])])  # the first of equal overlaps
            else:
                spare = np.flatnonzero(ok & (ignored_dt == 1))
                det = int(spare[0]) if len(spare) else -1
        if det < 0:
            if ignored_gt[i] == 0:
                fn += 1
        elif ignored_gt[i] == 1 or ignored_dt[det] == 1:
            assigned[det] = True
        else:
            tp += 1
            matched.append(dt_score[det])
            if compute_aos:
                deltas.append(gt_alpha[i] - dt_alpha[det])
            assigned[det] = True
    if compute_fp:
        fp = int(np.sum(~(assigned | (ignored_dt == -1) | (ignored_dt == 1) | below)))
        stuff = 0
        if metric == 0 and len(dc_boxes):
            dt_dc = image_box_overlap(dt_bbox, dc_boxes, 0)
            for k in range(len(dc_boxes)):
                for j in range(n_dt):
                    if assigned[j] or ignored_dt[j] in (-1, 1) or below[j]:
                        continue
                    if dt_dc[j, k] > min_overlap:
                        assigned[j] = True
                        stuff += 1
        fp -= stuff
        if compute_aos:  # summed one term after another, as OpenPCDet (numba's np.sum), for the same float
            similarity = 0.0
            for delta in deltas:
                similarity += (1.0 + math.cos(delta)) / 2.0
            if tp == 0 and fp == 0:
                similarity = -1.0
    return tp, fp, fn, similarity, np.asarray(matched, np.float64)


def get_thresholds(scores: np.ndarray, num_gt: int, num_sample_pts: int = NUM_SAMPLE_POINTS) -> np.ndarray:
    """The score thresholds at (about) evenly spaced recall positions, as OpenPCDet picks them."""
    scores = np.sort(np.asarray(scores, np.float64))[::-1]
    current, out = 0.0, []
    for i, score in enumerate(scores):
        l_recall = (i + 1) / num_gt
        r_recall = (i + 2) / num_gt if i < len(scores) - 1 else l_recall
        if (r_recall - current) < (current - l_recall) and i < len(scores) - 1:
            continue
        out.append(score)
        current += 1 / (num_sample_pts - 1.0)
    return np.asarray(out, np.float64)


def eval_class(gt_annos, dt_annos, classes, difficulties, metric: int, min_overlaps: np.ndarray,
               compute_aos: bool = False) -> dict:
    """precision / recall / orientation arrays [class, difficulty, overlap set, 41] of one metric."""
    overlaps = [frame_overlaps(dt, gt, metric) for gt, dt in zip(gt_annos, dt_annos)]
    shape = (len(classes), len(difficulties), min_overlaps.shape[0], NUM_SAMPLE_POINTS)
    precision, recall, aos = np.zeros(shape), np.zeros(shape), np.zeros(shape)
    for m, cls in enumerate(classes):
        for d, difficulty in enumerate(difficulties):
            frames, total_valid = [], 0
            for gt, dt in zip(gt_annos, dt_annos):
                num_valid, ignored_gt, ignored_dt, dc = clean_data(gt, dt, cls, difficulty)
                total_valid += num_valid
                frames.append((np.asarray(gt["alpha"], np.float64).reshape(-1),
                               np.asarray(dt["score"], np.float64).reshape(-1),
                               np.asarray(dt["alpha"], np.float64).reshape(-1),
                               np.asarray(dt["bbox"], np.float64).reshape(-1, 4), ignored_gt, ignored_dt, dc))
            for k, min_overlap in enumerate(min_overlaps[:, metric, m]):
                scores = [compute_statistics(ov, *f, metric, min_overlap)[4] for ov, f in zip(overlaps, frames)]
                scores = np.concatenate(scores) if scores else np.zeros(0)
                thresholds = get_thresholds(scores, total_valid)
                pr = np.zeros((len(thresholds), 4))
                for t, thresh in enumerate(thresholds):
                    for ov, f in zip(overlaps, frames):
                        tp, fp, fn, sim, _ = compute_statistics(ov, *f, metric, min_overlap, thresh, True, compute_aos)
                        pr[t] += (tp, fp, fn, 0.0)
                        if sim != -1:
                            pr[t, 3] += sim
                with np.errstate(divide="ignore", invalid="ignore"):
                    n = len(thresholds)
                    recall[m, d, k, :n] = pr[:, 0] / (pr[:, 0] + pr[:, 2])
                    precision[m, d, k, :n] = pr[:, 0] / (pr[:, 0] + pr[:, 1])
                    if compute_aos:
                        aos[m, d, k, :n] = pr[:, 3] / (pr[:, 0] + pr[:, 1])
                for arr in (precision, recall, aos):  # monotone: the best at any later threshold
                    arr[m, d, k, :n] = np.maximum.accumulate(arr[m, d, k, :n][::-1])[::-1]
    return {"precision": precision, "recall": recall, "orientation": aos}


def _sum_in_order(values: np.ndarray, indices) -> np.ndarray:
    """Sum of values[..., i] over indices, one after another: numpy's pairwise ``sum`` rounds
    differently from OpenPCDet's loop (last bits of the AP)."""
    total = np.zeros(values.shape[:-1])
    for i in indices:
        total = total + values[..., i]
    return total


def ap_r11(precision: np.ndarray) -> np.ndarray:
    """11-point AP (x 100): precision at threshold indices 0, 4, ..., 40."""
    return _sum_in_order(precision, range(0, precision.shape[-1], 4)) / 11 * 100


def ap_r40(precision: np.ndarray) -> np.ndarray:
    """40-point AP (x 100): precision at threshold indices 1..40."""
    return _sum_in_order(precision, range(1, precision.shape[-1])) / 40 * 100


# --------------------------------------------------------------------------- entry points


def _check_annos(annos: list[dict], role: str, need_score: bool) -> None:
    keys = ["name", "truncated", "occluded", "alpha", "bbox", "dimensions", "location", "rotation_y"]
    if need_score:
        keys.append("score")
    for k, anno in enumerate(annos):
        missing = [key for key in keys if key not in anno]
        if missing:
            raise InputError(None, f"{role} anno {k} lacks {', '.join(missing)}")
        n = len(anno["name"])
        for key in keys[1:]:
            if len(anno[key]) != n:
                raise InputError(None, f"{role} anno {k}: {key} has {len(anno[key])} entries for {n} boxes")


def kitti_eval(gt_annos: list[dict], dt_annos: list[dict], current_classes) -> dict:
    """AP of ``current_classes`` (names or OpenPCDet class ids) as ``get_official_eval_result``.

    Returns ``R11`` and ``R40``: {class: {metric (bbox, bev, 3d, aos): [overlap set 0, 1] of
    {easy, moderate, hard}}} in percent; ``precision`` / ``recall``: the 41 monotone values per
    {class: {metric: [set] of {difficulty: list}}}; ``min_overlaps`` per class; ``official``:
    OpenPCDet's returned dict (R40, first overlap set) and ``result_str`` its printout.
    """
    if len(gt_annos) != len(dt_annos):
        raise InputError(None, f"{len(gt_annos)} ground-truth frames but {len(dt_annos)} detection frames")
    _check_annos(gt_annos, "ground-truth", False)
    _check_annos(dt_annos, "detection", True)
    names = []
    for c in current_classes:
        name = CLASS_NAMES[c] if isinstance(c, (int, np.integer)) else str(c)
        if name not in CLASS_NAMES:
            raise InputError(None, f"unknown KITTI class {c!r}; known: {', '.join(CLASS_NAMES)}")
        names.append(name)
    class_ids = [CLASS_NAMES.index(n) for n in names]
    min_overlaps = MIN_OVERLAPS[:, :, class_ids]
    compute_aos = False
    for anno in dt_annos:  # as OpenPCDet: the first frame with detections decides
        if len(anno["alpha"]):
            compute_aos = bool(np.asarray(anno["alpha"]).reshape(-1)[0] != -10)
            break
    curves, ap = {}, {"R11": {}, "R40": {}}
    for metric, key in enumerate(METRICS):
        out = eval_class(gt_annos, dt_annos, names, (0, 1, 2), metric, min_overlaps, compute_aos and metric == 0)
        curves[key] = out
        if metric == 0 and compute_aos:
            curves["aos"] = {"precision": out["orientation"], "recall": out["recall"]}
    result = {"R11": {}, "R40": {}, "precision": {}, "recall": {}, "min_overlaps": {}, "compute_aos": compute_aos}
    for j, name in enumerate(names):
        result["min_overlaps"][name] = {m: [float(min_overlaps[s, i, j]) for s in range(2)]
                                        for i, m in enumerate(METRICS)}
        for rule, fn in (("R11", ap_r11), ("R40", ap_r40)):
            result[rule][name] = {
                m: [{diff: float(fn(curves[m]["precision"])[j, d, s]) for d, diff in enumerate(DIFFICULTIES)}
                    for s in range(min_overlaps.shape[0])]
                for m in curves}
        for part in ("precision", "recall"):
            result[part][name] = {
                m: [{diff: curves[m][part][j, d, s].tolist() for d, diff in enumerate(DIFFICULTIES)}
                    for s in range(min_overlaps.shape[0])]
                for m in curves}
    result["official"] = _official_dict(result, names)
    result["result_str"] = result_string(result, names)
    return result


def _official_dict(result: dict, names: list[str]) -> dict:
    """OpenPCDet's ap_dict: R40 AP of the first overlap set per class, metric and difficulty."""
    out = {}
    for name in names:
        for metric, label in (("3d", "3d"), ("bev", "bev"), ("bbox", "image"), ("aos", "aos")):
            if metric in result["R40"][name]:
                for diff in DIFFICULTIES:
                    out[f"{name}_{label}/{diff}_R40"] = result["R40"][name][metric][0][diff]
    return out


def result_string(result: dict, names: list[str]) -> str:
    """The AP table exactly in the layout of OpenPCDet's printout: per class and overlap set an
    R11 block (``Car AP@...:``) then an R40 block (``Car AP_R40@...:``), one line per metric with
    easy, moderate, hard (4 decimals; aos 2)."""
    lines = []
    for name in names:
        ov = result["min_overlaps"][name]
        for s in range(2):
            overlaps = f"{ov['bbox'][s]:.2f}, {ov['bev'][s]:.2f}, {ov['3d'][s]:.2f}"
            for rule, header in (("R11", "AP"), ("R40", "AP_R40")):
                lines.append(f"{name} {header}@{overlaps}:")
                for metric, label, digits in (("bbox", "bbox AP", 4), ("bev", "bev  AP", 4), ("3d", "3d   AP", 4),
                                              ("aos", "aos  AP", 2)):
                    if metric in result[rule][name]:
                        v = result[rule][name][metric][s]
                        lines.append(f"{label}:" + ", ".join(f"{v[d]:.{digits}f}" for d in DIFFICULTIES))
    return "\n".join(lines) + "\n"


def pi3det_annos(boxes_lidar, names, scores=None) -> dict:
    """KITTI-format anno of lidar boxes (N, 7) [x, y, z_centre, dx, dy, dz, heading] as Pi3DET's
    evaluation converts them: names through ``PI3DET_TO_KITTI`` (others kept), every box easy
    (image box [0, 0, 50, 50], not truncated or occluded), no range filter."""
    boxes = np.asarray(boxes_lidar, np.float64).reshape(-1, 7).copy()
    n = len(boxes)
    if len(names) != n:
        raise InputError(None, f"{len(names)} names for {n} boxes")
    anno = {
        "name": np.array([PI3DET_TO_KITTI.get(str(x), str(x)) for x in names], dtype=object).astype(str)
        if n else np.zeros(0, str),
        "truncated": np.zeros(n), "occluded": np.zeros(n), "bbox": np.zeros((n, 4)),
    }
    anno["bbox"][:, 2:4] = 50
    boxes[:, 2] -= boxes[:, 5] / 2  # bottom centre
    anno["location"] = np.stack([-boxes[:, 1], -boxes[:, 2], boxes[:, 0]], axis=1) if n else np.zeros((0, 3))
    anno["dimensions"] = boxes[:, [3, 5, 4]] if n else np.zeros((0, 3))  # l, h, w
    anno["rotation_y"] = -boxes[:, 6] - np.pi / 2.0
    anno["alpha"] = -np.arctan2(-boxes[:, 1], boxes[:, 0]) + anno["rotation_y"]
    if scores is not None:
        anno["score"] = np.asarray(scores, np.float64).reshape(-1)
        if len(anno["score"]) != n:
            raise InputError(None, f"{len(anno['score'])} scores for {n} boxes")
    return anno


def label_file_anno(path, need_score: bool = False) -> dict:
    """KITTI-format anno of a label_2 file (dimensions reordered h, w, l -> l, h, w as OpenPCDet's
    get_label_anno); ``need_score``: every line must carry the 16th column."""
    objects = read_objects(path)
    if need_score and any(o.score is None for o in objects):
        line = next(i for i, o in enumerate(objects, 1) if o.score is None)
        raise InputError(path, f"object {line} has no score (a prediction needs a 16th column)")
    n = len(objects)
    return {
        "name": np.array([o.type for o in objects], dtype=str) if n else np.zeros(0, str),
        "truncated": np.array([o.truncated for o in objects], np.float64),
        "occluded": np.array([o.occluded for o in objects], np.float64),
        "alpha": np.array([o.alpha for o in objects], np.float64),
        "bbox": np.array([o.bbox2d for o in objects], np.float64).reshape(n, 4),
        "dimensions": np.array([(o.dimensions[2], o.dimensions[0], o.dimensions[1]) for o in objects],
                               np.float64).reshape(n, 3),
        "location": np.array([o.location for o in objects], np.float64).reshape(n, 3),
        "rotation_y": np.array([o.rotation_y for o in objects], np.float64),
        "score": np.array([o.score if o.score is not None else 0.0 for o in objects], np.float64),
    }
