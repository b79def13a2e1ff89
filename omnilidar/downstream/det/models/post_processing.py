"""Detector3DTemplate.post_processing (OpenPCDet): score threshold + NMS per
sample, and the recall record at RECALL_THRESH_LIST (generate_recall_record)."""

from __future__ import annotations

import torch

from omnilidar.downstream.det.models.box_utils import strip_padding
from omnilidar.geometry.rotated_iou import boxes_iou3d
from omnilidar.downstream.det.ops.nms import class_agnostic_nms, multi_class_nms


def recall_record(box_preds: torch.Tensor, recall_dict: dict, batch_index: int, batch_dict: dict,
                  thresh_list) -> dict:
    """Add one sample's gt count and, per threshold, how many gt boxes some RoI
    (``roi_T``) and some final box (``rcnn_T``) overlap with 3D IoU above T."""
    if "gt_boxes" not in batch_dict:
        return recall_dict
    rois = batch_dict["rois"][batch_index] if "rois" in batch_dict else None
    if not recall_dict:
        recall_dict = {"gt": 0}
        for t in thresh_list:
            recall_dict[f"roi_{t}"] = 0
            recall_dict[f"rcnn_{t}"] = 0
    gt = strip_padding(batch_dict["gt_boxes"][batch_index])
    if len(gt) > 0:
        iou_rcnn = boxes_iou3d(box_preds[:, :7], gt[:, :7]) if len(box_preds) else gt.new_zeros((0, len(gt)))
        iou_roi = boxes_iou3d(rois[:, :7], gt[:, :7]) if rois is not None else None
        for t in thresh_list:
            if len(iou_rcnn):
                recall_dict[f"rcnn_{t}"] += int((iou_rcnn.max(dim=0).values > t).sum())
            if iou_roi is not None:
                recall_dict[f"roi_{t}"] += int((iou_roi.max(dim=0).values > t).sum())
        recall_dict["gt"] += len(gt)
    return recall_dict


def post_processing(batch_dict: dict, post_cfg: dict, num_class: int) -> tuple[list[dict], dict]:
    """Per sample: sigmoid scores, class-agnostic (or per-class) NMS with
    SCORE_THRESH; returns (pred_dicts, recall_dict) as OpenPCDet."""
    batch_size = int(batch_dict["batch_size"])
    thresh_list = post_cfg.get("RECALL_THRESH_LIST", [0.3, 0.5, 0.7])
    nms_cfg = post_cfg["NMS_CONFIG"]
    score_thresh = post_cfg.get("SCORE_THRESH")
    recall_dict: dict = {}
    pred_dicts = []
    for b in range(batch_size):
        if batch_dict.get("batch_index") is not None:
            mask = batch_dict["batch_index"] == b
        else:
            mask = b
        box_preds = batch_dict["batch_box_preds"][mask]
        cls_preds = batch_dict["batch_cls_preds"][mask]
        raw_cls_preds = cls_preds
        if not batch_dict.get("cls_preds_normalized", False):
            cls_preds = torch.sigmoid(cls_preds)
        if cls_preds.shape[1] not in (1, num_class):
            raise ValueError(f"class scores have {cls_preds.shape[1]} columns, expected 1 or {num_class}")
        # Unlike OpenPCDet, boxes refined from the zero padding of the RoI list
        # (fewer RoIs than NMS_POST_MAXSIZE survive the proposal NMS) are never
        # predictions: they have zero size and would count as false positives.
        real = (box_preds[:, 3:6] > 0).all(dim=1).nonzero().view(-1)
        if nms_cfg.get("MULTI_CLASSES_NMS", False):
            scores, labels, boxes = multi_class_nms(cls_preds[real], box_preds[real], nms_cfg, score_thresh)
            labels = labels + 1
        else:
            best, labels = cls_preds.max(dim=-1)
            if batch_dict.get("has_class_labels", False):
                key = "roi_labels" if "roi_labels" in batch_dict else "batch_pred_labels"
                labels = batch_dict[key][b]
            else:
                labels = labels + 1
            selected, scores = class_agnostic_nms(best[real], box_preds[real], nms_cfg, score_thresh)
            selected = real[selected]
            if post_cfg.get("OUTPUT_RAW_SCORE", False):  # the logits, before the sigmoid
                scores = raw_cls_preds.max(dim=-1).values[selected]
            labels, boxes = labels[selected], box_preds[selected]
        recall_dict = recall_record(box_preds if "rois" in batch_dict else boxes, recall_dict, b, batch_dict,
                                    thresh_list)
        pred_dicts.append({"pred_boxes": boxes, "pred_scores": scores, "pred_labels": labels})
    return pred_dicts, recall_dict
