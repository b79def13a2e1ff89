"""Greedy non-maximum suppression on rotated BEV boxes, and OpenPCDet's
class-agnostic / per-class wrappers (pcdet.models.model_utils.model_nms_utils).

The overlaps come sparse from ``iou.iou_bev_self_pairs`` (only pairs whose
circumscribed circles meet), so NMS over thousands of proposals never builds a
dense N x N matrix; the greedy pass itself is sequential by nature and runs on
the CPU over the suppression lists, stopping once ``post_max_size`` are kept.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from omnilidar.geometry.rotated_iou import iou_bev_self_pairs

# OpenPCDet NMS_TYPE names -> whether the IoU ignores headings.
NMS_TYPES = {"nms_gpu": False, "nms_normal_gpu": True}


def _score_order(scores: torch.Tensor, pre_max_size: int | None) -> torch.Tensor:
    """Indices by descending score; ties keep index order (a stable sort)."""
    order = torch.sort(scores, descending=True, stable=True).indices
    return order if pre_max_size is None else order[:pre_max_size]


def _greedy_keep(n: int, ia, ib, iou, thresh: float, post_max_size: int | None) -> np.ndarray:
    """Greedy NMS over boxes already sorted by score: pairs (ia < ib) with IoU
    strictly above ``thresh`` suppress ib when ia is kept."""
    hit = iou > thresh
    ia, ib = ia[hit].cpu().numpy(), ib[hit].cpu().numpy()
    by_row = np.argsort(ia, kind="stable")
    ia, ib = ia[by_row], ib[by_row]
    starts = np.searchsorted(ia, np.arange(n + 1))
    removed = np.zeros(n, dtype=bool)
    keep = []
    limit = n if post_max_size is None else post_max_size
    for i in range(n):
        if len(keep) >= limit:
            break
        if removed[i]:
            continue
        keep.append(i)
        removed[ib[starts[i]:starts[i + 1]]] = True
    return np.asarray(keep, dtype=np.int64)


def nms_rotated(boxes: torch.Tensor, scores: torch.Tensor, thresh: float,
                pre_max_size: int | None = None, post_max_size: int | None = None,
                axis_aligned: bool = False) -> torch.Tensor:
    """Greedy NMS of lidar boxes (N, 7) by rotated BEV IoU, as OpenPCDet's nms_gpu.

    Boxes are visited by descending score (only the first ``pre_max_size``); a box
    is dropped when its IoU with a kept, higher-scoring box is > ``thresh``.
    Returns the kept indices into ``boxes`` (long, on its device), by descending
    score, at most ``post_max_size``. ``axis_aligned`` ignores headings
    (OpenPCDet's nms_normal_gpu).
    """
    if boxes.ndim != 2 or boxes.shape[1] < 7 or scores.shape != boxes.shape[:1]:
        raise ValueError(f"nms needs boxes (N, 7) and scores (N,), got {tuple(boxes.shape)} and {tuple(scores.shape)}")
    order = _score_order(scores, pre_max_size)
    ia, ib, iou = iou_bev_self_pairs(boxes[order, :7], axis_aligned=axis_aligned, above=thresh)
    keep = _greedy_keep(len(order), ia, ib, iou, thresh, post_max_size)
    return order[torch.from_numpy(keep).to(order.device)]


def _nms_by_config(boxes: torch.Tensor, scores: torch.Tensor, nms_config: Mapping) -> torch.Tensor:
    """OpenPCDet's NMS step: top NMS_PRE_MAXSIZE by score, NMS_TYPE at NMS_THRESH,
    first NMS_POST_MAXSIZE kept (indices into ``boxes``)."""
    kind = nms_config["NMS_TYPE"]
    if kind not in NMS_TYPES:
        raise ValueError(f"NMS_TYPE {kind!r} is not one of {sorted(NMS_TYPES)}")
    return nms_rotated(boxes, scores, float(nms_config["NMS_THRESH"]),
                       pre_max_size=int(nms_config["NMS_PRE_MAXSIZE"]),
                       post_max_size=int(nms_config["NMS_POST_MAXSIZE"]),
                       axis_aligned=NMS_TYPES[kind])


def class_agnostic_nms(box_scores: torch.Tensor, box_preds: torch.Tensor, nms_config: Mapping,
                       score_thresh: float | None = None):
    """One NMS over all classes: returns (selected indices into the inputs, their scores).

    ``nms_config`` holds OpenPCDet's NMS_CONFIG keys (NMS_TYPE, NMS_THRESH,
    NMS_PRE_MAXSIZE, NMS_POST_MAXSIZE); boxes scoring below ``score_thresh`` are
    dropped first.
    """
    candidates = torch.arange(len(box_scores), device=box_scores.device)
    if score_thresh is not None:
        candidates = candidates[box_scores >= score_thresh]
    selected = candidates[_nms_by_config(box_preds[candidates], box_scores[candidates], nms_config)]
    return selected, box_scores[selected]


def multi_class_nms(cls_scores: torch.Tensor, box_preds: torch.Tensor, nms_config: Mapping,
                    score_thresh: float | None = None):
    """NMS per class column of ``cls_scores`` (N, num_class) over ``box_preds`` (N, 7+C).

    Returns (scores, labels, boxes) concatenated class by class; labels are the
    0-based column index, as OpenPCDet's multi_classes_nms.
    """
    scores, labels, boxes = [], [], []
    for k in range(cls_scores.shape[1]):
        selected, selected_scores = class_agnostic_nms(cls_scores[:, k], box_preds, nms_config, score_thresh)
        scores.append(selected_scores)
        labels.append(torch.full_like(selected, k))
        boxes.append(box_preds[selected])
    if not scores:
        return cls_scores.new_zeros(0), torch.zeros(0, dtype=torch.long, device=cls_scores.device), box_preds[:0]
    return torch.cat(scores), torch.cat(labels), torch.cat(boxes)
